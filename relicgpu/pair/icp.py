"""Rigid fitting: Kabsch from a cross-covariance, RANSAC over LCS correspondences for
the coarse pose, and ICP with the nearest-neighbour subset selection of Eq. 35
(Alg. 5) for the fine pose. Nearest neighbours and the cross-covariance reduction
run on the backend.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..backends import numpy as numpy_backend


def kabsch(cs: np.ndarray, ct: np.ndarray, h: np.ndarray) -> np.ndarray:
    """The 4x4 rigid transform carrying source onto target from centroids and H = sum (s-cs)(t-ct)^T."""
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    t = np.eye(4)
    t[:3, :3] = r
    t[:3, 3] = ct - r @ cs
    return t


def fit_rigid(source: np.ndarray, target: np.ndarray, backend=None) -> np.ndarray:
    if backend is None:
        backend = numpy_backend
    cs, ct, h, _ = backend.cross_covariance(source, target)
    return kabsch(np.asarray(cs, np.float64), np.asarray(ct, np.float64), np.asarray(h, np.float64))


def apply(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    return np.asarray(points, np.float64) @ transform[:3, :3].T + transform[:3, 3]


def invert(transform: np.ndarray) -> np.ndarray:
    """The inverse of a rigid 4x4 transform (transpose of the rotation, no general inverse)."""
    out = np.eye(4)
    out[:3, :3] = transform[:3, :3].T
    out[:3, 3] = -transform[:3, :3].T @ transform[:3, 3]
    return out


def batch_kabsch(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Kabsch for a batch of point triples: src, dst (B,k,3) -> (B,4,4)."""
    cs, cd = src.mean(axis=1), dst.mean(axis=1)
    h = np.einsum("bki,bkj->bij", src - cs[:, None], dst - cd[:, None])
    u, _, vt = np.linalg.svd(h)
    v = np.swapaxes(vt, 1, 2)
    d = np.sign(np.linalg.det(v @ np.swapaxes(u, 1, 2)))
    d[d == 0] = 1.0
    diag = np.zeros((len(src), 3, 3))
    diag[:, 0, 0] = diag[:, 1, 1] = 1.0
    diag[:, 2, 2] = d
    r = v @ diag @ np.swapaxes(u, 1, 2)
    out = np.tile(np.eye(4), (len(src), 1, 1))
    out[:, :3, :3] = r
    out[:, :3, 3] = cd - np.einsum("bij,bj->bi", r, cs)
    return out


def ransac_poses(source: np.ndarray, target: np.ndarray, iterations: int, inlier: float,
                 rng: np.random.Generator, keep: int) -> list[tuple[np.ndarray, int]]:
    """Rigid poses carrying source[i] onto target[i], from random triples, scored by inliers.

    Returns up to `keep` distinct poses (refitted on their inliers) with their inlier counts,
    best first.
    """
    k = len(source)
    if k < 3:
        return []
    idx = rng.integers(0, k, size=(iterations, 3))
    s, t = source[idx], target[idx]
    # triples must span a triangle of real size on both sides
    area = np.linalg.norm(np.cross(s[:, 1] - s[:, 0], s[:, 2] - s[:, 0]), axis=1)
    ok = (area > inlier ** 2) & (idx[:, 0] != idx[:, 1]) & (idx[:, 1] != idx[:, 2]) & (idx[:, 0] != idx[:, 2])
    if not ok.any():
        return []
    poses = batch_kabsch(s[ok], t[ok])
    moved = np.einsum("bij,kj->bki", poses[:, :3, :3], source) + poses[:, None, :3, 3]
    inl = np.linalg.norm(moved - target[None], axis=2) < inlier
    counts = inl.sum(axis=1)
    order = np.argsort(-counts, kind="stable")
    out: list[tuple[np.ndarray, int]] = []
    for b in order:
        if counts[b] < 3 or len(out) >= keep:
            break
        mask = inl[b]
        pose = fit_rigid(source[mask], target[mask])
        if any(same_pose(pose, p, inlier) for p, _ in out):
            continue
        out.append((pose, int(counts[b])))
    return out


