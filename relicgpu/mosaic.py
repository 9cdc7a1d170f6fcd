"""Image mosaic of overlapping relic photographs (paper sections 3.3 and 3.4).

`stitch(images)` places each image of a left-to-right (or, `vertical=True`, top-to-
bottom) sequence against the one before it and returns a `Mosaic`;
`relicgpu mosaic LEFT RIGHT [MORE ...] -o OUT.png` is the command line. For one pair
(left L, right R):

1. Preprocess (3.3.1): 3x3 median filter, then the local normalisation of Eq. 1-3.
2. Edges (3.3.1): Sobel gradient magnitude, binarised at Otsu's threshold.
3. LED (Eq. 4): D = box mean of the binary edges over a (2A+1)^2 window (a kernel).
4. Fuzzy C-means (Eq. 5-6) of the LED values of the search band into 3 classes,
   centres started at max, mean, min, iterated until the centres stop moving.
5. Feature centre: the low class is dropped; the LED of the two kept classes is
   averaged again over the (2A+1)^2 window and the point with the largest
   average is the centre of the feature region.
6. Template width by Eq. 7, starting at width / 8.
7. Local entropy (Eq. 8) of the blocks of the template's cross-shaped area and,
   for every block position, of R (a kernel); coarse matching every `coarse_step`
   pixels with sequential early stop, then fine matching pixel by pixel in a 5x5
   search, at a few small rotations of the template.
8. Verification (an addition): each match found in step 7 (the best and the next
   coarse minima) is a placement of R; the band-passed correlation over the whole
   overlap it implies ranks them, the best are refined there, and one is accepted
   when it beats every other placement; else the next feature region is tried.
   Then the images are composited with feathered blending over the overlap.

Readings where the paper is ambiguous or would not work as printed, and additions
(each is named again where it is implemented). The defaults were chosen on pairs of
scripts/bench_mosaic.py with seeds 1-4; the benchmark reports seeds 0 and 5-7.

- Eq. 1 with its sign branches is a linear map, G = M_i^d + sqrt(VAR_i^d/VAR_i) (I - M_i);
  M_i, VAR_i are the mean and variance over a w x w window; Eq. 2's M^d and M_0^d
  are one constant (`norm_mean`) and Eq. 3's Q_2 is alpha_2. With the default
  alpha_1 = alpha_2 = 0 the result is exactly invariant to a gray-level change
  a*I + b, which is the point of the step. VAR_i is floored at (k sigma)^2, sigma
  the image's noise (Immerkaer's estimate), so flat regions do not blow sensor
  noise up to full contrast; the floor scales with a gray-level change too.
- Edges are detected on the median-filtered image, not on the normalised one:
  local normalisation gives every region the same contrast, so edge density
  after it no longer tells textured regions from flat noisy ones. Otsu's
  threshold is taken over the search band (over the whole image one bright
  border, as in a fundus photograph, hides every other edge).
- Eq. 8 as printed, H = -sum P(i)(P(i) - 1) = 1 - sum P(i)^2, is the quadratic
  (Gini-Simpson) entropy, not Shannon's; it is used as printed. P is taken over
  `levels` gray levels of the normalised image (with 256 levels a 36-pixel block
  has nearly all P(i) = 1/36 and H says nothing), each pixel split linearly
  between its two nearest levels (`soft_bins`): with hard bins a pixel near a
  bin edge flips with the least noise and H jumps.
- "The benchmark template is divided into blocks": blocks of `block` pixels
  every `block_stride` pixels, i.e. overlapping (stride = block gives the paper's
  disjoint blocks; overlapping ones average the noise down: 92.9% of the 112
  tuning pairs within 1 px against 87.5% with disjoint blocks).
- "Recalculate the average of the two classes with larger LED": the mean over
  the (2A+1)^2 window of D times the indicator of the two kept classes.
- Eq. 7's "average C": the centre of the high class (the mean LED of all points
  is below almost any point the step can pick, so Eq. 7 would never act).
- The search band: the feature region must lie where the images overlap, so it
  is searched in the last `min_overlap` of L's width and away from the top and
  bottom by `max_shift` of the height; on the same premise R is searched only
  within `max_shift` of the height up or down. The template starts at width / 8
  but at least 4 blocks wide, and Eq. 7 may not grow it past the band.
- The threshold Thre of the sequential detection: by default the full cost of
  the candidate that leads after the first quarter of the blocks (times
  `min_distinctness`). It bounds the minimum from above, so the early stop prunes
  only candidates that cannot win and the answer is that of the exhaustive
  search. A fixed `thre` can be given instead, as in the paper.
- The cross-shaped area: two overlapping bars of blocks through the centre, each
  as long as the template and `cross_fraction` of it thick, so the corners, which
  a rotation moves most, are left out (the whole square matched 105 of the 112
  tuning pairs, the cross 104: no real difference, so the paper's cross stays). The fine search also tries the template
  rotated by `angles` degrees, so offset and a small rotation come out together,
  and ends with a parabola fit of T through the best pixel and its neighbours
  (sub-pixel).
- One variance floor per pair: VAR_i is floored at (k sigma)^2 with sigma the
  larger of the two images' noise estimates. With each image's own floor, a faint
  texture (cell, moon, retina backgrounds) lying under the noisier image's floor
  was stretched less there than in the other image, so its block entropies
  differed everywhere and the true place had 1.2-2x the smallest T. Tuning pairs
  (seeds 1-4, 240 pairs): 94.2% -> 95.8% within 1 px from this step alone.
- A feature region whose gradient is nearly one-directional (`min_isotropy`: a
  straight edge or parallel bands match themselves anywhere along their length)
  is skipped. Up to `retries` further feature regions (the next-best centres, a
  template width apart) may be tried before "no overlap found".
- Hierarchical search (3.4 names it; an addition in how): the coarse stage runs on
  the levels of the median-filtered image blurred by a Gaussian of `coarse_sigma`
  px before Eq. 1-3, the fine stage on those of the median-filtered image itself
  (`fine_sigma` = 0). At noise sigma 2-8 the 6x6-block entropies of the unblurred
  image are mostly noise on low-contrast photographs (cell, moon, retina): there
  the true place often had a larger T than some far one. Tuning pairs (seeds 1-4,
  240 pairs): 90.0% -> 93.8% within 1 px from this step.
- Verification over the whole overlap (an addition; the paper has no check):
  up to `candidates` coarse minima within `candidate_slack` of the best T go to
  the fine search, and each result is a placement (right point, angle). Its
  score is the normalised correlation of band-passed images (difference of
  Gaussians `corr_bandpass`, so sky gradients and vignetting do not correlate)
  over every pixel the two images share under it, away from the borders. The
  `refine_count` best of a region are refined from there by Gauss-Newton on
  L = a R(q(p)) + b over the right point, the angle and the gain and bias
  (`refine_placement`): the entropy fine stage leaves 1-5 px and up to 3 deg of
  error on noisy low-contrast areas, and the refinement converges from there to
  about 0.1 px. A placement is accepted when its correlation is at least
  `min_correlation`, beats every placement more than `distinct_px` away by
  `min_margin`, and `votes` regions refined onto it (the vote; the last region
  tried needs no second one). Why: a template of a few thousand pixels is
  ambiguous on repeated or one-directional structure (rocket, brick) and on
  faint texture, the whole overlap (tens of thousands of pixels) is not. On the
  tuning pairs the placement with the best refined correlation was within 1 px
  in 240 of 240, by a margin of at least 0.117 over any other; wrong placements
  refined to at most 0.94 (rocket, a few px off along its structure), true ones
  to 0.79-0.99. Tuning pairs: 95.8% -> 100% within 1 px.
- The placement is given at the feature point; with a rotation there is no single
  translation, so the composite rotates the right image about that point.
- Large photographs (an addition): images over `max_size` pixels are registered
  on copies shrunk by an integer factor f, then the fine search alone runs at full
  resolution, f + 2 pixels either way, on crops around the two areas, and the
  refinement on those crops (a 2800 x 2000 pair: about 1 s instead of minutes).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from scipy import ndimage

from .backends import BackendError, resolve
from .backends import numpy as reference
from .io.fragment import FragmentError


class MosaicError(FragmentError):
    """A mosaic that cannot be made from these images (the message names the images and the fault)."""


@dataclass(frozen=True)
class MosaicParams:
    """Parameters of the mosaic. Defaults were chosen on pairs cut with seeds 1-4 of
    scripts/bench_mosaic.py; the benchmark reports on seeds 0 and 5-7."""
    median: int = 3                # 3.3.1: median filter size
    norm_window: int = 31          # w of Eq. 1-3
    norm_mean: float = 128.0       # M^d = M_0^d of Eq. 2
    norm_var: float = 64.0 ** 2    # VAR_0^d of Eq. 3
    alpha1: float = 0.0            # Eq. 2
    alpha2: float = 0.0            # Eq. 3
    norm_var_floor: float = 1.0    # VAR_i floor (gray levels^2) ...
    noise_floor_k: float = 2.0     # ... raised to (k * the image's noise sigma)^2
    led_half: int = 8              # A of Eq. 4
    fcm_b: float = 2.0             # fuzzifier b of Eq. 5-6
    fcm_tol: float = 1e-9          # convergence: no centre moves more than tol * (max D - min D)
    fcm_max_iter: int = 1000
    template_div: float = 8.0      # initial template width = image width / template_div
    block: int = 6                 # entropy block size (pixels)
    block_stride: int = 3          # spacing of the blocks in the template (= block: disjoint blocks)
    levels: int = 6                # gray levels for Eq. 8 (<= 64)
    soft_bins: bool = True         # split each pixel between its two nearest levels
    coarse_step: int = 2           # 3.4: a sub-window every 2 or 3 pixels
    fine_radius: int = 2           # 3.4: 5x5 fine search
    cross_fraction: float = 0.8    # thickness of each bar of the cross, as a fraction of the template
    angles: tuple = (-1.5, -0.75, 0.0, 0.75, 1.5)  # rotations (degrees) tried in the fine search
    thre: float | None = None      # sequential-detection threshold; None: exact (see the module notes)
    min_overlap: float = 0.2       # the overlap is at least this fraction of the left image's width
    max_shift: float = 0.1         # perpendicular shift between neighbours, fraction of the height
    min_correlation: float = 0.5   # whole-overlap correlation (band-passed images) a placement needs ...
    min_margin: float = 0.05       # ... and by how much it must beat any placement more than distinct_px away
    distinct_px: float = 8.0       # placements closer than this (px, at either feature centre) are one
    votes: int = 2                 # regions that must refine onto a placement before the last region is tried
    refine_count: int = 3          # per region, the placements with the best raw correlation refined ...
    refine_floor: float = 0.2      # ... when it is at least this
    refine_iterations: int = 20    # Gauss-Newton steps of the refinement at most
    overlap_step: int = 3          # the overlap correlation samples every overlap_step-th pixel ...
    min_overlap_samples: int = 200  # ... and needs this many
    min_distinctness: float = 1.1  # coarse slack: candidates within this factor of the best T keep their exact T
    min_isotropy: float = 0.1      # feature regions with a less isotropic gradient are skipped
    retries: int = 4               # further feature regions tried until a placement is accepted
    max_size: int = 1000           # larger images are registered shrunk, then refined at full size
    coarse_sigma: float = 2.0      # hierarchical search: Gaussian (px) before Eq. 1-3 for the coarse stage ...
    fine_sigma: float = 0.0        # ... and for the fine stage (0: the median-filtered image as is)
    corr_bandpass: tuple = (1.5, 8.0)  # the correlation check compares G(s1) - G(s2) of the median-filtered images
    candidates: int = 8            # coarse minima of T taken to the fine search (placements) ...
    candidate_slack: float = 1.3   # ... those with T within this factor of the best


@dataclass
class PairMatch:
    """Where `right` sits against `left`: right pixel p lies at left_point + R(angle)(p - right_point)."""
    left_point: np.ndarray         # (2,) row, col of the feature centre in the left image
    right_point: np.ndarray        # (2,) where it was found in the right image
    angle: float                   # degrees
    offset: np.ndarray             # (2,) left_point - right_point: the right origin in left coordinates
    template_width: int
    cost: float                    # T at the match: summed |entropy difference| over the cross blocks
    correlation: float             # band-passed correlation over the whole overlap (the check)
    distinctness: float            # T of the best coarse match elsewhere over T of this one (reported)
    region_rank: int               # 0: the paper's feature region; k: the k-th next
    fcm_centres: np.ndarray        # (3,) high, medium, low
    fcm_iterations: int
    margin: float = np.inf         # correlation over that of the best placement more than distinct_px away
    entropy_point: np.ndarray = None  # (2,) where the entropy matching put the feature centre, before refinement
    entropy_rank: int = 0          # 0: the entropy match with the smallest coarse T was accepted; k: the k-th next
    timings: dict = field(default_factory=dict)


@dataclass
class Mosaic:
    """offsets[i] is the (row, col) of image i's origin in `image`; image i is rotated by angles[i] degrees about it."""
    offsets: np.ndarray            # (N, 2) float
    image: np.ndarray
    angles: np.ndarray = None      # (N,) degrees
    matches: list = field(default_factory=list)  # PairMatch of (i, i+1)


