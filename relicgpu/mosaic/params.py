"""The mosaic's parameters (`MosaicParams`), its error, and its results (`PairMatch`, `Mosaic`)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..io.fragment import FragmentError


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