def same_fit(p: np.ndarray, q: np.ndarray, scale: float) -> bool:
    """Whether two (4, 4) fits are one: within 0.06 degrees and a thousandth of the scale."""
    return bool(np.abs(p[:3, :3] - q[:3, :3]).max() < 1e-3 and np.abs(p[:3, 3] - q[:3, 3]).max() < 1e-3 * scale)


def same_pose(p: np.ndarray, q: np.ndarray, tol: float) -> bool:
    return np.linalg.norm(p[:3, 3] - q[:3, 3]) < 3 * tol and rotation_angle_deg(p[:3, :3] @ q[:3, :3].T) < 10.0


def distinct_poses(poses: np.ndarray, order: np.ndarray, count: int, tol: float) -> list[int]:
    """The first `count` of `order` whose poses differ from every one taken before (many starts
    converge to one pose; copies would crowd the others out of the hypotheses)."""
    taken: list[int] = []
    for k in order:
        if len(taken) == count:
            break
        if not any(same_pose(poses[k], poses[t], tol) for t in taken):
            taken.append(int(k))
    return taken


def rotation_angle_deg(r: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1))))


@dataclass(frozen=True)
class IcpResult:
    transform: np.ndarray
    mean_distance: float
    iterations: int


def icp(source: np.ndarray, target: np.ndarray, init: np.ndarray, backend, iterations: int,
        tolerance: float, reject: float, floor: float) -> IcpResult:
    """Point-to-point ICP (Alg. 5) moving `source` onto `target` from the pose `init`.

    Each round the subset X^p of the target nearest to the moved source (Eq. 35) is
    paired with it; pairs farther than the rejection distance (at most `reject`,
    shrinking with the median distance, never under `floor`) are left out of the fit.
    Stops when the mean distance d changes less than `tolerance`.
    """
    index = backend.nearest_index(target)
    poses, _ = batched_icp(source, target, np.asarray(init, np.float64)[None], backend, iterations, reject, floor,
                           tolerance if tolerance > 0 else 1e-300, index=index)
    _, dist = index.query(apply(poses[0], source))
    return IcpResult(poses[0], float(np.mean(dist)), iterations)


