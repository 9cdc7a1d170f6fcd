"""Placed fragments settled against every neighbour they touch, all at once (issue 16).

A pair's fit is held only by its own break. A thin wall's break is a narrow band, and once
rescanned (noisy samples, a smoothing reconstruction) its rims are rounded and its two sides stand
apart: the point-to-plane polish slides such fits along the band, 1.5-11 degrees off, and started
from the true pose drifts as far (corpus vessel-noisy, 12,000 faces a piece; docs/benchmarks.md,
"Placed fragments settled on all their neighbours"). A piece of an assembled object touches several
neighbours, along bands that run different ways: what one band leaves loose another holds.

`settle` moves the placed fragments of each group together (the group's first placed fragment
fixed): a round is one linearised point-to-plane solve for the moves of all of them (6 unknowns a
fragment) over the touching pairs of every two, up to `Params.settle_rounds` rounds, until a round
moves no fragment's surface more than STILL. A pair is a surface sample within `reach` of a
neighbour's that faces it (the break's two sides; skins lying side by side across a seam face the
same way), weighed 1 / (1 + (d / SPREAD)^2) by its distance d from the neighbour's tangent plane, so
that a corner that does not close pulls less than a seam that does. No segmentation is asked, and
contacts the matches did not name (the third piece at a corner, the far end of a closed loop) take
part. Moved one at a time onto neighbours that are themselves off, as this did before, the pieces
kept the error of a chain of near-right fits (rescanned breaks fit 0.2-1.3% of the size off, and
the seam at the chain's end does not close); solved together, the seams share it
(docs/benchmarks.md, "The settling solved for all pieces at once").

A fragment touching its neighbours at fewer than TRUSTED pairs when the settling starts stays
where it is and holds the others like the fixed one: at a tenth of the resolution (about 1,500
faces a piece) a piece touches its neighbours at 8-80 pairs, and steps on a handful of noisy pairs
pull it off its place (docs/benchmarks.md, "Moves on few pairs").
"""
from __future__ import annotations

import numpy as np

from ..pair.icp import apply, plane_step
from ..pair.verify import SurfaceSample
from ..params import Params

REACH = 1.0  # of Params.contact_distance: pairs farther apart take no part
SPREAD = 0.3  # of Params.contact_distance: the tangent-plane distance at which a pair weighs half
FACING = -0.5  # the cosine under which two surface points face each other
MIN_PAIRS = 12  # two fragments touching at fewer pairs than this do not pull on each other
TRUSTED = 50  # touching pairs: a fragment held by fewer stays where it is
STILL = 1e-4  # of the scale: a round that moves no fragment's surface more than this (RMS) ends the settling


def settle(pose: list, group: list[int], samples: list[SurfaceSample], params: Params, scale: float,
           backend, reach: float | None = None, trusted: int | None = None) -> list:
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
    trusted : a fragment touching at fewer pairs stays where it is (default TRUSTED)

    Returns
    -------
    list of (4, 4) float or None, the settled poses (new arrays; `pose` is not changed)
    """
    pose = [None if p is None else np.array(p, np.float64) for p in pose]
    reach = (REACH * params.contact_distance if reach is None else reach) * scale
    spread = SPREAD * params.contact_distance * scale
    for g in sorted(set(group)):
        placed = [i for i in range(len(pose)) if group[i] == g and pose[i] is not None
                  and len(samples[i].surface) >= MIN_PAIRS]
        if len(placed) < 2 or params.settle_rounds < 1:
            continue
        held, _ = _solve(placed, [], pose, samples, reach, spread, scale, backend)
        free = [i for i in placed[1:] if held.get(i, 0) >= (TRUSTED if trusted is None else trusted)]
        for _ in range(params.settle_rounds if free else 0):
            _, moves = _solve(placed, free, pose, samples, reach, spread, scale, backend)
            if moves is None:
                break
            moved = 0.0
            for i, step in moves.items():
                before = apply(pose[i], samples[i].surface)
                pose[i] = step @ pose[i]
                moved = max(moved, float(np.sqrt(((apply(pose[i], samples[i].surface) - before) ** 2)
                                                 .sum(axis=1).mean())))
            if moved < STILL * scale:
                break
    return pose


def _solve(placed: list[int], free: list[int], pose: list, samples: list[SurfaceSample], reach: float,
           spread: float, scale: float, backend) -> tuple[dict, dict | None]:
    """One linearised point-to-plane solve for the moves of the `free` fragments over the touching
    pairs of every two `placed` ones: ({fragment: its touching pairs}, {free fragment: (4, 4) step}),
    the steps None where no two touch."""
    surface = {i: (apply(pose[i], samples[i].surface), samples[i].normals @ pose[i][:3, :3].T) for i in placed}
    centre = {i: surface[i][0].mean(axis=0) for i in placed}
    radius = {i: float(np.sqrt(((surface[i][0] - centre[i]) ** 2).sum(axis=1).mean())) or 1.0 for i in placed}
    bound = {i: float(np.sqrt(((surface[i][0] - centre[i]) ** 2).sum(axis=1).max())) for i in placed}
    column = {i: 6 * k for k, i in enumerate(free)}
    normal = np.zeros((6 * len(free), 6 * len(free)))
    rhs = np.zeros(6 * len(free))
    held: dict[int, int] = {}
    for k in placed:
        near = [i for i in placed if i != k and np.linalg.norm(centre[i] - centre[k]) <= bound[i] + bound[k] + reach]
        if not near:
            continue
        index = backend.nearest_index(surface[k][0])
        for i in near:  # i's samples onto k's tangent planes
            p, p_normals = surface[i]
            idx, dist = index.query(p, within=reach)
            dist = np.asarray(dist, np.float64)
            idx = np.where(np.isfinite(dist), np.asarray(idx, np.int64), 0)
            q, n = surface[k][0][idx], surface[k][1][idx]
            use = (dist < reach) & (np.einsum("ij,ij->i", p_normals, n) < FACING)
            if np.count_nonzero(use) < MIN_PAIRS:
                continue
            held[i] = held.get(i, 0) + int(np.count_nonzero(use))
            p, q, n = p[use], q[use], n[use]
            off = np.einsum("ij,ij->i", p - q, n)
            weight = 1.0 / (1.0 + (off / spread) ** 2)
            # the pair's distance grows by (turn_i x (p - c_i) + radius_i t_i - turn_k x (q - c_k) - radius_k t_k) . n
            blocks = [(column[f], sign * np.concatenate([np.cross(x - centre[f], n), radius[f] * n], axis=1) / scale)
                      for f, x, sign in ((i, p, 1.0), (k, q, -1.0)) if f in column]
            for a, rows_a in blocks:
                rhs[a:a + 6] -= rows_a.T @ (weight * off / scale)
                for b, rows_b in blocks:
                    normal[a:a + 6, b:b + 6] += rows_a.T @ (rows_b * weight[:, None])
    if not held or not free:
        return held, None
    normal += 1e-9 * (np.trace(normal) / len(normal) + 1e-12) * np.eye(len(normal))
    x = np.linalg.solve(normal, rhs)
    return held, {i: plane_step(x[column[i]:column[i] + 6], centre[i], radius[i]) for i in free}
