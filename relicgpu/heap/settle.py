"""Placed fragments settled against every neighbour they touch, at once (issue 16).

A pair's fit is held only by its own break. A thin wall's break is a narrow band, and once
rescanned (noisy samples, a smoothing reconstruction) its rims are rounded and its two sides stand
apart: the point-to-plane polish slides such fits along the band, 1.5-11 degrees off, and started
from the true pose drifts as far (corpus vessel-noisy, 12,000 faces a piece; docs/benchmarks.md,
"Placed fragments settled on all their neighbours"). A piece of an assembled object touches several
neighbours, along bands that run different ways: what one band leaves loose another holds.

`settle` moves each placed fragment in turn (up to `Params.settle_rounds` rounds, until one moves
nothing; each group's lowest-index fragment fixed) by point-to-plane steps of its whole surface
sample onto the surfaces of the others of its group, taking only the pairs that touch now (within
`REACH` contact distances) and face each other (the break's two sides; skins lying side by side
across a seam face the same way). No segmentation is asked, and contacts the matches did not name
(the third piece at a corner, the far end of a closed loop) take part.

A move made on few pairs (under `TRUSTED`) is kept only where it leaves the fragment touching its
neighbours at no fewer pairs than before. At a tenth of the resolution (about 1,500 faces a piece)
a piece touches its neighbours at 8-80 such pairs, and a step on a handful of noisy pairs, or onto
a neighbour placed by a tight wrong match, pulls it away from the rest and the right pieces beyond
follow it; a step that mends a near miss closes the contact instead.
"""
from __future__ import annotations

import numpy as np

from ..pair.icp import apply, plane_step
from ..pair.verify import SurfaceSample
from ..params import Params

REACH = 0.5  # of Params.contact_distance: pairs farther apart take no part
FACING = -0.5  # the cosine under which two surface points face each other
STEPS = 5  # point-to-plane steps a fragment takes each round
MIN_PAIRS = 12  # fewer touching pairs than this move nothing
STILL = 1e-4  # of the scale: a round that moves no fragment's surface more than this (RMS) ends the settling
TRUSTED = 50  # touching pairs: a move made on fewer is undone where it leaves fewer


def settle(pose: list, group: list[int], samples: list[SurfaceSample], params: Params, scale: float,
           backend, reach: float | None = None) -> list:
    """Poses settled against all touching neighbours (see the module docstring).

    Parameters
    ----------
    pose : list of (4, 4) float or None, each fragment's pose in the assembly's frame (None: unplaced)
    group : list of int, each fragment's group
    samples : list of SurfaceSample, each fragment's, in its own frame
    params : `Params.settle_rounds` rounds (0: the poses as given), `Params.contact_distance`
    scale : the working scale
    backend : its `nearest_index` finds the pairs
    reach : how far apart a pair may lie, of the scale (default REACH contact distances)

    Returns
    -------
    list of (4, 4) float or None, the settled poses (new arrays; `pose` is not changed)
    """
    pose = [None if p is None else np.array(p, np.float64) for p in pose]
    reach = (REACH * params.contact_distance if reach is None else reach) * scale
    anchors = {min(i for i in range(len(group)) if group[i] == g) for g in set(group)}
    movable = [i for i in range(len(pose)) if pose[i] is not None and i not in anchors
               and len(samples[i].surface) >= MIN_PAIRS]
    placed = [_placed(samples[k], pose[k]) for k in range(len(pose))]  # (points, normals) in the assembly's frame
    spheres = [_sphere(p) for p in placed]
    for _ in range(params.settle_rounds if movable else 0):
        moved = 0.0
        for i in movable:
            others = [k for k in range(len(pose)) if k != i and group[k] == group[i] and pose[k] is not None
                      and _near(spheres[i], spheres[k], reach)]
            if not others:
                continue
            target = np.concatenate([placed[k][0] for k in others])
            normals = np.concatenate([placed[k][1] for k in others])
            before, index = placed[i][0], backend.nearest_index(target)
            new, held = _steps(samples[i].surface, samples[i].normals, target, normals, pose[i], reach, index)
            if held < TRUSTED and new is not pose[i] and np.count_nonzero(
                    _pairs(samples[i].surface, samples[i].normals, new, target, normals, reach, index)[2]) < held:
                continue
            pose[i] = new
            placed[i] = _placed(samples[i], pose[i])
            spheres[i] = _sphere(placed[i])
            moved = max(moved, float(np.sqrt(((placed[i][0] - before) ** 2).sum(axis=1).mean())))
        if moved < STILL * scale:
            break
    return pose


def _placed(sample: SurfaceSample, pose: np.ndarray | None):
    """A fragment's (N, 3) surface points and normals carried by its pose, or None where unplaced."""
    return None if pose is None else (apply(pose, sample.surface), sample.normals @ pose[:3, :3].T)


def _sphere(placed):
    if placed is None or len(placed[0]) == 0:
        return None
    centre = placed[0].mean(axis=0)
    return centre, float(np.sqrt(((placed[0] - centre) ** 2).sum(axis=1).max()))


def _near(a, b, reach: float) -> bool:
    return a is not None and b is not None and float(np.linalg.norm(a[0] - b[0])) <= a[1] + b[1] + reach


def _pairs(points: np.ndarray, point_normals: np.ndarray, pose: np.ndarray, target: np.ndarray,
           target_normals: np.ndarray, reach: float, index):
    """(N, 3) points carried by `pose`, the (N,) index of each one's nearest target point, and the
    (N,) mask of those within `reach` whose normals face the target's."""
    moved, turned = apply(pose, points), point_normals @ pose[:3, :3].T
    idx, dist = index.query(moved, within=reach)
    dist = np.asarray(dist, np.float64)
    idx = np.where(np.isfinite(dist), np.asarray(idx, np.int64), 0)
    return moved, idx, (dist < reach) & (np.einsum("ij,ij->i", turned, target_normals[idx]) < FACING)


def _steps(points: np.ndarray, point_normals: np.ndarray, target: np.ndarray, target_normals: np.ndarray,
           pose: np.ndarray, reach: float, index) -> tuple[np.ndarray, int]:
    """`pose` after STEPS point-to-plane steps of (N, 3) points (normals (N, 3)) onto the (M, 3)
    target's tangent planes, over the pairs within `reach` that face each other, and the count of
    those pairs at `pose` (the same array where no step was taken); the step turns about the moved
    points' centroid in units of their RMS radius (as `icp.refine_point_to_plane`)."""
    radius = float(np.sqrt(((points - points.mean(axis=0)) ** 2).sum(axis=1).mean())) or 1.0
    held = None
    for _ in range(STEPS):
        moved, idx, use = _pairs(points, point_normals, pose, target, target_normals, reach, index)
        count = np.count_nonzero(use)
        held = count if held is None else held
        if count < MIN_PAIRS:
            break
        p, q, n = moved[use], target[idx[use]], target_normals[idx[use]]
        centre = p.mean(axis=0)
        a = np.concatenate([np.cross((p - centre) / radius, n), n], axis=1)
        b = -np.einsum("ij,ij->i", p - q, n) / radius
        x = np.linalg.solve(a.T @ a + 1e-12 * np.eye(6), a.T @ b)
        pose = plane_step(x, centre, radius) @ pose
        if np.linalg.norm(x) < 1e-9:
            break
    return pose, held
