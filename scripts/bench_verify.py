#!/usr/bin/env python
"""The fits `match_pair` verifies, right and wrong, with every verification cue (issue 16 item 3).

    python scripts/bench_verify.py collect --out /tmp/fits.pkl                  # corpus pairs, 3 seeds
    python scripts/bench_verify.py collect --out /tmp/open.pkl --no-pairs --open 12   # bench_clouds' open meshes
    python scripts/bench_verify.py collect --out /tmp/multi.pkl --no-pairs --multi 6 --seeds 0,1
    python scripts/bench_verify.py report /tmp/fits.pkl /tmp/open.pkl /tmp/multi.pkl --train synth,rough,smooth
    python scripts/bench_verify.py forest                                       # assembly with a wrong match

`collect` runs `match_pair` with the verification told to refuse every fit, so that all the fits
it would look at (up to `Params.verify_at_most` a pair, best-touching first) are verified and
recorded: the two fracture samples, the transform, the verdict of the verification as it was
before the facing and sunk-surface checks for meshes (`Params.min_facing`,
`max_surface_penetration`), and the truth. A fit is right when its rotation error is under 2
degrees and b's vertices lie within 1% RMS of their true place (lengths relative to the object
size), wrong when over 5 degrees or 2%; fits in between are left out of the counts. Pairs of a
multi-piece object that do not touch have only wrong fits.

Cases (family = corpus family or "synth", the project's own generator; seeds --seeds):
two-piece objects of --faces faces a piece; with --open k the first k of bench_clouds' open
meshes (clean corpus pieces with three holes cut in the skin); with --multi k that many piece
pairs of each family's 5-piece object (touching ones first, up to half; --multi-faces); with
--realdata k that many piece pairs of each Blender set of ../shared/realdata (the rest at random).

`report` computes `verify.fit_cues` for every recorded fit, prints their quantiles over right and
wrong fits of the fitting families (--train, family prefixes), and counts, with the fitting
families and the held-out ones apart, the right fits kept and the wrong fits still accepted with
the checks of `Params`, and per pair which fit would be accepted first (as match_pair does).

`forest` takes each object's true matches (scores drawn in 0.2-0.6), makes one touching pair's
match wrong (b pulled --pull of the scale off a: no interpenetration, only the loops of the
other matches tell), scores it 0.9, and reports `assembly.grow_forest`'s part accuracy without
recovery (RECOVERY_ROUNDS = 0) and with it.
"""
from __future__ import annotations

import argparse
import pickle
import sys
import time
from dataclasses import replace

import numpy as np

sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parent))


def _label(rot: float, rms: float) -> str:
    if rot < 2.0 and rms < 0.01:
        return "right"
    return "wrong" if rot > 5.0 or rms > 0.02 else "near"


