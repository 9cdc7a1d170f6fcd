#!/usr/bin/env python
"""Time each stage of match_pair for pairs of the sizes in the paper's Table 1.

    python scripts/bench_pair.py [--backend numpy] [--repeats 3] [--json out.json]

Pairs come from relicgpu.synth (2-piece vases, slabs and torsos) whose two fragments have the
paper's per-fragment vertex counts within 5% (`CASES`: a shape, seed and `faces` found by a search
over seeds for the paper's ratio of the two counts, then over `faces` for their sum). Prints the
median time per stage (ms) over the repeats and the paper's total beside ours, and stops with an
error where a pair's counts are off by more than 5% (at --size-factor 1).
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time

import numpy as np

PAPER = [(8046, 10314, 1342), (5142, 4408, 892), (7250, 5692, 1311), (15064, 20956, 1890), (12476, 10346, 1420)]
# (shape, seed, faces, swap): relicgpu.synth.generate(shape, 2, seed, faces, noise=0.0005) gives the
# paper's pair (swap: its fragments in the other order), vertices 8163/10511, 5235/4321, 7121/5843,
# 15128/20809 and 12604/10373
CASES = [("vase", 12, 19394, False), ("torso", 18, 11070, True), ("vase", 27, 13135, False),
         ("slab", 19, 40721, False), ("slab", 13, 26354, False)]
MAX_COUNT_ERROR = 0.05


def main(argv=None) -> int:
    from relicgpu.params import SEGMENTATIONS, Params, parse_assignments, with_segmentations

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backend", default="numpy")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", default=None, help="write the results here")
    ap.add_argument("--size-factor", type=float, default=1.0,
                    help="scale the paper's vertex counts (e.g. 0.1 for a smoke run; figures need 1)")
    ap.add_argument("--segmentation", choices=SEGMENTATIONS,
                    help="Params.segmentation (default: Params' own)")
    ap.add_argument("--second-segmentation", choices=SEGMENTATIONS + ("none",),
                    help="Params.second_segmentation, the reading a pair is matched on again where the first "
                         "finds no fit (none: no second reading; default: Params' own)")
    ap.add_argument("--pairs", type=int, default=len(PAPER), help="only the first N pairs of the table")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                    help="a Params field (repeatable), e.g. facet_outline=0")
    args = ap.parse_args(argv)

    from relicgpu import synth
    from relicgpu.backends import resolve
    from relicgpu.pair.icp import rotation_angle_deg
    from relicgpu.pair.pipeline import match_pair, pair_scale
    from relicgpu.pair.prepare import prepare

    backend = resolve(args.backend)
    params = with_segmentations(Params(), args.segmentation, args.second_segmentation).with_(**parse_assignments(args.set))
    rows = []
    for (va, vb, paper_ms), (shape, seed, faces, swap) in list(zip(PAPER, CASES))[: args.pairs]:
        r = synth.generate(shape, pieces=2, seed=seed, faces=max(200, round(faces * args.size_factor)), noise=0.0005)
        i, j = (1, 0) if swap else (0, 1)
        a, b = r.fragments[i], r.fragments[j]
        off = max(abs(len(a.vertices) / va - 1), abs(len(b.vertices) / vb - 1))
        if args.size_factor == 1.0 and off > MAX_COUNT_ERROR:
            raise SystemExit(f"bench_pair: {shape} seed {seed} has {len(a.vertices)}/{len(b.vertices)} vertices, "
                             f"{off:.1%} off the paper's {va}/{vb} (more than {MAX_COUNT_ERROR:.0%}): update CASES")
        truth = np.linalg.inv(r.poses[i]) @ r.poses[j]
        scale = pair_scale(a, b, params)
        match_pair(a, b, params, backend, scale=scale)  # warm-up: kernel compiles, caches
        stages: dict[str, list[float]] = {}
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            pa = prepare(a, params, backend, scale=scale)
            pb = prepare(b, params, backend, scale=scale)
            t1 = time.perf_counter()
            m = match_pair(pa, pb, params, backend, scale=scale)
            t2 = time.perf_counter()
            for k in pa.timings:
                stages.setdefault(k, []).append(pa.timings[k] + pb.timings[k])
            for k in ("coarse", "icp+verify"):
                stages.setdefault(k, []).append(m.timings[k])
            stages.setdefault("total", []).append((t1 - t0) + (t2 - t1))
        rot = rotation_angle_deg(m.transform[:3, :3] @ truth[:3, :3].T)
        row = {"shape": shape, "vertices": [len(a.vertices), len(b.vertices)], "paper_vertices": [va, vb], "reason": m.reason,
               "paper_ms": paper_ms, "accepted": bool(m.accepted), "rotation_error_deg": rot,
               "ms": {k: 1000 * statistics.median(v) for k, v in stages.items()}}
        rows.append(row)
        print(f"  {shape} {row['vertices']}: {row['ms']['total']:.0f} ms", file=sys.stderr)

    names = list(rows[0]["ms"])
    print(f"\nmatch_pair stages, backend {backend.name}, median of {args.repeats} (ms)\n")
    head = f"| vertices (ours) | paper vertices | " + " | ".join(names) + " | paper total | matched | rot err |"
    print(head)
    print("|" + "---|" * (len(names) + 5))
    for r in rows:
        cells = " | ".join(f"{r['ms'][k]:.0f}" for k in names)
        print(f"| {r['vertices'][0]}/{r['vertices'][1]} | {r['paper_vertices'][0]}/{r['paper_vertices'][1]} | {cells} | "
              f"{r['paper_ms']} | {'yes' if r['accepted'] else 'no'} | {r['rotation_error_deg']:.2f} |")
    if args.json:
        from relicgpu.io.files import atomic_write_json
        atomic_write_json(args.json, {"backend": backend.name, "repeats": args.repeats, "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
