"""Benchmark of the feature fusion (issue 4): curvature alone, a fixed hand-weighted linear mix
of the four features, and the trained MLP, on held-out synthetic pairs.

    python scripts/bench_fusion.py [--pairs 200] [--workers 2] [--weights W.npz] [--lcs-only-full]
                                   [--out bench-results/fusion.json]

Objects cycle through all built-in shapes, 2 to 6 pieces and noise 0, 0.0005, 0.001 (of the
object size), synth seeds from 1000 (training uses 0.., model selection 500..); up to two touching
pairs per object, the first --pairs pairs in seed order. Every fusion sees the same pairs, each
segmented once (numpy backend); a fusion's fused values replace the contours' (checked once
against prepare with Params(fusion_weights=...)), so only the fusion differs. Per fusion:

- LCS true share: the LCS correspondences (circular LCS over every contour pair, as in
  match_pair) whose points lie within 1% of the pair scale of each other under the true pose;
- LCS starts ok: share of pairs where one of the RANSAC poses over those LCS correspondences
  (match_pair's LCS start source alone, same seed) carries b within 5% of the scale (RMS of its
  vertices) of its true place -- cheap, and what the fusion changes;
- pairs ok: full match_pair (every start source) accepted with b's vertices within 1% of the
  object size (RMS) of their true place; median pose error (RMS, object units) of its transform;
- with --lcs-only-full also match_pair from the LCS starts alone (other sources off), which
  isolates the fusion's effect on the splicing; --skip-full leaves the full match_pair out.

Last, per baseline: on how many pairs the MLP succeeds where the baseline fails and back.
Work is spread over --workers processes (at most 2 on the shared machine), one object each.
"""
from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one thread per worker process

import argparse  # noqa: E402
import json  # noqa: E402
import multiprocessing as mp  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

from relicgpu import fusion_data as fd  # noqa: E402
from relicgpu.pair import fusion as fusion_mod  # noqa: E402
from relicgpu import fusion_train as ft  # noqa: E402
from relicgpu.io.files import atomic_write_json  # noqa: E402
from relicgpu.params import Params  # noqa: E402
from relicgpu.pair.prepare import prepare  # noqa: E402

