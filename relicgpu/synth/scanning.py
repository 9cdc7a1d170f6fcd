"""Each piece as a scan would see it: the slivers the booleans leave collapsed or flipped
away (checked to stay one clean closed body), no vertex shared with a neighbour, and a
random pose to scatter it to."""
from __future__ import annotations

import math

import numpy as np

from .fracture import _random_unit

SCATTER_RANGE = 2.0  # translations uniform in [-2, 2]^3 object units


def _clean_slivers(v, f, labels, spacing, min_edge=0.2, flat_degrees=10.0, passes=3):
    """Remove the needle and cap triangles the booleans leave where a cut clips a triangle.

    Edges shorter than min_edge x spacing are collapsed (shortest first) when the
    link condition holds, so the mesh stays a closed manifold of the same topology;
    the surviving vertex keeps the position of the endpoint on a crease (a sharp
    edge or the border between fracture and original faces), so creases stay put,
    and a collapse that would turn a face over is skipped. Then the long edge of
    each remaining cap is flipped where its two faces are nearly coplanar (or the
    cap has no area). A few passes, until nothing changes. Returns (v, f, labels).
    """
    v = np.array(v, np.float64, copy=True)
    f = np.array(f, np.int64, copy=True)
    labels = np.asarray(labels, bool).copy()
    for _ in range(passes):
        f, labels, collapsed = _collapse_short_edges(v, f, labels, spacing, min_edge)
        f, labels, flipped = _flip_caps(v, f, labels, spacing, flat_degrees)
        if not collapsed:
            break
    v, f = _drop_unused(v, f)
    return v, f, labels


def _collapse_short_edges(v, f, labels, spacing, min_edge):
    """One pass of short-edge collapses (see _clean_slivers); moves v in place."""
    alive = np.ones(len(f), bool)
    fn = _unit_normals(v, f)
    area2 = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    speck = 1e-6 * spacing * spacing  # faces below this have no trustworthy normal
    sharp_cos = math.cos(math.radians(30.0))
    # A vertex is on a crease if an incident edge is sharp or its faces carry both labels.
    e_lo, e_hi, e_f0, e_f1 = _edge_faces(f)
    sharp = np.einsum("ij,ij->i", fn[e_f0], fn[e_f1]) < sharp_cos
    sharp &= (area2[e_f0] > speck) & (area2[e_f1] > speck)
    border = labels[e_f0] != labels[e_f1]
    crease = np.zeros(len(v), bool)
    crease[e_lo[sharp | border]] = True
    crease[e_hi[sharp | border]] = True
    length = np.linalg.norm(v[e_lo] - v[e_hi], axis=1)
    short = np.flatnonzero(length < min_edge * spacing)
    if len(short) == 0:
        return f, labels, 0

    vert_faces = [set() for _ in range(len(v))]
    for k, tri in enumerate(f.tolist()):
        for x in tri:
            vert_faces[x].add(k)
    collapsed = 0
    for e in short[np.argsort(length[short])]:
        a, b = int(e_lo[e]), int(e_hi[e])
        shared = vert_faces[a] & vert_faces[b]
        if len(shared) != 2:  # the edge is gone already
            continue
        opposite = {int(x) for k in shared for x in f[k]} - {a, b}
        ring_a = {int(x) for k in vert_faces[a] for x in f[k]} - {a}
        ring_b = {int(x) for k in vert_faces[b] for x in f[k]} - {b}
        if (ring_a & ring_b) != opposite:  # link condition: the collapse would pinch the surface
            continue
        if crease[b] and not crease[a]:
            a, b = b, a
        # b merges into a; try a's position, then b's and the midpoint (when a is no crease vertex).
        changed = sorted((vert_faces[a] | vert_faces[b]) - shared)
        tris = np.where(f[changed] == b, a, f[changed])
        candidates = [v[a].copy()] + ([v[b].copy(), 0.5 * (v[a] + v[b])] if not crease[a] or crease[b] else [])
        reliable = area2[changed] > speck
        for pos in candidates:
            p = v[tris]
            p[tris == a] = pos
            n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
            norm = np.linalg.norm(n, axis=1)
            turn = np.einsum("ij,ij->i", n, fn[changed]) > 0.5 * norm
            if (norm[reliable] > speck).all() and turn[reliable].all():
                break
        else:
            continue
        v[a] = pos
        f[changed] = tris
        fn[changed] = n / np.maximum(norm, 1e-300)[:, None]
        area2[changed] = norm
        for k in shared:
            alive[k] = False
            for x in f[k]:
                vert_faces[x].discard(k)
        vert_faces[a] = set(changed)
        vert_faces[b] = set()
        crease[a] = crease[a] or crease[b]
        collapsed += 1
    return f[alive], labels[alive], collapsed


