"""Issue 15, items 3 and 2: results do not depend on units, and scans that are not closed meshes
(sparse point clouds with or without normals, open meshes) are matched."""
import numpy as np
import pytest

from relicgpu import match_pair, synth
from relicgpu.heap.assembly import assemble
from relicgpu.pair.icp import rotation_angle_deg
from relicgpu.params import Params
from relicgpu.io.fragment import Fragment
from relicgpu.cloud.points import even_subsample

# (factor, offset): unit size; millimetres with the scans hundreds of millimetres from the origin;
# a thousandth of the size
UNITS = [(1000.0, 400.0), (0.001, 0.0)]


def _rescaled(fragments, factor, offset, seed=7):
    """The fragments in other units: scaled by `factor`, each moved by its own random offset of
    about `offset` (in the new units). Returns the fragments and the (3,) offsets."""
    rng = np.random.default_rng(seed)
    shifts = [offset * rng.normal(size=3) for _ in fragments]
    return [Fragment(f.name, f.vertices * factor + t, f.faces) for f, t in zip(fragments, shifts)], shifts


def _back_in_unit_size(transform, factor, shift_to, shift_from):
    """A transform between rescaled fragments (from one moved by shift_from onto one moved by
    shift_to) as the transform between the unit-size fragments."""
    out = np.eye(4)
    out[:3, :3] = transform[:3, :3]
    out[:3, 3] = (transform[:3, 3] + transform[:3, :3] @ shift_from - shift_to) / factor
    return out


def _pose_gap(t1, t2, points):
    """Rotation (degrees) between two transforms and the RMS distance between the points they move."""
    rot = rotation_angle_deg(t1[:3, :3] @ t2[:3, :3].T)
    d = points @ (t1[:3, :3] - t2[:3, :3]).T + (t1[:3, 3] - t2[:3, 3])
    return rot, float(np.sqrt((d ** 2).sum(1).mean()))


def test_even_subsample_is_the_same_in_any_units():
    pts = np.random.default_rng(0).normal(size=(5000, 3)) * [1.0, 0.5, 0.2]
    idx = even_subsample(pts, 700)
    assert 600 <= len(idx) <= 700
    assert np.array_equal(idx, np.unique(idx))
    for factor, offset in UNITS:
        assert np.array_equal(even_subsample(pts * factor + offset, 700), idx)


@pytest.fixture(scope="module")
def heap():
    return synth.generate("vase", pieces=3, seed=1, faces=3000, noise=0.0005, progress=False)


def test_the_same_heap_in_other_units_gives_the_same_assembly(heap):
    frags = heap.fragments
    ref = assemble(frags, backend="numpy", progress=False, workers=1)
    assert all(p is not None for p in ref.poses) and len(set(ref.groups)) == 1
    size = float(np.median([f.size for f in frags]))
    for factor, offset in UNITS:
        moved, shifts = _rescaled(frags, factor, offset)
        other = assemble(moved, backend="numpy", progress=False, workers=1)
        assert other.groups == ref.groups
        for i in range(1, len(frags)):
            # the pose of fragment i relative to fragment 0, in each run
            rel = np.linalg.inv(np.asarray(other.poses[0])) @ np.asarray(other.poses[i])
            rel_ref = np.linalg.inv(np.asarray(ref.poses[0])) @ np.asarray(ref.poses[i])
            rot, rms = _pose_gap(_back_in_unit_size(rel, factor, shifts[0], shifts[i]), rel_ref, frags[i].vertices)
            assert rot < 1e-3 and rms < 1e-6 * size, (factor, i, rot, rms)


@pytest.mark.parametrize("backend", ["numpy", "warp-cpu"])
def test_a_pair_in_other_units_gives_the_same_pose(heap, backend):
    if backend == "warp-cpu":
        pytest.importorskip("warp")  # a machine without warp (the lent GPU host as it comes) skips it
    a, b = heap.fragments[heap.touching[0][0]], heap.fragments[heap.touching[0][1]]
    ref = match_pair(a, b, backend=backend)
    assert ref.accepted, ref.reason
    for factor, offset in UNITS:
        (ma, mb), (sa, sb) = _rescaled([a, b], factor, offset)
        m = match_pair(ma, mb, backend=backend)
        assert m.accepted, m.reason
        rot, rms = _pose_gap(_back_in_unit_size(m.transform, factor, sa, sb), ref.transform, b.vertices)
        # float32 kernels round differently at another scale; the pose still agrees closely
        assert rot < 0.05 and rms < 1e-4 * b.size, (factor, rot, rms)


# --- item 2: scans that are not closed meshes -----------------------------------

def _cloud_pair(shape, seed, with_normals, n=2500):
    """A synthetic two-piece break as sparse clouds (n surface points a piece, noise 0.05% of the
    size) and the transform carrying b onto a. Also the true fracture label of every point."""
    import trimesh

    from relicgpu.cloud.points import cloud_fragment

    r = synth.generate(shape, pieces=2, seed=seed, faces=4000, noise=0.0005, progress=False)
    frags, labels = [], []
    for i, f in enumerate(r.fragments):
        mesh = f.to_trimesh()
        p, face = trimesh.sample.sample_surface(mesh, n, seed=100 * seed + i)
        p = p + np.random.default_rng(7 * seed + i).normal(size=p.shape) * 0.0005 * f.size
        frags.append(cloud_fragment(f.name, p, mesh.face_normals[face] if with_normals else None))
        labels.append(r.fracture_faces[i][face])
    return frags, labels, np.linalg.inv(r.poses[0]) @ r.poses[1]


def _with_holes(fragment, skin, rng, holes=3, radius=0.06):
    """The mesh with `holes` round holes (radius a fraction of its size) cut into its skin faces."""
    centres = fragment.vertices[fragment.faces].mean(axis=1)
    cut = np.zeros(len(centres), bool)
    for k in rng.choice(np.flatnonzero(skin), holes, replace=False):
        cut |= np.linalg.norm(centres - centres[k], axis=1) < radius * fragment.size
    faces = fragment.faces[~cut]
    used = np.unique(faces)
    remap = np.full(len(fragment.vertices), -1)
    remap[used] = np.arange(len(used))
    return Fragment(fragment.name, fragment.vertices[used], remap[faces].astype(np.int32))


def _assert_right(result, b, truth):
    assert result.accepted, result.reason
    rot, rms = _pose_gap(result.transform, truth, b.vertices)
    assert rot < 2.0 and rms < 0.01 * b.size, (rot, rms)


def test_estimated_normals_face_outward_and_fracture_points_rank_rough():
    from scipy.stats import rankdata

    from relicgpu.cloud.points import estimate_normals, fracture_likelihood

    # a board's broad faces meet its rim at right angles; a vase's thin wall shows both faces
    for shape in ("torso", "slab", "vase"):
        (a, _), (label, _), _ = _cloud_pair(shape, 1, with_normals=True)
        normals = estimate_normals(a.vertices)
        assert np.mean(np.einsum("ij,ij->i", normals, a.normals) > 0) > 0.95
        score = rankdata(fracture_likelihood(a.vertices, normals))
        auc = (score[label].sum() - label.sum() * (label.sum() + 1) / 2) / (label.sum() * (~label).sum())
        assert auc > 0.85


def test_estimated_normals_of_a_thin_shell_face_out_on_both_faces():
    from relicgpu.cloud.points import estimate_normals

    # a hemispherical sherd whose wall (3% of its radius) is about one point spacing thick: its
    # inner face must not be seen through the outer one, nor take its side over links across the
    # wall (both did: 20% of the normals turned the wrong way)
    rng = np.random.default_rng(0)
    points, normals = [], []
    for radius, side in ((1.0, 1.0), (0.97, -1.0)):
        d = rng.normal(size=(4000, 3))
        d = d / np.linalg.norm(d, axis=1)[:, None]
        d = d[d[:, 2] < 0]
        points.append(radius * d + rng.normal(size=d.shape) * 0.001)
        normals.append(side * d)
    points, normals = np.vstack(points), np.vstack(normals)
    assert np.mean(np.einsum("ij,ij->i", estimate_normals(points), normals) < 0) < 0.03


