"""Segmentation of a fragment into fracture and original surface regions (Alg. 2, section 3.7.2).

The paper grows regions across edges whose face normals differ less than a
threshold, merges tiny regions into their neighbours and calls a region a
fracture surface when its normal perturbation is large. On real scans a rough
fracture surface is itself full of sharp little edges, so growing first would
shatter it; here the order is: (1) the normal perturbation of every face (the
angle between its normal and the mean normal of its neighbourhood) says
fracture or original, smoothed by a majority vote of neighbours; (2) regions are
grown over edges between faces of the same class whose normal angle is below
the crease angle (the normal-angle kernel); (3) tiny regions are merged into the
neighbour they share most edges with, and take its class.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .params import Params


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


@dataclass(frozen=True)
class Segmentation:
    face_region: np.ndarray  # (F,) int region id per face
    region_is_fracture: np.ndarray  # (R,) bool
    face_roughness: np.ndarray  # (F,) degrees, normal perturbation
    edge_angle: np.ndarray  # (E,) degrees, normal angle of each interior edge
    normals: np.ndarray  # (F,3)
    areas: np.ndarray  # (F,)
    topology: Topology

    @property
    def fracture_faces(self) -> np.ndarray:
        return self.region_is_fracture[self.face_region]


def face_roughness(vertices, faces, normals, areas, radius: float, k: int = 24) -> np.ndarray:
    """Normal perturbation per face: the angle (degrees) between its normal and the
    area-weighted mean normal of the k nearest faces within `radius`."""
    centres = vertices[faces].mean(axis=1)
    k = int(min(k, len(faces)))
    dist, idx = cKDTree(centres).query(centres, k=k)
    idx = idx.reshape(len(faces), k)
    w = areas[idx] * (dist.reshape(len(faces), k) <= radius)
    mean = np.einsum("fk,fkd->fd", w, normals[idx])
    length = np.linalg.norm(mean, axis=1)
    mean = mean / np.where(length > 0, length, 1)[:, None]
    cos = np.clip(np.einsum("fd,fd->f", mean, normals), -1, 1)
    return np.degrees(np.arccos(cos))


def segment(vertices: np.ndarray, faces: np.ndarray, params: Params, scale: float, backend) -> Segmentation:
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    topo = mesh_topology(f)
    normals, areas = backend.face_normals(v, f)
    normals = np.asarray(normals, np.float64)
    areas = np.asarray(areas, np.float64)
    angle = np.degrees(np.asarray(backend.edge_angles(normals, topo.edge_faces), np.float64))

    rough = face_roughness(v, f, normals, areas, params.roughness_radius * scale)
    is_fracture = rough > params.roughness_threshold_deg
    is_fracture = _majority_smooth(is_fracture, topo.edge_faces, len(f), rounds=3)

    e0, e1 = topo.edge_faces[:, 0], topo.edge_faces[:, 1]
    joins = (is_fracture[e0] == is_fracture[e1]) & (angle < params.crease_angle_deg)
    region = _components(len(f), topo.edge_faces[joins])
    region = _merge_small(region, topo.edge_faces, params.min_region_faces)
    # A region's class is the area-weighted majority of its faces.
    n_regions = int(region.max()) + 1
    frac_area = np.bincount(region, weights=areas * is_fracture, minlength=n_regions)
    all_area = np.bincount(region, weights=areas, minlength=n_regions)
    region_is_fracture = frac_area > 0.5 * all_area
    return Segmentation(region, region_is_fracture, rough, angle, normals, areas, topo)


def _majority_smooth(labels: np.ndarray, edge_faces: np.ndarray, n: int, rounds: int) -> np.ndarray:
    """Each face takes the majority label of itself and its edge neighbours, a few times."""
    a, b = edge_faces[:, 0], edge_faces[:, 1]
    degree = np.bincount(a, minlength=n) + np.bincount(b, minlength=n) + 1
    for _ in range(rounds):
        x = labels.astype(np.int64)
        votes = x + np.bincount(a, weights=x[b], minlength=n) + np.bincount(b, weights=x[a], minlength=n)
        labels = votes * 2 > degree
    return labels


def _components(n: int, edges: np.ndarray) -> np.ndarray:
    g = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, labels = connected_components(g, directed=False)
    return labels.astype(np.int64)


def _merge_small(region: np.ndarray, edge_faces: np.ndarray, min_faces: int) -> np.ndarray:
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
