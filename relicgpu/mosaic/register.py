"""One pair: placements from the entropy matches checked by band-passed correlation over
the whole overlap, refined (Gauss-Newton), and one accepted (`register_pair`)."""
from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage

from .entropy import EntropyMatch, match_entropy
from .fcm import FeatureRegion, find_feature_regions, isotropy
from .params import MosaicError, MosaicParams, PairMatch
from .preprocess import Prepared, _block_mean, block_entropy, noise_sigma, prepare_image, to_gray


def _ncc(a: np.ndarray, b: np.ndarray) -> float:
    a = a - a.mean()
    b = b - b.mean()
    den = np.sqrt((a * a).sum() * (b * b).sum())
    return float((a * b).sum() / den) if den > 0 else 0.0


def _to_right(rows, cols, left_point, right_point, angle: float):
    """Where left pixels (rows, cols) lie in the right image under the placement: right pixel q
    sits at left_point + R(angle) (q - right_point), so q = right_point + R(angle)^T (p - left_point)."""
    a = np.deg2rad(angle)
    ca, sa = np.cos(a), np.sin(a)
    dy, dx = rows - left_point[0], cols - left_point[1]
    return right_point[0] + ca * dy - sa * dx, right_point[1] + sa * dy + ca * dx


def _overlap_samples(left: Prepared, right: Prepared, left_point, right_point, angle: float, step: int,
                     margin: float):
    """Left pixels on a `step` grid whose place in the right image lies `margin` px inside it;
    neither lies within the band-pass's outer scale of its image's border (the filter's
    border padding makes structure there that both images do not share)."""
    h, w = left.gray.shape
    hr, wr = right.gray.shape
    edge = int(np.ceil(left.border))
    margin = max(margin, right.border)
    rows, cols = np.mgrid[edge:h - edge:step, edge:w - edge:step]
    rows, cols = rows.ravel(), cols.ravel()
    qy, qx = _to_right(rows, cols, left_point, right_point, angle)
    inside = (qy >= margin) & (qy <= hr - 1 - margin) & (qx >= margin) & (qx <= wr - 1 - margin)
    return rows[inside], cols[inside]


def _correlated(prep: Prepared) -> np.ndarray:
    """The image the correlation compares: band-passed, or median-filtered without `corr_bandpass`."""
    return prep.bandpass if prep.bandpass is not None else prep.smoothed


def overlap_correlation(left: Prepared, right: Prepared, left_point, right_point, angle: float,
                        params: MosaicParams | None = None) -> float:
    """Normalised correlation of the band-passed images over the whole overlap that the placement
    implies (every `overlap_step`-th pixel; -1 when fewer than `min_overlap_samples` overlap)."""
    p = params or MosaicParams()
    rows, cols = _overlap_samples(left, right, left_point, right_point, angle, p.overlap_step, 1.0)
    if rows.size < p.min_overlap_samples:
        return -1.0
    qy, qx = _to_right(rows, cols, left_point, right_point, angle)
    src_l, src_r = _correlated(left), _correlated(right)
    b = ndimage.map_coordinates(src_r, [qy, qx], order=1, mode="nearest")
    return _ncc(src_l[rows, cols], b)


def refine_placement(left: Prepared, right: Prepared, left_point, right_point, angle: float,
                     params: MosaicParams | None = None, gradient=None) -> tuple[np.ndarray, float, float]:
    """The placement (right_point, angle) that maximises the band-passed correlation over the
    whole overlap, from a start within a few pixels: Gauss-Newton on left = a * right(q(p)) + b
    over the right point, the angle and a, b (gain and bias). `gradient` is np.gradient of the
    right band-passed image when already computed. Returns (right_point, angle, correlation)."""
    p = params or MosaicParams()
    rp = np.array(right_point, np.float64)
    theta = np.deg2rad(angle)
    limit = np.deg2rad(max(map(abs, p.angles), default=0.0) + 1.0)
    rows, cols = _overlap_samples(left, right, left_point, rp, angle, p.overlap_step, 8.0)
    if rows.size < p.min_overlap_samples:
        return rp, float(angle), -1.0
    src_r = _correlated(right)
    gy, gx = gradient if gradient is not None else np.gradient(src_r)
    target = _correlated(left)[rows, cols]
    dy, dx = rows - left_point[0], cols - left_point[1]
    hr, wr = right.gray.shape
    for _ in range(p.refine_iterations):
        ca, sa = np.cos(theta), np.sin(theta)
        qy, qx = rp[0] + ca * dy - sa * dx, rp[1] + sa * dy + ca * dx
        ok = (qy >= 0) & (qy <= hr - 1) & (qx >= 0) & (qx <= wr - 1)
        if ok.sum() < p.min_overlap_samples:
            break
        at = [qy[ok], qx[ok]]
        r = ndimage.map_coordinates(src_r, at, order=1)
        ry, rx = ndimage.map_coordinates(gy, at, order=1), ndimage.map_coordinates(gx, at, order=1)
        t = target[ok]
        gain_bias = np.stack([r, np.ones_like(r)], 1)
        coef, *_ = np.linalg.lstsq(gain_bias, t, rcond=None)
        gain, residual = coef[0], t - gain_bias @ coef
        dq_dtheta = (-sa * dy[ok] - ca * dx[ok], ca * dy[ok] - sa * dx[ok])
        jac = np.stack([gain * ry, gain * rx, gain * (ry * dq_dtheta[0] + rx * dq_dtheta[1]), r, np.ones_like(r)], 1)
        step, *_ = np.linalg.lstsq(jac, residual, rcond=None)
        move = np.clip(step[:2], -2.0, 2.0)  # a step at most the band-pass's fine scale
        turn = float(np.clip(step[2], -np.deg2rad(0.5), np.deg2rad(0.5)))
        rp = rp + move
        theta = float(np.clip(theta + turn, -limit, limit))
        if np.abs(move).max() < 0.01 and abs(turn) < 1e-4:
            break
    angle = float(np.rad2deg(theta))
    return rp, angle, overlap_correlation(left, right, left_point, rp, angle, p)


