"""Assembly (issue 5): batched screening, the spanning forest, joint refinement, outputs,
the part-accuracy metric, and resuming a killed CLI run from its cache."""
import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import trimesh

from relicgpu import synth
from relicgpu.heap.forest import (APART_NOTE, CLASH_THICKNESS, NEAR_MISS, Edge, _inv, grow_forest, overlap_volume,
                                  penetration, refine_poses)
from relicgpu.heap.assembly import _finish_groups, assemble
from relicgpu.heap.outputs import closed_solid
from relicgpu.heap.screen import lcs_lengths_bitparallel, screen, select_candidates
from relicgpu.backends import numpy as ref
from relicgpu.heap.evaluate import score, score_assembly
from relicgpu.io.load import load_directory
from relicgpu.params import Params
from relicgpu.pair.icp import apply
from relicgpu.pair.verify import SurfaceSample, vertex_normals

SMALL = dict(shape="vase", pieces=4, seed=0, faces=1200)
# Small enough for the CLI and resume tests; many-piece objects are in the mixed-directory test
# below and in scripts/bench_assembly.py.
END_TO_END = dict(shape="vase", pieces=3, seed=1, faces=4000, noise=0.0005)
CLI = [sys.executable, "-c", "import sys; from relicgpu.cli import main; sys.exit(main())"]


# --- data -------------------------------------------------------------------------

@pytest.fixture(scope="module")
def broken():
    return synth.generate(**SMALL, progress=False)


@pytest.fixture(scope="module")
def synth_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth")
    synth.write(synth.generate(**END_TO_END, progress=False), out)
    return out


@pytest.fixture(scope="module")
def shared_cache(tmp_path_factory):
    return tmp_path_factory.mktemp("cache")


@pytest.fixture(scope="module")
def local_result(synth_dir, shared_cache):
    frags = load_directory(synth_dir / "fragments")
    return assemble(frags, backend="numpy", progress=False, cache_dir=shared_cache), frags


def truth_samples(result, n_points=1500):
    """Surface samples built from the synth truth (fracture faces known), so the forest
    can be tested apart from segmentation."""
    out = []
    for frag, frac in zip(result.fragments, result.fracture_faces):
        normals, areas = ref.face_normals(frag.vertices, frag.faces)
        vn = vertex_normals(frag.vertices, np.asarray(frag.faces, np.int64), normals, areas)
        fv = np.unique(frag.faces[frac].ravel())
        rng = np.random.default_rng(0)
        if len(fv) > n_points:
            fv = np.sort(rng.choice(fv, n_points, replace=False))
        sv = np.arange(len(frag.vertices))
        if len(sv) > 2 * n_points:
            sv = np.sort(rng.choice(sv, 2 * n_points, replace=False))
        known = {"fracture": frag.vertices[fv], "fracture_region": np.zeros(len(fv), np.int64),
                 "fracture_normals": vn[fv], "surface": frag.vertices[sv], "normals": vn[sv]}
        out.append(SurfaceSample(**{f.name: known[f.name] for f in dataclasses.fields(SurfaceSample) if f.name in known}))
    return out


def true_edges(result, rng, offset=0):
    return [Edge(i + offset, j + offset, _inv(result.poses[i]) @ result.poses[j], float(rng.uniform(0.4, 0.9)))
            for i, j in result.touching]


def scale_of(fragments):
    return float(np.median([f.size for f in fragments]))


def _rot(deg, axis, centre):
    from scipy.spatial.transform import Rotation
    m = np.eye(4)
    m[:3, :3] = Rotation.from_rotvec(np.radians(deg) * np.asarray(axis, float) / np.linalg.norm(axis)).as_matrix()
    m[:3, 3] = centre - m[:3, :3] @ centre
    return m


# --- screening ----------------------------------------------------------------------

def test_bitparallel_lcs_equals_the_reference_on_ties_and_boundaries():
    rng = np.random.default_rng(7)
    for _ in range(25):
        na, nb = rng.integers(1, 5), rng.integers(1, 5)
        la, lb = rng.integers(0, 90, na), rng.integers(0, 200, nb)
        step = rng.choice([0.125, 0.25, 0.5])  # coarse values: many ties and |a - b| == eps exactly
        a = np.round(rng.normal(size=la.sum()) / step) * step
        b = np.round(rng.normal(size=lb.sum()) / step) * step
        ao, bo = np.concatenate([[0], np.cumsum(la)]), np.concatenate([[0], np.cumsum(lb)])
        pairs = np.array([(i, j) for i in range(na) for j in range(nb)])
        eps = float(rng.choice([0.0, 0.125, 0.25, 0.3]))
        want = ref.lcs_lengths(a, ao, b, bo, pairs, eps)
        got = lcs_lengths_bitparallel(a, ao, b, bo, pairs, eps, chunk=2)
        np.testing.assert_array_equal(got, want)


