#!/usr/bin/env python
"""Where `match_pair`'s search loses a pair's right pose (issue 16).

    python scripts/bench_search.py --families smooth-noisy,rough-clean --seeds 0,1 --labels roughness,hybrid,truth,facets

For every touching pair of each multi-piece corpus object (`--pieces`, `--faces` a piece), the
pair's fits are searched as `match_pair` searches them (`pipeline._candidate_fits`: starts from
the LCS, point-pair votes and patches face to face; a short ICP that ranks them; the best
distinct poses refined) and the rotation error against the truth is taken after each stage:
the best start, the best pose after the ranking ICP, the polished fits. Verification is not run:
this measures whether the right pose is among the fits at all.

The fracture labels the search runs on (`--labels`):

- `roughness`, `hybrid`, `regions`, `union`: that segmentation (`Params.segmentation`; the pipeline
  reads a mesh with roughness first, hybrid second, `Params.second_segmentation`);
- `truth`: the generator's per-face fracture labels in place of the segmentation, all of a
  piece's fracture one facet;
- `facets`: those labels split by the neighbour each fracture face touches (one facet per
  contact), the patches an ideal segmentation would give.

A row per family and labels: pairs with a start within 10 degrees, with a right fit among the
polished ones (rotation under 2 degrees), and with the first polished fit right (the one
`match_pair` verifies first). The last column is the other half of the question: pairs whose
true pose passes verification (`meshfit.verify_mesh`, or `band_fit` where that refuses it for
its residual or facing), the checks a right fit would have to pass; each pair's line on stderr
gives the reason where it does not.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from relicgpu.params import SEGMENTATIONS  # noqa: E402

LABELS = SEGMENTATIONS + ("truth", "facets")


def facet_labels(result) -> list[np.ndarray]:
    """(F_i,) int per fragment: 0 on skin, 1 + k on fracture faces nearest to piece k (assembled)."""
    from scipy.spatial import cKDTree

    placed = [f.vertices @ p[:3, :3].T + p[:3, 3] for f, p in zip(result.fragments, result.poses)]
    trees = [cKDTree(v) for v in placed]
    out = []
    for k, (f, truth) in enumerate(zip(result.fragments, result.fracture_faces)):
        centres = placed[k][f.faces].mean(axis=1)
        d = np.stack([trees[m].query(centres)[0] if m != k else np.full(len(centres), np.inf)
                      for m in range(len(placed))], axis=1)
        out.append(np.where(np.asarray(truth, bool), 1 + d.argmin(axis=1), 0))
    return out


def search_stages(pa, pb, truth: np.ndarray, params, backend, scale: float) -> dict:
    """Rotation errors (degrees) of the pair's search after each stage (b onto a against `truth`)."""
    import relicgpu.pair.pipeline as pl
    from relicgpu.pair.icp import rotation_angle_deg

    calls = []  # batched_icp: the ranking ICP (twice), then the ICP of the kept hypotheses
    icp, polish = pl.batched_icp, pl.refine_point_to_plane

    def spy_icp(src, dst, starts, *a, **k):
        out = icp(src, dst, starts, *a, **k)
        calls.append((np.array(starts), out[0]))
        return out

    def spy_polish(*a, **k):
        out = polish(*a, **k)
        calls.append((None, out))
        return out

    def errors(poses) -> np.ndarray:
        return np.array([rotation_angle_deg(p[:3, :3] @ truth[:3, :3].T) for p in poses])

    pl.batched_icp, pl.refine_point_to_plane = spy_icp, spy_polish
    try:
        fits, _ = pl._candidate_fits(pa, pb, params, backend, None, scale, {"prepare": 0.0})
    finally:
        pl.batched_icp, pl.refine_point_to_plane = icp, polish
    if not calls:
        return {"starts": 0, "start": None, "ranked": None, "fits": []}
    return {"starts": len(calls[0][0]), "start": float(errors(calls[0][0]).min()),
            "ranked": float(errors(calls[1][1]).min()),
            "fits": errors([f[0] for f in fits]).round(2).tolist()}


def truth_verification(pa, pb, truth: np.ndarray, params, backend, scale: float) -> dict:
    """Whether the true pose of b onto a passes the mesh verification `match_pair` applies
    (`verify_mesh`, then `band_fit` on a residual or facing refusal), its overlap and reason."""
    from relicgpu.pair.meshfit import band_fit, verify_mesh
    from relicgpu.pair.verify import index_cache

    index_of = index_cache(backend)
    ver = verify_mesh(pa.sample, pb.sample, truth, backend, params, scale, index_of, params.max_rmse)
    if not ver.accepted:
        ver = band_fit(pa.sample, pb.sample, truth, backend, params, scale, index_of, ver) or ver
    return {"truth_verifies": bool(ver.accepted), "truth_overlap": float(ver.overlap), "truth_reason": ver.reason}


