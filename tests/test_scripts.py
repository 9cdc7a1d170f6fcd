"""Every benchmark script runs end to end on tiny inputs, so none of them rots.

Figures come from full runs (docs/benchmarks.md gives each command); these runs only
check that each script still starts, computes and writes what it says it writes.
scripts/bench_generalize.py is run by tests/test_corpus.py.
"""
from __future__ import annotations

import os
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]

# (script, arguments; {tmp} is a fresh folder, and a file it names must exist afterwards)
CASES = [
    ("bench_bigmesh.py", "--faces 20000 --json {tmp}/big.json", "big.json"),
    ("bench_backends.py", "--quick --backends numpy,warp-cpu --sections normals,nn --repeats 1 --out {tmp}/bb",
     "bb/bench_backends.json"),
    ("bench_pair.py", "--pairs 1 --size-factor 0.15 --repeats 1 --json {tmp}/pair.json", "pair.json"),
    ("bench_assembly.py", "--grid-only --shapes slab --pieces 3 --seeds 0 --faces 1500 --backend numpy "
     "--work {tmp}/work --json {tmp}/asm.json", "asm.json"),
    ("bench_assembly.py", "--readings 1 --shapes slab --pieces 3 --seeds 0 --faces 1500 --backend numpy "
     "--work {tmp}/work --json {tmp}/readings.json", "readings.json"),
    ("bench_fusion.py", "--pairs 2 --skip-full --out {tmp}/fusion --cache-dir {tmp}/cache", None),
    ("bench_group.py", "--seeds 0 --train-seeds 1 --no-supervised --cache ''", None),
    ("bench_group.py", "--corpus voronoi-coarse --seeds 0", None),
    ("bench_group.py", "--fit 16 --fit-corpus voronoi-coarse rough-coarse --fit-corpus-seeds 0 1 --cache '' "
     "--describe-cache {tmp}/described", "described/rough-coarse_1.pkl"),
    ("bench_mosaic.py", "--pairs 1 --json {tmp}/mosaic.json", "mosaic.json"),
    ("bench_clouds.py", "--pairs 1 --first 2 --modes normals,normals-file,open,mesh --json {tmp}/clouds.json", "clouds.json"),
    ("bench_clouds.py", "--pairs 2 --first 2 --modes normals --workers 2 --json {tmp}/clouds.json", "clouds.json"),
    ("bench_clouds.py", "--source thin --kinds shelf04-flat --pairs 1 --modes normals --json {tmp}/thin.json",
     "thin.json"),
    ("bench_pointcloud.py", "--points 20000 --source slab --json {tmp}/pc.json", "pc.json"),
    ("bench_search.py", "--families rough-clean --pieces 3 --seeds 0 --faces 600 --set patch_turns=6 "
     "--json {tmp}/search.json",
     "search.json"),
    ("bench_segment.py", "--seeds 1 --only synth", None),
    ("bench_fine.py", "--families vessel-noisy --seeds 2 --pieces 2 --faces 2000 --json {tmp}/fine.json", "fine.json"),
    ("bench_settle.py", "--families voronoi-noisy --seeds 0 --pieces 3 --faces 600 --json {tmp}/settle.json",
     "settle.json"),
    ("bench_resolution.py", "--names slab --seeds 0 --faces 1500 --roughness-spacing 0,0.02", None),
    ("bench_verify.py", "collect --out {tmp}/fits.pkl --families synth --seeds 0 --faces 1500", "fits.pkl"),
    ("show_synth.py", "--shape slab --pieces 2 -o {tmp}/synth.png", "synth.png"),
]


def test_every_script_is_covered():
    covered = {c[0] for c in CASES} | {"bench_generalize.py"}
    assert {p.name for p in (ROOT / "scripts").glob("*.py")} == covered