def _fake_prepared(*contour_values):
    return SimpleNamespace(contours=[SimpleNamespace(fused=np.asarray(v, float)) for v in contour_values])


def test_screen_scores_the_mating_contour_highest_in_any_rotation_and_direction():
    rng = np.random.default_rng(3)
    x = rng.normal(size=120)
    mate = np.roll(x[::-1], 37) + rng.normal(0, 0.02, 120)  # opposite direction, other start
    prepared = [_fake_prepared(x), _fake_prepared(rng.normal(size=100), mate), _fake_prepared(rng.normal(size=130))]
    result = screen(prepared, Params(), ref)
    s = result.scores
    assert np.allclose(s, s.T)
    assert s[0, 1] > 0.95
    assert s[0, 1] > s[0, 2] + 0.1 and s[0, 1] > s[1, 2] + 0.1
    best_only = select_candidates(s, 1)
    assert (0, 1) in best_only and len(best_only) == 2  # fragment 2's best partner joins it
    assert select_candidates(s, 2) == [(0, 1), (0, 2), (1, 2)]


# --- the forest and refinement, from true matches -------------------------------------

def test_forest_from_true_matches_rebuilds_the_object(broken):
    rng = np.random.default_rng(0)
    samples = truth_samples(broken)
    edges = true_edges(broken, rng)
    n = len(broken.fragments)
    pose, group, notes = grow_forest(n, edges, samples, Params(), scale_of(broken.fragments), ref)
    assert all(v.startswith("used") for v in notes.values()), notes
    poses, groups = _finish_groups(pose, group)
    assert poses[0] is not None and np.allclose(poses[0], np.eye(4))  # the group's frame is its first fragment's
    s = score([f.vertices for f in broken.fragments], poses, groups, broken.poses, broken.touching,
              [(e.a, e.b, e.transform) for e in edges])
    assert s.part_accuracy == 1.0 and s.pair_precision == 1.0 and s.pair_recall == 1.0
    assert s.rotation_rmse_deg < 1e-4 and s.translation_rmse < 1e-9


def test_true_neighbours_do_not_count_as_interpenetrating(broken):
    samples = truth_samples(broken)
    solids = [closed_solid(f) for f in broken.fragments]
    assert all(s is not None for s in solids)
    depth = Params().penetration_depth * scale_of(broken.fragments)
    n = len(broken.fragments)
    for i in range(n):
        for j in range(i + 1, n):
            rel = _inv(broken.poses[i]) @ broken.poses[j]
            assert penetration(samples[i], samples[j], rel, ref, depth) <= Params().max_penetration
            share, thickness = overlap_volume(solids[i], solids[j], rel)
            assert thickness < 0.5 * CLASH_THICKNESS * scale_of(broken.fragments)


def test_forest_refuses_interpenetration_and_a_disagreeing_loop(broken):
    rng = np.random.default_rng(1)
    samples = truth_samples(broken)
    solids = [closed_solid(f) for f in broken.fragments]
    edges = true_edges(broken, rng)
    n = len(broken.fragments)
    scale = scale_of(broken.fragments)
    # a false match, scored above all: fragment j pushed into fragment i
    i, j = broken.touching[0]
    true_rel = _inv(broken.poses[i]) @ broken.poses[j]
    push = np.eye(4)
    push[:3, 3] = samples[i].surface.mean(axis=0) - (true_rel[:3, :3] @ samples[j].surface.mean(axis=0) + true_rel[:3, 3])
    clash = Edge(i, j, push @ true_rel, 0.99)
    share, thickness = overlap_volume(solids[i], solids[j], clash.transform)
    assert share > 0.05 and thickness > 2 * CLASH_THICKNESS * scale
    # a match that closes a loop the wrong way: a true pair, turned 20 degrees, scored lowest
    a, b = broken.touching[-1]
    rel = _inv(broken.poses[a]) @ broken.poses[b]
    turned = Edge(a, b, _rot(20, (0, 0, 1), samples[a].fracture.mean(axis=0)) @ rel, 0.1)
    others = [e for e in edges if (e.a, e.b) not in ((a, b), (i, j))]
    pose, group, notes = grow_forest(n, others + [clash, turned], samples, Params(), scale, ref, solids)
    assert "interpenetrate" in notes[(i, j)], notes
    assert notes[(a, b)].startswith("refused: disagrees with a closed loop"), notes
    poses, groups = _finish_groups(pose, group)
    s = score([f.vertices for f in broken.fragments], poses, groups, broken.poses, broken.touching,
              [(e.a, e.b, e.transform) for e in others])
    assert s.part_accuracy == 1.0