def _flip_caps(v, f, labels, spacing, flat_degrees):
    """Flip the longest edge of triangles with an angle over 150 degrees where the two
    faces are nearly coplanar and carry the same label, and the flip raises the smaller
    angle. A cap without area is flipped whatever its neighbour: its apex lies on the
    edge, so the flip does not change the surface."""
    f, labels = f.copy(), labels.copy()
    fn = _unit_normals(v, f)
    area2 = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    speck = 1e-6 * spacing * spacing
    flat_cos = math.cos(math.radians(flat_degrees))
    angles = _corner_angles(v, f)
    caps = np.flatnonzero(angles.max(axis=1) > 150.0)
    if len(caps) == 0:
        return f, labels, 0
    e_lo, e_hi, e_f0, e_f1 = _edge_faces(f)
    nv = len(v)
    keys = e_lo * nv + e_hi  # sorted, as _edge_faces sorts by (lo, hi)
    new_edges: set[int] = set()

    def edge_of(x, y):
        key = min(x, y) * nv + max(x, y)
        i = int(np.searchsorted(keys, key))
        return i if i < len(keys) and keys[i] == key else None

    touched = set()
    for t in caps:
        if t in touched:
            continue
        corner = int(np.argmax(angles[t]))
        apex = int(f[t, corner])
        a, b = int(f[t, (corner + 1) % 3]), int(f[t, (corner + 2) % 3])
        k = edge_of(a, b)
        if k is None:
            continue
        other = int(e_f1[k] if e_f0[k] == t else e_f0[k])
        if other in touched:
            continue
        flat = area2[t] <= speck
        if not flat and (labels[other] != labels[t] or fn[t] @ fn[other] < flat_cos):
            continue
        far = int(next(x for x in f[other] if x != a and x != b))
        if edge_of(apex, far) is not None or min(apex, far) * nv + max(apex, far) in new_edges:
            continue
        # t = (apex, a, b) in its winding; the flip gives (apex, a, far) and (apex, far, b).
        new = np.array([[apex, a, far], [apex, far, b]])
        n = np.cross(v[new[:, 1]] - v[new[:, 0]], v[new[:, 2]] - v[new[:, 0]])
        reference = fn[other] if flat else fn[t]
        if (np.linalg.norm(n, axis=1) <= speck).any() or (n @ reference <= 0).any():
            continue
        if _corner_angles(v, new).min() <= min(angles[t].min(), _corner_angles(v, f[[other]]).min()):
            continue
        f[t], f[other] = new
        if flat:
            labels[t] = labels[other]
        new_edges.add(min(apex, far) * nv + max(apex, far))
        touched.update((t, other))
    return f, labels, len(touched) // 2


def _corner_angles(v, f):
    t = v[f]
    out = np.empty((len(f), 3))
    for k in range(3):
        u, w = t[:, (k + 1) % 3] - t[:, k], t[:, (k + 2) % 3] - t[:, k]
        c = np.einsum("ij,ij->i", u, w) / np.maximum(np.linalg.norm(u, axis=1) * np.linalg.norm(w, axis=1), 1e-300)
        out[:, k] = np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))
    return out


def _unit_normals(v, f):
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def _edge_faces(f):
    """Undirected edges of a closed manifold mesh: (lo, hi, face0, face1) arrays."""
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    face_of = np.tile(np.arange(len(f)), 3)
    lo, hi = directed.min(axis=1), directed.max(axis=1)
    order = np.lexsort((hi, lo))
    lo, hi, face_of = lo[order], hi[order], face_of[order]
    return lo[0::2], hi[0::2], face_of[0::2], face_of[1::2]


def _drop_unused(v, f):
    used = np.zeros(len(v), bool)
    used[f.ravel()] = True
    if used.all():
        return v, f
    remap = np.cumsum(used) - 1
    return v[used], remap[f]


