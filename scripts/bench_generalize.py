"""How the pipeline holds on fractures it was not tuned on (issue 16): one row per family.

Families come from `relicgpu.synth.corpus` (fracture kind x scan kind: issue 16's twelve and the
three of `tetra`) and the ../shared/realdata sets with a known answer; the first row, "synth", is the control: the
project's own generator, where the pipeline was tuned. Per row:

  seg R / seg P   recall and precision of `relicgpu.pair.segment`'s fracture faces (the labels
                  `pipeline.prepare` uses) against the generator's, counted over all faces
  2nd R / 2nd P   the same of the second reading (`Params.second_segmentation`), on which a
                  pair is matched again where the first finds no fit ("-": none)
  pairs right     two-piece objects: `match_pair` accepted, rotation error < 2 degrees and
                  vertex RMS < 1% of the object size (largest side of its bounding box)
  rot err         median rotation error of the two-piece matches (accepted or not), degrees
  part acc        multi-piece objects through `relicgpu.assemble`: `evaluate.score` part
                  accuracy at 1% of the object size
  touch R         recall of the touching pairs among the used matches (multi-piece objects)
  matches right   multi-piece objects: of the verified matches (used and not), those that
                  join touching pieces within 2 degrees and 1% of the size of their true
                  relative pose, "verified right/verified (used right/used)": a wrong match the
                  assembly did not use cost it nothing, one it used misplaces a piece or more

    python scripts/bench_generalize.py --quick                       # a few minutes on 2 cores
    python scripts/bench_generalize.py --seeds 0,1,2 --json gen.json # the full table
    python scripts/bench_generalize.py --families voronoi-noisy --realdata none --backend warp-cpu
    python scripts/bench_generalize.py --families smooth-clean --realdata none --set patch_turns=36
    python scripts/bench_generalize.py --families vessel-noisy --realdata none --pieces 8 --every-pair
    python scripts/bench_generalize.py --families smooth-clean --realdata none --pieces 3,4 --no-two-piece \
        --multi-faces 6000 --coarse-faces 250

--coarse-faces N makes every other piece of each multi-piece object again at N faces a piece (the
same piece of the same cut, its pose and labels with it): pieces of one object at very different
resolutions, as Breaking Bad's are (190 to 15,000 faces a piece). Where a family's cut comes out
otherwise at N faces (rough and vessel cuts do), the case is skipped and says so.

--decimate-every-other N decimates every other piece of each multi-piece object towards N faces
(`relicgpu.synth.mixed.decimated`, within 0.5% of the size): pieces cut from one mesh at different
resolutions that share their break, Breaking Bad's case (with the `tetra` families, its faceted
breaks). --coarse-faces's pieces are remeshes of their own whose breaks stand off each other.

--every-pair also runs `match_pair` on every pair of pieces of each multi-piece object and prints
a second table: of the touching pairs, right / near (accepted within 5 degrees and 3% of the
size, over the bar) / wrong (accepted farther off) / missed; of the pairs that do not touch, the
accepted ones. A piece of an 8-piece object shares a fifth to a half of its break with one
neighbour, so these say more than the two-piece pairs.

A progress line per case goes to stderr; --dry builds the cases and checks their labels only.
"""
from __future__ import annotations

import argparse
import datetime
import json
import platform
import sys
import time

import numpy as np

from relicgpu.heap.evaluate import relative_pose_error, score
from relicgpu.synth import corpus
from relicgpu.synth.mixed import decimated
from relicgpu.pair.icp import invert
from relicgpu.params import SEGMENTATIONS, Params, parse_assignments, second_reading_params, with_segmentations

QUICK = {"seeds": "0", "faces": 3000, "multi_faces": 1500, "pieces": "5", "realdata_assemble": False}
FULL = {"seeds": "0,1,2", "faces": 6000, "multi_faces": 3000, "pieces": "5,8", "realdata_assemble": True}
CLOUD_PAIRS = ("breakingbad_drinkbottle_pointclouds",)  # realdata pairs of point clouds (known answer)
CONTROL = "synth"  # a control row: relicgpu.synth's own breaks (vase, torso, slab by seed; noise 0.0005)


