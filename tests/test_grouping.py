"""Fragment grouping (issue 7): descriptors, clustering, classifier, CLI."""
from __future__ import annotations

import json

import numpy as np
import pytest

from relicgpu import synth
from relicgpu.synth.generator import _AREA_GUESS
from relicgpu.heap import classifier as C, describe as D, grouping as G
from relicgpu.heap.run import assemble_grouped
from relicgpu.io.fragment import Fragment, FragmentError


def _scaled(frags, s, prefix):
    S = np.diag([s, s, s, 1.0])
    return [Fragment(prefix + f.name, f.transformed(S).vertices, f.faces) for f in frags]


EDGE = 0.03  # one scan resolution for the whole heap, absolute units


def _faces_at(shape, pieces, spacing):
    """synth.generate's `faces` for sampling `shape` at `spacing` object units (its own rule inverted)."""
    area, frac_area, c_orig, c_frac = _AREA_GUESS[shape]
    return int(round((c_orig * area + c_frac * frac_area * (pieces - 1) ** 0.75) / (pieces * spacing ** 2)))


@pytest.fixture(scope="module")
def mixture():
    """Three objects of different shapes and sizes, 4 pieces each, scanned at one resolution
    (EDGE absolute: each object meshed at EDGE / its scale in its own units)."""
    parts = [("vase", 0.6, 4, 11), ("slab", 1.5, 4, 12), ("torso", 1.0, 4, 13)]
    frags, labels = [], []
    for k, (shape, scale, pieces, seed) in enumerate(parts):
        r = synth.generate(shape, pieces=pieces, seed=seed, faces=_faces_at(shape, pieces, EDGE / scale),
                           progress=False)
        frags += _scaled(r.fragments, scale, f"o{k}_")
        labels += [k] * pieces
    order = np.random.default_rng(0).permutation(len(frags))
    return [frags[i] for i in order], [labels[i] for i in order]


def test_adjusted_rand_index():
    assert G.adjusted_rand_index([0, 0, 1, 1], [5, 5, 3, 3]) == pytest.approx(1.0)
    # hand-computed: contingency [[2,1],[0,2]] -> index 1.25, expected 0.8, max 2.0 -> (1.25-0.8)/(2-0.8)... in pairs
    truth, pred = [0, 0, 0, 1, 1], [0, 0, 1, 1, 1]
    # pairs: sum C(n_ij,2) = 1+0+0+1 = 2; rows C(3,2)+C(2,2) = 4; cols C(2,2)+C(3,2) = 4; C(5,2) = 10
    expected = (2 - 4 * 4 / 10) / (0.5 * (4 + 4) - 4 * 4 / 10)
    assert G.adjusted_rand_index(truth, pred) == pytest.approx(expected)
    assert G.adjusted_rand_index([0, 1, 2, 3], [0, 0, 0, 0]) == pytest.approx(0.0)


def test_silhouette_matches_definition():
    rng = np.random.default_rng(1)
    x = np.vstack([rng.normal(0, 1, (5, 2)), rng.normal(6, 1, (4, 2))])
    lab = np.array([0] * 5 + [1] * 4)
    d = np.linalg.norm(x[:, None] - x[None], axis=2)
    s = []
    for i in range(len(x)):
        own = (lab == lab[i]) & (np.arange(len(x)) != i)
        a = d[i, own].mean()
        b = d[i, lab != lab[i]].mean()
        s.append((b - a) / max(a, b))
    assert G.silhouette(d, lab) == pytest.approx(np.mean(s))


def test_wall_thickness_of_a_tube():
    import manifold3d as mf

    tube = mf.Manifold.cylinder(2.0, 0.5, 0.5, 96) - mf.Manifold.cylinder(2.2, 0.4, 0.4, 96).translate((0, 0, -0.1))
    m = tube.to_mesh()
    frag = Fragment("tube", np.asarray(m.vert_properties, float)[:, :3], np.asarray(m.tri_verts, np.int32))
    d = D.describe(frag)
    assert d.thickness == pytest.approx([0.1, 0.1, 0.1], rel=0.02)
    assert d.chord == pytest.approx(d.thickness) and d.wall_share > 0.9  # every inward ray meets the wall


def test_solid_pieces_have_chords_hollow_ones_walls():
    """Rays from a solid torso's pieces mostly end on a cut (fracture), a vase's on its inner wall."""
    share = {}
    for shape in ("torso", "vase"):
        r = synth.generate(shape, pieces=6, seed=1, faces=1500, progress=False)
        d = [D.describe(f) for f in r.fragments]
        assert all(np.all(np.isfinite(x.chord)) for x in d)
        share[shape] = np.median([x.wall_share for x in d])
    assert share["torso"] < 0.4 and share["vase"] > 0.7


