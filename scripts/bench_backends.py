#!/usr/bin/env python
"""Benchmark the compute backends on the kernel families and on match_pair.

For each family and size: the median wall time per backend (numpy arrays in,
numpy arrays out: transfers and host preparation included) and the speed-up over
the NumPy reference, printed as a table, saved as JSON and drawn as log-log
plots (PNG). Extra rows, marked as baselines:
  scipy-ckdtree-all-cores  cKDTree(workers=-1), the CPU goal for nearest neighbours
  numpy-bitparallel        a vectorised NumPy bit-parallel LCS (this script only),
                           a fairer CPU baseline than the reference's Python DP loop
Cases whose estimated time exceeds --max-seconds are skipped and listed as such.
The ppf section votes with point-pair tables built as match_pair builds them, from the
fracture samples of a synthetic vase broken in two (prepared once, a few seconds).

    python scripts/bench_backends.py                       # all backends here, all sections
    python scripts/bench_backends.py --backends warp-cuda:0,opencl --sections lcs,nn --out bench-results
"""
from __future__ import annotations

import argparse
import functools
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from relicgpu.backends import available_backends, get_backend  # noqa: E402
from relicgpu.backends import numpy as reference  # noqa: E402
from relicgpu.backends.base import DeviceTiming  # noqa: E402

SECTIONS = ("normals", "curvature", "lcs", "nn", "cov", "ppf", "match")
SIZES = {
    "normals": [10_000, 100_000, 1_000_000],  # faces
    "curvature": [1_000, 10_000, 100_000],  # contour points
    "lcs": [(100, 128), (1_000, 256), (10_000, 512)],  # (pairs, length)
    "nn": [10_000, 100_000, 1_000_000],  # source = target points
    "cov": [10_000, 100_000, 1_000_000],  # point pairs
    # (model points, scene points, every third a reference); (800, 800) is match_pair's (Params.ppf_points)
    "ppf": [(500, 450), (800, 800), (1_000, 1_200), (2_000, 2_100)],
}
QUICK_SIZES = {
    "normals": [10_000, 100_000],
    "curvature": [1_000, 10_000],
    "lcs": [(100, 128), (400, 256)],
    "nn": [10_000, 100_000],
    "cov": [10_000, 100_000],
    "ppf": [(300, 300)],
}
# The paper's Table 1: vertex counts of the two fragments of each pair.
TABLE1_PAIRS = [(8046, 10314), (5142, 4408), (7250, 5692), (15064, 20956), (12476, 10346)]


def median_time(fn, repeats: int, budget: float) -> tuple[float, int]:
    """Median of up to `repeats` timed calls after one warm-up call (compiles, caches);
    fewer repeats when the calls are slow (a total of about `budget` seconds)."""
    fn()
    times = []
    while len(times) < repeats:
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
        if sum(times) > budget:
            break
    return float(np.median(times)), len(times)


# --- inputs ---------------------------------------------------------------------

