"""Global multi-fragment assembly (issue 5): `relicgpu.assemble` and `relicgpu assemble DIR -o OUT`.

    load -> prepare every fragment at one common scale          (engine jobs, cached)
         -> screen: LCS lengths of all contour pairs at once    (one batched backend call, cached)
         -> top-k partners per fragment -> match_pair           (engine jobs, cached per pair)
         -> spanning forest of verified matches, best first,
            refusing merges that interpenetrate or break a closed loop
         -> what stayed apart matched against the merged placed groups (`grow`; cached per group pair)
         -> joint refinement: the pose graph, then all fragments settled together on every neighbour they touch
         -> assembly.json, assembly.glb, merged.stl

Every fragment is prepared at the same scale (the median fragment size, or
`Params.unit`) so that contour sampling steps and feature units agree between
all fragments; pair results are then comparable and cacheable.

Cache (OUT/cache or cache_dir): a file per prepared fragment, one for the screen
and one per matched pair, named by a hash of the fragment contents, the
parameters, the scale, the backend and the source of the pipeline stages, so a
result is reused only where it would be computed again identically. Files are
written atomically as soon as each job finishes: a run killed at any moment and
started again recomputes only what was not finished.
"""
from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..backends import resolve
from .engines import Job, make_engine
from ..io.files import atomic_write_bytes
from ..io.fragment import Fragment, FragmentError, is_cloud
from ..io.load import Batch, read_batch
from .cache import Cache, fragment_hash
from .forest import APART_NOTE, Edge, grow_forest, refine_poses, rim_first
from .grouping import heap_probability
from .describe import describe
from .grow import grow_groups
from .outputs import closed_solid, write_outputs
from .screen import SCREEN_LCS_WEIGHT, _ppf_screen_job, _screen_blocks, normalised_support, screen, select_candidates
from .settle import settle
from .support import held_by
from ..params import Params
from ..pair.denoise import smoothing_notes
from ..pair.icp import invert
from ..pair.pipeline import match_pair
from ..pair.prepare import prepare, received, shipped
from ..pair.result import failed_doc

# Screening: each fragment keeps its TOP_K best partners by screening score; a pair
# is matched in full when it is among the top k of either fragment (see docs/design.md).
TOP_K = 8
# ... in heaps of more than ALL_PAIRS_UP_TO fragments; smaller heaps (one pot's sherds) have every
# pair matched. On Blender's 20-piece cylinder (flat Voronoi cuts) the screen kept 44 of the 70
# touching pairs at k = 8 and the assembly placed 0.85 of the pieces; every pair (190 against 108,
# 1.6x the assembly's time) placed 0.95 (docs/benchmarks.md).
ALL_PAIRS_UP_TO = 24


# --- the result --------------------------------------------------------------


@dataclass(frozen=True)
class MatchRecord:
    """A pair matched in full (b carried onto a): verified or not, used or not, and why."""
    a: int
    b: int
    transform: np.ndarray
    score: float
    rmse: float
    overlap: float
    penetration: float
    used: bool
    note: str  # why it is used or not: the forest's decision, or the verification's reason
    accepted: bool = True  # passed verification (relicgpu.pair.verify)

    def to_dict(self, names: list[str]) -> dict:
        """The assembly.json entry: ``accepted`` (verified), ``used``, and ``reason``."""
        def number(x):
            return float(x) if math.isfinite(float(x)) else None
        return {"a": names[self.a], "b": names[self.b], "transform": np.asarray(self.transform).tolist(),
                "score": number(self.score), "rmse": number(self.rmse), "overlap": number(self.overlap),
                "penetration": number(self.penetration), "accepted": bool(self.accepted),
                "used": bool(self.used), "reason": self.note}