# --- kernels: LED box mean and block entropy (on the backend) ------------------

def led(image: np.ndarray, half: int, backend="numpy") -> np.ndarray:
    """Local edge density (Eq. 4): the mean of `image` over the (2A+1)^2 window
    centred on each pixel, pixels outside the image counting as 0. Same shape as image."""
    be = resolve(backend)
    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError(f"led needs a 2-D image, got shape {img.shape}")
    return be.led(img, half)


def block_entropy(levels: np.ndarray, block: int, n_levels: int, backend="numpy") -> np.ndarray:
    """Local entropy (Eq. 8) of every block x block block of a quantised image (levels
    in [0, n_levels-1], n_levels <= 64; real levels are split linearly between the two
    nearest bins); out[y, x] is the block whose top-left is (y, x), shape (H-block+1, W-block+1)."""
    be = resolve(backend)
    q = np.asarray(levels)
    if q.ndim != 2 or q.shape[0] < block or q.shape[1] < block:
        raise ValueError(f"block_entropy needs a 2-D image of at least {block}x{block}, got shape {q.shape}")
    if not 1 <= n_levels <= 64:
        raise ValueError(f"n_levels must be in 1..64, got {n_levels}")
    if q.size and not (q.min() >= 0 and q.max() <= n_levels - 1):
        raise ValueError(f"levels must lie in [0, {n_levels - 1}], got [{q.min()}, {q.max()}]")
    return be.block_entropy(q, block, n_levels)


