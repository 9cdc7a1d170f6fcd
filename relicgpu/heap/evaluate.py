"""Scoring an assembly against a known answer (synthetic breaks), shared by tests and benchmarks.

Truth: per fragment a 4x4 pose carrying its file coordinates into its object's
frame, an object label, and the list of touching pairs. Prediction: per fragment
a 4x4 pose into its group's frame (or None when unplaced) and a group id.

Part accuracy (issue 5): a fragment is right when, after moving the whole
predicted group so that one fragment sits on its truth (the best choice of that
fragment), its vertices lie within `tol` RMS of their true places, lengths in
units of the object size. An object is judged in the group holding most of its
fragments; its fragments elsewhere (or unplaced) are wrong, and so is a fragment
of another object in that group's frame. An object of one fragment is right by
itself when that fragment is in a group of its own.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..pair.icp import apply, invert


@dataclass(frozen=True)
class Score:
    part_accuracy: float  # share of fragments right
    right: np.ndarray  # (n,) bool
    rotation_rmse_deg: float  # over placed fragments of the objects' main groups, reference excluded
    translation_rmse: float  # of the fragment centroids, object units
    pair_precision: float  # used matches that join two fragments of one object at their true relative pose
    pair_recall: float  # truly touching pairs found among the used matches
    n_used: int
    n_touching: int
    details: dict = field(default_factory=dict)


def _rms(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))


def _angle_deg(r: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1))))


def relative_pose_error(vertices_b: np.ndarray, transform: np.ndarray, true_a: np.ndarray, true_b: np.ndarray) -> float:
    """RMS distance of b's vertices placed by `transform` (b onto a) from their true place relative to a."""
    truth = invert(true_a) @ true_b
    return _rms(apply(transform, vertices_b), apply(truth, vertices_b))


def score(vertices: list[np.ndarray], pred_poses: list, groups: list[int], true_poses: list[np.ndarray],
          touching: list[tuple[int, int]], used_matches: list[tuple[int, int, np.ndarray]],
          objects: list | None = None, unit: float = 1.0, tol: float = 0.01) -> Score:
    """Score a predicted assembly (see the module docstring).

    vertices: per fragment (V_i,3) in file coordinates; pred_poses: 4x4 or None;
    used_matches: (i, j, T) with T carrying j onto i; unit: the object size (lengths are divided by it).
    """
    n = len(vertices)
    objects = [0] * n if objects is None else list(objects)
    tol_abs = tol * unit
    right = np.zeros(n, bool)
    rot_err, trans_err = [], []
    for obj in sorted(set(objects), key=repr):
        members = [i for i in range(n) if objects[i] == obj]
        placed = [i for i in members if pred_poses[i] is not None]
        if len(members) == 1:
            i = members[0]
            right[i] = pred_poses[i] is None or sum(1 for g in groups if g == groups[i]) == 1
            continue
        if not placed:
            continue
        counts: dict[int, int] = {}
        for i in placed:
            counts[groups[i]] = counts.get(groups[i], 0) + 1
        main = min(counts, key=lambda g: (-counts[g], g))
        in_main = [i for i in placed if groups[i] == main]
        best = (-1, None, None)
        for r in in_main:  # the reference fragment that sits on its truth
            align = true_poses[r] @ invert(pred_poses[r])
            errs = {i: _rms(apply(align @ pred_poses[i], vertices[i]), apply(true_poses[i], vertices[i]))
                    for i in in_main}
            ok = sum(e <= tol_abs for e in errs.values())
            if ok > best[0]:
                best = (ok, r, align)
        _, r, align = best
        for i in in_main:
            pred = align @ pred_poses[i]
            good = _rms(apply(pred, vertices[i]), apply(true_poses[i], vertices[i])) <= tol_abs
            right[i] = good
            if i != r:
                rot_err.append(_angle_deg(pred[:3, :3] @ true_poses[i][:3, :3].T))
                c = vertices[i].mean(axis=0)
                trans_err.append(float(np.linalg.norm(apply(pred, c[None]) - apply(true_poses[i], c[None]))))
        # a fragment of another object placed in this object's main group is wrong
        intruders = [i for i in range(n) if objects[i] != obj and pred_poses[i] is not None and groups[i] == main]
        for i in intruders:
            right[i] = False

    truth = {(min(i, j), max(i, j)) for i, j in touching}
    good_pairs = 0
    found = set()
    for i, j, t in used_matches:
        key = (min(i, j), max(i, j))
        same_object = objects[i] == objects[j]
        # right when it puts the two at their true relative pose; pieces that meet over less than
        # synth's contact threshold (a corner, an edge) are not "touching" but a right fit all the same
        ok = same_object and relative_pose_error(vertices[j], np.asarray(t), true_poses[i], true_poses[j]) <= tol_abs
        good_pairs += ok
        if ok and key in truth:
            found.add(key)
    precision = good_pairs / len(used_matches) if used_matches else 1.0
    recall = len(found) / len(truth) if truth else 1.0
    rmse = lambda x: float(np.sqrt(np.mean(np.square(x)))) if x else 0.0  # noqa: E731
    return Score(float(right.mean()) if n else 1.0, right, rmse(rot_err), rmse(trans_err) / unit,
                 float(precision), float(recall), len(used_matches), len(truth),
                 {"rotation_errors_deg": rot_err, "translation_errors": trans_err})


def score_assembly(assembly, fragments: list, truth: dict, tol: float = 0.01) -> Score:
    """Score an Assembly against a synth truth dict (relicgpu.synth.read_truth); fragments
    are matched to the truth by name (file stem), objects are taken to be of unit size."""
    by_name = {e["name"]: e for e in truth["fragments"]}
    missing = [n for n in assembly.names if n not in by_name]
    if missing:
        raise ValueError(f"fragments not in the truth: {', '.join(missing[:5])}")
    index = {n: i for i, n in enumerate(assembly.names)}
    true_poses = [np.asarray(by_name[n]["pose"], np.float64) for n in assembly.names]
    objects = [by_name[n]["object"] for n in assembly.names]
    touching = [(index[a], index[b]) for a, b in truth["touching_pairs"] if a in index and b in index]
    used = [(m.a, m.b, np.asarray(m.transform)) for m in assembly.matches if m.used]
    vertices = [np.asarray(f.vertices, np.float64) for f in fragments]
    return score(vertices, list(assembly.poses), list(assembly.groups), true_poses, touching, used, objects,
                 unit=1.0, tol=tol)