@dataclass
class Assembly:
    names: list[str]
    poses: list  # 4x4 arrays (file coordinates -> the group's frame) or None when unplaced
    groups: list[int]  # group per fragment; 0 is the largest group, unplaced fragments have their own
    matches: list[MatchRecord]  # the verified matches
    timings: dict
    backend: str
    engine: str
    stats: dict = field(default_factory=dict)  # counts for reports (not written to assembly.json)
    screen_scores: np.ndarray | None = None  # (n,n) screening score of every fragment pair
    candidates: list = field(default_factory=list)  # (i, j) pairs that got the full match
    files: list = field(default_factory=list)  # the file name of each fragment (default: its name)
    skipped: list = field(default_factory=list)  # files and crumbs left out while loading, with why
    notes: list = field(default_factory=list)  # other loading decisions (files split into fragments)
    rejected: list = field(default_factory=list)  # MatchRecords of the candidates that failed verification

    @property
    def n_groups(self) -> int:
        return len(set(self.groups))

    def group_members(self) -> dict[int, list[int]]:
        out: dict[int, list[int]] = {}
        for i, g in enumerate(self.groups):
            out.setdefault(g, []).append(i)
        return out

    def support(self) -> tuple[list[int], list[bool]]:
        """The used matches at each fragment and whether it lies on a closed loop of them (`held_by`)."""
        return held_by(len(self.names), [(m.a, m.b) for m in self.matches if m.used])

    def to_dict(self) -> dict:
        used, on_loop = self.support()
        return {
            "version": 1,
            "fragments": [{"name": name, "file": file, "pose": None if pose is None else np.asarray(pose).tolist(),
                           "group": int(g), "used_matches": k, "on_loop": loop}
                          for name, file, pose, g, k, loop in zip(self.names, self.files or self.names, self.poses,
                                                                   self.groups, used, on_loop)],
            # every candidate pair matched in full: verified or not, used or not, and why
            "matches": [m.to_dict(self.names) for m in self.matches + self.rejected],
            "backend": self.backend,
            "engine": self.engine,
            "timings": {k: round(float(v), 4) for k, v in self.timings.items()},
            "skipped": list(self.skipped),
            "notes": list(self.notes),
        }

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2) + "\n"


# --- engine jobs (module level, so Ray workers import them by name) -------------

def _match_job(payload, *prepared):
    """Match a chunk of pairs; payload = (pairs, needs, params, backend, scale)."""
    pairs, needs, params, backend_name, scale = payload
    be = resolve(backend_name)
    by_index = dict(zip(needs, prepared))
    out = []
    for i, j in pairs:
        try:
            m = match_pair(by_index[i], by_index[j], params, be, scale=scale)
            doc = m.doc()
        except Exception as exc:  # one bad pair must not sink a run of thousands; reported, not cached
            doc = failed_doc(exc)
        out.append((i, j, doc))
    return out


# --- the whole job -----------------------------------------------------------------

def _load(fragments_or_dir) -> Batch:
    """The fragments of a directory, a list of files and Fragments, or a Batch (see io.read_batch):
    a file that cannot be read is skipped, not fatal; no fragment at all is."""
    batch = read_batch(fragments_or_dir)
    if not batch.fragments:
        why = f" ({batch.skipped[0]['reason']})" if batch.skipped else ""
        raise FragmentError(f"no fragments to assemble{why}")
    seen: dict[str, str] = {}
    for f in batch.fragments:
        if f.name in seen:
            raise FragmentError(f"{f.source or f.name}: two fragments are named {f.name!r} "
                                f"(also {seen[f.name]}); names must be unique")
        seen[f.name] = f.source or f.name
    return batch


def common_scale(fragments: list[Fragment], params: Params) -> float:
    """The one working scale of a group: Params.unit, else the median fragment size."""
    if params.unit:
        return float(params.unit)
    sizes = [f.size for f in fragments]
    scale = float(np.median(sizes))
    if not scale > 0:
        raise FragmentError("the fragments have no extent (all sizes are zero)")
    return scale


def _bar(total: int, show: bool, desc: str):
    from tqdm import tqdm
    return tqdm(total=total, desc=desc, unit="pair" if "match" in desc else "frag", file=sys.stderr,
                disable=not show, leave=False, dynamic_ncols=True)


