"""The skin across the seam: where a break leaves a turn of the fit loose, the skin holds it.

A thin board's break (a tile, a slab, a plank) is a long narrow band. Fitted on its points alone
the pose can turn about the band's length almost freely: in the point-to-plane normal equations
of a sparse cloud that direction is 90-500 times weaker than the strongest, and the fit settles
2-3 degrees off (issue 15, `docs/benchmarks.md`). The skin on the two sides of a fresh break
continues across it, so a fit folded at the seam puts one side's skin off the other's surface.

`seam_polish` adds that continuation to the point-to-plane polish: each skin point of one piece
near the other's skin is held to the other's surface extrapolated to it (a quadric height field
over the skin points within `REACH` of the seam, fitted once per round), each term weighed by
the inverse of its residual variance against the break's, the skin's outliers trimmed (`TRIM`).
It runs where the fit is loose (`looseness` under `LOOSE`): where the break pins every direction
the skin has nothing to add, and a worn or chipped rim could pull the fit; elsewhere a cloud
fit's polish is taken only where its skin then continues the partner's clearly better
(`skinhold.held_by_skin`). A cloud's fit of two crease regions that its skin picks is polished so
too (`pipeline._by_skin`, on the `free_surface` of both pieces).

`skin_continuation` asks the same quadrics a question instead: how much of the surface beside
the seam runs on into the partner's. It needs no segmentation and holds on rescanned breaks,
whose creases are noise: a mesh fit refused only for its residual is accepted on it
(`meshfit.outline_fit`, `Params.min_skin`), and of a cloud break's curved region fits, or a flat
cut's plane fits, which fit at several turns alike, it picks the turn (`pipeline._by_skin`,
`cutfit._plane_by_skin`).
"""
from __future__ import annotations

import itertools

import numpy as np

from .icp import apply, invert, plane_step, rotation_angle_deg

# Skin points of one piece within NEAR of the other's skin are held to it, extrapolated from the
# other's skin points within REACH of the nearest one, turned within AGREE (cosine) of the point's
# own normal; a fit over fewer than MIN_FIT points, or whose own residual (RMS) exceeds MAX_FIT,
# is no surface to extend (a crease, a thin wall's two faces), and a point farther than GATE of
# those residuals from it is not its continuation. Lengths are shares of the pair's scale.
# Measured on bench_clouds' synthetic pairs 0-47 without normals (docs/benchmarks.md).
NEAR = 0.05
REACH = 0.15
AGREE = 0.8
MIN_FIT = 10
MAX_FIT = 0.002
GATE = 4.0
# ... however tightly the quadric fits, its residual reads at least FIT_FLOOR (of the scale) in
# `seam_polish`'s gate: a cloud sampled off an exact surface fits its skin's quadrics to 1e-17,
# and gated so, no partner's skin point held a right fit (a bookshelf's board without noise:
# held by 1 point, refused as unsettled)
FIT_FLOOR = 1e-4
# The weakest direction of the break's own normal equations, as a share of the strongest, under
# which the fit is loose: slabs 0.002-0.011, vases and torsos 0.03-0.12 (one turned vase 0.009).
LOOSE = 0.02
ROUNDS = 3  # rounds of new quadrics; each runs STEPS Gauss-Newton steps on them
STEPS = 5
# Skin terms over TRIM times the median skin residual are left out of a step: a few skin points
# that do not continue the other's surface (a rim's fracture read as skin) set the fold of a slab
# 1.5-3 degrees off where 50 points hold it (bench_clouds slab seeds 41, 44: 2.2 and 3.2 degrees
# untrimmed, 1.2 and 0.5 at 3).
TRIM = 3.0
# Singular values of a quadric fit's normal equations under this share of the largest are taken
# as zero (a design's under its square root, 3e-7: a patch of points on a line).
GRAM_RCOND = 1e-13
MAX_WEIGHT = 100.0  # a skin term weighs at most this many break terms (a few points fitting too well)