def sheet_mesh(faces: int, rng):
    n = int(np.ceil(np.sqrt(faces / 2))) + 1
    x, y = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n), indexing="ij")
    z = 0.05 * np.sin(9 * x) * np.cos(7 * y) + 0.001 * rng.random(x.shape)
    v = np.stack([x.ravel(), y.ravel(), z.ravel()], 1) * 100 + [300.0, -20.0, 5.0]
    i = (np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None, :]).ravel()
    f = np.concatenate([np.stack([i, i + n, i + 1], 1), np.stack([i + 1, i + n, i + n + 1], 1)])[:faces]
    # interior edges: faces sharing a sorted vertex pair
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    owner = np.tile(np.arange(len(f)), 3)
    key = np.sort(e, 1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    key, owner = key[order], owner[order]
    same = np.all(key[1:] == key[:-1], 1)
    return v, f.astype(np.int32), np.stack([owner[:-1][same], owner[1:][same]], 1)


def closed_curve(n: int, rng):
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.stack([np.cos(t) + 0.2 * np.cos(5 * t), np.sin(t) + 0.1 * np.sin(3 * t), 0.3 * np.sin(2 * t)], 1) * 50


def screening_batch(pairs: int, length: int, rng):
    """`pairs` pairs as a square grid of a- and b-sequences (all against all), as in screening."""
    side = int(np.ceil(np.sqrt(pairs)))
    values = rng.random(side * length).astype(np.float32).astype(np.float64)
    offsets = np.arange(0, side * length + 1, length, dtype=np.int64)
    grid = np.stack(np.meshgrid(np.arange(side), np.arange(side), indexing="ij"), -1).reshape(-1, 2)[:pairs]
    return values, offsets, grid


def lcs_bitparallel_numpy(values, offsets, pairs, eps):
    """Vectorised NumPy bit-parallel LCS over a batch of equal-length pairs (a baseline)."""
    length = int(offsets[1] - offsets[0])
    seqs = values.reshape(-1, length)
    a, b = seqs[pairs[:, 0]], seqs[pairs[:, 1]]
    words = (length + 63) // 64
    pad = words * 64 - length
    v = np.full((len(pairs), words), np.uint64(0xFFFFFFFFFFFFFFFF))
    for i in range(length):
        flags = np.abs(a[:, i:i + 1] - b) < eps
        if pad:
            flags = np.pad(flags, ((0, 0), (0, pad)))
        m = np.packbits(flags, axis=1, bitorder="little").view(np.uint64)
        u = v & m
        carry = np.zeros(len(pairs), np.uint64)
        for w in range(words):
            s = v[:, w] + u[:, w]
            c1 = s < v[:, w]
            s2 = s + carry
            c2 = s2 < s
            v[:, w] = s2 | (v[:, w] & ~m[:, w])
            carry = (c1 | c2).astype(np.uint64)
    zeros = np.unpackbits(~v.view(np.uint8), axis=1, bitorder="little")[:, :length]
    return zeros.sum(1).astype(np.int32)


def uniform_points(n: int, rng):
    return rng.random((n, 3)) * 10 + 100


@functools.lru_cache(maxsize=None)
def _prepared_pair():
    """A synthetic vase broken in two, both pieces prepared (NumPy) with a fracture sample large
    enough for 2,000 point-pair points, and the pair's scale."""
    from relicgpu.params import Params
    from relicgpu.pair.pipeline import pair_scale
    from relicgpu.pair.prepare import prepare
    from relicgpu.synth import generate

    params = Params(icp_points=6000)
    a, b = generate("vase", pieces=2, seed=1, faces=40_000, noise=0.0005, progress=False).fragments[:2]
    scale = pair_scale(a, b, params)
    return prepare(a, params, "numpy", scale=scale), prepare(b, params, "numpy", scale=scale), params, scale


def ppf_tables(n_model: int, n_scene: int):
    """Point-pair tables as `match_pair` builds them (`prepare._ppf_table`: weighted, pairs within
    ppf_max_distance, the scene's normals flipped and every third point a reference), from the
    fracture samples of a synthetic pair, with n_model and n_scene points instead of ppf_points."""
    from relicgpu.pair.ppf import pair_table
    from relicgpu.pair.prepare import ppf_points, ppf_weights

    pa, pb, params, scale = _prepared_pair()
    step, reach = params.ppf_distance_step * scale, params.ppf_max_distance * scale
    pm, nm = ppf_points(pa.sample, n_model)
    ps, ns = ppf_points(pb.sample, n_scene)
    model = pair_table(pm, nm, step, params.ppf_angle_step_deg, max_distance=reach,
                       weights=ppf_weights(pa.sample, n_model))
    scene = pair_table(ps, -ns, step, params.ppf_angle_step_deg, reference_stride=3, sort=False, max_distance=reach,
                       weights=ppf_weights(pb.sample, n_scene))
    return model, scene


# --- sections -------------------------------------------------------------------

def run_kernels(names, sections, sizes, repeats, max_seconds, rows, log):
    rng = np.random.default_rng(0)
    backends = {n: get_backend(n) for n in names}

    def record(section, size, label, case, fn, work=None, unit=None, baseline=False, est=None):
        row = {"section": section, "size": size, "backend": label, "case": case, "baseline": baseline}
        if est is not None and est > max_seconds:
            row.update(skipped=f"estimated {est:.0f} s > --max-seconds {max_seconds:g}")
        else:
            try:
                t, n = median_time(fn, repeats, budget=max(3 * max_seconds, 1.0))
                row.update(seconds=t, repeats=n)
                if work is not None:
                    row.update(rate=work / t, unit=unit)
            except Exception as exc:  # a backend that fails a size is a result too
                row.update(error=f"{type(exc).__name__}: {exc}")
        rows.append(row)
        log(row)

    if "normals" in sections:
        for faces in sizes["normals"]:
            v, f, e = sheet_mesh(faces, rng)
            normals = reference.face_normals(v, f)[0]
            for name, be in backends.items():
                record("face_normals", faces, name, f"{faces} faces", lambda: be.face_normals(v, f))
                record("edge_angles", len(e), name, f"{len(e)} edges", lambda: be.edge_angles(normals, e))
    if "curvature" in sections:
        for n in sizes["curvature"]:
            p = closed_curve(n, rng)
            for name, be in backends.items():
                record("contour_features", n, name, f"{n} points, k=5, stride=2",
                       lambda: be.contour_features(p, 5, 2))
    if "lcs" in sections:
        # the reference's rate, from one small pair, decides whether it is run at a size
        a = rng.random(96)
        t0 = time.perf_counter()
        reference.lcs_length(a, a[::-1], 0.05)
        ref_cell_s = (time.perf_counter() - t0) / 96 ** 2
        for pairs, length in sizes["lcs"]:
            values, offsets, grid = screening_batch(pairs, length, rng)
            cells = pairs * length * length
            case = f"{pairs} pairs x {length}"
            for name, be in backends.items():
                record("lcs_screen", cells, name, case,
                       lambda: be.lcs_lengths(values, offsets, values, offsets, grid, 0.05),
                       work=cells, unit="cells/s", est=cells * ref_cell_s if name == "numpy" else None)
                kernel_only = be.device_kernel("lcs", values, offsets, values, offsets, grid, 0.05) \
                    if isinstance(be, DeviceTiming) else None
                if kernel_only is not None:
                    record("lcs_screen(kernel only)", cells, name, case, kernel_only, work=cells, unit="cells/s")
            record("lcs_screen", cells, "numpy-bitparallel", case,
                   lambda: lcs_bitparallel_numpy(values, offsets, grid, 0.05), work=cells, unit="cells/s",
                   baseline=True, est=cells * 2e-9)
        # the baseline must compute the same lengths
        values, offsets, grid = screening_batch(9, 70, rng)
        assert np.array_equal(lcs_bitparallel_numpy(values, offsets, grid, 0.05),
                              reference.lcs_lengths(values, offsets, values, offsets, grid, 0.05))
    if "nn" in sections:
        from scipy.spatial import cKDTree
        for n in sizes["nn"]:
            src, dst = uniform_points(n, rng), uniform_points(n, rng)
            case = f"{n} into {n}, uniform in a cube"
            for name, be in backends.items():
                record("nearest_neighbors", n, name, case, lambda: be.nearest_neighbors(src, dst),
                       est=n * 4e-6 if name == "numpy" else None)
                on_device = be.device_kernel("nearest", src, dst) if isinstance(be, DeviceTiming) else None
                if on_device is not None:
                    record("nearest_neighbors(device-resident)", n, name, case, on_device)
            record("nearest_neighbors", n, "scipy-ckdtree-all-cores", case,
                   lambda: cKDTree(dst).query(src, k=1, workers=-1), baseline=True)
    if "cov" in sections:
        for n in sizes["cov"]:
            s, t, w = uniform_points(n, rng), uniform_points(n, rng), rng.random(n)
            for name, be in backends.items():
                record("cross_covariance", n, name, f"{n} pairs", lambda: be.cross_covariance(s, t, w))
    if "ppf" in sections:
        for n_model, n_scene in sizes["ppf"]:
            model, scene = ppf_tables(n_model, n_scene)
            refs = len(scene.references)
            args = (model.start, model.ref, model.alpha, model.weight, scene.key, scene.ref, scene.alpha,
                    scene.weight, refs, model.n_points, 30, 32)
            votes = int(np.minimum(np.diff(model.start)[np.minimum(scene.key, len(model.start) - 2)], 32).sum())
            case = f"{model.n_points} x {refs} refs, {votes / 1e6:.1f}M votes"
            want = reference.ppf_votes(*args)
            for name, be in backends.items():
                got = be.ppf_votes(*args)  # the figures count only where the best totals agree
                if not np.allclose(got[1], want[1], rtol=1e-5, atol=0):
                    rows.append({"section": "ppf_votes", "size": n_model, "backend": name, "case": case,
                                 "baseline": False, "error": "differs from the reference"})
                    log(rows[-1])
                    continue
                record("ppf_votes", n_model, name, case, lambda: be.ppf_votes(*args))


def run_match(names, repeats, max_seconds, rows, log, pairs=TABLE1_PAIRS):
    try:
        import relicgpu
        from relicgpu.synth import generate
    except Exception as exc:
        log({"section": "match_pair", "error": f"not available: {exc}"})
        return
    for k, (va, vb) in enumerate(pairs):
        # generate() makes pieces of about `faces` faces each; a closed mesh has ~F/2 vertices
        made = generate("vase", pieces=2, seed=100 + k, faces=va + vb, progress=False)
        a, b = made.fragments[:2]
        case = f"paper {va}/{vb}; synthetic {len(a.vertices)}/{len(b.vertices)} vertices"
        results = {}
        for name in names:
            row = {"section": "match_pair", "size": len(a.vertices) + len(b.vertices), "backend": name,
                   "case": case, "baseline": False}
            try:
                out = {}

                def call():
                    out["m"] = relicgpu.match_pair(a, b, backend=name)
                t, n = median_time(call, repeats, budget=max(3 * max_seconds, 1.0))
                m = out["m"]
                row.update(seconds=t, repeats=n, accepted=bool(m.accepted), reason=str(m.reason),
                           rmse=float(m.rmse) if m.rmse is not None else None,
                           stage_seconds={k: float(v) for k, v in dict(getattr(m, "timings", {}) or {}).items()})
                results[name] = np.asarray(m.transform, float) if m.accepted else None
            except Exception as exc:
                row.update(error=f"{type(exc).__name__}: {exc}")
            rows.append(row)
            log(row)
        ref = results.get("numpy")
        if ref is not None:
            for name, tr in results.items():
                if tr is None or name == "numpy":
                    continue
                r = tr[:3, :3] @ ref[:3, :3].T
                angle = np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1)))
                shift = np.linalg.norm(tr[:3, 3] - ref[:3, 3]) / max(a.size, b.size)
                log({"section": "match_pair", "backend": name, "case": case,
                     "vs_numpy": f"rotation {angle:.4f} deg, translation {100 * shift:.4f}% of size"})