@dataclass
class Placement:
    """One hypothesis of where the right image sits: a feature region's entropy match, then
    (when refined) the placement that maximises the whole-overlap correlation from it."""
    region_index: int
    region: FeatureRegion
    match: EntropyMatch
    rank: int               # 0: the region's entropy match with the smallest coarse T; k: the k-th next minimum
    right_point: np.ndarray
    angle: float
    correlation: float      # whole-overlap band-passed correlation
    refined: bool = False


def _placement_distance(a: Placement, b: Placement) -> float:
    """The largest distance between where the two placements put either feature centre in the right image."""
    out = 0.0
    for pt in (a.region.centre, b.region.centre):
        qa = np.array(_to_right(pt[0], pt[1], a.region.centre, a.right_point, a.angle))
        qb = np.array(_to_right(pt[0], pt[1], b.region.centre, b.right_point, b.angle))
        out = max(out, float(np.linalg.norm(qa - qb)))
    return out


def _decide(placements: list, p: MosaicParams, final: bool):
    """The best refined placement and its margin over every other placement more than
    `distinct_px` away (its refined correlation, or the raw one when not refined), when it
    is accepted: correlation >= min_correlation, margin >= min_margin and, before the last
    region (`final` False), `votes` feature regions refined onto it. Else (None, margin).
    Of the placements refined to within a pixel of the best, the earliest region's is returned."""
    refined = [h for h in placements if h.refined and h.correlation > -1.0]
    if not refined:
        return None, 0.0
    best = max(refined, key=lambda h: h.correlation)
    near = [h for h in placements if _placement_distance(best, h) <= p.distinct_px]
    rivals = [h.correlation for h in placements if h not in near]
    margin = best.correlation - max(rivals, default=-1.0)
    support = len({h.region_index for h in near if h.refined})
    ok = best.correlation >= p.min_correlation and margin >= p.min_margin and (final or support >= p.votes)
    if not ok:
        return None, margin
    # regions that refined onto the same placement (within a pixel) agree: report the earliest of them,
    # the paper's feature region when it is one
    same = [h for h in refined if _placement_distance(best, h) <= 1.0]
    return min(same, key=lambda h: (h.region_index, -h.correlation)), margin


