"""Unit tests per pipeline stage on cases with known answers."""
import numpy as np
import pytest
import trimesh
from hypothesis import given, settings, strategies as st

from relicgpu.backends import numpy as ref
from relicgpu.pair.contour import region_boundary_loops, resample_closed
from relicgpu.pair.fusion import FusionModel, forward, fusion_inputs, hand_weighted_model, load_model, save_model
from relicgpu.pair.icp import apply, icp, ransac_poses, rotation_angle_deg
from relicgpu.pair.lcs import circular_lcs, lcs_backtrack, lcs_table
from relicgpu.params import Params
from relicgpu.pair.segment import mesh_topology, segment


def _box_cut_by_plane():
    import manifold3d as m3d
    box = m3d.Manifold.cube([1.0, 0.6, 0.4], center=True).refine(6)
    piece = box.trim_by_plane([1.0, 0.0, 0.0], 0.0)  # keeps x >= 0
    mesh = piece.to_mesh()
    return np.asarray(mesh.vert_properties[:, :3], np.float64), np.asarray(mesh.tri_verts, np.int64)


def test_box_cut_by_plane_has_right_angles_and_six_flat_regions():
    v, f = _box_cut_by_plane()
    topo = mesh_topology(f)
    normals, _ = ref.face_normals(v, f)
    angle = np.degrees(ref.edge_angles(normals, topo.edge_faces))
    # every edge is either flat (0) or a box edge (90 degrees)
    assert np.all((angle < 1e-6) | (np.abs(angle - 90) < 1e-6))
    assert (np.abs(angle - 90) < 1e-6).sum() > 0
    seg = segment(v, f, Params(min_region_faces=2, segmentation="roughness"), scale=1.0, backend=ref)
    # a box cut by a plane is a box: six flat faces, each one region, none of them rough (roughness alone)
    assert len(seg.region_is_fracture) == 6
    assert not seg.region_is_fracture.any()
    for r in range(6):
        n = normals[seg.face_region == r]
        assert np.allclose(n, n[0], atol=1e-9)


def test_region_boundary_of_a_flat_face_is_one_closed_loop():
    v, f = _box_cut_by_plane()
    normals, _ = ref.face_normals(v, f)
    top = normals[:, 2] > 0.99
    loops = region_boundary_loops(f, top)
    assert len(loops) == 1
    pts = v[loops[0]]
    assert np.allclose(pts[:, 2], 0.2)
    # counter-clockwise seen from outside (+z): positive signed area
    x, y = pts[:, 0], pts[:, 1]
    assert 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y) == pytest.approx(0.5 * 0.6)


def test_resample_closed_gives_even_steps():
    t = np.linspace(0, 2 * np.pi, 37)[:-1]
    circle = np.stack([np.cos(t), np.sin(t), 0 * t], 1)
    pts = resample_closed(circle, 0.05)
    steps = np.linalg.norm(np.diff(np.vstack([pts, pts[:1]]), axis=0), axis=1)
    assert steps.std() / steps.mean() < 0.02


def test_helix_curvature_and_torsion_match_closed_form():
    r, c = 1.0, 0.5  # helix (r cos t, r sin t, c t): kappa = r/(r^2+c^2), tau = c/(r^2+c^2)
    n = 4000
    t = np.linspace(0, 8 * np.pi, n, endpoint=False)
    pts = np.stack([r * np.cos(t), r * np.sin(t), c * t], 1)
    raw = ref.contour_features(pts, k=3, stride=2)
    inner = slice(100, n - 100)  # the contour is closed; skip the jump at its seam
    kappa, tau = raw[inner, 1], raw[inner, 2]
    assert np.allclose(kappa, r / (r * r + c * c), rtol=0.02)
    assert np.allclose(tau, c / (r * r + c * c), rtol=0.02)
    # chords at stride 2 of an evenly sampled curve: equal on both sides
    assert np.allclose(raw[inner, 3], raw[inner, 4], rtol=1e-9)


def _lcs_brute(a, b, eps):
    m, n = len(a), len(b)
    table = [[0] * (n + 1) for _ in range(m + 1)]
    for i in range(m):
        for j in range(n):
            if abs(a[i] - b[j]) < eps:
                table[i + 1][j + 1] = table[i][j] + 1
            else:
                table[i + 1][j + 1] = max(table[i][j + 1], table[i + 1][j])
    return table[m][n]


