"""Contour features: the smoothing before curvature, torsion and chords; k-cosine on the points as sampled."""
import numpy as np
import pytest

from relicgpu.backends import resolve
from relicgpu.backends import numpy as ref
from relicgpu.pair.features import contour_features, dimensionless, smooth_closed, smoothing_sigma


def _circle(n, r=1.0):
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.stack([r * np.cos(t), r * np.sin(t), np.zeros(n)], 1)


def test_smooth_closed_is_the_circular_gaussian_convolution():
    rng = np.random.default_rng(0)
    p = rng.normal(size=(40, 3))
    sigma = 2.5
    offsets = np.arange(-40 * 3, 40 * 3 + 1)  # the wrapped kernel, summed over enough periods
    w = np.exp(-0.5 * (offsets / sigma) ** 2)
    w /= w.sum()
    want = sum(wk * np.roll(p, -o, axis=0) for o, wk in zip(offsets, w))
    assert np.allclose(smooth_closed(p, sigma), want, atol=1e-9)
    assert np.array_equal(smooth_closed(p, 0), p)
    assert smooth_closed(np.zeros((0, 3)), 2).shape == (0, 3)


def test_smoothing_keeps_a_circle_round_and_centred():
    p = _circle(100) + [1, 2, 3]
    s = smooth_closed(p, 4.0)
    r = np.linalg.norm(s - [1, 2, 3], axis=1)
    assert np.allclose(s.mean(0), [1, 2, 3]) and np.ptp(r) < 1e-9
    assert np.isclose(r[0], np.exp(-2 * (np.pi * 4.0 / 100) ** 2))  # the k=1 mode's transfer


def test_features_hardly_see_a_jitter_finer_than_the_stride():
    n, step, stride = 200, 2 * np.pi / 200, 8
    smooth = _circle(n)
    # radial jitter of 1% of the radius from point to point (a mesh-edge staircase)
    zig = smooth * (1 + 0.01 * np.random.default_rng(0).uniform(-1, 1, n))[:, None]
    be = resolve("numpy")
    raw_s, f_s = contour_features(smooth, step, 4, stride, be)
    raw_z, f_z = contour_features(zig, step, 4, stride, be)
    # curvature of the unit circle ~ 1, the smoothing shrinks it a hair; the zigzag hardly shows
    assert np.allclose(raw_s[:, 1], 1.0, rtol=0.02)
    assert np.max(np.abs(raw_z[:, 1] - raw_s[:, 1])) < 0.25
    # without the smoothing the same zigzag moves the curvature by far more
    plain = ref.contour_features(zig, 4, stride)
    assert np.max(np.abs(plain[:, 1] - raw_s[:, 1])) > 2 * np.max(np.abs(raw_z[:, 1] - raw_s[:, 1]))
    # kcos comes from the points as sampled (the zigzag shows there), the rest from the smoothed ones
    assert np.array_equal(raw_z[:, 0], ref.contour_features(zig, 4, stride)[:, 0])
    sm = ref.contour_features(smooth_closed(zig, smoothing_sigma(stride)), 4, stride)
    assert np.array_equal(raw_z[:, 1:], sm[:, 1:])
    assert np.allclose(f_z, dimensionless(raw_z, step * stride))


@pytest.mark.parametrize("n", [1, 2, 3, 5])
def test_tiny_contours_give_finite_features(n):
    raw, f = contour_features(_circle(n), 0.1, 4, 8, resolve("numpy"))
    assert raw.shape == (n, 5) and f.shape == (n, 4) and np.all(np.isfinite(f))