def make_case(family: str, pieces: int | None, seed: int, faces: int):
    """The SynthResult of one case: a corpus family, the synth control, or a realdata set (pieces None)."""
    if pieces is None:
        return corpus.realdata(family, seed)
    if family == CONTROL:
        from relicgpu import synth
        return synth.generate(synth.SHAPES[seed % 3], pieces, seed, faces, noise=0.0005, progress=False)
    return corpus.generate(family, pieces, seed, faces)


def coarse_every_other(result, family: str, seed: int, faces: int):
    """`result` with every other piece (1, 3, ...) made again at `faces` faces a piece, or a
    ValueError where the cut comes out otherwise at that resolution (a piece's bounding box in the
    object frame more than 2% of the size off)."""
    from dataclasses import replace

    coarse = make_case(family, len(result.fragments), seed, faces)
    size = corpus.object_size(result)
    pieces = {k: (result, coarse)[k % 2] for k in range(len(result.fragments))}
    for k in range(1, len(result.fragments), 2):
        placed = [r.fragments[k].vertices @ r.poses[k][:3, :3].T + r.poses[k][:3, 3] for r in (result, coarse)]
        corners = [np.r_[p.min(0), p.max(0)] for p in placed]
        if np.abs(corners[0] - corners[1]).max() > 0.02 * size:
            raise ValueError(f"piece {k} comes out otherwise at {faces} faces")
    return replace(result, fragments=[pieces[k].fragments[k] for k in pieces],
                   poses=[pieces[k].poses[k] for k in pieces],
                   fracture_faces=[pieces[k].fracture_faces[k] for k in pieces])


def segmentation_counts(result, params: Params, backend) -> dict:
    """True positives, predicted and true fracture faces of `segment` over all fragments."""
    from relicgpu.pair.segment import segment

    tp = pred = true = faces = 0
    for frag, truth in zip(result.fragments, result.fracture_faces):
        labels = segment(frag.vertices, frag.faces, params, frag.size, backend).fracture_faces
        tp += int(np.count_nonzero(labels & truth))
        pred += int(np.count_nonzero(labels))
        true += int(np.count_nonzero(truth))
        faces += len(truth)
    return {"tp": tp, "pred": pred, "true": true, "faces": faces}


def rotation_error_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(a[:3, :3] @ b[:3, :3].T) - 1) / 2, -1, 1))))


def pose_errors(result, i: int, j: int, transform: np.ndarray, size: float) -> tuple[float, float]:
    """Rotation error (degrees) and vertex RMS (of `size`) of `transform` carrying piece j onto
    piece i, against their true relative pose."""
    true = invert(result.poses[i]) @ result.poses[j]
    rms = relative_pose_error(result.fragments[j].vertices, transform, result.poses[i], result.poses[j])
    return rotation_error_deg(transform, true), rms / size


def is_right(rot: float, rms: float) -> bool:
    """Within 2 degrees and 1% of the size: the bar for a right match."""
    return rot < 2.0 and rms < 0.01


def pair_case(result, params: Params, backend) -> dict:
    """match_pair on a two-piece object: b = fragment 1 carried onto a = fragment 0."""
    from relicgpu.pair.pipeline import match_pair

    size = corpus.object_size(result)
    a, b = result.fragments
    m = match_pair(a, b, params, backend)
    rot, rms = pose_errors(result, 0, 1, m.transform, size)
    return {"accepted": bool(m.accepted), "rotation_error_deg": rot, "rms": rms, "reason": m.reason,
            "right": bool(m.accepted and is_right(rot, rms))}


