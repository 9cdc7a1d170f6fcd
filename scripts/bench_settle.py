"""How far the settling moves pieces that are already right: each object's pieces at their true
poses, settled (`relicgpu.heap.settle`), and each piece's distance from its true place (RMS of its
vertices, a share of the object's size; the 1% bar of `evaluate.score`).

Started from the truth, a settling that holds pieces in place leaves every one well under 1%; one
that drifts on noisy contacts moves right pieces off (docs/benchmarks.md, "Moves on few pairs").
`--trusted` sets `settle.TRUSTED` (a fragment touching its neighbours at fewer pairs stays where it
is), several values side by side in one run; 0 turns the rule off.

    python scripts/bench_settle.py --families voronoi-noisy,vessel-noisy --seeds 0,1 --faces 1500
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from relicgpu.backends import resolve  # noqa: E402
from relicgpu.heap import settle as settling  # noqa: E402
from relicgpu.heap.assembly import common_scale  # noqa: E402
from relicgpu.pair.icp import apply  # noqa: E402
from relicgpu.pair.prepare import prepare  # noqa: E402
from relicgpu.params import Params  # noqa: E402
from relicgpu.synth import corpus  # noqa: E402


def drift(family: str, seed: int, pieces: int, faces: int, trusted: list[int], backend) -> dict:
    """Each piece's distance from its true place after settling from the truth, per `trusted` value.

    Returns
    -------
    dict: `faces` (mean faces a piece) and, per value, `off` ((pieces,) float, shares of the size)
    and `time_s`
    """
    result = corpus.generate(family, pieces=pieces, seed=seed, faces=faces, scatter=False)
    params = Params()
    scale = common_scale(result.fragments, params)
    samples = [prepare(f, params, backend, scale=scale).sample for f in result.fragments]
    size = corpus.object_size(result)
    out = {"faces": float(np.mean([len(f.faces) for f in result.fragments]))}
    saved = settling.TRUSTED
    try:
        for t in trusted:
            settling.TRUSTED = t
            t0 = time.perf_counter()
            pose = settling.settle(list(result.poses), [0] * pieces, samples, params, scale, backend)
            off = [float(np.sqrt(((apply(p, f.vertices) - apply(q, f.vertices)) ** 2).sum(axis=1).mean())) / size
                   for p, q, f in zip(pose, result.poses, result.fragments)]
            out[t] = {"off": np.array(off), "time_s": time.perf_counter() - t0}
    finally:
        settling.TRUSTED = saved
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--families", default="rough-noisy,smooth-noisy,voronoi-noisy,vessel-noisy,tetra-noisy",
                    help="comma list of relicgpu.synth.corpus families")
    ap.add_argument("--seeds", default="0,1,2,3")
    ap.add_argument("--pieces", type=int, default=5)
    ap.add_argument("--faces", type=int, default=1500, help="faces a piece")
    ap.add_argument("--trusted", default=f"0,{settling.TRUSTED}", help="comma list of settle.TRUSTED values")
    ap.add_argument("--backend", default="numpy")
    ap.add_argument("--json", help="write each object's per-piece distances here")
    args = ap.parse_args(argv)
    trusted = [int(t) for t in args.trusted.split(",")]
    backend = resolve(args.backend)
    rows = []
    print("| family | seed | faces/piece | " + " | ".join(f"TRUSTED {t}: max % / over 1% / s" for t in trusted) + " |")
    print("|---|---|---|" + "---|" * len(trusted))
    for family in args.families.split(","):
        for seed in (int(s) for s in args.seeds.split(",")):
            r = drift(family, seed, args.pieces, args.faces, trusted, backend)
            rows.append({"family": family, "seed": seed, **r})
            cells = [f"{100 * r[t]['off'].max():.2f} / {int((r[t]['off'] > 0.01).sum())} / {r[t]['time_s']:.1f}"
                     for t in trusted]
            print(f"| {family} | {seed} | {r['faces']:.0f} | " + " | ".join(cells) + " |", flush=True)
    for t in trusted:
        off = np.concatenate([r[t]["off"] for r in rows])
        print(f"TRUSTED {t}: {len(off)} pieces, median {100 * np.median(off):.3f}%, "
              f"over 1%: {int((off > 0.01).sum())}, median time {np.median([r[t]['time_s'] for r in rows]):.1f} s")
    if args.json:
        Path(args.json).write_text(json.dumps({"command": " ".join(["python"] + sys.argv), "rows": [
            {k: ({"off": v["off"].tolist(), "time_s": v["time_s"]} if isinstance(k, int) else v)
             for k, v in r.items()} for r in rows]}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
