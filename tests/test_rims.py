"""Rim agreement (verify.rim_agreement) and how match_pair weighs two readings' fits by it."""
from dataclasses import replace

import numpy as np
import pytest
import trimesh

import relicgpu.pair.pipeline as pl
from relicgpu.io.fragment import Fragment
from relicgpu.pair.icp import rotation_angle_deg
from relicgpu.pair.prepare import crease_points, prepare
from relicgpu.pair.verify import in_contact, index_cache, rim_agreement, sample_spacing
from relicgpu.params import Params


def _half(lo_x: float, hi_x: float, pose: np.ndarray) -> Fragment:
    """One half of a 2 x 1 x 0.5 block cut square at x = 1, finely triangulated, moved by pose."""
    box = trimesh.creation.box(bounds=[[lo_x, 0.0, 0.0], [hi_x, 1.0, 0.5]])
    v, f = trimesh.remesh.subdivide_to_size(box.vertices, box.faces, 0.04)
    return Fragment(f"half{lo_x:g}", v @ pose[:3, :3].T + pose[:3, 3], np.asarray(f, np.int32))


def _turn(axis: np.ndarray, angle_deg: float, about: np.ndarray) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = trimesh.transformations.rotation_matrix(np.radians(angle_deg), axis)[:3, :3]
    t[:3, 3] = about - t[:3, :3] @ about
    return t


@pytest.fixture(scope="module")
def halves():
    """The two halves prepared, b moved away; truth carries b's coordinates onto a's."""
    away = _turn(np.array([0.3, 1.0, 0.2]), 70.0, np.zeros(3))
    away[:3, 3] += [3.0, -1.0, 2.0]
    a, b = _half(0.0, 1.0, np.eye(4)), _half(1.0, 2.0, away)
    params = Params()
    pa, pb = (prepare(x, params, "numpy", scale=2.0) for x in (a, b))
    return pa, pb, np.linalg.inv(away), params


def test_crease_points_lie_along_the_edges_at_the_step():
    v = np.array([[0.0, 0, 0], [1.0, 0, 0], [1.0, 0.25, 0]])
    pts = crease_points(v, np.array([[0, 1], [1, 2]]), 0.1, 100)
    assert len(pts) == 10 + 3  # ceil(1 / 0.1) and ceil(0.25 / 0.1) pieces, a point at each middle
    assert np.allclose(pts[:, 2], 0) and np.all((pts[:, 1] == 0) | np.isclose(pts[:, 0], 1))
    assert crease_points(v, np.zeros((0, 2), np.int64), 0.1, 100).shape == (0, 3)


def test_in_contact_counts_points_between_sparse_samples_by_their_tangent_plane():
    # a plane sampled every 0.1, points on it between the samples, and points 0.03 above it
    g = np.arange(0.0, 1.01, 0.1)
    target = np.stack(np.meshgrid(g, g, [0.0]), -1).reshape(-1, 3)
    normals = np.tile([0.0, 0.0, 1.0], (len(target), 1))
    rng = np.random.default_rng(0)
    on = np.column_stack([rng.uniform(0.1, 0.9, (200, 2)), np.zeros(200)])
    off = on + [0.0, 0.0, 0.03]
    for pts, expect in ((on, True), (off, False)):
        from scipy.spatial import cKDTree
        dist, idx = cKDTree(target).query(pts)
        got = in_contact(pts, dist, idx, target, normals, 0.01, sample_spacing(target))
        assert np.all(got == expect)
        assert not np.all(in_contact(pts, dist, idx, target, None, 0.01, 0.1))  # by distance alone: sampling


def test_rims_agree_at_the_right_fit_and_not_at_a_turned_one(halves):
    pa, pb, truth, params = halves
    assert len(pa.sample.creases) > 50 and len(pb.sample.creases) > 50
    contact = params.contact_distance * 2.0
    index_of = index_cache(pl.resolve("numpy"))
    right = rim_agreement(pa.sample, pb.sample, truth, contact, index_of)
    # the cut face (1 x 0.5) turned a quarter about its normal: it lies on a's cut face, crosswise
    turned = _turn(np.array([1.0, 0, 0]), 90.0, np.array([1.0, 0.5, 0.25])) @ truth
    wrong = rim_agreement(pa.sample, pb.sample, turned, contact, index_of)
    assert right > 0.2 and wrong < 0  # right: the cut rim is 3 of the 10 units of each half's edges
    no_creases = replace(pa.sample, creases=None)
    assert rim_agreement(no_creases, pb.sample, truth, contact, index_of) == 0.0