def every_pair_case(result, params: Params, backend) -> dict:
    """match_pair on every pair of pieces (b = the later piece carried onto a): counts of the
    touching pairs right, near, wrong and missed, and of the other pairs accepted."""
    from relicgpu.heap.assembly import common_scale
    from relicgpu.pair.pipeline import match_pair
    from relicgpu.pair.prepare import prepare

    size = corpus.object_size(result)
    touching = {tuple(sorted(t)) for t in result.touching}
    n = len(result.fragments)
    scale = common_scale(result.fragments, params)  # one scale for all, as `assemble` prepares
    prepared = [prepare(f, params, backend, scale=scale) for f in result.fragments]
    counts = dict.fromkeys(("touching", "right", "near", "wrong", "missed", "apart", "apart_accepted"), 0)
    for i in range(n):
        for j in range(i + 1, n):
            m = match_pair(prepared[i], prepared[j], params, backend, scale=scale)
            if (i, j) not in touching:
                counts["apart"] += 1
                counts["apart_accepted"] += int(m.accepted)
                continue
            counts["touching"] += 1
            rot, rms = pose_errors(result, i, j, m.transform, size)
            kind = ("missed" if not m.accepted else "right" if is_right(rot, rms) else
                    "near" if rot < 5 and rms < 0.03 else "wrong")
            counts[kind] += 1
    return counts


def cloud_pair_case(name: str, params: Params, backend) -> dict:
    """The Breaking Bad bottle (two point clouds): the inverse of solution.json's T carries obj2 onto obj1."""
    from relicgpu.io.load import load_fragment
    from relicgpu.pair.pipeline import match_pair

    folder = corpus.REALDATA / name
    a, b = load_fragment(folder / "obj1_challenge.ply"), load_fragment(folder / "obj2_challenge.ply")
    true = invert(np.asarray(json.loads((folder / "solution.json").read_text())["T"], np.float64))
    both = np.vstack([a.vertices, b.vertices @ true[:3, :3].T + true[:3, 3]])
    size = float(np.ptp(both, axis=0).max())
    m = match_pair(a, b, params, backend)
    rot = rotation_error_deg(m.transform, true)
    rms = relative_pose_error(b.vertices, m.transform, np.eye(4), true) / size
    return {"accepted": bool(m.accepted), "rotation_error_deg": rot, "rms": rms, "reason": m.reason,
            "right": bool(m.accepted and is_right(rot, rms)), "points": [len(a.vertices), len(b.vertices)]}


def assembly_case(result, params: Params, backend, workers: int, size: float | None = None) -> dict:
    """`assemble` on the result's fragments, scored; size: the object's (default: `corpus.object_size`)."""
    from relicgpu.heap.assembly import assemble

    size = size or corpus.object_size(result)
    asm = assemble(list(result.fragments), params, backend, engine="local", workers=workers, progress=False)
    index = {f.name: i for i, f in enumerate(result.fragments)}
    order = [index[n] for n in asm.names]  # the assembly's fragments by name (it may reorder)
    at = {n: k for k, n in enumerate(asm.names)}
    touching = [(at[result.fragments[i].name], at[result.fragments[j].name]) for i, j in result.touching
                if result.fragments[i].name in at and result.fragments[j].name in at]
    used = [(m.a, m.b, np.asarray(m.transform)) for m in asm.matches if m.used]
    right = [match_right(result, order, m.a, m.b, np.asarray(m.transform), size) for m in asm.matches]
    s = score([result.fragments[k].vertices for k in order], list(asm.poses), list(asm.groups),
              [result.poses[k] for k in order], touching, used, unit=size)
    return {"part_accuracy": s.part_accuracy, "touching_recall": s.pair_recall, "used": s.n_used,
            "touching": s.n_touching, "verified": len(asm.matches), "groups": asm.n_groups,
            "fragments_assembled": len(asm.names), "verified_right": int(sum(right)),
            "used_right": int(sum(r for r, m in zip(right, asm.matches) if m.used))}


def match_right(result, order: list[int], a: int, b: int, transform: np.ndarray, size: float) -> bool:
    """Whether a match (assembly indices a, b; `transform` carries b onto a) joins touching pieces
    within 2 degrees and 1% of the size of their true relative pose."""
    i, j = order[a], order[b]
    if tuple(sorted((i, j))) not in {tuple(sorted(t)) for t in result.touching}:
        return False
    return is_right(*pose_errors(result, i, j, transform, size))


