"""Where the pair's fine stage takes a start near the truth: each touching pair of an object,
started a few degrees and a share of the size off its true pose, refined as `match_pair` refines
its starts (`fine.fine_stage`: ICP, then the point-to-plane polish), and counted right where it
ends under 2 degrees and 1% of the size (vertex RMS) from the truth.

A start the search brings within a few degrees should end right; on rescanned breaks the fine
stage drifted such starts off (docs/benchmarks.md, "The fine stage on facing pairs").
`--facing` sets `Params.fine_facing`, several values side by side in one run (none: no test);
`--facing-edge` sets `Params.facing_edge` (the median edge under which the test is made).

    python scripts/bench_fine.py --families vessel-noisy,voronoi-noisy --seeds 1 --pieces 6 --faces 12000
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from relicgpu.backends import resolve  # noqa: E402
from relicgpu.heap.assembly import common_scale  # noqa: E402
from relicgpu.pair.icp import apply, axis_rotation, invert, rotation_angle_deg  # noqa: E402
from relicgpu.pair.fine import fine_stage  # noqa: E402
from relicgpu.pair.prepare import prepare  # noqa: E402
from relicgpu.params import Params  # noqa: E402
from relicgpu.synth import corpus  # noqa: E402

# (degrees, share of the size) each start is off the truth: where the ranking ICP leaves right
# starts on rescans (1-2 degrees, about 1%) and twice that
OFFSETS = ((2.0, 0.01), (2.0, 0.01), (4.0, 0.02))


def starts_off(truth: np.ndarray, centre: np.ndarray, size: float, rng) -> list[np.ndarray]:
    """(4, 4) poses OFFSETS off the (4, 4) truth: turned about random axes through the (3,) centre
    (in the truth's target frame) and shifted along random directions."""
    out = []
    for deg, share in OFFSETS:
        axis, shift = rng.normal(size=3), rng.normal(size=3)
        turn = axis_rotation(axis / np.linalg.norm(axis), np.radians(deg))
        step = np.eye(4)
        step[:3, :3] = turn
        step[:3, 3] = centre - turn @ centre + share * size * shift / np.linalg.norm(shift)
        out.append(step @ truth)
    return out


def pair_errors(family: str, seed: int, pieces: int, faces: int, settings: dict, backend) -> list[dict]:
    """Each touching pair's fine stage from each start, per setting (name -> Params): rotation
    error (degrees) and vertex RMS (share of the size) of the result."""
    result = corpus.generate(family, pieces=pieces, seed=seed, faces=faces, scatter=False)
    params = Params()
    scale = common_scale(result.fragments, params)
    prepared = [prepare(f, params, backend, scale=scale) for f in result.fragments]
    size = corpus.object_size(result)
    rng = np.random.default_rng(seed)
    rows = []
    for i, j in sorted({tuple(sorted(t)) for t in result.touching}):
        pa, pb = prepared[i], prepared[j]
        truth = invert(result.poses[i]) @ result.poses[j]
        index = backend.nearest_index(pa.sample.fracture)
        v = result.fragments[j].vertices
        for k, start in enumerate(starts_off(truth, apply(truth, pb.sample.fracture.mean(axis=0)), size, rng)):
            row = {"pair": [i, j], "start": k}
            for name, p in settings.items():
                pose = fine_stage(pa, pb, start[None], p, backend, scale, index, 1)[0][0]
                row[name] = [rotation_angle_deg(pose[:3, :3] @ truth[:3, :3].T),
                             float(np.sqrt(((apply(pose, v) - apply(truth, v)) ** 2).sum(axis=1).mean())) / size]
            rows.append(row)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--families", default="vessel-noisy,smooth-noisy,voronoi-noisy,rough-noisy,tetra-noisy",
                    help="comma list of relicgpu.synth.corpus families")
    ap.add_argument("--seeds", default="1")
    ap.add_argument("--pieces", type=int, default=6)
    ap.add_argument("--faces", type=int, default=12000, help="faces a piece")
    ap.add_argument("--facing", default=f"none,{Params().fine_facing}", help="comma list of Params.fine_facing")
    ap.add_argument("--facing-edge", type=float, default=Params().facing_edge, help="Params.facing_edge")
    ap.add_argument("--backend", default="numpy")
    ap.add_argument("--json", help="write every pair's errors here")
    args = ap.parse_args(argv)
    base = Params(facing_edge=args.facing_edge)
    settings = {f: base.with_(fine_facing=None if f == "none" else float(f)) for f in args.facing.split(",")}
    backend = resolve(args.backend)
    names = list(settings)
    print("| family | seed | starts | " + " | ".join(f"facing {n}: right / median deg / median %" for n in names) + " |")
    print("|---|---|---|" + "---|" * len(names))
    every = []
    for family in args.families.split(","):
        for seed in (int(s) for s in args.seeds.split(",")):
            rows = pair_errors(family, seed, args.pieces, args.faces, settings, backend)
            every += [{"family": family, "seed": seed, **r} for r in rows]
            cells = []
            for n in names:
                e = np.array([r[n] for r in rows]).reshape(-1, 2)
                right = int(((e[:, 0] < 2.0) & (e[:, 1] < 0.01)).sum())
                cells.append(f"{right} / {np.median(e[:, 0]):.1f} / {100 * np.median(e[:, 1]):.2f}")
            print(f"| {family} | {seed} | {len(rows)} | " + " | ".join(cells) + " |", flush=True)
    for n in names:
        e = np.array([r[n] for r in every]).reshape(-1, 2)
        print(f"facing {n}: right {int(((e[:, 0] < 2.0) & (e[:, 1] < 0.01)).sum())} of {len(e)}")
    if args.json:
        Path(args.json).write_text(json.dumps({"command": " ".join(["python"] + sys.argv), "rows": every}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