def _frame(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    t1 = np.cross(normal, [1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.cross(normal, [0.0, 1.0, 0.0])
    t1 /= np.linalg.norm(t1)
    return t1, np.cross(normal, t1)


def seam_surfaces(skin: np.ndarray, skin_normals: np.ndarray, points: np.ndarray, point_normals: np.ndarray,
                  near: float, reach: float, max_fit: float, gate_floor: float = 0.0) -> list[tuple]:
    """Quadric patches of one piece's skin extended to the other's skin points near it.

    Parameters
    ----------
    skin, skin_normals : (N, 3) float, the first piece's skin points and outward unit normals
    points, point_normals : (M, 3) float, the other piece's skin points and normals, in the same frame
    near, reach, max_fit : lengths (see the module's constants)
    gate_floor : a point this close to the quadric continues it, however tightly the quadric fits

    Returns
    -------
    list of (index into points, (3,) origin, (3, 3) axes [t1, t2, n], (6,) coefficients of
    h = c0 + c1 u + c2 v + c3 u^2 + c4 u v + c5 v^2), for each point that extends the skin.
    """
    return [(i, centre, axes, coef) for i, centre, axes, coef, fit, off in
            _extensions(skin, skin_normals, points, point_normals, near, reach)[1]
            if fit <= max_fit and off <= max(GATE * max(fit, 1e-12), gate_floor)]


def _extensions(skin, skin_normals, points, point_normals, near: float, reach: float) -> tuple[int, list]:
    """The points within `near` of the skin, counted, and for each whose nearest skin point has
    at least MIN_FIT skin points within `reach` turned within AGREE of it: (index, quadric origin,
    axes, coefficients, the quadric's RMS residual, the point's distance from it)."""
    from scipy.spatial import cKDTree

    if len(skin) < MIN_FIT or len(points) == 0:
        return 0, []
    tree = cKDTree(skin)
    d, nearest = tree.query(points)
    close = np.flatnonzero(d < near)
    if len(close) == 0:
        return 0, []
    # one ball about each skin point that is some point's nearest, shared by the points nearest it
    centres, which = np.unique(nearest[close], return_inverse=True)
    balls = tree.query_ball_point(skin[centres], reach, return_sorted=False)
    ball_sizes = np.fromiter(map(len, balls), np.int64, len(balls))
    members = np.fromiter(itertools.chain.from_iterable(balls), np.int64, int(ball_sizes.sum()))
    sizes = ball_sizes[which]
    rows = np.repeat(np.arange(len(close)), sizes)
    flat = members[np.repeat((np.cumsum(ball_sizes) - ball_sizes)[which] - (np.cumsum(sizes) - sizes), sizes)
                   + np.arange(len(rows))]
    # the ball's points turned within AGREE of the point's normal
    turned = np.einsum("jd,jd->j", skin_normals[flat], point_normals[close][rows]) > AGREE
    rows, flat = rows[turned], flat[turned]
    sizes = np.bincount(rows, minlength=len(close))
    fitted = sizes >= MIN_FIT
    if not fitted.any():
        return len(fitted), []
    flat = flat[fitted[rows]]
    close, sizes = close[fitted], sizes[fitted]
    centre, axes, coef, fit = _quadrics(skin[flat], skin_normals[flat], np.cumsum(sizes) - sizes)
    uq, vq, hq = np.einsum("kij,kj->ik", axes, points[close] - centre)
    off = np.abs(hq - _height(coef.T, uq, vq))
    return len(fitted), [(int(i), centre[k], axes[k], coef[k], float(fit[k]), float(off[k])) for k, i in enumerate(close)]


def _quadrics(points: np.ndarray, normals: np.ndarray, starts: np.ndarray):
    """Quadric height fields, one over each run of the (n, 3) points (with (n, 3) normals) that
    begins at `starts` (K,) and ends where the next begins, along the run's mean normal: (K, 3)
    origins, (K, 3, 3) axes [t1, t2, n], (K, 6) coefficients (`_height`) and (K,) RMS residuals.
    Least squares with the minimum norm, as `numpy.linalg.lstsq`."""
    count = np.diff(np.append(starts, len(points)))
    rows = np.repeat(np.arange(len(starts)), count)
    centre = np.add.reduceat(points.T, starts, axis=1).T / count[:, None]
    m = np.add.reduceat(normals.T, starts, axis=1).T
    m /= np.linalg.norm(m, axis=1, keepdims=True)
    other = np.where(np.abs(m[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(m, other)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    axes = np.stack([t1, np.cross(m, t1), m], 1)
    u, v, h = np.einsum("nij,nj->in", axes[rows], points - centre[rows])
    # the normal equations (6 x 6 a run, not an SVD of each run's whole design: a ball of REACH
    # holds hundreds of points), over u and v in units of the run's own radius so that they are
    # well conditioned; a radius for the linear and its square for the quadratic terms keeps each
    # run's minimum-norm solution where the fit has no unique one (its null directions lie within them)
    radius = np.sqrt(np.add.reduceat(u * u + v * v, starts) / count)
    radius = np.where(radius > 0, radius, 1.0)
    su, sv = u / radius[rows], v / radius[rows]
    # the Gram matrix from the 15 monomials of degree up to 4 in (su, sv), and the design times h
    uu, uv, vv = su * su, su * sv, sv * sv
    design = np.stack([np.ones_like(su), su, sv, uu, uv, vv])
    sums = np.add.reduceat(np.concatenate([design, [uu * su, uu * sv, vv * su, vv * sv, uu * uu, uu * uv, uu * vv,
                                                    uv * vv, vv * vv], design * h]), starts, axis=1).T
    coef = (np.linalg.pinv(sums[:, _GRAM], rcond=GRAM_RCOND, hermitian=True) @ sums[:, 15:, None])[..., 0]
    residual = np.einsum("jn,nj->n", design, coef[rows]) - h
    fit = np.sqrt(np.add.reduceat(residual * residual, starts) / count)
    return centre, axes, coef / radius[:, None] ** np.array([0, 1, 1, 2, 2, 2]), fit


# Which of the monomials 1, u, v, u^2, uv, v^2, u^3, u^2 v, u v^2, v^3, u^4, u^3 v, u^2 v^2, u v^3,
# v^4 each entry of the design [1, u, v, u^2, uv, v^2]'s Gram matrix sums.
_GRAM = np.array([[0, 1, 2, 3, 4, 5],
                  [1, 3, 4, 6, 7, 8],
                  [2, 4, 5, 7, 8, 9],
                  [3, 6, 7, 10, 11, 12],
                  [4, 7, 8, 11, 12, 13],
                  [5, 8, 9, 12, 13, 14]])


def _height(coef, u, v):
    return coef[0] + coef[1] * u + coef[2] * v + coef[3] * u * u + coef[4] * u * v + coef[5] * v * v


def _planes(patches, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each (index, centre, axes, coef) patch, the point's residual over the quadric and the
    quadric's unit normal below it: (K,) indices, (K,) signed heights, (K, 3) normals."""
    if not patches:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3))
    idx = np.array([p[0] for p in patches])
    centre = np.array([p[1] for p in patches])
    axes = np.array([p[2] for p in patches])
    coef = np.array([p[3] for p in patches]).T
    u, v, h = np.einsum("kij,kj->ik", axes, points[idx] - centre)
    du = coef[1] + 2 * coef[3] * u + coef[4] * v
    dv = coef[2] + coef[4] * u + 2 * coef[5] * v
    normal = axes[:, 2] - du[:, None] * axes[:, 0] - dv[:, None] * axes[:, 1]
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    # the height over the quadric, along its normal (first order)
    return idx, (h - _height(coef, u, v)) * (normal * axes[:, 2]).sum(1), normal


def looseness(source: np.ndarray, target: np.ndarray, target_normals: np.ndarray, transform: np.ndarray,
              cutoff: float, index) -> float:
    """The weakest direction of the point-to-plane normal equations of the (N, 3) source moved by
    the (4, 4) transform onto the (M, 3) target with (M, 3) normals, as a share of the strongest
    (rotation in units of the source's RMS radius); 1.0 where fewer than 6 points are in reach."""
    jac, _, _ = _fracture_terms(source, target, target_normals, transform, cutoff, index)
    if len(jac) < 6:
        return 1.0
    values = np.linalg.eigvalsh(jac.T @ jac)
    return float(values[0] / values[-1]) if values[-1] > 0 else 1.0


def _fracture_terms(source, target, target_normals, transform, cutoff, index):
    moved = apply(transform, source)
    idx, dist = index.query(moved)
    idx, keep = np.asarray(idx, np.int64), np.asarray(dist) < cutoff
    centre = moved.mean(0)
    radius = float(np.sqrt(((moved - centre) ** 2).sum(1).mean())) or 1.0
    n = target_normals[idx[keep]]
    jac = np.concatenate([np.cross((moved[keep] - centre) / radius, n), n], 1)
    res = -np.einsum("ij,ij->i", moved[keep] - target[idx[keep]], n) / radius
    return jac, res, (centre, radius)


def seam_polish(fracture_a: np.ndarray, fracture_normals_a: np.ndarray, fracture_b: np.ndarray,
                skin_a: tuple[np.ndarray, np.ndarray], skin_b: tuple[np.ndarray, np.ndarray],
                transform: np.ndarray, cutoff: float, scale: float, index, wide_gate: float = 0.0) -> tuple[np.ndarray, int]:
    """The (4, 4) transform carrying b onto a polished on a's fracture planes and on the skin across
    the seam, both ways, and the number of skin points that held it in the last step.

    Parameters
    ----------
    fracture_a, fracture_normals_a : (P, 3) float, a's fracture sample and its outward normals
    fracture_b : (Q, 3) float, b's fracture sample (in b's frame)
    skin_a, skin_b : ((N, 3), (N, 3)) float, each piece's skin points and outward normals, own frame
    transform : (4, 4) float, the fit to start from
    cutoff : fracture pairs farther than this are left out
    scale : the pair's scale (NEAR, REACH, MAX_FIT are shares of it)
    index : nearest-neighbour index of fracture_a (`backend.nearest_index`)
    wide_gate : a skin point within this share of `cutoff` of the other's quadric holds the fit in
        the first round, half of it in the next, and so on, however tightly the quadric fits (0:
        only within GATE of its own residual). A start a few degrees off puts a clean skin out of
        its partner's gate, and the break alone then polishes it further off.
    """
    transform = np.array(transform, np.float64)
    held = 0
    for r in range(ROUNDS):
        floor = max(wide_gate * cutoff * 0.5 ** r, GATE * FIT_FLOOR * scale)
        moved_skin = apply(transform, skin_b[0]), skin_b[1] @ transform[:3, :3].T
        # a's skin extended to b's points (frame a), and b's to a's (frame b)
        on_a = seam_surfaces(*skin_a, *moved_skin, NEAR * scale, REACH * scale, MAX_FIT * scale, floor)
        back = invert(transform)
        on_b = seam_surfaces(*skin_b, apply(back, skin_a[0]), skin_a[1] @ back[:3, :3].T,
                             NEAR * scale, REACH * scale, MAX_FIT * scale, floor)
        for _ in range(STEPS):
            jac_f, res_f, (centre, radius) = _fracture_terms(fracture_b, fracture_a, fracture_normals_a,
                                                             transform, cutoff, index)
            if len(res_f) < 6:
                return transform, held
            # b's skin points (moved) over a's quadrics: moving b moves the points
            idx, h, n = _planes(on_a, apply(transform, skin_b[0]))
            p = apply(transform, skin_b[0][idx])
            jac_1 = np.concatenate([np.cross((p - centre) / radius, n), n], 1)
            # a's skin points over b's quadrics, taken into a's frame: moving b moves the surface
            back = invert(transform)
            idx2, h2, n2 = _planes(on_b, apply(back, skin_a[0]))
            n2 = n2 @ transform[:3, :3].T
            jac_2 = -np.concatenate([np.cross((skin_a[0][idx2] - centre) / radius, n2), n2], 1)
            jac_s = np.concatenate([jac_1, jac_2])
            res_s = -np.concatenate([h, h2]) / radius
            if len(res_s):
                keep = np.abs(res_s) <= TRIM * np.median(np.abs(res_s))
                jac_s, res_s = jac_s[keep], res_s[keep]
            held = len(res_s)
            weight = 0.0
            if held:
                # each term by the inverse of its variance: the skin is smooth, the break is not
                weight = float(np.mean(res_f ** 2) / max(np.mean(res_s ** 2), 1e-30))
                weight = min(weight, MAX_WEIGHT)
            lhs = jac_f.T @ jac_f + weight * jac_s.T @ jac_s + 1e-12 * np.eye(6)
            x = np.linalg.solve(lhs, jac_f.T @ res_f + weight * jac_s.T @ res_s)
            transform = plane_step(x, centre, radius) @ transform
            if np.linalg.norm(x) < 1e-9:
                break
    return transform, held


# A fit's skin continues its partner's where a free point (farther than 2 contact distances from
# the other surface) near the other's free surface lies within CONTINUES (a share of the scale) of
# the other's quadric extended to it.
CONTINUES = 0.004


def free_surface(points: np.ndarray, normals: np.ndarray, other: np.ndarray, contact: float):
    """The (K, 3) points and normals of a piece's (N, 3) surface points and normals farther than
    2 contact distances from the other piece's (M, 3) points (same frame): its skin beside the
    seam and beyond, wherever the fit leaves it free."""
    from scipy.spatial import cKDTree

    free = cKDTree(other).query(points)[0] > 2 * contact
    return points[free], normals[free]


def skin_continuation(a, b, transform: np.ndarray, contact: float, scale: float) -> float:
    """How much of the surface beside the seam continues the partner's: of the free points of
    each SurfaceSample (b's moved by the (4, 4) transform) within NEAR of the other's free
    surface, the share that lies on the other's free surface extended to it (a quadric over its
    points within REACH, normals within AGREE). No segmentation is asked for: at the right fit of
    a fresh break the skins on both sides meet smoothly; a face laid on a face with the rims
    apart puts one piece's side across the other's face. 0.0 where no free point is near."""
    continues, near = skin_points(a, b, transform, contact, scale)
    return continues / near if near else 0.0


def skin_points(a, b, transform: np.ndarray, contact: float, scale: float, skin_only: bool = False) -> tuple[int, int]:
    """`skin_continuation`'s counts: the free points that continue the partner's surface, and
    those near it; with `skin_only`, of the points the reading takes for skin (`surface_weight` 0)."""
    moved, moved_normals = apply(transform, b.surface), b.normals @ transform[:3, :3].T
    keep_a, keep_b = (_skin(s) if skin_only else slice(None) for s in (a, b))
    free_a = free_surface(a.surface[keep_a], a.normals[keep_a], moved, contact)
    free_b = free_surface(moved[keep_b], moved_normals[keep_b], a.surface, contact)
    near = continues = 0
    for skin, others in ((free_a, free_b), (free_b, free_a)):
        count, found = _extensions(*skin, *others, NEAR * scale, REACH * scale)
        near += count
        continues += int(sum(off < CONTINUES * scale for *_, off in found))
    return continues, near


def _skin(sample) -> np.ndarray | slice:
    """Which of a sample's surface points its reading takes for skin: all where it says nothing
    (clouds), or where it takes none (a piece it reads as all break, or matched whole as it reads
    next to none: `prepare.sampling_prob`)."""
    skin = None if sample.surface_weight is None else sample.surface_weight <= 0
    return skin if skin is not None and skin.any() else slice(None)


def skin_winner(skins, poses, min_skin: float, share: float, turn_deg: float) -> tuple[int, float] | None:
    """Of fits whose skin continues the partner's by `skins` (the (4, 4) `poses`), the one continuing
    most, where it continues by at least `min_skin` and every fit turned over `turn_deg` from it
    continues less than `share` times as much: (its index, the most such a turned fit continues), or
    None (a flat break fits its partner at one turn only, which the skin across the seam decides)."""
    best = int(np.argmax(skins))
    turned = [s for s, t in zip(skins, poses) if rotation_angle_deg(t[:3, :3] @ poses[best][:3, :3].T) > turn_deg]
    rival = max(turned, default=0.0)
    if skins[best] < min_skin or (turned and rival >= share * skins[best]):
        return None
    return best, rival
