"""Loading fragments and writing outputs.

`load_fragment(path)` reads STL, PLY, OBJ, OFF or GLB meshes through trimesh
into a `Fragment`; point clouds (.xyz, .pcd, .ply, .npy, and .las/.laz through
laspy: `read_las`) go through `relicgpu.pointcloud` when that stage is installed. Every fault a user can cause becomes a `FragmentError` that
names the file and the fault. Outputs are written atomically (a temporary file
beside the target, then a rename), never over an input.
"""
from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import re
import sys
import tempfile
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

MESH_SUFFIXES = {".stl", ".ply", ".obj", ".off", ".glb", ".gltf"}
# LAS/LAZ lidar clouds, read by laspy (`read_las`; LAZ through its lazrs backend)
LIDAR_SUFFIXES = {".las", ".laz"}
POINT_SUFFIXES = {".xyz", ".asc", ".txt", ".pcd", ".npy"} | LIDAR_SUFFIXES
FRAGMENT_SUFFIXES = MESH_SUFFIXES | POINT_SUFFIXES
# Extra dimensions of a LAS file read as normals, lower case (CloudCompare, PDAL and others)
LAS_NORMAL_NAMES = (("normalx", "normaly", "normalz"), ("normal_x", "normal_y", "normal_z"), ("nx", "ny", "nz"))
# A body of less than this fraction of the largest body's area in its file is a crumb: dropped.
CRUMB_FRACTION = 0.01
# Bodies of more faces than THIN_ABOVE are thinned at load to about THIN_TO faces (the working
# resolution: prepare samples a few thousand points a fragment); outputs reload the original.
THIN_ABOVE = 1_000_000
THIN_TO = 200_000
THIN_PASSES = 4  # clustering passes at most, each resizing the cubes towards THIN_TO faces


class FragmentError(ValueError):
    """Bad input: the message names the file and the fault."""


@dataclass(frozen=True, eq=False)
class Fragment:
    """A scanned fragment: a triangle mesh with a name (its id: see `fragment_ids`)."""
    name: str
    vertices: np.ndarray  # (V,3) float64
    faces: np.ndarray  # (F,3) int32
    source: str | None = None
    notes: tuple[str, ...] = field(default_factory=tuple)
    # faces of the body in its file when it was thinned at load (else 0): outputs read it again
    thinned_from: int = field(default=0, kw_only=True)

    @property
    def file(self) -> str:
        """The name of the file it was read from (with its extension), else its name."""
        return Path(self.source).name if self.source else self.name

    @property
    def size(self) -> float:
        """The diagonal of the axis-aligned bounding box: the length scale of the fragment."""
        if len(self.vertices) == 0:
            return 0.0
        return float(np.linalg.norm(self.vertices.max(0) - self.vertices.min(0)))

    def transformed(self, matrix: np.ndarray) -> "Fragment":
        m = np.asarray(matrix, np.float64)
        v = self.vertices @ m[:3, :3].T + m[:3, 3]
        return dataclasses.replace(self, vertices=v)

    def to_trimesh(self):
        import trimesh
        return trimesh.Trimesh(self.vertices, self.faces, process=False)


def is_cloud(fragment: Fragment) -> bool:
    """Whether a fragment is given as points alone (no faces): a scan that did not close."""
    return len(fragment.faces) == 0


def fragment_from_arrays(name: str, vertices, faces, source: str | None = None) -> Fragment:
    """Check and clean raw arrays into one Fragment (same rules as for files).

    A mesh of several bodies gives its largest body, and a note says so (see
    `fragments_from_arrays` for every body).
    """
    frags, skipped, notes = fragments_from_arrays(name, vertices, faces, source)
    return _largest_of(frags, skipped, notes, source or name)


def fragments_from_arrays(name: str, vertices, faces, source: str | None = None,
                          ) -> tuple[list[Fragment], list[dict], list[str]]:
    """Check and clean raw arrays into one Fragment per body.

    Parameters
    ----------
    name : str
        The fragment id; bodies of a mesh that holds several are named ``name#k``.
    vertices, faces : array_like
        (N, 3) coordinates and (M, 3) vertex indices.
    source : str, optional
        The file the arrays come from (names it in messages and in ``Fragment.file``).

    Returns
    -------
    fragments : list of Fragment
        The bodies kept, largest first.
    skipped : list of dict
        One ``{"file", "name", "reason"}`` per crumb dropped (see `split_bodies`).
    notes : list of str
        The decisions taken on this mesh (empty for a mesh of one body).

    Raises
    ------
    FragmentError
        Malformed arrays, or no face of non-zero area.
    """
    label = source or name
    v, f = _checked_arrays(label, vertices, faces)
    return split_bodies(name, label, source, [(v, f)])