# the baselines, on the inputs standardised with the trained model's statistics (so that the
# flag threshold eps means the same spread for all three): curvature alone, and the four
# features f with equal weight (no g terms)
CURVATURE = (0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
HAND_MIX = (0.0, 0.0, 0.0, 0.0, 0.5, 0.5, 0.5, 0.5)
NOISES = (0.0, 0.0005, 0.001)


def bench_specs(count: int, seed: int) -> list[fd.ObjectSpec]:
    shapes = fd.SHAPES
    return [fd.ObjectSpec(shapes[k % 3], 2 + (k // 3) % 5, seed + k, NOISES[(k // 15) % 3]) for k in range(count)]


_STATE: dict = {}


def _init(models, paths, full, full_lcs_only, cache_dir):
    _STATE.update(models=models, paths=paths, full=full, full_lcs_only=full_lcs_only, cache_dir=cache_dir)


def evaluate_object(spec: fd.ObjectSpec) -> list[dict]:
    """Every fusion on the touching pairs of one object: one row per pair."""
    models, paths = _STATE["models"], _STATE["paths"]
    rows = []
    for pair in fd.build_pairs([spec], progress=False, cache_dir=_STATE["cache_dir"]):
        row = {"spec": spec.__dict__, "i": pair.i, "j": pair.j}
        for name, model in models.items():
            params = Params(fusion_weights=str(paths[name]))
            check = ft.lcs_check(pair, model, params)
            r = {"lcs_true": check.score.true, "lcs_total": check.score.total, "start_ok": check.start_ok,
                 "start_err": check.start_error}
            if _STATE["full"]:
                r["ok"], r["err"], match = ft.pair_result(pair, model, params)
                r["reason"] = match.reason
            if _STATE["full_lcs_only"]:
                r["ok_lcs"], r["err_lcs"], _ = ft.pair_result(pair, model, ft.lcs_only(params))
            row[name] = r
        rows.append(row)
    return rows


def check_swap(spec: fd.ObjectSpec, models, paths, cache_dir) -> None:
    """The swapped fused values are what prepare makes with each weights file."""
    pair = fd.build_pairs([spec], progress=False, cache_dir=cache_dir)[0]
    for name, model in models.items():
        p = prepare(pair.prepared_a.fragment, Params(fusion_weights=str(paths[name])), "numpy", scale=pair.scale)
        q = ft.with_model(pair.prepared_a, model)
        if not all(np.allclose(c.fused, d.fused, atol=1e-9) for c, d in zip(p.contours, q.contours)):
            raise SystemExit(f"{name}: fused values differ from prepare's")


def summarise(rows: list[dict], names) -> dict:
    table = {}
    for name in names:
        r = [row[name] for row in rows]
        t = {
            "lcs_true_share": sum(x["lcs_true"] for x in r) / max(1, sum(x["lcs_total"] for x in r)),
            "lcs_correspondences": int(sum(x["lcs_total"] for x in r)),
            "lcs_starts_ok": float(np.mean([x["start_ok"] for x in r])),
        }
        if "ok" in r[0]:
            t["pair_success"] = float(np.mean([x["ok"] for x in r]))
            t["median_pose_error"] = float(np.median([x["err"] for x in r]))
        if "ok_lcs" in r[0]:
            t["lcs_only_pair_success"] = float(np.mean([x["ok_lcs"] for x in r]))
            t["lcs_only_median_pose_error"] = float(np.median([x["err_lcs"] for x in r]))
        table[name] = t
    return table


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=200)
    ap.add_argument("--seed", type=int, default=1000, help="synth seed of the first object")
    ap.add_argument("--weights", default=None, help="trained weights (default: the shipped ones)")
    ap.add_argument("--workers", type=int, default=2, help="processes (the shared machine has 2 cores)")
    ap.add_argument("--lcs-only-full", action="store_true", help="also run match_pair from the LCS starts alone")
    ap.add_argument("--skip-full", action="store_true", help="no match_pair with every start source")
    ap.add_argument("--out", default="bench-results/fusion.json")
    ap.add_argument("--cache-dir", default=None, help="prepared pairs cache (default: temp dir)")
    args = ap.parse_args(argv)
    if args.pairs < 1 or args.workers < 1:
        raise SystemExit("--pairs and --workers must be positive")

    trained = fusion_mod.load_model(args.weights)
    if trained.meta.get("made_by") != "relicgpu.fusion_train.train":
        print("note: the weights are not a trained MLP", file=sys.stderr)
    models = {
        "curvature": fusion_mod.hand_weighted_model(CURVATURE, trained.mean, trained.std),
        "hand mix": fusion_mod.hand_weighted_model(HAND_MIX, trained.mean, trained.std),
        "trained MLP": trained,
    }
    tmp = Path(tempfile.mkdtemp(prefix="bench-fusion-"))
    paths = {name: tmp / (name.replace(" ", "_") + ".npz") for name in models}
    for name, model in models.items():
        fusion_mod.save_model(paths[name], model)

    t0 = time.perf_counter()
    specs = bench_specs(args.pairs, args.seed)  # at least one touching pair per object
    check_swap(specs[0], models, paths, args.cache_dir)
    rows, used = [], 0
    bar = tqdm(total=args.pairs, desc="bench-fusion", file=sys.stderr)
    init = (models, paths, not args.skip_full, args.lcs_only_full, args.cache_dir)
    with mp.get_context("fork").Pool(min(args.workers, 2), _init, init) if args.workers > 1 else _Serial(init) as pool:
        for obj_rows in pool.imap(evaluate_object, specs, chunksize=1):  # in seed order
            used += 1
            take = obj_rows[: args.pairs - len(rows)]
            rows += take
            bar.update(len(take))
            if len(rows) >= args.pairs:
                pool.terminate()
                break
    bar.close()
    elapsed = time.perf_counter() - t0

    names = list(models)
    table = summarise(rows, names)
    print(f"{len(rows)} held-out pairs from {used} objects (seeds {args.seed}..{args.seed + used - 1}, shapes "
          f"{', '.join(fd.SHAPES)}, 2-6 pieces, noise 0-0.001), {args.workers} workers, {elapsed:.0f} s")
    cols = [("LCS true share", "lcs_true_share", ".4f"), ("LCS starts ok", "lcs_starts_ok", ".3f")]
    if not args.skip_full:
        cols += [("pairs ok", "pair_success", ".3f"), ("median err", "median_pose_error", ".2e")]
    if args.lcs_only_full:
        cols += [("LCS-only ok", "lcs_only_pair_success", ".3f"), ("LCS-only err", "lcs_only_median_pose_error", ".2e")]
    print(f"{'fusion':<12}" + "".join(f" {c[0]:>14}" for c in cols))
    for name, t in table.items():
        print(f"{name:<12}" + "".join(f" {format(t[key], fmt):>14}" for _, key, fmt in cols))
    versus = {}
    kinds = [("start_ok", "LCS starts ok")] + [("ok", "pairs ok")] * (not args.skip_full) \
        + [("ok_lcs", "LCS-only pairs ok")] * args.lcs_only_full
    for base in names[:-1]:
        versus[base] = {}
        for key, label in kinds:
            gain = sum(bool(r["trained MLP"][key] and not r[base][key]) for r in rows)
            loss = sum(bool(r[base][key] and not r["trained MLP"][key]) for r in rows)
            versus[base][key] = {"only_mlp": gain, "only_baseline": loss}
            print(f"trained MLP vs {base}, {label}: only with the MLP {gain}, only with {base} {loss}")
    doc = {"pairs": len(rows), "objects": used, "seed": args.seed, "seconds": round(elapsed, 1),
           "workers": args.workers, "lcs_eps": Params().lcs_eps, "feature_stride": Params().feature_stride,
           "start_within": ft.START_WITHIN, "params": Params().to_dict(), "curvature_mix": CURVATURE, "hand_mix": HAND_MIX, "weights": args.weights or "shipped",
           "weights_meta": trained.meta, "table": table, "versus": versus, "per_pair": rows}
    atomic_write_json(Path(args.out), json.loads(json.dumps(doc, default=_plain)))
    print(f"wrote {args.out}")
    return 0


def _plain(o):
    if isinstance(o, np.bool_):
        return bool(o)
    if isinstance(o, np.integer):
        return int(o)
    return float(o)


class _Serial:
    """Pool stand-in for --workers 1."""

    def __init__(self, init):
        _init(*init)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def imap(self, fn, items, chunksize=1):
        return map(fn, items)

    def terminate(self):
        pass


if __name__ == "__main__":
    sys.exit(main())