def _closed_mesh_fault(v, f, want_euler, volume):
    """None when (v, f) is an oriented closed manifold of one body with the given Euler
    characteristic and a volume within 2% of `volume`; else what is wrong."""
    if len(f) < 4:
        return "fewer than 4 faces"
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    if (np.linalg.norm(cross, axis=1) <= 1e-14).any():
        return "degenerate faces"
    n = len(v)
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    key = directed[:, 0] * n + directed[:, 1]
    rkey = directed[:, 1] * n + directed[:, 0]
    skey = np.sort(key)
    if (np.diff(skey) == 0).any():
        return "an edge used twice in the same direction (non-manifold or flipped)"
    pos = np.searchsorted(skey, rkey)
    pos = np.minimum(pos, len(skey) - 1)
    if not (skey[pos] == rkey).all():
        return "open edges"
    if len(v) - len(directed) // 2 + len(f) != want_euler:
        return "topology changed (pinched vertex or lost handle)"
    if _face_components(f) != 1:
        return "more than one body"
    vol = float(np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6.0)
    if abs(vol - volume) > 0.02 * abs(volume):
        return f"volume changed by {100 * (vol - volume) / volume:+.1f}%"
    return None


def _face_components(f):
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = int(f.max()) + 1
    rows = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
    cols = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    graph = coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(n, n))
    return connected_components(graph, directed=False)[0]


def _separate_shared_vertices(vertices, faces, rng, tol=1e-6):
    """Move every vertex that sits on a vertex of an earlier piece a little along its sharpest edge.

    Decimation keeps some vertices of the fine meshes, and neighbours' fine meshes
    share the vertices of their common cut; a scan never samples two fragments at
    the same points. Sliding along the incident edge with the largest dihedral
    angle keeps a vertex on the surface (and on a crease when it is on one).
    """
    from scipy.spatial import cKDTree

    vertices = [np.array(v, np.float64, copy=True) for v in vertices]
    for _round in range(5):
        owner = np.concatenate([np.full(len(v), k) for k, v in enumerate(vertices)])
        local = np.concatenate([np.arange(len(v)) for v in vertices])
        pairs = cKDTree(np.vstack(vertices)).query_pairs(tol, output_type="ndarray")
        if len(pairs) == 0:
            break
        pairs = pairs[owner[pairs[:, 0]] != owner[pairs[:, 1]]]
        if len(pairs) == 0:
            break
        later = np.where(owner[pairs[:, 0]] > owner[pairs[:, 1]], pairs[:, 0], pairs[:, 1])
        later = np.unique(later)
        for k in np.unique(owner[later]):
            _slide_vertices(vertices[k], faces[k], local[later[owner[later] == k]], rng)
    return vertices


def _slide_vertices(v, f, which, rng):
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    fn /= np.linalg.norm(fn, axis=1, keepdims=True)
    # Undirected edges with their two faces -> dihedral angle per edge.
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    face_of = np.tile(np.arange(len(f)), 3)
    lo, hi = directed.min(axis=1), directed.max(axis=1)
    order = np.lexsort((hi, lo))
    lo, hi, face_of = lo[order], hi[order], face_of[order]
    e0, e1 = lo[0::2], hi[0::2]
    cos = np.einsum("ij,ij->i", fn[face_of[0::2]], fn[face_of[1::2]])
    for vid in which:
        sel = np.flatnonzero((e0 == vid) | (e1 == vid))
        incident = np.flatnonzero((f == vid).any(axis=1))
        before = fn[incident]
        for edge in sel[np.argsort(cos[sel])]:  # sharpest first
            other = e1[edge] if e0[edge] == vid else e0[edge]
            old = v[vid].copy()
            v[vid] = old + rng.uniform(0.2, 0.4) * (v[other] - old)
            tri = v[f[incident]]
            after = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            norm = np.linalg.norm(after, axis=1)
            if (norm > 1e-14).all() and (np.einsum("ij,ij->i", after / norm[:, None], before) > 0.5).all():
                break
            v[vid] = old


def _vertex_normals(v, f):
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])  # area weighted
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, f[:, k], fn)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def _random_rotation(rng):
    q = _random_unit(rng, 4)
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def _random_placement(vertices, rng):
    """A rigid 4x4 taking object-frame points to a random pose: a random rotation about
    the piece's centroid, then the centroid moved to a random point of [-2, 2]^3."""
    rot = _random_rotation(rng)
    centroid = vertices.mean(axis=0)
    target = rng.uniform(-SCATTER_RANGE, SCATTER_RANGE, 3)
    m = np.eye(4)
    m[:3, :3] = rot
    m[:3, 3] = target - rot @ centroid
    return m


def _invert_rigid(m):
    inv = np.eye(4)
    inv[:3, :3] = m[:3, :3].T
    inv[:3, 3] = -m[:3, :3].T @ m[:3, 3]
    return inv