def assemble(fragments_or_dir, params: Params | None = None, backend="auto", engine="local", workers=None,
             cache_dir=None, progress=True, out_dir=None, address: str | None = None,
             top_k: int | None = None, gpus_per_task: float | None = None, objects=None) -> "Assembly":
    """Match and assemble a directory (or list, or io.Batch) of fragments.

    Files that cannot be read are skipped and crumbs dropped (io.read_batch); the result's
    `skipped` and `notes` say which. Returns an Assembly; with out_dir, also writes assembly.json, assembly.glb and the
    merged STL(s) there, and caches finished work in out_dir/cache (or cache_dir).
    engine: "local" or "ray" (address: a Ray cluster to join, else a local one starts;
    gpus_per_task: GPUs a Ray task takes where there are GPUs, default 1).
    top_k: partners per fragment matched in full (None: every pair in heaps of at most
    ALL_PAIRS_UP_TO fragments, else TOP_K).
    objects: optional class per fragment (relicgpu.heap.grouping's labels): only pairs within one
    class are matched, in one run over the whole heap (one engine, all pairs in parallel).
    """
    params = params or Params()
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    batch = _load(fragments_or_dir)
    fragments = batch.fragments
    n = len(fragments)
    timings["load"] = batch.seconds  # also when the caller read the files (the command line does)
    be = resolve(backend)
    backend_name = be.name
    scale = common_scale(fragments, params)
    if cache_dir is None and out_dir is not None:
        cache_dir = Path(out_dir) / "cache"
    cache = Cache(cache_dir, params, scale, backend_name)
    hashes = [fragment_hash(f) for f in fragments]
    show = bool(progress) and sys.stderr.isatty()
    stats: dict = {"fragments": n, "scale": scale}

    t0 = time.perf_counter()
    eng = make_engine(engine, workers, address, be, gpus_per_task)
    timings["engine"] = time.perf_counter() - t0  # starting (or joining) Ray
    try:
        # 1. prepare every fragment at the common scale
        t0 = time.perf_counter()
        prepared: list = [cache.get_prepared(f, h) for f, h in zip(fragments, hashes)]
        todo = [i for i in range(n) if prepared[i] is None]
        bar = _bar(len(todo), show, "prepare")

        def took_prepared(job, result):
            i = job.payload[0]
            prepared[i] = received(result, fragments[i])
            cache.put_prepared(hashes[i], prepared[i], fragments[i])
            bar.update(1)

        eng.map(_prepare_one, [Job((i, params, backend_name, scale), (i,)) for i in todo],
                {i: fragments[i] for i in todo}, took_prepared)
        bar.close()
        timings["prepare"] = time.perf_counter() - t0
        stats["contours"] = int(sum(len(p.contours) for p in prepared))
        stats["smoothed"] = smoothing_notes(p.fragment for p in prepared)

        # 2. screen all contour pairs in one batched call
        t0 = time.perf_counter()
        lcs = cache.get_array("screen", *hashes)
        if lcs is None or lcs.shape != (n, n):
            lcs = screen(prepared, params, be).scores
            cache.put_array("screen", lcs, *hashes)
        # the contour LCS ranks partners at chance on many-piece heaps; the point-pair votes
        # of each fragment pair (small tables, all pairs) rank them
        support = cache.get_array("screen-ppf", *hashes)
        if support is None or support.shape != (n, n):
            support = np.zeros((n, n))

            def took_support(job, result):
                for i, j, v in result:
                    support[i, j] = support[j, i] = v

            eng.map(_ppf_screen_job, [Job((pairs, needs, params, scale, backend_name), needs)
                                      for pairs, needs in _screen_blocks(n, eng.parallelism)],
                    {i: prepared[i] for i in range(n)}, took_support)
            cache.put_array("screen-ppf", support, *hashes)
        scores = normalised_support(support) + SCREEN_LCS_WEIGHT * lcs
        if objects is not None:
            objects = np.asarray(objects)
            if objects.shape != (n,):
                raise ValueError(f"objects: one class per fragment expected, got {objects.shape} for {n}")
            scores = np.where(objects[:, None] == objects[None, :], scores, 0.0)
        if top_k is None and n <= ALL_PAIRS_UP_TO:
            # every pair, those the screen scores 0 too (a cloud that is mostly break picks little of
            # it first, and its votes find nothing), but not across the given objects
            candidates = [(i, j) for i in range(n) for j in range(i + 1, n)
                          if objects is None or objects[i] == objects[j]]
        else:
            candidates = select_candidates(scores, top_k or TOP_K)
        timings["screen"] = time.perf_counter() - t0
        stats["candidates"] = len(candidates)
        stats["pairs"] = n * (n - 1) // 2

        # 3. full match of the candidates
        t0 = time.perf_counter()
        docs: dict[tuple[int, int], dict] = {}
        for i, j in candidates:
            doc = cache.get_pair(hashes[i], hashes[j])
            if doc is not None:
                docs[(i, j)] = doc
        todo_pairs = [p for p in candidates if p not in docs]
        stats["pairs_from_cache"] = len(candidates) - len(todo_pairs)
        chunk = 1 if eng.name == "local" else max(1, min(8, math.ceil(len(todo_pairs) / (4 * eng.parallelism))))
        jobs = []
        for s in range(0, len(todo_pairs), chunk):
            part = todo_pairs[s:s + chunk]
            needs = tuple(sorted({k for p in part for k in p}))
            jobs.append(Job((part, needs, params, backend_name, scale), needs))
        bar = _bar(len(todo_pairs), show, "match")
        errors = []

        def took_pairs(job, result):
            for i, j, doc in result:
                docs[(i, j)] = doc
                if doc.get("error"):
                    errors.append(f"{fragments[i].name} / {fragments[j].name}: {doc['reason']}")
                else:
                    cache.put_pair(hashes[i], hashes[j], doc)
                bar.update(1)

        eng.map(_match_job, jobs, {i: prepared[i] for i in range(n)}, took_pairs)
        bar.close()
        timings["match"] = time.perf_counter() - t0
        stats["errors"] = errors

        # 4. the assembly graph
        t0 = time.perf_counter()
        edges = [Edge(i, j, np.asarray(d["transform"], np.float64), float(d["score"]))
                 for (i, j), d in sorted(docs.items()) if d["accepted"]]
        samples = [p.sample for p in prepared]
        weighed = rim_first(edges, samples, params, scale, be)  # matches whose outlines agree first
        first = {(e.a, e.b) for e, w in zip(edges, weighed) if w.score > e.score}
        edges = weighed
        joined = sorted({k for e in edges for k in (e.a, e.b)})
        solids = [closed_solid(fragments[i]) if i in joined or params.grow_groups else None for i in range(n)]
        t1 = time.perf_counter()
        same_object = _same_object(fragments, hashes, params, cache, eng)
        timings["describe"] = time.perf_counter() - t1
        pose, group, notes = grow_forest(n, edges, samples, params, scale, be, solids, same_object)
        for key in first:
            notes[key] += " (its rims meet the partner's creases: weighed first)"
        used = [e for e in edges if notes[(e.a, e.b)].startswith("used")]
        stats["apart"] = sum(note.startswith(APART_NOTE) for note in notes.values())
        timings["assemble"] = time.perf_counter() - t0

        # 5. what stayed apart, matched against the placed groups
        t0 = time.perf_counter()
        joins = []
        if params.grow_groups:
            joins, grown = grow_groups(fragments, prepared, pose, group, candidates, samples, solids, params, scale,
                                       be, eng, show, cache, hashes, same_object)
            stats.update(grown)
        timings["grow"] = time.perf_counter() - t0
    finally:
        eng.close()
    used += [e for e, _, _ in joins]
    t0 = time.perf_counter()
    pose = refine_poses(pose, group, used, samples)
    pose = settle(pose, group, samples, params, scale, be)
    timings["refine"] = time.perf_counter() - t0

    names = [f.name for f in fragments]
    poses, groups = _finish_groups(pose, group)
    matches = [_record(e.a, e.b, docs[(e.a, e.b)], notes[(e.a, e.b)]) for e in edges]
    matches += [_record(e.a, e.b, doc | {"transform": e.transform.tolist()}, note) for e, doc, note in joins]
    rejected = [_record(i, j, d, f"not verified: {d['reason']}") for (i, j), d in sorted(docs.items())
                if not d["accepted"]]
    stats.update(accepted=len(edges), rims_first=len(first), used=len(used), cache_hits=cache.hits,
                 cache_writes=cache.writes, groups=len(set(groups)), placed=sum(p is not None for p in poses))
    timings["total"] = time.perf_counter() - t_start
    result = Assembly(names, poses, groups, matches, timings, backend_name, eng.name, stats, scores, candidates,
                      [f.file for f in fragments], list(batch.skipped), list(batch.notes) + stats["smoothed"], rejected)
    if out_dir is not None:
        t0 = time.perf_counter()
        write_outputs(result, fragments, out_dir, progress=show)
        result.timings["write"] = time.perf_counter() - t0
        result.timings["total"] = time.perf_counter() - t_start
        atomic_write_bytes(Path(out_dir) / "assembly.json", result.to_json().encode())
    return result


