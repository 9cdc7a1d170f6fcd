"""Groups grown against their placed pieces: a fragment (or a smaller group) that no pairwise match
placed is matched against the merged surface of a placed group.

A rescanned break is rebuilt on each side on its own, and a piece of a many-piece object shares a
fifth or less of its break with any one neighbour: pairwise, the right pose is often among no
start, or its contact too small to verify (docs/benchmarks.md). Against a placed group the piece's
break meets all its placed neighbours at once. The group's merged mesh leaves out the faces where
its members touch one another (within `JOINED` contact distances of another member), so that what
remains is the group's skin and its free break; it is prepared and matched like any fragment
(`match_pair`, the same verification but for interpenetration, `UNCHECKED`), and a fit is used
only where it interpenetrates no whole member (`forest.first_clash`). Rounds go on while a group
grows; a pair of groups is matched once for each of their compositions, and the match is cached
by the members' contents and poses.
"""
from __future__ import annotations

import hashlib
import sys

import numpy as np
from scipy.spatial import cKDTree
from tqdm import tqdm

from ..backends import resolve
from ..io.fragment import Fragment, is_cloud
from ..pair.icp import apply, invert
from ..pair.pipeline import match_pair
from ..pair.prepare import prepare
from ..pair.result import failed_doc
from ..params import Params
from .engines import Job
from .forest import Edge, apart, first_clash

# A group match does not judge interpenetration or sunk surfaces on the merged surface: it is open
# where the members touched, and points beside those holes read as inside it (a Blender cube shard
# at its true pose, 0.1 degrees off, read 18% inside the other nineteen and 5.5% sunk).
# `forest.first_clash` judges the fit against each whole member instead.
UNCHECKED = {"max_penetration": 1.0, "max_surface_penetration": 1.0}
# A member's face whose centre lies within this many contact distances of another member's
# vertices is where the two touch: left out of the group's merged mesh. Rescanned neighbours
# lie within one contact distance over only a sixth to a half of their contact.
JOINED = 2.0


def merged_fragment(fragments: list[Fragment], members: list[int], pose: list, reach: float) -> Fragment:
    """The members of a group as one mesh in the group's frame, less the faces where they touch.

    Parameters
    ----------
    fragments : list of Fragment
        Every fragment of the heap (meshes).
    members : list of int
        The group's fragments.
    pose : list of (4, 4) float
        Each fragment's pose in its group's frame.
    reach : float
        A face whose centre lies within this of another member's vertices is left out.
    """
    placed = [apply(pose[i], np.asarray(fragments[i].vertices, np.float64)) for i in members]
    vertices, faces, offset = [], [], 0
    for k, i in enumerate(members):
        v, f = placed[k], np.asarray(fragments[i].faces)
        others = [placed[m] for m in range(len(members)) if m != k]
        if others:
            d, _ = cKDTree(np.concatenate(others)).query(v[f].mean(axis=1), distance_upper_bound=reach)
            f = f[~(d <= reach)]
        used = np.unique(f)
        remap = np.full(len(v), -1, np.int64)
        remap[used] = np.arange(len(used))
        vertices.append(v[used])
        faces.append(remap[f] + offset)
        offset += len(used)
    name = "+".join(fragments[i].name for i in members)
    return Fragment(name, np.concatenate(vertices), np.concatenate(faces).astype(np.int32))


def _grow_job(payload, big, small):
    """Match a merged group (or one fragment) onto a larger group; payload = (trial, params, backend, scale)."""
    trial, params, backend_name, scale = payload
    try:
        return trial, match_pair(big, small, params, resolve(backend_name), scale=scale).doc()
    except Exception as exc:  # one bad group must not sink the assembly; reported in the stats
        return trial, failed_doc(exc)


def group_key(members: tuple, pose: list, hashes: list[str]) -> str:
    """A group's cache key: its members' contents and their poses in its frame."""
    h = hashlib.sha256()
    for i in members:
        h.update(hashes[i].encode())
        h.update(np.ascontiguousarray(pose[i], np.float64).tobytes())
    return h.hexdigest()[:32]


