"""Benchmark of fragment grouping (issue 7) on synthetic mixtures and corpus heaps (issue 16).

Mixtures: per seed, 3 to 8 objects of different shapes: the built-in vase / torso / slab
and five closed solids written here (tube, ring, brick, capsule, bowl), each scaled by its
own factor drawn log-uniformly in [0.5, 2] (synth normalises every object to a diagonal of
1, so the fragments are scaled copies), 4 to 10 pieces each, every object broken with its
own synth seed. Unsupervised: adjusted Rand index of `group_fragments` against the true
objects. Supervised: the PointNet classifier, classes = the eight shapes, trained on
objects broken with other synth seeds (and other scales), accuracy on every fragment of
the mixtures.

Every heap is "scanned at one resolution", as a real one is: every object is meshed at the
same absolute edge length (--edge; synth gets the `faces` that give spacing edge / scale in
the object's own units, and the file shapes are tessellated at that spacing), so the edge
length carries no object identity. The table's first part shows how far the achieved median
edge lengths still spread over the objects: thin walls narrower than a few edges (small
vases, bowls, tubes) force shorter edges on their fracture strips, and the shapes' own
tessellations differ a little on the original surface.

    python scripts/bench_group.py                 # full grid: 5 mixture seeds
    python scripts/bench_group.py --seeds 0 1 --train-seeds 1000 --no-supervised
    python scripts/bench_group.py --corpus smooth-noisy vessel-coarse --seeds 0 1 2   # heaps of corpus families
    python scripts/bench_group.py --fit 10 11 ... 29 40 ... 59 --fit-corpus FAMILY ... --describe-cache DIR
    python scripts/bench_group.py --assembly-only --assembly-faces 3000   # assemble --group vs alone vs heap

Corpus heaps (`--corpus`, `corpus_heap`): four objects of one `relicgpu.synth.corpus` family, each
its own solid, scaled and scanned at one resolution like the mixtures, 5-6 pieces each (about 22
fragments, the size of the issue's heaps of another generator).

The pair model of the unsupervised grouping (grouping.FEATURE_SCALES, PAIR_WEIGHTS) was fitted
with `--fit` on mixture seeds 10-29 and 40-59 and corpus heaps (seeds 0-19) of ten families, never
on the scored mixture seeds 0-4 nor on the corpus families smooth-noisy and vessel-coarse (kept out
of every fit and choice) nor on corpus seeds 20 and up. `--fit` also prints two cross-checks:
fitted on one half of the mixture seeds, the ARI on the other half; and each corpus fracture kind
left out of the fit in turn, the ARI on its families' heaps.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from relicgpu.heap import grouping as G  # noqa: E402
from relicgpu.heap import classifier as C  # noqa: E402
from relicgpu.heap import describe as D  # noqa: E402
from relicgpu import synth  # noqa: E402
from relicgpu.synth.generator import _AREA_GUESS, _AREA_GUESS_FILE  # noqa: E402
from relicgpu.heap.run import assemble_grouped  # noqa: E402
from relicgpu.io.fragment import Fragment  # noqa: E402

SHAPES = ("vase", "torso", "slab", "tube", "ring", "brick", "capsule", "bowl")
N_OBJECTS = (3, 5, 8, 4, 6, 7, 3, 8)  # per mixture seed, cycled
# One scanner resolution for the whole heap: edge length in units of a scale-1 object's diagonal
# (every object is meshed at EDGE / its scale in its own units). The smallest object (scale 0.5,
# 10 pieces) then has about 500 faces a piece, the largest (scale 2, 4 pieces) about 20000.
EDGE = 0.016


# Per shape, the bounding-box diagonal of the solid written below, in its own units: synth
# normalises it to 1, so a tessellation edge of e object units is e * RAW_DIAGONAL here.
RAW_DIAGONAL = {"tube": 1.9896, "ring": 2.2344, "brick": 1.1576, "capsule": 1.6359, "bowl": 1.5362}


def shape_source(shape: str, cache: Path, spacing: float) -> str:
    """A built-in synth shape, or the path of a closed solid written into cache/shapes,
    tessellated at about `spacing` object units (synth only refines a file's edges that are
    longer than 1.3 x its spacing: a finer file would keep its own, finer, resolution)."""
    if shape in synth.SHAPES:
        return shape
    e = spacing * RAW_DIAGONAL[shape]  # in the units of the file
    n = lambda length: max(8, int(math.ceil(length / e)))
    import manifold3d as mf
    import trimesh

    if shape == "tube":
        key, make = n(2 * math.pi * 0.46), lambda k: trimesh.creation.annulus(r_min=0.42, r_max=0.5, height=1.4,
                                                                              sections=k)
    elif shape == "ring":
        key = (n(2 * math.pi * 0.6), n(2 * math.pi * 0.18))
        make = lambda k: trimesh.creation.torus(major_radius=0.6, minor_radius=0.18, major_sections=k[0],
                                                minor_sections=k[1])
    elif shape == "brick":
        key, make = 0, lambda k: trimesh.creation.box((1.0, 0.5, 0.3))
    elif shape == "capsule":
        key = n(2 * math.pi * 0.3)
        make = lambda k: trimesh.creation.capsule(height=0.8, radius=0.3, count=[k, max(4, k // 2)])
    elif shape == "bowl":
        def make(k):
            shell = mf.Manifold.sphere(0.5, k) - mf.Manifold.sphere(0.45, k)
            shell = shell - mf.Manifold.cube((2, 2, 2), True).translate((0, 0, 1.1))
            m = shell.to_mesh()
            return trimesh.Trimesh(np.asarray(m.vert_properties)[:, :3], np.asarray(m.tri_verts))
        key = n(2 * math.pi * 0.5)
    else:
        raise ValueError(shape)
    path = cache / "shapes" / f"{shape}_{'x'.join(map(str, np.atleast_1d(key)))}.stl"
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        make(key).export(path)
    return str(path)


def synth_faces(shape: str, pieces: int, spacing: float) -> int:
    """The `faces` argument that makes synth.generate sample the object at `spacing` object units
    (synth.generate's own rule for its sampling density, inverted)."""
    if shape in synth.SHAPES:
        area, frac_area, c_orig, c_frac = _AREA_GUESS[shape]
    else:
        _, frac_area, c_orig, c_frac = _AREA_GUESS_FILE
        area = NORMALISED_AREA[shape]
    return int(round((c_orig * area + c_frac * frac_area * (pieces - 1) ** 0.75) / (pieces * spacing ** 2)))


# Surface area of the file shapes after synth's normalisation (diagonal 1), measured.
NORMALISED_AREA = {"tube": 2.160, "ring": 0.852, "brick": 1.418, "capsule": 0.983, "bowl": 1.520}


def broken(shape, scale, pieces, seed, edge, cache: Path | None):
    """The fragments of one object scaled by `scale` and sampled at `edge` absolute units (one
    scanner resolution for every object: edge / scale in the object's own units); cached as npz."""
    spacing = edge / scale
    faces = synth_faces(shape, pieces, spacing)
    if faces < 200:
        raise ValueError(f"{shape} x{scale:.2f} in {pieces} pieces at edge {edge}: {faces} faces a piece, "
                         f"synth needs 200; use a smaller --edge")
    src = shape_source(shape, cache or Path("/tmp/relicgpu_bench_honest"), spacing)
    path = None if cache is None else cache / f"{Path(src).stem}_{seed}_{pieces}_{faces}.npz"
    if path is not None and path.exists():
        d = np.load(path)
        frs = [Fragment(f"frag_{i:02d}", d[f"v{i}"], d[f"f{i}"]) for i in range(int(d["n"]))]
    else:
        frs = synth.generate(src, pieces=pieces, seed=seed, faces=faces, progress=False).fragments
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            np.savez(path, n=len(frs), **{f"v{i}": f.vertices for i, f in enumerate(frs)},
                     **{f"f{i}": f.faces for i, f in enumerate(frs)})
    S = np.diag([scale, scale, scale, 1.0])
    return [Fragment(f"{shape}{scale:.2f}_{seed}_{f.name}", f.transformed(S).vertices, f.faces) for f in frs]


def mixture(seed, edge, cache):
    rng = np.random.default_rng(seed)
    n = N_OBJECTS[seed % len(N_OBJECTS)]
    shapes = [SHAPES[i] for i in rng.choice(len(SHAPES), n, replace=False)]
    frags, labels = [], []
    for k, shape in enumerate(shapes):
        scale = float(np.exp(rng.uniform(np.log(0.5), np.log(2.0))))
        pieces = int(rng.integers(4, 11))
        frs = broken(shape, scale, pieces, 100 * seed + k, edge, cache)
        frags += frs
        labels += [shape] * len(frs)
    order = rng.permutation(len(frags))  # a heap has no order
    return [frags[i] for i in order], [labels[i] for i in order]


# Heaps of the corpus (relicgpu.synth.corpus, fractures this project's generator did not make):
# CORPUS_OBJECTS objects of one family (one material, one scanner), each its own solid (pebble,
# block, jar in turn; vessels for the vessel families) scaled log-uniformly in [0.5, 2], 5-6 pieces,
# CORPUS_FACES faces a piece at scale 1 and 5 pieces (one scanner resolution: x scale^2 x 5 / pieces;
# the coarse scans keep their few hundred).
CORPUS_OBJECTS = 4
CORPUS_FACES = 1500


def corpus_heap(family: str, seed: int):
    """The fragments of a heap of one corpus family and each one's object, in a random order."""
    import zlib
    from relicgpu.synth import corpus

    rng = np.random.default_rng([seed, zlib.crc32(family.encode())])
    frags, labels = [], []
    for k in range(CORPUS_OBJECTS):
        scale = float(np.exp(rng.uniform(np.log(0.5), np.log(2.0))))
        pieces = int(rng.integers(5, 7))
        faces = max(200, int(round(CORPUS_FACES * scale ** 2 * 5 / pieces)))
        r = corpus.generate(family, pieces=pieces, seed=1000 * seed + k, faces=faces)
        obj = f"{k}{r.params['solid']}{scale:.2f}"
        frags += [Fragment(f"{obj}_{f.name}", f.vertices * scale, f.faces) for f in r.fragments]
        labels += [obj] * len(r.fragments)
    order = rng.permutation(len(frags))
    return [frags[i] for i in order], [labels[i] for i in order]


def object_edges(frags, labels):
    """Per object of a heap: (median edge length on fracture faces, on the other faces), the
    faces told apart by relicgpu.pair.segment as the grouping sees them."""
    from relicgpu.backends import resolve
    from relicgpu.params import Params
    from relicgpu.pair.segment import segment

    per = {}
    for fr, lab in zip(frags, labels):
        v, f = fr.vertices, fr.faces.astype(np.int64)
        frac = segment(v, f, Params(), fr.size, resolve("numpy")).fracture_faces
        e = np.linalg.norm(v[f] - v[np.roll(f, 1, axis=1)], axis=2)  # (F, 3) the edges of each face
        a, b = per.setdefault(lab, ([], []))
        a.append(e[frac].ravel())
        b.append(e[~frac].ravel())
    return [(float(np.median(np.concatenate(a))), float(np.median(np.concatenate(b)))) for a, b in per.values()]


def _score(assemblies, fragments, objects, true_poses, touching):
    """Part accuracy (relicgpu.heap.evaluate) of one or several Assemblies over the whole mixture."""
    from relicgpu.heap.evaluate import score

    index = {f.name: i for i, f in enumerate(fragments)}
    poses, groups, used = [None] * len(fragments), [0] * len(fragments), []
    offset = 0
    for a in assemblies:
        for name, pose, g in zip(a.names, a.poses, a.groups):
            poses[index[name]], groups[index[name]] = pose, g + offset
        used += [(index[a.names[m.a]], index[a.names[m.b]], np.asarray(m.transform)) for m in a.matches if m.used]
        offset += max(a.groups) + 1
    return score([f.vertices for f in fragments], poses, groups, true_poses, touching, used, objects)


def bench_assembly(faces: int, pieces: int = 5) -> None:
    """assemble_grouped (what `relicgpu assemble --group` runs) vs assembling the heap at once vs
    each object alone (known answer), on one heap of a vase, a torso and a slab."""
    from relicgpu.heap.assembly import assemble

    fragments, objects, true_poses, touching = [], [], [], []
    for k, (shape, seed) in enumerate([("vase", 501), ("torso", 502), ("slab", 503)]):
        r = synth.generate(shape, pieces=pieces, seed=seed, faces=faces, progress=False)
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
    grouping, results = assemble_grouped(fragments, progress=False)
    t_grouped = time.perf_counter() - t0
    rows.append((f"assemble_grouped ({len(grouping.groups)} groups)", t_grouped,
                 _score([r for r in results if r is not None], fragments, objects, true_poses, touching)))
    t0 = time.perf_counter()
    whole = assemble(fragments, progress=False)
    rows.append(("whole heap at once", time.perf_counter() - t0, _score([whole], fragments, objects, true_poses,
                                                                       touching)))
    print(f"\nAssembly of a 3-object mixture (vase, torso, slab, synth seeds 501-503; {pieces} pieces of ~{faces} "
          f"faces each; "
          f"grouping ARI {G.adjusted_rand_index(objects, [grouping.labels[grouping.names.index(f.name)] for f in fragments]):.3f})")
    print(f"{'run':<34} {'seconds':>7} {'part acc':>8} {'pair prec':>9} {'pair rec':>8}")
    for name, t, sc in rows:
        print(f"{name:<34} {t:>7.1f} {sc.part_accuracy:>8.3f} {sc.pair_precision:>9.3f} {sc.pair_recall:>8.3f}")


def described(heap: str, seed: int, edge, cache, describe_cache: Path | None):
    """(descriptors, labels) of mixture `seed` (heap "synth") or of the corpus heap of family
    `heap`, kept as a pickle in describe_cache when given (stale once describe changes)."""
    import pickle

    path = None if describe_cache is None else describe_cache / f"{heap}_{seed}.pkl"
    if path is not None and path.exists():
        with open(path, "rb") as fh:
            return pickle.load(fh)
    frags, labels = mixture(seed, edge, cache) if heap == "synth" else corpus_heap(heap, seed)
    out = (D.describe_all(frags), labels)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "wb") as fh:
            pickle.dump(out, fh)
    return out


