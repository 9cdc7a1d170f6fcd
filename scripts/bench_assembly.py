"""Benchmark of `relicgpu.assemble` on synthetic breaks with a known answer (issue 5).

Grid: each built-in shape broken into 5 and 10 pieces, 3 seeds: part accuracy, RMSE of
rotation (degrees) and translation (object units), precision and recall of the used
pair matches, screening recall at the chosen top-k and for k = 1..8, and time.
Scale: directories of 10, 50 and 100 fragments (1, 5, 10 mixed 10-piece objects) with
the time of each stage.

    python scripts/bench_assembly.py                    # both, default sizes
    python scripts/bench_assembly.py --grid-only --faces 2000
    python scripts/bench_assembly.py --scale-only --backend warp-cuda --json out.json
    python scripts/bench_assembly.py --readings 2 --shapes vase --pieces 10 --seeds 0 --backend numpy

Prints tables; --json also writes all figures there. Synthetic data is kept under --work between runs, named by its settings and the source of relicgpu/synth/ (never reused from an older synth).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from relicgpu import synth
from relicgpu.heap.assembly import ALL_PAIRS_UP_TO, TOP_K, assemble
from relicgpu.heap.evaluate import score_assembly
from relicgpu.io.load import load_directory
from relicgpu.params import Params, SEGMENTATIONS, with_segmentations

SHAPES = ("vase", "torso", "slab")


def screening_ranks(scores: np.ndarray, pairs: list[tuple[int, int]]) -> list[int]:
    """For each pair, the best of the two ranks (0 = best partner) it has in its fragments' lists."""
    n = len(scores)
    order = {}
    for i in range(n):
        partners = sorted((j for j in range(n) if j != i and scores[i, j] > 0), key=lambda j: (-scores[i, j], j))
        order[i] = {j: r for r, j in enumerate(partners)}
    big = 10 ** 9
    return [min(order[i].get(j, big), order[j].get(i, big)) for i, j in pairs]


def run_one(frag_dir: Path, truth: dict, args, out_dir: Path | None = None) -> dict:
    frags = load_directory(frag_dir)
    t0 = time.perf_counter()
    objects, group_time = None, 0.0
    if getattr(args, "group", False):
        from relicgpu.heap.grouping import group_fragments
        objects = group_fragments(frags).labels
        group_time = time.perf_counter() - t0
    params = with_segmentations(Params(), getattr(args, "segmentation", None),
                                getattr(args, "second_segmentation", None))
    result = assemble(frags, params, backend=args.backend, engine=args.engine, workers=args.workers, progress=False,
                      top_k=args.top_k, out_dir=out_dir, cache_dir=None if out_dir is None else out_dir / "cache",
                      gpus_per_task=args.gpus_per_task, objects=objects)
    wall = time.perf_counter() - t0
    if objects is not None:
        result.timings["group"] = group_time
    s = score_assembly(result, frags, truth)
    index = {n: i for i, n in enumerate(result.names)}
    touching = [(index[a], index[b]) for a, b in truth["touching_pairs"]]
    ranks = screening_ranks(result.screen_scores, touching)
    accepted = {(m.a, m.b) for m in result.matches}
    cand = set(result.candidates)
    return {
        "fragments": len(frags), "faces": int(sum(len(f.faces) for f in frags)),
        "part_accuracy": s.part_accuracy, "rotation_rmse_deg": s.rotation_rmse_deg,
        "translation_rmse": s.translation_rmse, "pair_precision": s.pair_precision, "pair_recall": s.pair_recall,
        "used": s.n_used, "touching": s.n_touching, "groups": result.n_groups,
        "placed": int(sum(p is not None for p in result.poses)),
        "candidates": len(result.candidates), "all_pairs": len(frags) * (len(frags) - 1) // 2,
        "accepted": len(result.matches),
        "touching_screened_in": int(sum((min(i, j), max(i, j)) in cand for i, j in touching)),
        "touching_accepted": int(sum((min(i, j), max(i, j)) in accepted for i, j in touching)),
        "screen_ranks": ranks, "time": wall, "timings": result.timings, "backend": result.backend,
        "engine": result.engine,
    }


def synth_dir(work: Path, **settings) -> Path:
    """A synthetic break kept under `work` between runs, named by its settings and by the source
    of relicgpu/synth/: data from an older synth (or other --faces) is never silently reused."""
    source = b"".join(p.read_bytes() for p in sorted(Path(synth.__file__).parent.glob("*.py")))
    code = hashlib.sha256(source).hexdigest()[:8]
    name = "_".join(str(v) for v in settings.values())
    d = work / f"{name}_{code}"
    if not (d / "truth.json").exists():
        synth.write(synth.generate(**settings, progress=False), d)
    return d


