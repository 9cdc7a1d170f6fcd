"""Fracture contours: the boundary loops of each fracture region as closed, ordered
polylines, resampled at an even step (section 3.7.2 to 3.7.3).

A loop runs counter-clockwise seen from outside the fragment (the winding of its
faces), so the mating contour on the neighbour runs the other way.
"""
from __future__ import annotations

import numpy as np


def region_boundary_loops(faces: np.ndarray, face_mask: np.ndarray) -> list[np.ndarray]:
    """Closed vertex loops bounding the faces where face_mask is True.

    Boundary half-edges are the directed edges of masked faces whose twin is not a
    directed edge of a masked face. Where a vertex has several outgoing boundary
    half-edges (a pinch), loops are split there.
    """
    f = np.asarray(faces, np.int64)[face_mask]
    if len(f) == 0:
        return []
    half = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    n = int(half.max()) + 1
    code = half[:, 0] * n + half[:, 1]
    twin = half[:, 1] * n + half[:, 0]
    boundary = half[~np.isin(twin, code)]
    if len(boundary) == 0:
        return []
    nxt: dict[int, list[int]] = {}
    for u, v in boundary.tolist():
        nxt.setdefault(u, []).append(v)
    loops = []
    while nxt:
        start = next(iter(nxt))
        loop = [start]
        cur = start
        while True:
            outs = nxt.get(cur)
            if not outs:
                break
            v = outs.pop()
            if not outs:
                del nxt[cur]
            if v == start:
                break
            loop.append(v)
            cur = v
            if len(loop) > len(boundary):
                break
        if len(loop) >= 3:
            loops.append(np.array(loop, np.int64))
    return loops


def resample_closed(points: np.ndarray, step: float) -> np.ndarray:
    """Points at an even arc-length step along a closed polyline (at least 3 points kept)."""
    p = np.asarray(points, np.float64)
    closed = np.vstack([p, p[:1]])
    seg = np.linalg.norm(np.diff(closed, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    length = s[-1]
    if length <= 0:
        return p[:1].copy()
    n = max(3, int(round(length / step)))
    t = np.arange(n) * (length / n)
    return np.stack([np.interp(t, s, closed[:, d]) for d in range(3)], axis=1)


def loop_length(points: np.ndarray) -> float:
    p = np.asarray(points, np.float64)
    return float(np.linalg.norm(np.diff(np.vstack([p, p[:1]]), axis=0), axis=1).sum())
