"""The heap's commands: `relicgpu assemble DIR -o OUT` (relicgpu.heap.assembly), `relicgpu group`
and `relicgpu train-classifier` (relicgpu.heap.grouping, relicgpu.heap.classifier); and
`assemble_grouped`, which sorts the heap into objects and assembles each."""
from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

from .assembly import ALL_PAIRS_UP_TO, TOP_K, assemble
from ..backends import BackendError
from ..errors import CliError
from .classifier import Classifier, read_labels_csv, train_classifier
from .grouping import Grouping, LINK_CUT, _load, group_fragments
from ..io.files import atomic_write_json, grouped_lines
from ..io.load import load_fragment, read_batch


# --- assemble each group on its own -------------------------------------------------

def assemble_grouped(fragments_or_dir, out_dir=None, n_groups: int | None = None, classifier=None, **assemble_kw):
    """Group the heap, then assemble each group on its own.

    Returns (Grouping, [Assembly per group]). With out_dir, writes out_dir/groups.json and
    out_dir/assembly.json in the assembly format, each fragment carrying "object" (its
    classification group) and "group" (its assembled piece, numbered over all objects),
    plus each object's own outputs under out_dir/object_<k>/.
    """
    batch = _load(fragments_or_dir)
    fragments = batch.fragments
    if classifier is not None:
        names, _ = (classifier if isinstance(classifier, Classifier) else Classifier.load(classifier)).predict(fragments)
        classes = sorted(set(names), key=lambda c: (-names.count(c), c))
        grouping = Grouping([fr.name for fr in fragments], np.array([classes.index(c) for c in names]),
                            float("nan"), method="classifier", files=[fr.file for fr in fragments])
    else:
        grouping = group_fragments(fragments, n_groups)
    grouping = dataclasses.replace(grouping, skipped=list(batch.skipped) + grouping.skipped, notes=list(batch.notes))
    by_name = {fr.name: fr for fr in fragments}
    results, doc_fragments, doc_matches, timings = [], [], [], {}
    offset = 0
    for k, names in enumerate(grouping.groups):
        sub_out = None if out_dir is None else Path(out_dir) / f"object_{k}"
        members = [by_name[n] for n in names]
        if len(members) == 1:
            results.append(None)
            doc_fragments.append({"name": names[0], "file": members[0].file, "pose": np.eye(4).tolist(),
                                  "group": offset, "used_matches": 0, "on_loop": False, "object": k})
            offset += 1
            continue
        res = assemble(members, out_dir=sub_out, **assemble_kw)
        results.append(res)
        d = res.to_dict()
        for e in d["fragments"]:
            doc_fragments.append({**e, "group": e["group"] + offset, "object": k})
        doc_matches.extend(d["matches"])
        offset += res.n_groups
        for key, val in res.timings.items():
            timings[key] = timings.get(key, 0.0) + float(val)
    if out_dir is not None:
        out = Path(out_dir)
        atomic_write_json(out / "groups.json", grouping.to_dict())
        first = next((r for r in results if r is not None), None)
        atomic_write_json(out / "assembly.json", {
            "version": 1, "fragments": doc_fragments, "matches": doc_matches,
            "backend": first.backend if first else None, "engine": first.engine if first else None,
            "timings": {**{k: round(v, 4) for k, v in timings.items()},
                        **{f"group_{k}": round(float(v), 4) for k, v in grouping.timings.items()}},
            "objects": grouping.groups, "skipped": grouping.skipped, "notes": grouping.notes})
    return grouping, results



# --- command line ---------------------------------------------------------------------------

def _assemble_arguments(parser) -> None:
    parser.add_argument("directory", help="directory of fragment files (STL, PLY, OBJ, OFF, GLB, point clouds)")
    parser.add_argument("-o", "--out", required=True, help="output directory (created); the cache goes in OUT/cache")
    parser.add_argument("--backend", default="auto", help="numpy, warp-cpu, warp-cuda[:N], opencl[:PLATFORM] or auto")
    parser.add_argument("--engine", default="local", choices=["local", "ray"], help="where pairs are matched")
    parser.add_argument("--address", default=None, help="Ray cluster to join (e.g. ray://head:10001 or auto)")
    parser.add_argument("--workers", type=int, default=None,
                        help="parallel workers (forked processes or threads here, or local Ray CPUs; default: every core)")
    parser.add_argument("--gpus-per-task", type=float, default=None,
                        help="GPUs per Ray task where there are GPUs (default 1; e.g. 0.125 lets 8 tasks share one)")
    parser.add_argument("--cache-dir", default=None, help="cache directory (default OUT/cache)")
    parser.add_argument("--top-k", type=int, default=None,
                        help=f"partners per fragment matched in full (default: every pair in heaps of at most "
                             f"{ALL_PAIRS_UP_TO} fragments, else {TOP_K})")
    parser.add_argument("--quiet", action="store_true", help="no progress bar or summary on stderr")
    parser.add_argument("--group", action="store_true",
                        help="sort the heap into objects first (relicgpu.heap.grouping) and assemble each on its own")
    parser.add_argument("--classifier", default=None, metavar="WEIGHTS",
                        help="with --group: classify with weights from `relicgpu train-classifier`")