# --- report ---------------------------------------------------------------------

def add_speedups(rows):
    ref = {(r["section"], r["size"]): r["seconds"] for r in rows
           if r.get("backend") == "numpy" and "seconds" in r}
    for r in rows:
        base = ref.get((r.get("section"), r.get("size")))
        if base and "seconds" in r:
            r["speedup_vs_numpy"] = base / r["seconds"]


def table(rows) -> str:
    lines = [f"{'section':<36} {'case':<42} {'backend':<38} {'median':>11} {'vs numpy':>9}  rate / note"]
    for r in rows:
        if "section" not in r or "backend" not in r or "case" not in r:
            continue
        if "vs_numpy" in r:
            lines.append(f"{r['section']:<36} {r['case'][:42]:<42} {r['backend'][:38]:<38} {'':>11} {'':>9}  same transform as numpy? {r['vs_numpy']}")
            continue
        if "seconds" in r:
            t = r["seconds"]
            shown = f"{t * 1e3:9.3f}ms" if t < 10 else f"{t:9.2f} s "
        else:
            shown = "-"
        sp = f"{r['speedup_vs_numpy']:8.1f}x" if "speedup_vs_numpy" in r else ""
        note = r.get("skipped") or r.get("error") or ""
        if "rate" in r:
            note = f"{r['rate'] / 1e12:.4f} TCUPS ({r['rate'] / 1e9:.2f} Gcells/s)"
        if "accepted" in r:
            note = f"accepted={r['accepted']} ({r['reason']})"
        label = r["backend"] + (" [baseline]" if r.get("baseline") else "")
        lines.append(f"{r['section']:<36} {r['case'][:42]:<42} {label[:38]:<38} {shown:>11} {sp:>9}  {note}")
    return "\n".join(lines)


