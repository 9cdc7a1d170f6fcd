#!/usr/bin/env python
"""Match two-piece fractures given as sparse point clouds (or open meshes) and count right poses.

    python scripts/bench_clouds.py                                  # 10 pairs, with and without normals
    python scripts/bench_clouds.py --pairs 12 --first 12 --modes none   # held-out pairs 12-23
    python scripts/bench_clouds.py --source corpus --pairs 12           # an independent generator
    python scripts/bench_clouds.py --pairs 192 --modes none --workers 16  # a process a pair, 16 at a time
    python scripts/bench_clouds.py --source corpus --set min_skin=None  # Params changed for every pair
    python scripts/bench_clouds.py --source thin --pairs 108            # bookshelves and a plant, 12 seeds
    python scripts/bench_clouds.py --source corpus --kinds vessel-clean --pairs 48   # one family, seeds 0-47
    python scripts/bench_clouds.py --source realdata --pairs 20         # Blender shards, touching pairs 0-9 of each set
    python scripts/bench_clouds.py --source corpus --pieces 5 --pairs 8  # 8 objects of 5 pieces, assembled

Pair k is relicgpu.synth's two-piece {vase, torso, slab}[k % 3] of seed k // 3 (4,000 faces or --faces,
scanner noise 0.05% of the size); with --source corpus the clean two-piece object of
relicgpu.synth.corpus family {rough, smooth, voronoi, vessel}-clean [k % 4] of seed k // 4; with
--source thin relicgpu.synth.thin's family [k % 9] ({shelf02, shelf04, plant} x {flat, smooth,
rough}) of seed k // 9; with --source realdata the touching pair k // 2 (in `corpus.realdata`'s
order) of the ../shared/realdata Blender set [k % 2] (cell-fracture shards of a cube and a
cylinder, third-party: fractures this project did not make). --kinds keeps some of the source's
kinds (pair k is then kinds[k % len] of seed k // len). Each piece becomes --points points drawn
from its surface (seed 100 k + i) with Gaussian noise of --noise times the piece's size, with the
true normals (`normals`), with none (`none`), with normals estimated off the points as a scanner's
software writes them, passed as scanned (`estimated`), with the true normals' lines signed at
random (`unoriented`), as the mesh itself with three holes cut into its skin (`open`), or as the
closed mesh itself (`mesh`); `normals-file` and `none-file` write the cloud to an .xyz file and
read it back with `load_fragment`, as `relicgpu match` and `assemble` read a user's cloud (a cloud
that closes into a solid may come back meshed). A pair is right when `match_pair` accepts it with a
rotation error under 2 degrees and the moved piece's points within 1% RMS of their true place,
lengths relative to the object's size (the largest side of its assembled bounding box). A pair
accepted at a wrong pose is counted apart: it is worse than a miss. The summary gives each mode's
counts over all pairs and per shape (synth), family (corpus, thin) or set (realdata).

With --pieces over 2, case k is the object of pair k's kind and seed broken into that many pieces
(synth, corpus): every piece becomes an input as above (piece i seeded as piece i of pair k), the
inputs are assembled (`relicgpu.heap.assembly.assemble`, one process a case) and scored as
`bench_generalize.py` scores an object: part accuracy (pieces within 1% of the size of their true
place, from the best anchor), touching recall, used matches right.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace

import numpy as np

from relicgpu.params import Params, parse_assignments

SHAPES = ("vase", "torso", "slab")


CORPUS = ("rough-clean", "smooth-clean", "voronoi-clean", "vessel-clean")
MODES = ("normals", "none", "estimated", "unoriented", "normals-file", "none-file", "open", "mesh")


def source_kinds(source: str, kinds: str = "") -> tuple[str, ...]:
    """The shapes or families that pairs cycle through: all of `source`'s, or those of the comma list `kinds`."""
    from relicgpu.synth import thin
    from relicgpu.synth.corpus import FAMILIES, REALDATA_SETS

    default = {"synth": SHAPES, "corpus": CORPUS, "thin": thin.FAMILIES, "realdata": REALDATA_SETS}[source]
    every = FAMILIES if source == "corpus" else default
    chosen = tuple(k for k in kinds.split(",") if k) or default
    unknown = [k for k in chosen if k not in every]
    if unknown:
        raise ValueError(f"unknown {source} kinds {', '.join(unknown)}; choose from {', '.join(every)}")
    return chosen


def pair_case(k: int, source: str, kinds: str = "") -> tuple[str, int]:
    """(shape or family, seed) of pair k."""
    chosen = source_kinds(source, kinds)
    return chosen[k % len(chosen)], k // len(chosen)


