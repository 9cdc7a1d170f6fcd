"""Benchmark of fragment grouping (issue 7) on synthetic mixtures.

Mixtures: per seed, 3 to 8 objects of different shapes: the built-in vase / torso / slab
and five closed solids written here (tube, ring, brick, capsule, bowl), each scaled by its
own factor drawn log-uniformly in [0.5, 2] (synth normalises every object to a diagonal of
1, so the fragments are scaled copies), 4 to 10 pieces each, every object broken with its
own synth seed. Unsupervised: adjusted Rand index of `group_fragments` against the true
objects. Supervised: the PointNet classifier, classes = the eight shapes, trained on
objects broken with other synth seeds (and other scales), accuracy on every fragment of
the mixtures.

    python scripts/bench_group.py                 # full grid: 5 mixture seeds
    python scripts/bench_group.py --seeds 0 1 --train-seeds 1000
    python scripts/bench_group.py --fit 10 11 12 13 14 15 16 17 18 19   # refit grouping.PAIR_WEIGHTS

The pair model of the unsupervised grouping (grouping.PAIR_WEIGHTS) was fitted with `--fit` on
mixture seeds 10-19, never on the scored seeds; `--fit` also prints a cross-check: fitted on
one half of those seeds, the ARI on the other half.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from relicgpu import grouping as G  # noqa: E402
from relicgpu import synth  # noqa: E402
from relicgpu.io import Fragment  # noqa: E402

SHAPES = ("vase", "torso", "slab", "tube", "ring", "brick", "capsule", "bowl")
N_OBJECTS = (3, 5, 8, 4, 6, 7, 3, 8)  # per mixture seed, cycled


def shape_source(shape: str, cache: Path) -> str:
    """A built-in synth shape, or the path of a closed solid written into cache/shapes."""
    if shape in synth.SHAPES:
        return shape
    path = cache / "shapes" / f"{shape}.stl"
    if path.exists():
        return str(path)
    import manifold3d as mf
    import trimesh

    if shape == "tube":
        mesh = trimesh.creation.annulus(r_min=0.42, r_max=0.5, height=1.4, sections=96)
    elif shape == "ring":
        mesh = trimesh.creation.torus(major_radius=0.6, minor_radius=0.18, major_sections=96, minor_sections=32)
    elif shape == "brick":
        mesh = trimesh.creation.box((1.0, 0.5, 0.3))
    elif shape == "capsule":
        mesh = trimesh.creation.capsule(height=0.8, radius=0.3, count=[48, 48])
    elif shape == "bowl":
        shell = mf.Manifold.sphere(0.5, 96) - mf.Manifold.sphere(0.45, 96)
        shell = shell - mf.Manifold.cube((2, 2, 2), True).translate((0, 0, 1.1))
        m = shell.to_mesh()
        mesh = trimesh.Trimesh(np.asarray(m.vert_properties)[:, :3], np.asarray(m.tri_verts))
    else:
        raise ValueError(shape)
    path.parent.mkdir(parents=True, exist_ok=True)
    mesh.export(path)
    return str(path)


def broken(shape, scale, pieces, seed, faces, cache: Path | None):
    """The fragments of one object, scaled; cached as npz (synth is the slow part)."""
    path = None if cache is None else cache / f"{shape}_{seed}_{pieces}_{faces}.npz"
    if path is not None and path.exists():
        d = np.load(path)
        frs = [Fragment(f"frag_{i:02d}", d[f"v{i}"], d[f"f{i}"]) for i in range(int(d["n"]))]
    else:
        frs = synth.generate(shape_source(shape, cache), pieces=pieces, seed=seed, faces=faces,
                             progress=False).fragments
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            np.savez(path, n=len(frs), **{f"v{i}": f.vertices for i, f in enumerate(frs)},
                     **{f"f{i}": f.faces for i, f in enumerate(frs)})
    S = np.diag([scale, scale, scale, 1.0])
    return [Fragment(f"{shape}{scale:.2f}_{seed}_{f.name}", f.transformed(S).vertices, f.faces) for f in frs]


def mixture(seed, faces, cache):
    rng = np.random.default_rng(seed)
    n = N_OBJECTS[seed % len(N_OBJECTS)]
    shapes = [SHAPES[i] for i in rng.choice(len(SHAPES), n, replace=False)]
    frags, labels = [], []
    for k, shape in enumerate(shapes):
        scale = float(np.exp(rng.uniform(np.log(0.5), np.log(2.0))))
        pieces = int(rng.integers(4, 11))
        frs = broken(shape, scale, pieces, 100 * seed + k, faces, cache)
        frags += frs
        labels += [shape] * len(frs)
    order = rng.permutation(len(frags))  # a heap has no order
    return [frags[i] for i in order], [labels[i] for i in order]


def _score(assemblies, fragments, objects, true_poses, touching):
    """Part accuracy (relicgpu.evaluate) of one or several Assemblies over the whole mixture."""
    from relicgpu.evaluate import score

    index = {f.name: i for i, f in enumerate(fragments)}
    poses, groups, used = [None] * len(fragments), [0] * len(fragments), []
    offset = 0
    for a in assemblies:
        for name, pose, g in zip(a.names, a.poses, a.groups):
            poses[index[name]], groups[index[name]] = pose, g + offset
        used += [(index[a.names[m.a]], index[a.names[m.b]], np.asarray(m.transform)) for m in a.matches if m.used]
        offset += max(a.groups) + 1
    return score([f.vertices for f in fragments], poses, groups, true_poses, touching, used, objects)


def bench_assembly(faces: int) -> None:
    """assemble_grouped vs assembling the heap at once vs each object alone (known answer)."""
    from relicgpu.assembly import assemble

    fragments, objects, true_poses, touching = [], [], [], []
    for k, (shape, seed) in enumerate([("vase", 501), ("torso", 502), ("slab", 503)]):
        r = synth.generate(shape, pieces=4, seed=seed, faces=faces, progress=False)
        base = len(fragments)
        fragments += [Fragment(f"o{k}_{f.name}", f.vertices, f.faces) for f in r.fragments]
        objects += [k] * len(r.fragments)
        true_poses += list(r.poses)
        touching += [(base + i, base + j) for i, j in r.touching]
    rows = []
    t0 = time.perf_counter()
    alone = [assemble([f for f, o in zip(fragments, objects) if o == k], progress=False) for k in range(3)]
    rows.append(("each object alone (truth)", time.perf_counter() - t0, _score(alone, fragments, objects, true_poses,
                                                                             touching)))
    t0 = time.perf_counter()
    grouping, results = G.assemble_grouped(fragments, progress=False)
    t_grouped = time.perf_counter() - t0
    rows.append((f"assemble_grouped ({len(grouping.groups)} groups)", t_grouped,
                 _score([r for r in results if r is not None], fragments, objects, true_poses, touching)))
    t0 = time.perf_counter()
    whole = assemble(fragments, progress=False)
    rows.append(("whole heap at once", time.perf_counter() - t0, _score([whole], fragments, objects, true_poses,
                                                                       touching)))
    print(f"\nAssembly of a 3-object mixture (vase, torso, slab; 4 pieces of ~{faces} faces each; "
          f"grouping ARI {G.adjusted_rand_index(objects, [grouping.labels[grouping.names.index(f.name)] for f in fragments]):.3f})")
    print(f"{'run':<34} {'seconds':>7} {'part acc':>8} {'pair prec':>9} {'pair rec':>8}")
    for name, t, sc in rows:
        print(f"{name:<34} {t:>7.1f} {sc.part_accuracy:>8.3f} {sc.pair_precision:>9.3f} {sc.pair_recall:>8.3f}")


def fit(seeds, faces, cache) -> None:
    """Fit the pair models (with and without scan resolution) on these mixture seeds and print them."""
    heaps = []
    for s in seeds:
        frags, labels = mixture(s, faces, cache)
        heaps.append((G.describe_all(frags), labels, frags))
    half = len(heaps) // 2
    for resolution, name in ((True, "PAIR_WEIGHTS"), (False, "PAIR_WEIGHTS_NO_RESOLUTION")):
        w = G.fit_pair_model([(d, l) for d, l, _ in heaps], resolution)
        cross = []
        if half >= 1:
            for train, test in ((heaps[:half], heaps[half:]), (heaps[half:], heaps[:half])):
                wt = G.fit_pair_model([(d, l) for d, l, _ in train], resolution)
                for d, l, _ in test:
                    L = float(np.median([x.size for x in d]))
                    v, sg = (np.stack(a) for a in zip(*(x.evidence(L) for x in d)))
                    p = G.same_object_probability(v, sg, resolution, weights=wt)
                    cross.append(G.adjusted_rand_index(l, G.cluster(1 - p)[0]))  # at G.LINK_CUT
        print(f"{name} = ({', '.join(f'{x:.3f}' for x in w)})  # {', '.join(G.FEATURE_NAMES[:len(w) - 1])}, "
              f"intercept; two-fold ARI over seeds {list(seeds)}: mean {np.mean(cross):.3f}, min {np.min(cross):.3f}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    ap.add_argument("--train-seeds", type=int, nargs="+", default=[1000, 1001, 1002, 1003, 1004])
    ap.add_argument("--train-pieces", type=int, default=7)
    ap.add_argument("--faces", type=int, default=600, help="faces per fragment (default: 600)")
    ap.add_argument("--epochs", type=int, default=100)
    ap.add_argument("--cache", default="/tmp/relicgpu_bench_group", help="synth cache ('' for none)")
    ap.add_argument("--no-supervised", action="store_true")
    ap.add_argument("--no-resolution", action="store_true",
                    help="unsupervised grouping without the scan-resolution features")
    ap.add_argument("--fit", type=int, nargs="+", default=None, metavar="SEED",
                    help="fit the pair model on these mixture seeds, print it, and stop")
    ap.add_argument("--assembly", action="store_true",
                    help="also: assemble a 3-object mixture with grouping, without, and each object alone")
    ap.add_argument("--assembly-faces", type=int, default=2000, help="faces per fragment there (default: 2000)")
    args = ap.parse_args(argv)
    cache = Path(args.cache) if args.cache else None
    if args.fit:
        fit(args.fit, args.faces, cache)
        return 0

    rows = []
    mixtures = []
    for s in args.seeds:
        t0 = time.perf_counter()
        frags, labels = mixture(s, args.faces, cache)
        t1 = time.perf_counter()
        g = G.group_fragments(frags, resolution=not args.no_resolution)
        t2 = time.perf_counter()
        ari = G.adjusted_rand_index(labels, g.labels)
        mixtures.append((frags, labels))
        rows.append((s, len(set(labels)), len(frags), int(g.labels.max()) + 1, ari, t1 - t0, t2 - t1))
        print(f"seed {s}: {len(set(labels))} objects, {len(frags)} fragments -> {int(g.labels.max()) + 1} groups, "
              f"ARI {ari:.3f} ({t2 - t1:.1f} s)", file=sys.stderr)

    print(f"\nUnsupervised grouping (pair model on descriptor z{'' if args.no_resolution else ' with scan resolution'}"
          f", average linkage cut at p = {1 - G.LINK_CUT:.2g})")
    print(f"{'seed':>4} {'objects':>7} {'frags':>5} {'groups':>6} {'ARI':>6} {'synth s':>7} {'group s':>7}")
    for s, no, nf, ng, ari, ts, tg in rows:
        print(f"{s:>4} {no:>7} {nf:>5} {ng:>6} {ari:>6.3f} {ts:>7.1f} {tg:>7.1f}")
    aris = [r[4] for r in rows]
    print(f"mean ARI {np.mean(aris):.3f}, min {np.min(aris):.3f} (goal: >= 0.9)")

    if args.assembly:
        bench_assembly(args.assembly_faces)
    if args.no_supervised:
        return 0
    t0 = time.perf_counter()
    train_f, train_l = [], []
    for ts in args.train_seeds:
        rng = np.random.default_rng(ts)
        for k, shape in enumerate(SHAPES):
            scale = float(np.exp(rng.uniform(np.log(0.5), np.log(2.0))))
            frs = broken(shape, scale, args.train_pieces, ts * 10 + k, args.faces, cache)
            train_f += frs
            train_l += [shape] * len(frs)
    t1 = time.perf_counter()
    clf = G.train_classifier(train_f, train_l, epochs=args.epochs, progress=True)
    t2 = time.perf_counter()
    print(f"\nSupervised PointNet: trained on {len(train_f)} fragments of {len(SHAPES)} shapes, synth seeds "
          f"{args.train_seeds} x10+k ({t1 - t0:.1f} s synth, {t2 - t1:.1f} s train, {args.epochs} epochs)")
    print(f"{'seed':>4} {'frags':>5} {'accuracy':>8}")
    correct = total = 0
    confusions = {}
    for s, (frags, labels) in zip(args.seeds, mixtures):
        pred, _ = clf.predict(frags)
        ok = sum(p == l for p, l in zip(pred, labels))
        for p, l in zip(pred, labels):
            if p != l:
                confusions[(l, p)] = confusions.get((l, p), 0) + 1
        correct += ok
        total += len(labels)
        print(f"{s:>4} {len(labels):>5} {ok / len(labels):>8.3f}")
    print(f"held-out accuracy {correct / total:.3f} over {total} fragments (goal: >= 0.95); "
          f"predict {time.perf_counter() - t2:.1f} s")
    if confusions:
        print("errors (true -> predicted: count): " + ", ".join(f"{a} -> {b}: {n}" for (a, b), n in
                                                             sorted(confusions.items(), key=lambda t: -t[1])))
    return 0


if __name__ == "__main__":
    sys.exit(main())