def test_curvature_of_a_cylinder():
    import trimesh
    from trimesh.remesh import subdivide_to_size

    c = trimesh.creation.cylinder(radius=1.0, height=3.0, sections=96)
    v, f = subdivide_to_size(c.vertices, c.faces, max_edge=0.1)
    d = D.describe(Fragment("cyl", np.asarray(v, float), np.asarray(f, np.int32)))
    side = d.curvatures[np.abs(d.curvatures[:, 0] - 1.0) < 0.1]
    assert len(side) > 0.5 * len(d.curvatures)  # the side holds most of the area
    assert np.abs(side[:, 1]).max() < 0.05  # along the axis: flat
    # The flat caps, bounded by 90-degree creases, read as cuts: the side is the skin. Its points
    # (curvedness 1 / sqrt(2)) count for the shape index at a reference length of 2.
    si, _ = d.shape_measures(2.0)
    assert si[1] == pytest.approx(0.5, abs=0.05)  # |shape index| of a cylinder


def test_solid_piece_has_a_chord_but_no_wall():
    """A pebble cut in two by a smooth curved surface (relicgpu.synth.corpus): rays from its skin
    end on the cut (fracture), not on the original surface again: a chord, few wall hits."""
    from relicgpu.synth import corpus

    r = corpus.generate("smooth-clean", pieces=2, seed=0, faces=3000)
    assert r.params["solid"] == "pebble"
    d = D.describe(r.fragments[0])
    assert d.wall_share < 0.4
    assert np.all(np.isfinite(d.chord))


def test_curvature_of_a_sphere():
    import trimesh
    ball = trimesh.creation.icosphere(subdivisions=4, radius=2.0)
    d = D.describe(Fragment("ball", np.asarray(ball.vertices, float), np.asarray(ball.faces, np.int32)))
    assert np.allclose(d.kmax, 0.5, rtol=0.05) and np.allclose(d.kmin, 0.5, rtol=0.05)
    si, cv = d.shape_measures(2.0)
    assert si == pytest.approx([1.0] * 3, abs=0.02) and cv == pytest.approx([np.arcsinh(1.0)] * 3, rel=0.05)
    assert d.thickness[1] == pytest.approx(4.0, rel=0.1)  # a solid: chords through the centre region


def _pure_and_few(labels, pred, extra=2):
    """No group mixes two objects, and at most `extra` more groups than objects."""
    pairs = {(l, p) for l, p in zip(labels, pred)}
    assert len({p for _, p in pairs}) == len(pairs), f"a group mixes objects: {sorted(pairs)}"
    assert len(set(pred)) <= len(set(labels)) + extra


def test_group_finds_the_objects(mixture):
    frags, labels = mixture
    g = G.group_fragments(frags)
    _pure_and_few(labels, g.labels)
    assert G.adjusted_rand_index(labels, g.labels) >= 0.9
    groups = G.group(frags)
    assert sorted(n for grp in groups for n in grp) == sorted(f.name for f in frags)


def _descriptor(thickness, rng, patches=None):
    th = thickness * np.exp(rng.normal(0, 0.01, 3))
    return D.Descriptor("x", np.full(3, 1.0), np.full(3, 0.5), np.sort(th), 1.0, 5.0, 0.01, 0.2,
                        1.0 * np.exp(rng.normal(0, 0.01)), None, None, patches)


def test_interval_gaps_are_zero_where_quartiles_overlap():
    rng = np.random.default_rng(2)
    a, b, c = (_descriptor(t, rng) for t in (0.02, 0.02, 0.02))
    a = D.Descriptor(**{**a.__dict__, "kmax": np.array([1.0, 1.5, 2.0])})
    b = D.Descriptor(**{**b.__dict__, "kmax": np.array([1.8, 2.5, 3.0])})
    c = D.Descriptor(**{**c.__dict__, "kmax": np.array([4.0, 4.1, 4.2])})
    gaps = G.interval_gaps([a, b, c], 1.0)[:, :, D.GAP_NAMES.index("kmax")]
    assert gaps[0, 1] == 0.0  # [asinh 1, asinh 2] and [asinh 1.8, asinh 3] overlap
    assert gaps[0, 2] == pytest.approx(np.arcsinh(4.0) - np.arcsinh(2.0))
    assert gaps[1, 2] == gaps[2, 1] == pytest.approx(np.arcsinh(4.0) - np.arcsinh(3.0))


def test_shipped_pair_model_matches_its_inputs():
    assert len(G.FEATURE_SCALES) == len(D.FEATURE_NAMES)
    assert len(G.PAIR_WEIGHTS) == G.N_PAIR_INPUTS + 1


