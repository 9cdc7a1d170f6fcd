"""3.3.1 preprocessing: gray, median filter, local normalisation (Eq. 1-3), edges, quantised
levels; the LED (Eq. 4) and block-entropy (Eq. 8) kernels on the backend; `prepare_image`."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ..backends import resolve
from .params import MosaicParams


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


def _block_mean(gray: np.ndarray, factor: int) -> np.ndarray:
    """Mean of factor x factor blocks (the ragged last rows and columns dropped)."""
    h, w = gray.shape[0] // factor * factor, gray.shape[1] // factor * factor
    return gray[:h, :w].reshape(h // factor, factor, w // factor, factor).mean((1, 3))
