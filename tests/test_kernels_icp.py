"""Family 4 (nearest neighbours, cross-covariance): every backend against the reference,
and the reference against brute force.

Tolerances. The device search runs in float32 on coordinates shifted to the target
bounding-box centre (each off by up to 2^-24 * L/2, L the bounding-box diagonal of
both sets), so it may pick, among near-ties, a point up to ~2e-7 * L farther than
the true nearest; the distance it returns is recomputed in float64 for the point
it picked. Hence:
  distance : |d - d_ref| <= 1e-6 * L, and d equals |source - target[idx]| (rtol 1e-12)
  index    : any index whose float64 distance meets the line above (ties are free)
  covariance (float64 sums on the device): centroids, H, wsum within 1e-9 relative
"""
from __future__ import annotations

import numpy as np
import pytest

from relicgpu.backends import numpy as ref


def _check_nn(backend, source, target):
    idx, dist = backend.nearest_neighbors(source, target)
    assert idx.dtype == np.int32 and idx.shape == (len(source),)
    assert dist.dtype == np.float64 and dist.shape == (len(source),)
    _, dist_ref = ref.nearest_neighbors(source, target)
    assert idx.min() >= 0 and idx.max() < len(target)
    np.testing.assert_allclose(dist, np.linalg.norm(source - target[idx], axis=1), rtol=1e-12, atol=0)
    both = np.concatenate([source, target])
    size = np.linalg.norm(both.max(0) - both.min(0))
    assert np.all(np.abs(dist - dist_ref) <= 1e-6 * size)
    return idx, dist


def _sphere(rng, n, radius=1.0):
    u, w = rng.random(n) * 2 * np.pi, np.arccos(1 - 2 * rng.random(n))
    return radius * np.stack([np.cos(u) * np.sin(w), np.sin(u) * np.sin(w), np.cos(w)], 1)


# --- the reference against brute force -----------------------------------------

def test_reference_nearest_neighbours_against_brute_force():
    rng = np.random.default_rng()
    s, t = rng.normal(size=(300, 3)), rng.normal(size=(200, 3))
    d_all = np.linalg.norm(s[:, None] - t[None], axis=2)
    idx, dist = ref.nearest_neighbors(s, t)
    np.testing.assert_allclose(dist, d_all.min(1), rtol=1e-12)
    np.testing.assert_allclose(d_all[np.arange(300), idx], d_all.min(1), rtol=1e-12)


def test_reference_cross_covariance_by_hand():
    rng = np.random.default_rng()
    s = rng.normal(size=(50, 3))
    w = rng.random(50)
    rot = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    t = s @ rot.T + [1.0, -2.0, 3.0]
    cs, ct, h, wsum = ref.cross_covariance(s, t, w)
    np.testing.assert_allclose(cs, (w[:, None] * s).sum(0) / w.sum())
    np.testing.assert_allclose(ct, cs @ rot.T + [1.0, -2.0, 3.0])
    np.testing.assert_allclose(h, np.einsum("i,ij,ik->jk", w, s - cs, t - ct), atol=1e-12)
    assert wsum == pytest.approx(w.sum())
    assert ref.cross_covariance(s, t, np.zeros(50))[3] == 0.0


# --- every backend against the reference ------------------------------------------

@pytest.mark.parametrize("n_source,n_target", [(100, 50), (3000, 3000), (40000, 30000)])
def test_nearest_neighbours_random_far_from_origin(backend, n_source, n_target):
    rng = np.random.default_rng()
    offset = rng.normal(size=3) * 1000
    _check_nn(backend, rng.random((n_source, 3)) * 10 + offset, rng.random((n_target, 3)) * 10 + offset)


def test_nearest_neighbours_surface_points(backend):
    rng = np.random.default_rng()
    target = _sphere(rng, 50000, 3.0)
    source = _sphere(rng, 20000, 3.0) + rng.normal(size=(20000, 3)) * 0.01
    _check_nn(backend, source, target)


def test_nearest_neighbours_duplicates_and_identity(backend):
    rng = np.random.default_rng()
    target = rng.random((5000, 3))
    target = np.concatenate([target, target[:2000]])  # every one of these twice
    idx, dist = _check_nn(backend, target, target)
    assert np.all(dist == 0)


def test_nearest_neighbours_flat_and_straight_targets(backend):
    rng = np.random.default_rng()
    plane = np.c_[rng.random((20000, 2)), np.zeros(20000)]  # zero extent in z
    _check_nn(backend, rng.random((10000, 3)) - [0, 0, 0.5], plane)
    line = np.outer(rng.random(5000), [1.0, 2.0, 3.0])  # a segment
    _check_nn(backend, rng.normal(size=(2000, 3)), line)


def test_nearest_neighbours_far_queries_and_single_target(backend):
    rng = np.random.default_rng()
    target = rng.random((20000, 3))
    far = rng.normal(size=(3000, 3)) * 50  # mostly outside the target box, some very far
    _check_nn(backend, far, target)
    _check_nn(backend, far, target[:1])
    _check_nn(backend, target[:10], target[5:6])


def test_nearest_neighbours_clustered_targets(backend):
    rng = np.random.default_rng()
    target = np.concatenate([rng.normal(size=(20000, 3)) * 0.01, rng.normal(size=(200, 3)) * 0.01 + 100])
    _check_nn(backend, rng.random((1000, 3)) * 100, target)


