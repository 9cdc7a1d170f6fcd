"""Contour point features (sections 3.7.3 and 3.8.1).

The backend's curvature kernel gives, per point of a closed contour, the k-cosine
curvature (Eq. 13-16), the discrete curvature and torsion (Eq. 25-26) and the right
and left chords (Eq. 27-28) at the feature stride. Here they are made
dimensionless with the stride's arc length L = stride * step, so that two
fragments of the same object, sampled at the same step, give comparable numbers:

    f = (kappa * L, asinh(tau * L), chord_right / L, chord_left / L)

(torsion is compressed by asinh: it explodes where the curve is locally straight).
Feature points (Eq. 17) are the points whose k-cosine curvature tops every other
in a window around them.
"""
from __future__ import annotations

import numpy as np


def contour_features(points: np.ndarray, step: float, k: int, stride: int, backend) -> tuple[np.ndarray, np.ndarray]:
    """Return (raw (N,5) [kcos, kappa, tau, chord_right, chord_left], f (N,4) dimensionless)."""
    raw = np.asarray(backend.contour_features(np.asarray(points, np.float64), k, stride), np.float64)
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
