"""Scans whose vertices are noisy at the scale of their triangles, told from the mesh itself and
matched on a smoothed copy.

A scanner's noise added after the mesh was made (a rescan decimated, then jittered, as raw
scanner output is) tilts every small triangle and flips the skinniest: the skin reads as rough
as the break, the segmentation takes most of the surface for fracture, and pairs that match on
the same rescans without that noise are refused or turned half a turn (docs/benchmarks.md, "Scans
noisy after their mesh was made"). The noise is told from geometry by where it lies: a surface's
own shape bends its vertices out of their neighbours' mean smoothly, noise does so at random from
one vertex to the next. So a vertex's offset from the mean of its neighbours, along the normal,
less the mean of its neighbours' offsets, is its noise; the smoothest fifth of the vertices
(`NOISE_QUANTILE`) still carrying more than `NOISE_RATIO` of the median edge means noise is
everywhere. A mesh whose neighbouring faces lie exactly in one plane over `EXACT_SHARE` of its
area (a cell-fracture shard, a CAD mesh) is exact, whatever its creases read, and is left as it
is, as is a mesh of few faces (under `MIN_FACES`), whose creases and curvature lie a few edges
apart and read as noise.

Such a mesh is matched on a copy smoothed by Taubin's lambda|mu filter (rounds of the umbrella
operator until it reads `SMOOTH_TO`, at most `ROUNDS`), which takes out the noise at the
triangles' scale and keeps the shape (it neither shrinks the piece nor moves it): the poses found
carry the mesh as given.
"""
from __future__ import annotations

import dataclasses
import weakref

import numpy as np
from scipy.sparse import csr_matrix

from ..io.fragment import Fragment
from ..topology import mesh_topology, vertex_adjacency

# Chosen on the corpus's five rescanned families (seeds 1, 20-23 and 30-33) with noise of 0.1-0.2%
# of the size added after decimation, the clean and coarse families, synth's pieces and the Blender
# and tombstone sets (docs/benchmarks.md, "Scans noisy after their mesh was made"): the clean meshes
# read 0.000-0.010, the rescans as made 0.003-0.023 (12,000 faces: under 0.026), with the noise added
# 0.017-0.030 at 0.1% (where they still match as they are, and flat cuts smoothed slide) and
# 0.030-0.054 at 0.2% (where half of them no longer match)
NOISE_RATIO = 0.03
NOISE_QUANTILE = 0.2
# Under MIN_FACES a piece's creases and curvature, a few edges apart on a decimated rescan, read as
# noise: tetra-noisy at 3,000 faces (2,000-3,400 a piece) had 15 of 52 pieces flagged, and smoothed
# its objects assembled at 0.00-0.25 where as given at 1.00; the rescans at 12,000 faces have 8,000-
# 13,500 a piece
MIN_FACES = 6000
EXACT_DEG = 0.02  # neighbouring faces this close in normal lie in one plane: exact geometry (noisy scans: none)
EXACT_SHARE = 0.1  # the Blender shards 0.18-0.72 of their area, noisy scans and synth's noisy pieces 0.00-0.03
# ... smoothed round by round until it reads no noisier than SMOOTH_TO (the rescans as made at 12,000
# faces read 0.003-0.013), at most ROUNDS rounds: each round takes out about a third of the noise,
# and every round also rounds the rims and flat cuts' edges that matching reads
SMOOTH_TO = 0.01
ROUNDS = 5
LAMBDA, MU = 0.5, -0.53  # Taubin's pass band 1 / LAMBDA + 1 / MU = 0.11: the triangles' scale is smoothed

SMOOTHED = "matched on a copy smoothed"  # the note a smoothed copy carries (`smoothing_notes`)

_SMOOTHED: "weakref.WeakKeyDictionary[Fragment, Fragment]" = weakref.WeakKeyDictionary()  # noisy -> its copy
_AS_GIVEN: "weakref.WeakSet[Fragment]" = weakref.WeakSet()  # fragments matched as they are (copies among them)


def _umbrella(faces: np.ndarray, n: int) -> csr_matrix:
    """(n, n) mean over each vertex's neighbours across edges (rows of isolated vertices zero)."""
    a = vertex_adjacency(faces, n)
    degree = np.asarray(a.sum(axis=1)).ravel()
    return csr_matrix(a.multiply(1.0 / np.maximum(degree, 1.0)[:, None]))


