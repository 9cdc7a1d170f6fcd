"""Axes of revolution: the sherds of a wheel-made vessel turn about one axis.

The normal lines of a surface of revolution all meet its axis (Pottmann and Randrup, "Rotational
and helical surface approximation for reverse engineering", 1998). For an axis of direction d and
moment d̄ (Plücker coordinates) and a normal line through p of direction n, that is the linear
condition d . (p x n) + d̄ . n = 0; the axis is the least-squares solution over the skin, with
|d| = 1. A fit that lays two pieces together must carry one piece's axis onto the other's: a
sherd laid half a turn off on its band (the wrong fits that pass on a rescanned vessel's skin)
puts its axis on the far side of the wall. Only skins that turn (`AXIS_TURN`) about axes they hold
firmly (`AXIS_HELD`) are asked: the normal lines of a flat tile meet any line along them, at
infinity. A patch of any smooth surface fits some surface of revolution to second order, so a
piece that is not a thin wall (`Params.region_thin_wall`: a jar's thick wall, a bottle's base, a
column drum) is asked only where it is plainly one (`SOLID_HELD`, `SOLID_NEAR`, and its skin
turning about the axis itself, `Axis.about`): the axis of a pebble's piece means nothing.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..backends.numpy import query_threads
from .icp import axis_rotation, distinct_poses, rotation_between

# the second-smallest eigenvalue of the axis's normal equations over the smallest: a skin that
# turns about one axis holds it (clean vessel sherds 27-550, rescanned 3-50); at 8 one clean
# corpus sherd whose roughness reading took its break for skin held a wrong axis (8.1)
AXIS_HELD = 10.0
# the middle eigenvalue of the skin normals' second moment: a cylinder's arc of phi radians gives
# about phi^2 / 12, so 0.03 asks an arc of about 35 degrees (corpus vessel sherds 0.05-0.43)
AXIS_TURN = 0.03
AXIS_DEG = 15.0  # axes more than this apart in direction do not meet ...
AXIS_STRETCH = 0.15  # ... nor where they lie farther apart than `Params.axis_apart` (of the scale) within this of the foot
# a piece that is not a thin wall: held at least SOLID_HELD, and its normal lines within SOLID_NEAR
# (of the scale; their median distance) of the axis. Every piece of the corpus (twelve families,
# seeds 1-4, 5 and 8 pieces) and of the two Blender sets, first reading, 10th to 90th percentile:
# jars' pieces 0.005-0.066, blocks' 0.041-0.096, pebbles' 0.026-0.087. At the true pose no touching
# pair so asked is refused; the refused nearest the bars held 16.2 at 0.0107 and 18.7 at 0.021
SOLID_HELD = 20.0
SOLID_NEAR = 0.01
NEIGHBOURS = 12  # normals averaged over this many nearest skin faces (a rescan's face normals are noisy)
ROUNDS = 4  # reweighting rounds: break faces read as skin, lips and chips weigh less


@dataclass(frozen=True)
class Axis:
    direction: np.ndarray  # (3,) unit
    foot: np.ndarray  # (3,) the point of the axis nearest the skin's centroid
    held: float  # how firmly the skin holds the direction (second-smallest over smallest eigenvalue)
    near: float = 0.0  # the median distance of the skin's normal lines from the axis (object units)
    # how the skin turns about the axis: the smaller eigenvalue of the second moment of its normals
    # across it (a flat-faced shard's main face "holds" the axis along its normal, and turns none)
    about: float = 0.0
    thin: bool = True  # the skin of a thin wall


def _fit(points: np.ndarray, normals: np.ndarray, weights: np.ndarray):
    centre = weights @ points / weights.sum()
    rows = np.c_[np.cross(points - centre, normals), normals]  # each normal line: (p x n, n)
    m = (rows * weights[:, None]).T @ rows
    a, b, c = m[:3, :3], m[:3, 3:], m[3:, 3:]
    c_inv = np.linalg.pinv(c + 1e-9 * np.trace(c) * np.eye(3))  # a cylinder's normals span a plane only
    lam, vec = np.linalg.eigh(a - b @ c_inv @ b.T)
    d = vec[:, 0]
    moment = -c_inv @ b.T @ d
    residual = rows @ np.r_[d, moment]
    return Axis(d, np.cross(d, moment) + centre, float(lam[1] / max(lam[0], 1e-300))), residual


def skin_axis(centres: np.ndarray, normals: np.ndarray, areas: np.ndarray, thin: bool = True) -> Axis | None:
    """The axis of revolution of a skin, or None where under `NEIGHBOURS` faces or where it does not
    turn (`AXIS_TURN`). `thin`: the skin is a thin wall's (asked more leniently, `axes_meet`).

    Parameters
    ----------
    centres, normals : (n, 3) float, the skin's face centres and unit normals
    areas : (n,) float, their areas
    """
    if len(centres) < NEIGHBOURS:
        return None
    moment = (normals * areas[:, None]).T @ normals / max(areas.sum(), 1e-300)
    if np.linalg.eigvalsh(moment)[1] < AXIS_TURN:
        return None
    _, near = cKDTree(centres).query(centres, k=NEIGHBOURS, workers=query_threads())
    around = normals[near]
    # a line has no sign: the two skins of a wall face apart, and must not cancel
    sign = np.sign(np.einsum("ikj,ij->ik", around, normals))
    smooth = (around * sign[..., None]).sum(1)
    smooth /= np.maximum(np.linalg.norm(smooth, axis=1), 1e-300)[:, None]
    axis, residual = _fit(centres, smooth, areas)
    floor = 1e-9 * float(np.ptp(centres, axis=0).max())  # half a skin on one exact plane: a zero median
    for _ in range(ROUNDS):
        s = max(2 * float(np.median(np.abs(residual))), floor, 1e-300)
        weights = areas / (1 + (residual / s) ** 2)
        axis, residual = _fit(centres, smooth, weights)
    d = axis.direction
    across = smooth - np.outer(smooth @ d, d)
    sine = np.linalg.norm(across, axis=1)
    # the normals across the axis span at most its normal plane: their moment's zero eigenvalue comes first
    about = float(np.linalg.eigvalsh((across * weights[:, None]).T @ across / weights.sum())[1])
    near = float(np.median(np.abs(residual) / np.maximum(sine, 1e-3)))
    return Axis(axis.direction, axis.foot, axis.held, near, about, thin)


def axes_apart(a: Axis, b: Axis, transform: np.ndarray, scale: float) -> tuple[float, float]:
    """(degrees, distance) between a's axis and b's carried by `transform` (4, 4): the angle
    between their directions, and the farthest b's axis lies from the stretch of a's within
    `AXIS_STRETCH` times `scale` of its foot, in units of `scale`."""
    d = transform[:3, :3] @ b.direction
    foot = transform[:3, :3] @ b.foot + transform[:3, 3]
    degrees = float(np.degrees(np.arccos(min(1.0, abs(float(a.direction @ d))))))
    ends = a.foot + np.outer([-AXIS_STRETCH * scale, AXIS_STRETCH * scale], a.direction) - foot
    off = ends - np.outer(ends @ d, d)
    return degrees, float(np.linalg.norm(off, axis=1).max() / scale)


def firm(axis: Axis, scale: float) -> bool:
    """Whether a fit is asked to keep this axis (see the module docstring)."""
    if axis.thin:
        return axis.held >= AXIS_HELD
    return axis.held >= SOLID_HELD and axis.near <= SOLID_NEAR * scale and axis.about >= AXIS_TURN


def axes_meet(a: Axis | None, b: Axis | None, transform: np.ndarray, scale: float, apart: float | None) -> str | None:
    """None where two pieces' axes meet under `transform`, or where either is missing or loosely
    held (`firm`; or `apart` is None); else the reason they do not."""
    if apart is None or a is None or b is None or not (firm(a, scale) and firm(b, scale)):
        return None
    degrees, distance = axes_apart(a, b, transform, scale)
    if degrees <= AXIS_DEG and distance <= apart:
        return None
    return (f"the two pieces' axes of revolution do not meet ({degrees:.0f} degrees, {distance:.2f} of the scale "
            f"apart)")


# A sherd turned half a turn about its wall's normal, upside down, keeps its axis of revolution
# where it was, and fits its partner alike where the wall runs along the axis (a cylinder's); but
# the tilt of a wall that narrows or widens turns the other way. So a fit is refused where the two
# walls beside the seam (within PROFILE_REACH of the scale) tilt in opposite senses, or where both
# tilt under PROFILE_TILT (about 5 degrees: up and down alike). Clouds matched on a thin wall's
# normals (`cloud.wall_normals`), vessel-clean pairs 0-47: the five fits laid upside down tilt in
# opposite senses (0.03-0.11); the 14 right ones in one sense, the larger 0.20-0.36.
PROFILE_TILT = 0.09
PROFILE_REACH = 0.2


def profile_tilt(points: np.ndarray, normals: np.ndarray, axis: Axis, near: np.ndarray) -> float:
    """How the wall tilts along its `axis` at the `near` (boolean or indices) of the (n, 3) points with
    their (n, 3) unit normals: the mean part of the skin's normals along the axis, each turned to
    face away from the axis (the inner skin of a wall faces it), so both skins read alike."""
    radial = points - axis.foot
    radial -= np.outer(radial @ axis.direction, axis.direction)
    away = np.sign(np.einsum("ij,ij->i", normals, radial))
    along = (normals @ axis.direction) * away
    return float(along[near].mean()) if np.any(near) else 0.0


def profile_tilts(a_points, a_normals, b_points, b_normals, a_axis: Axis, b_axis: Axis, transform: np.ndarray,
                  scale: float) -> tuple[float, float]:
    """How each piece's wall tilts along its axis (`profile_tilt`) within PROFILE_REACH of the scale of
    the other under a fit (b moved by `transform`, (4, 4)), b's read in a's sense of the axis. Points
    (n, 3) and unit normals (n, 3) of each piece in its own frame."""
    moved = b_points @ transform[:3, :3].T + transform[:3, 3]
    reach = PROFILE_REACH * scale
    near_a = cKDTree(moved).query(a_points, distance_upper_bound=reach)[0] <= reach
    near_b = cKDTree(a_points).query(moved, distance_upper_bound=reach)[0] <= reach
    direction = transform[:3, :3] @ b_axis.direction
    moved_axis = Axis(direction, transform[:3, :3] @ b_axis.foot + transform[:3, 3], b_axis.held)
    tilt_b = profile_tilt(moved, b_normals @ transform[:3, :3].T, moved_axis, near_b)
    return profile_tilt(a_points, a_normals, a_axis, near_a), tilt_b * float(np.sign(direction @ a_axis.direction))


def profiles_agree(a_points, a_normals, a_axis: Axis | None, b_points, b_normals, b_axis: Axis | None,
                   transform: np.ndarray, scale: float) -> str | None:
    """None where two pieces' walls tilt alike along their axes beside the seam of a fit (b moved by
    `transform`, (4, 4)), or where either axis is missing or loosely held (`firm`); else the reason
    the fit may be laid upside down (see `PROFILE_TILT`). Points (n, 3) and unit normals (n, 3)
    of each piece in its own frame."""
    if a_axis is None or b_axis is None or not (firm(a_axis, scale) and firm(b_axis, scale)):
        return None
    tilt_a, tilt_b = profile_tilts(a_points, a_normals, b_points, b_normals, a_axis, b_axis, transform, scale)
    if max(abs(tilt_a), abs(tilt_b)) < PROFILE_TILT:
        return (f"the wall runs along its axis beside the seam (tilts {tilt_a:+.2f} and {tilt_b:+.2f}): "
                f"laid upside down it would fit alike")
    if tilt_a * tilt_b < 0:
        return (f"the wall tilts one way beside the seam and the other way across it ({tilt_a:+.2f}, "
                f"{tilt_b:+.2f}): laid upside down")
    return None


# Two sherds of one vessel share its axis: a fit that lays b's axis on a's leaves a turn about it and
# a slide along it (and the axis's sense). Each pair of break points at radii within AXIS_REACH
# contacts of each other, with normals facing (their parts along, around and across the axis, which
# the turn and slide keep, under FACING), votes for the turn and slide that lay one on the other;
# a break's two outlines coincide at the right one only. Votes fall in cells AXIS_REACH contacts
# wide (the turn's measured as arc length at the median radius).
AXIS_REACH = 2.0
AXIS_FACING = -0.5
BAND_DEG = 60.0  # a normal turned this far off the radius lies on a wall's cut (`band_points`)


def _cylindrical(points: np.ndarray, normals: np.ndarray, axis: Axis):
    """Angle, height and radius of (n, 3) points about `axis`, and their (n, 3) unit normals' parts
    (outward, around, along)."""
    d = axis.direction
    e1 = np.linalg.svd(d[None])[2][1]
    e2 = np.cross(d, e1)
    rel = points - axis.foot
    x, y, z = rel @ e1, rel @ e2, rel @ d
    angle, radius = np.arctan2(y, x), np.hypot(x, y)
    out = np.c_[np.cos(angle), np.sin(angle)]
    nx, ny = normals @ e1, normals @ e2
    parts = np.c_[nx * out[:, 0] + ny * out[:, 1], -nx * out[:, 1] + ny * out[:, 0], normals @ d]
    return angle, z, radius, parts


def axis_starts(a_points, a_normals, a_axis: Axis, b_points, b_normals, b_axis: Axis, contact: float,
                count: int) -> np.ndarray:
    """(K, 4, 4) poses carrying b onto a that lay b's axis on a's in either sense, best first by the
    break points' votes (see `AXIS_REACH`), at most `count` distinct ones.

    Parameters
    ----------
    a_points, a_normals : (n, 3) float, a's break points and their unit normals
    b_points, b_normals : (m, 3) float, b's
    a_axis, b_axis : each piece's axis in its own frame
    """
    reach = AXIS_REACH * contact
    ta, za, ra, na = _cylindrical(a_points, a_normals, a_axis)
    cell_angle = reach / max(float(np.median(ra)), reach)
    poses, votes = [], []
    for sense in (1.0, -1.0):
        rot = rotation_between(sense * b_axis.direction, a_axis.direction)
        base = np.eye(4)
        base[:3, :3], base[:3, 3] = rot, a_axis.foot - rot @ b_axis.foot
        tb, zb, rb, nb = _cylindrical(b_points @ rot.T + base[:3, 3], b_normals @ rot.T, a_axis)
        i, j = np.nonzero((np.abs(ra[:, None] - rb[None]) < reach) & (na @ nb.T < AXIS_FACING))
        if len(i) == 0:
            continue
        turn = np.mod(ta[i] - tb[j] + np.pi, 2 * np.pi) - np.pi
        cells = np.c_[np.floor(turn / cell_angle), np.floor((za[i] - zb[j]) / reach)].astype(np.int64)
        found, back, n = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
        back = back.ravel()
        for c in np.argsort(-n, kind="stable")[:4 * count]:
            at = back == c
            angle, slide = float(np.mean(turn[at])), float(np.mean((za[i] - zb[j])[at]))
            spin = np.eye(4)
            spin[:3, :3] = axis_rotation(a_axis.direction, angle)
            spin[:3, 3] = a_axis.foot - spin[:3, :3] @ a_axis.foot + slide * a_axis.direction
            poses.append(spin @ base)
            votes.append(n[c])
    if not poses:
        return np.zeros((0, 4, 4))
    poses = np.array(poses)
    return poses[distinct_poses(poses, np.argsort(-np.array(votes), kind="stable"), count, reach)]


def band_points(points: np.ndarray, normals: np.ndarray, axis: Axis) -> tuple[np.ndarray, np.ndarray]:
    """The (k, 3) points of (n, 3) `points` whose (n, 3) unit `normals` turn off the radius of `axis`
    by more than BAND_DEG, and their normals: a wall's cut (and its lip), where the skin's face it."""
    radial = _cylindrical(points, normals, axis)[3][:, 0]
    keep = np.abs(radial) < np.cos(np.radians(BAND_DEG))
    return points[keep], normals[keep]

