"""A fragment and its checks: the cleaned, checked arrays a file loads into (one `Fragment` a
body), the crumbs and bodies split off, thinning of very large meshes, and the `FragmentError`
every fault a user can cause becomes (naming the file and the fault)."""
from __future__ import annotations

import dataclasses
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..progress import progress_bar

# A body of less than this fraction of the largest body's area in its file is a crumb: dropped.
CRUMB_FRACTION = 0.01
# Bodies of more faces than THIN_ABOVE are thinned at load to about THIN_TO faces (the working
# resolution: prepare samples a few thousand points a fragment); outputs reload the original.
THIN_ABOVE = 1_000_000
THIN_TO = 200_000
THIN_PASSES = 4  # clustering passes at most, each resizing the cubes towards THIN_TO faces
# a body wound inward (negative signed volume) is turned outward where it encloses more than this
# share of its bounding box; an open sheet encloses next to nothing and is left as wound
ENCLOSED = 1e-3


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
    degenerate and duplicate faces and unused vertices removed; wound outward (`outward`).
    `describe` False skips what only makes a note (the watertightness test: 0.7 GiB and seconds
    on 6M faces) and rewinding patch by patch."""
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
    edges = _edges(f) if describe else None  # (rewinding leaves every edge where it was)
    f, turned = outward(v, f, rewind=describe, edges=edges)
    notes += [f"{label}: {why}" for why in turned]
    if edges is not None and not np.all(edges[2] == 2):  # (`is_watertight`)
        notes.append(f"{label}: the mesh is not watertight (open boundary); accepted, as scans often are")
    return Fragment(name, v, f.astype(np.int32), source, tuple(notes), thinned_from=thinned_from)


def outward(v: np.ndarray, f: np.ndarray, rewind: bool = True, edges: tuple | None = None,
            ) -> tuple[np.ndarray, list[str]]:
    """Faces wound alike across every edge and outward, and what was turned to make them so.

    A scan exported inside out, or with patches wound the other way, has normals that point into
    the solid: the checks that read which side of a surface is solid (facing, interpenetration)
    then pass a fit turned half over (corpus rough-clean seed 1, one piece inside out: accepted 180
    degrees off). Outward is where the signed volume is positive; a body that encloses next to
    none (an open sheet) is left as wound. `rewind` False turns the body as a whole only (a file of
    millions of faces read again for the outputs: rewinding patch by patch walks the whole graph).

    Parameters
    ----------
    v : (n, 3) float
    f : (m, 3) int
    edges : `_edges(f)` where the caller has it

    Returns
    -------
    faces : (m, 3) int
    turned : list of str, one line for each change made
    """
    turned = []
    if rewind and _misrun_edges(*(edges or _edges(f))):
        import trimesh

        mesh = trimesh.Trimesh(v, f, process=False)
        trimesh.repair.fix_winding(mesh)
        f = np.asarray(mesh.faces)
        turned.append("faces wound inconsistently; each patch rewound to agree with its neighbours")
    if signed_volume(v, f) < -ENCLOSED * float(np.prod(np.ptp(v, axis=0))):
        f = np.ascontiguousarray(f[:, ::-1])
        turned.append("faces wound inward (normals into the solid); turned outward")
    return f, turned


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


def signed_volume(v: np.ndarray, f: np.ndarray, chunk: int = 1_000_000) -> float:
    """The volume the faces enclose, positive where they are wound outward; taken about the
    vertices' centroid (a scan far from the origin keeps its digits), `chunk` faces at a time."""
    centre, total = v.mean(axis=0), 0.0
    for start in range(0, len(f), chunk):
        t = v[f[start:start + chunk]] - centre
        total += float(np.einsum("ij,ij->", t[:, 0], np.cross(t[:, 1], t[:, 2])))
    return total / 6.0


def _edges(f: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each face's three edges as it runs them, (3m, 2) int64; the undirected edge of each, (3m,);
    and how many faces share each undirected edge, (E,)."""
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]).astype(np.int64, copy=False)
    _, edge, count = unique_rows(np.sort(directed, axis=1))
    return directed, edge, count


def _misrun_edges(directed: np.ndarray, edge: np.ndarray, count: np.ndarray) -> int:
    """How many edges of exactly two faces both faces run the same way (an edge of more faces,
    where sheets meet, says nothing of their winding), from a body's `_edges`."""
    two = count[edge] == 2
    forward = directed[:, 0] < directed[:, 1]
    runs = np.bincount(edge[two], weights=forward[two], minlength=len(count))
    return int(np.sum((count == 2) & (runs != 1)))


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
    return bool(np.all(_edges(np.asarray(faces, np.int64))[2] == 2))