def test_pair_model_fit_recovers_a_separating_rule():
    """fit_feature_scales + fit_pair_model on heaps whose objects differ only in thickness learn
    negative thickness weights and split a new heap by them."""
    rng = np.random.default_rng(0)

    def heap(n_obj, per):
        desc, labels = [], []
        for k in range(n_obj):
            for _ in range(per):
                desc.append(_descriptor(0.02 * 2.0 ** k, rng))
                labels.append(k)
        return desc, labels

    heaps = [heap(4, 5), heap(3, 6)]
    scales = G.fit_feature_scales(heaps)
    assert scales.shape == (len(D.FEATURE_NAMES),)
    assert scales[1] == pytest.approx(0.01, rel=0.5)  # the log-thickness jitter of one object
    w = G.fit_pair_model(heaps, scales)
    # thickness enters as the median/quartile z (per knot block) and the quartile-interval gap
    k, blocks = len(D.FEATURE_NAMES) + len(D.GAP_NAMES), 1 + len(G.Z_KNOTS)
    thick = [b * k + i for b in range(blocks)
             for i in (0, 1, 2, len(D.FEATURE_NAMES) + D.GAP_NAMES.index("log_thickness"))]
    assert w[thick].sum() < -0.5 and w[-1] > 0
    d, labels = heap(3, 5)
    p = G.same_object_probability(G.pair_features(d, scales), w)
    assert G.adjusted_rand_index(labels, G.cluster(1 - p)[0]) == pytest.approx(1.0)


def test_cluster_gathers_the_leftovers():
    """Two tight groups, and three fragments each too unlike any other to join at LINK_CUT but
    alike enough for LEFTOVER_CUT: they end in one group, not three."""
    d = np.full((10, 10), 0.99)
    d[:4, :4] = 0.05
    d[4:7, 4:7] = 0.05
    d[7:, 7:] = 0.6
    np.fill_diagonal(d, 0.0)
    labels, _ = G.cluster(d)
    assert len(set(labels[:4])) == 1 and len(set(labels[4:7])) == 1 and len(set(labels[7:])) == 1
    assert len(set(labels)) == 3
    alone, _ = G.cluster(d, leftover_cut=G.LINK_CUT)  # no second stage
    assert len(set(alone)) == 5


def test_fracture_relief_scales_with_the_fragment():
    """The relief spectrum is a length: a fragment scaled by 2 has twice the relief at twice the radius."""
    r = synth.generate("slab", pieces=2, seed=4, faces=1500, progress=False)
    frag = r.fragments[0]
    d1 = D.describe(frag)
    d2 = D.describe(_scaled([frag], 2.0, "big_")[0])
    radius = 0.1 * d1.size
    assert np.isfinite(D.spectrum_at(d1, radius))
    assert D.spectrum_at(d2, 2 * radius) == pytest.approx(2 * D.spectrum_at(d1, radius), rel=1e-6)
    assert np.isnan(D.spectrum_at(d1, 10 * d1.size))  # beyond what was measured


def test_patch_match_finds_the_other_side_of_a_cut():
    rng = np.random.default_rng(3)
    cut = np.array([[0.05, 0.3, 0.2]])
    other = np.array([[0.02, 0.25, 0.1], [0.01, 0.1, 0.1]])
    a = _descriptor(0.02, rng, np.vstack([cut * 1.02, other]))
    b = _descriptor(0.02, rng, np.vstack([other * 3, cut]))
    c = _descriptor(0.02, rng, other * 5)
    m = G.patch_match([a, b, c])
    assert m[0, 1] == m[1, 0] == pytest.approx(np.log(G.PATCH_TOLERANCE / np.log(1.02)), rel=1e-6)
    assert m[0, 2] == 0.0 and m[1, 2] == 0.0


def test_group_one_object_stays_one_group():
    r = synth.generate("vase", pieces=4, seed=3, faces=300, progress=False)
    assert len(G.group(r.fragments)) == 1


def test_group_cli(tmp_path, mixture):
    from relicgpu.cli import main
    from relicgpu.io.files import write_mesh

    frags, labels = mixture
    src = tmp_path / "heap"
    for f in frags:
        write_mesh(src / f"{f.name}.ply", f.vertices, f.faces)
    assert main(["group", str(src), "-o", str(tmp_path / "out"), "--quiet"]) == 0
    doc = json.loads((tmp_path / "out" / "groups.json").read_text())
    truth = {f.name: l for f, l in zip(frags, labels)}
    got = {e["name"]: e["group"] for e in doc["fragments"]}
    _pure_and_few([truth[n] for n in got], list(got.values()))
    assert main(["group", str(src), "-o", str(tmp_path / "out2"), "--groups", "3", "--quiet"]) == 0
    doc = json.loads((tmp_path / "out2" / "groups.json").read_text())
    got = {e["name"]: e["group"] for e in doc["fragments"]}
    assert G.adjusted_rand_index([truth[n] for n in got], list(got.values())) >= 0.9
    assert main(["group", str(src), "-o", str(tmp_path / "o3"), "--distance", "1.5", "--quiet"]) == 2
    assert main(["group", str(tmp_path / "nowhere"), "-o", str(tmp_path / "o2"), "--quiet"]) == 2
    assert main(["group", str(src), "-o", str(src), "--quiet"]) == 2