@pytest.mark.parametrize("script,args,output", CASES, ids=[c[0] for c in CASES])
def test_script_runs_on_tiny_inputs(script, args, output, tmp_path):
    cmd = [sys.executable, str(ROOT / "scripts" / script)] + shlex.split(args.format(tmp=tmp_path))
    run = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=900,
                         env={**os.environ, "RELICGPU_BACKEND": "numpy"})
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-4000:]
    assert run.stdout.strip() or run.stderr.strip()
    if output:
        assert (tmp_path / output).is_file()


def test_bench_clouds_matches_a_pair_of_real_shards(tmp_path):
    """`--source realdata`: a touching pair of a ../shared/realdata Blender set, as clouds."""
    from relicgpu.synth.corpus import REALDATA, REALDATA_SETS

    if not (REALDATA / REALDATA_SETS[0]).is_dir():
        pytest.skip(f"{REALDATA} is absent (third-party sets, not in the repository)")
    cmd = [sys.executable, str(ROOT / "scripts" / "bench_clouds.py"), "--source", "realdata", "--pairs", "1",
           "--modes", "normals", "--json", str(tmp_path / "real.json")]
    run = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stderr[-4000:]
    import json

    row = json.loads((tmp_path / "real.json").read_text())["rows"][0]
    assert row["case"] == f"{REALDATA_SETS[0]} pair 0" and not row["reason"].startswith("error")


def test_bench_group_corpus_heap_holds_four_objects_of_one_family():
    """A corpus heap: four objects of distinct solids (the fourth repeats the first's kind of solid
    at another scale), 5-6 pieces each, shuffled."""
    sys.path.insert(0, str(ROOT / "scripts"))
    from bench_group import corpus_heap

    frags, labels = corpus_heap("rough-coarse", 3)
    objects = sorted(set(labels))
    assert len(objects) == 4 and len(frags) == len(labels)
    assert all(5 <= labels.count(o) <= 6 for o in objects)
    assert len({o[1:-4] for o in objects[:3]}) == 3  # pebble, block, jar
    assert labels != sorted(labels)
    sizes = {o: np.median([f.size for f, l in zip(frags, labels) if l == o]) for o in objects}
    assert max(sizes.values()) > 1.3 * min(sizes.values())  # scaled apart


def test_bench_search_facets_name_each_contact():
    """bench_search's ideal patches: a piece's fracture faces split by the neighbour they touch."""
    sys.path.insert(0, str(ROOT / "scripts"))
    from bench_search import facet_labels
    from relicgpu.synth import corpus

    result = corpus.generate("voronoi-clean", 3, 0, 600)
    labels = facet_labels(result)
    for k, (lab, truth) in enumerate(zip(labels, result.fracture_faces)):
        assert np.array_equal(lab > 0, np.asarray(truth, bool))
        assert k + 1 not in lab  # never its own piece
    for i, j in result.touching:
        assert np.count_nonzero(labels[i] == 1 + j) > 0 and np.count_nonzero(labels[j] == 1 + i) > 0


def test_bench_generalize_scores_a_match_against_the_true_relative_pose():
    """A verified match is right only between touching pieces, within 2 degrees and 1% of the size."""
    sys.path.insert(0, str(ROOT / "scripts"))
    from bench_generalize import match_right
    from relicgpu.pair.icp import invert
    from relicgpu.synth import corpus

    result = corpus.generate("voronoi-coarse", 3, 0, 300)
    size = corpus.object_size(result)
    i, j = result.touching[0]
    true = invert(result.poses[i]) @ result.poses[j]
    order = list(range(len(result.fragments)))
    assert match_right(result, order, i, j, true, size)
    assert match_right(result, order[::-1], len(order) - 1 - i, len(order) - 1 - j, true, size)  # by assembly index
    turn = np.eye(4)
    c, s = np.cos(np.radians(3)), np.sin(np.radians(3))
    turn[:2, :2] = [[c, -s], [s, c]]
    assert not match_right(result, order, i, j, true @ turn, size)
    shift = np.eye(4)
    shift[0, 3] = 0.02 * size
    assert not match_right(result, order, i, j, shift @ true, size)
    apart = [(p, q) for p in order for q in order if p < q and (p, q) not in result.touching]
    if apart:
        p, q = apart[0]
        assert not match_right(result, order, p, q, invert(result.poses[p]) @ result.poses[q], size)


