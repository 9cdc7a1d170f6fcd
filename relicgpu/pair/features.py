"""Contour point features (sections 3.7.3 and 3.8.1).

The backend's curvature kernel gives, per point of a closed contour, the k-cosine
curvature (Eq. 13-16), the discrete curvature and torsion (Eq. 25-26) and the right
and left chords (Eq. 27-28) at the feature stride. Here they are made
dimensionless with the stride's arc length L = stride * step, so that two
fragments of the same object, sampled at the same step, give comparable numbers:

    f = (kappa * L, asinh(tau * L), chord_right / L, chord_left / L)

(torsion is compressed by asinh: it explodes where the curve is locally straight).

Curvature, torsion and chords are taken on the contour smoothed by a circular Gaussian
of sigma = stride / 4 points. A contour follows mesh edges, so at a few points' scale
its shape is the triangulation's zigzag, which two mating fragments do not share: on
synthetic breaks at 4000 faces the rank correlation of kappa between truly
corresponding points of mating contours is 0.44 at stride 3 unsmoothed and 0.53 at
stride 8 smoothed (torsion 0.33 -> 0.45, chords 0.1 -> 0.15), and the LCS of
standardised curvature alone gives a RANSAC start within 5% of the true pose on 19 of
39 training pairs instead of 7 (relicgpu.fusion_train.lcs_check). The k-cosine curvature stays on the unsmoothed points:
feature points (Eq. 17) are the points whose k-cosine curvature tops every other in
a window around them.
"""
from __future__ import annotations

import numpy as np


def smooth_closed(points: np.ndarray, sigma: float) -> np.ndarray:
    """A closed polyline smoothed by a circular Gaussian of `sigma` points (exact, via FFT)."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    n = len(p)
    if sigma <= 0 or n < 3:
        return p.copy()
    k = np.fft.rfftfreq(n) * n  # frequency index 0..n/2
    transfer = np.exp(-2.0 * (np.pi * sigma * k / n) ** 2)
    return np.fft.irfft(np.fft.rfft(p, axis=0) * transfer[:, None], n=n, axis=0)


def smoothing_sigma(stride: int) -> float:
    return stride / 4.0


def contour_features(points: np.ndarray, step: float, k: int, stride: int, backend) -> tuple[np.ndarray, np.ndarray]:
    """Return (raw (N,5) [kcos, kappa, tau, chord_right, chord_left], f (N,4) dimensionless).

    kcos from the contour as sampled, the other four from it smoothed (see the module note)."""
    p = np.asarray(points, np.float64)
    raw = np.asarray(backend.contour_features(p, k, stride), np.float64)
    if smoothing_sigma(stride) > 0 and len(p) >= 3:
        smooth = np.asarray(backend.contour_features(smooth_closed(p, smoothing_sigma(stride)), k, stride), np.float64)
        raw = np.concatenate([raw[:, :1], smooth[:, 1:]], axis=1)
    return raw, dimensionless(raw, step * stride)


def dimensionless(raw: np.ndarray, arc: float) -> np.ndarray:
    f = np.empty((len(raw), 4))
    f[:, 0] = raw[:, 1] * arc
    f[:, 1] = np.arcsinh(raw[:, 2] * arc)
    f[:, 2] = raw[:, 3] / arc
    f[:, 3] = raw[:, 4] / arc
    return f


def feature_points(kcos: np.ndarray, window: int) -> np.ndarray:
    """Indices of curvature peaks (Eq. 17): kcos_i >= every kcos within +-window, strictly
    above the contour's median (so flat runs give no peaks)."""
    n = len(kcos)
    if n == 0:
        return np.zeros(0, np.int64)
    w = min(window, (n - 1) // 2)
    stack = np.stack([np.roll(kcos, s) for s in range(-w, w + 1)])
    is_peak = (kcos >= stack.max(axis=0)) & (kcos > np.median(kcos))
    return np.flatnonzero(is_peak)