def heap_ari(heap, scales=None, weights=None, cut=None) -> float:
    """ARI of group_fragments' clustering of described (descriptors, labels) under a pair model."""
    d, labels = heap
    p = G.same_object_probability(G.pair_features(d, scales), weights)
    return G.adjusted_rand_index(labels, G.cluster(1 - p, None, G.LINK_CUT if cut is None else cut)[0])


def fit(seeds, edge, cache, corpus_families=(), corpus_seeds=(), describe_cache=None, cut=None) -> None:
    """Fit grouping.FEATURE_SCALES and PAIR_WEIGHTS on these mixture seeds and corpus heaps and
    print them, with two checks: fitted on one half of the mixture seeds, the ARI on the other
    half; and with each fracture kind of the corpus left out, the ARI on its families' heaps."""
    heaps = {}
    todo = [("synth", s) for s in seeds] + [(f, s) for f in corpus_families for s in corpus_seeds]
    for k, (h, s) in enumerate(todo):
        heaps[(h, s)] = described(h, s, edge, cache, describe_cache)
        print(f"described {h} seed {s} ({k + 1}/{len(todo)}): {len(heaps[(h, s)][1])} fragments", file=sys.stderr)

    def fitted(hs):
        scales = G.fit_feature_scales(hs)
        return scales, G.fit_pair_model(hs, scales)

    scales, w = fitted(list(heaps.values()))
    print(f"FEATURE_SCALES = ({', '.join(f'{x:.4f}' for x in scales)})")
    print(f"PAIR_WEIGHTS = ({', '.join(f'{x:.3f}' for x in w)})")
    print(f"# per knot block (z, then max(z - t, 0) for t in {G.Z_KNOTS}): {', '.join(D.FEATURE_NAMES)}, gaps of "
          f"{', '.join(D.GAP_NAMES)}; then patch_match, intercept")
    synth = [k for k in heaps if k[0] == "synth"]
    rest = [heaps[k] for k in heaps if k[0] != "synth"]
    half = len(synth) // 2
    cross = []
    for train, test in ((synth[:half], synth[half:]), (synth[half:], synth[:half])):
        if train and test:
            sc, wt = fitted([heaps[k] for k in train] + rest)
            cross += [heap_ari(heaps[k], sc, wt, cut) for k in test]
    if cross:
        print(f"two-fold ARI over mixture seeds {list(seeds)}: mean {np.mean(cross):.3f}, min {np.min(cross):.3f}")
    for kind in sorted({f.split("-")[0] for f in corpus_families}):
        sc, wt = fitted([v for k, v in heaps.items() if not k[0].startswith(kind + "-")])
        for f in [f for f in corpus_families if f.startswith(kind + "-")]:
            a = [heap_ari(heaps[(f, s)], sc, wt, cut) for s in corpus_seeds]
            print(f"{kind} left out: {f} ARI mean {np.mean(a):.3f}, min {np.min(a):.3f} over {len(a)} heaps")