# --- 3.3.1 preprocessing -------------------------------------------------------

def noise_sigma(gray: np.ndarray) -> float:
    """Standard deviation of white noise in an image (Immerkaer 1996): the mean absolute
    response to the Laplacian-difference mask N, times sqrt(pi/2) / 6."""
    img = np.asarray(gray, np.float64)
    if min(img.shape) < 3:
        return 0.0
    mask = np.array([[1.0, -2.0, 1.0], [-2.0, 4.0, -2.0], [1.0, -2.0, 1.0]])
    resp = ndimage.correlate(img, mask, mode="reflect")[1:-1, 1:-1]
    return float(np.sqrt(np.pi / 2.0) / 6.0 * np.abs(resp).mean())


def median3(gray: np.ndarray, size: int = 3) -> np.ndarray:
    """The 3x3 median filter of 3.3.1, the border pixel repeated outside the image."""
    img = np.asarray(gray, np.float64)
    if size in (3, 5):
        try:  # OpenCV's float32 median is some 30x faster than scipy's; same values
            import cv2
            return cv2.medianBlur(img.astype(np.float32), size).astype(np.float64)
        except ImportError:
            pass
    return ndimage.median_filter(img, size=size, mode="nearest")


def local_normalise(gray: np.ndarray, window: int = 31, mean0: float = 128.0, var0: float = 64.0 ** 2,
                    alpha1: float = 0.0, alpha2: float = 0.0, var_floor: float = 1.0) -> np.ndarray:
    """Eq. 1-3. M_i, VAR_i: mean and variance over the window x window neighbourhood (reflected
    at the border); M_i^d = M0 + alpha1 (M_i - M0) (Eq. 2, reading M^d = M_0^d = mean0);
    VAR_i^d = VAR0 + alpha2 (VAR_i - VAR0) (Eq. 3);
    G = M_i^d +/- sqrt(VAR_i^d (I - M_i)^2 / VAR_i), + where I > M_i (Eq. 1).
    VAR_i is floored at var_floor (a flat patch would otherwise divide by ~0)."""
    img = np.asarray(gray, np.float64)
    m = ndimage.uniform_filter(img, window, mode="reflect")
    var = ndimage.uniform_filter(img * img, window, mode="reflect") - m * m
    var = np.maximum(var, var_floor)
    m_d = mean0 + alpha1 * (m - mean0)
    var_d = var0 + alpha2 * (var - var0)
    dev = np.sqrt(var_d * (img - m) ** 2 / var)
    return np.where(img > m, m_d + dev, m_d - dev)