def test_match_pair_takes_the_second_readings_fit_where_its_rims_agree_more(halves, monkeypatch):
    """Both readings pass a fit at different poses: the one whose rims meet the other's creases wins."""
    pa, pb, truth, params = halves
    pa, pb = (replace(p, second=p) for p in (pa, pb))  # the second reading: its fits are scripted below
    turned = _turn(np.array([1.0, 0, 0]), 90.0, np.array([1.0, 0.5, 0.25])) @ truth

    def fit(transform):
        return pl.PairMatch(transform, True, 0.5, 0.001, 0.5, 0.0, np.zeros((0, 2), np.int64), -1, -1, "accepted")

    for first, second, expect_second in ((turned, truth, True), (truth, turned, False)):
        calls = iter([fit(first), fit(second)])
        monkeypatch.setattr(pl, "_match_prepared", lambda *a, **k: next(calls))
        m = pl.match_pair(pa, pb, params, "numpy", scale=2.0)
        assert m.accepted
        assert rotation_angle_deg(m.transform[:3, :3] @ truth[:3, :3].T) < 1e-6
        assert ("(hybrid segmentation; its rims agree" in m.reason) == expect_second
        assert m.score == (0.25 if expect_second else 0.5)  # a second reading's fit scores half


def test_outline_points_find_a_rounded_crease_that_no_edge_angle_shows():
    """A unit cube with edges rounded (radius 0.04), meshed by marching cubes as a rescan would be:
    no edge is sharper than the crease angle, yet the outline points (where the surface turns
    within outline_radius) line the cube's edges and none lies on a face."""
    from skimage.measure import marching_cubes

    from relicgpu.pair.prepare import outline_points
    from relicgpu.pair.segment import segment

    step, radius = 0.02, 0.04
    axis = np.arange(-0.6, 0.6 + step, step)
    grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1)
    q = np.abs(grid) - (0.5 - radius)
    sdf = np.linalg.norm(np.maximum(q, 0), axis=-1) + np.minimum(q.max(-1), 0) - radius
    v, f, _, _ = marching_cubes(sdf, 0.0, spacing=(step,) * 3)
    mesh = trimesh.Trimesh(v + axis[0], f)
    params, scale = Params(), 1.7
    seg = segment(mesh.vertices, mesh.faces, params, scale, pl.resolve("numpy"))
    assert seg.edge_angle.max() < params.crease_angle_deg
    points = outline_points(mesh.vertices, mesh.faces, seg, params.outline_radius * scale, params.outline_spread, 3000)
    assert len(points) > 500
    near = np.abs(points) > 0.5 - 0.12  # per coordinate: near one of the two faces across it
    assert np.all(near.sum(axis=1) >= 2)  # near two faces at once: along an edge


def corpus_pair(family: str, seed: int):
    """The two fragments of a two-piece corpus object (6,000 faces a piece) and the truth
    carrying the second onto the first."""
    from relicgpu.synth import corpus

    r = corpus.generate(family, 2, seed, 6000)
    return r.fragments, np.linalg.inv(r.poses[0]) @ r.poses[1]


@pytest.fixture(scope="module")
def noisy_pair():
    """A two-piece object of smooth cuts, rescanned (noise, smoothing reconstruction, decimation)."""
    return corpus_pair("smooth-noisy", 0)


def test_a_rescanned_pair_is_accepted_on_its_outline_and_only_there(noisy_pair):
    """The right fit of a rescanned break mates less closely than max_rmse allows; it passes on its
    outline, scored half, on its skin where outlines are not consulted, and is refused for its
    residual where neither is."""
    (a, b), truth = noisy_pair
    m = pl.match_pair(a, b, Params(), "numpy")
    assert m.accepted and m.reason.startswith("accepted on its outline"), m.reason
    assert rotation_angle_deg(m.transform[:3, :3] @ truth[:3, :3].T) < 2.0
    assert abs(m.score - pl.OUTLINE_SCORE * m.overlap * (1 - m.penetration)) < 1e-9
    strict = pl.match_pair(a, b, Params(min_outline=None, min_skin=None), "numpy")
    assert not strict.accepted and strict.reason.startswith("residual"), strict.reason
    # its skin beside the seam runs on into the partner's: accepted on that where outlines are off
    skin = pl.match_pair(a, b, Params(min_outline=None), "numpy")
    assert skin.accepted and skin.reason.startswith("accepted on its skin"), skin.reason
    assert rotation_angle_deg(skin.transform[:3, :3] @ truth[:3, :3].T) < 2.0


