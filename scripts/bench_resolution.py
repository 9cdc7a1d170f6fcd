#!/usr/bin/env python
"""Match two-piece objects meshed finely (scanner-like resolution) and count right poses.

    python scripts/bench_resolution.py --names vase,torso,slab --seeds 4,5,6,7 --faces 24000
    python scripts/bench_resolution.py --source corpus --names rough-noisy,vessel-noisy --seeds 1 --faces 16000
    python scripts/bench_resolution.py --roughness-spacing 0,0.02     # the old roughness beside today's

Each object is relicgpu.synth's (noise 0.05% of the size) or relicgpu.synth.corpus's two-piece object of
--faces faces a piece; `match_pair` runs once per value of --roughness-spacing
(`Params.roughness_spacing`; 0: the roughness at the mesh's own edges). A pair is right when
accepted with a rotation error under 2 degrees and the moved piece within 1% RMS of its place
(lengths relative to the object's size); accepted otherwise is WRONG, not accepted a miss.
"""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np


def verdict(a, b, truth, match) -> tuple[str, float]:
    """'right', 'WRONG' or 'miss', and the rotation error in degrees, of a match carrying b onto a."""
    from bench_clouds import score  # the same measure as the cloud benchmark's

    rot, rms = score(a, b, truth, match.transform)
    if not match.accepted:
        return "miss", rot
    return ("right" if rot < 2.0 and rms < 0.01 else "WRONG"), rot


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--source", choices=("synth", "corpus"), default="synth")
    ap.add_argument("--names", default="vase,torso,slab", help="synth shapes or corpus families, comma list")
    ap.add_argument("--seeds", default="0,1,2,3")
    ap.add_argument("--faces", type=int, default=24000, help="faces a piece")
    ap.add_argument("--roughness-spacing", default=None,
                    help="comma list of Params.roughness_spacing values (default: Params' own)")
    ap.add_argument("--backend", default="numpy")
    args = ap.parse_args(argv)

    from relicgpu import synth
    from relicgpu.synth import corpus
    from relicgpu.params import Params
    from relicgpu.pair.pipeline import match_pair

    spacings = [None] if args.roughness_spacing is None else [float(x) for x in args.roughness_spacing.split(",")]
    params = [Params() if s is None else Params(roughness_spacing=s) for s in spacings]
    counts = [dict(right=0, WRONG=0, miss=0) for _ in params]
    for name in args.names.split(","):
        for seed in (int(s) for s in args.seeds.split(",")):
            r = (synth.generate(name, pieces=2, seed=seed, faces=args.faces, noise=0.0005, progress=False)
                 if args.source == "synth" else corpus.generate(name, pieces=2, seed=seed, faces=args.faces))
            a, b = r.fragments
            truth = np.linalg.inv(r.poses[0]) @ r.poses[1]
            cells = []
            for p, count in zip(params, counts):
                t0 = time.perf_counter()
                v, rot = verdict(a, b, truth, match_pair(a, b, p, args.backend))
                count[v] += 1
                cells.append(f"{v} {rot:.1f} deg ({time.perf_counter() - t0:.1f} s)")
            print(f"  {name} seed {seed} ({len(a.faces)}/{len(b.faces)} faces): " + " | ".join(cells), flush=True)
    print(f"\n{args.source} two-piece objects at {args.faces} faces a piece, backend {args.backend}")
    for s, count in zip(spacings, counts):
        label = "Params' own" if s is None else f"{s:g}"
        print(f"  roughness_spacing {label}: {count['right']} right, {count['WRONG']} accepted at a wrong pose, "
              f"{count['miss']} missed")
    return 0


if __name__ == "__main__":
    sys.exit(main())