def run(args) -> dict:
    from relicgpu.backends import resolve

    preset = QUICK if args.quick else FULL
    seeds = [int(s) for s in (args.seeds or preset["seeds"]).split(",")]
    pieces = [int(p) for p in (args.pieces or preset["pieces"]).split(",") if int(p) > 1]
    families = ((CONTROL,) + corpus.FAMILIES if args.families == "all" else
                [f for f in args.families.split(",") if f])
    realdata = (list(corpus.REALDATA_SETS) + list(CLOUD_PAIRS) if args.realdata == "all" else
                [] if args.realdata == "none" else args.realdata.split(","))
    faces = args.faces or preset["faces"]
    multi_faces = args.multi_faces or preset["multi_faces"]
    params = with_segmentations(Params(), args.segmentation, args.second_segmentation).with_(**args.set)
    second = second_reading_params(params)
    backend = resolve(args.backend)
    plan = [(fam, seed, 2) for fam in families for seed in seeds] if args.two_piece else []
    plan += [(fam, seed, p) for fam in families for seed in seeds for p in pieces]
    plan += [(name, seed, None) for name in realdata for seed in seeds[:1]]
    cases = []
    for k, (fam, seed, n) in enumerate(plan, 1):
        t0 = time.perf_counter()
        case = {"family": fam, "seed": seed, "pieces": n}
        if fam in CLOUD_PAIRS:  # point clouds: no faces to label, one pair with a known answer
            if not (corpus.REALDATA / fam).is_dir() or args.dry:
                continue
            p = case["pair"] = cloud_pair_case(fam, params, backend)
            case.update(pieces=2, faces_per_piece=0.0, true_share=float("nan"), time_s=time.perf_counter() - t0)
            print(f"[{k}/{len(plan)}] {fam}: {p['points']} points, pair {'accepted' if p['accepted'] else 'rejected'} "
                  f"rot {p['rotation_error_deg']:.1f} deg rms {p['rms']:.3f} -> {'right' if p['right'] else 'wrong'} "
                  f"({case['time_s']:.1f} s)", file=sys.stderr, flush=True)
            cases.append(case)
            continue
        try:
            result = make_case(fam, n, seed, faces if n == 2 else multi_faces)
        except FileNotFoundError as exc:
            print(f"[{k}/{len(plan)}] {fam}: skipped ({exc})", file=sys.stderr, flush=True)
            continue
        if args.coarse_faces and n not in (None, 2):
            try:
                result = coarse_every_other(result, fam, seed, args.coarse_faces)
            except ValueError as exc:
                print(f"[{k}/{len(plan)}] {fam} seed {seed}: skipped ({exc})", file=sys.stderr, flush=True)
                continue
        if args.decimate_every_other and n not in (None, 2):
            result = decimated(result, args.decimate_every_other)
        case["pieces"] = len(result.fragments)
        case["faces_per_piece"] = float(np.mean([len(f.faces) for f in result.fragments]))
        case["true_share"] = float(np.mean(np.concatenate(result.fracture_faces)))
        case["generate_s"] = time.perf_counter() - t0
        line = f"{case['pieces']} pcs x {case['faces_per_piece']:.0f} faces, true fracture {case['true_share']:.2f}"
        if not args.dry:
            case["seg"] = segmentation_counts(result, params, backend)
            c = case["seg"]
            line += f", seg R {c['tp'] / max(c['true'], 1):.2f} P {c['tp'] / max(c['pred'], 1):.2f}"
            if second is not None:
                case["seg2"] = segmentation_counts(result, second, backend)
                c = case["seg2"]
                line += f", second R {c['tp'] / max(c['true'], 1):.2f} P {c['tp'] / max(c['pred'], 1):.2f}"
            if n == 2:
                case["pair"] = pair_case(result, params, backend)
                p = case["pair"]
                line += (f", pair {'accepted' if p['accepted'] else 'rejected'} rot {p['rotation_error_deg']:.1f} deg "
                         f"rms {p['rms']:.3f} -> {'right' if p['right'] else 'wrong'}")
            elif n is not None or (args.realdata_assemble if args.realdata_assemble is not None
                                   else preset["realdata_assemble"]):
                case["assembly"] = assembly_case(result, params, backend, args.workers)
                if args.every_pair and n is not None:
                    case["every_pair"] = every_pair_case(result, params, backend)
                a = case["assembly"]
                line += (f", part acc {a['part_accuracy']:.2f}, touching recall {a['touching_recall']:.2f}, "
                         f"right matches {a['verified_right']} of {a['verified']} verified, {a['used_right']} of "
                         f"{a['used']} used")
        case["time_s"] = time.perf_counter() - t0
        print(f"[{k}/{len(plan)}] {fam} seed {seed}: {line} ({case['time_s']:.1f} s)", file=sys.stderr, flush=True)
        cases.append(case)
    return {"command": " ".join(["python"] + sys.argv), "date": datetime.date.today().isoformat(),
            "backend": backend.name, "set": args.set,
            "machine": f"{platform.machine()} {platform.processor() or ''}".strip(),
            "rows": table_rows(cases), "cases": cases}