def test_a_half_turn_whose_outline_agrees_but_whose_skin_does_not_continue_is_refused():
    """A flat rescanned break turned half a turn keeps its nearly symmetric outline but lays its
    sides across the partner's: the skin beside the seam does not continue (corpus voronoi-noisy
    seed 1, outlines agree 0.67, skin 0.02). With the fine stage on all pairs (`Params.fine_facing`
    None): accepted on its outline where the skin is not asked (`Params.outline_skin` and
    `Params.seam_skin` None), refused where it is. On the facing pairs the fine stage finds the
    right fit, accepted on its skin."""
    (a, b), truth = corpus_pair("voronoi-noisy", 1)
    unasked = pl.match_pair(a, b, Params(outline_skin=None, seam_skin=None, fine_facing=None), "numpy")
    assert unasked.accepted and unasked.reason.startswith("accepted on its outline"), unasked.reason
    assert rotation_angle_deg(unasked.transform[:3, :3] @ truth[:3, :3].T) > 90.0
    m = pl.match_pair(a, b, Params(fine_facing=None), "numpy")
    assert not m.accepted, m.reason
    now = pl.match_pair(a, b, Params(), "numpy")
    assert now.accepted and now.reason.startswith("accepted on its skin"), now.reason
    assert rotation_angle_deg(now.transform[:3, :3] @ truth[:3, :3].T) < 2.0


def test_a_thin_walls_fit_that_faces_too_little_is_accepted_on_its_rims():
    """A coarse vessel's break is a narrow band: at the right fit its skins beside the seam touch
    side by side over more points than the band faces the partner's (corpus vessel-coarse seed
    4 faces 0.03, under min_facing 0.06), but its rims lie on the partner's creases (0.52):
    accepted on them, scored half, and refused for facing where they are not asked."""
    (a, b), truth = corpus_pair("vessel-coarse", 4)
    m = pl.match_pair(a, b, Params(), "numpy")
    assert m.accepted and m.reason.startswith("accepted on its rims"), m.reason
    assert rotation_angle_deg(m.transform[:3, :3] @ truth[:3, :3].T) < 2.0
    assert abs(m.score - pl.OUTLINE_SCORE * m.overlap * (1 - m.penetration)) < 1e-9
    unasked = pl.match_pair(a, b, Params(facing_rims=None, second_segmentation=None), "numpy")
    assert not unasked.accepted and unasked.reason.startswith("facing"), unasked.reason


def test_assembly_joins_the_match_whose_rims_agree_before_a_better_scored_one(halves):
    """Two verified fits of one pair: the turned one scores more (a flat break laid on its partner
    crosswise touches as widely), the right one puts the rims together and is joined first."""
    from relicgpu.heap.forest import RIM_WEIGHT, Edge, grow_forest, rim_first

    pa, pb, truth, params = halves
    turned = _turn(np.array([1.0, 0, 0]), 90.0, np.array([1.0, 0.5, 0.25])) @ truth
    edges = [Edge(0, 1, turned, 0.9), Edge(0, 1, truth, 0.2)]
    samples = [pa.sample, pb.sample]
    weighed = rim_first(edges, samples, params, 2.0, pl.resolve("numpy"))
    assert [e.score for e in weighed] == [0.9, 0.2 + RIM_WEIGHT]
    assert [e.score for e in rim_first(edges, samples, params.with_(rim_priority=None), 2.0, "numpy")] == [0.9, 0.2]

    for given, right_used in ((weighed, True), (edges, False)):
        pose, group, _ = grow_forest(2, given, samples, params, 2.0, pl.resolve("numpy"))
        placed = np.linalg.inv(pose[0]) @ pose[1]
        assert group[0] == group[1]
        assert (rotation_angle_deg(placed[:3, :3] @ truth[:3, :3].T) < 1e-6) == right_used


def test_assemble_says_which_matches_were_weighed_first_for_their_rims(halves):
    """assembly.json's reason of a match weighed first, and the count in the stats (the bar set
    below any fit's agreement, then off)."""
    from relicgpu.heap.assembly import assemble

    pa, pb, _, params = halves
    for priority, expect in ((-1.0, 1), (None, 0)):
        asm = assemble([pa.fragment, pb.fragment], params.with_(rim_priority=priority, unit=2.0), "numpy",
                       engine="local", workers=1, progress=False)
        (m,) = asm.matches
        assert m.used and m.note.startswith("used: ")
        assert m.note.endswith("weighed first)") == bool(expect), m.note
        assert asm.stats["rims_first"] == expect