def _same_object(fragments: list[Fragment], hashes: list[str], params: Params, cache: Cache, eng) -> np.ndarray | None:
    """(n, n) p(one object) of every pair of fragments (`heap.grouping`'s descriptor model, each
    fragment described on the engine; colour left out: the files are not read again), which the
    forest and the growth ask before joining two groups (`Params.apart_below`); None where that is
    off, for fewer than three fragments, where any is a cloud, or where one cannot be described."""
    n = len(fragments)
    if params.apart_below is None or n < 3 or any(is_cloud(f) for f in fragments):
        return None
    p = cache.get_array("same-object", *hashes)
    if p is None or p.shape != (n, n):
        found: list = [None] * n

        def took(job, result):
            found[job.payload[0]] = result

        eng.map(_describe_one, [Job((i,), (i,)) for i in range(n)], dict(enumerate(fragments)), took)
        if any(d is None for d in found):
            return None
        p = heap_probability(found)
        cache.put_array("same-object", p, *hashes)
    return p


def _describe_one(payload, fragment):
    """`describe` of one fragment, or None where it cannot be described (too few faces ...)."""
    try:
        return describe(fragment)
    except (FragmentError, ValueError, np.linalg.LinAlgError):
        return None


def _record(a: int, b: int, doc: dict, note: str) -> MatchRecord:
    """A MatchRecord from a pair's match document and the decision on it (`note`)."""
    return MatchRecord(a, b, np.asarray(doc["transform"], np.float64), float(doc["score"]), float(doc["rmse"]),
                       float(doc["overlap"]), float(doc["penetration"]), note.startswith("used"), note,
                       bool(doc["accepted"]))


def _prepare_one(payload, fragment):
    """Prepare one fragment; the fragment is left out of the result where the caller has it (`shipped`)."""
    _, params, backend_name, scale = payload
    return shipped(prepare(fragment, params, resolve(backend_name), scale=scale, with_second=True), fragment)


def _finish_groups(pose: list, group: list[int]) -> tuple[list, list[int]]:
    """Number groups (largest first, then by lowest fragment index), express each group's poses
    in the frame of its lowest-index fragment, and leave fragments that joined nothing unplaced."""
    n = len(group)
    members: dict[int, list[int]] = {}
    for i, g in enumerate(group):
        members.setdefault(g, []).append(i)
    order = sorted(members.values(), key=lambda m: (-len(m), m[0]))
    poses: list = [None] * n
    groups = [0] * n
    for label, m in enumerate(order):
        anchor = invert(pose[m[0]])
        for i in m:
            groups[i] = label
            poses[i] = anchor @ pose[i] if len(m) > 1 else None
    return poses, groups