def edge_map(gray: np.ndarray, region=None) -> np.ndarray:
    """Edge detection and binarisation (3.3.1): Sobel gradient magnitude above Otsu's threshold."""
    from skimage.filters import threshold_otsu
    img = np.asarray(gray, np.float64)
    mag = np.hypot(ndimage.sobel(img, 0, mode="reflect"), ndimage.sobel(img, 1, mode="reflect"))
    ref = mag if region is None else mag[region]
    if not np.any(ref > ref.min()):
        return np.zeros(img.shape, bool)
    return mag > threshold_otsu(ref)


def quantise(normalised: np.ndarray, levels: int, soft: bool = False) -> np.ndarray:
    """Gray levels 0..levels-1 of a normalised image (values clipped to [0, 256))."""
    g = np.clip(np.asarray(normalised, np.float64), 0.0, 255.999)
    if soft:
        return np.clip(g * (levels / 256.0) - 0.5, 0.0, levels - 1.0)
    return (g * (levels / 256.0)).astype(np.int32)


# --- 3.3.2 fuzzy C-means --------------------------------------------------------

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


# --- 3.4 local entropy matching ---------------------------------------------------

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


def _ncc(a: np.ndarray, b: np.ndarray) -> float:
    a = a - a.mean()
    b = b - b.mean()
    den = np.sqrt((a * a).sum() * (b * b).sum())
    return float((a * b).sum() / den) if den > 0 else 0.0


