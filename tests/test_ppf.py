"""Point-pair-feature voting (coarse poses for partial contacts) and trimmed batched ICP."""
import numpy as np
import pytest

from relicgpu.backends import get_backend
from relicgpu.backends import numpy as numpy_backend
from relicgpu.pair.icp import apply, axis_rotation, batched_icp, refine_point_to_plane, rotation_angle_deg
from relicgpu.pair.ppf import pair_table, ppf_poses, smoothed_normals, vote_poses


def _rough_sheet(rng, n=900, size=1.0):
    """Points of a rough height field z = h(x, y) with their upward normals."""
    xy = rng.uniform(-size / 2, size / 2, (n, 2))
    k = rng.normal(0, 6, (6, 2))
    ph = rng.uniform(0, 2 * np.pi, 6)
    amp = 0.04 / np.arange(1, 7)
    z = (amp * np.sin(xy @ k.T + ph)).sum(1)
    grad = (amp * np.cos(xy @ k.T + ph)) @ k
    normals = np.column_stack([-grad, np.ones(n)])
    return np.column_stack([xy, z]), normals / np.linalg.norm(normals, axis=1, keepdims=True)


def _random_pose(rng, shift=1.0):
    axis = rng.normal(size=3)
    t = np.eye(4)
    t[:3, :3] = axis_rotation(axis / np.linalg.norm(axis), rng.uniform(0.5, 3.0))[:3, :3]
    t[:3, 3] = rng.normal(0, shift, 3)
    return t


def test_smoothed_normals_of_a_noisy_plane_are_the_plane_normal_and_keep_orientation():
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-1, 1, (500, 2)), rng.normal(0, 1e-3, 500)])
    given = np.tile([0.0, 0.3, -1.0], (500, 1))  # rough guess, pointing down
    n = smoothed_normals(pts, given, 0.3)
    assert np.allclose(n, [0, 0, -1], atol=0.02)
    assert smoothed_normals(pts[:2], given[:2], 0.3).shape == (2, 3)  # too few points: given back


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_ppf_finds_a_mating_surface_that_covers_a_third_of_each_side(seed):
    rng = np.random.default_rng(seed)
    pts, nrm = _rough_sheet(rng)
    # a: the left two thirds of the sheet; b: the right two thirds, seen from the other side
    # (normals flipped), moved away. They share the middle third.
    a = pts[:, 0] < 1 / 6
    b = pts[:, 0] > -1 / 6
    truth = _random_pose(rng)
    b_pts, b_nrm = apply(np.linalg.inv(truth), pts[b]), -nrm[b] @ np.linalg.inv(truth)[:3, :3].T
    poses = ppf_poses(pts[a], nrm[a], b_pts, -b_nrm, dist_step=0.03, keep=10)
    assert poses and all(v1 >= v2 for (_, v1), (_, v2) in zip(poses, poses[1:]))
    errors = [(rotation_angle_deg(p[:3, :3] @ truth[:3, :3].T), np.linalg.norm(apply(p, b_pts) - pts[b], axis=1).max())
              for p, _ in poses[:3]]
    assert min(e[0] for e in errors) < 8.0
    assert min(e[1] for e in errors) < 0.1


def test_ppf_on_too_few_points_gives_nothing():
    assert ppf_poses(np.zeros((2, 3)), np.tile([0, 0, 1.0], (2, 1)), np.zeros((5, 3)),
                     np.tile([0, 0, 1.0], (5, 1)), 0.1) == []
    assert ppf_poses(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), 0.1) == []


def _bent_partial_overlap():
    """A rough sheet as target and, 3 degrees off, a source of which a quarter lies on the
    target and the rest runs beyond its edge, bent away at ~56 degrees (another fracture
    facet). Returns source, target, the source's true points and the start pose."""
    rng = np.random.default_rng(4)
    pts, _ = _rough_sheet(rng, n=2000, size=1.0)
    target = pts[pts[:, 0] < -0.1]
    source_true = pts[pts[:, 0] > -0.35].copy()
    bend = source_true[:, 0] > -0.1
    source_true[bend, 2] += 1.5 * (source_true[bend, 0] + 0.1)
    start = np.eye(4)
    start[:3, :3] = axis_rotation(np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2]), np.radians(3))[:3, :3]
    start[:3, 3] = [0.02, -0.01, 0.015]
    return apply(np.linalg.inv(start), source_true), target, source_true, start