@settings(max_examples=150, deadline=None)
@given(st.lists(st.integers(0, 5), max_size=12), st.lists(st.integers(0, 5), max_size=12))
def test_lcs_table_and_backtrack_against_brute_force(a, b):
    a = np.array(a, float)
    b = np.array(b, float)
    flags = np.abs(a[:, None] - b[None, :]) < 0.5
    table = lcs_table(flags)
    assert table[-1, -1] == _lcs_brute(a, b, 0.5)
    assert ref.lcs_length(a, b, 0.5) == _lcs_brute(a, b, 0.5)
    path = lcs_backtrack(flags, table)
    assert len(path) == table[-1, -1]
    if len(path):
        assert np.all(np.diff(path[:, 0]) > 0) and np.all(np.diff(path[:, 1]) > 0)
        assert flags[path[:, 0], path[:, 1]].all()


def test_circular_lcs_finds_a_reversed_rotated_copy():
    rng = np.random.default_rng(1)
    a = rng.normal(size=60)
    b = np.roll(a[::-1], 17) + rng.normal(scale=0.01, size=60)
    fwd, rev = circular_lcs(a, b, 0.05, ref)
    assert rev.length == 60 > fwd.length
    # every pair links a point to its true copy
    i, j = rev.pairs[:, 0], rev.pairs[:, 1]
    assert np.all(b[j] == pytest.approx(a[i], abs=0.05))


def _random_rotation(rng):
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _axis_angle(axis, degrees):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    th = np.radians(degrees)
    return np.eye(3) + np.sin(th) * k + (1 - np.cos(th)) * k @ k


def test_icp_recovers_a_known_rigid_motion_of_a_noisy_point_set():
    rng = np.random.default_rng(7)
    # a bumpy, asymmetric surface patch (like a fracture surface)
    xy = rng.random((3000, 2))
    z = 0.1 * np.sin(7 * xy[:, 0]) * np.cos(5 * xy[:, 1]) + 0.05 * xy[:, 0] ** 2
    target = np.column_stack([xy, z])
    truth = np.eye(4)
    truth[:3, :3] = _axis_angle([0.3, -0.5, 0.8], 12)
    truth[:3, 3] = [0.05, -0.03, 0.02]
    source = apply(np.linalg.inv(truth), target[::2]) + rng.normal(scale=0.002, size=target[::2].shape)
    fit = icp(source, target, np.eye(4), ref, iterations=200, tolerance=1e-9, reject=1.0, floor=0.01)
    assert rotation_angle_deg(fit.transform[:3, :3] @ truth[:3, :3].T) < 0.5
    assert np.linalg.norm(fit.transform[:3, 3] - truth[:3, 3]) < 0.005


def test_ransac_finds_the_pose_among_outliers():
    rng = np.random.default_rng(2)
    src = rng.random((80, 3))
    truth = np.eye(4)
    truth[:3, :3] = _random_rotation(rng)
    truth[:3, 3] = [1, 2, 3]
    dst = apply(truth, src)
    dst[:40] = rng.random((40, 3)) * 3  # half the correspondences are wrong
    poses = ransac_poses(src, dst, 300, 0.01, np.random.default_rng(0), keep=3)
    best, count = poses[0]
    assert count >= 40
    assert np.allclose(best, truth, atol=1e-6)


def test_fusion_inputs_follow_eq_29_to_32():
    f = np.arange(12, dtype=float).reshape(3, 4) ** 2
    x = fusion_inputs(f)
    g = 2 * f - np.roll(f, 1, 0) - np.roll(f, -1, 0)
    assert np.allclose(x[:, :4], g) and np.allclose(x[:, 4:], f)
    assert fusion_inputs(np.zeros((0, 4))).shape == (0, 8)


def test_fusion_weights_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    model = FusionModel((rng.normal(size=(8, 5)), rng.normal(size=(5, 1))), (rng.normal(size=5), rng.normal(size=1)),
                        rng.normal(size=8), rng.random(8) + 0.5, {"seed": 0})
    save_model(tmp_path / "w.npz", model)
    back = load_model(tmp_path / "w.npz")
    x = rng.normal(size=(20, 8))
    assert np.allclose(forward(model, x), forward(back, x))
    assert back.meta == {"seed": 0}


def test_hand_weighted_model_is_the_linear_mix():
    mix = np.array([0.5, 0, 0, 0, 1, -2, 0, 0.25])
    model = hand_weighted_model(mix)
    x = np.random.default_rng(0).normal(size=(30, 8))
    assert np.allclose(forward(model, x), x @ mix)