def test_labels_csv_faults(tmp_path):
    p = tmp_path / "labels.csv"
    p.write_text("file,label\na.ply,pot\nb.ply\n")
    with pytest.raises(FragmentError, match="line 3"):
        C.read_labels_csv(p)
    with pytest.raises(FragmentError, match="no such file"):
        C.read_labels_csv(tmp_path / "none.csv")
    p.write_text("file,label\nsub/a.ply, pot\n")
    files, labels = C.read_labels_csv(p)
    assert files == [tmp_path / "sub" / "a.ply"] and labels == ["pot"]


def test_train_classifier_cli(tmp_path, mixture):
    pytest.importorskip("torch")
    from relicgpu.cli import main
    from relicgpu.io.files import write_mesh

    frags, labels = mixture
    rows = ["file,label"]
    for f, l in zip(frags, labels):
        write_mesh(tmp_path / "frags" / f"{f.name}.ply", f.vertices, f.faces)
        rows.append(f"frags/{f.name}.ply,object{l}")
    (tmp_path / "labels.csv").write_text("\n".join(rows) + "\n")
    out = tmp_path / "clf.pt"
    assert main(["train-classifier", str(tmp_path / "labels.csv"), "-o", str(out), "--epochs", "40", "--quiet"]) == 0
    clf = C.Classifier.load(out)
    pred, prob = clf.predict(frags)
    assert prob.shape == (len(frags), 3)
    assert np.mean([p == f"object{l}" for p, l in zip(pred, labels)]) >= 0.9  # it learned its training set
    assert main(["group", str(tmp_path / "frags"), "-o", str(tmp_path / "g"), "--classifier", str(out),
                 "--quiet"]) == 0
    doc = json.loads((tmp_path / "g" / "groups.json").read_text())
    assert doc["method"] == "classifier" and len(doc["fragments"]) == len(frags)
    (tmp_path / "bad.pt").write_bytes(b"not torch")
    assert main(["group", str(tmp_path / "frags"), "-o", str(tmp_path / "g2"), "--classifier",
                 str(tmp_path / "bad.pt"), "--quiet"]) == 2


def test_assemble_grouped_writes_objects(tmp_path):
    frags, obj = [], {}
    for k, (shape, scale, seed) in enumerate([("vase", 0.6, 11), ("slab", 1.5, 12)]):
        r = synth.generate(shape, pieces=2, seed=seed, faces=300, progress=False)
        for f in _scaled(r.fragments, scale, f"o{k}_"):
            frags.append(f)
            obj[f.name] = k
    grouping, results = assemble_grouped(frags, tmp_path / "out", progress=False)
    assert len(results) == 2
    doc = json.loads((tmp_path / "out" / "assembly.json").read_text())
    got = {e["name"]: e["object"] for e in doc["fragments"]}
    assert G.adjusted_rand_index([obj[n] for n in got], list(got.values())) == pytest.approx(1.0)
    # assembled groups never mix objects
    pieces = {}
    for e in doc["fragments"]:
        pieces.setdefault(e["group"], set()).add(e["object"])
    assert all(len(s) == 1 for s in pieces.values())
    assert (tmp_path / "out" / "groups.json").exists() and (tmp_path / "out" / "object_0" / "assembly.json").exists()


def test_assemble_cli_group_flag_writes_groups_and_objects(tmp_path):
    import json
    import subprocess
    import sys

    a = synth.generate(shape="vase", pieces=2, seed=1, faces=1500, progress=False)
    b = synth.generate(shape="slab", pieces=2, seed=2, faces=1500, progress=False)
    synth.write_many([a, b], tmp_path / "heap")
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-m", "relicgpu.cli", "assemble", str(tmp_path / "heap" / "fragments"),
                           "-o", str(out), "--group", "--backend", "numpy", "--quiet"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert (out / "groups.json").exists()
    doc = json.loads((out / "assembly.json").read_text())
    assert len(doc["fragments"]) == 4
    assert all("object" in f for f in doc["fragments"])