def test_trimmed_icp_converges_on_a_partial_overlap_where_the_median_rule_is_dragged_off():
    source, target, source_true, start = _bent_partial_overlap()
    be = get_backend("numpy")
    trimmed, _ = batched_icp(source, target, np.eye(4)[None], be, 40, 0.3, 0.01, trim=0.2)
    median, _ = batched_icp(source, target, np.eye(4)[None], be, 40, 0.3, 0.01, trim=0.5)

    def err(p):
        return np.linalg.norm(apply(p, source) - source_true, axis=1).max()
    assert err(trimmed[0]) < 0.005
    assert err(median[0]) > 0.1


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_screen_trim_keeps_a_start_on_a_seventh_of_the_source_that_the_fit_trim_drags_off(seed):
    # The screen of match_pair's starts: a point-pair vote lands a few degrees off on a contact of
    # ~14% of b's fracture sample, the rest of b bending away within the screen's reject distance.
    # With the fitting trim (0.2) the nearest fifth reaches past the contact and the fit leaves;
    # with the screen's (0.05) it stays near the contact (the final ICP then polishes it).
    from relicgpu.params import Params
    p = Params()
    rng = np.random.default_rng(seed)
    pts, _ = _rough_sheet(rng, n=2000, size=1.0)
    target = pts[pts[:, 0] < -0.1]
    source_true = pts[pts[:, 0] > -0.2].copy()
    bend = source_true[:, 0] > -0.1
    source_true[bend, 2] += 1.5 * (source_true[bend, 0] + 0.1)
    assert 0.12 < np.mean(~bend) < 0.16
    start = np.eye(4)
    start[:3, :3] = axis_rotation(np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2]), np.radians(4))[:3, :3]
    start[:3, 3] = [0.02, -0.01, 0.015]
    source = apply(np.linalg.inv(start), source_true)
    be = get_backend("numpy")
    iterations = p.screen_iterations + p.screen_more_iterations

    def contact_error(trim):
        pose, _ = batched_icp(source, target, np.eye(4)[None], be, iterations, p.screen_reject, p.contact_distance,
                              trim=trim)
        return np.sqrt(np.mean(np.sum((apply(pose[0], source) - source_true)[~bend] ** 2, axis=1)))
    assert contact_error(p.screen_trim) < 0.06
    assert contact_error(p.icp_trim) > 0.2


def _shared_third(seed):
    """A rough sheet's left two thirds (a) and right two thirds (b, moved by `truth`, normals
    flipped as a mating surface's): they share the middle third."""
    rng = np.random.default_rng(seed)
    pts, nrm = _rough_sheet(rng)
    a, b = pts[:, 0] < 1 / 6, pts[:, 0] > -1 / 6
    truth = _random_pose(rng)
    inv = np.linalg.inv(truth)
    return pts[a], nrm[a], apply(inv, pts[b]), nrm[b] @ inv[:3, :3].T, truth, pts[b]


def test_ppf_votes_with_unit_weights_are_the_unweighted_votes():
    a_pts, a_nrm, b_pts, b_nrm, _, _ = _shared_third(0)
    plain = vote_poses(pair_table(a_pts, a_nrm, 0.03), pair_table(b_pts, b_nrm, 0.03, reference_stride=3, sort=False),
                       0.06, keep=5)
    ones_a, ones_b = np.ones(len(a_pts)), np.ones(len(b_pts))
    weighted = vote_poses(pair_table(a_pts, a_nrm, 0.03, weights=ones_a),
                          pair_table(b_pts, b_nrm, 0.03, reference_stride=3, sort=False, weights=ones_b), 0.06, keep=5)
    assert len(plain) == len(weighted)
    for (p, v), (q, w) in zip(plain, weighted):
        assert np.allclose(p, q) and v == pytest.approx(w)