def grow_groups(fragments: list[Fragment], prepared: list, pose: list, group: list[int], candidates: list,
                samples: list, solids: list, params: Params, scale: float, backend, engine,
                progress: bool = False, cache=None, hashes: list[str] | None = None,
                same_object: np.ndarray | None = None) -> tuple[list[tuple[Edge, dict, str]], dict]:
    """Join groups to placed groups by matching them whole (see the module docstring).

    `pose` and `group` (as `forest.grow_forest` returns them) are updated in place. Two groups are
    tried when a candidate pair links them and the larger has at least two members; meshes only.
    cache, hashes: the assembly's `Cache` and fragment hashes (each group match is kept there by
    `group_key`, as a pair's match is). Returns the edges that record each join (a member of the
    larger group, the nearest member of the joined one, and their relative transform) with the
    match's record and a note, and counts.
    """
    n = len(fragments)
    reach = JOINED * params.contact_distance * scale
    linked = {(min(i, j), max(i, j)) for i, j in candidates}
    use_cache = cache is not None and hashes is not None
    tried: set = set()
    joins: list = []
    stats = {"grow_tried": 0, "grow_joined": 0, "grow_errors": 0}
    merged: dict = {}  # merged and prepared groups by their members (poses are fixed within a group)

    def members_of() -> dict[int, tuple]:
        out: dict[int, list] = {}
        for i in range(n):
            out.setdefault(group[i], []).append(i)
        return {g: tuple(m) for g, m in out.items()}

    def prepared_group(m: tuple):
        if len(m) == 1 and np.allclose(pose[m[0]], np.eye(4)):
            return prepared[m[0]]
        if m not in merged:
            frag = merged_fragment(fragments, list(m), pose, reach)
            merged[m] = prepare(frag, params, backend, scale=scale, with_second=True)
        return merged[m]

    for _ in range(n):
        members = members_of()
        trials = []
        for gb, big in members.items():
            if len(big) < 2:
                continue
            for gs, small in members.items():
                if gs == gb or (len(small), small[0]) > (len(big), big[0]) or (big, small) in tried:
                    continue
                if any(is_cloud(fragments[i]) for i in big + small):
                    continue
                if not any((min(i, j), max(i, j)) in linked for i in big for j in small):
                    continue
                if apart(list(big), list(small), same_object, params) is not None:
                    continue
                tried.add((big, small))
                trials.append((big, small, gb, gs))
        if not trials:
            break
        keys = {t: (group_key(t[0], pose, hashes), group_key(t[1], pose, hashes)) if use_cache else None
                for t in trials}
        found = []

        def took(trial, doc, fresh=True):
            stats["grow_tried"] += 1
            if doc.get("error"):
                stats["grow_errors"] += 1
            elif fresh and use_cache:
                cache.put_pair(*keys[trial], doc)
            if doc["accepted"]:
                found.append((float(doc["score"]), trial, doc))

        todo = []
        for t in trials:
            doc = cache.get_pair(*keys[t]) if use_cache else None
            if doc is None:
                todo.append(t)
            else:
                took(t, doc, fresh=False)
        objects = {}
        for big, small, _, _ in todo:
            objects[big], objects[small] = prepared_group(big), prepared_group(small)
        bar = tqdm(total=len(todo), desc="grow groups", unit="match", file=sys.stderr, disable=not progress,
                   leave=False, dynamic_ncols=True)

        def took_job(job, result):
            took(*result)
            bar.update(1)

        loose = params.with_(**UNCHECKED)
        engine.map(_grow_job, [Job((t, loose, backend.name, scale), t[:2]) for t in todo], objects, took_job)
        bar.close()
        grew = False
        for score, (big, small, gb, gs), doc in sorted(found, key=lambda t: (-t[0], t[1])):
            if any(group[i] != gb for i in big) or any(group[i] != gs for i in small):
                continue  # one of the two joined another group earlier in this round: its frame moved
            big_now = [i for i in range(n) if group[i] == gb]
            move = np.asarray(doc["transform"], np.float64)  # small's group frame -> big's group frame
            clash = first_clash(big_now, list(small), pose, move, samples, params, scale, backend, solids)
            if clash is not None:
                continue
            for q in small:
                pose[q] = move @ pose[q]
                group[q] = gb
            a, q = _nearest_members(big, small, pose, samples, reach)
            note = (f"used: joined against the merged surface of {len(big)} placed fragments "
                    f"(no pairwise match placed {'it' if len(small) == 1 else 'its group'}; {doc['reason']})")
            joins.append((Edge(a, q, invert(pose[a]) @ pose[q], score), doc, note))
            stats["grow_joined"] += 1
            grew = True
        if not grew:
            break
    return joins, stats


def _nearest_members(big: tuple, small: tuple, pose: list, samples: list, reach: float) -> tuple[int, int]:
    """The member of each group that touch most (fracture points of one near the other's)."""
    trees = {a: cKDTree(apply(pose[a], samples[a].fracture)) for a in big if len(samples[a].fracture)}
    best, pair = -1, (big[0], small[0])
    for q in small:
        pts = apply(pose[q], samples[q].fracture)
        if not len(pts):
            continue
        for a, tree in trees.items():
            count = int(np.sum(tree.query(pts, distance_upper_bound=reach)[0] <= reach))
            if count > best:
                best, pair = count, (a, q)
    return pair
