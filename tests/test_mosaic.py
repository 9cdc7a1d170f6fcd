"""Tests of the image mosaic (issue 8, paper sections 3.3 to 3.4): each equation on
hand-computed values, the kernels on every backend against the float64 reference,
and registration accuracy on pairs cut from a scikit-image sample photograph."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from relicgpu import mosaic as M
from relicgpu.mosaic import register as R

# --- 3.3.1: median filter, Eq. 1-3: local normalisation -------------------------------


def test_median3_against_scipy():
    rng = np.random.default_rng(5)
    img = rng.random((31, 40)) * 255
    want = ndimage.median_filter(img, size=3, mode="nearest")
    np.testing.assert_allclose(M.median3(img), want, atol=1e-4)  # float32 inside
    img[10, 10] = 1e4  # an impulse is removed
    assert M.median3(img)[10, 10] < 256


def test_eq1_above_the_local_mean():
    # 3x3 window over the whole image: M_i = 1, VAR_i = 81/9 - 1 = 8, I - M_i = 8
    img = np.zeros((3, 3))
    img[1, 1] = 9.0
    g = M.local_normalise(img, window=3, mean0=100.0, var0=32.0, var_floor=0.0)
    assert g[1, 1] == pytest.approx(100.0 + np.sqrt(32.0 * 64.0 / 8.0))  # 116


def test_eq1_below_the_local_mean():
    # M_i = 8, VAR_i = 72 - 64 = 8, I - M_i = -8: the "Others" branch
    img = np.full((3, 3), 9.0)
    img[1, 1] = 0.0
    g = M.local_normalise(img, window=3, mean0=100.0, var0=32.0, var_floor=0.0)
    assert g[1, 1] == pytest.approx(100.0 - 16.0)


def test_eq2_eq3_weights():
    # M_i^d = 100 + 0.5 (1 - 100) = 50.5; VAR_i^d = 32 + 0.5 (8 - 32) = 20
    img = np.zeros((3, 3))
    img[1, 1] = 9.0
    g = M.local_normalise(img, window=3, mean0=100.0, var0=32.0, alpha1=0.5, alpha2=0.5, var_floor=0.0)
    assert g[1, 1] == pytest.approx(50.5 + np.sqrt(20.0 * 64.0 / 8.0))


def test_normalisation_removes_a_gray_level_change():
    rng = np.random.default_rng(0)
    img = ndimage.gaussian_filter(rng.random((40, 50)) * 255, 2)
    a = M.local_normalise(img, window=9, var_floor=1e-6)
    b = M.local_normalise(0.7 * img + 30.0, window=9, var_floor=1e-6)
    np.testing.assert_allclose(a, b, atol=1e-6)


# --- Eq. 4: local edge density -------------------------------------------------------


def test_eq4_single_edge_pixel():
    e = np.zeros((5, 5))
    e[2, 2] = 1
    d = M.led(e, 1, "numpy")
    expected = np.zeros((5, 5))
    expected[1:4, 1:4] = 1.0 / 9.0
    np.testing.assert_allclose(d, expected)


def test_eq4_border_counts_outside_as_zero():
    d = M.led(np.ones((4, 6)), 1, "numpy")
    assert d[0, 0] == pytest.approx(4 / 9)
    assert d[0, 2] == pytest.approx(6 / 9)
    assert d[1, 2] == pytest.approx(1.0)


def test_eq4_matches_a_direct_sum():
    rng = np.random.default_rng(1)
    e = (rng.random((23, 31)) < 0.3).astype(float)
    a = 3
    padded = np.pad(e, a)
    direct = np.array([[padded[i:i + 2 * a + 1, j:j + 2 * a + 1].sum() for j in range(31)] for i in range(23)])
    np.testing.assert_allclose(M.led(e, a, "numpy"), direct / (2 * a + 1) ** 2, atol=1e-12)


# --- Eq. 5-6: fuzzy C-means ----------------------------------------------------------


def test_eq5_memberships_by_hand():
    # b = 2: U_k = d_k^-2 / sum_m d_m^-2 with d = (2, 1, 2)
    u = M.fcm_memberships(np.array([2.0]), np.array([0.0, 1.0, 4.0]), 2.0)
    np.testing.assert_allclose(u[0], [1 / 6, 2 / 3, 1 / 6])
    # b = 3: exponent 2/(b-1) = 1, U_k = d_k^-1 / sum: (1/2, 1, 1/2) / 2
    u = M.fcm_memberships(np.array([2.0]), np.array([0.0, 1.0, 4.0]), 3.0)
    np.testing.assert_allclose(u[0], [0.25, 0.5, 0.25])
    # a value on a centre belongs to it alone
    np.testing.assert_allclose(M.fcm_memberships(np.array([1.0]), np.array([0.0, 1.0, 4.0]), 2.0)[0], [0, 1, 0])


def _fcm_direct(values, b, iterations):
    """Eq. 5-6 written point by point in float64, centres started at max, mean, min."""
    v = [float(x) for x in np.ravel(values)]
    c = [max(v), sum(v) / len(v), min(v)]
    for _ in range(iterations):
        u = []
        for x in v:
            d = [abs(x - ck) for ck in c]
            if 0.0 in d:
                hits = [1.0 if dk == 0 else 0.0 for dk in d]
                u.append([h / sum(hits) for h in hits])
            else:
                inv = [(1.0 / dk) ** (2.0 / (b - 1.0)) for dk in d]
                u.append([ik / sum(inv) for ik in inv])
        c = [sum(u[i][k] ** b * v[i] for i in range(len(v))) / sum(u[i][k] ** b for i in range(len(v)))
             for k in range(3)]
    return np.array(c), np.array(u)


def test_eq6_one_step_against_direct():
    values = np.array([[0.0, 0.1, 0.1], [0.5, 0.52, 0.9], [1.0, 0.95, 0.2]])
    res = M.fuzzy_cmeans(values, b=2.0, tol=0.0, max_iter=1)
    direct, _ = _fcm_direct(values, 2.0, 1)
    np.testing.assert_allclose(res.centres, direct, rtol=1e-12)


@pytest.mark.parametrize("b", [1.5, 2.0, 3.0])
def test_fcm_converged_against_direct(b):
    rng = np.random.default_rng(2)
    values = np.round(rng.random((6, 7)) ** 2, 2)  # repeated values, as LED has
    res = M.fuzzy_cmeans(values, b=b, tol=1e-12, max_iter=2000)
    assert res.converged
    direct, u = _fcm_direct(values, b, res.iterations)
    np.testing.assert_allclose(res.centres, direct, rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(res.labels, u.argmax(1))
    # step 4: the centres no longer move
    again = M.fuzzy_cmeans(values, b=b, tol=1e-12, max_iter=res.iterations + 1)
    np.testing.assert_allclose(again.centres, res.centres, atol=1e-10)
    assert res.centres[0] > res.centres[1] > res.centres[2]


def test_fcm_rejects_bad_input():
    with pytest.raises(ValueError):
        M.fuzzy_cmeans(np.array([]))
    with pytest.raises(ValueError):
        M.fuzzy_cmeans(np.array([1.0, 2.0]), b=1.0)


# --- Eq. 7 and Eq. 8 ---------------------------------------------------------------------


def test_eq7_template_width():
    assert M.template_width(64, 0.25, 0.5) == pytest.approx(128.0)
    assert M.template_width(64, 0.6, 0.5) == 64.0  # not below C: unchanged
    assert M.template_width(64, 0.0, 0.5) == 64.0  # no edges at all: nothing to scale by


def test_eq8_by_hand():
    assert M.quadratic_entropy(np.array([0, 0, 0, 0]), 2) == pytest.approx(0.0)
    assert M.quadratic_entropy(np.array([0, 0, 1, 1]), 2) == pytest.approx(0.5)
    assert M.quadratic_entropy(np.array([0, 1, 2, 3]), 4) == pytest.approx(0.75)
    assert M.quadratic_entropy(np.array([0, 0, 0, 3]), 4) == pytest.approx(1 - (0.75 ** 2 + 0.25 ** 2))


def test_block_entropy_map_matches_per_block():
    rng = np.random.default_rng(3)
    q = rng.integers(0, 8, (17, 21))
    h = M.block_entropy(q, 5, 8, "numpy")
    assert h.shape == (13, 17)
    for y, x in [(0, 0), (4, 9), (12, 16)]:
        assert h[y, x] == pytest.approx(M.quadratic_entropy(q[y:y + 5, x:x + 5], 8))


def test_soft_levels_split_between_bins():
    # a level of 1.25 counts 0.75 in bin 1 and 0.25 in bin 2
    q = np.array([[1.25, 1.0], [2.0, 0.0]])
    p = np.array([1.0, 1.75, 1.25]) / 4
    assert M.block_entropy(q, 2, 3, "numpy")[0, 0] == pytest.approx(1 - (p ** 2).sum())
    assert M.quadratic_entropy(q, 3) == pytest.approx(1 - (p ** 2).sum())


# --- sequential detection -----------------------------------------------------------------


def test_sequential_costs_exact_by_default_and_stops_at_a_threshold():
    rng = np.random.default_rng(4)
    hmap = rng.random((40, 40))
    offsets = np.array([[0, 0], [0, 4], [4, 0], [4, 4], [2, 2], [6, 1]])
    cand = np.stack(np.meshgrid(np.arange(30), np.arange(30), indexing="ij"), -1).reshape(-1, 2)
    tmpl = hmap[12 + offsets[:, 0], 7 + offsets[:, 1]] + rng.normal(0, 0.01, len(offsets))
    full = np.array([np.abs(tmpl - hmap[y + offsets[:, 0], x + offsets[:, 1]]).sum() for y, x in cand])
    pruned = M.sequential_costs(tmpl, offsets, hmap, cand)
    assert np.argmin(pruned) == np.argmin(full)
    assert tuple(cand[np.argmin(pruned)]) == (12, 7)
    kept = np.isfinite(pruned)
    np.testing.assert_allclose(pruned[kept], full[kept])
    assert kept.sum() < len(cand) // 2  # most candidates stopped early
    fixed = M.sequential_costs(tmpl, offsets, hmap, cand, thre=1.0)
    np.testing.assert_array_equal(np.isfinite(fixed), full <= 1.0)


# --- kernels on every backend ---------------------------------------------------------------


def _kernel_backends():
    from relicgpu.backends import available_backends
    return [n for n in available_backends() if n != "numpy"]


KERNEL_BACKENDS = _kernel_backends()


@pytest.mark.parametrize("backend", KERNEL_BACKENDS)
@pytest.mark.parametrize("half", [0, 1, 4, 9])
def test_led_kernel_against_numpy(backend, half):
    rng = np.random.default_rng(half)
    e = (rng.random((37, 53)) < 0.35).astype(np.float32)
    out = M.led(e, half, backend)
    assert out.shape == e.shape
    np.testing.assert_allclose(out, M.led(e, half, "numpy"), atol=1e-6)
    # a real-valued image too (the feature score box-filters D)
    d = rng.random((12, 9)).astype(np.float32)
    np.testing.assert_allclose(M.led(d, half, backend), M.led(d, half, "numpy"), atol=1e-5)


@pytest.mark.parametrize("backend", KERNEL_BACKENDS)
@pytest.mark.parametrize("block,levels", [(1, 2), (4, 8), (6, 16), (8, 64)])
def test_block_entropy_kernel_against_numpy(backend, block, levels):
    rng = np.random.default_rng(block)
    hard = rng.integers(0, levels, (31, 45)).astype(np.float64)
    soft = rng.random((31, 45)) * (levels - 1)
    soft[0, :5] = levels - 1  # the top level exactly
    for q in (hard, soft):
        out = M.block_entropy(q, block, levels, backend)
        assert out.shape == (31 - block + 1, 45 - block + 1)
        np.testing.assert_allclose(out, M.block_entropy(q, block, levels, "numpy"), atol=2e-6)


def test_block_entropy_rejects_bad_levels():
    with pytest.raises(ValueError):
        M.block_entropy(np.full((4, 4), 8.0), 2, 8)
    with pytest.raises(ValueError):
        M.block_entropy(np.zeros((4, 4)), 2, 65)
    with pytest.raises(ValueError):
        M.block_entropy(np.zeros((3, 4)), 4, 8)


# --- registration and stitching on a sample photograph ------------------------------------


def _photo(name="astronaut"):
    import skimage.data
    return getattr(skimage.data, name)()


def _crop(img, origin, shape, angle_deg=0.0):
    """img[origin + c + R(angle) (q - c)] for q over a crop of `shape` (c its centre), bilinear."""
    h, w = shape
    c = np.array([(h - 1) / 2.0, (w - 1) / 2.0])
    qy, qx = np.mgrid[0:h, 0:w].astype(np.float64)
    a = np.deg2rad(angle_deg)
    sy = origin[0] + c[0] + np.cos(a) * (qy - c[0]) + np.sin(a) * (qx - c[1])
    sx = origin[1] + c[1] - np.sin(a) * (qy - c[0]) + np.cos(a) * (qx - c[1])
    chans = [img] if img.ndim == 2 else [img[..., k] for k in range(img.shape[2])]
    out = [ndimage.map_coordinates(ch.astype(np.float64), [sy, sx], order=1, mode="reflect") for ch in chans]
    return out[0] if img.ndim == 2 else np.stack(out, -1)


def _truth(origin_left, origin_right, shape, angle_deg, left_point):
    h, w = shape
    c = np.array([(h - 1) / 2.0, (w - 1) / 2.0])
    d = np.asarray(origin_left, float) + left_point - np.asarray(origin_right, float) - c
    a = np.deg2rad(angle_deg)
    return c + np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]) @ d


def _u8(a):
    return np.clip(np.rint(a), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("name,origin_left,origin_right,angle,noise,gain,bias", [
    ("camera", (100, 20), (110, 190), 0.0, 2.0, 1.0, 0.0),
    ("astronaut", (100, 20), (95, 150), 1.2, 4.0, 0.85, 20.0),
    ("coffee", (60, 40), (70, 250), -1.6, 5.0, 1.15, -15.0),
])
def test_register_pair_within_a_pixel(name, origin_left, origin_right, angle, noise, gain, bias):
    img = _photo(name)
    rng = np.random.default_rng(7)
    shape = (300, 300)
    left = _u8(_crop(img, origin_left, shape) + rng.normal(0, noise, shape + img.shape[2:]))
    right = _u8(gain * _crop(img, origin_right, shape, angle) + bias + rng.normal(0, noise, shape + img.shape[2:]))
    pm = M.register_pair(left, right)
    truth = _truth(origin_left, origin_right, shape, angle, pm.left_point)
    assert np.abs(pm.right_point - truth).max() <= 1.0
    assert abs(pm.angle - angle) <= 1.0
    assert pm.correlation >= M.MosaicParams().min_correlation


def test_stitch_three_photographs_back_into_one():
    img = _photo("astronaut")
    shape = (260, 220)
    origins = [(60, 10), (66, 150), (58, 280)]
    parts = [img[y:y + shape[0], x:x + shape[1]] for y, x in origins]
    result = M.stitch(parts, backend="numpy")
    assert isinstance(result, M.Mosaic)
    rel = result.offsets - result.offsets[0]
    np.testing.assert_allclose(rel, np.array(origins, float) - origins[0], atol=1.0)
    np.testing.assert_allclose(result.angles, 0.0, atol=1.0)
    # where the mosaic is covered it reproduces the photograph
    top = int(round(result.offsets[0][0])) - origins[0][0]
    left0 = int(round(result.offsets[0][1])) - origins[0][1]
    y0, y1 = 66, 60 + shape[0]
    x0, x1 = 10, 280 + shape[1]
    got = result.image[y0 + top:y1 + top, x0 + left0:x1 + left0].astype(float)
    want = img[y0:y1, x0:x1].astype(float)
    assert result.image.dtype == np.uint8 and result.image.shape[2] == 3
    assert np.abs(got - want).mean() < 4.0


def test_stitch_vertical_sequence():
    img = _photo("camera")
    parts = [img[20:220, 100:400], img[150:350, 96:396]]
    result = M.stitch([p for p in parts], backend="numpy", vertical=True)
    np.testing.assert_allclose(result.offsets[1] - result.offsets[0], [130.0, -4.0], atol=1.0)


def test_no_overlap_is_an_error():
    img = _photo("camera")
    left = img[50:350, 0:250]
    right = _photo("coins")[0:300, 0:250]
    with pytest.raises(M.MosaicError, match="no overlap found|no edges"):
        M.register_pair(left, right, names=("a.png", "b.png"))


def test_too_small_is_an_error():
    with pytest.raises(M.MosaicError, match="too small"):
        M.register_pair(np.zeros((30, 40), np.uint8), np.zeros((30, 40), np.uint8))
    with pytest.raises(M.MosaicError, match="at least two"):
        M.stitch([np.zeros((300, 300), np.uint8)])


# --- command line ---------------------------------------------------------------------------


def _write_png(path, array):
    from PIL import Image
    Image.fromarray(array).save(path)
    return str(path)


def test_cli_stitches_and_refuses_bad_input(tmp_path, capsys):
    from PIL import Image

    from relicgpu.cli import main
    img = _photo("astronaut")
    a = _write_png(tmp_path / "a.png", img[40:300, 0:260])
    b = _write_png(tmp_path / "b.png", img[44:304, 170:430])
    out = tmp_path / "out" / "mosaic.png"
    assert main(["mosaic", a, b, "-o", str(out), "--backend", "numpy"]) == 0
    stitched = np.asarray(Image.open(out))
    assert stitched.shape[1] == pytest.approx(430, abs=2) and stitched.shape[0] == pytest.approx(264, abs=2)
    assert not list(out.parent.glob(".*.tmp"))  # atomic: no temporary left behind

    assert main(["mosaic", a, str(tmp_path / "missing.png"), "-o", str(out)]) == 2
    assert "missing.png: no such file" in capsys.readouterr().err
    bad = tmp_path / "bad.png"
    bad.write_text("not an image")
    assert main(["mosaic", a, str(bad), "-o", str(out)]) == 2
    assert "bad.png: cannot read as an image" in capsys.readouterr().err
    assert main(["mosaic", a, b, "-o", a]) == 2
    assert "refusing to overwrite an input" in capsys.readouterr().err
    tiny = _write_png(tmp_path / "tiny.png", img[:20, :20])
    assert main(["mosaic", tiny, b, "-o", str(out)]) == 2
    assert "too small" in capsys.readouterr().err
    assert main(["mosaic", a, "-o", str(out)]) == 2
    assert main(["mosaic", a, b, "-o", str(tmp_path / "out.xyz")]) == 2
    assert "unknown image suffix" in capsys.readouterr().err


def test_isotropy_tells_edges_from_corners():
    y, x = np.mgrid[0:40, 0:40]
    edge = (x > 20).astype(float) * 100
    corner = ((x > 20) & (y > 20)).astype(float) * 100
    checker = (((x // 5) + (y // 5)) % 2).astype(float) * 100
    assert M.isotropy(edge, (20, 20), 30) < 0.01
    assert M.isotropy(corner, (20, 20), 30) > 0.3
    assert M.isotropy(checker, (20, 20), 30) > 0.8


def test_large_photographs_are_registered_shrunk_then_refined():
    img = ndimage.zoom(_photo("astronaut")[..., 1].astype(float), 3, order=1)  # 1536 x 1536
    rng = np.random.default_rng(9)
    shape, origin_left, origin_right, angle = (1100, 1000), (200, 20), (230, 560), 0.8
    left = _u8(_crop(img, origin_left, shape) + rng.normal(0, 3, shape))
    right = _u8(_crop(img, origin_right, shape, angle) + rng.normal(0, 3, shape))
    pm = M.register_pair(left, right)
    assert "full_resolution" in pm.timings  # 1100 px > max_size: two scales
    truth = _truth(origin_left, origin_right, shape, angle, pm.left_point)
    assert np.abs(pm.right_point - truth).max() <= 1.0


def test_one_variance_floor_from_the_given_noise():
    rng = np.random.default_rng(5)
    img = 100.0 + rng.normal(0, 3.0, (60, 60))
    p = M.MosaicParams(coarse_sigma=0.0, corr_bandpass=())
    prep = M.prepare_image(img, p, noise=10.0)
    want = M.local_normalise(M.median3(img), p.norm_window, p.norm_mean, p.norm_var, var_floor=(2.0 * 10.0) ** 2)
    np.testing.assert_allclose(prep.normalised, want)
    own = M.prepare_image(img, p)  # its own estimate, about 3: a far lower floor, so more contrast
    assert own.normalised.std() > 2.0 * prep.normalised.std()


def _placement(centre, right_point, corr, k=0, refined=True):
    region = M.FeatureRegion(centre, 42, None, None, None)
    m = M.EntropyMatch(right_point[0], right_point[1], 0.0, 1.0, 1.0)
    return M.Placement(k, region, m, 0, np.array(right_point, float), 0.0, corr, refined)


def test_decide_needs_a_margin_and_votes():
    p = M.MosaicParams()
    a = _placement((100, 300), (90, 100), 0.95, k=0)
    same = _placement((200, 300), (190.5, 100.0), 0.93, k=1)     # another region, 0.5 px from a's placement
    rival = _placement((100, 300), (90, 130), 0.92, k=0)         # 30 px away
    near = _placement((100, 300), (93, 100), 0.99, k=0, refined=False)  # within distinct_px: the same placement
    assert R._placement_distance(a, same) == pytest.approx(0.5)
    best, margin = R._decide([a, near], p, final=False)
    assert best is None  # one region only, and not the last
    best, margin = R._decide([a, near], p, final=True)
    assert best is a and margin == pytest.approx(0.95 + 1.0)
    best, margin = R._decide([a, same, near], p, final=False)
    assert best is a  # two regions refined onto it
    better = _placement((200, 300), (190.2, 100.0), 0.97, k=1)  # within a pixel of a, correlating higher
    assert R._decide([a, better], p, final=False)[0] is a  # the earlier region's (the paper's) is reported
    best, margin = R._decide([a, same, rival], p, final=True)
    assert best is None and margin == pytest.approx(0.03)  # a rival within min_margin
    low = _placement((100, 300), (90, 100), 0.4, k=0)
    assert R._decide([low], p, final=True)[0] is None  # below min_correlation


def test_overlap_correlation_ignores_a_smooth_gradient():
    # a ramp correlates with itself shifted along it on the raw image, not once band-passed
    yy, xx = np.mgrid[0:120, 0:120].astype(float)
    rng = np.random.default_rng(3)
    img = 2.0 * xx + rng.normal(0, 3.0, xx.shape)
    p = M.MosaicParams()
    prep = M.prepare_image(img, p)
    raw_p = M.MosaicParams(corr_bandpass=())
    raw_prep = M.prepare_image(img, raw_p)
    assert M.overlap_correlation(prep, prep, (60, 60), (60, 60), 0.0, p) > 0.99   # the same place
    shifted = M.overlap_correlation(prep, prep, (60, 60), (30, 60), 0.0, p)      # 30 px along the isolines
    raw = M.overlap_correlation(raw_prep, raw_prep, (60, 60), (30, 60), 0.0, raw_p)
    assert raw > 0.8 and shifted < 0.3


def test_refine_placement_recovers_offset_and_angle():
    img = _photo("camera").astype(float)
    rng = np.random.default_rng(11)
    shape, origin_left, origin_right, angle = (240, 240), (120, 60), (130, 200), 1.3
    left = _crop(img, origin_left, shape) + rng.normal(0, 4, shape)
    right = 0.9 * _crop(img, origin_right, shape, angle) + 10 + rng.normal(0, 4, shape)
    p = M.MosaicParams()
    pl, pr = M.prepare_image(left, p), M.prepare_image(right, p)
    centre = (120, 200)
    truth = _truth(origin_left, origin_right, shape, angle, np.array(centre, float))
    start = truth + np.array([2.5, -3.0])
    before = M.overlap_correlation(pl, pr, centre, start, 0.0, p)
    point, found, corr = M.refine_placement(pl, pr, centre, start, 0.0, p)
    assert np.abs(point - truth).max() < 0.25 and abs(found - angle) < 0.1
    assert corr > 0.9 > before