# a thin-walled vase (narrow break), a torso and a slab, with and without normals
# (issue 15, without normals: torso seed 2's first pick held a third of its large break; slab seed
# 2's right pose was rejected for interpenetration its estimated normals made up far from the other
# surface; slab seed 9 was accepted 2.4 degrees off, turned about its narrow break, before the skin
# across the seam held it: relicgpu.pair.seam)
@pytest.mark.parametrize("shape,seed,with_normals", [("vase", 0, True), ("vase", 0, False), ("torso", 0, True),
                                                     ("slab", 9, False),
                                                     ("torso", 0, False), ("torso", 1, True), ("torso", 1, False),
                                                     ("slab", 1, True), ("torso", 2, False),
                                                     ("slab", 2, False)])
def test_sparse_clouds_are_matched_on_their_points(shape, seed, with_normals):
    (a, b), _, truth = _cloud_pair(shape, seed, with_normals)
    _assert_right(match_pair(a, b, backend="numpy"), b, truth)


def test_cloud_interpenetration_counts_only_near_the_other_surface():
    from relicgpu.backends import resolve
    from relicgpu.pair.cloudmatch import MAX_PENETRATION, PENETRATION_REACH, cloud_penetration
    from relicgpu.pair.verify import SurfaceSample

    be = resolve("numpy")
    g = np.stack(np.meshgrid(np.linspace(0, 1, 21), np.linspace(0, 1, 21)), -1).reshape(-1, 2)
    up = np.tile([0.0, 0.0, 1.0], (len(g), 1))
    far = np.array([[10.0, 10.0, 10.0]])  # fracture samples away from the test: no contact zone

    def sample(z):
        pts = np.column_stack([g, np.full(len(g), z)])
        return SurfaceSample(far, np.zeros(1, np.int64), up[:1], pts, up)

    depth, contact = 0.01, 0.01
    a = sample(0.0)  # a's solid lies below z = 0
    inside = cloud_penetration(a, sample(-2 * depth), np.eye(4), depth, contact, be.nearest_index)
    assert inside == 1.0  # b's skin two depths inside a, within reach
    beyond = cloud_penetration(a, sample(-(PENETRATION_REACH + 2) * depth), np.eye(4), depth, contact, be.nearest_index)
    assert beyond == 0.0  # beyond the reach the nearest normal says nothing (verify's mesh check reaches 8)
    touching = cloud_penetration(a, sample(-0.5 * depth), np.eye(4), depth, contact, be.nearest_index)
    assert touching <= MAX_PENETRATION


def test_clouds_are_verified_on_their_own_interpenetration_measured_once():
    from relicgpu.backends import resolve
    from relicgpu.pair.cloudmatch import cloud_penetration, verify_clouds
    from relicgpu.pair.verify import SurfaceSample, verify

    be = resolve("numpy")
    g = np.stack(np.meshgrid(np.linspace(0, 1, 21), np.linspace(0, 1, 21)), -1).reshape(-1, 2)
    up = np.tile([0.0, 0.0, 1.0], (len(g), 1))
    frac = np.column_stack([g * 0.2 + 2.0, np.zeros(len(g))])  # both fracture samples in contact, away from the skins

    def sample(z):
        return SurfaceSample(frac, np.zeros(len(frac), np.int64), up, np.column_stack([g, np.full(len(g), z)]), up)

    depth, contact = 0.01, 0.01
    a, sunk = sample(0.0), sample(-2 * depth)
    args = (np.eye(4), be, contact, 1.0, 0.1, depth)
    plain = verify(a, sunk, *args, None, be.nearest_index, mutual=True)
    assert plain.accepted and np.isnan(plain.penetration)  # None: not measured, not refused on
    assert not verify(a, sunk, *args, 0.5, be.nearest_index, mutual=True).accepted
    ver = verify_clouds(a, sunk, *args, be.nearest_index)
    assert ver.penetration == cloud_penetration(a, sunk, np.eye(4), depth, contact, be.nearest_index) == 1.0
    assert not ver.accepted and ver.reason.startswith("interpenetration")
    assert verify_clouds(a, sample(0.0), *args, be.nearest_index, min_facing=0.0).accepted  # skins laid alike


@pytest.mark.parametrize("shape,seed", [("vase", 0), ("torso", 0), ("slab", 0)])
def test_open_meshes_with_holes_in_the_skin_are_matched(shape, seed):
    r = synth.generate(shape, pieces=2, seed=seed, faces=4000, noise=0.0005, progress=False)
    rng = np.random.default_rng(seed)
    a, b = (_with_holes(f, ~frac, rng) for f, frac in zip(r.fragments, r.fracture_faces))
    _assert_right(match_pair(a, b, backend="numpy"), b, np.linalg.inv(r.poses[0]) @ r.poses[1])


def test_a_cloud_that_does_not_close_loads_as_points(tmp_path):
    from relicgpu.io.load import load_fragment
    from relicgpu.cloud.points import CloudFragment

    d = np.c_[np.random.default_rng(0).uniform(size=(2500, 2)), np.zeros(2500)]  # an open, flat sheet
    np.savetxt(tmp_path / "shell.xyz", d)
    frag = load_fragment(tmp_path / "shell.xyz")
    assert isinstance(frag, CloudFragment) and len(frag.faces) == 0 and frag.normals is None
    assert any("matched on its points" in n for n in frag.notes)
    moved = frag.transformed(np.diag([1.0, -1.0, -1.0, 1.0]))
    assert isinstance(moved, CloudFragment) and np.allclose(moved.vertices[:, 2], -frag.vertices[:, 2])