def _checked_arrays(label: str, vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) finite float64 vertices and (M, 3) int64 faces that index them, or a FragmentError."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise FragmentError(f"{label}: vertices must be an (N, 3) array, got shape {v.shape}")
    if f.size == 0:
        raise FragmentError(f"{label}: the mesh has no faces")
    if f.ndim != 2 or f.shape[1] != 3:
        raise FragmentError(f"{label}: faces must be triangles, an (M, 3) array, got shape {f.shape}")
    if not np.isfinite(v).all():
        bad = int((~np.isfinite(v)).any(axis=1).sum())
        raise FragmentError(f"{label}: {bad} vertices have NaN or infinite coordinates")
    if f.min() < 0 or f.max() >= len(v):
        raise FragmentError(f"{label}: faces refer to vertices that do not exist (index {int(f.max())} of {len(v)})")
    return v, f.astype(np.int64)


def split_bodies(name: str, label: str, source: str | None, parts, thin_above: int | None = None,
                 progress: bool = True, describe: bool = True) -> tuple[list[Fragment], list[dict], list[str]]:
    """Split meshes into bodies, drop the crumbs and clean each body kept into a Fragment.

    A crumb is a body of less than CRUMB_FRACTION of the largest body's area (over all
    `parts`, e.g. the meshes of one GLB scene). Bodies are numbered by decreasing area;
    when more than one is kept they are named ``name#1``, ``name#2``, ... and the crumbs
    take the numbers after them. A body of more than `thin_above` faces is thinned to
    about THIN_TO faces (`thin`, reporting on stderr unless `progress` is False) before
    cleaning; `describe`: see `_clean_body`. Returns (fragments, skipped, notes) as
    `fragments_from_arrays`.
    """
    bodies = [(v, f[faces]) for v, f in parts for faces in _body_faces(v, f)]
    areas = np.array([_area(v, f) for v, f in bodies])
    order = np.argsort(-areas, kind="stable")
    largest = float(areas[order[0]])
    if not largest > 0:
        raise FragmentError(f"{label}: the mesh has no faces left after removing degenerate ones")
    kept = [i for i in order if areas[i] >= CRUMB_FRACTION * largest]
    ids = [name] if len(kept) == 1 else [f"{name}#{k}" for k in range(1, len(bodies) + 1)]
    file = Path(source).name if source else name
    frags = [_clean_body(ids[k], *bodies[i], label if len(kept) == 1 else f"{label} ({ids[k]})", source,
                         thin_above, progress, describe) for k, i in enumerate(kept)]
    skipped = [{"file": file, "name": f"{name}#{k + 1}",
                "reason": f"{label}: body {k + 1} of {len(bodies)} is a crumb ({len(bodies[i][1])} faces, "
                          f"{100 * areas[i] / largest:.2g}% of the largest body's area); dropped"}
               for k, i in enumerate(order) if k >= len(kept)]
    notes = []
    if len(bodies) > 1:
        notes.append(f"{label}: {len(bodies)} bodies: kept {len(kept)} ({', '.join(f.name for f in frags)}), "
                     f"dropped {len(skipped)} crumb(s) under {100 * CRUMB_FRACTION:g}% of the largest body's area")
    return frags, skipped, notes


