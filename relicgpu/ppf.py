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

from dataclasses import dataclass

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


@dataclass(frozen=True, eq=False)
class PairTable:
    """Quantised features of point pairs (ref, other) of one oriented point set, sorted by key
    when it is the model side. Depends on the points and the quantisation only, so a fragment's
    tables can be built once and used against every partner."""
    frames: np.ndarray  # (N,4,4) point to origin, normal onto +x
    key: np.ndarray  # (M,) int64
    ref: np.ndarray  # (M,) the pair's reference point
    alpha: np.ndarray  # (M,) angle of the other point about +x in the reference's frame
    n_points: int
    references: np.ndarray  # the points used as references
    centroid: np.ndarray  # of the points


def pair_table(points: np.ndarray, normals: np.ndarray, dist_step: float, angle_step_deg: float = 12.0,
               reference_stride: int = 1, sort: bool = True) -> PairTable:
    """Every pair (ref, other) with ref among every `reference_stride`-th point."""
    n = len(points)
    angle_step = np.radians(angle_step_deg)
    angle_bins = int(np.ceil(np.pi / angle_step)) + 1
    frames = _frames(points, normals) if n else np.zeros((0, 4, 4))
    refs = np.arange(0, n, max(1, reference_stride))
    r = np.repeat(refs, n)
    o = np.tile(np.arange(n), len(refs))
    ok = r != o
    r, o = r[ok], o[ok]
    key = _keys(_pair_features(points[r], normals[r], points[o], normals[o], dist_step, angle_step), angle_bins)
    alpha = _alphas(frames, r, points[o])
    if sort:
        order = np.argsort(key, kind="stable")
        key, r, alpha = key[order], r[order], alpha[order]
    centroid = points.mean(axis=0) if n else np.zeros(3)
    return PairTable(frames, key, r.astype(np.int32), alpha.astype(np.float32), n, refs, centroid)


def vote_poses(model: PairTable, scene: PairTable, cluster_distance: float, alpha_bins: int = 30, keep: int = 24,
               bucket_cap: int = 32, cluster_angle_deg: float = 12.0) -> list[tuple[np.ndarray, int]]:
    """Poses carrying the scene's points onto the model's, from Drost's votes: the best cell of
    each scene reference gives a pose; up to `keep` of them, most supported first, with their
    support (the votes of all poses within cluster_distance / cluster_angle_deg of them)."""
    na, refs = model.n_points, scene.references
    if na < 3 or scene.n_points < 3 or len(model.key) == 0 or len(scene.key) == 0:
        return []
    lo = np.searchsorted(model.key, scene.key, "left")
    found = np.searchsorted(model.key, scene.key, "right") - lo
    # A feature shared by many pairs (a flat stretch) says little and would flood the votes:
    # each scene pair votes with at most `bucket_cap` of its model pairs, spread over the bucket.
    counts = np.minimum(found, bucket_cap)
    if counts.sum() == 0:
        return []
    pair = np.repeat(np.arange(len(scene.key)), counts)
    rank = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    match = lo[pair] + rank * found[pair] // counts[pair]
    alpha = model.alpha[match].astype(np.float64) - scene.alpha[pair]
    abin = np.floor((alpha + np.pi) / (2 * np.pi) * alpha_bins).astype(np.int64) % alpha_bins
    ref_index = np.searchsorted(refs, scene.ref[pair])
    cell = (ref_index * na + model.ref[match]) * alpha_bins + abin
    votes = np.bincount(cell, minlength=len(refs) * na * alpha_bins).reshape(len(refs), na * alpha_bins)

    best = votes.argmax(axis=1)
    best_votes = votes[np.arange(len(refs)), best]
    m_ref, m_alpha = best // alpha_bins, best % alpha_bins
    angle = (m_alpha + 0.5) / alpha_bins * 2 * np.pi - np.pi
    c, sn = np.cos(angle), np.sin(angle)
    Rx = np.tile(np.eye(4), (len(refs), 1, 1))
    Rx[:, 1, 1], Rx[:, 1, 2], Rx[:, 2, 1], Rx[:, 2, 2] = c, -sn, sn, c
    poses = np.linalg.inv(model.frames[m_ref]) @ Rx @ scene.frames[refs]
    # Every reference point inside the contact votes for the same pose, noise peaks scatter:
    # score each pose by the votes of all poses like it (Drost's pose clustering), then keep
    # the best-scored, skipping those like one already kept.
    like = _similar(poses, scene.centroid, cluster_distance, cluster_angle_deg)
    support = like.astype(np.float64) @ best_votes
    out: list[tuple[np.ndarray, int]] = []
    taken = np.zeros(len(refs), bool)
    for k in np.argsort(-support, kind="stable"):
        if len(out) >= keep or support[k] < 3:
            break
        if taken[k]:
            continue
        taken |= like[k]
        out.append((poses[k], int(support[k])))
    return out


def _similar(poses: np.ndarray, centre: np.ndarray, distance: float, angle_deg: float) -> np.ndarray:
    """(N,N) bool: poses that turn by less than angle_deg relative to each other and put `centre`
    within `distance` of each other."""
    r = poses[:, :3, :3]
    cos = (np.einsum("aij,bij->ab", r, r) - 1.0) / 2.0
    c = np.einsum("nij,j->ni", r, centre) + poses[:, :3, 3]
    gap = np.linalg.norm(c[:, None] - c[None], axis=2)
    return (cos > np.cos(np.radians(angle_deg))) & (gap < distance)


def ppf_poses(a_points: np.ndarray, a_normals: np.ndarray, b_points: np.ndarray, b_normals: np.ndarray,
              dist_step: float, angle_step_deg: float = 12.0, alpha_bins: int = 30, reference_stride: int = 3,
              keep: int = 24, bucket_cap: int = 32) -> list[tuple[np.ndarray, int]]:
    """Poses carrying b onto a where b's surface (normals as given, i.e. already flipped for a
    mating surface) lies on a's; up to `keep`, most votes first, with their vote counts."""
    if len(a_points) < 3 or len(b_points) < 3:
        return []
    model = pair_table(a_points, a_normals, dist_step, angle_step_deg)
    scene = pair_table(b_points, b_normals, dist_step, angle_step_deg, reference_stride, sort=False)
    return vote_poses(model, scene, 2 * dist_step, alpha_bins, keep, bucket_cap)