def test_forest_settles_a_near_miss_and_still_refuses_a_deep_clash(broken):
    # a right fit pushed 1.8% of the scale into its partner (a rescanned flat cut's miss) clashes thinly:
    # the two settled together no longer do, and the join is kept at the settled pose; pushed 8% it
    # stays refused (settling it out would carry it off its match)
    samples = truth_samples(broken)
    solids = [closed_solid(f) for f in broken.fragments]
    scale = scale_of(broken.fragments)
    i, j = 1, 2
    assert (i, j) in broken.touching
    true_rel = _inv(broken.poses[i]) @ broken.poses[j]
    towards = true_rel[:3, :3] @ samples[j].fracture_normals.mean(axis=0)  # j's break faces i
    towards /= np.linalg.norm(towards)

    def pushed(depth):
        push = np.eye(4)
        push[:3, 3] = depth * scale * towards
        return Edge(i, j, push @ true_rel, 0.9)

    def error(transform):
        return np.sqrt(np.mean(np.sum((apply(transform, broken.fragments[j].vertices)
                                       - apply(true_rel, broken.fragments[j].vertices)) ** 2, axis=1))) / scale

    near = pushed(0.018)
    share, thickness = overlap_volume(solids[i], solids[j], near.transform)
    assert share > 0.002 and CLASH_THICKNESS < thickness / scale < NEAR_MISS * CLASH_THICKNESS
    pose, group, notes = grow_forest(len(broken.fragments), [near], samples, Params(), scale, ref, solids)
    assert notes[(i, j)].startswith("used: spanning tree") and "settled together" in notes[(i, j)], notes
    assert group[i] == group[j] and error(_inv(pose[i]) @ pose[j]) < 0.5 * error(near.transform)
    deep = pushed(0.08)
    _, group, notes = grow_forest(len(broken.fragments), [deep], samples, Params(), scale, ref, solids)
    assert "interpenetrate" in notes[(i, j)] and group[i] != group[j], notes


def test_forest_keeps_apart_groups_that_look_like_two_objects(broken):
    # true matches, the halves {0, 1} and {2, 3} joined first; the descriptors call the halves two
    # objects (p(one object) 0.01 between them): the right matches across are refused, and no
    # tree edge is dropped for it. One fragment alone is never told apart (its descriptors mislead)
    samples, n, scale = truth_samples(broken), len(broken.fragments), scale_of(broken.fragments)
    assert sorted(broken.touching) == [(0, 1), (0, 3), (1, 2), (1, 3), (2, 3)]
    rel = {(i, j): _inv(broken.poses[i]) @ broken.poses[j] for i, j in broken.touching}
    halves = {0: 0, 1: 0, 2: 1, 3: 1}
    edges = [Edge(i, j, t, 0.9 if halves[i] == halves[j] else 0.5) for (i, j), t in rel.items()]
    p = np.array([[0.9 if halves[i] == halves[j] else 0.01 for j in range(n)] for i in range(n)])
    _, group, notes = grow_forest(n, edges, samples, Params(), scale, ref, same_object=p)
    assert group[0] == group[1] != group[2] == group[3], notes
    assert all(notes[k].startswith(APART_NOTE) for k in [(0, 3), (1, 2), (1, 3)]), notes
    assert "0.01 under 0.05" in notes[(0, 3)] + notes[(1, 2)] + notes[(1, 3)]
    _, group, notes = grow_forest(n, edges, samples, Params(apart_below=None), scale, ref, same_object=p)
    assert len(set(group)) == 1 and all(v.startswith("used") for v in notes.values()), notes
    alone = np.where((np.arange(n)[:, None] == 0) != (np.arange(n)[None, :] == 0), 0.01, 0.9)
    first = [Edge(i, j, t, 0.5 if 0 in (i, j) else 0.9) for (i, j), t in rel.items()]
    _, group, notes = grow_forest(n, first, samples, Params(), scale, ref, same_object=alone)
    assert len(set(group)) == 1, notes


