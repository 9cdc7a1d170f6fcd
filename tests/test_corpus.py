"""relicgpu.synth.corpus: every family builds, its labels lie on the cuts, poses and contacts are the truth."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from relicgpu import synth
from relicgpu.synth import corpus

ROOT = Path(__file__).resolve().parents[1]
_CACHE: dict = {}


def _case(family, pieces=2, seed=0, faces=800):
    key = (family, pieces, seed, faces)
    if key not in _CACHE:
        _CACHE[key] = corpus.generate(family, pieces, seed, faces)
    return _CACHE[key]


def _distance_to(points, v, f, rng=np.random.default_rng(0)):
    """Distance of points (N,3) to a mesh, up to its sampling spacing (dense surface samples)."""
    samples, _, _ = corpus._surface_samples(v, f, 200_000, rng)
    return cKDTree(samples).query(points)[0]


@pytest.mark.parametrize("family", corpus.FAMILIES)
def test_family_builds_with_sane_labels_on_the_cut(family):
    r = _case(family)
    assert len(r.fragments) == 2 and r.touching == [(0, 1)]
    size = r.params["size"]
    placed = r.placed_back()
    for i, (frag, lab) in enumerate(zip(placed, r.fracture_faces)):
        assert lab.shape == (len(frag.faces),) and lab.dtype == bool
        # a faceted break keeps its faces through decimation where the smooth skin loses them
        assert 0.01 <= lab.mean() <= (0.8 if family == "tetra-noisy" else 0.6), f"fracture share {lab.mean():.3f}"
        if not family.startswith("vessel"):  # a vessel's cut is only the thin band: too few faces to test like this
            other = placed[1 - i]
            d = _distance_to(frag.vertices[frag.faces].mean(1), other.vertices, other.faces)
            tol = 0.01 * size if family.endswith("noisy") else 0.003 * size
            assert np.median(d[lab]) < tol  # fracture faces lie on the other piece
            assert np.median(d[~lab]) > 3 * tol  # the skin does not
    if family.endswith("coarse"):
        assert np.mean([len(f.faces) for f in r.fragments]) < 1000


def test_vessel_wall_is_thin():
    r = _case("vessel-clean")
    assert 0.02 <= r.params["wall"] / r.params["size"] <= 0.05 * 1.2


def test_poses_round_trip_through_write(tmp_path):
    r = _case("voronoi-noisy")
    placed = r.placed_back()
    lo = np.min([f.vertices.min(0) for f in placed], axis=0)
    hi = np.max([f.vertices.max(0) for f in placed], axis=0)
    assert np.linalg.norm(hi - lo) == pytest.approx(1.0, abs=0.03)  # the object frame: diagonal 1, centred
    assert np.abs(lo + hi).max() < 0.03
    assert max(np.abs(f.vertices).max() for f in placed) < 1.0 < max(np.abs(f.vertices).max() for f in r.fragments)
    synth.write(r, tmp_path)
    truth, labels = synth.read_truth(tmp_path), synth.load_labels(tmp_path)
    for entry, pose, frag, lab in zip(truth["fragments"], r.poses, r.fragments, r.fracture_faces):
        np.testing.assert_allclose(entry["pose"], pose)
        np.testing.assert_array_equal(labels[entry["name"]], lab)
        assert entry["faces"] == len(frag.faces)
    assert truth["touching_pairs"] == [["frag_00", "frag_01"]]


def test_deterministic_and_seeded():
    a, b = corpus.generate("rough-coarse", 2, 3), corpus.generate("rough-coarse", 2, 3)
    np.testing.assert_array_equal(a.fragments[0].vertices, b.fragments[0].vertices)
    np.testing.assert_array_equal(a.poses[1], b.poses[1])
    c = corpus.generate("rough-coarse", 2, 4)
    assert c.fragments[0].vertices.shape != a.fragments[0].vertices.shape or \
        not np.allclose(c.fragments[0].vertices, a.fragments[0].vertices)


@pytest.mark.parametrize("family", ["voronoi-coarse", "smooth-coarse"])
def test_multi_piece_contacts_are_mutual(family):
    r = _case(family, pieces=6)
    assert len(r.fragments) == 6
    assert r.touching == sorted(set(r.touching)) and all(i < j for i, j in r.touching)
    assert {i for p in r.touching for i in p} == set(range(6))  # every piece touches another
    placed = r.placed_back()
    for i, j in r.touching:  # both sides of a contact carry fracture faces near the other
        for a, b in ((i, j), (j, i)):
            fa, fb = placed[a], placed[b]
            d = _distance_to(fa.vertices[fa.faces].mean(1)[r.fracture_faces[a]], fb.vertices, fb.faces)
            assert (d < 0.005).sum() >= 1


def test_unknown_family_is_refused():
    with pytest.raises(ValueError, match="unknown family"):
        corpus.generate("rough-laser")


def test_real_set_helpers_on_two_boxes_and_a_crumb():
    import manifold3d as mf

    def arrays(m):
        mesh = m.to_mesh()
        return np.array(mesh.vert_properties, np.float64)[:, :3], np.array(mesh.tri_verts, np.int64)

    va, fa = arrays(mf.Manifold.cube([1, 1, 1]).refine_to_length(0.2))
    vb, fb = arrays(mf.Manifold.cube([1, 1, 1]).translate([1, 0, 0]).refine_to_length(0.2))
    vc, fc = arrays(mf.Manifold.cube([0.05, 0.05, 0.05]).translate([3, 3, 3]))  # a crumb in the same file
    v, f = corpus._main_body(np.vstack([vb, vc]), np.vstack([fb, fc + len(vb)]))
    assert len(f) == len(fb) and v[:, 0].max() == pytest.approx(2.0)
    la, lb = corpus._near_other([(va, fa), (v, f)], 0.01)
    ca = va[fa].mean(1)
    np.testing.assert_array_equal(la, np.isclose(ca[:, 0], 1.0))  # the shared face, and only it
    assert lb.sum() == la.sum()


def test_bench_quick_runs_on_one_family(tmp_path):
    out = tmp_path / "g.json"
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "bench_generalize.py"), "--quick", "--families",
                           "rough-coarse", "--realdata", "none", "--every-pair", "--json", str(out)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "| rough-coarse |" in proc.stdout and "[2/2] rough-coarse" in proc.stderr
    doc = json.loads(out.read_text())
    (row,) = doc["rows"]
    assert row["pairs"] == 1 and row["multi_objects"] == 1 and 0 <= row["seg_recall"] <= 1
    assert 0 <= row["seg2_recall"] <= 1 and 0 <= row["seg2_precision"] <= 1  # the second reading (hybrid)
    assert 0 <= row["verified_right"] <= row["verified"] and 0 <= row["used_right"] <= row["used"] <= row["verified"]
    c = row["every_pair"]  # a 5-piece object: ten pairs, each counted once
    assert c["touching"] + c["apart"] == 10 and c["touching"] == doc["cases"][1]["assembly"]["touching"]
    assert c["right"] + c["near"] + c["wrong"] + c["missed"] == c["touching"] and 0 <= c["apart_accepted"] <= c["apart"]
    assert "| rough-coarse | " + str(c["touching"]) + " | " + str(c["right"]) + " |" in proc.stdout


def test_decimated_pieces_keep_their_break_and_pose():
    from relicgpu.synth.mixed import decimated
    r = _case("tetra-clean", pieces=2, faces=800)
    d = decimated(r, 200)
    assert len(d.fragments[1].faces) < len(r.fragments[1].faces) and d.fragments[0] is r.fragments[0]
    placed, before = d.placed_back()[1], r.placed_back()[1]
    # within the tolerance (0.5% of the size) of the piece it was, labels carried to its faces
    assert _distance_to(placed.vertices, before.vertices, before.faces).max() < 0.006 * r.params["size"]
    lab = d.fracture_faces[1]
    assert lab.shape == (len(placed.faces),) and 0.05 < lab.mean() < 0.95
