"""Triangle-mesh neighbourhoods and the small statistics the segmentation and its cues share:
interior edges and their faces, ring averages over the surface, connected regions, weighted
quantiles and Otsu's split."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix, csr_matrix, identity
from scipy.sparse.csgraph import connected_components


@dataclass(frozen=True)
class Topology:
    """Edges of a triangle mesh shared by exactly two faces, and its open boundary."""
    edge_faces: np.ndarray  # (E,2) int32, the two faces of each interior edge
    edge_vertices: np.ndarray  # (E,2) int64, the vertices of that edge
    boundary_edges: np.ndarray  # (B,2) int64, edges with one face


def mesh_topology(faces: np.ndarray) -> Topology:
    f = np.asarray(faces, np.int64)
    nf = len(f)
    half = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    face_of = np.tile(np.arange(nf), 3)
    key = np.sort(half, axis=1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    key, face_of = key[order], face_of[order]
    same_as_next = np.all(key[1:] == key[:-1], axis=1)
    starts = np.flatnonzero(np.concatenate([[True], ~same_as_next]))
    counts = np.diff(np.concatenate([starts, [len(key)]]))
    two = starts[counts == 2]
    edge_faces = np.stack([face_of[two], face_of[two + 1]], axis=1).astype(np.int32)
    boundary = key[starts[counts == 1]]
    return Topology(edge_faces, key[two], boundary)


def vertex_adjacency(faces: np.ndarray, n: int) -> csr_matrix:
    """(n, n) 1 where two of n vertices share an edge of the (F, 3) faces (once, however many
    faces share it), else 0."""
    f = np.asarray(faces, np.int64)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    a = coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(n, n)).tocsr()
    a.data[:] = 1.0
    return a


def ring_average(values: np.ndarray, weights: np.ndarray, edge_faces: np.ndarray, rings: int) -> np.ndarray:
    """Weighted mean of per-face values over the faces within `rings` edge-steps.

    The neighbourhood follows the surface, not space: across a thin wall the faces
    of the other side are near in space but belong to another surface.
    """
    n = len(weights)
    a, b = edge_faces[:, 0], edge_faces[:, 1]
    reach = coo_matrix((np.ones(2 * len(a)), (np.concatenate([a, b]), np.concatenate([b, a]))), shape=(n, n)).tocsr()
    reach = reach + identity(n, format="csr")
    num = values * (weights[:, None] if values.ndim == 2 else weights)
    den = weights.copy()
    for _ in range(rings):
        num, den = reach @ num, reach @ den
    den = np.where(den > 0, den, 1)
    return num / (den[:, None] if values.ndim == 2 else den)


def weighted_quantile(x: np.ndarray, w: np.ndarray, q):
    """The w-weighted q-quantile(s) of x (N,), N >= 1 (q a number or an array of them)."""
    order = np.argsort(x)
    cum = np.cumsum(w[order])
    return x[order][np.searchsorted(cum, np.asarray(q) * cum[-1])]


def otsu_split(x: np.ndarray, w: np.ndarray) -> float:
    """Otsu's threshold of values x (N,) with weights w (N,): the x that splits them into the
    two classes (<= and >) of most between-class variance."""
    if len(x) < 2:
        return float(x[0]) if len(x) else 0.0
    order = np.argsort(x)
    x, w = x[order], w[order]
    w0 = np.cumsum(w)[:-1]
    s0 = np.cumsum(w * x)[:-1]
    w1 = w.sum() - w0
    between = w0 * w1 * (s0 / np.maximum(w0, 1e-300) - ((w * x).sum() - s0) / np.maximum(w1, 1e-300)) ** 2
    return float(x[np.argmax(between)])


def components(n: int, edges: np.ndarray) -> np.ndarray:
    g = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, labels = connected_components(g, directed=False)
    return labels.astype(np.int64)


def merge_small(region: np.ndarray, edge_faces: np.ndarray, min_faces: int) -> np.ndarray:
    """Merge regions with fewer than min_faces faces into the neighbour sharing most edges."""
    region = region.copy()
    for _ in range(20):
        sizes = np.bincount(region)
        small = sizes < min_faces
        if not small[region].any() or small.all():
            break
        ra, rb = region[edge_faces[:, 0]], region[edge_faces[:, 1]]
        cross = ra != rb
        ra, rb = ra[cross], rb[cross]
        # candidate moves: small region -> neighbour, weighted by shared edges; prefer big neighbours
        src = np.concatenate([ra, rb])
        dst = np.concatenate([rb, ra])
        keep = small[src]
        src, dst = src[keep], dst[keep]
        if len(src) == 0:
            break
        pair_key = src * (region.max() + 1) + dst
        uniq, counts = np.unique(pair_key, return_counts=True)
        s, d = uniq // (region.max() + 1), uniq % (region.max() + 1)
        score = counts + 1e-6 * sizes[d]
        order = np.lexsort((-score, s))
        first = np.concatenate([[True], s[order][1:] != s[order][:-1]])
        target = np.arange(len(sizes))
        target[s[order][first]] = d[order][first]
        # avoid swapping two small regions into each other in the same round
        mutual = target[target] == np.arange(len(sizes))
        mutual &= target != np.arange(len(sizes))
        target[mutual & (np.arange(len(sizes)) < target)] = np.arange(len(sizes))[mutual & (np.arange(len(sizes)) < target)]
        region = target[region]
    _, region = np.unique(region, return_inverse=True)
    return region.astype(np.int64)
