"""Groups grown against their placed pieces (relicgpu.heap.grow)."""
import numpy as np
import pytest

from relicgpu.heap.assembly import common_scale
from relicgpu.heap.cache import Cache, fragment_hash
from relicgpu.heap.engines import LocalEngine
from relicgpu.heap.grow import merged_fragment, grow_groups
from relicgpu.heap.outputs import closed_solid
from relicgpu.io.fragment import Fragment
from relicgpu.pair.icp import invert
from relicgpu.pair.prepare import prepare
from relicgpu.params import Params
from relicgpu.synth import corpus
from relicgpu.backends import numpy as ref


def _box(lo, hi, n=4):
    import trimesh
    box = trimesh.creation.box(bounds=[lo, hi])
    for _ in range(n):
        box = box.subdivide()
    return Fragment("box", np.asarray(box.vertices), np.asarray(box.faces, np.int32))


def test_merged_group_leaves_out_the_faces_where_its_members_touch():
    a, b = _box([0, 0, 0], [1, 1, 1]), _box([1, 0, 0], [2, 1, 1])
    merged = merged_fragment([a, b], [0, 1], [np.eye(4), np.eye(4)], reach=0.05)
    x = merged.vertices[merged.faces].mean(axis=1)[:, 0]
    assert not np.any(np.abs(x - 1.0) < 1e-9)  # the shared wall is gone from both
    x_a, x_b = (f.vertices[f.faces].mean(axis=1)[:, 0] for f in (a, b))
    far = np.sum(np.abs(x_a - 1) > 0.1) + np.sum(np.abs(x_b - 1) > 0.1)
    assert np.sum(np.abs(x - 1) > 0.1) == far  # away from the wall, every face of both kept
    apart = np.eye(4)
    apart[0, 3] = 5.0
    assert len(merged_fragment([a, b], [0, 1], [np.eye(4), apart], reach=0.05).faces) == len(a.faces) + len(b.faces)


def _rot_err(t, p):
    r = t[:3, :3] @ p[:3, :3].T
    return float(np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1))))


def test_a_rescanned_piece_joins_its_placed_group_and_a_stranger_stays_apart():
    """Rough-noisy 5 pieces seed 2 (a rescan: pairwise, an assembly places 2 of 5): four pieces
    placed at their true poses as one group; the fifth is matched against their merged surface and
    lands within 2 degrees and 1% of the size, a piece of another object joins nothing."""
    obj = corpus.generate("rough-noisy", pieces=5, seed=2, faces=3000)
    stranger = corpus.generate("smooth-clean", pieces=2, seed=0, faces=1500).fragments[0]
    fragments = list(obj.fragments) + [stranger]
    n, loose = len(fragments), 1
    params = Params()
    scale = common_scale(fragments, params)
    prepared = [prepare(f, params, ref, scale=scale, with_second=True) for f in fragments]
    pose = [np.array(p) if i != loose else np.eye(4) for i, p in enumerate(obj.poses)] + [np.eye(4)]
    group = [0 if i != loose else loose for i in range(5)] + [5]
    candidates = [(i, j) for i in range(n) for j in range(i + 1, n)]
    samples = [p.sample for p in prepared]
    solids = [closed_solid(f) for f in fragments]
    joins, stats = grow_groups(fragments, prepared, pose, group, candidates, samples, solids, params, scale, ref,
                               LocalEngine(1))
    assert stats["grow_joined"] == 1 and len(joins) == 1
    assert group[loose] == 0 and group[5] == 5
    assert _rot_err(pose[loose], obj.poses[loose]) < 2.0
    v = obj.fragments[loose].vertices
    gap = (v @ pose[loose][:3, :3].T + pose[loose][:3, 3]) - (v @ obj.poses[loose][:3, :3].T + obj.poses[loose][:3, 3])
    assert np.sqrt(np.mean(np.sum(gap ** 2, axis=1))) < 0.01 * obj.params["size"]
    edge, doc, note = joins[0]
    assert edge.b == loose and doc["accepted"] and note.startswith("used: joined against the merged surface")
    np.testing.assert_allclose(pose[edge.a] @ edge.transform, pose[loose], atol=1e-9)
    assert stats["grow_tried"] >= 2  # the stranger was tried too, and refused


def test_a_group_is_tried_once_in_a_composition_and_kept_in_the_cache(tmp_path):
    """Nothing joins: each pair of groups is matched once, then the rounds stop; run again on the
    same cache, the match is read back, not made again."""
    calls = []

    class Counting(LocalEngine):
        def map(self, fn, jobs, objects, on_result):
            calls.append(len(jobs))
            return super().map(fn, jobs, objects, on_result)

    obj = corpus.generate("voronoi-coarse", pieces=3, seed=0, faces=500)
    stranger = corpus.generate("rough-coarse", pieces=2, seed=1, faces=500).fragments[0]
    fragments = list(obj.fragments[:2]) + [stranger]
    params = Params()
    scale = common_scale(fragments, params)
    prepared = [prepare(f, params, ref, scale=scale) for f in fragments]
    cache = Cache(tmp_path, params, scale, ref.name)
    hashes = [fragment_hash(f) for f in fragments]
    for run in range(2):
        pose = [np.array(obj.poses[0]), np.array(obj.poses[1]), np.eye(4)]
        group = [0, 0, 2]
        joins, stats = grow_groups(fragments, prepared, pose, group, [(0, 2), (1, 2)], [p.sample for p in prepared],
                                   [None] * 3, params, scale, ref, Counting(1), cache=cache, hashes=hashes)
        assert joins == [] and stats["grow_tried"] == 1 and group == [0, 0, 2]
    assert calls == [1, 0] and cache.writes == 1 and cache.hits == 1


def test_a_blender_shard_in_its_cavity_joins_although_the_merged_surface_is_open():
    """Blender's cube, shard 12 (third-party Cell Fracture; it touches seven others): against the
    other nineteen at their true poses its right fit reads 18% inside the merged surface, which is
    open where they touched; judged against each whole member instead, it joins."""
    from relicgpu.synth.corpus import REALDATA
    if not (REALDATA / "blender_cube_20_seed_2").is_dir():
        pytest.skip(f"{REALDATA} is absent (third-party sets, not in the repository)")
    obj = corpus.realdata("blender_cube_20_seed_2", seed=0)
    fragments, loose, n = obj.fragments, 12, len(obj.fragments)
    params = Params()
    scale = common_scale(fragments, params)
    prepared = [prepare(f, params, ref, scale=scale, with_second=i == loose) for i, f in enumerate(fragments)]
    pose = [np.array(p) if i != loose else np.eye(4) for i, p in enumerate(obj.poses)]
    group = [0 if i != loose else loose for i in range(n)]
    joins, stats = grow_groups(fragments, prepared, pose, group, [(0, loose)], [p.sample for p in prepared],
                               [closed_solid(f) for f in fragments], params, scale, ref, LocalEngine(1))
    assert stats["grow_joined"] == 1 and group[loose] == 0
    assert _rot_err(pose[loose], obj.poses[loose]) < 1.0