def _clean_body(name: str, v: np.ndarray, f: np.ndarray, label: str, source: str | None,
                thin_above: int | None = None, progress: bool = True, describe: bool = True) -> Fragment:
    """One body's faces -> a Fragment: thinned where it has more than `thin_above` faces;
    degenerate and duplicate faces and unused vertices removed. `describe` False skips what
    only makes a note (the watertightness test: 0.7 GiB and seconds on 6M faces)."""
    notes: list[str] = []
    thinned_from = 0
    if thin_above is not None and len(f) > thin_above:
        thinned_from = len(f)
        v, f = thin(v, f, min(THIN_TO, thin_above), label, progress)
        notes.append(f"{label}: {thinned_from} faces thinned to {len(f)} for matching (vertex clustering); "
                     "the outputs carry the original mesh")
    degenerate = degenerate_faces(v, f)
    # Duplicate faces: the same vertex set, whatever the order.
    first, _, _ = unique_rows(np.sort(f, axis=1))
    duplicate = np.ones(len(f), bool)
    duplicate[first] = False
    drop = degenerate | duplicate
    if drop.any():
        msg = f"{label}: removed {int(degenerate.sum())} degenerate and {int((duplicate & ~degenerate).sum())} duplicate faces"
        warnings.warn(msg, stacklevel=5)
        notes.append(msg)
        f = f[~drop]
    v, f = _used_vertices(v, f)
    pieces = _body_faces(v, f) if drop.any() or thinned_from else [f]
    if len(pieces) > 1:  # only degenerate faces held it together
        f = f[max(pieces, key=lambda p: _area(v, f[p]))]
        v, f = _used_vertices(v, f)
        notes.append(f"{label}: fell apart into {len(pieces)} bodies once degenerate faces were removed; kept the largest")
    if describe and not is_watertight(f):
        notes.append(f"{label}: the mesh is not watertight (open boundary); accepted, as scans often are")
    return Fragment(name, v, f.astype(np.int32), source, tuple(notes), thinned_from=thinned_from)


def thin(v: np.ndarray, f: np.ndarray, target: int, label: str = "mesh", progress: bool = True,
         ) -> tuple[np.ndarray, np.ndarray]:
    """Thin a mesh to about `target` faces by vertex clustering, reporting on stderr.

    Space is cut into cubes of side ``sqrt(2 A / target)`` (A: the surface area, so about
    `target` faces survive); the vertices of a cube merge at their mean, and faces whose
    corners fall into fewer than three cubes vanish. Memory stays a few arrays of the input's
    size.

    Parameters
    ----------
    v : (V, 3) float64 vertices
    f : (F, 3) int faces
    target : int
    label : str, names the mesh on the progress line
    progress : bool
        A line on stderr when done, and a live bar (one step a clustering pass) while
        stderr is a terminal; nothing when False (``--quiet``).

    Returns
    -------
    vertices : (V', 3) float64
    faces : (F', 3) int64, F' about `target`
    """
    t0 = time.perf_counter()
    side = np.sqrt(2.0 * _area(v, f) / target)
    with progress_bar(THIN_PASSES, f"thinning {Path(label).name}", progress, unit="pass") as bar:
        for _ in range(THIN_PASSES):  # a cube side that lands within 25% of the target
            vv, ff = _cluster(v, f, side)
            bar.update(1)
            bar.set_postfix_str(f"{len(ff):,} faces")
            if 0.75 * target <= len(ff) <= 1.25 * target:
                break
            side *= np.sqrt(len(ff) / target)
    if progress:
        print(f"thinning {label}: {len(f):,} -> {len(ff):,} faces in {time.perf_counter() - t0:.1f} s",
              file=sys.stderr, flush=True)
    return vv, ff


def progress_bar(total: int, desc: str, progress: bool = True, unit: str = "it"):
    """A tqdm bar on stderr, shown only when `progress` (no ``--quiet``) and stderr is a
    terminal, as the command line's other bars; it vanishes when done (``leave=False``).
    Units "faces" and "B" (bytes) are shown scaled (1.35M faces, 95.2MB)."""
    from tqdm import tqdm
    return tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, leave=False, dynamic_ncols=True,
                disable=not (progress and sys.stderr.isatty()), unit_scale=unit in ("faces", "B"))


# read_batch shows a bar in bytes when its files hold more than this (a few seconds' reading)
READ_BAR_ABOVE = 50 * 2 ** 20


def _cluster(v: np.ndarray, f: np.ndarray, side: float) -> tuple[np.ndarray, np.ndarray]:
    """Vertex clustering on cubes of `side`: (mean vertex per cube, faces spanning three cubes)."""
    cell = np.floor((v - v.min(0)) / side).astype(np.int64)
    dims = cell.max(0) + 1
    _, cluster = np.unique((cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2], return_inverse=True)
    cluster = cluster.ravel()
    del cell
    n = int(cluster.max()) + 1
    counts = np.bincount(cluster, minlength=n)[:, None]
    centres = np.stack([np.bincount(cluster, weights=v[:, k], minlength=n) for k in range(3)], 1) / counts
    g = cluster[f]
    g = g[(g[:, 0] != g[:, 1]) & (g[:, 1] != g[:, 2]) & (g[:, 0] != g[:, 2])]
    first, _, _ = unique_rows(np.sort(g, axis=1))
    return centres, g[np.sort(first)]