def pair_name(k: int, source: str, kinds: str = "") -> str:
    return ("%s pair %d" if source == "realdata" else "%s seed %d") % pair_case(k, source, kinds)


def make_pair(k: int, mode: str, points: int, noise: float, source: str = "synth", kinds: str = "",
              faces: int = 4000):
    """The two fragments of pair k in `mode` and the truth carrying b onto a (synth and corpus
    objects made of about `faces` faces)."""
    kind, seed = pair_case(k, source, kinds)
    r = make_object(source, kind, seed, 2, faces)
    pieces = r.touching[seed] if source == "realdata" else (0, 1)
    truth = np.linalg.inv(r.poses[pieces[0]]) @ r.poses[pieces[1]]
    frags = [as_input(r.fragments[i], r.fracture_faces[i] if r.fracture_faces else None, mode, points, noise, k, i)
             for i in pieces]
    return frags[0], frags[1], truth


def make_object(source: str, kind: str, seed: int, pieces: int, faces: int):
    """The source's object (`SynthResult`) of `kind` and `seed` in `pieces` pieces (thin: two; realdata: the set)."""
    from relicgpu import synth
    from relicgpu.synth import corpus, thin

    if source == "corpus":
        return corpus.generate(kind, pieces=pieces, seed=seed, faces=faces)
    if source == "thin":
        return thin.generate(kind, seed=seed)
    if source == "realdata":
        return corpus.realdata(kind, seed=0)
    return synth.generate(kind, pieces=pieces, seed=seed, faces=faces, noise=0.0005, progress=False)


def as_input(f, fracture: np.ndarray | None, mode: str, points: int, noise: float, k: int, i: int):
    """Piece i of case k as `mode` gives it: a cloud of `points` drawn off its surface (seed 100 k + i,
    noise seed 7 k + i) with its normals as the mode has them, or its mesh (`open`: holes cut, `mesh`)."""
    from relicgpu.cloud.points import cloud_fragment
    import trimesh

    if mode == "mesh":
        return f
    if mode == "open":
        return _cut_holes(f, fracture, np.random.default_rng(100 * k + i))
    m = f.to_trimesh()
    p, fi = trimesh.sample.sample_surface(m, points, seed=100 * k + i)
    p = p + np.random.default_rng(7 * k + i).normal(size=p.shape) * noise * f.size
    normals = m.face_normals[fi] if mode.startswith("normals") else None
    if mode == "estimated":  # as a scanner's software writes them: plane fits, oriented
        from relicgpu.cloud.points import estimate_normals
        normals = estimate_normals(p)
    if mode == "unoriented":  # the true normals' lines, each sign at random
        normals = m.face_normals[fi] * np.random.default_rng(11 * k + i).choice([-1.0, 1.0], (len(p), 1))
    return _through_a_file(f.name, p, normals) if mode.endswith("-file") else cloud_fragment(f.name, p, normals)


def _through_a_file(name: str, points: np.ndarray, normals):
    """The cloud written to NAME.xyz (with its normals as three more columns) and read back by
    `load_fragment`."""
    import tempfile
    from pathlib import Path

    from relicgpu.io.load import load_fragment

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / f"{name}.xyz"
        np.savetxt(path, points if normals is None else np.c_[points, normals])
        return load_fragment(path, name=name)


def _cut_holes(fragment, fracture: np.ndarray, rng, holes: int = 3, radius: float = 0.06):
    """The fragment with `holes` round holes (radius a share of its size) cut into its skin."""
    from relicgpu.io.fragment import Fragment

    centres = fragment.vertices[fragment.faces].mean(1)
    keep = np.ones(len(centres), bool)
    skin = np.flatnonzero(~np.asarray(fracture, bool))
    for c in centres[rng.choice(skin, holes, replace=False)]:
        keep &= np.linalg.norm(centres - c, axis=1) > radius * fragment.size
    faces = fragment.faces[keep | np.asarray(fracture, bool)]
    used = np.unique(faces)
    remap = np.full(len(fragment.vertices), -1)
    remap[used] = np.arange(len(used))
    return Fragment(fragment.name, fragment.vertices[used], remap[faces].astype(np.int32), fragment.source)