def grid(args, work: Path) -> list[dict]:
    rows = []
    for shape in args.shapes:
        for pieces in args.pieces:
            for seed in args.seeds:
                d = synth_dir(work, shape=shape, pieces=pieces, seed=seed, faces=args.faces)
                row = run_one(d / "fragments", synth.read_truth(d), args)
                row.update(shape=shape, pieces=pieces, seed=seed)
                rows.append(row)
                print(f"  {shape:6s} {pieces:3d} seed {seed}: accuracy {row['part_accuracy']:.2f}, "
                      f"precision {row['pair_precision']:.2f}, recall {row['pair_recall']:.2f}, "
                      f"{row['time']:.1f} s", file=sys.stderr, flush=True)
    return rows


def readings(args, work: Path) -> list[dict]:
    """The grid's objects assembled with the second segmentation (--second-segmentation, default
    Params') and without it, alternating --readings times: median times, their ratio, accuracy."""
    import statistics
    from argparse import Namespace

    rows = []
    for shape in args.shapes:
        for pieces in args.pieces:
            for seed in args.seeds:
                d = synth_dir(work, shape=shape, pieces=pieces, seed=seed, faces=args.faces)
                runs: dict = {"with": [], "without": []}
                for _ in range(args.readings):
                    for key, second in (("with", args.second_segmentation), ("without", "none")):
                        runs[key].append(run_one(d / "fragments", synth.read_truth(d),
                                                 Namespace(**{**vars(args), "second_segmentation": second})))
                row = {"shape": shape, "pieces": pieces, "seed": seed}
                for key, got in runs.items():
                    row[f"time_{key}"] = statistics.median(r["time"] for r in got)
                    row[f"accuracy_{key}"] = min(r["part_accuracy"] for r in got)
                row["ratio"] = row["time_with"] / row["time_without"]
                rows.append(row)
                print(f"  {shape:6s} {pieces:3d} seed {seed}: with the second reading {row['time_with']:.1f} s "
                      f"(accuracy {row['accuracy_with']:.2f}), without {row['time_without']:.1f} s "
                      f"({row['accuracy_without']:.2f}), ratio {row['ratio']:.2f}", flush=True)
    return rows