def plot(rows, path: Path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sections = [s for s in dict.fromkeys(r["section"] for r in rows if "seconds" in r and "size" in r)]
    if not sections:
        return
    cols = 3
    fig, axes = plt.subplots((len(sections) + cols - 1) // cols, cols, figsize=(5 * cols, 4 * ((len(sections) + cols - 1) // cols)),
                             squeeze=False)
    for ax, section in zip(axes.ravel(), sections):
        for backend in dict.fromkeys(r["backend"] for r in rows if r["section"] == section):
            pts = sorted((r["size"], r["seconds"]) for r in rows
                         if r["section"] == section and r["backend"] == backend and "seconds" in r)
            if pts:
                x, y = zip(*pts)
                ax.loglog(x, y, "o-", label=backend)
        ax.set_title(section)
        ax.set_xlabel("cells" if section == "lcs_screen" else "size")
        ax.set_ylabel("median seconds")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    for ax in axes.ravel()[len(sections):]:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--backends", default="all",
                    help="comma-separated names or prefixes (numpy, warp-cpu, warp-cuda:0, opencl, ...); default all here")
    ap.add_argument("--sections", default=",".join(SECTIONS), help=f"comma-separated subset of {','.join(SECTIONS)}")
    ap.add_argument("--quick", action="store_true", help="small sizes only (a smoke run)")
    ap.add_argument("--repeats", type=int, default=5, help="timed calls per case (median reported)")
    ap.add_argument("--max-seconds", type=float, default=20.0,
                    help="skip a case whose estimated single-call time is longer (numpy LCS, numpy NN at 1M)")
    ap.add_argument("--out", default="bench-results", help="output directory for bench_backends.json and .png")
    args = ap.parse_args(argv)

    here = available_backends()
    if args.backends == "all":
        names = here
    else:
        wanted = [w.strip() for w in args.backends.split(",") if w.strip()]
        names = [n for n in here if any(n == w or n.startswith(w) for w in wanted)]
        if "numpy" not in names:
            names = ["numpy"] + names  # the speed-up column needs the reference
    sections = [s.strip() for s in args.sections.split(",") if s.strip()]
    unknown = set(sections) - set(SECTIONS)
    if unknown:
        ap.error(f"unknown sections {sorted(unknown)}")
    sizes = QUICK_SIZES if args.quick else SIZES

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows: list[dict] = []

    def log(row):
        print(json.dumps(row), file=sys.stderr, flush=True)

    devices = {n: getattr(get_backend(n), "device_name", "host CPU") for n in names}
    run_kernels(names, sections, sizes, args.repeats, args.max_seconds, rows, log)
    if "match" in sections:
        run_match(names, min(args.repeats, 3), args.max_seconds, rows, log)
    add_speedups(rows)
    text = table(rows)
    print(text)
    meta = {"host": platform.node(), "machine": platform.machine(), "python": platform.python_version(),
            "backends": devices, "repeats": args.repeats, "max_seconds": args.max_seconds,
            "time": time.strftime("%Y-%m-%d %H:%M:%S")}
    from relicgpu.io.files import atomic_write_json

    atomic_write_json(out / "bench_backends.json", {"meta": meta, "rows": rows})
    (out / "bench_backends.txt").write_text(text + "\n")
    plot(rows, out / "bench_backends.png")
    print(f"wrote {out / 'bench_backends.json'}, {out / 'bench_backends.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