def to_gray(image: np.ndarray) -> np.ndarray:
    """Luminance in [0, 255] as float64 from a gray, RGB or RGBA array (uint8, uint16 or float in [0, 1])."""
    img = np.asarray(image)
    if img.dtype == np.uint8:
        scale = 1.0
    elif img.dtype == np.uint16:
        scale = 255.0 / 65535.0
    elif img.dtype.kind == "f":
        scale = 255.0 if img.size and float(np.nanmax(img)) <= 1.0 else 1.0
    else:
        scale = 1.0
    f = img.astype(np.float64) * scale
    if f.ndim == 3:
        f = f[..., :3] @ np.array([0.299, 0.587, 0.114]) if f.shape[2] >= 3 else f[..., 0]
    return f


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


@dataclass
class FeatureRegion:
    """The benchmark template of 3.3.2: its centre (row, col) in the left image and width."""
    centre: tuple
    width: int
    led: np.ndarray             # D of Eq. 4 over the whole left image
    fcm: FcmResult              # the clustering of the band's LED values
    centres: np.ndarray         # (3,) FCM centres sorted high, medium, low


@dataclass
class Prepared:
    """One image after 3.3.1: gray, median-filtered, normalised (Eq. 1-3) and quantised; the
    coarse_* pair is the same after a Gaussian of `coarse_sigma` (the coarse search's input),
    `denoised` that Gaussian's input blurred, `bandpass` the image the correlation check uses."""
    gray: np.ndarray
    smoothed: np.ndarray
    normalised: np.ndarray
    levels: np.ndarray
    coarse_normalised: np.ndarray = None
    coarse_levels: np.ndarray = None
    denoised: np.ndarray = None
    bandpass: np.ndarray = None
    border: float = 0.0   # px at the border where `bandpass` is unreliable

    def __post_init__(self):
        if self.coarse_normalised is None:
            self.coarse_normalised, self.coarse_levels = self.normalised, self.levels
        if self.denoised is None:
            self.denoised = self.smoothed