def scale(args, work: Path) -> list[dict]:
    d = work / "scale"
    objects = []
    for k in range(max(args.scale_sizes) // 10):
        shape = SHAPES[k % len(SHAPES)]
        objects.append(synth_dir(d, shape=shape, pieces=10, seed=100 + k, faces=args.scale_faces))
    rows = []
    for size in args.scale_sizes:
        mixed = d / f"mixed_{size}_{args.scale_faces}_{objects[0].name.rsplit('_', 1)[-1]}"  # the synth version
        if not (mixed / "truth.json").exists():
            _mix(objects[: size // 10], mixed)
        row = run_one(mixed / "fragments", synth.read_truth(mixed), args)
        row.update(size=size)
        rows.append(row)
        print(f"  {size:4d} fragments: {row['time']:.1f} s, accuracy {row['part_accuracy']:.2f}, "
              f"groups {row['groups']}", file=sys.stderr, flush=True)
    return rows


def _mix(object_dirs: list[Path], out: Path) -> None:
    """One directory holding the fragments of several written objects (prefixed o<k>_), with a merged truth."""
    import shutil
    (out / "fragments").mkdir(parents=True, exist_ok=True)
    merged = {"version": 1, "objects": [], "fragments": [], "touching_pairs": [], "contacts": []}
    for k, src in enumerate(object_dirs):
        truth = json.loads((src / "truth.json").read_text())
        prefix = f"o{k}_"
        names = {}
        for e in truth["fragments"]:
            new = prefix + e["name"]
            names[e["name"]] = new
            shutil.copyfile(src / e["file"], out / "fragments" / f"{new}.ply")
            merged["fragments"].append({**e, "name": new, "file": f"fragments/{new}.ply", "object": k})
        merged["touching_pairs"] += [[names[a], names[b]] for a, b in truth["touching_pairs"]]
        merged["objects"].append({"id": k, "source": str(src)})
    (out / "truth.json").write_text(json.dumps(merged))


def _mean(rows, key):
    return float(np.mean([r[key] for r in rows])) if rows else float("nan")


def print_grid(rows: list[dict], top_k: int) -> dict:
    print("\nGrid: part accuracy, rotation / translation RMSE, precision / recall of used pairs, time")
    print(f"{'shape':6s} {'pieces':>6s} {'acc':>6s} {'rot deg':>8s} {'transl':>8s} {'prec':>6s} {'recall':>6s} "
          f"{'cand':>9s} {'screen rec':>10s} {'time s':>7s}")
    summary = {}
    for shape in sorted({r["shape"] for r in rows}, key=SHAPES.index):
        for pieces in sorted({r["pieces"] for r in rows}):
            sel = [r for r in rows if r["shape"] == shape and r["pieces"] == pieces]
            if not sel:
                continue
            touching = sum(r["touching"] for r in sel)
            screened = sum(r["touching_screened_in"] for r in sel)
            cand = f"{sum(r['candidates'] for r in sel)}/{sum(r['all_pairs'] for r in sel)}"
            print(f"{shape:6s} {pieces:6d} {_mean(sel, 'part_accuracy'):6.3f} {_mean(sel, 'rotation_rmse_deg'):8.3f} "
                  f"{_mean(sel, 'translation_rmse'):8.4f} {_mean(sel, 'pair_precision'):6.3f} "
                  f"{_mean(sel, 'pair_recall'):6.3f} {cand:>9s} {screened / max(touching, 1):10.3f} "
                  f"{_mean(sel, 'time'):7.1f}")
            summary[f"{shape}_{pieces}"] = {k: _mean(sel, k) for k in
                                            ("part_accuracy", "rotation_rmse_deg", "translation_rmse",
                                             "pair_precision", "pair_recall", "time")}
    worst = min(rows, key=lambda r: r["part_accuracy"])
    print(f"all: accuracy {_mean(rows, 'part_accuracy'):.3f} (worst {worst['part_accuracy']:.2f}: "
          f"{worst['shape']} {worst['pieces']} seed {worst['seed']}), precision {_mean(rows, 'pair_precision'):.3f}, "
          f"runs with accuracy >= 0.95: {sum(r['part_accuracy'] >= 0.95 for r in rows)}/{len(rows)}")
    # screening recall against k: touching pairs that the top-k rule keeps
    ranks = [x for r in rows for x in r["screen_ranks"]]
    print("\nScreening recall of touching pairs by k (pair kept when in the top k of either fragment):")
    curve = {}
    for k in range(1, 9):
        curve[k] = float(np.mean([x < k for x in ranks])) if ranks else float("nan")
    print("  " + "  ".join(f"k={k}: {v:.3f}" for k, v in curve.items()) + f"   (chosen k = {top_k if top_k is not None else 'default'})")
    summary["screen_recall_by_k"] = curve
    return summary


def print_scale(rows: list[dict]) -> None:
    print("\nScale: mixed 10-piece objects")
    stages = ["group", "load", "engine", "prepare", "screen", "match", "assemble", "refine", "write"]
    print(f"{'frags':>5s} {'faces':>8s} {'cand/all':>11s} " + " ".join(f"{s:>8s}" for s in stages)
          + f" {'total s':>8s} {'acc':>6s} {'groups':>6s}")
    for r in rows:
        t = r["timings"]
        print(f"{r['fragments']:5d} {r['faces']:8d} {r['candidates']:>5d}/{r['all_pairs']:<5d} "
              + " ".join(f"{t.get(s, 0.0):8.2f}" for s in stages)
              + f" {r['time']:8.1f} {r['part_accuracy']:6.3f} {r['groups']:6d}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--backend", default="auto")
    ap.add_argument("--engine", default="local", choices=["local", "ray"])
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--gpus-per-task", type=float, default=None, help="Ray: GPUs per task where there are GPUs")
    ap.add_argument("--top-k", type=int, default=None,
                    help=f"partners per fragment matched in full (default: assemble's: every pair up to {ALL_PAIRS_UP_TO} fragments, else {TOP_K})")
    ap.add_argument("--group", action="store_true",
                    help="classify the heap first (relicgpu.heap.grouping) and match only within each class")
    ap.add_argument("--segmentation", choices=SEGMENTATIONS,
                    help="Params.segmentation (default: Params' own)")
    ap.add_argument("--second-segmentation", choices=SEGMENTATIONS + ("none",),
                    help="Params.second_segmentation, the reading a pair is matched on again where the first "
                         "finds no fit (none: no second reading; default: Params' own)")
    ap.add_argument("--faces", type=int, default=4000, help="faces per fragment in the grid (synth's default)")
    ap.add_argument("--shapes", nargs="+", default=list(SHAPES))
    ap.add_argument("--pieces", nargs="+", type=int, default=[5, 10])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--scale-sizes", nargs="+", type=int, default=[10, 50, 100])
    ap.add_argument("--scale-faces", type=int, default=5000, help="faces per fragment in the scale run")
    ap.add_argument("--readings", type=int, default=0,
                    help="only time the grid's objects with and without the second reading, alternating this "
                         "many times (medians and their ratio)")
    ap.add_argument("--grid-only", action="store_true")
    ap.add_argument("--scale-only", action="store_true")
    ap.add_argument("--work", default=None, help="where synthetic data is kept (reused between runs)")
    ap.add_argument("--json", default=None, help="also write the rows to this JSON file")
    args = ap.parse_args(argv)

    work = Path(args.work) if args.work else Path(tempfile.gettempdir()) / "relicgpu_bench_assembly"
    work.mkdir(parents=True, exist_ok=True)
    report = {"machine": {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(),
                          "python": platform.python_version()},
              "args": {k: v for k, v in vars(args).items()}}
    if args.readings:
        report["readings"] = readings(args, work)
    elif not args.scale_only:
        print("grid ...", file=sys.stderr)
        rows = grid(args, work)
        report["grid"] = rows
        report["grid_summary"] = print_grid(rows, args.top_k)
    if not (args.grid_only or args.readings):
        print("scale ...", file=sys.stderr)
        rows = scale(args, work)
        report["scale"] = rows
        print_scale(rows)
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1, default=float))
        print(f"\nwrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