def score(a, b, truth, transform) -> tuple[float, float]:
    """Rotation error (degrees) and RMS of b's points relative to the object's size."""
    from relicgpu.pair.icp import rotation_angle_deg

    rot = rotation_angle_deg(transform[:3, :3] @ truth[:3, :3].T)
    placed = b.vertices @ transform[:3, :3].T + transform[:3, 3]
    true = b.vertices @ truth[:3, :3].T + truth[:3, 3]
    whole = np.concatenate([a.vertices, true])
    size = float((whole.max(0) - whole.min(0)).max())
    return rot, float(np.sqrt(((placed - true) ** 2).sum(1).mean()) / size)


def run_pair(k: int, mode: str, points: int, noise: float, source: str, backend: str,
             changes: dict | None = None, kinds: str = "", faces: int = 4000) -> dict:
    """match_pair on pair k in `mode` with Params changed by `changes`, scored (a row of the JSON). A pair
    that cannot be made or matched is a row too, not accepted, its reason "error: ..." (the run goes on)."""
    from relicgpu import match_pair

    t0 = time.perf_counter()
    row = {"mode": mode, "pair": k, "case": pair_name(k, source, kinds)}
    try:
        a, b, truth = make_pair(k, mode, points, noise, source, kinds, faces)
        t0 = time.perf_counter()
        m = match_pair(a, b, Params().with_(**(changes or {})), backend=backend)
    except Exception as err:  # noqa: BLE001 - one pair's fault is reported in its row
        return {**row, "accepted": False, "rotation_error_deg": float("inf"), "rms": float("inf"),
                "reason": f"error: {type(err).__name__}: {err}", "seconds": time.perf_counter() - t0}
    rot, rms = score(a, b, truth, m.transform)
    return {**row, "accepted": bool(m.accepted), "rotation_error_deg": rot, "rms": rms, "reason": m.reason,
            "seconds": time.perf_counter() - t0}


def run_object(k: int, mode: str, points: int, noise: float, source: str, backend: str,
               changes: dict | None = None, kinds: str = "", faces: int = 4000, pieces: int = 5) -> dict:
    """`assemble` on the pieces of object k (case k's kind and seed, in `pieces` pieces) as `mode` gives
    them, scored as `bench_generalize.py` scores an object (a row of the JSON; an error is a row too)."""
    from bench_generalize import assembly_case

    from relicgpu.synth import corpus

    t0 = time.perf_counter()
    row = {"mode": mode, "object": k, "pieces": pieces, "case": pair_name(k, source, kinds)}
    try:
        r = make_object(source, *pair_case(k, source, kinds), pieces, faces)
        inputs = [as_input(f, r.fracture_faces[i], mode, points, noise, k, i) for i, f in enumerate(r.fragments)]
        size = corpus.object_size(r)  # of the meshes the inputs are drawn off
        t0 = time.perf_counter()
        found = assembly_case(replace(r, fragments=inputs), Params().with_(**(changes or {})), backend, 1, size)
    except Exception as err:  # noqa: BLE001 - one object's fault is reported in its row
        return {**row, "part_accuracy": 0.0, "error": f"{type(err).__name__}: {err}",
                "seconds": time.perf_counter() - t0}
    return {**row, **found, "seconds": time.perf_counter() - t0}


def is_right(row: dict) -> bool:
    return row["accepted"] and row["rotation_error_deg"] < 2 and row["rms"] < 0.01


def summarise(rows: list[dict]) -> dict:
    """{mode: {"right", "wrong_accepted", "pairs", "by_kind": {shape or family: [right, wrong, pairs]}}}."""
    summary = {}
    for row in rows:
        s = summary.setdefault(row["mode"], {"right": 0, "wrong_accepted": 0, "pairs": 0, "by_kind": {}})
        kind = s["by_kind"].setdefault(row["case"].rsplit(" ", 2)[0], [0, 0, 0])
        right, wrong = is_right(row), row["accepted"] and not is_right(row)
        s["right"] += right
        s["wrong_accepted"] += wrong
        s["pairs"] += 1
        kind[0], kind[1], kind[2] = kind[0] + right, kind[1] + wrong, kind[2] + 1
    return summary