def test_a_fit_that_passed_only_in_the_band_asks_the_second_reading(halves, monkeypatch):
    """A first-reading fit accepted on its outline (a residual over the bound) whose rims agree
    less than the second reading's fit: the second's is taken, scored half; with
    `second_when_banded` off, or where the first fit passed every check, the first is kept."""
    pa, pb, truth, params = halves
    pa, pb = (replace(p, second=p) for p in (pa, pb))
    off = _turn(np.array([1.0, 0, 0]), 4.0, np.array([1.0, 0.5, 0.25])) @ truth  # its rims agree less, above 0

    def fit(transform, reason):
        return pl.PairMatch(transform, True, 0.5, 0.001, 0.5, 0.0, np.zeros((0, 2), np.int64), -1, -1, reason)

    banded = "accepted on its outline (outlines agree 0.40; residual 0.004 above 0.003)"
    cases = ((params, banded, True), (replace(params, second_when_banded=False), banded, False),
             (params, "accepted", False))
    for p, first_reason, expect_second in cases:
        calls = iter([fit(off, first_reason), fit(truth, "accepted")])
        monkeypatch.setattr(pl, "_match_prepared", lambda *a, **k: next(calls))
        m = pl.match_pair(pa, pb, p, "numpy", scale=2.0)
        assert m.accepted
        err = rotation_angle_deg(m.transform[:3, :3] @ truth[:3, :3].T)
        assert (err < 1e-6) == expect_second and ("(hybrid segmentation; its rims agree" in m.reason) == expect_second
        assert m.score == (0.25 if expect_second else 0.5)
        assert (next(calls, None) is None) == expect_second  # the second reading asked only where expected


def test_a_fit_that_passes_gives_way_to_one_in_the_band_whose_skin_continues():
    """On a noisy rescan every fit of a flat break lies near the residual bound: a break laid half a
    turn off on its partner's may pass while the right fit, a little rougher, falls in the band.
    The one passing in the band whose skin beside the seam continues at least SKIN_OVER times as
    much is taken (corpus voronoi-noisy seed 1: the right fit's skin 0.5, the half turn's 0.02);
    never the other way round, and not where the skin is not asked (`Params.min_skin` None)."""
    from relicgpu.pair.meshfit import skin_over_band, verify_mesh

    (a, b), truth = corpus_pair("voronoi-noisy", 1)
    params = Params()
    scale = pl.pair_scale(a, b, params)
    pa, pb = (prepare(x, params, "numpy", scale=scale) for x in (a, b))
    normal = pa.sample.fracture_normals.mean(axis=0)
    half = _turn(normal / np.linalg.norm(normal), 180.0, pa.sample.fracture.mean(axis=0)) @ truth
    index_of = index_cache(pl.resolve("numpy"))
    fits = [(t, verify_mesh(pa.sample, pb.sample, t, pl.resolve("numpy"), params, scale, index_of, params.max_rmse),
             -1, -1, None) for t in (truth, half)]
    over = skin_over_band(pa.sample, pb.sample, params, scale, fits[1], [fits[0]])
    assert over is not None and over[0] is truth and "that of a fit that passes" in over[1].reason
    assert skin_over_band(pa.sample, pb.sample, params, scale, fits[0], [fits[1]]) is None
    assert skin_over_band(pa.sample, pb.sample, params.with_(min_skin=None), scale, fits[1], [fits[0]]) is None


def test_the_fine_stage_holds_a_rescanned_thin_wall_at_its_fit_on_the_facing_pairs(backend):
    """A rescanned break's skin beside it, read as break, lies near the partner's skin facing the
    same way and holds the fine stage's fit of a thin wall's band off the truth (corpus
    vessel-noisy seed 2 at 12,000 faces a piece: a start 2 degrees off ends 1.0% of the size off).
    Between two fine meshes only pairs whose normals face each other are used (`Params.fine_facing`):
    0.4%. On coarse meshes (`Params.facing_edge`) the test is not made."""
    from relicgpu.pair.fine import facing_test, fine_stage
    from relicgpu.pair.icp import apply
    from relicgpu.synth import corpus

    r = corpus.generate("vessel-noisy", 2, 2, 12000)
    size, truth = corpus.object_size(r), np.linalg.inv(r.poses[0]) @ r.poses[1]
    params = Params()
    scale = pl.pair_scale(*r.fragments, params)
    pa, pb = (prepare(x, params, backend, scale=scale) for x in r.fragments)
    start = _turn(np.array([0.3, 1.0, 0.2]), 2.0, apply(truth, pb.sample.fracture.mean(axis=0))) @ truth
    index = backend.nearest_index(pa.sample.fracture)

    def off(p):
        pose = fine_stage(pa, pb, start[None], p, backend, scale, index, 1)[0][0]
        v = r.fragments[1].vertices
        return float(np.sqrt(((apply(pose, v) - apply(truth, v)) ** 2).sum(1).mean())) / size

    facing = facing_test(pa, pb, params, scale)
    assert facing is not None and facing[2] == params.fine_facing
    assert off(params) < 0.006
    assert off(params.with_(fine_facing=None)) > 0.008
    coarse = corpus.generate("vessel-coarse", 2, 2, 400)
    assert facing_test(*(prepare(x, params, "numpy", scale=scale) for x in coarse.fragments), params, scale) is None