def scan_noise(vertices: np.ndarray, faces: np.ndarray) -> float:
    """The noise of a mesh's vertices at the scale of its triangles, over its median edge: the
    `NOISE_QUANTILE` quantile over vertices of |offset from the neighbours' mean along the normal,
    less the neighbours' mean offset|.

    Parameters
    ----------
    vertices : (V, 3) float
    faces : (F, 3) int
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    return _noise(v, f, _umbrella(f, len(v))) if len(f) else 0.0


def _noise(v: np.ndarray, f: np.ndarray, mean: csr_matrix) -> float:
    """`scan_noise` of (V, 3) float64 vertices and (F, 3) int64 faces, given their `_umbrella`."""
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    normals = np.zeros_like(v)
    for c in range(3):
        np.add.at(normals, f[:, c], cross)
    normals = normals + mean @ normals  # over the ring too: a noisy vertex's own normal is noise
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    offset = np.einsum("ij,ij->i", v - mean @ v, normals)
    edges = np.linalg.norm(v[f[:, [1, 2, 0]]] - v[f], axis=2)
    return float(np.quantile(np.abs(offset - mean @ offset), NOISE_QUANTILE) / max(float(np.median(edges)), 1e-300))


def exact_share(vertices: np.ndarray, faces: np.ndarray) -> float:
    """The share of a mesh's area in faces that lie in one plane (`EXACT_DEG`) with a neighbour."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    area = np.linalg.norm(cross, axis=1)
    unit = cross / np.maximum(area, 1e-300)[:, None]
    pairs = mesh_topology(f).edge_faces
    flat = pairs[np.einsum("ij,ij->i", unit[pairs[:, 0]], unit[pairs[:, 1]]) > np.cos(np.radians(EXACT_DEG))]
    exact = np.zeros(len(f), bool)
    exact[flat.ravel()] = True
    return float(area[exact].sum() / max(float(area.sum()), 1e-300))


def is_noisy(vertices: np.ndarray, faces: np.ndarray) -> bool:
    """Whether a mesh is noisy at its triangles' scale (see the module docstring)."""
    return _noisy_reading(vertices, faces) is not None


def _noisy_reading(vertices: np.ndarray, faces: np.ndarray) -> float | None:
    """The mesh's `scan_noise` where it is noisy (`is_noisy`), else None."""
    if len(faces) < MIN_FACES:
        return None
    noise = scan_noise(vertices, faces)
    return noise if noise > NOISE_RATIO and exact_share(vertices, faces) < EXACT_SHARE else None


def taubin(vertices: np.ndarray, faces: np.ndarray, rounds: int = ROUNDS, until: float = 0.0) -> tuple[np.ndarray, int]:
    """(V, 3) vertices after Taubin's lambda|mu smoothing over the mesh's edges, round by round until
    they read no noisier than `until` (`scan_noise`) or after `rounds` rounds, and the rounds taken."""
    v = np.array(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    mean = _umbrella(f, len(v))
    for k in range(rounds):
        for step in (LAMBDA, MU):
            v += step * (mean @ v - v)
        if until > 0 and _noise(v, f, mean) <= until:
            return v, k + 1
    return v, rounds


def denoised(fragment: Fragment) -> Fragment:
    """The fragment to match: itself, or where its mesh is noisy (`is_noisy`) a smoothed copy (the
    same faces and frame; a note says so), made once while the fragment lives."""
    if fragment in _AS_GIVEN or len(fragment.faces) == 0:
        return fragment
    copy = _SMOOTHED.get(fragment)
    if copy is not None:
        return copy
    noise = _noisy_reading(fragment.vertices, fragment.faces)
    if noise is None:
        _AS_GIVEN.add(fragment)
        return fragment
    vertices, rounds = taubin(fragment.vertices, fragment.faces, ROUNDS, SMOOTH_TO)
    note = (f"{fragment.file}: its vertices are noisy at its triangles' scale ({noise:.3f} of its median "
            f"edge); {SMOOTHED} {rounds} round{'s' if rounds > 1 else ''} (Taubin)")
    copy = dataclasses.replace(fragment, vertices=vertices, notes=fragment.notes + (note,))
    _AS_GIVEN.add(copy)
    _SMOOTHED[fragment] = copy
    return copy


def smoothing_notes(fragments) -> list[str]:
    """The notes of those of `fragments` (what `prepare` matched on) that are smoothed copies."""
    return [note for f in fragments if f is not None for note in f.notes if SMOOTHED in note]
