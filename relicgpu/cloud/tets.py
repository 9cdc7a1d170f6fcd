"""The tetrahedra of a Delaunay tetrahedralisation and the surface carved out of them (steps 3-6
of `relicgpu.cloud.triangulate`): the alpha flood, the largest inside body, the boundary wound
outwards, and its repair where the surface touches itself."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..io.fragment import FragmentError

def _tet_geometry(q: np.ndarray, simplices: np.ndarray, chunk: int = 500_000):
    """Per tetrahedron: circumradius of the face opposite each vertex (T,4), six times the
    signed volume, and the longest edge."""
    n = len(simplices)
    face_radius = np.empty((n, 4))
    volume6 = np.empty(n)
    longest = np.empty(n)
    for s in range(0, n, chunk):
        p = q[simplices[s:s + chunk]]  # (t,4,3)
        edges = {(i, j): p[:, j] - p[:, i] for i in range(4) for j in range(i + 1, 4)}
        sq = {key: np.einsum("ij,ij->i", e, e) for key, e in edges.items()}
        longest[s:s + chunk] = np.sqrt(np.max(np.stack(list(sq.values())), axis=0))
        volume6[s:s + chunk] = np.einsum("ij,ij->i", np.cross(edges[0, 1], edges[0, 2]), edges[0, 3])
        for k in range(4):
            i, j, m = (v for v in range(4) if v != k)
            cross = np.cross(edges[i, j], edges[i, m])
            area2 = np.sqrt(np.einsum("ij,ij->i", cross, cross))  # twice the area
            with np.errstate(divide="ignore", invalid="ignore"):
                r = np.sqrt(sq[i, j] * sq[i, m] * sq[j, m]) / (2.0 * area2)
            face_radius[s:s + chunk, k] = np.where(area2 > 0, r, np.inf)
    return face_radius, volume6, longest


# Faces of a positively oriented tetrahedron (v0..v3), wound outwards; row k is opposite vertex k.
_OUT_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])


class _Tets:
    """The Delaunay tetrahedralisation with the arrays the carving needs."""

    def __init__(self, q: np.ndarray):
        from scipy.spatial import Delaunay
        from scipy.spatial import QhullError

        # A jitter of 1e-9 (q spans [-1, 1]) breaks exact coplanarity, as of points
        # sampled from flat faces, which makes Qhull merge facets for minutes.
        q = q + np.random.default_rng(0).uniform(-1e-9, 1e-9, q.shape)
        try:
            tri = Delaunay(q, qhull_options="Qbb Qz Q12")
        except QhullError as exc:
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
            raise FragmentError(f"the points span no volume (flat or collinear?): Qhull says {first}") from None
        self.q = q
        self.simplices = tri.simplices.astype(np.int64)
        self.neighbors = tri.neighbors.astype(np.int64)
        self.n_points = len(q)
        self.face_radius, self.volume6, self.longest = _tet_geometry(q, self.simplices)

    def edge_keys(self, which: np.ndarray) -> np.ndarray:
        """(len(which),6) keys (lo * n + hi) of the edges of the given tetrahedra, in the order of _TET_EDGES."""
        s = self.simplices[which]
        lo = np.stack([np.minimum(s[:, i], s[:, j]) for i, j in _TET_EDGES], 1)
        hi = np.stack([np.maximum(s[:, i], s[:, j]) for i, j in _TET_EDGES], 1)
        return lo * self.n_points + hi


def _outside_by_flood(tets: _Tets, alpha: float) -> np.ndarray:
    """Tetrahedra reached from infinity through faces of circumradius above alpha."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(tets.simplices)
    passable = tets.face_radius > alpha
    t, k = np.nonzero(passable)
    other = tets.neighbors[t, k]
    other = np.where(other < 0, n, other)  # node n is the outside of the convex hull
    graph = coo_matrix((np.ones(len(t), np.int8), (t, other)), shape=(n + 1, n + 1))
    _, labels = connected_components(graph, directed=False)
    return labels[:n] == labels[n]


def _largest_body(tets: _Tets, inside: np.ndarray) -> tuple[np.ndarray, int, float]:
    """Keep the largest face-connected set of inside tetrahedra (by volume).

    Returns the kept set, the number of bodies and the kept share of the inside volume.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(inside)
    idx = np.nonzero(inside)[0]
    if len(idx) == 0:
        return inside, 0, 0.0
    nb = tets.neighbors
    t, k = np.nonzero(inside[:, None] & (nb >= 0))
    other = nb[t, k]
    keep = inside[other]
    graph = coo_matrix((np.ones(int(keep.sum()), np.int8), (t[keep], other[keep])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    body, body_of = np.unique(labels[idx], return_inverse=True)
    vol = np.bincount(body_of, np.abs(tets.volume6[idx]))
    best = int(np.argmax(vol))
    out = np.zeros(n, bool)
    out[idx[body_of == best]] = True
    total = float(vol.sum())
    return out, len(body), float(vol[best] / total) if total > 0 else 1.0


def _boundary(tets: _Tets, inside: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Boundary triangles of the inside tetrahedra, wound outwards, and the tetrahedron of each."""
    nb = tets.neighbors
    nb_inside = np.where(nb >= 0, inside[np.maximum(nb, 0)], False)
    t, k = np.nonzero(inside[:, None] & ~nb_inside)
    order = _OUT_FACES[k]
    negative = tets.volume6[t] < 0
    order[negative] = order[negative][:, [0, 2, 1]]
    faces = np.take_along_axis(tets.simplices[t], order, axis=1)
    return faces, t


