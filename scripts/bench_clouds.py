#!/usr/bin/env python
"""Match two-piece fractures given as sparse point clouds (or open meshes) and count right poses.

    python scripts/bench_clouds.py                                  # 10 pairs, with and without normals
    python scripts/bench_clouds.py --pairs 12 --first 12 --modes none   # held-out pairs 12-23
    python scripts/bench_clouds.py --source corpus --pairs 12           # an independent generator

Pair k is relicgpu.synth's two-piece {vase, torso, slab}[k % 3] of seed k // 3 (4,000 faces,
scanner noise 0.05% of the size), or with --source corpus the clean two-piece object of
relicgpu.synth.corpus family {rough, smooth, voronoi, vessel}-clean [k % 4] of seed k // 4; each piece becomes --points points drawn from its surface
(seed 100 k + i) with Gaussian noise of --noise times the piece's size, with the true normals
(`normals`), with none (`none`), or as the mesh itself with three holes cut into its skin
(`open`). A pair is right when `match_pair` accepts it with a rotation error under 2 degrees and
the moved piece's points within 1% RMS of their true place, lengths relative to the object's
size (the largest side of its assembled bounding box). A pair accepted at a wrong pose is
counted apart: it is worse than a miss.
"""
from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

SHAPES = ("vase", "torso", "slab")


CORPUS = ("rough-clean", "smooth-clean", "voronoi-clean", "vessel-clean")


def pair_name(k: int, source: str) -> str:
    return f"{SHAPES[k % 3]} seed {k // 3}" if source == "synth" else f"{CORPUS[k % 4]} seed {k // 4}"


def make_pair(k: int, mode: str, points: int, noise: float, source: str = "synth"):
    """The two fragments of pair k in `mode` and the truth carrying b onto a."""
    import trimesh

    from relicgpu import synth
    from relicgpu.synth import corpus
    from relicgpu.cloud.points import cloud_fragment

    if source == "corpus":
        r = corpus.generate(CORPUS[k % 4], pieces=2, seed=k // 4, faces=4000)
    else:
        r = synth.generate(SHAPES[k % 3], pieces=2, seed=k // 3, faces=4000, noise=0.0005, progress=False)
    truth = np.linalg.inv(r.poses[0]) @ r.poses[1]
    frags = []
    for i, f in enumerate(r.fragments):
        m = f.to_trimesh()
        if mode == "open":
            frags.append(_cut_holes(f, r.fracture_faces[i], np.random.default_rng(100 * k + i)))
            continue
        p, fi = trimesh.sample.sample_surface(m, points, seed=100 * k + i)
        p = p + np.random.default_rng(7 * k + i).normal(size=p.shape) * noise * f.size
        frags.append(cloud_fragment(f.name, p, m.face_normals[fi] if mode == "normals" else None))
    return frags[0], frags[1], truth


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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=10)
    ap.add_argument("--first", type=int, default=0, help="index of the first pair")
    ap.add_argument("--modes", default="normals,none", help="comma list of normals, none, open")
    ap.add_argument("--points", type=int, default=2500)
    ap.add_argument("--noise", type=float, default=0.0005)
    ap.add_argument("--source", choices=["synth", "corpus"], default="synth")
    ap.add_argument("--backend", default="numpy")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)

    from relicgpu import match_pair

    rows, summary = [], {}
    for mode in args.modes.split(","):
        right = wrong = 0
        for k in range(args.first, args.first + args.pairs):
            a, b, truth = make_pair(k, mode, args.points, args.noise, args.source)
            t0 = time.perf_counter()
            m = match_pair(a, b, backend=args.backend)
            rot, rms = score(a, b, truth, m.transform)
            good = rot < 2 and rms < 0.01
            right += bool(m.accepted and good)
            wrong += bool(m.accepted and not good)
            tag = "right" if m.accepted and good else ("WRONG ACCEPTED" if m.accepted else "rejected")
            rows.append({"mode": mode, "pair": k, "case": pair_name(k, args.source), "accepted": bool(m.accepted),
                         "rotation_error_deg": rot, "rms": rms, "reason": m.reason, "seconds": time.perf_counter() - t0})
            print(f"  {mode:7s} {pair_name(k, args.source)}: rot {rot:7.2f} deg, rms {rms:.4f}, {tag} "
                  f"({m.reason}) {rows[-1]['seconds']:.1f} s", file=sys.stderr, flush=True)
        summary[mode] = {"right": right, "wrong_accepted": wrong, "pairs": args.pairs}
    print(f"\n{args.source} pairs {args.first}-{args.first + args.pairs - 1}, {args.points} points, noise {args.noise}, "
          f"backend {args.backend}")
    for mode, s in summary.items():
        print(f"  {mode:8s} {s['right']}/{s['pairs']} right, {s['wrong_accepted']} accepted at a wrong pose")
    if args.json:
        from relicgpu.io.files import atomic_write_json
        atomic_write_json(args.json, {"summary": summary, "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