def table_rows(cases: list) -> list[dict]:
    rows = []
    for fam in dict.fromkeys(c["family"] for c in cases):
        cs = [c for c in cases if c["family"] == fam]
        seg = [c["seg"] for c in cs if "seg" in c]
        seg2 = [c["seg2"] for c in cs if "seg2" in c]
        pairs = [c["pair"] for c in cs if "pair" in c]
        asm = [c["assembly"] for c in cs if "assembly" in c]
        tp, pred, true = (sum(s[k] for s in seg) for k in ("tp", "pred", "true"))
        tp2, pred2, true2 = (sum(s[k] for s in seg2) for k in ("tp", "pred", "true"))
        rows.append({
            "family": fam, "objects": len(cs),
            "faces_per_piece": float(np.mean([c["faces_per_piece"] for c in cs])) if seg or args_dry(cs) else None,
            "true_share": float(np.mean([c["true_share"] for c in cs])) if seg or args_dry(cs) else None,
            "seg_recall": tp / true if seg and true else None, "seg_precision": tp / pred if seg and pred else None,
            "seg2_recall": tp2 / true2 if seg2 and true2 else None,
            "seg2_precision": tp2 / pred2 if seg2 and pred2 else None,
            "pairs_right": sum(p["right"] for p in pairs), "pairs": len(pairs),
            "rotation_error_deg": float(np.median([p["rotation_error_deg"] for p in pairs])) if pairs else None,
            "part_accuracy": float(np.mean([a["part_accuracy"] for a in asm])) if asm else None,
            "touching_recall": float(np.mean([a["touching_recall"] for a in asm])) if asm else None,
            "verified_right": sum(a.get("verified_right", 0) for a in asm),
            "verified": sum(a["verified"] for a in asm), "used_right": sum(a.get("used_right", 0) for a in asm),
            "used": sum(a["used"] for a in asm),
            "every_pair": {k: sum(c["every_pair"][k] for c in cs if "every_pair" in c)
                           for k in next((c["every_pair"] for c in cs if "every_pair" in c), {})},
            "multi_objects": len(asm), "time_s": float(sum(c["time_s"] for c in cs))})
    return rows


def args_dry(cases: list) -> bool:
    """Cases built without the pipeline (--dry) still report their sizes."""
    return all("seg" not in c and "pair" not in c for c in cases)