def run(family: str, seed: int, labels: str, args, backend) -> list[dict]:
    import relicgpu.pair.prepare as prep
    import relicgpu.pair.pipeline as pl
    from relicgpu.heap.assembly import common_scale
    from relicgpu.params import Params
    from relicgpu.synth import corpus

    result = corpus.generate(family, args.pieces, seed, args.faces)
    params = Params(segmentation=labels if labels in SEGMENTATIONS else Params.segmentation,
                    second_segmentation=None).with_(**args.set)
    scale = common_scale(result.fragments, params)
    given = {"truth": [np.asarray(t, np.int64) for t in result.fracture_faces],
             "facets": facet_labels(result)}.get(labels)
    segment = prep.segment

    def labelled(v, f, *a, k: int = 0, **kw):
        seg = segment(v, f, *a, **kw)
        facet = given[k]
        region = (facet > 0).astype(np.int64)
        return replace(seg, face_region=region, face_facet=facet, region_is_fracture=np.array([False, True]),
                       face_fracture_prob=region.astype(np.float64))

    prepared = []
    for k, frag in enumerate(result.fragments):
        if given is not None:  # the segmentation's own labels replaced by the generator's
            prep.segment = lambda v, f, *a, k=k, **kw: labelled(v, f, *a, k=k, **kw)
        try:
            prepared.append(pl.prepare(frag, params, backend, scale))
        finally:
            prep.segment = segment
    rows = []
    for i, j in result.touching:
        t0 = time.perf_counter()
        truth = np.linalg.inv(result.poses[i]) @ result.poses[j]
        s = search_stages(prepared[i], prepared[j], truth, params, backend, scale)
        s.update(truth_verification(prepared[i], prepared[j], truth, params, backend, scale))
        rows.append({"family": family, "seed": seed, "labels": labels, "pair": [i, j], **s,
                     "time_s": time.perf_counter() - t0})
        print(f"{family} seed {seed} {labels} {i}-{j}: {s['starts']} starts, best {s['start']:.1f} deg, "
              f"ranked {s['ranked']:.1f}, fits {s['fits']}" if s["start"] is not None else
              f"{family} seed {seed} {labels} {i}-{j}: no starts", f"| the truth: {s['truth_reason']}",
              file=sys.stderr, flush=True)
    return rows


def table(rows: list[dict]) -> list[str]:
    lines = ["| family | labels | touching pairs | a start within 10 deg | a right fit | first fit right | the truth verifies |",
             "|---|---|---|---|---|---|---|"]
    keys = sorted({(r["family"], LABELS.index(r["labels"])) for r in rows})
    for family, li in keys:
        got = [r for r in rows if r["family"] == family and r["labels"] == LABELS[li]]
        near = sum(r["start"] is not None and r["start"] < 10 for r in got)
        right = sum(any(e < 2 for e in r["fits"]) for r in got)
        first = sum(bool(r["fits"]) and r["fits"][0] < 2 for r in got)
        verifies = sum(r["truth_verifies"] for r in got)
        lines.append(f"| {family} | {LABELS[li]} | {len(got)} | {near} | {right} | {first} | {verifies} |")
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--families", default="rough-clean,smooth-clean,voronoi-clean,vessel-clean,"
                    "rough-noisy,smooth-noisy,voronoi-noisy,vessel-noisy")
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--pieces", type=int, default=5)
    ap.add_argument("--faces", type=int, default=3000, help="faces a piece")
    ap.add_argument("--labels", default="roughness,hybrid,truth,facets", help=f"comma list of {LABELS}")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                    help="a Params field set for the search (repeatable), e.g. patch_turns=24")
    ap.add_argument("--backend", default="numpy")
    ap.add_argument("--json", help="write every pair's row here")
    args = ap.parse_args(argv)
    from relicgpu.backends import resolve
    from relicgpu.params import parse_assignments

    try:
        args.set = parse_assignments(args.set)
    except ValueError as err:
        ap.error(f"--set {err}")

    labels = args.labels.split(",")
    unknown = set(labels) - set(LABELS)
    if unknown:
        ap.error(f"unknown --labels {sorted(unknown)}; choose from {LABELS}")
    backend = resolve(args.backend)
    rows = []
    for family in args.families.split(","):
        for seed in (int(s) for s in args.seeds.split(",")):
            for lab in labels:
                rows += run(family, seed, lab, args, backend)
    print("\n".join(table(rows)))
    if args.json:
        Path(args.json).write_text(json.dumps({"command": " ".join(sys.argv), "backend": backend.name, "set": args.set,
                                               "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
