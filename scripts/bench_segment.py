"""Fracture-segmentation recall and precision per family (issue 16, item 2).

Area-weighted face recall / precision of `relicgpu.pair.segment` against each generator's labels, a row
per family and a column pair per `Params.segmentation` method: relicgpu.synth shapes (vase, torso,
slab; --synth-noise, 0 being the assembly grid's), relicgpu.synth.corpus families (where that module is
present) and the ../shared/realdata Blender sets (corpus.realdata). Families marked * were held out
when the "hybrid" thresholds (segment.HYBRID_*, segment_cues.MODE_GAP and crease_regions' wide
creases) were chosen: voronoi-*, vessel-* and the Blender sets (the earlier "regions" fit held out
smooth-noisy, vessel-coarse and the cylinder); "overall" is the mean over the corpus and real rows.
Usage:

    .venv/bin/python scripts/bench_segment.py [--seeds 3] [--only voronoi,vessel] [--methods roughness,hybrid]

Seeds alternate 2 and 4 pieces (synth: 2 and 5); --pieces N gives every object N. Target: recall >= 0.9 and precision >= 0.8 on every row.
"""
import argparse
import time

import numpy as np

from relicgpu import synth
from relicgpu.backends import numpy as ref
from relicgpu.params import Params
from relicgpu.pair.segment import segment

HELD_OUT = ("voronoi", "vessel", "real-")  # untouched by the choice of the hybrid thresholds


def cases(seeds, synth_noise, only, pieces=0):
    for shape in ("vase", "torso", "slab"):
        for s in range(seeds):
            for noise in synth_noise:
                yield f"synth-{shape}-noise{noise}", lambda shape=shape, s=s, noise=noise: synth.generate(
                    shape, pieces=pieces or (2 if s % 2 == 0 else 5), seed=s, faces=4000, noise=noise)
    try:
        from relicgpu.synth import corpus
    except ImportError:
        return
    for fam in corpus.FAMILIES:
        for s in range(seeds):
            yield f"corpus-{fam}", lambda fam=fam, s=s: corpus.generate(fam, pieces=pieces or (2 if s % 2 == 0 else 4),
                                                                      seed=s)
    for name in corpus.REALDATA_SETS:
        yield f"real-{name}", lambda name=name: corpus.realdata(name)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--synth-noise", default="0,0.0005,0.002")
    ap.add_argument("--only", default="")
    ap.add_argument("--methods", default="roughness,regions,union,hybrid")
    ap.add_argument("--verbose", action="store_true")
    ap.add_argument("--pieces", type=int, default=0,
                    help="pieces per synth/corpus object (0: alternate 2 and 5 / 2 and 4); many pieces give inner, mostly-fracture pieces")
    a = ap.parse_args()
    only = [x for x in a.only.split(",") if x]
    methods = a.methods.split(",")
    stats = {}
    for fam, make in cases(a.seeds, [float(x) for x in a.synth_noise.split(",")], only, a.pieces):
        if only and not any(o in fam for o in only):
            continue
        try:
            r = make()
        except FileNotFoundError as e:
            print(f"{fam}: skipped ({e})")
            continue
        for frag, lab in zip(r.fragments, r.fracture_faces):
            row = np.stack([_score(frag, np.asarray(lab, bool), m) for m in methods])
            stats[fam] = stats.get(fam, 0) + row
            if a.verbose:
                print(f"  {fam} {frag.name} faces {len(frag.faces)} " + " ".join(
                    f"{m} {x[0] / max(x[2], 1e-12):.2f}/{x[0] / max(x[1], 1e-12):.2f}" for m, x in zip(methods, row)))
    _table(stats, methods)


def _score(frag, lab, method):
    """[true-positive area, predicted area, true area, seconds, 1] of one fragment."""
    v, f = np.asarray(frag.vertices, np.float64), np.asarray(frag.faces, np.int64)
    t = time.perf_counter()
    pred = segment(v, f, Params(segmentation=method), frag.size, ref).fracture_faces
    dt = time.perf_counter() - t
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    return np.array([area[pred & lab].sum(), area[pred].sum(), area[lab].sum(), dt, 1.0])


def _table(stats, methods):
    print(f"{'family':36s}" + "".join(f" {m[:9]:>9s} rec  prec  s/pc" for m in methods))
    groups = {"overall": [], "held-out": []}
    for fam, rows in stats.items():
        held = any(h in fam for h in HELD_OUT)
        cells = []
        for tp, pa, ta, dt, n in rows:
            r, p = tp / max(ta, 1e-12), tp / max(pa, 1e-12)
            cells.append((r, p))
        line = "".join(f"      {r:5.3f} {p:5.3f} {row[3] / row[4]:5.2f}{' ' if r >= 0.9 and p >= 0.8 else '<'}"
                       for (r, p), row in zip(cells, rows))
        print(f"{fam + (' *' if held else ''):36s}{line}")
        if not fam.startswith("synth"):
            groups["overall"].append(cells)
        if held:
            groups["held-out"].append(cells)
    for name, cells in groups.items():
        if cells:
            mean = np.mean(np.array(cells), axis=0)
            print(f"{'mean ' + name:36s}" + "".join(f"      {r:5.3f} {p:5.3f}       " for r, p in mean))


if __name__ == "__main__":
    main()
