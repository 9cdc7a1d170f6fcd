"""Spin-image descriptors of fracture surface points, for coarse poses between partial contacts.

Where two fragments touch over only part of their fracture surfaces, neither the
patches' centres nor whole contours line up; local descriptors of the rough surface
still do. For a point p with normal n, the neighbours q within a radius are binned by
their distance from the normal line, |(q-p) - ((q-p).n) n|, and their height along it,
(q-p).n: a small 2-D histogram (Johnson's spin image). A mating surface is the same
surface seen from the other side, so its descriptors are taken with flipped normals.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def spin_images(points: np.ndarray, normals: np.ndarray, radius: float, bins: tuple[int, int] = (5, 6),
                k: int = 48, flip: bool = False) -> np.ndarray:
    """(N, bins[0]*bins[1]) normalised spin images at every point."""
    n = len(points)
    if n == 0:
        return np.zeros((0, bins[0] * bins[1]))
    k = min(k, n)
    dist, idx = cKDTree(points).query(points, k=k, distance_upper_bound=radius)
    valid = np.isfinite(dist)
    idx = np.where(valid, idx, 0)
    d = points[idx] - points[:, None]
    nrm = -normals if flip else normals
    beta = np.einsum("nkd,nd->nk", d, nrm)
    alpha = np.sqrt(np.maximum((d * d).sum(-1) - beta ** 2, 0))
    ia = np.clip((alpha / radius * bins[0]).astype(int), 0, bins[0] - 1)
    ib = np.clip(((beta / radius + 0.5) * bins[1]).astype(int), 0, bins[1] - 1)
    inside = valid & (np.abs(beta) < 0.5 * radius)
    cell = (ia * bins[1] + ib)
    out = np.zeros((n, bins[0] * bins[1]))
    rows = np.repeat(np.arange(n), k).reshape(n, k)
    np.add.at(out, (rows[inside], cell[inside]), 1.0)
    total = out.sum(1, keepdims=True)
    return out / np.where(total > 0, total, 1)


def descriptor_correspondences(desc_a: np.ndarray, desc_b: np.ndarray, ratio: float = 0.8) -> np.ndarray:
    """(K,2) pairs (i of a, j of b): each b descriptor's nearest in a, kept when clearly nearer
    than the second nearest (Lowe's ratio test)."""
    if len(desc_a) < 2 or len(desc_b) == 0:
        return np.zeros((0, 2), np.int64)
    dist, idx = cKDTree(desc_a).query(desc_b, k=2)
    keep = dist[:, 0] < ratio * dist[:, 1]
    return np.stack([idx[keep, 0], np.flatnonzero(keep)], axis=1).astype(np.int64)