def _cases(args):
    """(family, seed, kind, a, b, truth, size) for every case asked for."""
    from relicgpu import synth
    from relicgpu.synth import corpus

    from bench_clouds import CORPUS, make_pair

    families = args.families.split(",")
    seeds = [int(s) for s in args.seeds.split(",")]
    for name in (corpus.REALDATA_SETS if args.realdata else ()):
        try:
            r = corpus.realdata(name, 0)
        except FileNotFoundError:
            continue
        n = len(r.fragments)
        apart = [(i, j) for i in range(n) for j in range(i + 1, n) if (i, j) not in r.touching]
        chosen = r.touching[: (args.realdata + 1) // 2]
        chosen += [apart[k] for k in np.random.default_rng(0).choice(len(apart), args.realdata - len(chosen), False)]
        for i, j in chosen:
            truth = np.linalg.inv(r.poses[i]) @ r.poses[j]
            kind = "multi-touching" if (i, j) in r.touching else "multi-apart"
            yield name, 0, kind, r.fragments[i], r.fragments[j], truth, corpus.object_size(r)
    for k in range(args.remeshed):
        shape, seed = ("vase", "torso", "slab")[k % 3], k // 3
        r, a, b = remeshed_pair(shape, seed)
        yield f"synth-remeshed-{shape}", seed, "pair", a, b, np.linalg.inv(r.poses[0]) @ r.poses[1], corpus.object_size(r)
    for k in range(args.open):
        a, b, truth = make_pair(k, "open", 0, 0.0, "corpus")
        whole = np.vstack([a.vertices, b.vertices @ truth[:3, :3].T + truth[:3, 3]])
        yield CORPUS[k % 4].replace("-clean", "-open"), k // 4, "open", a, b, truth, float(np.ptp(whole, 0).max())
    for fam in families:
        for seed in seeds:
            if args.pairs:
                r = (synth.generate(synth.SHAPES[seed % 3], 2, seed, args.faces, noise=0.0005, progress=False)
                     if fam == "synth" else corpus.generate(fam, 2, seed, args.faces))
                truth = np.linalg.inv(r.poses[0]) @ r.poses[1]
                yield fam, seed, "pair", r.fragments[0], r.fragments[1], truth, corpus.object_size(r)
            if args.multi:
                r = (synth.generate(synth.SHAPES[seed % 3], 5, seed, args.multi_faces, noise=0.0005, progress=False)
                     if fam == "synth" else corpus.generate(fam, 5, seed, args.multi_faces))
                pairs = [(i, j) for i in range(5) for j in range(i + 1, 5)]
                touching = [p for p in pairs if p in r.touching]
                apart = [p for p in pairs if p not in r.touching]
                chosen = (touching[: (args.multi + 1) // 2] + apart)[: args.multi]
                for i, j in chosen:
                    truth = np.linalg.inv(r.poses[i]) @ r.poses[j]
                    kind = "multi-touching" if (i, j) in r.touching else "multi-apart"
                    yield fam, seed, kind, r.fragments[i], r.fragments[j], truth, corpus.object_size(r)


def remeshed_pair(shape: str, seed: int, n_points: int = 40000, noise: float = 0.001):
    """A synth two-piece object and its pieces sampled (n_points uniform on the surface, each
    moved by up to noise x the piece's diagonal in a random direction) and meshed again by
    `triangulate.mesh_for_matching`, as tests/test_pointcloud.py's remeshed pairs: a scan reconstructed
    by the project's own mesher as load_fragment meshes it (returns the SynthResult and the two
    remeshed Fragments)."""
    import trimesh

    from relicgpu.cloud import triangulate as pc
    from relicgpu import synth
    from relicgpu.io.fragment import Fragment

    result = synth.generate(shape, pieces=2, seed=seed, progress=False)
    out = []
    for i, frag in enumerate(result.fragments):
        mesh = frag.to_trimesh()
        p, _ = trimesh.sample.sample_surface(mesh, n_points, seed=10 + i)
        rng = np.random.default_rng(11 + i)
        d = rng.normal(size=p.shape)
        d /= np.linalg.norm(d, axis=1)[:, None]
        p = p + d * rng.uniform(0.0, noise * float(np.linalg.norm(mesh.extents)), (len(p), 1))
        res = pc.mesh_for_matching(p)  # as load_fragment meshes a cloud
        out.append(Fragment(frag.name, res.vertices, res.faces, None, res.notes))
    return result, out[0], out[1]


def collect(args) -> int:
    import relicgpu.pair.meshfit as mf
    import relicgpu.pair.pipeline as pl
    from relicgpu.backends import resolve
    from relicgpu.heap.evaluate import relative_pose_error
    from relicgpu.pair.icp import rotation_angle_deg
    from relicgpu.params import Params, with_segmentations

    # one reading's fits: the spy refuses every fit, so a second reading would run on every pair
    params = with_segmentations(Params(), args.segmentation, "none")
    be = resolve(args.backend)
    original = mf.verify  # the mesh fits' verification (meshfit.verify_mesh)
    calls: list = []

    def spy(a, b, transform, *rest, **kw):
        if kw.get("max_surface_penetration", 1.0) < 1.0:  # a mesh pair: the verification before these checks
            kw = dict(kw, min_facing=0.0, max_surface_penetration=1.0)
        v = original(a, b, transform, *rest, **kw)
        calls.append({"a": a, "b": b, "transform": np.array(transform), "args": tuple(x for x in rest[1:] if not callable(x)), "kw": {
            k: x for k, x in kw.items() if k != "index_of" and not callable(x)}, "verdict": v})
        return replace(v, accepted=False)

    mf.verify = spy
    records = []
    for fam, seed, kind, a, b, truth, size in _cases(args):
        t0 = time.perf_counter()
        calls.clear()
        scale = pl.pair_scale(a, b, params)
        pl.match_pair(a, b, params, be)
        fits = []
        for c in calls:
            rot = rotation_angle_deg(c["transform"][:3, :3] @ truth[:3, :3].T)
            rms = relative_pose_error(b.vertices, c["transform"], np.eye(4), truth) / size
            fits.append({"transform": c["transform"], "rotation_error_deg": rot, "rms": rms,
                         "label": "wrong" if kind == "multi-apart" else _label(rot, rms),
                         "accepted": bool(c["verdict"].accepted), "reason": c["verdict"].reason,
                         "a": c["a"], "b": c["b"], "args": c["args"], "kw": c["kw"]})
        records.append({"family": fam, "seed": seed, "kind": kind, "scale": scale, "size": size,
                        "segmentation": params.segmentation, "fits": fits})
        first = next((f for f in fits if f["accepted"]), None)
        print(f"{fam} seed {seed} {kind}: {len(fits)} fits, labels "
              f"{[f['label'][0] for f in fits]}, today accepts "
              f"{'nothing' if first is None else first['label'] + ' (%.1f deg)' % first['rotation_error_deg']} "
              f"({time.perf_counter() - t0:.1f} s)", file=sys.stderr, flush=True)
        with open(args.out, "wb") as fh:  # after every case: a stopped run keeps what it finished
            pickle.dump(records, fh, protocol=5)
    mf.verify = original
    return 0


def fit_table(records: list, backend) -> list[dict]:
    """One row per recorded fit: its case, label, today's verdict and `verify.fit_cues`."""
    from relicgpu.pair.verify import fit_cues

    rows = []
    for pair, rec in enumerate(records):
        for order, f in enumerate(rec["fits"]):
            contact, max_rmse, min_overlap, depth = f["args"][:4]
            cues = fit_cues(f["a"], f["b"], f["transform"], backend, contact, depth)
            rows.append({"pair": pair, "order": order, "family": rec["family"], "seed": rec["seed"],
                         "kind": rec["kind"], "segmentation": rec["segmentation"], "label": f["label"],
                         "rot": f["rotation_error_deg"], "today": f["accepted"], "reason": f["reason"],
                         **cues})
    return rows


def _family(row: dict) -> str:
    return row["family"].split("-")[0]


def passes(row: dict, rule: dict) -> bool:
    """Whether a fit that today's verification accepts also passes the extra checks of `rule`."""
    if not row["today"]:
        return False
    return all(row[k] >= t if kind == "min" else row[k] <= t for k, (kind, t) in rule.items())


def count(rows: list, rule: dict, families) -> dict:
    """Right fits kept, wrong fits accepted and pairs' first accepted fit (right, wrong, none)."""
    sel = [r for r in rows if _family(r) in families or r["family"] in families]
    out = {"right_fits": sum(r["label"] == "right" for r in sel),
           "right_kept": sum(r["label"] == "right" and passes(r, rule) for r in sel),
           "right_today": sum(r["label"] == "right" and r["today"] for r in sel),
           "wrong_today": sum(r["label"] == "wrong" and r["today"] for r in sel),
           "wrong_kept": sum(r["label"] == "wrong" and passes(r, rule) for r in sel)}
    pairs: dict = {}
    for r in sel:
        pairs.setdefault((r["segmentation"], r["pair"]), []).append(r)
    for name, test in (("today", lambda r: r["today"]), ("rule", lambda r: passes(r, rule))):
        firsts = [next((r["label"] for r in sorted(p, key=lambda r: r["order"]) if test(r)), "none")
                  for p in pairs.values()]
        out[f"pairs_right_{name}"] = firsts.count("right")
        out[f"pairs_wrong_{name}"] = firsts.count("wrong")
    out["pairs"] = len(pairs)
    return out


def chosen_rule() -> dict:
    """The checks `match_pair` adds for meshes (Params.min_facing, max_surface_penetration), as
    cue -> ("min" or "max", threshold) over `fit_cues`."""
    from relicgpu.params import Params

    p = Params()
    return {"facing": ("min", p.min_facing), "pen_all": ("max", p.max_surface_penetration)}


def report(args) -> int:
    from relicgpu.backends import resolve

    be = resolve("numpy")
    records = []
    for path in args.records:
        with open(path, "rb") as fh:
            records += [dict(r, source=path) for r in pickle.load(fh)]
    rows = fit_table(records, be)
    cues = [k for k in rows[0] if k not in ("pair", "order", "family", "seed", "kind", "segmentation", "label",
                                            "rot", "today", "reason")]
    if args.dump:
        for r in rows:
            print(" ".join(f"{k}={r[k]:.3f}" if isinstance(r[k], float) else f"{k}={r[k]}" for k in r))
    train = args.train.split(",")
    fams = sorted({_family(r) for r in rows} | {r["family"] for r in rows if r["family"] == "synth"})
    test = [f for f in fams if f not in train]
    print("cue quantiles (5%, 50%, 95%) over fits today's verification accepts, training families:")
    for k in cues:
        line = f"  {k:18s}"
        for lab in ("right", "wrong"):
            v = [r[k] for r in rows if r["label"] == lab and r["today"] and (_family(r) in train or r["family"] in train)]
            line += f" {lab} " + (" ".join(f"{x:.3f}" for x in np.quantile(v, [0.05, 0.5, 0.95])) if v else "-")
        print(line)
    rule = chosen_rule()
    print(f"extra checks {rule} on the fits the recorded verification accepted")
    for name, group in (("train " + ",".join(train), train), ("held out " + ",".join(test), test)):
        c = count(rows, rule, group)
        print(f"  {name}: right fits {c['right_fits']}, accepted today {c['right_today']}, with the rule "
              f"{c['right_kept']}; wrong fits accepted today {c['wrong_today']}, with the rule {c['wrong_kept']}; "
              f"pairs {c['pairs']}: first accepted right/wrong today {c['pairs_right_today']}/"
              f"{c['pairs_wrong_today']}, with the rule {c['pairs_right_rule']}/{c['pairs_wrong_rule']}")
    return 0


def truth_samples(result, n_points: int = 1500) -> list:
    """Surface samples from the generator's fracture labels (the forest apart from segmentation)."""
    from relicgpu.backends import numpy as ref
    from relicgpu.cloud.points import even_subsample
    from relicgpu.pair.verify import SurfaceSample, vertex_normals

    out = []
    for frag, frac in zip(result.fragments, result.fracture_faces):
        normals, areas = ref.face_normals(frag.vertices, frag.faces)
        vn = vertex_normals(frag.vertices, np.asarray(frag.faces, np.int64), normals, areas)
        fv = np.unique(frag.faces[frac].ravel())
        fv = fv[even_subsample(frag.vertices[fv], n_points)]
        sv = even_subsample(frag.vertices, 2 * n_points)
        out.append(SurfaceSample(frag.vertices[fv], np.zeros(len(fv), np.int64), vn[fv], frag.vertices[sv], vn[sv]))
    return out


def forest(args) -> int:
    """Assembly with one wrong match among the right ones: part accuracy without and with recovery."""
    from relicgpu import synth
    from relicgpu.synth import corpus
    from relicgpu.heap import forest as assembly
    from relicgpu.heap.forest import Edge, grow_forest
    from relicgpu.heap.assembly import _finish_groups
    from relicgpu.heap.outputs import closed_solid
    from relicgpu.backends import numpy as ref
    from relicgpu.heap.evaluate import score
    from relicgpu.pair.icp import invert
    from relicgpu.params import Params

    rounds = assembly.RECOVERY_ROUNDS
    totals = {"cases": 0, "without": 0.0, "with": 0.0, "recovered": 0, "hurt": 0}
    for fam in args.families.split(","):
        for seed in (int(x) for x in args.seeds.split(",")):
            r = (synth.generate(synth.SHAPES[seed % 3], args.pieces, seed, args.faces, noise=0.0005, progress=False)
                 if fam == "synth" else corpus.generate(fam, args.pieces, seed, args.faces))
            n, size = len(r.fragments), corpus.object_size(r)
            samples = truth_samples(r)
            solids = [closed_solid(f) for f in r.fragments]
            scale = float(np.median([f.size for f in r.fragments]))
            rng = np.random.default_rng(seed)
            right = [Edge(i, j, invert(r.poses[i]) @ r.poses[j], float(rng.uniform(0.2, 0.6))) for i, j in r.touching]
            for k, (i, j) in enumerate(r.touching[: args.wrong_per_object]):
                truth = invert(r.poses[i]) @ r.poses[j]
                away = (samples[j].surface.mean(0) @ truth[:3, :3].T + truth[:3, 3]) - samples[i].surface.mean(0)
                pull = np.eye(4)
                pull[:3, 3] = args.pull * scale * away / max(np.linalg.norm(away), 1e-12)
                edges = [e for e in right if (e.a, e.b) != (i, j)] + [Edge(i, j, pull @ truth, 0.9)]
                acc = {}
                for label, rr in (("without", 0), ("with", rounds)):
                    assembly.RECOVERY_ROUNDS = rr
                    pose, group, notes = grow_forest(n, edges, samples, Params(), scale, ref, solids)
                    poses, groups = _finish_groups(pose, group)
                    acc[label] = score([f.vertices for f in r.fragments], poses, groups, r.poses, r.touching, [],
                                       unit=size).part_accuracy
                assembly.RECOVERY_ROUNDS = rounds
                totals["cases"] += 1
                totals["without"] += acc["without"]
                totals["with"] += acc["with"]
                totals["recovered"] += acc["with"] == 1.0 and acc["without"] < 1.0
                totals["hurt"] += acc["with"] < acc["without"]
                print(f"{fam} seed {seed} wrong ({i},{j}): part accuracy {acc['without']:.2f} -> {acc['with']:.2f} "
                      f"({notes[(i, j)][:60]})", file=sys.stderr, flush=True)
    c = max(totals["cases"], 1)
    print(f"{totals['cases']} objects with one wrong match (pulled {args.pull} of the scale off a touching pair, "
          f"scored above every right one): mean part accuracy {totals['without'] / c:.3f} without recovery, "
          f"{totals['with'] / c:.3f} with; {totals['recovered']} recovered fully, {totals['hurt']} made worse")
    return 0


def main(argv=None) -> int:
    from relicgpu.params import SEGMENTATIONS

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="command", required=True)
    c = sub.add_parser("collect", help="run match_pair and record every verified fit")
    c.add_argument("--out", required=True, help="pickle of the records")
    c.add_argument("--families", default="synth,rough-clean,rough-noisy,rough-coarse,smooth-clean,smooth-noisy,"
                                          "smooth-coarse,voronoi-clean,voronoi-noisy,voronoi-coarse,vessel-clean,"
                                          "vessel-noisy,vessel-coarse")
    c.add_argument("--seeds", default="0,1")
    c.add_argument("--faces", type=int, default=2000)
    c.add_argument("--multi-faces", type=int, default=1500)
    c.add_argument("--pairs", action=argparse.BooleanOptionalAction, default=True, help="two-piece objects")
    c.add_argument("--remeshed", type=int, default=0, help="the first k synth pieces sampled and meshed again "
                                                             "(vase, torso, slab; seeds 0, 1, ...)")
    c.add_argument("--open", type=int, default=0, help="the first k of bench_clouds' open-mesh pairs")
    c.add_argument("--multi", type=int, default=0, help="piece pairs of each 5-piece object (touching first)")
    c.add_argument("--segmentation", choices=SEGMENTATIONS)
    c.add_argument("--realdata", type=int, default=0, help="piece pairs of each ../shared/realdata Blender set "
                                                           "(touching ones first, up to half)")
    c.add_argument("--backend", default="numpy")
    r = sub.add_parser("report", help="cues and threshold counts of recorded fits")
    r.add_argument("records", nargs="+")
    r.add_argument("--train", default="synth,rough,smooth", help="family prefixes the thresholds were fitted on")
    r.add_argument("--dump", action="store_true", help="one line per fit with every cue")
    f = sub.add_parser("forest", help="one wrong match among right ones: part accuracy without/with recovery")
    f.add_argument("--families", default="synth,rough-clean,smooth-clean,voronoi-clean,vessel-clean")
    f.add_argument("--seeds", default="0,1")
    f.add_argument("--pieces", type=int, default=6)
    f.add_argument("--faces", type=int, default=1200)
    f.add_argument("--pull", type=float, default=0.1, help="the wrong match: b pulled this share of the scale off a")
    f.add_argument("--wrong-per-object", type=int, default=3, help="touching pairs made wrong in turn")
    args = ap.parse_args(argv)
    if args.command == "forest":
        return forest(args)
    if args.command == "collect":
        return collect(args)
    return report(args)


if __name__ == "__main__":
    sys.exit(main())