def test_nearest_neighbours_edge_cases(backend):
    idx, dist = backend.nearest_neighbors(np.zeros((0, 3)), np.ones((4, 3)))
    assert idx.shape == (0,) and dist.shape == (0,)
    with pytest.raises(ValueError):
        backend.nearest_neighbors(np.ones((4, 3)), np.zeros((0, 3)))


def test_nearest_neighbours_non_finite_is_an_error(device_backend):
    target = np.random.default_rng().random((100, 3))
    target[7, 1] = np.nan
    with pytest.raises(ValueError):
        device_backend.nearest_neighbors(np.zeros((3, 3)), target)


def test_nearest_index_answers_every_query_like_nearest_neighbours(backend):
    """One index, many queries (an ICP's rounds): small (brute force) and large (grid) ones,
    inside and far outside the target's box, an empty one; each against the reference."""
    rng = np.random.default_rng()
    target = _sphere(rng, 30000) + 5.0
    index = backend.nearest_index(target)
    for source in (rng.normal(size=(40, 3)) + 5.0, _sphere(rng, 120000, 1.01) + 5.0, target[::7],
                   rng.normal(size=(5000, 3)) * 50, target[:1]):
        idx, dist = index.query(source)
        assert idx.dtype == np.int32 and dist.dtype == np.float64 and idx.shape == (len(source),)
        i_ref, d_ref = _check_nn(backend, source, target)
        np.testing.assert_allclose(dist, np.linalg.norm(source - target[idx], axis=1), rtol=1e-12, atol=0)
        both = np.concatenate([source, target])
        assert np.all(np.abs(dist - d_ref) <= 1e-6 * np.linalg.norm(both.max(0) - both.min(0)))
    idx, dist = index.query(np.zeros((0, 3)))
    assert idx.shape == (0,) and dist.shape == (0,)
    one = backend.nearest_index(target[3:4])  # a length-1 target
    idx, dist = one.query(target[:10])
    assert np.all(idx == 0)
    np.testing.assert_allclose(dist, np.linalg.norm(target[:10] - target[3], axis=1), rtol=1e-12)


def test_nearest_index_within_a_reach_is_exact_inside_it(backend):
    """`query(within=r)`: every point nearer than r as without it; a farther one either exact or
    (len(target), inf), the k-d tree's early stop; on the reach itself and with r = 0 too. Sizes
    past every backend's brute-force bound: the grid search stops at the reach."""
    rng = np.random.default_rng()
    target = _sphere(rng, 30000)
    index = backend.nearest_index(target)
    source = np.concatenate([_sphere(rng, 2000, 1.05), rng.normal(size=(2000, 3)) * 3, target[:5]])
    idx0, d0 = index.query(source)
    for reach in (0.0, 0.05, float(np.median(d0)), 10.0):
        idx, dist = index.query(source, within=reach)
        assert idx.dtype == np.int32 and dist.dtype == np.float64 and idx.shape == (len(source),)
        near = d0 < reach
        np.testing.assert_array_equal(dist[near], d0[near])
        np.testing.assert_allclose(dist[near], np.linalg.norm(source[near] - target[idx[near]], axis=1), rtol=1e-12)
        cut = ~np.isfinite(dist)
        assert np.all(idx[cut] == len(target)) and not np.any(cut & near)
        kept = ~near & ~cut
        np.testing.assert_array_equal(dist[kept], d0[kept])


def test_nearest_index_faults(backend):
    with pytest.raises(ValueError):
        backend.nearest_index(np.zeros((0, 3)))
    bad = np.random.default_rng().random((50, 3))
    bad[4, 2] = np.inf
    with pytest.raises(ValueError):
        backend.nearest_index(bad)
    with pytest.raises(ValueError, match="NaN or infinite"):
        backend.nearest_index(np.ones((5, 3))).query(bad)


@pytest.mark.parametrize("n", [1, 7, 1000, 300000])
def test_cross_covariance(backend, n):
    if getattr(backend, "real", np.float64) != np.float64:
        pytest.skip("device without double precision")
    rng = np.random.default_rng()
    s = rng.normal(size=(n, 3)) * 5 + 1000
    t = rng.normal(size=(n, 3)) - 300
    for w in (None, rng.random(n)):
        got, want = backend.cross_covariance(s, t, w), ref.cross_covariance(s, t, w)
        for g, x in zip(got, want):
            np.testing.assert_allclose(g, x, rtol=1e-9, atol=1e-9 * np.max(np.abs(want[2])))


def test_cross_covariance_zero_weights_and_empty(backend):
    s = np.ones((5, 3))
    cs, ct, h, wsum = backend.cross_covariance(s, s, np.zeros(5))
    assert wsum == 0.0 and not np.any(h) and not np.any(cs)
    assert backend.cross_covariance(np.zeros((0, 3)), np.zeros((0, 3)))[3] == 0.0


def test_nearest_neighbours_large_arrays(device_backend):
    # over 4 MB per array: CUDA backends stage these through pinned host memory
    rng = np.random.default_rng()
    _check_nn(device_backend, rng.random((200000, 3)) * 50 - 7, rng.random((180000, 3)) * 50)
