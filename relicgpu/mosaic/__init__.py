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

Modules: `params` (MosaicParams, MosaicError, PairMatch, Mosaic), `preprocess` (3.3.1
and the LED and entropy kernels), `fcm` (3.3.2, the feature region), `entropy` (3.4),
`register` (verification, refinement, `register_pair`), `stitching` (`stitch`,
compositing, image files), `command` (`relicgpu mosaic`).
"""
from __future__ import annotations

from .entropy import EntropyMatch, cross_blocks, match_entropy, quadratic_entropy, sequential_costs
from .fcm import (FcmResult, FeatureRegion, fcm_memberships, find_feature_region, find_feature_regions, fuzzy_cmeans,
                  isotropy, template_width)
from .params import Mosaic, MosaicError, MosaicParams, PairMatch
from .preprocess import (Prepared, block_entropy, edge_map, led, local_normalise, median3, noise_sigma, prepare_image,
                         quantise, to_gray)
from .register import Placement, overlap_correlation, refine_placement, register_pair
from .stitching import composite, load_image, save_image, stitch

__all__ = ["EntropyMatch", "cross_blocks", "match_entropy", "quadratic_entropy",
           "sequential_costs", "FcmResult", "FeatureRegion", "fcm_memberships", "find_feature_region",
           "find_feature_regions", "fuzzy_cmeans", "isotropy", "template_width", "Mosaic", "MosaicError",
           "MosaicParams", "PairMatch", "Prepared", "block_entropy", "edge_map", "led", "local_normalise", "median3",
           "noise_sigma", "prepare_image", "quantise", "to_gray", "Placement", "overlap_correlation",
           "refine_placement", "register_pair", "composite", "load_image", "save_image", "stitch"]