def format_table(rows: list[dict]) -> str:
    f = lambda x, spec=".2f": "-" if x is None else format(x, spec)  # noqa: E731
    head = ("| family | objects | faces/piece | true fracture | seg R | seg P | 2nd R | 2nd P | pairs right | rot err deg "
            "| part acc | touch R | matches right | time s |")
    lines = [head, "|" + "---|" * 14]
    for r in rows:
        pairs = f"{r['pairs_right']}/{r['pairs']}" if r["pairs"] else "-"
        matches = (f"{r['verified_right']}/{r['verified']} ({r['used_right']}/{r['used']})"
                   if r.get("multi_objects") and "verified" in r else "-")
        lines.append(f"| {r['family']} | {r['objects']} | {f(r['faces_per_piece'], '.0f')} | {f(r['true_share'])} | "
                     f"{f(r['seg_recall'])} | {f(r['seg_precision'])} | {f(r.get('seg2_recall'))} | "
                     f"{f(r.get('seg2_precision'))} | {pairs} | {f(r['rotation_error_deg'], '.1f')} | "
                     f"{f(r['part_accuracy'])} | {f(r['touching_recall'])} | {matches} | {r['time_s']:.0f} |")
    return "\n".join(lines)


def format_pair_table(rows: list[dict]) -> str:
    """The --every-pair table: a line per family whose multi-piece objects had every pair matched."""
    lines = ["| family | touching pairs | right | near | wrong | missed | other pairs | of them accepted |",
             "|" + "---|" * 8]
    for r in rows:
        c = r.get("every_pair")
        if c:
            lines.append(f"| {r['family']} | {c['touching']} | {c['right']} | {c['near']} | {c['wrong']} | "
                         f"{c['missed']} | {c['apart']} | {c['apart_accepted']} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--families", default="all",
                    help=f"comma list or 'all' ({CONTROL} (the control), {', '.join(corpus.FAMILIES)})")
    ap.add_argument("--realdata", default="all",
                    help=f"comma list, 'all' or 'none' ({', '.join(corpus.REALDATA_SETS + CLOUD_PAIRS)}; "
                         "skipped where absent)")
    ap.add_argument("--seeds", help="comma list of seeds (quick: 0; full: 0,1,2)")
    ap.add_argument("--pieces", help="piece counts of the multi-piece objects, comma list; 0 for none "
                                     "(quick: 5; full: 5,8)")
    ap.add_argument("--faces", type=int, help="faces a piece of two-piece objects (quick 1500, full 4000)")
    ap.add_argument("--multi-faces", type=int, help="faces a piece of multi-piece objects (quick 800, full 2000)")
    ap.add_argument("--coarse-faces", type=int,
                    help="make every other piece of each multi-piece object again at this many faces")
    ap.add_argument("--decimate-every-other", type=int,
                    help="decimate every other piece of each multi-piece object towards this many faces")
    ap.add_argument("--backend", default="numpy", help="numpy, warp-cpu, ... (default numpy)")
    ap.add_argument("--workers", type=int, default=1, help="assemble's local workers (default 1)")
    ap.add_argument("--two-piece", action=argparse.BooleanOptionalAction, default=True,
                    help="the two-piece objects of each family and seed (default: yes)")
    ap.add_argument("--quick", action="store_true", help="one seed, small pieces, no realdata assembly")
    ap.add_argument("--realdata-assemble", action=argparse.BooleanOptionalAction, default=None,
                    help="assemble the 20-piece realdata sets (default: not in --quick)")
    ap.add_argument("--segmentation", choices=SEGMENTATIONS,
                    help="Params.segmentation for every case (default: Params' own)")
    ap.add_argument("--second-segmentation", choices=SEGMENTATIONS + ("none",),
                    help="Params.second_segmentation, the reading a pair is matched on again where the first "
                         "finds no fit (none: no second reading; default: Params' own)")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                    help="a Params field for every case (repeatable), e.g. patch_turns=36")
    ap.add_argument("--every-pair", action="store_true",
                    help="also match every pair of pieces of each multi-piece object (a second table)")
    ap.add_argument("--dry", action="store_true", help="build the cases and report their labels only")
    ap.add_argument("--json", help="write the rows and every case here")
    args = ap.parse_args(argv)
    try:
        args.set = parse_assignments(args.set)
    except ValueError as err:
        ap.error(f"--set {err}")
    out = run(args)
    print(format_table(out["rows"]))
    if args.every_pair:
        print()
        print(format_pair_table(out["rows"]))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(out, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