def test_crease_regions_split_a_cloud_at_its_creases_with_and_without_normals():
    from relicgpu.pair.cloudmatch import crease_regions
    from relicgpu.cloud.points import estimate_normals

    # a box's six faces (sides 1, 0.8, 0.6): six smooth regions between its creases
    rng = np.random.default_rng(0)
    half = np.array([0.5, 0.4, 0.3])
    pts, normals = [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            p = rng.uniform(-half, half, size=(int(3000 * np.prod(np.delete(half, axis)) / 0.47), 3))
            p[:, axis] = sign * half[axis]
            n = np.zeros_like(p)
            n[:, axis] = sign
            pts.append(p)
            normals.append(n)
    truth = np.concatenate([np.full(len(p), k) for k, p in enumerate(pts)])
    pts, normals = np.concatenate(pts), np.concatenate(normals)
    for given in (normals, None):
        regions = crease_regions(pts, estimate_normals(pts, given), given is not None)
        assert len(regions) == 6
        for region in regions:  # each region lies on one face, and holds most of it
            labels = np.bincount(truth[region], minlength=6)
            assert labels.max() == len(region)
            assert len(region) > (0.9 if given is not None else 0.6) * np.sum(truth == labels.argmax())


def _corpus_cloud_pair(family, seed, pair, with_normals=True, noise=0.0005):
    """A clean two-piece object of the independent corpus (not relicgpu.synth) as sparse clouds,
    drawn as scripts/bench_clouds.py draws its pair `pair` (noise a share of the size), and the
    transform carrying b onto a."""
    import trimesh

    from relicgpu.synth import corpus
    from relicgpu.cloud.points import cloud_fragment

    r = corpus.generate(family, pieces=2, seed=seed, faces=4000)
    frags = []
    for i, f in enumerate(r.fragments):
        mesh = f.to_trimesh()
        p, face = trimesh.sample.sample_surface(mesh, 2500, seed=100 * pair + i)
        p = p + np.random.default_rng(7 * pair + i).normal(size=p.shape) * noise * f.size
        frags.append(cloud_fragment(f.name, p, mesh.face_normals[face] if with_normals else None))
    return frags, np.linalg.inv(r.poses[0]) @ r.poses[1]


def test_a_clean_smooth_break_is_matched_on_its_crease_regions():
    """A break with no roughness (a smooth cut of the independent corpus, not relicgpu.synth)."""
    frags, truth = _corpus_cloud_pair("smooth-clean", 0, 1)
    result = match_pair(*frags, backend="numpy")
    assert result.reason.startswith("accepted (crease regions"), result.reason
    _assert_right(result, frags[1], truth)


@pytest.mark.parametrize("seed, pair, with_normals", [(2, 9, True), (3, 13, False)])
def test_a_smooth_cut_whose_regions_hold_skin_is_matched_on_its_skin(seed, pair, with_normals):
    """A smooth curved cut whose crease regions run on into the skin past a shallow rim: its right
    fit touches over a fifth of the regions and faces 0.80 (seed 2; under the region bars, so it
    was missed), and wins on the skin across its seam among the looser fits of curved regions."""
    frags, truth = _corpus_cloud_pair("smooth-clean", seed, pair, with_normals)
    result = match_pair(*frags, backend="numpy")
    assert "touching over" in result.reason and "its skin continues" in result.reason, result.reason
    _assert_right(result, frags[1], truth)


def test_a_cloud_sampled_without_noise_reads_a_roughness_floor():
    """Points drawn off an exact plane read no roughness of their own; every residual bound read
    off it would be 0 (`cloudmatch.ROUGHNESS_FLOOR`). A noisy plane reads its noise."""
    from relicgpu.pair.cloudmatch import ROUGHNESS_FLOOR, point_spacing, roughness

    rng = np.random.default_rng(1)
    plane = np.c_[rng.uniform(0, 1, (800, 2)), np.zeros(800)]
    assert roughness(plane) == pytest.approx(ROUGHNESS_FLOOR * point_spacing(plane))
    noisy = plane + np.c_[np.zeros((800, 2)), 0.01 * rng.normal(size=800)]
    assert roughness(noisy) > 2 * ROUGHNESS_FLOOR * point_spacing(noisy)


def test_a_flat_cut_sampled_without_noise_is_matched():
    """A Voronoi cut's clouds without normals drawn off the exact surface (no scanner noise): its
    planes read roughness 0 and their fits' residual bound with it, and the right fit was refused
    (before `cloudmatch.ROUGHNESS_FLOOR`: none accepted, overlap 0.01)."""
    frags, truth = _corpus_cloud_pair("voronoi-clean", 0, 2, with_normals=False, noise=0.0)
    result = match_pair(*frags, backend="numpy")
    assert result.reason.startswith("accepted (a flat cut"), result.reason
    _assert_right(result, frags[1], truth)


def test_flat_regions_are_not_matched_on_their_skin_alone():
    """Two flat crease regions hold a fit in neither its slide nor its turn in the plane: the
    looser region fits of a Voronoi cut (seed 44, the flat-cut path off: its fit is accepted 1.1
    degrees and 1.1% of the size off) are not taken on their skin (without
    `cloudmatch.LOOSE_CURVED` it was accepted 7-10 degrees off)."""
    from relicgpu.pair.cloudmatch import curvedness

    frags, truth = _corpus_cloud_pair("voronoi-clean", 44, 178)
    result = match_pair(*frags, Params().with_(min_plane=None), backend="numpy")
    assert "touching over" not in result.reason, result.reason
    if result.accepted:
        _assert_right(result, frags[1], truth)
    rng = np.random.default_rng(0)
    disc = np.c_[rng.uniform(-1, 1, (500, 2)), 0.001 * rng.normal(size=500)]
    cap = np.c_[disc[:, :2], 0.3 * (disc[:, :2] ** 2).sum(1)]
    assert curvedness(disc) < 0.005 < 0.05 < curvedness(cap)


@pytest.mark.parametrize("family, seed, pair", [("voronoi-clean", 47, 190), ("rough-clean", 19, 76)])
def test_a_pick_fit_whose_skin_does_not_continue_is_refused(family, seed, pair):
    """Clouds without normals whose roughness picks passed a face laid on a face, 154 and 73
    degrees off (the skin beside the seam continued the partner's over 9 of 360 and 1 of 137
    points): refused for it, then left unmatched (Voronoi seed 47) or matched right on the crease
    regions (rough seed 19)."""
    frags, truth = _corpus_cloud_pair(family, seed, pair, with_normals=False)
    result = match_pair(*frags, backend="numpy")
    if result.accepted:
        _assert_right(result, frags[1], truth)
    else:
        assert result.reason.startswith("the skin beside its seam does not continue"), result.reason


@pytest.mark.parametrize("seed", [16, 52])
def test_a_piece_with_no_rough_point_is_matched_on_its_wide_pick(seed):
    """A piece's first fracture pick is empty (no point over its median roughness): the wide
    pick's fit is verified (seed 16), and left as it is by the polish on the skin (seed 52), on
    the wide pick, not on nothing (both raised before)."""
    frags, truth = _corpus_cloud_pair("rough-clean", seed, 4 * seed)
    result = match_pair(*frags, backend="numpy")
    _assert_right(result, frags[1], truth)


@pytest.mark.parametrize("with_normals", [True, False])
def test_the_rough_class_is_picked_where_it_is_most_of_a_piece(with_normals):
    """An inner piece of a many-piece break is mostly break (78% here): a pick above its median
    roughness holds a tenth of it, the rough class of Otsu's split most of it; a piece that is
    mostly skin has no such class (no point)."""
    import trimesh

    from relicgpu.synth import corpus
    from relicgpu.pair.cloudmatch import cloud_likelihood

    def picks(fragment, labels, seed):
        mesh = fragment.to_trimesh()
        p, face = trimesh.sample.sample_surface(mesh, 2500, seed=seed)
        given = mesh.face_normals[face] if with_normals else None
        truth = np.asarray(labels, bool)[face]
        return truth, cloud_likelihood(p, given) >= 0.5, cloud_likelihood(p, given, majority=True) >= 0.5

    r = corpus.generate("rough-clean", pieces=5, seed=0, faces=3000)
    truth, first, rough = picks(r.fragments[3], r.fracture_faces[3], 3)
    assert truth.mean() > 0.7
    assert (first & truth).sum() < 0.15 * truth.sum()
    assert (rough & truth).sum() > 0.7 * truth.sum() and (rough & truth).sum() > 0.7 * rough.sum()
    slab = synth.generate("slab", pieces=2, seed=0, faces=4000, noise=0.0005, progress=False)
    truth, first, rough = picks(slab.fragments[0], slab.fracture_faces[0], 0)
    assert (first & truth).sum() > 0.9 * truth.sum() and not rough.any()


def test_a_piece_that_is_mostly_break_is_matched_on_its_rough_class(monkeypatch):
    """A rough break scanned without normals whose pieces read mostly rough (corpus seed 10):
    the picks above the median roughness find no fit, the crease regions none either; the rough
    classes of both pieces match right. Such a fit is not held on the skin after (`held_by_skin`):
    the Blender cube's inner shards 1 and 11 at 20,000 points, right to 0.1 degree on their rough
    classes, were refused as loose and held by 1 skin point (an inner piece has no skin there)."""
    import relicgpu.pair.pipeline as pl

    frags, truth = _corpus_cloud_pair("rough-clean", 10, 40, with_normals=False)
    refused = lambda pa, pb, params, be, scale, result: pl.replace(result, accepted=False, reason="held by none")
    monkeypatch.setattr(pl, "held_by_skin", refused)
    result = match_pair(*frags, backend="numpy")
    assert "mostly break" in result.reason, result.reason
    _assert_right(result, frags[1], truth)


def test_a_mostly_break_pair_keeps_the_fit_that_touches_most_of_those_that_pass(monkeypatch):
    """Inner cells of a Blender cube (shards 15 and 16 at 20,000 points) passed, on their rough classes,
    a fit 5.2 degrees off (overlap 0.127) before the right one (0.137): that reading verifies every fit
    and keeps the one that touches most less its penetration. Here the rough pair above, its fits
    scripted: the truth turned 3 degrees about the break (it passes, touching less) before the truth."""
    from dataclasses import replace

    import trimesh

    import relicgpu.pair.pipeline as pl
    from relicgpu.pair.icp import apply

    frags, truth = _corpus_cloud_pair("rough-clean", 10, 40, with_normals=False)
    params, be = Params(), pl.resolve("numpy")
    scale = pl.pair_scale(*frags, params)
    pa, pb = (pl._as_prepared(f, params, be, scale) for f in frags)
    centre = apply(truth, pb.sample.fracture).mean(axis=0)
    turn = trimesh.transformations.rotation_matrix(np.radians(3.0), [1.0, 0, 0], centre) @ truth
    none = np.zeros((0, 2), np.int64)
    real_fits = pl._candidate_fits
    monkeypatch.setattr(pl, "_candidate_fits", lambda *a: ([(turn, -1, -1, none), (truth, -1, -1, none)],
                                                           real_fits(*a)[1]))
    unmatched = pl.PairMatch(np.eye(4), False, 0.0, np.inf, 0.0, 0.0, none, -1, -1, "no fit")
    p = pl.cloud_params(params, frags, scale)
    first = pl._match_prepared(*(replace(x, sample=s) for x, s in zip((pa, pb), pl.majority_samples(frags, p, scale))),
                               p, be, None, scale, {"prepare": 0.0})
    assert first.accepted and np.allclose(first.transform, turn)  # the first that passes, elsewhere
    result = pl._match_majority(pa, pb, p, be, scale, {"prepare": 0.0}, unmatched)
    assert result.accepted and np.allclose(result.transform, truth), result.reason
    assert result.overlap > first.overlap


@pytest.mark.parametrize("with_normals", [True, False])
def test_the_skin_does_not_decide_between_flat_regions_laid_on_each_other(with_normals):
    """A flat cut through a rounded solid (the corpus's Voronoi cell, scanned with and without
    normals): with the flat-cut path aside, its flat crease regions' fits were decided by the skin
    beside the seam (`pipeline._by_skin`). Two flat faces of skin laid on each other continue each
    other's skin too, wherever the faces beside them lie in one plane (a board's half turn, 0.50;
    the Blender cube's shards, 0.23 on one CPU): the skin now decides among curved regions' fits
    only, and a flat cut is the planes' (`cutfit`), which matches this one right."""
    frags, truth = _corpus_cloud_pair("voronoi-clean", 0, 2, with_normals)
    aside = match_pair(*frags, params=Params(min_plane=None), backend="numpy")
    assert "its skin continues the partner's" not in aside.reason, aside.reason
    assert not aside.accepted or _pose_gap(aside.transform, truth, frags[1].vertices)[0] < 2.0, aside.reason
    result = match_pair(*frags, backend="numpy")
    assert result.reason.startswith("accepted (a flat cut"), result.reason
    _assert_right(result, frags[1], truth)


def test_a_board_s_faces_laid_on_each_other_half_a_turn_off_are_not_taken_on_their_skin(monkeypatch):
    """A bookshelf of boards 0.02 thick cut rough (seed 1, with normals): two boards' flat faces
    laid on each other half a turn off continued each other's skin 0.50 across the seam and won the
    skin's vote (179.5 degrees off; the boards' fit asked after it put it right). The vote now
    takes no fit of flat regions, and the pair is matched right."""
    from relicgpu.pair import pipeline

    (a, b), truth, _ = _thin_cloud_pair("shelf02-rough", 1, 11)
    won, real = [], pipeline._by_skin

    def by_skin(*args, **kwargs):
        out = real(*args, **kwargs)
        won.append(out)
        return out

    monkeypatch.setattr(pipeline, "_by_skin", by_skin)
    result = match_pair(a, b, backend="numpy")
    _assert_right(result, b, truth)
    for fit in won:
        assert fit is None or _pose_gap(fit.transform, truth, b.vertices)[0] < 2.0, fit.reason


def test_a_flat_cut_is_matched_on_its_rim():
    """A flat cut whose crease regions fit at two turns alike (voronoi seed 9: refused as
    ambiguous by the region path, 179 degrees apart): its plane laid on the partner's, turned
    and slid until the skin beside the two rims agrees (`planar`), is right."""
    frags, truth = _corpus_cloud_pair("voronoi-clean", 9, 38)
    result = match_pair(*frags, backend="numpy")
    assert result.reason.startswith("accepted (a flat cut"), result.reason
    _assert_right(result, frags[1], truth)
    rot, _ = _pose_gap(result.transform, truth, frags[1].vertices)
    assert rot < 0.5, rot


def test_a_flat_cut_without_normals_is_matched_on_its_rim():
    """The same without scanned normals (voronoi seed 16): the normals estimated at the rim lean
    towards the cut, and its crease regions fit at two poses alike (refused as ambiguous); with
    the rim's normals fitted on the skin alone (`planar.RIM_NEIGHBOURS`) its flat cut is right."""
    frags, truth = _corpus_cloud_pair("voronoi-clean", 16, 66, with_normals=False)
    result = match_pair(*frags, backend="numpy")
    assert result.reason.startswith("accepted (a flat cut"), result.reason
    _assert_right(result, frags[1], truth)


@pytest.mark.parametrize("seed, pair, with_normals", [(36, 36, True), (39, 158, False)])
def test_a_flat_cut_held_alike_at_several_poses_is_decided_by_its_skin(seed, pair, with_normals):
    """A flat cut whose rim and face are held alike at poses a few degrees or a slide apart (voronoi
    seed 36; seed 39 without normals: 0.2 and 6 degrees within 0.01) was refused as ambiguous; the
    skin beside the seam continues the partner's most at the right one (seed 39: 0.78 against 0.23),
    and no fit at another turn comes near it."""
    frags, truth = _corpus_cloud_pair("voronoi-clean", seed, pair, with_normals)
    result = match_pair(*frags, backend="numpy")
    assert result.reason.startswith("accepted (a flat cut") and "its skin continues" in result.reason, result.reason
    _assert_right(result, frags[1], truth)


@pytest.mark.parametrize("seed, with_normals", [(84, True), (63, False)])
def test_a_flat_cut_is_turned_in_its_plane_to_where_its_skin_continues(seed, with_normals, monkeypatch):
    """A flat cut's turn in its plane read off its sparse rims alone is a few degrees off (voronoi seed 84:
    3.7 degrees, 2.0% of the size; seed 63 without normals: 1.7 degrees, 1.05%); turned about the cut's
    normal to where the skin beside the seam continues the partner's most (`cutfit.turned_to_skin`), it is
    right."""
    from relicgpu.pair import cutfit

    frags, truth = _corpus_cloud_pair("voronoi-clean", seed, seed, with_normals)
    result = match_pair(*frags, backend="numpy")
    assert result.reason.startswith("accepted (a flat cut"), result.reason
    _assert_right(result, frags[1], truth)
    monkeypatch.setattr(cutfit, "SKIN_TURN_DEG", 0.0)
    monkeypatch.setattr(cutfit, "SKIN_SLIDE", 0.0)
    rims_only = match_pair(*frags, backend="numpy")
    rot, rms = _pose_gap(rims_only.transform, truth, frags[1].vertices)
    assert rims_only.accepted and (rot > 1.5 or rms > 0.01 * frags[1].size), (rot, rms)


def test_a_flat_cut_is_slid_in_its_plane_to_where_its_skin_continues(monkeypatch):
    """A flat cut's slide in its plane is read off its sparse rims too (voronoi seed 67 without normals: 0.3
    degrees but 1.1% of the object's size off, turned alone, 0.3% once slid); slid along the cut's axes to where the skin beside the seam
    continues the partner's most (`cutfit.turned_to_skin`), it is right."""
    from relicgpu.pair import cutfit

    frags, truth = _corpus_cloud_pair("voronoi-clean", 67, 67, with_normals=False)
    result = match_pair(*frags, backend="numpy")
    assert result.reason.startswith("accepted (a flat cut"), result.reason
    _assert_right(result, frags[1], truth)
    slid = _pose_gap(result.transform, truth, frags[1].vertices)[1]
    monkeypatch.setattr(cutfit, "SKIN_SLIDE", 0.0)
    turned_only = match_pair(*frags, backend="numpy")
    rot, rms = _pose_gap(turned_only.transform, truth, frags[1].vertices)
    assert turned_only.accepted and rms > 2 * slid, (rot, rms, slid)


def test_a_loose_fit_its_skin_does_not_hold_is_refused():
    """A flat cut without normals whose roughness picks are skin, not break (voronoi seed 62), fits loosely at
    half a turn off, and its polish on the skin across the seam is held by 16 points: nothing sets it, so it
    is refused (`skinhold.LOOSE_HELD`) instead of accepted 145 degrees off."""
    frags, _ = _corpus_cloud_pair("voronoi-clean", 62, 62, with_normals=False)
    result = match_pair(*frags, backend="numpy")
    assert not result.accepted
    assert result.reason.startswith("unsettled: loose on its break"), result.reason


def test_a_flat_cut_that_fits_at_two_poses_is_refused():
    """A flat cut whose rim and face are held alike at turns 90 degrees apart, and whose skin
    beside the seam continues the partner's alike at both (voronoi seed 38: 0.62 and 0.56, the
    one continuing more the wrong one): refused as ambiguous rather than guessed."""
    frags, _ = _corpus_cloud_pair("voronoi-clean", 38, 154)
    result = match_pair(*frags, backend="numpy")
    assert not result.accepted
    assert result.reason.startswith("ambiguous: a flat cut"), result.reason


def test_a_thin_walls_break_is_matched_on_its_bands():
    """A vessel's wall cut through (the corpus's vessel-clean seed 2, with normals): both picks are
    bands a spacing or two wide, whose right fit faces 0.38 (under `MIN_FACING`; refused before)
    and is matched as a thin cut once the skin across its seam holds it and continues on."""
    from relicgpu.pair.cloudmatch import cloud_sample, cloud_skin, point_spacing, thin_pick

    frags, truth = _corpus_cloud_pair("vessel-clean", 2, 11)
    result = match_pair(*frags, backend="numpy")
    assert result.reason.startswith("accepted (thin walls' bands"), result.reason
    _assert_right(result, frags[1], truth)
    solid, _ = _corpus_cloud_pair("rough-clean", 0, 0)
    for f, thin in ((frags[0], True), (solid[0], False)):
        points = np.asarray(f.vertices)
        sample = cloud_sample(points, f.normals, Params(), float(np.ptp(points, 0).max()))
        assert thin_pick(cloud_skin(f, sample)[0], sample, point_spacing(points)) is thin


def test_a_sherd_laid_upside_down_on_its_band_is_refused_on_its_axes():
    """A rescanned vessel's two sherds with normals (the corpus's vessel-noisy seed 3): the thin
    walls' bands took a fit 178 degrees off, 50 of 118 skin points beside the seam continuing the
    partner's. There the sherds' axes of revolution, read off the scanned normals, lie 43 degrees
    apart (`skinhold.on_axes`): refused, as a mesh's fit would be."""
    frags, truth = _corpus_cloud_pair("vessel-noisy", 3, 15)
    result = match_pair(*frags, backend="numpy")
    if result.accepted:
        _assert_right(result, frags[1], truth)
    else:
        assert "axes of revolution do not meet" in result.reason, result.reason


def test_a_rescanned_vessel_s_sherds_are_matched_with_one_axis_laid_on_the_other():
    """Vessel-noisy seed 15 with normals: every reading's fit failed its checks (overlap 0.07 at 159
    degrees off); started with one sherd's axis of revolution laid on the other's (`sheets.axis_fit`)
    and checked as sherds of one vessel (`sheets.axis_check`), it is matched right."""
    frags, truth = _corpus_cloud_pair("vessel-noisy", 15, 15)
    result = match_pair(*frags, backend="numpy")
    assert result.reason.startswith("accepted (axis laid on axis"), result.reason
    _assert_right(result, frags[1], truth)


def test_sherds_whose_picks_hold_their_lips_are_matched_on_their_seam():
    """Vessel-noisy seed 13 with normals: the picks hold the lips and bases as well as the break, so
    even the true pose overlaps 0.11 of them (under `Params.min_overlap`) and every reading refused
    it. An axis fit is not asked to overlap: its seam, the skin beside it continuing the partner's
    along a break's length (`sheets.AXIS_SEAM`), holds it: matched right."""
    frags, truth = _corpus_cloud_pair("vessel-noisy", 13, 13)
    result = match_pair(*frags, backend="numpy")
    assert result.reason.startswith("accepted (axis laid on axis"), result.reason
    _assert_right(result, frags[1], truth)


def test_clouds_that_their_normals_do_not_match_are_matched_on_their_points_alone():
    """Smooth-clean seed 11 with normals: every path on the given normals refuses it (its best fit
    touches none of the break); as if scanned without normals, matched right, and said so
    (`Params.points_alone`). Without it, refused."""
    frags, truth = _corpus_cloud_pair("smooth-clean", 11, 45)
    result = match_pair(*frags, backend="numpy")
    assert result.reason.endswith("(on the points alone, the given normals set aside)"), result.reason
    _assert_right(result, frags[1], truth)
    assert not match_pair(*frags, Params(points_alone=False), backend="numpy").accepted


def test_thin_walls_whose_normals_a_program_fitted_are_matched_with_the_walls_normals():
    """Vessel-clean seed 0 with normals fitted to the points (12-nearest planes, as a scanner's
    software writes them): across a wall two spacings thick they blend both faces, nothing matches
    on them, and both picks are thin walls' bands, so the points alone are not asked; the wall's own
    normals (`cloud.wall_normals`) match it, and say so. Without `Params.points_alone`, refused."""
    from relicgpu.cloud.points import cloud_fragment, estimate_normals

    bare, truth = _corpus_cloud_pair("vessel-clean", 0, 3, with_normals=False)
    frags = [cloud_fragment(f.name, f.vertices, estimate_normals(f.vertices)) for f in bare]
    result = match_pair(*frags, backend="numpy")
    assert result.reason.endswith("(with a thin wall's normals, the given normals set aside)"), result.reason
    _assert_right(result, frags[1], truth)
    assert not match_pair(*frags, Params(points_alone=False), backend="numpy").accepted


def test_a_boards_fit_laying_the_axes_apart_lets_the_axes_be_laid_on_each_other():
    """Vessel-noisy seed 52 with normals: its picks are thin walls' bands, and the boards' starts
    (`sheets.sheet_fit`) passed a fit 17 degrees off whose axes of revolution do not meet. Refused
    at the pipeline's end, it kept the axis starts from being asked; refused where it was found, it
    lets them be: matched right."""
    frags, truth = _corpus_cloud_pair("vessel-noisy", 52, 52)
    result = match_pair(*frags, backend="numpy")
    assert result.reason.startswith("accepted (axis laid on axis"), result.reason
    _assert_right(result, frags[1], truth)


def test_a_sherd_laid_on_the_other_s_wall_is_not_taken_from_its_axis():
    """Vessel-noisy seed 20 with normals: of its axis fits, those 77-82 degrees off lay one sherd where
    it overlaps the other on their surface of revolution (0.015-0.020 sunk, over
    `sheets.AXIS_INSIDE`), and those half a turn off touch along a seam of 0.007 of the scale squared
    (under `sheets.AXIS_SEAM`): not taken."""
    frags, truth = _corpus_cloud_pair("vessel-noisy", 20, 20)
    result = match_pair(*frags, backend="numpy")
    if result.accepted:
        _assert_right(result, frags[1], truth)


def test_a_cloud_reads_its_axis_of_revolution_off_its_scanned_normals_alone():
    """A wall of a cylinder (radius 1, a third of a turn, 0.05 thick) scanned with normals holds its
    axis; a flat board's normals hold none, nor does a cloud scanned without normals."""
    from relicgpu.cloud.points import cloud_fragment
    from relicgpu.pair.prepare import prepare

    rng = np.random.default_rng(0)
    angle, height = rng.uniform(0, 2 * np.pi / 3, 3000), rng.uniform(0, 1.5, 3000)
    radius = np.where(rng.random(3000) < 0.5, 1.0, 0.95)
    radial = np.c_[np.cos(angle), np.sin(angle), np.zeros(3000)]
    wall = radial * radius[:, None] + np.c_[np.zeros((3000, 2)), height]
    normals = radial * np.where(radius == 1.0, 1.0, -1.0)[:, None]
    axis = prepare(cloud_fragment("wall", wall, normals), backend="numpy").sample.axis
    assert axis is not None and abs(axis.direction[2]) > 0.99
    assert np.linalg.norm(axis.foot[:2]) < 0.02
    board = np.c_[rng.uniform(0, 1, (3000, 2)), np.where(rng.random(3000) < 0.5, 0.0, 0.02)]
    facing = np.c_[np.zeros((3000, 2)), np.where(board[:, 2] > 0, 1.0, -1.0)]
    assert prepare(cloud_fragment("board", board, facing), backend="numpy").sample.axis is None
    assert prepare(cloud_fragment("bare", wall, None), backend="numpy").sample.axis is None


def test_a_thin_walls_cloud_without_normals_is_matched_with_the_walls_normals():
    """A vessel's wall two point spacings thick, scanned without normals (the corpus's vessel-clean
    seed 15): the usual estimate's planes span both faces and nothing is matched; with each face's
    normals and the break strip's between them (`cloud.wall_normals`) the bands are."""
    frags, truth = _corpus_cloud_pair("vessel-clean", 15, 15, with_normals=False)
    result = match_pair(*frags, backend="numpy")
    assert result.reason.endswith("(with a thin wall's normals; the clouds had none)"), result.reason
    _assert_right(result, frags[1], truth)


def test_a_thin_walls_fit_without_normals_whose_axes_do_not_meet_is_refused():
    """Vessel-clean seed 21 without normals: with the thin wall's normals its bands pass at a fit 23
    degrees off, which carries one sherd's axis of revolution 22 degrees off the other's; refused
    (the right fits so found keep the axes within 0.8-5.6 degrees), where the reading finds it
    (`skinhold.on_axes`, or within the thin paths) or after (`match_pair`'s own ask)."""
    frags, _ = _corpus_cloud_pair("vessel-clean", 21, 21, with_normals=False)
    result = match_pair(*frags, backend="numpy")
    assert not result.accepted
    said = result.reason.partition("with a thin wall's normals")[2]
    assert "the two pieces' axes of revolution do not meet" in said, result.reason


def test_a_thin_walls_fit_a_few_degrees_off_is_polished_home():
    """Two sherds of a 5-piece vessel (the corpus's vessel-clean seed 4, pieces 0 and 2) as clouds,
    started 3.3 degrees off: the usual skin gate holds nothing at first and the band alone polishes
    the fit 11 degrees off; with the gate widened at first (`THIN_WIDE_GATE`) it comes home."""
    import trimesh

    from relicgpu.backends import resolve
    from relicgpu.cloud.points import cloud_fragment
    from relicgpu.pair import cloudmatch, pipeline
    from relicgpu.pair.icp import axis_rotation
    from relicgpu.pair.verify import index_cache
    from relicgpu.synth import corpus

    r = corpus.generate("vessel-clean", pieces=5, seed=4, faces=3000)
    clouds = []
    for i in (0, 2):
        f = r.fragments[i]
        mesh = f.to_trimesh()
        p, face = trimesh.sample.sample_surface(mesh, 2500, seed=400 + i)
        p = p + np.random.default_rng(28 + i).normal(size=p.shape) * 0.0005 * f.size
        clouds.append(cloud_fragment(f.name, p, mesh.face_normals[face]))
    truth = np.linalg.inv(r.poses[0]) @ r.poses[2]
    be, params = resolve("numpy"), Params()
    scale = pipeline.pair_scale(*clouds, params)
    pa, pb = (pipeline._as_prepared(c, params, be, scale) for c in clouds)
    params = cloudmatch.cloud_params(params, clouds, scale)
    skins = [cloudmatch.cloud_skin(p.fragment, p.sample) for p in (pa, pb)]
    spacing = max(cloudmatch.point_spacing(np.asarray(c.vertices)) for c in clouds)
    axis = np.random.default_rng(0).normal(size=3)
    off = np.eye(4)
    off[:3, :3] = axis_rotation(axis / np.linalg.norm(axis), np.radians(3.3))
    centre = pa.sample.fracture.mean(0)
    off[:3, 3] = centre - off[:3, :3] @ centre
    found = cloudmatch.thin_wall_fit(skins, [pa.sample, pb.sample], [off @ truth], spacing, params, scale, be,
                                     index_cache(be))
    assert found is not None
    assert rotation_angle_deg(found[0][:3, :3] @ truth[:3, :3].T) < 2.0
    narrow, _ = cloudmatch.seam.seam_polish(
        pa.sample.fracture, pa.sample.fracture_normals, pb.sample.fracture, *skins, off @ truth,
        params.contact_distance * scale, scale, be.nearest_index(pa.sample.fracture))
    assert rotation_angle_deg(narrow[:3, :3] @ truth[:3, :3].T) > 5.0


def test_a_fit_slid_along_its_break_is_polished_on_the_skin():
    """A flat Voronoi cut of the independent corpus (seed 45, without normals): the break's own
    polish leaves the fit slid along it (1.9 degrees and over 1% of the size off); polished on the
    skin across the seam it continues the partner's skin far better, and is right."""
    frags, truth = _corpus_cloud_pair("voronoi-clean", 45, 182, with_normals=False)
    result = match_pair(*frags, backend="numpy")
    assert "slid on its break" in result.reason, result.reason
    _assert_right(result, frags[1], truth)


def test_a_loose_fit_is_polished_with_the_gate_whose_skin_continues():
    """A smooth cut of the independent corpus (seed 7, with normals): loose on its break, polished
    on the skin with the usual gate it stays 2.6 degrees off (40 skin points held); with the gate
    widened at first its skin continues the partner's better, and it is right."""
    frags, truth = _corpus_cloud_pair("smooth-clean", 7, 29)
    result = match_pair(*frags, backend="numpy")
    assert "loose on its break" in result.reason, result.reason
    _assert_right(result, frags[1], truth)


def test_a_faceted_skin_sampled_with_face_normals_still_shows_its_break(monkeypatch):
    from relicgpu.cloud import points

    # a plant's faceted leaves and pot, sampled with their face normals as a CAD model's cloud is:
    # neighbours at exactly 0 degrees dragged the rough break under the split (nothing picked)
    (a, _), _, (truth, _) = _thin_cloud_pair("plant-rough", 1, 17)

    def picked():
        return points.fracture_likelihood(a.vertices, a.normals) >= 0.5

    pick = picked()
    assert (pick & truth).sum() >= 0.5 * truth.sum() and (pick & truth).sum() >= 0.2 * pick.sum()
    monkeypatch.setattr(points, "EMPTY_PICK", 0.0)  # the first reading alone
    assert (picked() & truth).sum() < 0.1 * truth.sum()


def _thin_cloud_pair(family, seed, k, noise=0.0005):
    """bench_clouds' pair k: the two halves of `relicgpu.synth.thin` family seed as 2,500 points
    each with their face normals (noise a share of the size), the truth carrying b onto a, and
    each point's fracture label."""
    import trimesh

    from relicgpu.cloud.points import cloud_fragment
    from relicgpu.synth import thin

    r = thin.generate(family, seed=seed)
    clouds, labels = [], []
    for i, f in enumerate(r.fragments):
        mesh = f.to_trimesh()
        p, face = trimesh.sample.sample_surface(mesh, 2500, seed=100 * k + i)
        p = p + np.random.default_rng(7 * k + i).normal(size=p.shape) * noise * f.size
        clouds.append(cloud_fragment(f.name, p, mesh.face_normals[face]))
        labels.append(np.asarray(r.fracture_faces[i])[face])
    return clouds, np.linalg.inv(r.poses[0]) @ r.poses[1], labels


def test_a_bookshelf_s_sparse_clouds_in_files_are_matched_on_their_points_and_normals(tmp_path, capsys):
    """Two 2,500-point clouds of a bookshelf cut flat, with their scan normals, as a user gives them:
    meshed, such a cloud closed into a slab the segmentation misread, and its normals were dropped
    (0 of 18 thin pairs right that way). Read as points with their normals, the pair is matched."""
    import json

    from relicgpu.cli import main

    (a, b), truth, _ = _thin_cloud_pair("shelf04-flat", 0, 3)
    paths = []
    for f in (a, b):
        paths.append(tmp_path / f"{f.name}.xyz")
        np.savetxt(paths[-1], np.c_[f.vertices, f.normals])
    assert main(["match", *map(str, paths), "-o", str(tmp_path / "m"), "--backend", "numpy"]) == 0
    assert "2500 points with normals; matched on its points and their normals" in capsys.readouterr().err
    doc = json.loads((tmp_path / "m" / "match.json").read_text())
    assert doc["accepted"], doc["reason"]
    rot, rms = _pose_gap(np.array(doc["transform"]), truth, b.vertices)
    assert rot < 2.0 and rms < 0.01 * b.size, (rot, rms)


def test_two_boards_front_edges_laid_on_each_other_are_no_thin_cut():
    """A bookshelf of boards 0.02 thick cut rough: its boards' front edges pick as bands as its
    break does, and were accepted laid on each other, half a turn off (`thin_wall_fit`). Their
    contact has one normal on both sides, a break's does not (`one_face_seam`)."""
    from relicgpu.backends import resolve
    from relicgpu.pair.cloudmatch import one_face_seam
    from relicgpu.pair.verify import SurfaceSample, index_cache

    (a, b), truth, _ = _thin_cloud_pair("shelf02-rough", 0, 2)
    result = match_pair(a, b, backend="numpy")
    assert not result.accepted or _pose_gap(result.transform, truth, b.vertices)[0] < 2.0, result.reason

    rng = np.random.default_rng(0)
    strip = np.column_stack([rng.uniform(0, 1, 200), rng.uniform(0, 0.02, 200), np.zeros(200)])
    flat = np.tile([0.0, 0.0, 1.0], (200, 1))
    rough = flat + rng.normal(size=(200, 3)) * 0.3
    rough /= np.linalg.norm(rough, axis=1)[:, None]
    def sample(normals):
        return SurfaceSample(strip, np.zeros(200, np.int64), normals, strip, normals)
    index_of = index_cache(resolve("numpy"))
    assert one_face_seam(sample(flat), sample(-flat), np.eye(4), 0.02, index_of)
    assert not one_face_seam(sample(rough), sample(-rough), np.eye(4), 0.02, index_of)
    assert not one_face_seam(sample(flat), sample(-rough), np.eye(4), 0.02, index_of)


def test_crease_regions_that_touch_widest_where_one_is_flat_decide_nothing():
    """A bookshelf of boards 0.02 thick cut smooth: two of its boards' flat faces touch widest laid
    on each other half a turn off, and that touch alone was taken (`_match_regions`). A flat region
    holds no turn or slide, so the fit is refused there, and the thin walls' bands then find the
    break."""
    from relicgpu import match_pair

    (a, b), truth, _ = _thin_cloud_pair("shelf02-smooth", 11, 100)
    result = match_pair(a, b, backend="numpy")
    assert result.accepted and _pose_gap(result.transform, truth, b.vertices)[0] < 2.0, result.reason


def test_a_board_s_crease_regions_fit_gives_way_to_its_boards_fit():
    """A bookshelf of boards 0.02 thick cut smooth (seed 4, with normals): two of its boards' narrow
    faces, crease regions, laid on each other a quarter turn off, were accepted on their skin. Both
    picks are thin walls' bands, so the fit of the boards' breaks framed by their boards is asked
    first (`pipeline._boards_before_regions`), and it is right. Whether the regions' reading finds
    that quarter turn depends on the CPU's rounding (an AMD EPYC without AVX-512 finds the truth),
    so the guard is also handed that wrong fit itself."""
    from dataclasses import replace

    from relicgpu.backends import resolve
    from relicgpu.pair import pipeline
    from relicgpu.pair.cloudmatch import cloud_params
    from relicgpu.pair.prepare import prepare

    (a, b), truth, _ = _thin_cloud_pair("shelf02-smooth", 4, 37)
    result = match_pair(a, b, backend="numpy")
    assert "framed by their boards" in result.reason, result.reason
    _assert_right(result, b, truth)

    params, be = Params(), resolve("numpy")
    scale = pipeline.pair_scale(a, b, params)
    pa, pb = (prepare(f, params, be, scale=scale) for f in (a, b))
    params = cloud_params(params, (pa.fragment, pb.fragment), scale)
    centre = b.vertices.mean(0)
    quarter = np.eye(4)
    quarter[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    quarter[:3, 3] = centre - quarter[:3, :3] @ centre
    wrong = replace(result, transform=truth @ quarter, reason="accepted (crease regions)")
    assert _pose_gap(wrong.transform, truth, b.vertices)[0] > 45.0
    guarded = pipeline._boards_before_regions(pa, pb, params, be, scale, {}, wrong)
    assert "framed by their boards" in guarded.reason, guarded.reason
    _assert_right(guarded, b, truth)


def test_a_board_sampled_without_noise_is_held_by_its_skin():
    """A bookshelf's board cut flat, drawn off the exact surface: its skin's quadrics fit to 1e-17
    and gated by that, no partner's skin point held the right fit, which was refused as unsettled
    ("held at 1 points"; `seam.FIT_FLOOR`)."""
    (a, b), truth, _ = _thin_cloud_pair("shelf04-flat", 2, 21, noise=0.0)
    result = match_pair(a, b, backend="numpy")
    assert "the skin across the seam held it" in result.reason, result.reason
    _assert_right(result, b, truth)


def test_a_board_s_fit_is_polished_on_its_skin_with_the_usual_gate_as_well(monkeypatch):
    """A bookshelf of boards 0.02 thick cut smooth (seed 2, with normals): its one start that
    verifies, polished on the skin across the seam with the gate widened, is slid 1.1% of the size
    along its strips; polished with the usual gate it holds (`sheets.BOARD_GATES`)."""
    from relicgpu.pair import sheets

    (a, b), truth, _ = _thin_cloud_pair("shelf02-smooth", 2, 19)
    result = match_pair(a, b, backend="numpy")
    assert "framed by their boards" in result.reason, result.reason
    _assert_right(result, b, truth)
    monkeypatch.setattr(sheets, "BOARD_GATES", (sheets.THIN_WIDE_GATE,))
    result = match_pair(a, b, backend="numpy")
    assert result.accepted and _pose_gap(result.transform, truth, b.vertices)[1] > 0.01 * b.size


def test_a_flat_cut_laid_face_to_face_faces_as_any_cloud_fit_does():
    """A clean flat cut through a solid (the corpus's voronoi-clean seed 11, 2,500 points a piece
    with normals): its planes' fit is right, but was refused for facing under the region fits' bar
    (REGION_FACING): beside the cut the skin touches across the seam side by side (facing 0.69-0.79
    at such pairs' true poses). The planes lie face to face by construction, so the clouds' own
    facing bar is asked."""
    frags, truth = _corpus_cloud_pair("voronoi-clean", 11, 46)
    result = match_pair(*frags, backend="numpy")
    assert "flat cut" in result.reason, result.reason
    _assert_right(result, frags[1], truth)


def test_a_board_broken_across_is_matched_from_starts_framed_by_its_boards(backend, monkeypatch):
    """A bookshelf of boards 0.02 thick (about a point spacing) cut rough: the point-pair votes'
    fits lay the boards' narrow faces on each other, and no fit near the truth was among them
    (refused). One break point of each piece framed by its break normal and its board's normal
    fixes the pose up to the board's side (`sheets.sheet_starts`); the fit found so is right."""
    from relicgpu.pair import pipeline

    _thin_pair_right_and_refused_without(("shelf02-rough", 0, 2), "framed by their boards", backend, monkeypatch,
                                         pipeline, "sheet_fit", None)


def test_a_pot_broken_smooth_beside_faceted_leaves_is_matched_on_one_piece_s_creases(backend, monkeypatch):
    """A plant cut smooth through its pot: the piece holding the leaves and stem reads as rough on
    its faceted skin as on its break, so its roughness pick misses the break (refused). Its break
    read off its creases (`sheets.crease_fit`) against the partner's pick is matched right."""
    from relicgpu.pair import sheets

    _thin_pair_right_and_refused_without(("plant-smooth", 8, 79), "b's break read off its creases", backend,
                                         monkeypatch, sheets, "bulk_reads_rough", False)


def _thin_pair_right_and_refused_without(case, why, backend, monkeypatch, module, name, answer):
    """`_thin_cloud_pair(*case)` matched right with `why` in its reason, and (numpy) refused once
    `module.name` answers `answer` whatever it is asked."""
    (a, b), truth, _ = _thin_cloud_pair(*case)
    result = match_pair(a, b, backend=backend)
    assert why in result.reason, result.reason
    _assert_right(result, b, truth)
    if backend == "numpy":
        monkeypatch.setattr(module, name, lambda *args: answer)
        assert not match_pair(a, b, backend=backend).accepted


def test_a_board_s_broken_strip_is_read_off_its_creases_where_the_skin_reads_rough():
    """`sheets.crease_sample` picks the end strip of a board 0.02 thick (normals turned 90 degrees
    from both faces'), not its faces; `points.bulk_reads_rough` is false for the board's flat faces
    and true where every face's normals scatter as a break's do."""
    from relicgpu.cloud.points import bulk_reads_rough
    from relicgpu.pair.sheets import crease_sample
    from relicgpu.pair.verify import SurfaceSample

    rng = np.random.default_rng(2)
    faces = np.column_stack([rng.uniform(0, 0.5, 3200), rng.uniform(0, 0.3, 3200), np.repeat([0.0, 0.02], 1600)])
    end = np.column_stack([np.zeros(60), rng.uniform(0, 0.3, 60), rng.uniform(0, 0.02, 60)])
    points = np.concatenate([faces, end])
    normals = np.concatenate([np.repeat([[0, 0, -1.0], [0, 0, 1.0]], 1600, axis=0), np.tile([-1.0, 0, 0], (60, 1))])
    sample = SurfaceSample(points[:0], np.zeros(0, np.int64), normals[:0], points, normals)
    picked = crease_sample(points, normals, sample, Params(), 0.5)
    on_end = picked.fracture[:, 0] == 0.0
    assert on_end.sum() >= 45 and on_end.mean() >= 0.5, (on_end.sum(), len(on_end))
    np.testing.assert_allclose(picked.fracture_normals[on_end], [[-1.0, 0, 0]] * int(on_end.sum()))
    assert not bulk_reads_rough(points, normals)
    scattered = normals + rng.normal(scale=0.4, size=normals.shape)
    assert bulk_reads_rough(points, scattered / np.linalg.norm(scattered, axis=1, keepdims=True))


def test_a_break_point_is_framed_by_its_break_normal_and_its_boards():
    """`sheets.board_frames` on a board 0.02 thick (two faces) broken across at x = 0: each break
    point's frame is (its break normal, the board's normal up to its side, their cross product)."""
    from relicgpu.pair.sheets import board_frames
    from relicgpu.pair.verify import SurfaceSample

    rng = np.random.default_rng(1)
    faces = np.column_stack([rng.uniform(0, 0.5, 800), rng.uniform(0, 0.3, 800), np.repeat([0.0, 0.02], 400)])
    face_normals = np.repeat([[0, 0, -1.0], [0, 0, 1.0]], 400, axis=0)
    end = np.column_stack([np.zeros(60), rng.uniform(0, 0.3, 60), rng.uniform(0, 0.02, 60)])
    end_normals = np.tile([-1.0, 0, 0], (60, 1))
    sample = SurfaceSample(end, np.zeros(60, np.int64), end_normals, np.concatenate([faces, end]),
                           np.concatenate([face_normals, end_normals]))
    frames, which = board_frames(sample)
    assert len(which) == 60
    np.testing.assert_allclose(frames[:, :, 0], end_normals)
    np.testing.assert_allclose(np.abs(frames[:, 2, 1]), 1.0, atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(frames), 1.0, atol=1e-9)


def test_a_dense_cloud_is_matched_on_cloud_points_spread_evenly():
    """A cloud with normals denser than `Params.cloud_points` is prepared on that many of its own
    points, spread evenly, each with its own normal; the fragment itself keeps every point."""
    from relicgpu.cloud.points import cloud_fragment
    from relicgpu.pair.prepare import prepare, thinned_cloud

    rng = np.random.default_rng(3)
    d = rng.normal(size=(20000, 3)) * [1.0, 0.6, 0.3]
    n = d / np.linalg.norm(d, axis=1)[:, None]
    frag = cloud_fragment("e", n * [1.0, 0.6, 0.3], n)  # an ellipsoid's points, the sphere's normals
    p = prepare(frag, Params(cloud_points=5000), "numpy")
    got = p.fragment
    assert 4000 < len(got.vertices) <= 5000 and len(frag.vertices) == 20000
    row = {tuple(v): i for i, v in enumerate(frag.vertices)}
    i = np.array([row[tuple(v)] for v in got.vertices])
    assert np.array_equal(got.normals, frag.normals[i])
    # spread evenly: every point lies in a voxel of the thinning's grid that keeps one of them
    from scipy.spatial import cKDTree
    from relicgpu.cloud.points import choose_voxel
    gap = cKDTree(got.vertices).query(frag.vertices)[0].max()
    assert gap <= np.sqrt(3) * choose_voxel(frag.vertices, 5000) * (1 + 1e-9), gap
    assert thinned_cloud(frag, 0) is frag and thinned_cloud(frag, 20000) is frag
    bare = cloud_fragment("e", frag.vertices)  # no normals: kept whole
    assert thinned_cloud(bare, 5000) is bare
