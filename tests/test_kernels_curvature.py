"""Family 2 (contour features): every backend against the float64 reference,
and the reference against closed-form curves.

The kernels of this family compute in float64 (second and third differences at a
small step lose too many digits in float32), so the tolerances are tight:
  kcos, chords, kappa : |x - x_ref| <= 1e-9 * (|x_ref| + 1)      (curves of size ~1 to 100)
  tau                 : same, where the reference curvature is not tiny
                        (tau = (r' x r'') . r''' / |r' x r''|^2 is ill-conditioned where
                        r' x r'' -> 0); exactly 0 where the curve is exactly straight
  special values      : exact (-1 kcos, 0 kappa/tau) on identical points, 0 kappa/tau on
                        exactly straight runs (kcos there within 1e-12 of -1).
"""
from __future__ import annotations

import numpy as np
import pytest

from relicgpu.backends import numpy as ref


def _needs_fp64(backend):
    if getattr(backend, "real", np.float64) != np.float64:
        pytest.skip("device without double precision")


def _close(got, want, where=None):
    assert got.shape == want.shape and got.dtype == np.float64
    ok = np.abs(got - want) <= 1e-9 * (np.abs(want) + 1)
    if where is not None:
        ok |= ~where
    assert ok.all(), (np.argwhere(~ok)[:5], got[~ok][:5], want[~ok][:5])


def _random_closed_curve(rng, n, scale, offset):
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    coeff = rng.normal(size=(3, 3, 2)) / np.arange(1, 4)[None, :, None]
    pts = sum(coeff[:, j, 0][None, :] * np.cos((j + 1) * t)[:, None]
              + coeff[:, j, 1][None, :] * np.sin((j + 1) * t)[:, None] for j in range(3))
    return pts * scale + offset


# --- the reference against closed forms ------------------------------------------

def test_reference_kcos_on_a_regular_polygon():
    n, k, radius = 60, 4, 3.0
    t = 2 * np.pi * np.arange(n) / n
    pts = np.stack([radius * np.cos(t), radius * np.sin(t), np.zeros(n)], 1)
    m = np.arange(1, k + 1)
    chord = 2 * radius * np.sin(np.pi * m / n)
    expected = np.sum(-np.cos(2 * np.pi * m / n) / (2 * chord)) / np.sum(1 / (2 * chord))
    f = ref.contour_features(pts, k, 1)
    np.testing.assert_allclose(f[:, 0], expected, rtol=1e-12)
    np.testing.assert_allclose(f[:, 3], chord[0], rtol=1e-12)
    np.testing.assert_allclose(f[:, 4], chord[0], rtol=1e-12)


def test_reference_curvature_and_torsion_of_a_helix():
    r, c, n = 2.0, 0.5, 4000
    t = np.linspace(0, 8 * np.pi, n)
    pts = np.stack([r * np.cos(t), r * np.sin(t), c * t], 1)
    f = ref.contour_features(pts, 3, 2)
    inner = slice(10, n - 10)  # the ends wrap around
    np.testing.assert_allclose(f[inner, 1], r / (r * r + c * c), rtol=1e-4)
    np.testing.assert_allclose(f[inner, 2], c / (r * r + c * c), rtol=1e-3)


def test_reference_circle_has_curvature_one_over_radius_and_no_torsion():
    n, radius = 2000, 5.0
    t = 2 * np.pi * np.arange(n) / n
    pts = np.stack([radius * np.cos(t), radius * np.sin(t), np.full(n, 7.0)], 1)
    f = ref.contour_features(pts, 5, 3)
    np.testing.assert_allclose(f[:, 1], 1 / radius, rtol=1e-4)
    assert np.all(np.abs(f[:, 2]) < 1e-6)


# --- every backend against the reference ------------------------------------------

@pytest.mark.parametrize("n,k,stride", [(500, 5, 2), (97, 12, 1), (2000, 3, 7)])
def test_contour_features_random_curves(backend, n, k, stride):
    _needs_fp64(backend)
    rng = np.random.default_rng()
    pts = _random_closed_curve(rng, n, scale=rng.uniform(1, 100), offset=rng.normal(size=3) * 1000)
    got, want = backend.contour_features(pts, k, stride), ref.contour_features(pts, k, stride)
    for col in (0, 1, 3, 4):
        _close(got[:, col], want[:, col])
    _close(got[:, 2], want[:, 2], where=want[:, 1] > 1e-6 * np.median(want[:, 1]))


def test_contour_features_duplicate_points_and_straight_runs(backend):
    _needs_fp64(backend)
    rng = np.random.default_rng()
    pts = _random_closed_curve(rng, 200, 10.0, 0.0)
    pts[50:55] = pts[50]  # a run of duplicates
    pts[100:140] = np.arange(40)[:, None] * np.array([1.0, 2.0, -1.0])  # exactly straight
    got, want = backend.contour_features(pts, 6, 2), ref.contour_features(pts, 6, 2)
    for col in (0, 1, 3, 4):
        _close(got[:, col], want[:, col])
    straight = slice(106, 134)
    assert np.all(want[straight, 1] == 0) and np.all(got[straight, 1] == 0)
    assert np.all(got[straight, 2] == 0) and np.all(np.abs(got[straight, 0] + 1) < 1e-12)
    _close(got[:, 2], want[:, 2], where=want[:, 1] > 1e-6 * np.median(want[:, 1]))


@pytest.mark.parametrize("n", [1, 2, 3, 5])
def test_contour_features_tiny_contours(backend, n):
    _needs_fp64(backend)
    rng = np.random.default_rng()
    pts = rng.normal(size=(n, 3))
    for k, stride in [(1, 1), (4, 3), (9, 2)]:  # neighbourhoods wider than the contour
        got, want = backend.contour_features(pts, k, stride), ref.contour_features(pts, k, stride)
        for col in range(5):
            _close(got[:, col], want[:, col], where=(want[:, 1] > 1e-9) if col == 2 else None)
    if n == 1:
        np.testing.assert_array_equal(backend.contour_features(pts, 3, 1), [[-1, 0, 0, 0, 0]])


def test_contour_features_identical_points(backend):
    pts = np.tile([[3.0, -2.0, 1.5]], (17, 1))
    got = backend.contour_features(pts, 4, 2)
    np.testing.assert_array_equal(got, np.tile([[-1, 0, 0, 0, 0]], (17, 1)))


def test_contour_features_empty(backend):
    assert backend.contour_features(np.zeros((0, 3)), 3, 1).shape == (0, 5)