def _assemble_main(args) -> int:
    if args.workers is not None and args.workers < 1:
        raise CliError(f"--workers must be at least 1, got {args.workers}")
    if args.top_k is not None and args.top_k < 1:
        raise CliError(f"--top-k must be at least 1, got {args.top_k}")
    if args.address and args.engine != "ray":
        raise CliError("--address needs --engine ray")
    log = (lambda *a: None) if args.quiet else (lambda *a: print(*a, file=sys.stderr))
    src = Path(args.directory)
    if not src.is_dir():
        raise CliError(f"{src}: not a directory")
    if Path(args.out).resolve() == src.resolve():
        raise CliError(f"{args.out}: the output directory must not be the input directory")
    batch = read_batch(src, progress=not args.quiet)
    for line in batch.messages():  # every file or crumb left out, even with --quiet
        print(line, file=sys.stderr)
    batch.require(2)
    if args.group:
        grouping, results = assemble_grouped(batch, args.out, classifier=args.classifier, backend=args.backend,
                                             engine=args.engine, workers=args.workers, cache_dir=args.cache_dir,
                                             progress=not args.quiet, address=args.address, top_k=args.top_k,
                                             gpus_per_task=args.gpus_per_task)
        log(f"{len(grouping.groups)} object(s) of sizes {[len(g) for g in grouping.groups]}; "
            f"wrote {Path(args.out) / 'assembly.json'}, groups.json, object_<k>/")
        for k, res in enumerate(results):
            for line in support_lines(res) if res is not None else []:
                log(f"object {k}: {line}")
        return 0
    try:
        result = assemble(batch, backend=args.backend, engine=args.engine, workers=args.workers,
                          cache_dir=args.cache_dir, progress=not args.quiet, out_dir=args.out,
                          address=args.address, top_k=args.top_k, gpus_per_task=args.gpus_per_task)
    except BackendError as exc:
        raise CliError(str(exc)) from None
    except (RuntimeError, ValueError) as exc:
        if "ray" in str(exc).lower() or "gpus_per_task" in str(exc):
            raise CliError(str(exc)) from None
        raise
    s = result.stats
    log(f"{s['fragments']} fragments, {s['contours']} contours; backend {result.backend}, engine {result.engine}")
    log(f"screened {s['pairs']} pairs, matched {s['candidates']} ({s['pairs_from_cache']} from cache), "
        f"{s['accepted']} verified, {s['used']} used")
    if s.get("grow_tried"):
        log(f"{s['grow_joined']} of {s['grow_tried']} fragments or groups left apart joined a placed group "
            f"when matched against its merged surface")
    if s.get("apart"):
        log(f"{s['apart']} verified match(es) not used: they join groups that look like pieces of different "
            f"objects (see assembly.json)")
    sizes = sorted((len(m) for m in result.group_members().values() if len(m) > 1), reverse=True)
    log(f"{s['placed']} fragments placed in {len(sizes)} group(s) of sizes {sizes}; "
        f"{s['fragments'] - s['placed']} unplaced")
    for line in support_lines(result):
        log(line)
    for e in s["errors"]:
        log(f"warning: pair failed: {e}")
    for line in grouped_lines("note", s.get("smoothed", []) + s.get("merge_notes", [])):
        log(line)
    log("  " + "  ".join(f"{k} {v:.2f} s" for k, v in result.timings.items()))
    merged = not any("no merged.stl written" in n for n in s.get("merge_notes", []))
    log(f"wrote {Path(args.out) / 'assembly.json'}, assembly.glb" + (", merged.stl" if merged else ""))
    return 0


def support_lines(result, shown: int = 12) -> list[str]:
    """How the placed fragments are held: how many lie on a closed loop of used matches, and the
    names of those that rest on one match alone (the ones to check first)."""
    used, on_loop = result.support()
    placed = [i for i, p in enumerate(result.poses) if p is not None]
    if not placed:
        return []
    lone = [result.names[i] for i in placed if used[i] <= 1]
    lines = [f"{sum(on_loop[i] for i in placed)} of {len(placed)} placed fragments lie on a closed loop of matches"]
    if lone:
        more = f" and {len(lone) - shown} more" if len(lone) > shown else ""
        lines.append(f"{len(lone)} rest on one match alone (check these first; on_loop and used_matches in "
                     f"assembly.json): {', '.join(lone[:shown])}{more}")
    return lines