def register_pair(left, right, params: MosaicParams | None = None, backend="numpy",
                  names=("left", "right")) -> PairMatch:
    """Find where `right` sits against `left` (arrays, gray or colour), the right image
    overlapping the right part of the left one. Raises MosaicError when it cannot.

    Each feature region's entropy matches (the best and the next coarse minima) are
    placements; the best by whole-overlap correlation are refined, and one is accepted when
    it correlates well, clearly better than any other placement, and (before the last region)
    a second region's match refines onto it too.

    Images larger than `max_size` are registered on copies shrunk by an integer factor f
    (block means), and the match is then refined at full resolution by the fine search
    alone, f + fine_radius pixels either way, then by the correlation over the two crops;
    the checks are those of the shrunk copies."""
    p = params or MosaicParams()
    t0 = time.perf_counter()
    timings = {}
    gl, gr = to_gray(left), to_gray(right)
    f = max(1, int(np.ceil(max(gl.shape + gr.shape) / p.max_size)))
    sl, sr = (_block_mean(g, f) if f > 1 else g for g in (gl, gr))
    # one variance floor for both images: with each image's own, a faint texture under the floor of
    # the noisier image is amplified less there than in the other, and its entropies differ throughout
    noise = max(noise_sigma(sl), noise_sigma(sr))
    pl, pr = prepare_image(sl, p, noise), prepare_image(sr, p, noise)
    timings["preprocess"] = time.perf_counter() - t0
    t = time.perf_counter()
    regions = find_feature_regions(pl, p, backend, names[0], 1 + p.retries)
    timings["feature_region"] = time.perf_counter() - t
    t = time.perf_counter()
    hmap = np.asarray(block_entropy(pr.levels, p.block, p.levels, backend), np.float64)
    hmap_coarse = hmap if pr.coarse_levels is pr.levels else np.asarray(
        block_entropy(pr.coarse_levels, p.block, p.levels, backend), np.float64)
    timings["entropy_map"] = time.perf_counter() - t
    t = time.perf_counter()
    gradient = np.gradient(_correlated(pr))
    placements, edge_like, chosen, margin = [], 0, None, 0.0
    usable = [k for k, r in enumerate(regions) if isotropy(pl.smoothed, r.centre, r.width) >= p.min_isotropy]
    edge_like = len(regions) - len(usable)
    timings["verify"] = 0.0
    for n, k in enumerate(usable):
        region = regions[k]
        em = match_entropy(pl, pr, region, p, backend, names, hmap, hmap_coarse=hmap_coarse)
        tv = time.perf_counter()
        found = [Placement(k, region, m, j, np.array([m.row, m.col]), m.angle,
                           overlap_correlation(pl, pr, region.centre, (m.row, m.col), m.angle, p))
                 for j, m in enumerate([em] + em.alternatives)]
        found.sort(key=lambda h: -h.correlation)
        for h in found[:p.refine_count]:
            if h.correlation >= p.refine_floor:
                h.right_point, h.angle, h.correlation = refine_placement(pl, pr, region.centre, h.right_point,
                                                                         h.angle, p, gradient)
                h.refined = True
        placements += found
        chosen, margin = _decide(placements, p, final=n == len(usable) - 1)
        timings["verify"] += time.perf_counter() - tv
        if chosen is not None:
            break
    if chosen is None:
        if not placements:
            why = f"{edge_like} feature regions edge-like (one gradient direction)"
        else:
            best = max(placements, key=lambda h: h.correlation)
            why = (f"the best placement correlates {best.correlation:.2f} over the overlap (needs "
                   f"{p.min_correlation}), {margin:.2f} above another one (needs {p.min_margin})")
        raise MosaicError(f"{names[0]} and {names[1]}: no overlap found: {len(regions)} feature regions tried, "
                          f"{why}; the images must overlap by at least {p.min_overlap:.0%}")
    timings["match"] = time.perf_counter() - t
    region, em, corr = chosen.region, chosen.match, chosen.correlation
    right_point, angle = chosen.right_point, chosen.angle
    entropy_point = f * np.array([em.row, em.col]) + (f - 1) / 2.0
    if f > 1:  # refine at full resolution around the scaled-up match, on crops around both areas
        t = time.perf_counter()
        width = f * region.width
        centre = np.array([f * region.centre[0] + (f - 1) // 2, f * region.centre[1] + (f - 1) // 2])
        start = f * right_point + (f - 1) / 2.0
        radius = f + p.fine_radius
        # room for the rotated area, the normalisation window and the median filter
        half = int(0.55 * width * (1.0 + np.deg2rad(max(map(abs, p.angles), default=0.0)))) + p.norm_window + 4
        lo_l = np.maximum(centre - half, 0)
        lo_r = np.maximum(np.floor(start).astype(int) - half - radius, 0)
        crop_l = gl[lo_l[0]:centre[0] + half + 1, lo_l[1]:centre[1] + half + 1]
        crop_r = gr[lo_r[0]:int(start[0]) + half + radius + 2, lo_r[1]:int(start[1]) + half + radius + 2]
        noise = max(noise_sigma(gl), noise_sigma(gr))
        full_l, full_r = prepare_image(crop_l, p, noise), prepare_image(crop_r, p, noise)
        local = replace(region, centre=tuple(int(v) for v in centre - lo_l), width=width)
        em = match_entropy(full_l, full_r, local, p, backend, names, start=start - lo_r, radius=radius)
        local_point, angle, _ = refine_placement(full_l, full_r, local.centre, (em.row, em.col), angle, p)
        right_point = local_point + lo_r
        region = replace(region, centre=tuple(int(v) for v in centre), width=width)
        timings["full_resolution"] = time.perf_counter() - t
    left_point = np.array(region.centre, np.float64)
    right_point = np.asarray(right_point, np.float64)
    timings["total"] = time.perf_counter() - t0
    return PairMatch(left_point, right_point, angle, left_point - right_point, region.width, em.cost, corr,
                     em.distinctness, chosen.region_index, region.centres, region.fcm.iterations, margin=margin,
                     entropy_point=entropy_point, entropy_rank=chosen.rank, timings=timings)