def rotation_between(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The smallest rotation carrying unit vector u onto unit vector v."""
    c = float(np.dot(u, v))
    axis = np.cross(u, v)
    s = np.linalg.norm(axis)
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        # opposite: half a turn about any axis normal to u
        other = np.array([1.0, 0, 0]) if abs(u[0]) < 0.9 else np.array([0, 1.0, 0])
        axis = np.cross(u, other)
        axis /= np.linalg.norm(axis)
        return 2 * np.outer(axis, axis) - np.eye(3)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]]) / s
    return np.eye(3) + s * k + (1 - c) * k @ k


def axis_rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def facing_poses(centre_a, normal_a, centre_b, normal_b, steps: int) -> np.ndarray:
    """Poses putting patch b face to face with patch a (centres together, normals opposite),
    at `steps` turns about the common normal: (steps,4,4)."""
    base = rotation_between(np.asarray(normal_b), -np.asarray(normal_a))
    out = np.tile(np.eye(4), (steps, 1, 1))
    for k in range(steps):
        r = axis_rotation(np.asarray(normal_a), 2 * np.pi * k / steps) @ base
        out[k, :3, :3] = r
        out[k, :3, 3] = centre_a - r @ centre_b
    return out


def _pair_weights(used: np.ndarray, idx: np.ndarray, weights: np.ndarray | None,
                  target_weights: np.ndarray | None) -> np.ndarray:
    """(H,N) weights of the nearest pairs (source point i, target point idx[h, i]): `used` (H,N)
    times the source point's weight (N,) and the target point's (M,) where given."""
    w = used.astype(np.float64)
    if weights is not None:
        w = w * weights[None]
    if target_weights is not None:
        w = w * target_weights[idx]
    return w


def _trim_cutoff(dist: np.ndarray, trim: float, reject: float, floor: float) -> np.ndarray:
    """(H,) each row's pair cutoff: 3x its `trim` quantile, within [floor, reject]. `dist` (H, N)
    may hold inf for pairs beyond `reject` (`NearestIndex.query(within=reject)`): where the
    quantile reads one, the cutoff is `reject`. The pairs used are those the exact distances
    give: each nearer than reject lies below the quantile's order statistics then."""
    with np.errstate(invalid="ignore"):
        q = np.quantile(dist, trim, axis=1)
    return np.maximum(floor, np.minimum(reject, np.where(np.isfinite(q), 3.0 * q, np.inf)))


def batched_icp(source: np.ndarray, target: np.ndarray, poses: np.ndarray, backend, iterations: int,
                reject: float, floor: float, tolerance: float = 0.0, trim: float = 0.5,
                index=None, weights: np.ndarray | None = None,
                target_weights: np.ndarray | None = None, facing: tuple | None = None) -> tuple[np.ndarray, np.ndarray]:
    """ICP (Alg. 5, as `icp`) for many starting poses at once: every round is ONE nearest-neighbour
    launch over all hypotheses' points. Stops after `iterations` rounds or when no hypothesis's
    mean distance changes by `tolerance` or more. Returns the poses and each one's share of source
    points ending within `floor` of the target.

    Pairs count when nearer than 3x the `trim` quantile of the distances (within [floor, reject]):
    where only part of the source touches the target (a partial contact) a low quantile keeps
    the rest of the source from dragging the fit off. index: the target's nearest-neighbour
    index where the caller keeps one.

    weights : (N,) optional, of the source points; target_weights : (M,) optional, of the target
        points (fracture likelihoods): a pair weighs the product in the cross-covariance, and
        the share counts source points by their weight.
    facing : optional (source normals (N, 3), target normals (M, 3), cosine): a pair is used only
        where the source point's normal, turned by the pose, faces the target point's by more
        (their cosine under the bound); the share counts every point."""
    poses = np.array(poses, np.float64)
    h, n = len(poses), len(source)
    point_weight = np.ones(n) if weights is None else np.asarray(weights, np.float64)
    share = np.zeros(h)
    prev = np.full(h, np.inf)
    index = backend.nearest_index(target) if index is None else index  # one upload (and grid) for all rounds
    for _ in range(iterations):
        moved = np.matmul(source, np.swapaxes(poses[:, :3, :3], 1, 2)) + poses[:, None, :3, 3]
        # a k-d tree stops early past `reject` (most points of a start far from the truth): such
        # pairs come back (M, inf), weigh nothing, and leave every round as the exact distances do
        idx, dist = index.query(moved.reshape(-1, 3), within=reject)
        dist = np.asarray(dist, np.float64).reshape(h, n)
        idx = np.where(np.isfinite(dist), np.asarray(idx, np.int64).reshape(h, n), 0)
        cutoff = _trim_cutoff(dist, trim, reject, floor)
        w = _pair_weights((dist < cutoff[:, None]) & _faces(facing, poses, idx), idx, weights, target_weights)
        share = (dist < floor) @ point_weight / max(point_weight.sum(), 1e-12)
        wsum = np.maximum(w.sum(axis=1), 1e-12)
        dist = np.where(w > 0, dist, 0.0)
        matched = target[idx]
        cs = np.matmul(w[:, None, :], moved)[:, 0] / wsum[:, None]
        ct = np.matmul(w[:, None, :], matched)[:, 0] / wsum[:, None]
        # (BLAS matmuls: a three-operand einsum here cost more than the nearest-neighbour step on a GPU)
        hmat = np.matmul(np.swapaxes((moved - cs[:, None]) * w[..., None], 1, 2), matched - ct[:, None])
        u, _, vt = np.linalg.svd(hmat)
        v = np.swapaxes(vt, 1, 2)
        d = np.sign(np.linalg.det(v @ np.swapaxes(u, 1, 2)))
        d[d == 0] = 1.0
        r = v @ (np.eye(3)[None] * np.stack([np.ones(h), np.ones(h), d], 1)[:, None, :]) @ np.swapaxes(u, 1, 2)
        step = np.tile(np.eye(4), (h, 1, 1))
        step[:, :3, :3] = r
        step[:, :3, 3] = ct - np.einsum("hij,hj->hi", r, cs)
        ok = (w > 0).sum(axis=1) >= 3
        poses[ok] = step[ok] @ poses[ok]
        mean = (w * dist).sum(axis=1) / wsum
        if tolerance > 0 and np.all(np.abs(prev - mean) < tolerance):
            break
        prev = mean
    return poses, share


def _faces(facing: tuple | None, poses: np.ndarray, idx: np.ndarray) -> np.ndarray | bool:
    """(H, N) whether each source point's normal, turned by its (H, 4, 4) pose, faces its nearest
    target point's (idx (H, N)) by more than `facing`'s cosine; True where `facing` is None."""
    if facing is None:
        return True
    source_normals, target_normals, bound = facing
    turned = np.matmul(source_normals, np.swapaxes(poses[:, :3, :3], 1, 2))
    return np.einsum("hij,hij->hi", turned, target_normals[idx]) < bound


def plane_step(x: np.ndarray, centre: np.ndarray, radius: float) -> np.ndarray:
    """The (4, 4) rigid step of a linearised point-to-plane solve `x` (6,), in units of `radius`:
    p -> turn (p - centre) + centre + radius * x[3:], the turn of |x[:3]| radians about x[:3]."""
    turn = axis_rotation(x[:3] / (np.linalg.norm(x[:3]) or 1.0), float(np.linalg.norm(x[:3])))
    step = np.eye(4)
    step[:3, :3] = turn
    step[:3, 3] = centre - turn @ centre + radius * x[3:]
    return step


def refine_point_to_plane(source: np.ndarray, target: np.ndarray, target_normals: np.ndarray, init: np.ndarray,
                          backend, iterations: int, cutoff: float, index=None, weights: np.ndarray | None = None,
                          target_weights: np.ndarray | None = None, facing: tuple | None = None) -> np.ndarray:
    """Polish converged poses by minimising distances to the target's tangent planes.

    Two samplings of one surface never share points, so point-to-point ICP stops at the
    sampling's graininess; the linearised point-to-plane step (6x6 normal equations)
    goes below it. Pairs farther than `cutoff` are left out. init: one (4,4) pose or a
    stack (H,4,4), polished together (one nearest-neighbour launch a round), each stopping
    on its own when its step vanishes or fewer than 6 pairs are left.

    The step turns about the moved source's centroid and is solved in units of the source's
    RMS radius, so that the result does not depend on the units or on how far from the
    origin the points lie (a turn about a far origin is mostly translation). weights (N,) and
    target_weights (M,) and facing: optional, as in `batched_icp`.
    """
    poses = np.array(init, np.float64)
    single = poses.ndim == 2
    poses = poses.reshape(-1, 4, 4)
    active = np.ones(len(poses), bool)
    n = len(source)
    radius = float(np.sqrt(((source - source.mean(0)) ** 2).sum(1).mean())) or 1.0
    index = backend.nearest_index(target) if index is None else index
    for _ in range(iterations):
        live = np.flatnonzero(active)
        if len(live) == 0:
            break
        moved = np.matmul(source, np.swapaxes(poses[live, :3, :3], 1, 2)) + poses[live, None, :3, 3]
        idx, dist = index.query(moved.reshape(-1, 3), within=cutoff)  # (as in batched_icp)
        dist = np.asarray(dist, np.float64).reshape(len(live), n)
        idx = np.where(np.isfinite(dist), np.asarray(idx, np.int64).reshape(len(live), n), 0)
        keep = _pair_weights((dist < cutoff) & _faces(facing, poses[live], idx), idx, weights, target_weights)
        enough = (keep > 0).sum(axis=1) >= 6
        q, nrm = target[idx], target_normals[idx]
        centre = moved.mean(axis=1, keepdims=True)
        arm = (moved - centre) / radius
        root = np.sqrt(keep)  # each pair's residual weighs keep in the normal equations
        a = np.concatenate([np.cross(arm, nrm), nrm], axis=2) * root[..., None]
        b = -np.einsum("hij,hij->hi", moved - q, nrm) / radius * root
        ata = np.matmul(np.swapaxes(a, 1, 2), a) + 1e-12 * np.eye(6)
        atb = np.matmul(np.swapaxes(a, 1, 2), b[..., None])[..., 0]
        for k, h in enumerate(live):
            if not enough[k]:
                active[h] = False
                continue
            try:
                x = np.linalg.solve(ata[k], atb[k])
            except np.linalg.LinAlgError:
                active[h] = False
                continue
            poses[h] = plane_step(x, centre[k, 0], radius) @ poses[h]
            if np.linalg.norm(x) < 1e-9:
                active[h] = False
    return poses[0] if single else poses