def prepare_image(image: np.ndarray, params: MosaicParams | None = None, noise: float | None = None) -> Prepared:
    """3.3.1 for one image. `noise` is the noise sigma that sets the variance floor of Eq. 1-3
    (None: this image's own estimate); register_pair gives both images of a pair the larger one."""
    p = params or MosaicParams()
    gray = to_gray(image)
    smoothed = median3(gray, p.median)
    floor = p.norm_var_floor
    if p.noise_floor_k > 0:
        floor = max(floor, (p.noise_floor_k * (noise_sigma(gray) if noise is None else noise)) ** 2)

    def normalise(img):
        n = local_normalise(img, p.norm_window, p.norm_mean, p.norm_var, p.alpha1, p.alpha2, floor)
        return n, quantise(n, p.levels, p.soft_bins)

    normalised, levels = normalise(ndimage.gaussian_filter(smoothed, p.fine_sigma, mode="nearest")
                                   if p.fine_sigma > 0 else smoothed)
    if p.coarse_sigma > 0:
        denoised = ndimage.gaussian_filter(smoothed, p.coarse_sigma, mode="nearest")
        coarse_normalised, coarse_levels = normalise(denoised)
    else:
        denoised, coarse_normalised, coarse_levels = smoothed, normalised, levels
    bandpass = None
    if p.corr_bandpass:
        bandpass = (ndimage.gaussian_filter(smoothed, p.corr_bandpass[0], mode="nearest")
                    - ndimage.gaussian_filter(smoothed, p.corr_bandpass[1], mode="nearest"))
    border = 1.5 * float(p.corr_bandpass[1]) if p.corr_bandpass else 0.0
    return Prepared(gray, smoothed, normalised, levels, coarse_normalised, coarse_levels, denoised, bandpass, border)


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