@pytest.mark.parametrize("recovery", [True, False])
def test_forest_drops_a_wrong_match_scored_above_the_right_ones(broken, recovery, monkeypatch):
    # a wrong match of a touching pair (b pulled 10% of the scale away from a: no interpenetration,
    # so only the loops of the other matches say it is wrong), scored above every right one
    import relicgpu.heap.forest as assembly

    if not recovery:
        monkeypatch.setattr(assembly, "RECOVERY_ROUNDS", 0)
    rng = np.random.default_rng(3)
    samples = truth_samples(broken)
    solids = [closed_solid(f) for f in broken.fragments]
    scale = scale_of(broken.fragments)
    edges = true_edges(broken, rng)
    a, b = 1, 3  # fragment 3 touches 0, 1 and 2: three loops through it
    rel = _inv(broken.poses[a]) @ broken.poses[b]
    away = samples[b].surface.mean(axis=0) @ rel[:3, :3].T + rel[:3, 3] - samples[a].surface.mean(axis=0)
    pull = np.eye(4)
    pull[:3, 3] = 0.1 * scale * away / np.linalg.norm(away)
    wrong = Edge(a, b, pull @ rel, 0.95)
    others = [e for e in edges if (e.a, e.b) != (a, b)]
    pose, group, notes = grow_forest(len(broken.fragments), others + [wrong], samples, Params(), scale, ref, solids)
    accuracy = _part_accuracy(broken, pose, group)
    if recovery:
        assert notes[(a, b)].startswith("refused: contradicted by the other matches"), notes
        assert all(notes[(e.a, e.b)].startswith("used") for e in others), notes
        assert accuracy == 1.0
    else:  # the case recovery is for: the wrong match is used and the object comes out wrong
        assert notes[(a, b)] == "used: spanning tree"
        assert accuracy < 1.0


def test_forest_keeps_a_right_match_that_refused_interpenetrating_ones(broken):
    # the right match (0, 1) alone, and two wrong ones that each push a fragment into the place
    # of 0 or 1: leaving (0, 1) out would let both wrong ones join (two tree edges for one), but
    # they close no loop, so (0, 1) stays and they stay refused
    samples = truth_samples(broken)
    solids = [closed_solid(f) for f in broken.fragments]
    scale = scale_of(broken.fragments)

    def onto(i, j, k):
        """j placed (in i's frame) with its centroid on fragment k's true centroid."""
        rel = _inv(broken.poses[i]) @ broken.poses[j]
        target = (_inv(broken.poses[i]) @ broken.poses[k])
        shift = np.eye(4)
        shift[:3, 3] = (samples[k].surface.mean(axis=0) @ target[:3, :3].T + target[:3, 3]) - (
            samples[j].surface.mean(axis=0) @ rel[:3, :3].T + rel[:3, 3])
        return shift @ rel

    right = Edge(0, 1, _inv(broken.poses[0]) @ broken.poses[1], 0.6)
    wrong = [Edge(0, 2, onto(0, 2, 1), 0.15), Edge(1, 3, onto(1, 3, 0), 0.15)]
    pose, group, notes = grow_forest(len(broken.fragments), [right] + wrong, samples, Params(), scale, ref, solids)
    assert notes[(0, 1)] == "used: spanning tree", notes
    assert all("interpenetrate" in notes[(e.a, e.b)] for e in wrong), notes


def test_two_objects_end_in_two_groups(broken):
    other = synth.generate(shape="slab", pieces=3, seed=1, faces=800, progress=False)
    rng = np.random.default_rng(2)
    n0 = len(broken.fragments)
    samples = truth_samples(broken) + truth_samples(other)
    edges = true_edges(broken, rng) + true_edges(other, rng, offset=n0)
    frags = broken.fragments + other.fragments
    pose, group, notes = grow_forest(len(frags), edges, samples, Params(), scale_of(frags), ref)
    poses, groups = _finish_groups(pose, group)
    assert groups == [0] * n0 + [1] * len(other.fragments)
    s = score([f.vertices for f in frags], poses, groups, broken.poses + other.poses,
              broken.touching + [(i + n0, j + n0) for i, j in other.touching],
              [(e.a, e.b, e.transform) for e in edges], objects=[0] * n0 + [1] * len(other.fragments))
    assert s.part_accuracy == 1.0