def test_bench_generalize_makes_every_other_piece_coarse_where_the_cut_allows():
    """--coarse-faces: pieces of one object at very different resolutions (Breaking Bad's)."""
    sys.path.insert(0, str(ROOT / "scripts"))
    from bench_generalize import coarse_every_other
    from relicgpu.synth import corpus

    fine = corpus.generate("voronoi-clean", 3, 2, 2000)
    mixed = coarse_every_other(fine, "voronoi-clean", 2, 250)
    faces = [len(f.faces) for f in mixed.fragments]
    assert faces[1] < faces[0] / 3 and faces[1] < faces[2] / 3
    assert [len(x) for x in mixed.fracture_faces] == faces and mixed.touching == fine.touching
    placed = [f.vertices @ p[:3, :3].T + p[:3, 3] for f, p in zip(mixed.fragments, mixed.poses)]
    assert np.abs(placed[1].min(0) - (fine.fragments[1].vertices @ fine.poses[1][:3, :3].T
                                     + fine.poses[1][:3, 3]).min(0)).max() < 0.02 * corpus.object_size(fine)
    with pytest.raises(ValueError, match="comes out otherwise at 250 faces"):
        coarse_every_other(corpus.generate("rough-clean", 3, 2, 2000), "rough-clean", 2, 250)


def test_set_reads_params_fields_by_their_type_and_names_a_bad_one():
    """The benchmarks' --set NAME=VALUE (relicgpu.params.parse_assignments)."""
    from relicgpu.params import parse_assignments

    got = parse_assignments(["patch_turns=36", "contact_distance=0.02", "rim_priority=None", "min_outline=0.2",
                             "second_segmentation=regions"])
    assert got == {"patch_turns": 36, "contact_distance": 0.02, "rim_priority": None, "min_outline": 0.2,
                   "second_segmentation": "regions"}
    assert type(got["patch_turns"]) is int
    for bad, why in (("no_such_field=1", "NAME a Params field"), ("patch_turns", "NAME=VALUE"),
                     ("patch_turns=many", "patch_turns must be int")):
        with pytest.raises(ValueError, match=why):
            parse_assignments([bad])


def test_bench_clouds_reports_a_pair_it_cannot_match_and_goes_on():
    """A pair whose clouds cannot be made (no points) is a refused row naming the fault, not a crash."""
    sys.path.insert(0, str(ROOT / "scripts"))
    from bench_clouds import run_pair, summarise

    row = run_pair(2, "normals", 0, 0.0005, "thin", "numpy", kinds="shelf04-flat")
    assert row["case"] == "shelf04-flat seed 2" and not row["accepted"]
    assert row["reason"].startswith("error: ") and row["rotation_error_deg"] == float("inf")
    assert summarise([row])["normals"]["pairs"] == 1


def test_bench_clouds_assembles_an_object_of_clouds_and_scores_it():
    """`--pieces 3`: the corpus's rough-clean seed 0 in three pieces, as clouds with their normals,
    assembled whole by `assemble` (every used match right); a case that cannot be made is a row
    naming its fault."""
    sys.path.insert(0, str(ROOT / "scripts"))
    from bench_clouds import main, run_object

    row = run_object(0, "normals", 2500, 0.0005, "corpus", "numpy", kinds="rough-clean", pieces=3)
    assert row["case"] == "rough-clean seed 0" and row["pieces"] == 3
    assert row["part_accuracy"] == 1.0 and row["used"] == row["used_right"] >= 2, row
    bad = run_object(0, "normals", 0, 0.0005, "corpus", "numpy", kinds="rough-clean", pieces=3)
    assert bad["part_accuracy"] == 0.0 and bad["error"], bad
    with pytest.raises(SystemExit):
        main(["--source", "thin", "--pieces", "3"])