def corpus_table(families, seeds) -> int:
    """ARI of group_fragments on heaps of corpus families, a row per family."""
    print(f"Unsupervised grouping of corpus heaps ({CORPUS_OBJECTS} objects of one family, 5-6 pieces each), "
          f"seeds {list(seeds)}")
    print(f"{'family':>15} {'heaps':>5} {'frags':>5} {'groups':>6} {'ARI mean':>8} {'ARI min':>7} {'group s':>7}")
    for family in families:
        aris, groups, frags, secs = [], [], [], []
        for s in seeds:
            fr, labels = corpus_heap(family, s)
            t0 = time.perf_counter()
            g = G.group_fragments(fr)
            secs.append(time.perf_counter() - t0)
            aris.append(G.adjusted_rand_index(labels, g.labels))
            groups.append(int(g.labels.max()) + 1)
            frags.append(len(fr))
            print(f"{family} seed {s}: {len(fr)} fragments -> {groups[-1]} groups, ARI {aris[-1]:.3f}", file=sys.stderr)
        print(f"{family:>15} {len(seeds):>5} {np.mean(frags):>5.1f} {np.mean(groups):>6.1f} {np.mean(aris):>8.3f} "
              f"{np.min(aris):>7.3f} {np.median(secs):>7.1f}", flush=True)
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    ap.add_argument("--train-seeds", type=int, nargs="+", default=[1000, 1001, 1002, 1003, 1004])
    ap.add_argument("--train-pieces", type=int, default=7)
    ap.add_argument("--edge", type=float, default=EDGE,
                    help=f"scan resolution, one for every object: edge length in units of a scale-1 object's "
                         f"diagonal (default: {EDGE})")
    ap.add_argument("--epochs", type=int, default=100)
    ap.add_argument("--classifier-seed", type=int, default=0, help="torch seed of the PointNet's training")
    ap.add_argument("--cache", default="/tmp/relicgpu_bench_honest", help="synth cache ('' for none)")
    ap.add_argument("--no-supervised", action="store_true")
    ap.add_argument("--fit", type=int, nargs="+", default=None, metavar="SEED",
                    help="fit the pair model on these mixture seeds, print it, and stop")
    ap.add_argument("--corpus", nargs="+", default=None, metavar="FAMILY",
                    help="score heaps of these relicgpu.synth.corpus families at --seeds instead (see corpus_heap)")
    ap.add_argument("--fit-corpus", nargs="+", default=(), metavar="FAMILY",
                    help="with --fit: also fit on heaps of these corpus families")
    ap.add_argument("--fit-corpus-seeds", type=int, nargs="+", default=list(range(20)))
    ap.add_argument("--describe-cache", default="",
                    help="with --fit: keep each heap's descriptors here (stale once relicgpu.heap.describe changes)")
    ap.add_argument("--assembly", action="store_true",
                    help="also: assemble a 3-object mixture with grouping, without, and each object alone")
    ap.add_argument("--assembly-faces", type=int, default=2000, help="faces per fragment there (default: 2000)")
    ap.add_argument("--assembly-pieces", type=int, default=5, help="pieces per object there (default: 5)")
    ap.add_argument("--assembly-only", action="store_true", help="only the assembly comparison")
    args = ap.parse_args(argv)
    cache = Path(args.cache) if args.cache else None
    if args.fit:
        fit(args.fit, args.edge, cache, args.fit_corpus, args.fit_corpus_seeds,
            Path(args.describe_cache) if args.describe_cache else None)
        return 0
    if args.corpus:
        return corpus_table(args.corpus, args.seeds)

    if args.assembly_only:
        bench_assembly(args.assembly_faces, args.assembly_pieces)
        return 0
    rows = []
    mixtures = []
    edges = []
    for s in args.seeds:
        t0 = time.perf_counter()
        frags, labels = mixture(s, args.edge, cache)
        t1 = time.perf_counter()
        g = G.group_fragments(frags)
        t2 = time.perf_counter()
        ari = G.adjusted_rand_index(labels, g.labels)
        mixtures.append((frags, labels))
        edges += object_edges(frags, labels)
        rows.append((s, len(set(labels)), len(frags), int(g.labels.max()) + 1, ari, t1 - t0, t2 - t1))
        print(f"seed {s}: {len(set(labels))} objects, {len(frags)} fragments -> {int(g.labels.max()) + 1} groups, "
              f"ARI {ari:.3f} ({t2 - t1:.1f} s)", file=sys.stderr)

    print(f"\nScan resolution: median edge length per object / --edge, on its fracture and original faces "
          f"(relicgpu.pair.segment), over the objects of all mixtures")
    print(f"{'surface':>8} {'min':>6} {'q25':>6} {'median':>6} {'q75':>6} {'max':>6}")
    for name, col in (("fracture", 0), ("original", 1)):
        x = np.array([e[col] for e in edges]) / args.edge
        print(f"{name:>8} " + " ".join(f"{q:>6.3f}" for q in np.nanquantile(x, [0, 0.25, 0.5, 0.75, 1.0])))
    print(f"\nUnsupervised grouping (pair model on feature z, quartile-interval gaps and fracture-patch match, "
          f"average linkage cut at "
          f"p = {1 - G.LINK_CUT:.2g}, leftovers at p = {1 - G.LEFTOVER_CUT:.2g})")
    print(f"{'seed':>4} {'objects':>7} {'frags':>5} {'groups':>6} {'ARI':>6} {'synth s':>7} {'group s':>7}")
    for s, no, nf, ng, ari, ts, tg in rows:
        print(f"{s:>4} {no:>7} {nf:>5} {ng:>6} {ari:>6.3f} {ts:>7.1f} {tg:>7.1f}")
    aris = [r[4] for r in rows]
    print(f"mean ARI {np.mean(aris):.3f}, min {np.min(aris):.3f} (goal: >= 0.9)")

    if args.assembly:
        bench_assembly(args.assembly_faces, args.assembly_pieces)
    if args.no_supervised:
        return 0
    t0 = time.perf_counter()
    train_f, train_l = [], []
    for ts in args.train_seeds:
        rng = np.random.default_rng(ts)
        for k, shape in enumerate(SHAPES):
            scale = float(np.exp(rng.uniform(np.log(0.5), np.log(2.0))))
            frs = broken(shape, scale, args.train_pieces, ts * 10 + k, args.edge, cache)
            train_f += frs
            train_l += [shape] * len(frs)
    t1 = time.perf_counter()
    clf = C.train_classifier(train_f, train_l, epochs=args.epochs, seed=args.classifier_seed, progress=True)
    t2 = time.perf_counter()
    print(f"\nSupervised PointNet: trained on {len(train_f)} fragments of {len(SHAPES)} shapes, synth seeds "
          f"{args.train_seeds} x10+k ({t1 - t0:.1f} s synth, {t2 - t1:.1f} s train, {args.epochs} epochs, "
          f"seed {args.classifier_seed})")
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
