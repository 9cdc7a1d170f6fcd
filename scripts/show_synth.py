"""Render a synthetic broken object to a PNG: pieces put back by their truth poses,
then exploded a little, each piece its own colour, fracture faces darker.

    python scripts/show_synth.py --shape vase --pieces 5 --seed 0 -o synth_vase.png
    python scripts/show_synth.py --from OUT -o out.png     # a directory written by `relicgpu synth`
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from relicgpu import synth  # noqa: E402
from relicgpu.io.load import load_fragment  # noqa: E402

COLOURS = np.array([
    [0.90, 0.45, 0.25], [0.30, 0.60, 0.85], [0.45, 0.75, 0.35], [0.85, 0.75, 0.30], [0.65, 0.45, 0.80],
    [0.35, 0.80, 0.75], [0.90, 0.55, 0.65], [0.60, 0.60, 0.60], [0.75, 0.50, 0.30], [0.40, 0.45, 0.85],
])


def placed_back_from_dir(out: Path):
    truth = synth.read_truth(out)
    labels = synth.load_labels(out) if (out / "labels.npz").exists() else {}
    meshes = []
    for entry in truth["fragments"]:
        frag = load_fragment(out / entry["file"]).transformed(entry["pose"])
        meshes.append((frag.vertices, frag.faces.astype(np.int64), labels.get(entry["name"])))
    return meshes, f"{out} ({len(meshes)} fragments)"


def placed_back_from_result(result: synth.SynthResult):
    meshes = [(f.vertices, f.faces.astype(np.int64), lab)
              for f, lab in zip(result.placed_back(), result.fracture_faces)]
    p = result.params
    title = (f"{result.shape}, {p['pieces']} pieces, seed {result.seed}, ~{p['faces']} faces, "
             f"roughness {p['roughness']}, noise {p['noise']}; "
             + (f"touching {result.touching}" if len(result.touching) <= 6 else f"{len(result.touching)} touching pairs"))
    return meshes, title


def draw(ax, meshes, explode, elev, azim, title):
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    centre = np.concatenate([m[0] for m in meshes]).mean(axis=0)
    light = np.array([0.4, -0.5, 0.75])
    light /= np.linalg.norm(light)
    polys, colours = [], []
    for k, (v, f, lab) in enumerate(meshes):
        offset = explode * (v.mean(axis=0) - centre)
        tri = v[f] + offset
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
        shade = 0.35 + 0.65 * np.abs(n @ light)  # two-sided: inner walls of the vase show too
        base = np.tile(COLOURS[k % len(COLOURS)], (len(f), 1))
        if lab is not None:
            base[lab] *= 0.55  # fracture faces darker
        polys.append(tri)
        colours.append(np.clip(base * shade[:, None], 0, 1))
    coll = Poly3DCollection(np.concatenate(polys), facecolors=np.concatenate(colours), edgecolors="none",
                            linewidths=0)
    ax.add_collection3d(coll)
    allv = np.concatenate([p.reshape(-1, 3) for p in polys])
    lo, hi = allv.min(0), allv.max(0)
    mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo).max()
    ax.set_xlim(mid[0] - half, mid[0] + half)
    ax.set_ylim(mid[1] - half, mid[1] + half)
    ax.set_zlim(mid[2] - half, mid[2] + half)
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=elev, azim=azim)
    ax.set_axis_off()
    ax.set_title(title, fontsize=9)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--from", dest="source", type=Path, help="read a directory written by `relicgpu synth`")
    ap.add_argument("--shape", default="vase")
    ap.add_argument("--pieces", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--faces", type=int, default=4000)
    ap.add_argument("--noise", type=float, default=0.0)
    ap.add_argument("--roughness", type=float, default=0.02)
    ap.add_argument("--explode", type=float, default=0.5, help="move pieces out by this fraction of their "
                                                               "centroid's distance from the object centre")
    ap.add_argument("-o", "--out", type=Path, default=Path("synth.png"))
    args = ap.parse_args(argv)

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if args.source:
        meshes, title = placed_back_from_dir(args.source)
    else:
        t0 = time.perf_counter()
        result = synth.generate(args.shape, pieces=args.pieces, seed=args.seed, faces=args.faces, noise=args.noise,
                                roughness=args.roughness)
        print(f"generated in {time.perf_counter() - t0:.2f} s", file=sys.stderr)
        meshes, title = placed_back_from_result(result)
    fig = plt.figure(figsize=(16, 5.6))
    views = [(0.0, 20, -60, "put back"), (args.explode, 20, -60, "exploded"), (args.explode, 65, 30, "exploded, from above")]
    for k, (explode, elev, azim, label) in enumerate(views):
        draw(fig.add_subplot(1, 3, k + 1, projection="3d"), meshes, explode, elev, azim, label)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(args.out, dpi=100)
    print(f"wrote {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
