"""Point-pair-feature voting for coarse poses between partial contacts (Drost et al. 2010).

Two fragments that touch over only part of their fracture surfaces share no whole
contour and no patch centre, and small local descriptors of a rough surface do not
repeat well between two scans of it. Pairs of oriented points do: for points
m1, m2 with normals n1, n2 the feature

    F = (|d|, angle(n1, d), angle(n2, d), angle(n1, n2)),   d = m2 - m1

is the same on the mating surface seen from the other side (its normals flipped)
wherever both points lie in the contact. Every pair of fragment a is hashed by its
quantised F; each reference point of b, paired with the other points of b, looks
its features up and votes for (point of a it sits on, turn about the normal). The
contact region's pairs all vote for the same cell, the rest scatter, so the peaks
give poses even when the contact is a fifth of each surface.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def smoothed_normals(points: np.ndarray, normals: np.ndarray, radius: float, k: int = 32) -> np.ndarray:
    """Normals of the local plane fit (PCA of up to k neighbours within `radius`), oriented like
    the given normals.

    Vertex normals of a rough surface depend on how it was triangulated; the plane
    of a neighbourhood a few sample spacings wide does not."""
    n = len(points)
    if n < 3:
        return normals.astype(np.float64).copy()
    dist, idx = cKDTree(points).query(points, k=min(k, n), distance_upper_bound=radius)
    w = np.isfinite(dist).astype(np.float64)
    idx = np.where(w > 0, idx, 0)
    q = points[idx]
    count = w.sum(1)
    mean = np.einsum("nk,nkd->nd", w, q) / count[:, None]
    d = (q - mean[:, None]) * w[..., None]
    _, vecs = np.linalg.eigh(np.einsum("nki,nkj->nij", d, d))
    m = vecs[:, :, 0]
    m *= np.where(np.einsum("nd,nd->n", m, normals) >= 0, 1.0, -1.0)[:, None]
    return np.where((count >= 6)[:, None], m, normals)


def _frames(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(N,4,4) rigid transforms moving each point to the origin and its normal onto +x."""
    n = len(points)
    x = np.array([1.0, 0.0, 0.0])
    nrm = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    axis = np.cross(nrm, x)
    s = np.linalg.norm(axis, axis=1)
    c = nrm @ x
    # Rodrigues; for normals along -x turn about z by pi
    k = np.where(s[:, None] > 1e-9, axis / np.maximum(s, 1e-12)[:, None], np.array([0.0, 0.0, 1.0]))
    angle = np.arctan2(s, c)
    K = np.zeros((n, 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    R = np.eye(3) + np.sin(angle)[:, None, None] * K + (1 - np.cos(angle))[:, None, None] * (K @ K)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = -np.einsum("nij,nj->ni", R, points)
    return T


def _pair_features(p1, n1, p2, n2, dist_step, angle_step):
    d = p2 - p1
    length = np.linalg.norm(d, axis=-1)
    u = d / np.maximum(length, 1e-12)[..., None]

    def ang(a, b):
        return np.arccos(np.clip(np.einsum("...i,...i->...", a, b), -1.0, 1.0))

    q = np.stack([length / dist_step, ang(n1, u) / angle_step, ang(n2, u) / angle_step, ang(n1, n2) / angle_step],
                 axis=-1)
    return np.floor(q).astype(np.int64)


def _alphas(frames: np.ndarray, ref: np.ndarray, other_points: np.ndarray) -> np.ndarray:
    """Angle about +x of each other point in the frame of its reference point."""
    p = np.einsum("nij,nj->ni", frames[ref][:, :3, :3], other_points) + frames[ref][:, :3, 3]
    return np.arctan2(p[:, 2], p[:, 1])


def _keys(q: np.ndarray, angle_bins: int) -> np.ndarray:
    return ((q[:, 0] * angle_bins + q[:, 1]) * angle_bins + q[:, 2]) * angle_bins + q[:, 3]


def ppf_poses(a_points: np.ndarray, a_normals: np.ndarray, b_points: np.ndarray, b_normals: np.ndarray,
              dist_step: float, angle_step_deg: float = 12.0, alpha_bins: int = 30, reference_stride: int = 3,
              max_distance: float | None = None, keep: int = 24,
              bucket_cap: int = 32) -> list[tuple[np.ndarray, int]]:
    """Poses carrying b onto a where b's surface (normals as given, i.e. already flipped for a
    mating surface) lies on a's; up to `keep`, most votes first, with their vote counts."""
    na, nb = len(a_points), len(b_points)
    if na < 3 or nb < 3:
        return []
    angle_step = np.radians(angle_step_deg)
    angle_bins = int(np.ceil(np.pi / angle_step)) + 1
    fa, fb = _frames(a_points, a_normals), _frames(b_points, b_normals)

    # model table: every ordered pair of a (within max_distance), sorted by key
    i, j = np.nonzero(~np.eye(na, dtype=bool))
    if max_distance is not None:
        near = np.linalg.norm(a_points[j] - a_points[i], axis=1) <= max_distance
        i, j = i[near], j[near]
    key_a = _keys(_pair_features(a_points[i], a_normals[i], a_points[j], a_normals[j], dist_step, angle_step),
                  angle_bins)
    alpha_a = _alphas(fa, i, a_points[j])
    order = np.argsort(key_a, kind="stable")
    key_a, ref_a, alpha_a = key_a[order], i[order], alpha_a[order]

    refs = np.arange(0, nb, max(1, reference_stride))
    r = np.repeat(refs, nb)
    s = np.tile(np.arange(nb), len(refs))
    ok = r != s
    if max_distance is not None:
        ok &= np.linalg.norm(b_points[s] - b_points[r], axis=1) <= max_distance
    r, s = r[ok], s[ok]
    key_b = _keys(_pair_features(b_points[r], b_normals[r], b_points[s], b_normals[s], dist_step, angle_step),
                  angle_bins)
    alpha_b = _alphas(fb, r, b_points[s])
    lo = np.searchsorted(key_a, key_b, "left")
    hi = np.searchsorted(key_a, key_b, "right")
    found = hi - lo
    # A feature shared by many pairs (a flat stretch) says little and would flood the votes:
    # each scene pair votes with at most `bucket_cap` of its model pairs, spread over the bucket.
    counts = np.minimum(found, bucket_cap)
    if counts.sum() == 0:
        return []
    scene = np.repeat(np.arange(len(key_b)), counts)
    rank = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    model = lo[scene] + rank * found[scene] // counts[scene]
    alpha = alpha_a[model] - alpha_b[scene]
    abin = np.floor((alpha + np.pi) / (2 * np.pi) * alpha_bins).astype(np.int64) % alpha_bins
    ref_index = np.searchsorted(refs, r[scene])
    cell = (ref_index * na + ref_a[model]) * alpha_bins + abin
    votes = np.bincount(cell, minlength=len(refs) * na * alpha_bins).reshape(len(refs), na * alpha_bins)

    # the best cell per reference point of b gives one pose
    best = votes.argmax(axis=1)
    best_votes = votes[np.arange(len(refs)), best]
    m_ref, m_alpha = best // alpha_bins, best % alpha_bins
    angle = (m_alpha + 0.5) / alpha_bins * 2 * np.pi - np.pi
    c, sn = np.cos(angle), np.sin(angle)
    Rx = np.tile(np.eye(4), (len(refs), 1, 1))
    Rx[:, 1, 1], Rx[:, 1, 2], Rx[:, 2, 1], Rx[:, 2, 2] = c, -sn, sn, c
    poses = np.linalg.inv(fa[m_ref]) @ Rx @ fb[refs]
    order = np.argsort(-best_votes, kind="stable")
    out: list[tuple[np.ndarray, int]] = []
    for k in order:
        if best_votes[k] < 3 or len(out) >= keep:
            break
        out.append((poses[k], int(best_votes[k])))
    return out