def test_ppf_vote_weights_put_the_likely_fracture_first():
    """Points weighted by a fracture likelihood: the shared third likely, the rest of each side
    unlikely (1e-3): the best-supported pose is the true one."""
    a_pts, a_nrm, b_pts, b_nrm, truth, b_true = _shared_third(1)
    wa = np.where(np.abs(a_pts[:, 0]) < 1 / 6, 1.0, 1e-3)
    wb = np.where(np.abs(b_true[:, 0]) < 1 / 6, 1.0, 1e-3)
    model = pair_table(a_pts, a_nrm, 0.03, weights=wa)
    assert model.weight.shape == model.key.shape
    scene = pair_table(b_pts, b_nrm, 0.03, reference_stride=3, sort=False, weights=wb)
    pose, _ = vote_poses(model, scene, 0.06, keep=3)[0]
    assert rotation_angle_deg(pose[:3, :3] @ truth[:3, :3].T) < 8.0


def test_weighted_icp_leaves_out_points_of_no_weight():
    """The partial overlap of the trim test: the median rule is dragged off by the bent part,
    unless the bent part's points weigh nothing; unit weights change nothing."""
    source, target, source_true, start = _bent_partial_overlap()
    bend = source_true[:, 0] > -0.1  # the bent part (bending moves z only)
    be = get_backend("numpy")
    plain, share = batched_icp(source, target, np.eye(4)[None], be, 40, 0.3, 0.01, trim=0.5)
    ones, share_ones = batched_icp(source, target, np.eye(4)[None], be, 40, 0.3, 0.01, trim=0.5,
                                   weights=np.ones(len(source)), target_weights=np.ones(len(target)))
    assert np.allclose(plain, ones) and np.allclose(share, share_ones)
    weighted, _ = batched_icp(source, target, np.eye(4)[None], be, 40, 0.3, 0.01, trim=0.5,
                              weights=np.where(bend, 0.0, 1.0))
    assert np.linalg.norm(apply(weighted[0], source) - source_true, axis=1).max() < 0.005


class _Exact:
    """The numpy index asked without its reach: every distance exact."""

    def __init__(self, target):
        self.index = numpy_backend.nearest_index(target)

    def query(self, source, within=None):
        return self.index.query(source)


def test_batched_icp_is_the_same_when_the_search_stops_at_its_reach():
    """A k-d tree that gives up past the reject distance (`NearestIndex.query(within=)`) leaves
    every round as it was, bit for bit: starts near and far, rows whose trim quantile lies inside
    the reach, beyond it, and on its edge (one order statistic inside, the next beyond)."""
    rng = np.random.default_rng(5)
    target = rng.random((400, 3))
    source = target[:21] + 0.03 * rng.normal(size=(21, 3))
    source[11:] += 0.5  # 11 of 21 points near: the median's order statistics straddle the reach
    starts = np.tile(np.eye(4), (5, 1, 1))
    starts[1, :3, 3] = 3.0  # every point beyond reach
    starts[2, :3, :3] = axis_rotation(np.array([0.0, 0.0, 1.0]), 0.3)
    starts[3, :3, 3] = 0.02
    starts[4, :3, :3] = axis_rotation(np.array([1.0, 0.0, 0.0]), 2.0)
    weights, target_weights = rng.random(21), rng.random(400)
    for trim, iterations in ((0.5, 1), (0.5, 6), (0.05, 6), (0.2, 6)):
        got, exact = (batched_icp(source, target, starts, numpy_backend, iterations, 0.1, 0.01, trim=trim, index=index,
                                  weights=weights, target_weights=target_weights)
                      for index in (None, _Exact(target)))
        np.testing.assert_array_equal(got[0], exact[0])
        np.testing.assert_array_equal(got[1], exact[1])


def test_point_to_plane_polish_is_the_same_when_the_search_stops_at_its_cutoff():
    rng = np.random.default_rng(6)
    target = rng.random((500, 3))
    normals = rng.normal(size=(500, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    source = target[:60] + 0.01 * rng.normal(size=(60, 3))
    source[30:] += 0.3  # half of the points beyond the cutoff
    starts = np.tile(np.eye(4), (3, 1, 1))
    starts[1, :3, 3] = 0.004
    starts[2, :3, :3] = axis_rotation(np.array([0.0, 1.0, 0.0]), 0.05)
    got, exact = (refine_point_to_plane(source, target, normals, starts, numpy_backend, 5, 0.02, index=index)
                  for index in (None, _Exact(target)))
    np.testing.assert_array_equal(got, exact)