def _block_mean(gray: np.ndarray, factor: int) -> np.ndarray:
    """Mean of factor x factor blocks (the ragged last rows and columns dropped)."""
    h, w = gray.shape[0] // factor * factor, gray.shape[1] // factor * factor
    return gray[:h, :w].reshape(h // factor, factor, w // factor, factor).mean((1, 3))


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


# --- stitching -------------------------------------------------------------------

def _rot(angle_deg: float) -> np.ndarray:
    """R(angle) acting on (row, col) vectors, as used by _sample_box."""
    a = np.deg2rad(angle_deg)
    return np.array([[np.cos(a), np.sin(a)], [-np.sin(a), np.cos(a)]])


def composite(images: list, transforms: list) -> tuple[np.ndarray, np.ndarray]:
    """Blend images placed by (A, t) (image pixel p lands at A p + t, (row, col)) into one
    canvas, each weighted by its distance to its own border (feathering over the overlaps).
    Returns the canvas (dtype of the inputs) and the canvas position of each image origin."""
    colour = any(np.asarray(im).ndim == 3 for im in images)
    arrs = []
    for im in images:
        a = np.asarray(im)
        if a.ndim == 3 and a.shape[2] == 4:
            a = a[..., :3]
        if colour and a.ndim == 2:
            a = np.repeat(a[..., None], 3, 2)
        arrs.append(a)
    dtype = arrs[0].dtype
    corners = []
    for a, (m, t) in zip(arrs, transforms):
        h, w = a.shape[:2]
        c = np.array([[0, 0], [0, w - 1], [h - 1, 0], [h - 1, w - 1]], np.float64)
        corners.append(c @ m.T + t)
    allc = np.concatenate(corners)
    lo = np.floor(allc.min(0) + 1e-6)  # an origin at -4.0000001 is at -4
    size = (np.ceil(allc.max(0) - 1e-6) - lo + 1).astype(int)
    shape = (size[0], size[1]) + ((3,) if colour else ())
    acc = np.zeros(shape)
    wsum = np.zeros(tuple(size))
    for a, (m, t), c in zip(arrs, transforms, corners):
        h, w = a.shape[:2]
        t = t - lo
        y0, x0 = np.maximum(np.floor(c.min(0) - lo + 1e-6), 0).astype(int)
        y1, x1 = np.minimum(np.ceil(c.max(0) - lo - 1e-6).astype(int) + 1, size)
        yy, xx = np.mgrid[y0:y1, x0:x1].astype(np.float64)
        inv = np.linalg.inv(m)
        sy = inv[0, 0] * (yy - t[0]) + inv[0, 1] * (xx - t[1])
        sx = inv[1, 0] * (yy - t[0]) + inv[1, 1] * (xx - t[1])
        weight = np.minimum.reduce([sy + 0.5, h - 0.5 - sy, sx + 0.5, w - 0.5 - sx])
        weight = np.clip(weight, 0.0, None)
        chans = [a] if a.ndim == 2 else [a[..., k] for k in range(a.shape[2])]
        vals = [ndimage.map_coordinates(ch.astype(np.float64), [sy, sx], order=1, mode="nearest") for ch in chans]
        v = vals[0] if a.ndim == 2 else np.stack(vals, -1)
        wv = weight if a.ndim == 2 else weight[..., None]
        acc[y0:y1, x0:x1] += wv * v
        wsum[y0:y1, x0:x1] += weight
    out = acc / np.maximum(wsum if not colour else wsum[..., None], 1e-12)
    if np.issubdtype(dtype, np.integer):
        info = np.iinfo(dtype)
        out = np.clip(np.rint(out), info.min, info.max).astype(dtype)
    origins = np.array([t - lo for _, t in transforms])
    return out, origins


def stitch(images, backend="auto", params: MosaicParams | None = None, vertical: bool = False,
           progress: bool = False) -> Mosaic:
    """Stitch a left-to-right sequence of overlapping photographs (arrays or paths);
    `vertical=True` for a top-to-bottom one. Each image is placed against the one before it."""
    be = resolve(backend)
    p = params or MosaicParams()
    names, arrays = [], []
    for i, im in enumerate(images):
        if isinstance(im, (str, Path)):
            names.append(str(im))
            arrays.append(load_image(im))
        else:
            names.append(f"image {i}")
            arrays.append(np.asarray(im))
    if len(arrays) < 2:
        raise MosaicError("a mosaic needs at least two images")
    for n, a in zip(names, arrays):
        if a.ndim not in (2, 3) or min(a.shape[:2]) < 1:
            raise MosaicError(f"{n}: not an image (array of shape {a.shape})")
    work = [np.swapaxes(a, 0, 1) if vertical else a for a in arrays]
    pairs = range(len(work) - 1)
    if progress:
        from tqdm import tqdm
        pairs = tqdm(pairs, desc="mosaic", unit="pair", leave=False)
    matches = []
    m, t = np.eye(2), np.zeros(2)
    transforms = [(m, t)]
    for i in pairs:
        pm = register_pair(work[i], work[i + 1], p, be, names=(names[i], names[i + 1]))
        matches.append(pm)
        r = _rot(pm.angle)
        # right pixel q -> left frame: left_point + R (q - right_point) -> mosaic: m(.) + t
        t = m @ (pm.left_point - r @ pm.right_point) + t
        m = m @ r
        transforms.append((m, t))
    canvas, origins = composite(work, transforms)
    angles = np.array([np.rad2deg(np.arctan2(mm[0, 1], mm[0, 0])) for mm, _ in transforms])
    if vertical:
        canvas = np.swapaxes(canvas, 0, 1)
        origins = origins[:, ::-1]
        angles = -angles
    return Mosaic(origins, canvas, angles, matches)


# --- files and command line --------------------------------------------------------

def load_image(path) -> np.ndarray:
    """An image file as uint8/uint16 gray or RGB; faults become MosaicError naming the file."""
    from PIL import Image, UnidentifiedImageError
    path = Path(path)
    if not path.exists():
        raise MosaicError(f"{path}: no such file")
    if path.is_dir():
        raise MosaicError(f"{path}: is a directory, not an image")
    try:
        with Image.open(path) as im:
            im.load()
            if im.mode in ("I;16", "I;16B", "I;16L"):
                arr = np.asarray(im, np.uint16)
            elif im.mode in ("L", "RGB"):
                arr = np.asarray(im)
            elif im.mode in ("1", "LA", "I", "F"):
                arr = np.asarray(im.convert("L"))
            else:
                arr = np.asarray(im.convert("RGB"))
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as exc:
        raise MosaicError(f"{path}: cannot read as an image ({exc})") from None
    if min(arr.shape[:2]) < 1:
        raise MosaicError(f"{path}: empty image")
    return arr


_FORMATS = {".png": "PNG", ".jpg": "JPEG", ".jpeg": "JPEG", ".tif": "TIFF", ".tiff": "TIFF", ".bmp": "BMP",
            ".webp": "WEBP"}


def save_image(path, image: np.ndarray) -> None:
    """Write an image atomically; the format comes from the suffix."""
    import io as _io
    from PIL import Image
    from .io.files import atomic_write_bytes
    path = Path(path)
    fmt = _FORMATS.get(path.suffix.lower())
    if fmt is None:
        raise MosaicError(f"{path}: unknown image suffix; use one of {', '.join(sorted(_FORMATS))}")
    arr = np.asarray(image)
    if fmt != "PNG" and arr.dtype == np.uint16:
        arr = (arr // 257).astype(np.uint8)
    buf = _io.BytesIO()
    Image.fromarray(arr).save(buf, format=fmt)
    atomic_write_bytes(path, buf.getvalue())


def cli_add_arguments(parser) -> None:
    parser.add_argument("images", nargs="+", metavar="IMAGE",
                        help="overlapping photographs in order, left to right (LEFT RIGHT [MORE ...])")
    parser.add_argument("-o", "--output", required=True, metavar="OUT.png", help="the stitched image")
    parser.add_argument("--backend", default="auto", help="numpy, warp-cpu, warp-cuda[:N], opencl[:PLATFORM] or auto")
    parser.add_argument("--vertical", action="store_true", help="the images run top to bottom")
    parser.add_argument("--min-overlap", type=float, default=MosaicParams.min_overlap,
                        help="smallest overlap as a fraction of the image width (default %(default)s)")


def cli_main(args) -> int:
    from .errors import CliError
    from .io.files import ensure_not_input
    if len(args.images) < 2:
        raise CliError("give at least two images (LEFT RIGHT [MORE ...])")
    if not 0.05 <= args.min_overlap <= 0.95:
        raise CliError(f"--min-overlap must be between 0.05 and 0.95, got {args.min_overlap}")
    out = Path(args.output)
    if out.suffix.lower() not in _FORMATS:
        raise CliError(f"{out}: unknown image suffix; use one of {', '.join(sorted(_FORMATS))}")
    ensure_not_input(out, args.images)
    try:
        backend = resolve(args.backend)
    except BackendError as exc:
        raise CliError(str(exc)) from None
    params = replace(MosaicParams(), min_overlap=args.min_overlap)
    result = stitch([Path(x) for x in args.images], backend=backend, params=params, vertical=args.vertical,
                    progress=True)
    save_image(out, result.image)
    for name, (row, col), angle in zip(args.images, result.offsets, result.angles):
        print(f"{name}: origin at row {row:.1f}, col {col:.1f}, rotated {angle:+.2f} deg")
    print(f"wrote {out} ({result.image.shape[1]}x{result.image.shape[0]} px, backend {backend.name})")
    return 0
