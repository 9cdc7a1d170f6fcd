#!/usr/bin/env python
"""Benchmark: read and mesh a large point cloud (relicgpu.cloud).

Samples N points (default 1 million) uniformly on the surface of a fragment,
moves each by up to NOISE (a fraction of the fragment size) in a random
direction, writes them to a file, then times reading the file and meshing it
into a closed surface. Prints the time of each step, the peak memory
(tracemalloc: Python and NumPy allocations; ru_maxrss: the whole process,
Qhull included), and checks the result: one closed manifold, Hausdorff distance
to the source surface.

    python scripts/bench_pointcloud.py                      # 1M points, vase fragment, .npy
    python scripts/bench_pointcloud.py --points 200000 --format xyz --source sphere
    python scripts/bench_pointcloud.py --points 60000 --source torso --gaussian 0.0005 --for-matching

The source is fragment 0 of `relicgpu.synth.generate(shape, pieces=2, seed)`,
or a unit sphere with --source sphere (no other stage needed).
"""
from __future__ import annotations

import argparse
import os
import resource
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np


def source_mesh(kind: str, seed: int):
    import trimesh

    if kind == "sphere":
        return trimesh.creation.icosphere(6), "unit sphere"
    from relicgpu import synth

    result = synth.generate(kind, pieces=2, seed=seed, progress=False)
    frag = result.fragments[0]
    return frag.to_trimesh(), f"synth {kind} seed {seed}, {frag.name} ({len(frag.faces)} faces)"


def sample_cloud(mesh, n: int, noise: float, seed: int, gaussian: float = 0.0) -> np.ndarray:
    """n points on the mesh's surface, each moved by up to `noise` times its diagonal in a random
    direction, or (gaussian > 0) by a normal deviate of `gaussian` times its largest side per axis."""
    import trimesh

    pts, _ = trimesh.sample.sample_surface(mesh, n, seed=seed)
    if gaussian > 0:
        return pts + np.random.default_rng(seed + 1).normal(size=pts.shape) * gaussian * float(mesh.extents.max())
    rng = np.random.default_rng(seed + 1)
    d = rng.normal(size=pts.shape)
    d /= np.linalg.norm(d, axis=1)[:, None]
    size = float(np.linalg.norm(mesh.extents))
    return pts + d * rng.uniform(0.0, noise * size, (n, 1))


def write_cloud(pts: np.ndarray, path: Path) -> None:
    if path.suffix == ".npy":
        np.save(path, pts)
    else:
        np.savetxt(path, pts, fmt="%.9g")