def unique_rows(a) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The distinct rows of an integer array, in lexicographic order (as ``np.unique(a, axis=0)``,
    several times faster and leaner on millions of rows: one int64 sort key where the ranges
    allow, else a lexsort).

    Parameters
    ----------
    a : (N, k) int

    Returns
    -------
    first : (U,) int64, the index of each distinct row's first occurrence
    inverse : (N,) int64, the distinct row of each row
    counts : (U,) int64, how many rows each distinct row has
    """
    a = np.asarray(a, np.int64)
    n = len(a)
    if n == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64)
    low = a.min(0)
    # Python ints: max - min can overflow int64 (e.g. the bit patterns of floats, to weld by position)
    spans = [int(hi) - int(lo) + 1 for hi, lo in zip(a.max(0), low)]
    if int(np.prod([float(x) for x in spans])) < 2 ** 62:  # mixed radix, first column most significant
        key = np.zeros(n, np.int64)
        for k in range(a.shape[1]):
            key = key * spans[k] + (a[:, k] - low[k])
        order = np.argsort(key, kind="stable")
        key = key[order]
        new = np.empty(n, bool)
        new[0] = True
        np.not_equal(key[1:], key[:-1], out=new[1:])
        del key
    else:
        order = np.lexsort(a.T[::-1])
        rows = a[order]
        new = np.empty(n, bool)
        new[0] = True
        np.any(rows[1:] != rows[:-1], axis=1, out=new[1:])
        del rows
    starts = np.flatnonzero(new)
    inverse = np.empty(n, np.int64)
    inverse[order] = np.cumsum(new) - 1
    return order[starts], inverse, np.diff(np.append(starts, n))


def degenerate_faces(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Faces with a repeated vertex index or no area to speak of, whatever the units and origin.

    Parameters
    ----------
    v : (V, 3) float64 vertex coordinates
    f : (F, 3) int vertex indices

    Returns
    -------
    (F,) bool: True for a degenerate face.

    A face is degenerate when twice its area is under ``1e-14 * diag**2`` (diag: the
    diagonal of the mesh's bounding box), or under what rounding of the coordinates can
    make of a flat triangle (a few ulps of the largest coordinate times diag): a mesh
    scaled by 1e-3 and moved 400 units away keeps the same faces.
    """
    diag = float(np.linalg.norm(v.max(0) - v.min(0))) if len(v) else 0.0
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    area2 = np.linalg.norm(cross, axis=1)
    rounding = 8 * np.finfo(np.float64).eps * float(np.abs(v).max(initial=0.0)) * diag
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
    return repeated | (area2 <= max(1e-14 * diag ** 2, rounding))


def _used_vertices(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drop vertices no face uses, keeping the order of the rest."""
    used = np.zeros(len(v), bool)
    used[f.ravel()] = True
    remap = np.cumsum(used) - 1
    return v[used], remap[f]


def _area(v: np.ndarray, f: np.ndarray) -> float:
    return 0.5 * float(np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1).sum())


def _largest_of(frags: list[Fragment], skipped: list[dict], notes: list[str], label: str) -> Fragment:
    """The largest body of a file or mesh, its notes saying what else the file held."""
    main = frags[0]
    if len(frags) == 1 and not skipped:
        return main
    extra = (f"{label}: holds {len(frags) + len(skipped)} bodies; using the largest "
             f"({len(main.faces)} faces) as {main.name!r}",)
    return dataclasses.replace(main, notes=tuple(notes) + extra + main.notes)


def _body_faces(vertices: np.ndarray, faces: np.ndarray) -> list[np.ndarray]:
    """Face indices of each connected body (faces joined where they share a vertex position)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    if len(faces) == 0:
        return []
    # Merge coincident vertices first: many formats (STL) store each triangle apart.
    low = vertices.min(0)
    diag = float(np.linalg.norm(vertices.max(0) - low)) or 1.0
    _, inverse, _ = unique_rows(np.round((vertices - low) * (1e12 / diag)))
    f = inverse[faces]
    n = len(inverse)
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]]])
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    _, body = np.unique(labels[f[:, 0]], return_inverse=True)
    order = np.argsort(body, kind="stable")
    return np.split(order, np.cumsum(np.bincount(body))[:-1])


