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

from ..backends import numpy as numpy_backend


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


def _pair_keys(points, normals, refs, dist_step, angle_step, angle_bins):
    """(R,n) keys of the quantised features of every pair (refs[r], other point)."""
    d = points[None, :, :] - points[refs][:, None, :]
    length = np.linalg.norm(d, axis=2)
    u = d / np.maximum(length, 1e-12)[..., None]

    def ang(cos):
        return np.floor(np.arccos(np.clip(cos, -1.0, 1.0)) / angle_step).astype(np.int64)

    q0 = np.floor(length / dist_step).astype(np.int64)
    q1 = ang(np.einsum("rnd,rd->rn", u, normals[refs]))
    q2 = ang(np.einsum("rnd,nd->rn", u, normals))
    q3 = ang(normals[refs] @ normals.T)
    return ((q0 * angle_bins + q1) * angle_bins + q2) * angle_bins + q3


@dataclass(frozen=True, eq=False)
class PairTable:
    """Quantised features of point pairs (ref, other) of one oriented point set, sorted by key
    (with `start`, the first pair of every key) when it is the model side. Depends on the points
    and the quantisation only, so a fragment's tables can be built once and used against every
    partner."""
    frames: np.ndarray  # (N,4,4) point to origin, normal onto +x
    key: np.ndarray  # (M,) int64
    ref: np.ndarray  # (M,) int32: the pair's reference, as an index into `references`
    alpha: np.ndarray  # (M,) float32: angle of the other point about +x in the reference's frame
    n_points: int
    references: np.ndarray  # the points used as references
    centroid: np.ndarray  # of the points
    start: np.ndarray | None = None  # (K+2,) model side: pairs start[k]:start[k+1] have key k
    weight: np.ndarray | None = None  # (M,) float32: w[ref] * w[other] of per-point weights; None: all 1


def pair_table(points: np.ndarray, normals: np.ndarray, dist_step: float, angle_step_deg: float = 12.0,
               reference_stride: int = 1, sort: bool = True, max_distance: float | None = None,
               weights: np.ndarray | None = None) -> PairTable:
    """Every pair (ref, other) with ref among every `reference_stride`-th point (and, with
    max_distance, the other point in a distance bin that starts within max_distance).

    points, normals : (N,3); weights : (N,) optional per-point weights (fracture likelihoods): a
    pair weighs the product of its two points' (`PairTable.weight`)."""
    n = len(points)
    angle_step = np.radians(angle_step_deg)
    angle_bins = int(np.ceil(np.pi / angle_step)) + 1
    frames = _frames(points, normals) if n else np.zeros((0, 4, 4))
    refs = np.arange(0, n, max(1, reference_stride))
    # every (reference, other) pair at once, a row per reference; a point is not its own partner
    key = _pair_keys(points, normals, refs, dist_step, angle_step, angle_bins)
    # angle about +x of each other point in the frame of its reference
    yz = np.matmul(frames[refs, 1:3, :3], points.T) + frames[refs, 1:3, 3][:, :, None]
    alpha = np.arctan2(yz[:, 1], yz[:, 0]).astype(np.float32)
    other = np.ones((len(refs), n), bool)
    other[np.arange(len(refs)), refs] = False
    if max_distance is not None:
        # a small contact's pairs are short; long pairs only add chance agreements elsewhere
        other &= key // angle_bins ** 3 <= max_distance / dist_step
    ref, partner = (i.astype(np.int32) for i in np.nonzero(other))
    key, alpha = key[other], alpha[other]
    weight = None if weights is None else (weights[refs][ref] * weights[partner]).astype(np.float32)
    start = None
    if sort:
        order = np.argsort(key, kind="stable")
        key, ref, alpha = key[order], ref[order], alpha[order]
        weight = None if weight is None else weight[order]
        start = np.searchsorted(key, np.arange((int(key[-1]) if len(key) else -1) + 3))
    centroid = points.mean(axis=0) if n else np.zeros(3)
    return PairTable(frames, key, ref, alpha, n, refs, centroid, start, weight)


def vote_poses(model: PairTable, scene: PairTable, cluster_distance: float, alpha_bins: int = 30, keep: int = 24,
               bucket_cap: int = 32, cluster_angle_deg: float = 12.0, backend=None) -> list[tuple[np.ndarray, float]]:
    """Poses carrying the scene's points onto the model's, from Drost's votes: the best cell of
    each scene reference gives a pose; up to `keep` of them, most supported first, with their
    support (the votes of all poses within cluster_distance / cluster_angle_deg of them).
    The model table must be sorted (its `start`); it has every point as a reference. Where the
    tables carry pair weights a vote weighs the model pair's times the scene pair's. The votes
    run on `backend` (`Backend.ppf_votes`; None: the NumPy reference); the clustering on the host.

    A feature shared by many pairs (a flat stretch) says little and would flood the votes: each
    scene pair votes with at most `bucket_cap` of its model pairs, spread over the bucket."""
    na, refs = model.n_points, scene.references
    if na < 3 or scene.n_points < 3 or len(model.key) == 0 or len(scene.key) == 0:
        return []
    be = numpy_backend if backend is None else backend
    best, best_votes = be.ppf_votes(model.start, model.ref, model.alpha, model.weight, scene.key, scene.ref,
                                    scene.alpha, scene.weight, len(refs), na, alpha_bins, bucket_cap)
    if not np.any(best_votes > 0):
        return []
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
    out: list[tuple[np.ndarray, float]] = []
    taken = np.zeros(len(refs), bool)
    for k in np.argsort(-support, kind="stable"):
        if len(out) >= keep or support[k] < 3:
            break
        if taken[k]:
            continue
        taken |= like[k]
        out.append((poses[k], float(support[k])))
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
              keep: int = 24, bucket_cap: int = 32, backend=None) -> list[tuple[np.ndarray, float]]:
    """Poses carrying b onto a where b's surface (normals as given, i.e. already flipped for a
    mating surface) lies on a's; up to `keep`, most votes first, with their vote counts (votes
    on `backend`, as `vote_poses`)."""
    if len(a_points) < 3 or len(b_points) < 3:
        return []
    model = pair_table(a_points, a_normals, dist_step, angle_step_deg)
    scene = pair_table(b_points, b_normals, dist_step, angle_step_deg, reference_stride, sort=False)
    return vote_poses(model, scene, 2 * dist_step, alpha_bins, keep, bucket_cap, backend=backend)
