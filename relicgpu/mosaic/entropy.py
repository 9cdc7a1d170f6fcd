"""3.4 local entropy matching: the cross-shaped template's block entropies against every
block position of the right image, coarse with sequential early stop, then fine."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from ..backends import numpy as reference
from .fcm import FeatureRegion
from .params import MosaicError, MosaicParams
from .preprocess import Prepared, block_entropy, quantise


def quadratic_entropy(block_levels: np.ndarray, n_levels: int) -> float:
    """Eq. 8 for one sub-image: H = -sum_i P(i) (P(i) - 1)."""
    q = np.asarray(block_levels, np.float64).ravel()
    p = np.clip(1.0 - np.abs(q[:, None] - np.arange(n_levels)[None, :]), 0.0, None).sum(0) / q.size
    return float(-(p * (p - 1.0)).sum())


def sequential_costs(template_h: np.ndarray, block_offsets: np.ndarray, hmap: np.ndarray,
                     cand: np.ndarray, thre: float | None = None, slack: float = 1.0) -> np.ndarray:
    """T for each candidate top-left cand[i] = (y, x): sum over blocks k of
    |template_h[k] - hmap[y + oy_k, x + ox_k]|, adding blocks in order and dropping a
    candidate as soon as its running T passes `thre` (its T is then +inf).
    thre=None: `slack` times the full T of the candidate leading after a quarter of the
    blocks. That is an upper bound of slack * (the minimum), so every candidate within
    that factor of the minimum is kept with its exact T, and slack=1 drops only the
    candidates that cannot win."""
    cand = np.asarray(cand, np.int64).reshape(-1, 2)
    n, k = len(cand), len(template_h)
    total = np.zeros(n)
    if n == 0:
        return total
    alive = np.arange(n)
    start = 0
    if thre is None:
        start = max(1, k // 4)
        for j in range(start):
            total += np.abs(template_h[j] - hmap[cand[:, 0] + block_offsets[j, 0], cand[:, 1] + block_offsets[j, 1]])
        lead = int(np.argmin(total))
        y, x = cand[lead]
        thre = slack * float(np.abs(template_h - hmap[y + block_offsets[:, 0], x + block_offsets[:, 1]]).sum())
        thre += 1e-9 * (1.0 + thre)  # the running sums add in another order: keep the leader itself
        alive = alive[total <= thre]
    for j in range(start, k):
        if alive.size == 0:
            break
        c = cand[alive]
        total[alive] += np.abs(template_h[j] - hmap[c[:, 0] + block_offsets[j, 0], c[:, 1] + block_offsets[j, 1]])
        alive = alive[total[alive] <= thre]
    out = np.full(n, np.inf)
    out[alive] = total[alive]
    return out


def cross_blocks(width: int, p: MosaicParams) -> tuple[np.ndarray, tuple]:
    """Top-left corners, relative to the feature centre, of the blocks of the cross-shaped area
    of a template `width` wide: a horizontal and a vertical bar through the centre, each as long
    as the template and `cross_fraction` of it thick (at least one block). Blocks lie on a
    `block_stride` grid over the template and count when they fit inside either bar.
    Returns (K, 2) offsets and the template box (top, left, height, width)."""
    b = p.block
    stride = p.block_stride or b
    height = width
    top, left = -(height // 2), -(width // 2)
    thick = min(width, max(b, int(round(width * p.cross_fraction))))
    ys = np.arange(top, top + height - b + 1, stride)
    xs = np.arange(left, left + width - b + 1, stride)
    oy, ox = np.meshgrid(ys, xs, indexing="ij")
    lo = -(thick // 2)
    in_h = (oy >= lo) & (oy + b <= lo + thick)
    in_v = (ox >= lo) & (ox + b <= lo + thick)
    keep = in_h | in_v
    return np.stack([oy[keep], ox[keep]], 1), (top, left, height, width)


def _sample_box(image: np.ndarray, centre, box, angle_deg: float) -> np.ndarray:
    """The box (top, left, height, width) around `centre`, sampled through a rotation by
    angle_deg about the centre: out[u] = image[centre + R(angle) u], bilinear."""
    top, left, height, width = box
    uy, ux = np.meshgrid(np.arange(top, top + height, dtype=np.float64),
                         np.arange(left, left + width, dtype=np.float64), indexing="ij")
    a = np.deg2rad(angle_deg)
    ca, sa = np.cos(a), np.sin(a)
    ry = centre[0] + ca * uy + sa * ux
    rx = centre[1] - sa * uy + ca * ux
    return ndimage.map_coordinates(np.asarray(image, np.float64), [ry, rx], order=1, mode="nearest")


@dataclass
class EntropyMatch:
    """The result of 3.4 for one feature region."""
    row: float              # where the feature centre lies in the right image (sub-pixel)
    col: float
    angle: float            # degrees: the rotation of the template that matched best
    cost: float             # T at the best integer position
    distinctness: float     # T of the best coarse position farther than a block away, over T of the best
    alternatives: list = field(default_factory=list)  # EntropyMatch of the next coarse minima (see candidates)


def match_entropy(left: Prepared, right: Prepared, region: FeatureRegion, params: MosaicParams | None = None,
                  backend="numpy", names=("left", "right"), hmap: np.ndarray | None = None,
                  start=None, radius: int | None = None, hmap_coarse: np.ndarray | None = None) -> EntropyMatch:
    """3.4: coarse then fine local-entropy matching of the cross-shaped feature area in the
    right image. `hmap` / `hmap_coarse` are the block-entropy maps of the right image's
    `levels` / `coarse_levels` when already computed. With `start` (row, col) the coarse
    stage is skipped and the fine search starts there, `radius` pixels either way (the
    block entropies are then computed around it only)."""
    p = params or MosaicParams()
    cy, cx = region.centre
    hr, wr = right.gray.shape
    offsets, box = cross_blocks(region.width, p)
    both = fine_offsets = offsets
    y_lo, y_hi = -both[:, 0].min(), hr - p.block - both[:, 0].max()
    x_lo, x_hi = -both[:, 1].min(), wr - p.block - both[:, 1].max()
    if start is None:
        # the perpendicular shift is at most max_shift of the height (the band was chosen on that premise)
        shift = int(np.ceil(p.max_shift * left.gray.shape[0]))
        y_lo, y_hi = max(y_lo, cy - shift), min(y_hi, cy + shift)
    else:
        r0 = int(radius if radius is not None else p.fine_radius)
        sy, sx = int(round(start[0])), int(round(start[1]))
        y_lo, y_hi = max(y_lo, sy - r0), min(y_hi, sy + r0)
        x_lo, x_hi = max(x_lo, sx - r0), min(x_hi, sx + r0)
    if y_lo > y_hi or x_lo > x_hi:
        raise MosaicError(f"{names[1]}: image too small ({wr}x{hr} px) for the {box[3]}x{box[2]}-px feature area "
                          f"of {names[0]}")
    fine_levels = right.levels
    origin = np.zeros(2, np.int64)  # hmap[i, j] is the block whose top-left is origin + (i, j)
    if hmap is None:
        if start is None:
            hmap = np.asarray(block_entropy(fine_levels, p.block, p.levels, backend), np.float64)
        else:
            origin = np.array([y_lo + both[:, 0].min(), x_lo + both[:, 1].min()])
            end = (y_hi + both[:, 0].max() + p.block, x_hi + both[:, 1].max() + p.block)
            hmap = np.asarray(block_entropy(fine_levels[origin[0]:end[0], origin[1]:end[1]], p.block, p.levels,
                                            backend), np.float64)
    local = fine_offsets - origin  # candidate + local indexes hmap

    def template_entropies(angle, offs, coarse):
        top, left_ = box[0], box[1]
        lv, nm = (left.coarse_levels, left.coarse_normalised) if coarse else (left.levels, left.normalised)
        if angle == 0:
            patch = lv[cy + top:cy + top + box[2], cx + left_:cx + left_ + box[3]]
        else:
            patch = quantise(_sample_box(nm, (cy, cx), box, angle), p.levels, p.soft_bins)
        dense = reference.block_entropy(patch, p.block, p.levels)
        return dense[offs[:, 0] - top, offs[:, 1] - left_]

    def grid(ys, xs):
        return np.stack(np.meshgrid(ys, xs, indexing="ij"), -1).reshape(-1, 2)

    if start is None:
        # coarse: a sub-window every coarse_step pixels, sequential detection. Candidates within
        # min_distinctness times the best keep their exact T, to measure how distinct the best is.
        if hmap_coarse is None:
            hmap_coarse = hmap if fine_levels is right.coarse_levels else np.asarray(
                block_entropy(right.coarse_levels, p.block, p.levels, backend), np.float64)
        hc = template_entropies(0.0, offsets, True)
        cand = grid(np.arange(y_lo, y_hi + 1, p.coarse_step), np.arange(x_lo, x_hi + 1, p.coarse_step))
        slack = max(1.0, p.min_distinctness, p.candidate_slack if p.candidates > 1 else 1.0)
        coarse = sequential_costs(hc, offsets, hmap_coarse, cand, p.thre, slack)
        if not np.isfinite(coarse).any():
            raise MosaicError(f"{names[0]} and {names[1]}: no overlap found (every sub-window passed the threshold)")
        ib = int(np.argmin(coarse))
        by, bx = cand[ib]
        far = np.abs(cand - cand[ib]).max(1) > max(p.block, 2 * p.coarse_step)
        second = coarse[far].min() if far.any() else np.inf
        distinct = float(second / coarse[ib]) if coarse[ib] > 0 else (np.inf if second > 0 else 1.0)
        starts = [(by, bx)]
        if p.candidates > 1:  # further local minima of T, a template quarter apart, within slack of the best
            apart = max(p.block, region.width // 4)
            for j in np.argsort(coarse, kind="stable")[1:]:
                if len(starts) >= p.candidates or coarse[j] > p.candidate_slack * coarse[ib]:
                    break
                if all(max(abs(cand[j][0] - y), abs(cand[j][1] - x)) > apart for y, x in starts):
                    starts.append(tuple(cand[j]))
    else:
        by, bx = min(max(sy, y_lo), y_hi), min(max(sx, x_lo), x_hi)
        distinct = np.inf  # not measured here
        starts = [(by, bx)]

    templates = {a: template_entropies(a, fine_offsets, False) for a in p.angles}

    def fine_search(by, bx):
        # fine: pixel by pixel in a (2r+1)^2 window at each angle; a best on the window's edge
        # means the minimum lies beyond it, so the window moves there (a few times at most)
        r = p.fine_radius
        best = (np.inf, 0.0, int(by), int(bx))
        for _ in range(4):
            y0, x0 = best[2], best[3]
            fine = grid(np.arange(max(y0 - r, y_lo), min(y0 + r, y_hi) + 1),
                        np.arange(max(x0 - r, x_lo), min(x0 + r, x_hi) + 1))
            for angle, ht in templates.items():
                costs = sequential_costs(ht, local, hmap, fine)
                i = int(np.argmin(costs))
                if costs[i] < best[0]:
                    best = (float(costs[i]), float(angle), int(fine[i][0]), int(fine[i][1]))
            on_edge = (best[2] in (y0 - r, y0 + r) and y_lo < best[2] < y_hi) or \
                      (best[3] in (x0 - r, x0 + r) and x_lo < best[3] < x_hi)
            if not on_edge:
                break
        cost, angle, my, mx = best

        # sub-pixel: the vertex of the parabola through T at the best and its two neighbours, per axis
        ht = templates[angle]
        sub = [float(my), float(mx)]
        for axis, (lo, hi) in enumerate([(y_lo, y_hi), (x_lo, x_hi)]):
            pos = (my, mx)[axis]
            if lo < pos < hi:
                step = np.zeros(2, np.int64)
                step[axis] = 1
                c_minus, c_plus = sequential_costs(ht, local, hmap,
                                                   np.array([(my, mx) - step, (my, mx) + step]), np.inf)
                curv = c_minus - 2.0 * cost + c_plus
                if curv > 0:
                    sub[axis] += float(np.clip(0.5 * (c_minus - c_plus) / curv, -0.5, 0.5))
        return sub[0], sub[1], angle, cost

    found = [fine_search(y, x) for y, x in starts]
    alts = [EntropyMatch(*f, distinct) for f in found[1:]]
    return EntropyMatch(*found[0], distinct, alts)