def count_bodies(vertices: np.ndarray, faces: np.ndarray) -> int:
    """Connected components of the faces, joining faces that share a vertex position."""
    return len(_body_faces(np.asarray(vertices, np.float64), np.asarray(faces, np.int64)))


def is_watertight(faces: np.ndarray) -> bool:
    """Every undirected edge is shared by exactly two faces."""
    f = np.asarray(faces, np.int64)
    _, _, counts = unique_rows(np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1))
    return bool(np.all(counts == 2))


def load_fragment(path, name: str | None = None) -> Fragment:
    """Read a mesh (or a point cloud, triangulated) into a checked, cleaned Fragment.

    A file of several bodies (or a scene of several meshes) gives its largest body; its
    notes say so. `load_fragments` gives every body.
    """
    frags, skipped, notes = load_fragments(path, name)
    return _largest_of(frags, skipped, notes, str(path))


def load_fragments(path, name: str | None = None, thin_above: int | None = THIN_ABOVE, progress: bool = True,
                   ) -> tuple[list[Fragment], list[dict], list[str]]:
    """Read one file into a Fragment per body (or per mesh of a scene), crumbs dropped.

    Parameters
    ----------
    path : path-like
        A mesh (STL, PLY, OBJ, OFF, GLB/glTF) or point-cloud file.
    name : str, optional
        The id of the fragment (default: the file stem); bodies are ``name#k``.
    thin_above : int or None
        Bodies of more faces are thinned to about THIN_TO faces (`thin`; the fragment's
        ``thinned_from`` and a note say so); None keeps every face.
    progress : bool
        Report thinning on stderr (`thin`); False for ``--quiet``.

    Returns
    -------
    fragments, skipped, notes
        As `fragments_from_arrays`.

    Raises
    ------
    FragmentError
        The file cannot be read; the message names the file and the fault.
    """
    p = Path(path)
    label = str(p)
    name = name or p.stem
    if not p.exists():
        raise FragmentError(f"{label}: no such file")
    if p.is_dir():
        raise FragmentError(f"{label}: is a directory, not a mesh file")
    suffix = p.suffix.lower()
    if suffix in POINT_SUFFIXES or (suffix == ".ply" and _ply_without_faces(p)):
        try:
            from . import pointcloud
        except ImportError as exc:  # the point-cloud stage is optional
            raise FragmentError(f"{label}: point clouds need relicgpu.pointcloud ({exc})") from exc
        return [pointcloud.load_point_cloud_fragment(p, name=name)], [], []
    if suffix not in MESH_SUFFIXES:
        raise FragmentError(f"{label}: unknown format {suffix or '(no extension)'!r}; use STL, PLY, OBJ, OFF or GLB")
    parts = [_checked_arrays(label, v, f) for v, f in _read_meshes(p, label)]
    return split_bodies(name, label, label, parts, thin_above, progress)


def load_original(fragment: Fragment) -> Fragment:
    """A fragment as its file holds it: read again where it was thinned at load (same
    cleaning, no thinning, nothing on stderr), else the fragment itself (also when the file
    can no longer be read). A file that is that one body is not split into bodies again.
    Its notes are not made again (they were said at load): no watertightness test.
    """
    if not fragment.thinned_from or not fragment.source:
        return fragment
    label = fragment.source
    try:
        parts = [_checked_arrays(label, v, f) for v, f in _read_meshes(Path(label), label)]
        if len(parts) == 1 and len(parts[0][1]) == fragment.thinned_from:
            (v, f), = parts
            del parts
            return _clean_body(fragment.name, v, f, label, fragment.source, describe=False)
        name = fragment.name
        for base in [name] + ([name.rsplit("#", 1)[0]] if "#" in name else []):
            found = [f for f in split_bodies(base, label, label, parts, None, False, describe=False)[0]
                     if f.name == name]
            if found:
                return found[0]
    except FragmentError:
        pass
    return fragment


# Formats trimesh reads as one mesh: loaded without force="mesh", which on a 6M-face PLY costs
# 0.8 GiB more at its peak (a scene is made and flattened again).
SINGLE_MESH_SUFFIXES = {".ply", ".stl", ".off"}
# After reading a mesh of more faces, trimesh's objects (reference cycles: a mesh and its
# visuals) are collected at once rather than at the next automatic collection: 0.8 GiB on 6M faces.
COLLECT_ABOVE = 200_000