def test_refinement_spreads_loop_error_and_brings_poses_closer(broken):
    rng = np.random.default_rng(4)
    samples = truth_samples(broken)
    edges = []
    for e in true_edges(broken, rng):
        c = broken.fragments[e.b].vertices.mean(axis=0)
        edges.append(Edge(e.a, e.b, e.transform @ _rot(1.0, rng.normal(size=3), c), e.score))
    n = len(broken.fragments)
    scale = scale_of(broken.fragments)
    params = Params()
    pose, group, notes = grow_forest(n, edges, samples, params, scale, ref)
    used = [e for e in edges if notes[(e.a, e.b)].startswith("used")]
    assert len(used) > n - 1  # there are loops to refine
    before = score([f.vertices for f in broken.fragments], *_finish_groups(pose, group), broken.poses, broken.touching, [])
    after = score([f.vertices for f in broken.fragments], *_finish_groups(refine_poses(pose, group, used, samples), group),
                  broken.poses, broken.touching, [])
    assert after.rotation_rmse_deg < 0.9 * before.rotation_rmse_deg
    assert after.part_accuracy == 1.0


def test_part_accuracy_counts_a_moved_fragment_wrong(broken):
    verts = [f.vertices for f in broken.fragments]
    n = len(verts)
    s = score(verts, list(broken.poses), [0] * n, broken.poses, broken.touching, [])
    assert s.part_accuracy == 1.0
    moved = list(broken.poses)
    moved[2] = np.eye(4)
    moved[2][:3, 3] = [0.05, 0, 0]
    moved[2] = moved[2] @ broken.poses[2]
    s = score(verts, moved, [0] * n, broken.poses, broken.touching, [])
    assert s.part_accuracy == (n - 1) / n and not s.right[2]
    # the whole group moved together is still right: only relative placement counts
    shift = np.eye(4)
    shift[:3, 3] = [3.0, -1.0, 0.5]
    s = score(verts, [shift @ p for p in broken.poses], [0] * n, broken.poses, broken.touching, [])
    assert s.part_accuracy == 1.0
    # unplaced fragments are wrong; an object split in two groups counts its main group only
    s = score(verts, [broken.poses[0], broken.poses[1], None, None], [0, 0, 1, 2], broken.poses, broken.touching, [])
    assert s.part_accuracy == 0.5


# --- end to end on a synthetic object ------------------------------------------------------

def test_every_matched_pair_says_whether_it_was_accepted_and_why(broken):
    """issue 15 item 2: assembly.json lists every candidate pair matched in full, verified or
    not, each with `accepted`, `used` and a `reason` (the verification's, or the forest's)."""
    result = assemble(broken.fragments, backend="numpy", progress=False)
    doc = json.loads(result.to_json())
    names = result.names
    assert sorted((m["a"], m["b"]) for m in doc["matches"]) == sorted((names[i], names[j]) for i, j in result.candidates)
    verify_words = ("overlap", "residual", "interpenetration", "no fracture contours", "no consistent", "error")
    for m in doc["matches"]:
        assert isinstance(m["accepted"], bool) and isinstance(m["used"], bool) and m["reason"], m
        if not m["accepted"]:
            assert not m["used"] and m["reason"].startswith("not verified: ")
            assert any(w in m["reason"] for w in verify_words), m["reason"]
        elif not m["used"]:
            assert m["reason"].startswith("refused: "), m["reason"]
        else:
            assert m["reason"].startswith("used: "), m["reason"]
    assert any(not m["accepted"] for m in doc["matches"]), "expected a pair that failed verification"
    assert [m for m in doc["matches"] if m["accepted"]] == [m.to_dict(names) for m in result.matches]


def test_objects_restrict_matching_to_pairs_within_one_class(broken):
    labels = [0, 0, 1, 1]
    result = assemble(broken.fragments, backend="numpy", progress=False, objects=labels)
    assert result.candidates == [(0, 1), (2, 3)]
    assert all(labels[m.a] == labels[m.b] for m in result.matches)
    with pytest.raises(ValueError, match="one class per fragment"):
        assemble(broken.fragments, backend="numpy", progress=False, objects=[0, 1])