# Edges of a tetrahedron (local vertex pairs, the order of _Tets.edge_keys) and the two other vertices.
_TET_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
_TET_EDGE_OTHERS = np.array([[2, 3], [1, 3], [1, 2], [0, 3], [0, 2], [0, 1]])


@dataclass
class _Surface:
    """The boundary of the inside tetrahedra, made a combinatorial 2-manifold by splitting pinches."""
    faces: np.ndarray  # (F,3) indices into `source`
    source: np.ndarray  # (V,) point index of each (possibly duplicated) vertex
    bad_edges: np.ndarray  # keys of edges shared by more than two faces before splitting
    bad_vertices: np.ndarray  # points whose faces formed more than one fan
    component: np.ndarray  # (F,) edge-connected component of each face
    inconsistent: int  # paired edges run the same way in both faces (wrong winding)
    closed: bool  # every edge of `faces` has exactly two faces


def _pair_incidences(tets: _Tets, inside: np.ndarray, faces: np.ndarray, face_tet: np.ndarray):
    """Pair the two faces meeting at each edge; at an edge with more faces, pair the two faces
    that bound the same run of inside tetrahedra around it."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    nf, n = len(faces), tets.n_points
    a = faces.T.ravel()  # incidence i = slot * nf + face: the edge from corner slot to slot+1
    b = np.roll(faces, -1, axis=1).T.ravel()
    keys = np.minimum(a, b) * n + np.maximum(a, b)
    uniq, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    group = inverse.astype(np.int64)
    bad = counts[inverse] > 2
    bad_keys = uniq[counts > 2]
    if bad.any():
        n_tets = len(tets.simplices)
        ends = np.zeros(n, bool)
        ends[bad_keys // n] = True
        ends[bad_keys % n] = True
        maybe = np.nonzero(inside & (ends[tets.simplices].sum(axis=1) >= 2))[0]
        maybe_keys = tets.edge_keys(maybe)
        tt, ss = np.nonzero(np.isin(maybe_keys, bad_keys))
        e_idx = np.searchsorted(bad_keys, maybe_keys[tt, ss])
        tt = maybe[tt]
        node_keys = np.unique(e_idx * n_tets + tt)
        rows, cols = [], []
        for c in (0, 1):
            other = tets.neighbors[tt, _TET_EDGE_OTHERS[ss, c]]
            ok = other >= 0
            ok[ok] = inside[other[ok]]
            rows.append(np.searchsorted(node_keys, e_idx[ok] * n_tets + tt[ok]))
            cols.append(np.searchsorted(node_keys, e_idx[ok] * n_tets + other[ok]))
        rows, cols = np.concatenate(rows), np.concatenate(cols)
        graph = coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(len(node_keys),) * 2)
        _, run = connected_components(graph, directed=False)
        inc = np.nonzero(bad)[0]
        e_of = np.searchsorted(bad_keys, keys[inc])
        node = np.searchsorted(node_keys, e_of * n_tets + face_tet[inc % nf])
        group[inc] = len(uniq) + run[node]
    order = np.argsort(group, kind="stable")
    first, second = order[0::2], order[1::2]
    if len(order) % 2 or not np.array_equal(group[first], group[second]):
        raise RuntimeError("internal error: boundary edges do not pair up")
    return first, second, bad_keys


def _links(faces: np.ndarray, first: np.ndarray, second: np.ndarray):
    """The wedges (3*face+corner) that each pair of faces joins at either end of its edge."""
    nf = len(faces)
    f1, s1 = first % nf, first // nf
    f2, s2 = second % nf, second // nf
    # The edge runs from corner s to s+1; in the other face the same vertex sits at s2 or s2+1.
    s1b, s2b = (s1 + 1) % 3, (s2 + 1) % 3
    same = faces[f1, s1] == faces[f2, s2]
    w1a, w1b = 3 * f1 + s1, 3 * f1 + s1b
    w2a = 3 * f2 + np.where(same, s2, s2b)
    w2b = 3 * f2 + np.where(same, s2b, s2)
    return w1a, w2a, w1b, w2b


def _components(rows: np.ndarray, cols: np.ndarray, n: int):
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    graph = coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(n, n))
    return connected_components(graph, directed=False)


def _fans(faces: np.ndarray, first: np.ndarray, second: np.ndarray):
    """Label each wedge (face, corner) by the fan of faces it belongs to around its vertex:
    wedges at a vertex are joined across every paired edge. Returns (labels, count)."""
    w1a, w2a, w1b, w2b = _links(faces, first, second)
    n_fans, fan = _components(np.concatenate([w1a, w1b]), np.concatenate([w2a, w2b]), 3 * len(faces))
    return fan.astype(np.int64), n_fans


def _repair_double_edges(faces: np.ndarray, first: np.ndarray, second: np.ndarray, max_rounds: int = 6):
    """Re-pair the faces of edges still shared by four (or more) faces after splitting pinched vertices.

    This happens where the faces around an end of the edge form one fan that passes
    the edge more than once. Cutting that fan at the edge gives arcs; each arc takes
    its own copy of the end and the two faces of the edge that bound it. A round
    handles one edge per vertex, so that the arcs pair up.
    """
    nf = len(faces)
    for _ in range(max_rounds):
        fan, n_fans = _fans(faces, first, second)
        new = fan.reshape(nf, 3)
        f1, s1 = first % nf, first // nf
        va, vb = new[f1, s1], new[f1, (s1 + 1) % 3]
        lo, hi = np.minimum(va, vb), np.maximum(va, vb)
        key = lo * n_fans + hi
        _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
        bad = counts[inverse] > 1
        if not bad.any():
            return first, second, fan, n_fans, True
        # One edge per vertex and round: those that come first (by key) at both of their ends.
        idx = np.nonzero(bad)[0]
        ends = np.concatenate([lo[idx], hi[idx]])
        keys2 = np.tile(key[idx], 2)
        order = np.lexsort((keys2, ends))
        head = np.r_[True, ends[order][1:] != ends[order][:-1]]
        first_at_end = np.full(n_fans, -1, np.int64)
        first_at_end[ends[order][head]] = keys2[order][head]
        chosen = bad & (first_at_end[lo] == key) & (first_at_end[hi] == key)
        # The fans of the cut ends (the lower end of each chosen edge), without the joins
        # across the chosen edges, on the small graph of those wedges only.
        is_cut = np.zeros(n_fans, bool)
        is_cut[lo[chosen]] = True
        w1a, w2a, w1b, w2b = _links(faces, first, second)
        at_a = is_cut[va] & ~chosen
        at_b = is_cut[vb] & ~chosen
        wedge_vertex = fan  # the new vertex of every wedge
        nodes = np.nonzero(is_cut[wedge_vertex])[0]
        rows = np.searchsorted(nodes, np.concatenate([w1a[at_a], w1b[at_b]]))
        cols = np.searchsorted(nodes, np.concatenate([w2a[at_a], w2b[at_b]]))
        _, arc_of_node = _components(rows, cols, len(nodes))
        inc = np.concatenate([first[chosen], second[chosen]])
        end = np.tile(lo[chosen], 2)
        f_inc = inc % nf
        corner = np.argmax(new[f_inc] == end[:, None], axis=1)
        arc = arc_of_node[np.searchsorted(nodes, 3 * f_inc + corner)]
        _, edge_no = np.unique(key[chosen], return_inverse=True)
        group = np.tile(edge_no, 2) * (3 * nf) + arc
        order = np.argsort(group, kind="stable")
        g = group[order]
        if len(g) % 2 or not np.array_equal(g[0::2], g[1::2]):
            break
        first = np.concatenate([first[~chosen], inc[order[0::2]]])
        second = np.concatenate([second[~chosen], inc[order[1::2]]])
    fan, n_fans = _fans(faces, first, second)
    return first, second, fan, n_fans, False


def _surface(tets: _Tets, inside: np.ndarray) -> _Surface:
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    faces, face_tet = _boundary(tets, inside)
    nf = len(faces)
    if nf == 0:
        empty = np.zeros(0, np.int64)
        return _Surface(np.zeros((0, 3), np.int64), empty, empty, empty, empty, 0, True)
    first, second, bad_keys = _pair_incidences(tets, inside, faces, face_tet)
    first, second, fan, n_fans, closed = _repair_double_edges(faces, first, second)
    source = np.empty(n_fans, np.int64)
    source[fan] = faces.ravel()
    copies = np.bincount(source, minlength=tets.n_points)
    f1, s1, f2, s2 = first % nf, first // nf, second % nf, second // nf
    face_graph = coo_matrix((np.ones(len(f1), np.int8), (f1, f2)), shape=(nf, nf))
    _, component = connected_components(face_graph, directed=False)
    inconsistent = int(np.count_nonzero(faces[f1, s1] == faces[f2, s2]))
    return _Surface(fan.reshape(nf, 3), source, bad_keys, np.nonzero(copies > 1)[0], component,
                    inconsistent, closed)
