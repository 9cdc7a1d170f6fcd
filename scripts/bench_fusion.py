"""Benchmark of the feature fusion (issue 4): curvature alone, a fixed hand-weighted linear mix
of the four features, and the trained MLP, on held-out synthetic pairs.

    python scripts/bench_fusion.py [--pairs 200] [--time-limit 600] [--weights W.npz] [--out F.json]

Objects cycle through all built-in shapes, 2 to 6 pieces and noise 0, 0.0005, 0.001 (of the
object size), synth seeds from 1000 (training uses 0.., model selection 500..); up to two touching
pairs per object. Per fusion model and pair:
- LCS true share: the LCS correspondences (circular LCS over every contour pair, as in
  match_pair) whose points lie within 1% of the pair scale of each other under the true pose;
- pair success: match_pair accepted with b's vertices within 1% of the object size (RMS) of
  their true place, with Params(fusion_weights=model file) (all starts), and with
  max_patches=0 as well (LCS starts alone);
- median pose error (RMS of b's vertices, object units) of both.
The fragments are segmented once per pair; each model's fused values replace the contours'
(checked once against prepare with Params(fusion_weights=...)). Stops starting new pairs after
--time-limit seconds and says how many pairs it ran.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from relicgpu import fusion as fusion_mod
from relicgpu import fusion_train as ft
from relicgpu.io import atomic_write_json
from relicgpu.params import Params
from relicgpu.pipeline import prepare

# the hand-weighted mix: the four standardised features f with equal weight (no g terms)
HAND_MIX = (0.0, 0.0, 0.0, 0.0, 0.5, 0.5, 0.5, 0.5)


def bench_specs(count: int, seed: int) -> list[ft.ObjectSpec]:
    shapes, noises = ft.SHAPES, (0.0, 0.0005, 0.001)
    return [ft.ObjectSpec(shapes[k % 3], 2 + (k // 3) % 5, seed + k, noises[(k // 15) % 3]) for k in range(count)]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=200)
    ap.add_argument("--time-limit", type=float, default=600.0, help="seconds after which no new pair is started")
    ap.add_argument("--seed", type=int, default=1000)
    ap.add_argument("--weights", default=None, help="trained weights (default: the shipped ones)")
    ap.add_argument("--out", default="bench-results/fusion.json")
    ap.add_argument("--cache-dir", default=None)
    args = ap.parse_args(argv)

    trained = fusion_mod.load_model(args.weights)
    if trained.meta.get("made_by") != "relicgpu.fusion_train.train":
        print("note: the weights are not a trained MLP", file=sys.stderr)
    tmp = Path(tempfile.mkdtemp(prefix="bench-fusion-"))
    models = {
        "curvature": fusion_mod.hand_weighted_model(),
        "hand mix": fusion_mod.hand_weighted_model(HAND_MIX, trained.mean, trained.std),
        "trained MLP": trained,
    }
    paths = {}
    for name, model in models.items():
        paths[name] = tmp / (name.replace(" ", "_") + ".npz")
        fusion_mod.save_model(paths[name], model)
    eps = Params().lcs_eps

    rows = {name: {"lcs_true": 0, "lcs_total": 0, "ok": [], "err": [], "ok_lcs": [], "err_lcs": []} for name in models}
    t0 = time.perf_counter()
    done, checked, k = 0, False, 0
    bar = tqdm(total=args.pairs, desc="bench-fusion", file=sys.stderr)
    specs = bench_specs(4 * args.pairs, args.seed)
    while done < args.pairs and k < len(specs) and time.perf_counter() - t0 < args.time_limit:
        for pair in ft.build_pairs([specs[k]], progress=False, cache_dir=args.cache_dir):
            if done >= args.pairs or time.perf_counter() - t0 >= args.time_limit:
                break
            if not checked:  # the swapped fused values are what prepare makes with the weights file
                for name in models:
                    p = prepare(pair.prepared_a.fragment, Params(fusion_weights=str(paths[name])), "numpy",
                                scale=pair.scale)
                    q = ft.with_model(pair.prepared_a, models[name])
                    assert all(np.allclose(c.fused, d.fused, atol=1e-9) for c, d in zip(p.contours, q.contours))
                checked = True
            for name, model in models.items():
                row = rows[name]
                s = ft.lcs_score(pair, model, eps)
                row["lcs_true"] += s.true
                row["lcs_total"] += s.total
                params = Params(fusion_weights=str(paths[name]))
                ok, err, _ = ft.pair_result(pair, model, params)
                row["ok"].append(ok)
                row["err"].append(err)
                ok, err, _ = ft.pair_result(pair, model, params.with_(max_patches=0))
                row["ok_lcs"].append(ok)
                row["err_lcs"].append(err)
            done += 1
            bar.update(1)
        k += 1
    bar.close()
    elapsed = time.perf_counter() - t0

    table = {}
    for name, r in rows.items():
        table[name] = {
            "lcs_true_share": r["lcs_true"] / max(1, r["lcs_total"]),
            "lcs_correspondences": r["lcs_total"],
            "pair_success": float(np.mean(r["ok"])) if r["ok"] else 0.0,
            "median_pose_error": float(np.median(r["err"])) if r["err"] else float("nan"),
            "lcs_only_pair_success": float(np.mean(r["ok_lcs"])) if r["ok_lcs"] else 0.0,
            "lcs_only_median_pose_error": float(np.median(r["err_lcs"])) if r["err_lcs"] else float("nan"),
        }
    print(f"{done} held-out pairs from {k} objects (seeds {args.seed}..{args.seed + k - 1}, shapes "
          f"{', '.join(ft.SHAPES)}, 2-6 pieces, noise 0-0.001) in {elapsed:.0f} s"
          + ("" if done >= args.pairs else f" -- stopped at the {args.time_limit:.0f} s limit, short of {args.pairs}"))
    head = f"{'fusion':<12} {'LCS true share':>14} {'pairs ok':>9} {'median err':>11} {'LCS-only ok':>12} {'LCS-only err':>13}"
    print(head)
    for name, t in table.items():
        print(f"{name:<12} {t['lcs_true_share']:>14.4f} {t['pair_success']:>9.3f} {t['median_pose_error']:>11.2e} "
              f"{t['lcs_only_pair_success']:>12.3f} {t['lcs_only_median_pose_error']:>13.2e}")
    doc = {"pairs": done, "objects": k, "seed": args.seed, "seconds": round(elapsed, 1), "time_limit": args.time_limit,
           "lcs_eps": eps, "hand_mix": HAND_MIX, "weights": args.weights or "shipped", "weights_meta": trained.meta,
           "table": table, "per_pair": {n: {key: r[key] for key in ("ok", "err", "ok_lcs", "err_lcs")}
                                         for n, r in rows.items()}}
    atomic_write_json(Path(args.out), json.loads(json.dumps(doc, default=lambda o: bool(o) if isinstance(o, np.bool_) else float(o))))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
