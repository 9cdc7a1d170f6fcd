"""3.3.2 the feature region: fuzzy C-means (Eq. 5-6) of the LED in the search band, the
template width of Eq. 7, and the isotropy that skips one-directional regions."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from .params import MosaicError, MosaicParams
from .preprocess import Prepared, edge_map, led


def fcm_memberships(values: np.ndarray, centres: np.ndarray, b: float) -> np.ndarray:
    """Eq. 5: U_k(D) = |D - C_k|^(-2/(b-1)) / sum_m |D - C_m|^(-2/(b-1)), shape (n, K).
    A value equal to one or more centres belongs to them alone (in equal shares)."""
    d = np.abs(np.asarray(values, np.float64)[:, None] - np.asarray(centres, np.float64)[None, :])
    zero = d == 0
    p = 2.0 / (b - 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        # U_k = 1 / sum_m (d_k / d_m)^p, stable when the d are tiny
        ratio = (d[:, :, None] / d[:, None, :]) ** p
        u = 1.0 / ratio.sum(2)
    hit = zero.any(1)
    u[hit] = zero[hit] / zero[hit].sum(1, keepdims=True)
    return u


@dataclass
class FcmResult:
    centres: np.ndarray    # (3,) in the order they were started: max, mean, min
    labels: np.ndarray     # (n,) class with the largest membership
    iterations: int
    converged: bool


def fuzzy_cmeans(values: np.ndarray, b: float = 2.0, tol: float = 1e-9, max_iter: int = 1000) -> FcmResult:
    """Fuzzy C-means of 3.3.2 into 3 classes: centres started at max, mean, min (step 1),
    memberships by Eq. 5 (step 2), centres by Eq. 6 (step 3), repeated until no centre
    moves by more than tol * (max - min) (step 4); each value takes its largest membership.

    Eq. 6 sums over points, so points with equal values contribute equally: the
    iteration runs over the distinct values weighted by their counts (LED takes
    at most (2A+1)^2 + 1 values), which gives the same centres far faster."""
    v = np.asarray(values, np.float64).ravel()
    if v.size == 0:
        raise ValueError("fuzzy_cmeans needs at least one value")
    if b <= 1:
        raise ValueError(f"the fuzzifier b must be > 1, got {b}")
    uniq, inverse, counts = np.unique(v, return_inverse=True, return_counts=True)
    c = np.array([v.max(), v.mean(), v.min()])
    scale = max(v.max() - v.min(), np.finfo(float).tiny)
    converged = False
    it = 0
    for it in range(1, max_iter + 1):
        u = fcm_memberships(uniq, c, b)
        wgt = u ** b * counts[:, None]
        new = (wgt * uniq[:, None]).sum(0) / np.maximum(wgt.sum(0), np.finfo(float).tiny)
        moved = np.abs(new - c).max()
        c = new
        if moved <= tol * scale:
            converged = True
            break
    labels = fcm_memberships(uniq, c, b).argmax(1)[inverse]
    return FcmResult(c, labels, it, converged)


def _feature_geometry(width: int, height: int, p: MosaicParams):
    """The initial template width and the ranges (inclusive) of valid feature centres in the
    left image: the template inside the last min_overlap of the width, the cross-shaped area
    at least max_shift of the height from the top and the bottom."""
    tw0 = int(round(max(width / p.template_div, 4 * p.block) / p.block)) * p.block
    band_left = int(np.floor(width * (1.0 - p.min_overlap)))
    margin = int(np.ceil(height * p.max_shift))
    half = tw0 // 2
    cols = (band_left + half, width - (tw0 - half))
    rows = (margin + half, height - margin - (tw0 - half))
    return tw0, cols, rows


@dataclass
class FeatureRegion:
    """The benchmark template of 3.3.2: its centre (row, col) in the left image and width."""
    centre: tuple
    width: int
    led: np.ndarray             # D of Eq. 4 over the whole left image
    fcm: FcmResult              # the clustering of the band's LED values
    centres: np.ndarray         # (3,) FCM centres sorted high, medium, low


def template_width(width: float, led_centre: float, c: float) -> float:
    """Eq. 7: templatewidth = templatewidth * (C / D(i, j)) when D(i, j) < C, else unchanged.
    C is read as the centre of the high LED class (see the module notes)."""
    if 0 < led_centre < c:
        return width * (c / led_centre)
    return float(width)


def find_feature_regions(left: Prepared, params: MosaicParams | None = None, backend="numpy",
                         name: str = "left", count: int = 1) -> list[FeatureRegion]:
    """3.3.2: edges, LED (Eq. 4), FCM (Eq. 5-6) over the band where the overlap must be, the
    centre of the feature region and the template width (Eq. 7). The first region is the
    paper's; the next ones (up to `count`) are the next-best centres at least a template
    width away from those before, for when a match is rejected."""
    p = params or MosaicParams()
    hl, wl = left.gray.shape
    tw0, (c0, c1), (r0, r1) = _feature_geometry(wl, hl, p)
    if c0 > c1 or r0 > r1:
        raise MosaicError(f"{name}: image too small ({wl}x{hl} px): a {tw0}-px template must fit in the last "
                          f"{p.min_overlap:.0%} of its width and {p.max_shift:.0%} from top and bottom")
    edges = edge_map(left.smoothed, (slice(r0, r1 + 1), slice(c0, c1 + 1)))
    dmap = np.asarray(led(edges.astype(np.float32), p.led_half, backend), np.float64)
    band = dmap[r0:r1 + 1, c0:c1 + 1]
    if band.max() <= 0:
        raise MosaicError(f"{name}: no edges in the part that must overlap the next image: no feature region")
    fcm = fuzzy_cmeans(band, p.fcm_b, p.fcm_tol, p.fcm_max_iter)
    order = np.argsort(-fcm.centres)  # high, medium, low
    keep = np.zeros(dmap.shape)
    keep[r0:r1 + 1, c0:c1 + 1] = (fcm.labels != order[2]).reshape(band.shape)
    # "the average of the two kept classes is recalculated": their LED, averaged over the window
    score = np.asarray(led(dmap * keep, p.led_half, backend), np.float64)
    score_band = np.where(keep[r0:r1 + 1, c0:c1 + 1] > 0, score[r0:r1 + 1, c0:c1 + 1], -np.inf)
    c_high = fcm.centres[order[0]]
    band_left = int(np.floor(wl * (1.0 - p.min_overlap)))
    margin = int(np.ceil(hl * p.max_shift))
    regions = []
    yy, xx = np.mgrid[r0:r1 + 1, c0:c1 + 1]
    while len(regions) < count and np.isfinite(score_band).any():
        iy, ix = np.unravel_index(int(np.argmax(score_band)), score_band.shape)
        cy, cx = r0 + iy, c0 + ix
        tw = template_width(tw0, dmap[cy, cx], c_high)
        room = 2 * min(cx - band_left, wl - 1 - cx, cy - margin, hl - 1 - margin - cy) + 1
        tw = max(tw0, int(min(tw, room) // p.block) * p.block)
        regions.append(FeatureRegion((int(cy), int(cx)), int(tw), dmap, fcm, fcm.centres[order]))
        score_band[np.maximum(np.abs(yy - cy), np.abs(xx - cx)) < tw0] = -np.inf
    return regions


def find_feature_region(left: Prepared, params: MosaicParams | None = None, backend="numpy",
                        name: str = "left") -> FeatureRegion:
    """The paper's feature region (the first of `find_feature_regions`)."""
    return find_feature_regions(left, params, backend, name, 1)[0]


def isotropy(image: np.ndarray, centre, width: int) -> float:
    """Smaller over larger eigenvalue of the gradient structure tensor of the width x width
    window at centre: near 0 for a straight edge or parallel bands, which match themselves
    anywhere along their length (the aperture problem), up to 1 for corners and texture."""
    h = width // 2
    y0, x0 = max(centre[0] - h, 0), max(centre[1] - h, 0)
    win = np.asarray(image, np.float64)[y0:centre[0] - h + width, x0:centre[1] - h + width]
    if min(win.shape) < 3:
        return 0.0
    gy, gx = ndimage.sobel(win, 0), ndimage.sobel(win, 1)
    a, b, c = (gx * gx).sum(), (gx * gy).sum(), (gy * gy).sum()
    root = np.sqrt(((a - c) / 2.0) ** 2 + b * b)
    big, small = (a + c) / 2.0 + root, (a + c) / 2.0 - root
    return float(small / big) if big > 0 else 0.0
