"""Fracture-segmentation recall and precision per family (issue 16, item 2).

Area-weighted face recall / precision of `relicgpu.segment` against each generator's labels, a row
per family: relicgpu.synth shapes (vase, torso, slab; --synth-noise), relicgpu.corpus families (where
that module is present) and the ../shared/realdata Blender sets (corpus.realdata). Usage:

    .venv/bin/python scripts/bench_segment.py [--seeds 3] [--only voronoi,vessel] [--verbose]

Seeds alternate 2 and 4 pieces (synth: 2 and 5). Target: recall >= 0.9 and precision >= 0.8 on every row.
"""
import argparse
import time

import numpy as np

from relicgpu import synth
from relicgpu.backends import numpy as ref
from relicgpu.params import Params
from relicgpu.segment import segment


def cases(seeds, synth_noise, only):
    for shape in ("vase", "torso", "slab"):
        for s in range(seeds):
            for noise in synth_noise:
                yield f"synth-{shape}-noise{noise}", lambda shape=shape, s=s, noise=noise: synth.generate(
                    shape, pieces=2 if s % 2 == 0 else 5, seed=s, faces=4000, noise=noise)
    try:
        from relicgpu import corpus
    except ImportError:
        return
    for fam in corpus.FAMILIES:
        for s in range(seeds):
            yield f"corpus-{fam}", lambda fam=fam, s=s: corpus.generate(fam, pieces=2 if s % 2 == 0 else 4, seed=s)
    for name in corpus.REALDATA_SETS:
        yield f"real-{name}", lambda name=name: corpus.realdata(name)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--synth-noise", default="0.0005,0.002")
    ap.add_argument("--only", default="")
    ap.add_argument("--verbose", action="store_true")
    a = ap.parse_args()
    only = [x for x in a.only.split(",") if x]
    stats = {}
    for fam, make in cases(a.seeds, [float(x) for x in a.synth_noise.split(",")], only):
        if only and not any(o in fam for o in only):
            continue
        try:
            r = make()
        except FileNotFoundError as e:
            print(f"{fam}: skipped ({e})")
            continue
        for frag, lab in zip(r.fragments, r.fracture_faces):
            v, f = np.asarray(frag.vertices, np.float64), np.asarray(frag.faces, np.int64)
            t = time.perf_counter()
            pred = segment(v, f, Params(), frag.size, ref).fracture_faces
            dt = time.perf_counter() - t
            area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
            lab = np.asarray(lab, bool)
            row = np.array([area[pred & lab].sum(), area[pred].sum(), area[lab].sum(), dt, 1.0])
            stats[fam] = stats.get(fam, 0) + row
            if a.verbose:
                print(f"  {fam} {frag.name} faces {len(f)} recall {row[0] / max(row[2], 1e-12):.2f} "
                      f"precision {row[0] / max(row[1], 1e-12):.2f}")
    print(f"{'family':40s} {'recall':>7s} {'prec':>7s} {'pieces':>6s} {'s/piece':>8s}")
    for fam, (tp, pa, ta, dt, n) in stats.items():
        r, p = tp / max(ta, 1e-12), tp / max(pa, 1e-12)
        print(f"{fam:40s} {r:7.3f} {p:7.3f} {int(n):6d} {dt / n:8.3f}{'' if r >= 0.9 and p >= 0.8 else '  <--'}")


if __name__ == "__main__":
    main()