def summarise_objects(rows: list[dict]) -> dict:
    """{mode: {"objects", "part_accuracy" (mean), "whole", "by_kind": {family: [mean part accuracy, objects]}}}."""
    summary = {}
    for mode in dict.fromkeys(row["mode"] for row in rows):
        mine = [row for row in rows if row["mode"] == mode]
        kinds = {}
        for row in mine:
            kinds.setdefault(row["case"].rsplit(" ", 2)[0], []).append(row["part_accuracy"])
        summary[mode] = {"objects": len(mine), "part_accuracy": float(np.mean([r["part_accuracy"] for r in mine])),
                         "whole": sum(r["part_accuracy"] >= 1.0 for r in mine),
                         "by_kind": {kind: [float(np.mean(v)), len(v)] for kind, v in kinds.items()}}
    return summary


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=10)
    ap.add_argument("--first", type=int, default=0, help="index of the first pair")
    ap.add_argument("--modes", default="normals,none", help=f"comma list of {', '.join(MODES)}")
    ap.add_argument("--points", type=int, default=2500)
    ap.add_argument("--noise", type=float, default=0.0005)
    ap.add_argument("--faces", type=int, default=4000,
                    help="faces of the synth and corpus objects the clouds are drawn off (a cloud denser than "
                         "its mesh repeats each facet's normal)")
    ap.add_argument("--source", choices=["synth", "corpus", "thin", "realdata"], default="synth")
    ap.add_argument("--kinds", default="", help="comma list of the source's shapes or families to cycle through "
                    "(corpus: any of its twelve families, e.g. rough-noisy; default its clean ones)")
    ap.add_argument("--backend", default="numpy")
    ap.add_argument("--workers", type=int, default=1, help="pairs matched at once, a process each")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                    help="a Params field for every pair (repeatable), e.g. min_skin=None")
    ap.add_argument("--pieces", type=int, default=2,
                    help="over 2: case k is an object of that many pieces (synth or corpus), its inputs assembled "
                         "(`assemble`, one process) and scored by part accuracy")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    try:
        changes = parse_assignments(args.set)
    except ValueError as err:
        ap.error(f"--set {err}")
    unknown = [m for m in args.modes.split(",") if m not in MODES]
    if unknown:
        ap.error(f"--modes: unknown {', '.join(unknown)}; choose from {', '.join(MODES)}")
    try:
        source_kinds(args.source, args.kinds)
    except ValueError as err:
        ap.error(f"--kinds: {err}")

    objects = args.pieces > 2
    if objects and args.source not in ("synth", "corpus"):
        ap.error("--pieces over 2: --source synth or corpus")
    jobs = [(k, mode, args.points, args.noise, args.source, args.backend, changes, args.kinds, args.faces)
            + ((args.pieces,) if objects else ()) for mode in args.modes.split(",")
            for k in range(args.first, args.first + args.pairs)]
    run, rows = run_object if objects else run_pair, []

    def report(row):
        rows.append(row)
        if objects:
            said = row.get("error") or (f"{row['used_right']} of {row['used']} used matches right, "
                                        f"touching recall {row['touching_recall']:.2f}, {row['groups']} groups")
            print(f"  {row['mode']:7s} {row['case']} ({row['pieces']} pieces): part accuracy "
                  f"{row['part_accuracy']:.2f} ({said}) {row['seconds']:.1f} s", file=sys.stderr, flush=True)
            return
        tag = "right" if is_right(row) else ("WRONG ACCEPTED" if row["accepted"] else "rejected")
        print(f"  {row['mode']:7s} {row['case']}: rot {row['rotation_error_deg']:7.2f} deg, rms {row['rms']:.4f}, "
              f"{tag} ({row['reason']}) {row['seconds']:.1f} s", file=sys.stderr, flush=True)

    if args.workers > 1:
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(args.workers) as pool:
            for row in pool.map(run, *zip(*jobs)):
                report(row)
    else:
        for job in jobs:
            report(run(*job))
    summary = summarise_objects(rows) if objects else summarise(rows)
    print(f"\n{args.source} {'objects' if objects else 'pairs'} {args.first}-{args.first + args.pairs - 1}"
          f"{f' of {args.pieces} pieces' if objects else ''}, {args.points} points, noise {args.noise}, "
          f"backend {args.backend}")
    for mode, s in summary.items():
        if objects:
            kinds = ", ".join(f"{kind} {acc:.2f} ({n})" for kind, (acc, n) in s["by_kind"].items())
            print(f"  {mode:8s} mean part accuracy {s['part_accuracy']:.3f} of {s['objects']} objects, "
                  f"{s['whole']} whole: {kinds}")
            continue
        kinds = ", ".join(f"{kind} {r}/{n}" + (f" ({w} wrong)" if w else "") for kind, (r, w, n) in s["by_kind"].items())
        print(f"  {mode:8s} {s['right']}/{s['pairs']} right, {s['wrong_accepted']} accepted at a wrong pose: {kinds}")
    if args.json:
        from relicgpu.io.files import atomic_write_json
        atomic_write_json(args.json, {"summary": summary, "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