def _read_meshes(p: Path, label: str) -> list[tuple[np.ndarray, np.ndarray]]:
    """(vertices, faces) of each mesh of a file: one, or one per mesh of a GLB/glTF scene.

    Returns
    -------
    list of (vertices (V, 3) float64, faces (F, 3) int)
    """
    import gc

    import trimesh

    suffix = p.suffix.lower()
    scene = suffix in (".glb", ".gltf")
    force = {} if scene or suffix in SINGLE_MESH_SUFFIXES else {"force": "mesh"}
    try:
        with warnings.catch_warnings():  # e.g. an OBJ whose .mtl is missing: the geometry is what counts
            warnings.simplefilter("ignore")
            loaded = trimesh.load(str(p), process=False, **force)
            if isinstance(loaded, trimesh.Scene) and not scene:  # e.g. an STL of several solids: as force="mesh"
                loaded = loaded.to_mesh()
            meshes = loaded.dump() if isinstance(loaded, trimesh.Scene) else [loaded]
    except Exception as exc:
        raise FragmentError(f"{label}: unreadable {suffix[1:].upper()} file ({type(exc).__name__}: {exc})") from None
    out = [(np.asarray(m.vertices, np.float64), np.asarray(m.faces))
           for m in meshes if len(getattr(m, "vertices", ())) and len(getattr(m, "faces", ()))]
    faces = sum(len(f) for _, f in out)
    del loaded
    if faces > COLLECT_ABOVE:
        meshes.clear()
        gc.collect()
    if not out and not any(len(getattr(m, "vertices", ())) for m in meshes):
        raise FragmentError(f"{label}: unreadable or empty {suffix[1:].upper()} file (no vertices)")
    if not out:
        raise FragmentError(f"{label}: the mesh has no faces")
    return out


def read_las(path, label: str | None = None) -> tuple[np.ndarray, np.ndarray | None, list[str]]:
    """Read a LAS or LAZ point cloud with laspy.

    Parameters
    ----------
    path : path-like, a .las or .laz file (LAZ needs laspy's lazrs backend)
    label : str, optional
        Names the file in messages (default: the path).

    Returns
    -------
    points : (N, 3) float64
        x, y, z with the file's scales and offsets applied.
    normals : (N, 3) float64 or None
        From extra dimensions NormalX/NormalY/NormalZ, normal_x/... or nx/ny/nz (any case),
        made unit length; None when the file has none, or some are zero or not finite
        (a note says so).
    notes : list of str

    Raises
    ------
    FragmentError
        laspy (or for LAZ a decompression backend) is missing, or the file cannot be read.
    """
    p = Path(path)
    label = label or str(p)
    kind = p.suffix[1:].upper() or "LAS"
    try:
        import laspy
    except ImportError:
        raise FragmentError(f"{label}: {kind} point clouds need laspy (pip install laspy lazrs); "
                            "or convert it to .ply, .pcd, .xyz or .npy") from None
    if kind == "LAZ" and not laspy.LazBackend.detect_available():
        raise FragmentError(f"{label}: LAZ needs a decompression backend for laspy (pip install lazrs)")
    try:
        las = laspy.read(str(p))
        points = np.column_stack([np.asarray(las.x, np.float64), np.asarray(las.y, np.float64),
                                  np.asarray(las.z, np.float64)])
        extra = {n.lower(): n for n in las.point_format.extra_dimension_names}
        found = next((names for names in LAS_NORMAL_NAMES if all(n in extra for n in names)), None)
        normals = None if found is None else np.column_stack([np.asarray(las[extra[n]], np.float64) for n in found])
    except Exception as exc:  # laspy raises its own errors, and struct/ValueError/OSError on truncated files
        raise FragmentError(f"{label}: unreadable {kind} file ({type(exc).__name__}: {exc})") from None
    notes: list[str] = []
    if normals is not None:
        with np.errstate(invalid="ignore"):
            length = np.linalg.norm(normals, axis=1)
        if not (np.isfinite(length).all() and (length > 0).all()):
            notes.append(f"{label}: normals ({', '.join(extra[n] for n in found)}) hold zero, NaN or infinite "
                         "vectors; ignored")
            normals = None
        else:
            normals = normals / length[:, None]
    return points, normals, notes


