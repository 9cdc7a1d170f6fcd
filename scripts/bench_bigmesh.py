#!/usr/bin/env python
"""Peak memory and time of `relicgpu assemble` on a heap holding one very big fragment.

    python scripts/bench_bigmesh.py                     # a 5M-face fragment (issue 15: under 4 GiB)
    python scripts/bench_bigmesh.py --faces 20000       # a tiny run (tests/test_scripts.py)

The heap is relicgpu.synth's two-piece --shape of --seed, written to a temporary folder as
binary PLY; its larger piece is refined by midpoint subdivision (every face cut in four: the
surface does not move) to about --faces faces (from at least --base), and a small cube that
matches nothing is added (a fragment left unplaced). `relicgpu assemble DIR -o OUT --backend numpy --quiet` runs in a subprocess under
GNU time (``/usr/bin/time -v``; else the child's ru_maxrss from `resource`): the script prints
its peak resident set size, its wall time, the phase times from assembly.json, and checks what
the outputs carry: the big piece's faces in assembly.glb, merged.stl's facets and whether they
close into consistently oriented shells (`outputs.is_closed`, corners welded by exact
position; shells written side by side pass too, so read the notes on merging with it).
--json writes the figures.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

GIB = 1024 ** 3


def make_heap(directory: Path, faces: int, shape: str, seed: int, base: int) -> dict:
    """Write the heap; the faces of each file."""
    import trimesh

    from relicgpu import synth

    splits = 0  # subdivisions: each multiplies the faces by four
    while faces / 4 ** (splits + 1) >= base:
        splits += 1
    want = faces / 4 ** splits  # faces of the big piece before subdividing
    asked = want
    for _ in range(3):  # the pieces' sizes vary about the mean asked for: aim the larger one at `want`
        r = synth.generate(shape, pieces=2, seed=seed, faces=max(200, int(asked)), progress=False)
        big = int(np.argmax([len(f.faces) for f in r.fragments]))
        got = len(r.fragments[big].faces)
        if abs(got - want) <= 0.05 * want:
            break
        asked *= want / got
    counts = {}
    for k, frag in enumerate(r.fragments):
        v, f = np.asarray(frag.vertices, np.float64), np.asarray(frag.faces, np.int64)
        for _ in range(splits if k == big else 0):
            v, f = trimesh.remesh.subdivide(v, f)
        name = f"{shape}_{k}.ply"
        trimesh.Trimesh(v, f, process=False).export(directory / name)
        counts[name] = len(f)
        del v, f
    cube = trimesh.creation.box((0.2, 0.2, 0.2))
    cube.apply_translation([5.0, 0, 0])
    cube.export(directory / "cube.ply")
    counts["cube.ply"] = len(cube.faces)
    return counts


def run_assemble(heap: Path, out: Path) -> dict:
    """Run the assemble in a child; its peak RSS (bytes), wall time and output."""
    cmd = [sys.executable, "-m", "relicgpu.cli", "assemble", str(heap), "-o", str(out), "--backend", "numpy",
           "--quiet"]
    gnu_time = shutil.which("time") if Path("/usr/bin/time").exists() else None
    env = {**os.environ, "RELICGPU_BACKEND": "numpy"}
    t0 = time.perf_counter()
    if gnu_time:
        run = subprocess.run(["/usr/bin/time", "-v"] + cmd, capture_output=True, text=True, env=env)
        found = re.search(r"Maximum resident set size \(kbytes\): (\d+)", run.stderr)
        peak = int(found.group(1)) * 1024 if found else None
    else:
        run = subprocess.run(cmd, capture_output=True, text=True, env=env)
        peak = None
    wall = time.perf_counter() - t0
    if peak is None:  # the largest child so far: this is the only child that did real work
        peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024
    return {"rc": run.returncode, "peak_rss_bytes": peak, "wall_s": wall, "stderr": run.stderr, "stdout": run.stdout}


def check_outputs(out: Path, counts: dict) -> dict:
    """What the outputs carry: faces of each mesh in assembly.glb, merged.stl's facets, the notes."""
    import struct

    doc = json.loads((out / "assembly.json").read_text())
    glb = (out / "assembly.glb").read_bytes()
    length, _ = struct.unpack_from("<II", glb, 12)
    gltf = json.loads(glb[20:20 + length])
    glb_faces = {m["name"]: gltf["accessors"][m["primitives"][0]["indices"]]["count"] // 3
                 for m in gltf["meshes"] if "indices" in m["primitives"][0]}
    merged = out / "merged.stl"
    facets = closed = None
    if merged.exists():
        from relicgpu.io.files import STL_FACET
        from relicgpu.heap.outputs import is_closed

        corners = np.fromfile(merged, STL_FACET, offset=84)["corners"].reshape(-1, 3)
        facets = len(corners) // 3
        closed = is_closed(corners, np.arange(len(corners)).reshape(-1, 3))  # welded by exact position
        del corners
    return {"glb_faces": glb_faces, "merged_facets": facets, "merged_closed": closed, "notes": doc.get("notes", []),
            "timings": doc.get("timings", doc.get("stats", {}).get("timings", {})),
            "placed": sum(f["pose"] is not None for f in doc["fragments"])}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--faces", type=int, default=5_000_000, help="faces of the big fragment (at least)")
    ap.add_argument("--shape", default="slab", choices=["vase", "torso", "slab"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--base", type=int, default=2000,
                    help="the big piece is made of at least this many faces, subdivided to about --faces")
    ap.add_argument("--keep", help="a folder to keep the heap and outputs in (default: a temporary one)")
    ap.add_argument("--json", help="write the figures here")
    args = ap.parse_args(argv)

    root = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="bench_bigmesh_"))
    try:
        heap, out = root / "heap", root / "out"
        heap.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        counts = make_heap(heap, args.faces, args.shape, args.seed, args.base)
        made = time.perf_counter() - t0
        big = max(counts, key=counts.get)
        print(f"heap: {', '.join(f'{k} {v:,} faces' for k, v in counts.items())} "
              f"({(heap / big).stat().st_size / 2 ** 20:.0f} MiB PLY; made in {made:.1f} s)", flush=True)
        result = run_assemble(heap, out)
        if result["rc"] != 0:
            print(result["stderr"][-3000:], file=sys.stderr)
            print(f"relicgpu assemble exited {result['rc']}", file=sys.stderr)
            return 1
        carried = check_outputs(out, counts)
        figures = {"faces": counts, "peak_rss_bytes": result["peak_rss_bytes"],
                   "peak_rss_gib": result["peak_rss_bytes"] / GIB, "wall_s": result["wall_s"], **carried}
        print(f"assemble: peak RSS {figures['peak_rss_gib']:.2f} GiB, wall {result['wall_s']:.1f} s, "
              f"{carried['placed']} of {len(counts)} fragments placed")
        if carried["timings"]:
            print("timings (s): " + ", ".join(f"{k} {v:.1f}" for k, v in carried["timings"].items()
                                              if isinstance(v, (int, float))))
        stem = Path(big).stem
        print(f"assembly.glb: {stem} {carried['glb_faces'].get(stem, 0):,} faces (file {counts[big]:,}); "
              + (f"merged.stl: {carried['merged_facets']:,} facets, "
                 + ("every shell closed and oriented" if carried["merged_closed"] else "not watertight")
                 if carried["merged_facets"] is not None else "no merged.stl"))
        for note in carried["notes"]:
            if "merged" in note or "thinned" in note:
                print(f"note: {note}")
        if args.json:
            Path(args.json).write_text(json.dumps(figures, indent=2) + "\n")
    finally:
        if not args.keep:
            shutil.rmtree(root, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
