"""Refinement of a triangulated cloud (step 7 of `relicgpu.cloud.triangulate`): edge flips towards
the cloud's normals and a quadric vertex smoothing, keeping the mesh a closed manifold."""
from __future__ import annotations

import numpy as np

from ..io.fragment import count_bodies
from ..topology import vertex_adjacency

# Refinement (step 7): unit normals of the cloud from this many nearest points; rounds of
# edge flips; the vertex move's neighbourhood (edge steps) and its pull to the old position.
NORMAL_NEIGHBOURS = 16
FLIP_ROUNDS = 12
FLIP_MARGIN = 1e-3
SMOOTH_RINGS = 2
SMOOTH_STAY = 0.2

def _unit(x: np.ndarray) -> np.ndarray:
    length = np.linalg.norm(x, axis=-1, keepdims=True)
    return x / np.where(length > 0, length, 1.0)


def _area_vectors(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Per face, the normal scaled by twice the area."""
    return np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])


def cloud_normals(vertices: np.ndarray, faces: np.ndarray, cloud: np.ndarray,
                  k: int = NORMAL_NEIGHBOURS) -> np.ndarray:
    """Unit normal at each vertex: the least principal axis of its k nearest cloud points,
    turned to agree with the mesh's area-weighted vertex normal (outwards)."""
    from scipy.spatial import cKDTree

    k = min(k, len(cloud))
    _, idx = cKDTree(cloud).query(vertices, k=k, workers=-1)
    normals = np.empty_like(vertices)
    for s in range(0, len(vertices), 200_000):
        nb = cloud[idx[s:s + 200_000]]
        nb = nb - nb.mean(axis=1, keepdims=True)
        _, vec = np.linalg.eigh(np.einsum("nki,nkj->nij", nb, nb))
        normals[s:s + 200_000] = vec[:, :, 0]
    mesh_normals = np.zeros_like(vertices)
    area = _area_vectors(vertices, faces)
    for c in range(3):
        for axis in range(3):
            mesh_normals[:, axis] += np.bincount(faces[:, c], area[:, axis], minlength=len(vertices))
    return normals * np.where(np.einsum("ij,ij->i", normals, mesh_normals) < 0, -1.0, 1.0)[:, None]


def _edge_pairs(faces: np.ndarray):
    """For each edge of a closed manifold: its ends (a, b) as in the first face, the vertex
    opposite in that face (c) and in the other (d), both faces, and the sorted edge keys.
    None when some edge is not shared by exactly two faces."""
    nf, n = len(faces), int(faces.max()) + 1
    a, b, c = faces.ravel(), np.roll(faces, -1, axis=1).ravel(), np.roll(faces, -2, axis=1).ravel()
    key = np.minimum(a, b) * n + np.maximum(a, b)
    order = np.argsort(key, kind="stable")
    k = key[order]
    if len(k) % 2 or not np.array_equal(k[0::2], k[1::2]) or (len(k) > 2 and (k[2::2] == k[1:-1:2]).any()):
        return None
    h1, h2 = order[0::2], order[1::2]
    face = np.arange(3 * nf) // 3
    return a[h1], b[h1], c[h1], c[h2], face[h1], face[h2], k[0::2], n


def flip_edges(vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray, rounds: int = FLIP_ROUNDS):
    """Flip edges where both new triangles agree better with the vertex normals than the old
    pair's worse one did (by cosine to the mean normal of their corners). Each round flips an
    independent set of edges (no face twice) whose new edge does not exist yet, so the mesh
    stays a closed manifold. Returns the new faces (None if the mesh is not a closed
    manifold) and the number of flips."""
    f = np.asarray(faces, np.int64).copy()
    v = vertices
    # a flip that leaves a triangle of (nearly) no area would have no trustworthy normal
    tiny = 1e-12 * float(np.ptp(v, axis=0).max()) ** 2
    total = 0

    def agreement(t):
        area = _area_vectors(v, t)
        cos = np.einsum("ij,ij->i", _unit(area), _unit(normals[t].sum(axis=1)))
        return np.where(np.einsum("ij,ij->i", area, area) > tiny ** 2, cos, -2.0)

    changed = np.ones(len(f), bool)  # an edge's gain depends on its two faces only
    for _ in range(rounds):
        pairs = _edge_pairs(f)
        if pairs is None:
            return None, total
        a, b, c, d, f1, f2, keys, n = pairs
        e = np.nonzero((changed[f1] | changed[f2]) & (c != d))[0]
        a, b, c, d, f1, f2 = a[e], b[e], c[e], d[e], f1[e], f2[e]
        t1, t2 = np.stack([a, d, c], 1), np.stack([d, b, c], 1)
        old = np.minimum(agreement(np.stack([a, b, c], 1)), agreement(np.stack([b, a, d], 1)))
        gain = np.minimum(agreement(t1), agreement(t2)) - old
        new_key = np.minimum(c, d) * n + np.maximum(c, d)
        cand = np.nonzero(gain > FLIP_MARGIN)[0]
        at = np.minimum(np.searchsorted(keys, new_key[cand]), len(keys) - 1)  # keys are sorted
        cand = cand[keys[at] != new_key[cand]]
        if len(cand) == 0:
            break
        changed[:] = False  # candidates that lose to a neighbour below are tried again next round
        changed[f1[cand]] = changed[f2[cand]] = True
        cand = cand[np.argsort(-gain[cand], kind="stable")]  # largest gain first
        rank = np.arange(len(cand))
        first = np.full(len(f), len(cand))
        np.minimum.at(first, np.concatenate([f1[cand], f2[cand]]), np.concatenate([rank, rank]))
        cand = cand[(first[f1[cand]] == rank) & (first[f2[cand]] == rank)]
        _, once = np.unique(new_key[cand], return_index=True)  # two flips must not make one edge
        cand = cand[np.sort(once)]
        f[f1[cand]] = t1[cand]
        f[f2[cand]] = t2[cand]
        total += len(cand)
    return f, total


def quadric_smooth(vertices: np.ndarray, faces: np.ndarray, rings: int = SMOOTH_RINGS,
                   stay: float = SMOOTH_STAY) -> np.ndarray:
    """Move each vertex to the point nearest (least squares) to the planes of the triangles
    within `rings` edge steps, weighted by area, plus `stay` times their summed weight (the
    trace of the plane quadric) pulling it to where it was. On a smooth patch this removes noise across the surface and
    barely moves along it; at a crease the planes of both sides hold it on the crease."""
    from scipy.sparse import coo_matrix

    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    nv, nf = len(v), len(f)
    area_vec = _area_vectors(v, f)
    area = 0.5 * np.linalg.norm(area_vec, axis=1)
    normal = _unit(area_vec)
    centre = v[f].mean(axis=1)
    nn = np.einsum("fi,fj->fij", normal, normal) * area[:, None, None]
    q = np.concatenate([nn.reshape(nf, 9), np.einsum("fij,fj->fi", nn, centre)], axis=1)
    incidence = coo_matrix((np.ones(3 * nf), (f.ravel(), np.repeat(np.arange(nf), 3))), shape=(nv, nf)).tocsr()
    acc = incidence @ q
    if rings > 1:
        adjacency = vertex_adjacency(f, nv)
        for _ in range(rings - 1):
            acc = acc + adjacency @ acc
    mat = acc[:, :9].reshape(nv, 3, 3)
    pull = stay * np.trace(mat, axis1=1, axis2=2)
    mat = mat + pull[:, None, None] * np.eye(3)
    rhs = acc[:, 9:] + pull[:, None] * v
    moved = v.copy()
    ok = pull > 0
    moved[ok] = np.linalg.solve(mat[ok], rhs[ok][:, :, None])[:, :, 0]
    return moved


def refine_surface(vertices: np.ndarray, faces: np.ndarray, cloud: np.ndarray):
    """Step 7 of the module notes: flips by the cloud's normals, one quadric smoothing, flips
    again. Returns (vertices, faces), or None when the mesh is not a closed manifold."""
    f = np.asarray(faces, np.int64)
    normals = cloud_normals(vertices, f, cloud)
    f, _ = flip_edges(vertices, f, normals)
    if f is None:
        return None
    v = quadric_smooth(vertices, f)
    f, _ = flip_edges(v, f, normals)
    if f is None:
        return None
    return v, f.astype(np.int32)


# decimate: error-bounded edge collapse (manifold3d's simplify) at the first tolerance of this sweep,
# a share of the largest side, that leaves at most the target number of faces.
DECIMATE_TOLERANCES = np.geomspace(1e-4, 2e-2, 16)


def decimate(vertices: np.ndarray, faces: np.ndarray, target: int):
    """A closed manifold mesh with at most about `target` faces, by error-bounded edge collapse.

    Collapses move the surface by at most the tolerance, so sharp rims and concave folds the
    dense mesh holds stay; thinning the cloud before meshing bridges folds narrower than a few
    of its (coarser) point spacings instead.

    Parameters
    ----------
    vertices : (V, 3) float
    faces : (F, 3) int, a closed manifold
    target : int

    Returns
    -------
    vertices : (V', 3) float64
    faces : (F', 3) int32
    tolerance : float, the largest move allowed (0: the mesh was small enough)
    None where manifold3d does not take the mesh as a closed manifold.
    """
    import manifold3d

    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    if len(f) <= target:
        return v, f.astype(np.int32), 0.0
    centre = 0.5 * (v.min(0) + v.max(0))  # float32 inside manifold3d: keep the coordinates small
    solid = manifold3d.Manifold(manifold3d.Mesh((v - centre).astype(np.float32), f.astype(np.uint32)))
    if solid.status() != manifold3d.Error.NoError or solid.num_tri() != len(f):
        return None
    side = float(np.ptp(v, axis=0).max())
    for tolerance in side * DECIMATE_TOLERANCES:
        thinner = solid.simplify(float(tolerance))
        if thinner.num_tri() <= target:
            break
    mesh = thinner.to_mesh()
    return (np.asarray(mesh.vert_properties[:, :3], np.float64) + centre,
            np.asarray(mesh.tri_verts, np.int32), float(tolerance))


def closed_manifold_fault(vertices: np.ndarray, faces: np.ndarray) -> str | None:
    """None when the mesh is one closed, consistently wound, outward body with no degenerate
    faces and no two vertices at one place; else what is wrong."""
    v, f = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
    if len(f) < 4:
        return "fewer than 4 faces"
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    if (np.einsum("ij,ij->i", cross, cross) == 0).any():
        return "degenerate faces"
    d = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    key = np.sort(d[:, 0] * len(v) + d[:, 1])
    if (np.diff(key) == 0).any():
        return "an edge used twice in one direction (non-manifold or flipped)"
    if not np.isin(d[:, 1] * len(v) + d[:, 0], key).all():
        return "open edges"
    if len(np.unique(v, axis=0)) != len(v):
        return "two vertices at one place (the surface touches itself)"
    if count_bodies(v, f) != 1:
        return "more than one body"
    if np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() <= 0:
        return "wound inwards"
    return None