def _ply_without_faces(path: Path) -> bool:
    """True for a PLY whose header declares no faces (a point cloud)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(4096)
    except OSError:
        return False
    if not head.startswith(b"ply"):
        return False
    header = head.split(b"end_header")[0].decode("ascii", "replace")
    for line in header.splitlines():
        parts = line.split()
        if len(parts) == 3 and parts[0] == "element" and parts[1] == "face":
            return int(parts[2]) == 0
    return True


# --- a batch of files -------------------------------------------------------

@dataclass
class Batch:
    """Fragments read from many files, and every file or body left out, with why.

    ``skipped`` holds ``{"file", "reason"}`` per unreadable file and ``{"file", "name",
    "reason"}`` per crumb; ``notes`` the other decisions (files split into several
    fragments, degenerate faces removed, open meshes accepted). Both go into assembly.json
    and groups.json, one line each on the terminal.
    """
    fragments: list[Fragment]
    skipped: list[dict] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    seconds: float = 0.0  # time taken to read it

    def messages(self) -> list[str]:
        """The terminal lines: one per kind of decision (see `grouped_lines`; the JSON lists each)."""
        return (grouped_lines("skipped", [s["reason"] for s in self.skipped])
                + grouped_lines("note", self.notes))

    def require(self, n: int = 2) -> None:
        """Raise FragmentError when fewer than n fragments could be read."""
        if len(self.fragments) < n:
            unread = [s for s in self.skipped if "name" not in s]
            raise FragmentError(f"only {len(self.fragments)} fragment(s) could be read, {n} are needed"
                                + (f" ({len(unread)} file(s) skipped, first: {unread[0]['reason']})" if unread else ""))


def grouped_lines(prefix: str, messages: list[str], shown: int = 3) -> list[str]:
    """Terminal lines for messages ``"<file>: <what>"``: one line per kind of `what` (its
    numbers and parentheses aside), the first message in full and a count of the others like it.

    ["a.ply: not watertight", "b.ply: not watertight"] -> ["note: a.ply: not watertight
    (and 1 more like it: b.ply)"]
    """
    kinds: dict[str, list[str]] = {}
    for m in messages:
        what = m.split(": ", 1)[-1]
        kind = re.sub(r"\d+(?:\.\d+)?(?:e[-+]?\d+)?", "#", re.sub(r"\([^)]*\)", "()", what))
        kinds.setdefault(kind, []).append(m)
    lines = []
    for group in kinds.values():
        line = f"{prefix}: {group[0]}"
        if len(group) > 1:
            others = [m.split(": ", 1)[0] for m in group[1:]]
            listed = ", ".join(others[:shown]) + (", ..." if len(others) > shown else "")
            line += f" (and {len(others)} more like it: {listed}; all listed in the JSON output)"
        lines.append(line)
    return lines


def fragment_ids(files) -> list[str]:
    """The id of each file of a batch: its stem where no other file has that stem, else its
    name with the extension (``a.ply`` and ``a.obj``), else the path as given."""
    names = [Path(f).name for f in files]
    stems = [Path(f).stem for f in files]
    return [s if stems.count(s) == 1 else n if names.count(n) == 1 else str(f)
            for f, n, s in zip(files, names, stems)]


def fragment_files(directory) -> list[Path]:
    """The fragment files of a directory, sorted by name (FragmentError when there are none)."""
    d = Path(directory)
    if not d.is_dir():
        raise FragmentError(f"{d}: not a directory")
    files = sorted(p for p in d.iterdir() if p.is_file() and p.suffix.lower() in FRAGMENT_SUFFIXES)
    if not files:
        raise FragmentError(f"{d}: no fragment files (STL, PLY, OBJ, OFF, GLB, or point clouds) found")
    return files


def read_batch(fragments_or_dir, progress: bool = True) -> Batch:
    """Read a directory, or a list of files and Fragments; a file that cannot be read is skipped.

    Files are named by `fragment_ids`; Fragments given keep their names. `progress`: report
    the thinning of big meshes on stderr (`thin`); False for ``--quiet``.
    """
    if isinstance(fragments_or_dir, Batch):
        return fragments_or_dir
    if isinstance(fragments_or_dir, (str, os.PathLike)):
        items: list = fragment_files(fragments_or_dir)
    else:
        items = list(fragments_or_dir)
    t0 = time.perf_counter()
    paths = [Path(x) for x in items if not isinstance(x, Fragment)]
    ids = iter(fragment_ids(paths))
    batch = Batch([])
    # a bar in bytes read (a 5M-face mesh takes seconds to read and split before it is thinned)
    sizes = [0 if isinstance(x, Fragment) or not Path(x).is_file() else Path(x).stat().st_size for x in items]
    with progress_bar(sum(sizes), "reading", progress and sum(sizes) > READ_BAR_ABOVE, unit="B") as bar:
        for item, size in zip(items, sizes):
            if isinstance(item, Fragment):
                batch.fragments.append(item)
                continue
            p = Path(item)
            bar.set_postfix_str(p.name)
            try:
                with warnings.catch_warnings():  # what cleaning warns of is in the fragments' notes
                    warnings.simplefilter("ignore")
                    frags, skipped, notes = load_fragments(p, next(ids), progress=progress)
            except FragmentError as exc:
                batch.skipped.append({"file": p.name, "reason": str(exc)})
                continue
            finally:
                bar.update(size)
            batch.fragments += frags
            batch.skipped += skipped
            batch.notes += notes + [n for f in frags for n in f.notes]
    batch.seconds = time.perf_counter() - t0
    return batch


def load_directory(directory) -> list[Fragment]:
    """All fragments of a directory's files (sorted by name); see `read_batch` for what is skipped."""
    return read_batch(directory).fragments


# --- atomic outputs --------------------------------------------------------

@contextlib.contextmanager
def atomic_open(path):
    """A binary file to write `path` through: a temporary file in the same directory, renamed
    over `path` when the block ends without an exception (removed otherwise)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w+b") as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        # mkstemp makes the file private (0600); give it the mode a plain open() would
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def atomic_write_bytes(path, data: bytes) -> None:
    """Write data to path via a temporary file in the same directory and a rename."""
    with atomic_open(path) as fh:
        fh.write(data)


def atomic_write_json(path, obj) -> None:
    atomic_write_bytes(path, (json.dumps(obj, indent=2, default=_json_default) + "\n").encode())


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


# A binary STL facet: unit normal, three corners, a zero attribute count (50 bytes).
STL_FACET = np.dtype([("normal", "<f4", (3,)), ("corners", "<f4", (3, 3)), ("attr", "<u2")])
STL_CHUNK = 1 << 19  # facets converted at a time (about 40 MB of temporaries)


def write_stl(fh, parts, on_faces=None) -> int:
    """Write meshes into one binary STL, a chunk of faces at a time (nothing the size of the
    whole file is held in memory); the facet count is filled in at the end (`fh` must seek).

    Parameters
    ----------
    fh : binary file open for writing at its start
    parts : iterable of (vertices (V, 3) float32 or float64, faces (F, 3) int)
        Consumed one at a time: a generator can free each mesh once written.
    on_faces : callable(int), optional
        Told how many faces each chunk wrote (a progress bar).

    Returns
    -------
    int, the facets written
    """
    fh.write(b"relicgpu binary STL".ljust(80, b" "))
    fh.write(np.uint32(0).tobytes())
    total = 0
    for vertices, faces in parts:
        for start in range(0, len(faces), STL_CHUNK):
            tri = np.asarray(vertices[np.asarray(faces[start:start + STL_CHUNK], np.int64)], np.float64)  # (c, 3, 3)
            normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            length = np.linalg.norm(normal, axis=1, keepdims=True)
            facets = np.zeros(len(tri), STL_FACET)
            facets["normal"] = np.divide(normal, length, out=np.zeros_like(normal), where=length > 0)
            facets["corners"] = tri
            fh.write(facets.tobytes())
            total += len(tri)
            if on_faces is not None:
                on_faces(len(tri))
    end = fh.tell()
    fh.seek(80)
    fh.write(np.uint32(total).tobytes())
    fh.seek(end)
    return total


def write_mesh(path, vertices, faces) -> None:
    """Write a mesh (format from the suffix) atomically; STL through `write_stl`."""
    import trimesh
    path = Path(path)
    if path.suffix.lower() == ".stl":
        with atomic_open(path) as fh:
            write_stl(fh, [(vertices, faces)])
        return
    data = trimesh.Trimesh(np.asarray(vertices), np.asarray(faces), process=False).export(file_type=path.suffix[1:].lower())
    atomic_write_bytes(path, data if isinstance(data, bytes) else data.encode())


def ensure_not_input(out_path, inputs) -> None:
    """Refuse to write an output over one of the inputs."""
    out = Path(out_path).resolve()
    for i in inputs:
        if Path(i).resolve() == out:
            raise FragmentError(f"{out}: refusing to overwrite an input file")