def hausdorff(a, b, n: int = 50000) -> tuple[float, float]:
    """(largest distance from a's surface to b's, from b's to a's), over n samples of each."""
    import trimesh

    pa, _ = trimesh.sample.sample_surface(a, n, seed=11)
    pb, _ = trimesh.sample.sample_surface(b, n, seed=12)
    _, da, _ = trimesh.proximity.closest_point(b, pa)
    _, db, _ = trimesh.proximity.closest_point(a, pb)
    return float(da.max()), float(db.max())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=int, default=1_000_000)
    ap.add_argument("--source", default="vase", help="vase, torso, slab (relicgpu.synth) or sphere")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--noise", type=float, default=0.001, help="largest displacement, a fraction of the size")
    ap.add_argument("--format", choices=["npy", "xyz"], default="npy", help="file format the cloud is read from")
    ap.add_argument("--gaussian", type=float, default=0.0,
                    help="Gaussian noise instead: sigma per axis, a fraction of the largest side")
    ap.add_argument("--max-points", type=int, default=None, help="thinning target (default: the module's)")
    ap.add_argument("--for-matching", action="store_true",
                    help="mesh as load_fragment does (triangulate.mesh_for_matching: dense, then decimated)")
    ap.add_argument("--no-check", action="store_true", help="skip the Hausdorff check (slow for big meshes)")
    ap.add_argument("--json", type=Path, help="also write the figures to this JSON file")
    args = ap.parse_args(argv)

    import trimesh

    from relicgpu.cloud import triangulate as pc
    from relicgpu.cloud.refine import closed_manifold_fault
    from relicgpu.io.clouds import read_point_cloud

    default = pc.DENSE_POINTS if args.for_matching else pc.MAX_POINTS
    max_points = default if args.max_points is None else (args.max_points or None)
    mesh, label = source_mesh(args.source, args.seed)
    size = float(np.linalg.norm(mesh.extents))
    pts = sample_cloud(mesh, args.points, args.noise, args.seed, args.gaussian)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"source: {label}, size {size:.4g}")
    noise = (f"Gaussian noise {args.gaussian:.3%} of the largest side" if args.gaussian > 0
             else f"noise up to {args.noise:.2%} of size")
    print(f"cloud: {args.points} points, {noise}, {args.format}; "
          f"max_points {max_points}; load average {load:.2f} on {os.cpu_count()} CPUs")

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"cloud.{args.format}"
        write_cloud(pts, path)
        del pts
        rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        tracemalloc.start()
        t0 = time.perf_counter()
        cloud = read_point_cloud(path)
        t_read = time.perf_counter() - t0
        t1 = time.perf_counter()
        mesh_it = pc.mesh_for_matching if args.for_matching else pc.triangulate
        result = mesh_it(cloud.points, max_points=max_points, progress=sys.stderr.isatty(), label=str(path))
        t_mesh = time.perf_counter() - t1
        _, peak_traced = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        rss_peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

    fault = closed_manifold_fault(result.vertices, result.faces)
    out = trimesh.Trimesh(result.vertices, result.faces, process=False)
    figures = {
        "points": args.points, "source": label, "format": args.format, "noise": args.noise,
        "gaussian": args.gaussian, "for_matching": args.for_matching,
        "max_points": max_points, "meshed_points": result.n_meshed, "voxel": result.voxel,
        "spacing": result.spacing, "alpha": result.alpha, "faces": len(result.faces),
        "read_s": round(t_read, 2), "mesh_s": round(t_mesh, 2), "total_s": round(t_read + t_mesh, 2),
        "steps_s": {k: round(v, 2) for k, v in result.timings.items()},
        "peak_tracemalloc_mb": round(peak_traced / 2**20, 1),
        "peak_rss_mb": round(rss_peak, 1), "rss_before_mb": round(rss_before, 1),
        "closed_manifold": fault is None, "fault": fault, "euler": int(out.euler_number),
        "load_average": load,
    }
    if not args.no_check:
        to_source, to_mesh = hausdorff(out, mesh)
        figures["hausdorff_mesh_to_source_pct"] = round(100 * to_source / size, 4)
        figures["hausdorff_source_to_mesh_pct"] = round(100 * to_mesh / size, 4)
        figures["hausdorff_pct_of_size"] = max(figures["hausdorff_mesh_to_source_pct"],
                                               figures["hausdorff_source_to_mesh_pct"])
        figures["hausdorff_pct_of_largest_side"] = round(100 * max(to_source, to_mesh) / float(mesh.extents.max()), 4)

    print(f"read:  {t_read:6.2f} s")
    print(f"mesh:  {t_mesh:6.2f} s  " + "  ".join(f"{k} {v:.2f}" for k, v in result.timings.items()))
    print(f"total: {t_read + t_mesh:6.2f} s")
    print(f"peak memory: tracemalloc {figures['peak_tracemalloc_mb']} MiB, "
          f"process maxrss {figures['peak_rss_mb']} MiB (before reading: {figures['rss_before_mb']} MiB)")
    print(f"result: {result.n_meshed} points meshed (voxel {result.voxel:.4g}), alpha {result.alpha:.4g} "
          f"= {result.alpha / result.spacing:.2f} spacings, {len(result.faces)} faces, "
          f"{'one closed manifold' if fault is None else 'FAULT: ' + fault}, Euler {figures['euler']}")
    if "hausdorff_pct_of_size" in figures:
        print(f"Hausdorff distance to the source, both ways: {figures['hausdorff_pct_of_size']:.3f}% of size "
              f"(mesh to source {figures['hausdorff_mesh_to_source_pct']:.3f}%, "
              f"source to mesh {figures['hausdorff_source_to_mesh_pct']:.3f}%; "
              f"{figures['hausdorff_pct_of_largest_side']:.3f}% of the largest side)")
    for note in result.notes:
        print(f"note: {note}")
    if args.json:
        from relicgpu.io.files import atomic_write_json
        atomic_write_json(args.json, figures)
    return 0 if fault is None else 1


if __name__ == "__main__":
    sys.exit(main())