def _group_arguments(parser, name) -> None:
    if name == "train-classifier":
        parser.add_argument("labels", metavar="LABELS.csv", help="rows `file,label` (paths relative to the csv)")
        parser.add_argument("-o", "--out", default=None,
                            help="weights file to write (default: classifier.pt beside LABELS.csv)")
        parser.add_argument("--epochs", type=int, default=120, help="training epochs (default: 120)")
        parser.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
        parser.add_argument("--quiet", action="store_true", help="no progress bar or summary")
        return
    parser.add_argument("directory", metavar="DIR", help="directory of fragment meshes")
    parser.add_argument("-o", "--out", required=True, help="output directory (groups.json)")
    parser.add_argument("--groups", type=int, default=None, help="number of groups (default: found)")
    parser.add_argument("--distance", type=float, default=None,
                        help=f"cut the tree where the mean probability of one object between two clusters "
                             f"falls below 1 - DISTANCE (default: {LINK_CUT})")
    parser.add_argument("--classifier", default=None, metavar="WEIGHTS",
                        help="classify with weights from `relicgpu train-classifier` instead of clustering")
    parser.add_argument("--quiet", action="store_true", help="no progress bar or summary")


def _group_main(args, name) -> int:
    log = (lambda *a: None) if args.quiet else (lambda *a: print(*a, file=sys.stderr))
    if name == "train-classifier":
        if args.epochs < 1:
            raise CliError(f"--epochs must be at least 1, got {args.epochs}")
        files, labels = read_labels_csv(args.labels)
        out = Path(args.out) if args.out else Path(args.labels).parent / "classifier.pt"
        if out.resolve() in {f.resolve() for f in files} or out.resolve() == Path(args.labels).resolve():
            raise CliError(f"{out}: the weights file must not be an input")
        fragments = [load_fragment(f) for f in files]
        t0 = time.perf_counter()
        clf = train_classifier(fragments, labels, args.epochs, args.seed, progress=not args.quiet)
        clf.save(out)
        pred, _ = clf.predict(fragments)
        acc = float(np.mean([p == l for p, l in zip(pred, labels)]))
        log(f"{len(fragments)} fragments, {len(clf.classes)} classes; training accuracy {acc:.3f}, "
            f"final loss {clf.history[-1]:.3f} ({time.perf_counter() - t0:.1f} s); wrote {out}")
        return 0

    src = Path(args.directory)
    if not src.is_dir():
        raise CliError(f"{src}: not a directory")
    if Path(args.out).resolve() == src.resolve():
        raise CliError(f"{args.out}: the output directory must not be the input directory")
    if args.groups is not None and args.groups < 1:
        raise CliError(f"--groups must be at least 1, got {args.groups}")
    batch = _load(src)
    for line in batch.messages():  # every file or crumb left out, even with --quiet
        print(line, file=sys.stderr)
    batch.require(2)
    fragments = batch.fragments
    if args.classifier:
        clf = Classifier.load(args.classifier)
        pred, prob = clf.predict(fragments)
        classes = sorted(set(pred), key=lambda c: (-pred.count(c), c))
        doc = {"version": 1, "method": "classifier", "classes": classes,
               "groups": [[fr.name for fr, p in zip(fragments, pred) if p == c] for c in classes],
               "fragments": [{"name": fr.name, "file": fr.file, "group": classes.index(p), "label": p,
                              "probability": float(pr.max())} for fr, p, pr in zip(fragments, pred, prob)]}
    else:
        if args.distance is not None and not 0.0 < args.distance < 1.0:
            raise CliError(f"--distance must lie between 0 and 1, got {args.distance}")
        doc = group_fragments(fragments, args.groups, args.distance, progress=not args.quiet).to_dict()
    for line in grouped_lines("skipped", [s["reason"] for s in doc.get("skipped", [])]):  # clouds with no surface
        print(line, file=sys.stderr)
    doc.update(skipped=batch.skipped + doc.get("skipped", []), notes=batch.notes)
    atomic_write_json(Path(args.out) / "groups.json", doc)
    sizes = [len(x) for x in doc["groups"]]
    log(f"{sum(sizes)} fragments in {len(sizes)} group(s) of sizes {sizes}; wrote {Path(args.out) / 'groups.json'}")
    return 0


def cli_add_arguments(parser, name="assemble") -> None:
    """The arguments of `relicgpu assemble`, `relicgpu group` or `relicgpu train-classifier`."""
    if name == "assemble":
        _assemble_arguments(parser)
    else:
        _group_arguments(parser, name)


def cli_main(args, name="assemble") -> int:
    return _assemble_main(args) if name == "assemble" else _group_main(args, name)