def test_a_small_heap_matches_every_pair_even_those_the_screen_scores_zero(broken, monkeypatch):
    """A cloud that is mostly break picks little of it first and its screen votes find nothing:
    in a heap of up to ALL_PAIRS_UP_TO fragments every pair is still matched in full."""
    import relicgpu.heap.assembly as assembly_module

    monkeypatch.setattr(assembly_module, "normalised_support", lambda support: np.zeros_like(support))
    monkeypatch.setattr(assembly_module, "SCREEN_LCS_WEIGHT", 0.0)
    result = assemble(broken.fragments, backend="numpy", progress=False)
    assert result.candidates == [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    assert result.n_groups == 1


def test_assemble_small_synthetic_object(local_result, synth_dir):
    result, frags = local_result
    s = score_assembly(result, frags, synth.read_truth(synth_dir))
    assert s.part_accuracy >= 0.95, (s, result.stats, [m.note for m in result.matches])
    assert s.pair_precision >= 0.95
    assert result.n_groups == 1
    doc = result.to_dict()
    assert set(doc) == {"version", "fragments", "matches", "backend", "engine", "timings", "skipped", "notes"}
    assert all(m["accepted"] and m["reason"] for m in doc["matches"][:len(result.matches)])
    assert [f["name"] for f in doc["fragments"]] == [f.name for f in frags]
    assert [f["file"] for f in doc["fragments"]] == [f.file for f in frags]  # issue 15: the file name as given


def test_mixed_directory_of_two_objects_gives_two_groups(tmp_path):
    a = synth.generate(shape="vase", pieces=5, seed=2, faces=4000, noise=0.0005, progress=False)
    b = synth.generate(shape="torso", pieces=5, seed=0, faces=4000, noise=0.0005, progress=False)
    synth.write_many([a, b], tmp_path)
    frags = load_directory(tmp_path / "fragments")
    result = assemble(frags, backend="numpy", progress=False)
    truth = synth.read_truth(tmp_path)
    s = score_assembly(result, frags, truth)
    objects = {e["name"]: e["object"] for e in truth["fragments"]}
    placed_groups = {}
    for name, g, pose in zip(result.names, result.groups, result.poses):
        if pose is not None:
            placed_groups.setdefault(g, set()).add(objects[name])
    assert all(len(o) == 1 for o in placed_groups.values())  # no group mixes objects
    assert len(placed_groups) == 2
    assert s.part_accuracy >= 0.95 and s.pair_precision >= 0.95


def _run_cli(src, out, *extra, quiet=True):
    cmd = [*CLI, "assemble", str(src), "-o", str(out), "--backend", "numpy", *extra]
    if quiet:
        cmd.append("--quiet")
    return cmd


def test_cli_writes_outputs_and_leaves_inputs_alone(tmp_path, synth_dir, local_result, shared_cache):
    src = synth_dir / "fragments"
    before = {p.name: p.read_bytes() for p in src.iterdir()}
    out = tmp_path / "out"
    # the API run above filled the cache: the command line computes nothing again
    proc = subprocess.run(_run_cli(src, out, "--cache-dir", str(shared_cache), quiet=False), capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    result, frags = local_result
    assert f"({len(result.candidates)} from cache)" in proc.stderr
    assert {p.name: p.read_bytes() for p in src.iterdir()} == before
    doc = json.loads((out / "assembly.json").read_text())
    assert _without_timings(doc) == _without_timings(result.to_dict())
    assert not (out / "cache").exists()
    scene = trimesh.load(out / "assembly.glb", force="scene")
    assert sorted(scene.graph.nodes_geometry) == sorted(f.name for f in frags)
    merged = trimesh.load(out / "merged.stl", force="mesh")
    assert merged.is_watertight
    broken_volume = synth.read_truth(synth_dir)["objects"][0]["volume"]
    placed = [i for i, p in enumerate(result.poses) if p is not None and result.groups[i] == 0]
    if len(placed) == len(frags):  # all placed right: the union is the object again
        assert abs(merged.volume - broken_volume) < 0.03 * broken_volume
    assert "verified" in proc.stderr
    assert "placed fragments lie on a closed loop of matches" in proc.stderr
    used = [(m["a"], m["b"]) for m in doc["matches"] if m["used"]]
    for f in doc["fragments"]:
        assert f["used_matches"] == sum(f["name"] in pair for pair in used)
        assert not f["on_loop"] or f["used_matches"] >= 2  # a loop needs two matches at each fragment on it


def _without_timings(doc):
    return {k: v for k, v in doc.items() if k != "timings"}


def _children(pid: int) -> list[int]:
    """The processes whose parent is `pid` (Linux's /proc; none elsewhere)."""
    kids = []
    for status in Path("/proc").glob("[0-9]*/status"):
        try:
            fields = dict(line.split(":\t", 1) for line in status.read_text().splitlines() if ":\t" in line)
        except OSError:
            continue
        if fields.get("PPid", "").strip() == str(pid):
            kids.append(int(status.parent.name))
    return kids


def _alive(pid: int) -> bool:
    """Whether `pid` runs (a zombie left unreaped by a container's init does not)."""
    try:
        return "\tZ" not in Path(f"/proc/{pid}/status").read_text().split("State:", 1)[1][:4]
    except (OSError, IndexError):
        return False


def test_cli_killed_mid_run_resumes_from_its_cache(tmp_path, synth_dir, local_result):
    src = synth_dir / "fragments"
    out = tmp_path / "out"
    pairs_dir = out / "cache" / "pairs"
    proc = subprocess.Popen(_run_cli(src, out), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline and proc.poll() is None:
        if pairs_dir.exists() and any(p.suffix == ".json" for p in pairs_dir.iterdir()):
            break
        time.sleep(0.01)
    assert proc.poll() is None, "the run ended before it could be killed: " + proc.stderr.read().decode()[-2000:]
    workers = _children(proc.pid)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and any(map(_alive, workers)):
        time.sleep(0.05)
    assert not [w for w in workers if _alive(w)], "forked workers outlived the killed run"
    done = sorted(p.name for p in pairs_dir.iterdir() if p.suffix == ".json")
    mtimes = {p.name: p.stat().st_mtime_ns for p in pairs_dir.iterdir() if p.suffix == ".json"}
    assert done and not (out / "assembly.json").exists()
    result, _ = local_result
    assert len(done) < len(result.candidates)  # killed mid-way, not at the end

    again = subprocess.run(_run_cli(src, out, quiet=False), capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr
    assert f"({len(done)} from cache)" in again.stderr
    # the finished pairs were read, not recomputed
    assert all((pairs_dir / name).stat().st_mtime_ns == t for name, t in mtimes.items())
    doc = json.loads((out / "assembly.json").read_text())
    assert _without_timings(doc) == _without_timings(result.to_dict())


def test_cli_reports_a_bad_directory_in_one_line(tmp_path):
    proc = subprocess.run([*CLI, "assemble", str(tmp_path / "nope"), "-o",
                           str(tmp_path / "o")], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert "not a directory" in proc.stderr and "Traceback" not in proc.stderr


def _part_accuracy(broken, pose, group) -> float:
    """Part accuracy of a forest's poses and groups (`grow_forest`) against the truth."""
    poses, groups = _finish_groups(pose, group)
    return score([f.vertices for f in broken.fragments], poses, groups, broken.poses, broken.touching, []).part_accuracy


def _around_3(broken):
    """The truth's samples, solids and scale, and right matches (0.8) of every touching pair but
    those of fragment 3 (which touches 0, 1 and 2)."""
    samples = truth_samples(broken)
    solids = [closed_solid(f) for f in broken.fragments]
    scale = scale_of(broken.fragments)
    others = [Edge(i, j, _inv(broken.poses[i]) @ broken.poses[j], 0.8) for i, j in broken.touching if 3 not in (i, j)]
    return samples, solids, scale, others


def test_forest_weighs_each_rival_placement_alone(broken, monkeypatch):
    # fragment 3 touches 0, 1 and 2: one right match (1, 3) and two wrong ones, each placing 3 at
    # its own wrong place (pulled off the object by 10% and 20% of the scale: no interpenetration).
    # Summed, the wrong ones outweigh the right one; each alone does not, and wrong matches scatter
    import relicgpu.heap.forest as assembly

    monkeypatch.setattr(assembly, "RECOVERY_ROUNDS", 0)  # the rule itself, not the recovery after it
    samples, solids, scale, others = _around_3(broken)
    centre = np.mean([samples[i].surface.mean(axis=0) @ broken.poses[i][:3, :3].T + broken.poses[i][:3, 3]
                      for i in range(len(broken.fragments))], axis=0)  # the object's, in its frame

    def pulled(i, share):
        """3 placed in i's frame, moved off the object's centre by share of the scale."""
        rel = _inv(broken.poses[i]) @ broken.poses[3]
        out = samples[3].surface.mean(axis=0) @ broken.poses[3][:3, :3].T + broken.poses[3][:3, 3] - centre
        move = np.eye(4)
        move[:3, 3] = _inv(broken.poses[i])[:3, :3] @ (share * scale * out / np.linalg.norm(out))
        return move @ rel

    right = Edge(1, 3, _inv(broken.poses[1]) @ broken.poses[3], 0.5)
    wrong = [Edge(0, 3, pulled(0, 0.1), 0.3), Edge(2, 3, pulled(2, 0.2), 0.3)]
    pose, group, notes = grow_forest(len(broken.fragments), others + [right] + wrong, samples, Params(), scale, ref,
                                     solids)
    assert notes[(1, 3)] == "used: spanning tree", notes
    assert all(notes[(e.a, e.b)].startswith("refused: disagrees with a closed loop") for e in wrong), notes
    assert _part_accuracy(broken, pose, group) == 1.0


def test_forest_takes_the_placement_two_matches_agree_on_over_one_scored_higher(broken, monkeypatch):
    # fragment 3 touches 0, 1 and 2: two right matches (0, 3) and (1, 3), scored low (small
    # contacts), and a wrong one (2, 3) pulled 10% of the scale off, scored above their sum (a flat
    # face laid on a face). Two matches that agree close a loop; one alone closes none
    import relicgpu.heap.forest as assembly

    monkeypatch.setattr(assembly, "RECOVERY_ROUNDS", 0)  # the rule itself, not the recovery after it
    samples, solids, scale, others = _around_3(broken)
    right = [Edge(i, 3, _inv(broken.poses[i]) @ broken.poses[3], 0.2) for i in (0, 1)]
    rel = _inv(broken.poses[2]) @ broken.poses[3]
    away = samples[3].surface.mean(axis=0) @ rel[:3, :3].T + rel[:3, 3] - samples[2].surface.mean(axis=0)
    pull = np.eye(4)
    pull[:3, 3] = 0.1 * scale * away / np.linalg.norm(away)
    wrong = Edge(2, 3, pull @ rel, 0.5)
    pose, group, notes = grow_forest(len(broken.fragments), others + right + [wrong], samples, Params(), scale, ref,
                                     solids)
    assert notes[(2, 3)] == "refused: other matches between the two groups agree on another placement", notes
    assert all(notes[(e.a, e.b)].startswith("used") for e in right), notes
    assert _part_accuracy(broken, pose, group) == 1.0
    monkeypatch.setattr(assembly, "BACK_BY_COUNT", False)  # weighed by score alone, the wrong one joins
    _, _, notes = grow_forest(len(broken.fragments), others + right + [wrong], samples, Params(), scale, ref, solids)
    assert notes[(2, 3)] == "used: spanning tree", notes


def test_a_heap_matches_a_dense_cloud_on_the_points_match_pair_reads(tmp_path):
    """`prepare` matches a cloud with normals on at most Params.cloud_points of its points
    (`thinned_cloud`). A heap ships and caches its prepared fragments without the fragment and
    sets it back in: that set the file's whole cloud back, so the readings that go back to the
    fragment (the majority pick, the skin) read 20,000 points where `match_pair` read 6,000 (the
    Blender cube's shards 15 and 16 as clouds: refused in the heap, right as a pair). The thinned
    copy travels with the prepared fragment; a mesh, which prepare does not thin, still does not."""
    from relicgpu.cloud.points import cloud_fragment
    from relicgpu.heap.assembly import _prepare_one
    from relicgpu.heap.cache import Cache, fragment_hash
    from relicgpu.pair.prepare import received

    r = synth.generate("slab", pieces=2, seed=0, faces=2000, noise=0.0005, progress=False)
    mesh = r.fragments[0]
    points, face = trimesh.sample.sample_surface(mesh.to_trimesh(), 9000, seed=0)
    cloud = cloud_fragment("dense", points, mesh.to_trimesh().face_normals[face])
    params = Params()
    cache = Cache(tmp_path, params, mesh.size, ref.name)
    for fragment, thinned in ((cloud, True), (mesh, False)):
        payload = (0, params, ref.name, mesh.size)
        shipped = _prepare_one(payload, fragment)
        assert (shipped.fragment is None) != thinned
        prepared = received(shipped, fragment)
        cache.put_prepared(fragment_hash(fragment), prepared, fragment)
        cached = cache.get_prepared(fragment, fragment_hash(fragment))
        for p in (prepared, cached):
            if thinned:
                assert len(p.fragment.vertices) == len(prepared.fragment.vertices) <= params.cloud_points
                assert np.array_equal(p.fragment.vertices, prepared.fragment.vertices)
            else:
                assert p.fragment is mesh
