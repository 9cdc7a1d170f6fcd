"""Benchmark of the image mosaic (issue 8): local-entropy matching against OpenCV.

Cuts pairs from the sample photographs that ship inside scikit-image (no
download; photographs over 640 px are scaled down): a left crop and a right crop
that overlaps it by 20% to 60% of the width, shifted up or down by up to 5% of
the height, with Gaussian noise on both (sigma drawn from --noise, default 2-8
gray levels), a gray-level change a*I + b on the right one (a in 0.8-1.25, b in
+-25) and a rotation of the right one about its centre by up to 2 degrees.

relicgpu.mosaic.register_pair does the whole registration (it may answer "no
overlap found", which counts as a miss). Its error is the distance between
where it puts its feature centre in the right crop and where that point truly
is (the offset error at that point). OpenCV's cv2.matchTemplate
(TM_CCOEFF_NORMED, on the noisy gray crops) gets the same square template:
the feature region relicgpu used, or the paper's first one when relicgpu
rejected the pair. Times: relicgpu's whole registration against OpenCV's
matchTemplate call alone.

    python scripts/bench_mosaic.py [--pairs 60] [--seed 0] [--backend numpy] [--noise 2 8] [--json out.json]
    python scripts/bench_mosaic.py --example docs/mosaic_example.png

Prints a table, every miss (image, overlap, rotation, outcome) and where the
accepted placements came from; the issue's bar is an offset within 1 px in >= 95%
of pairs. The mosaic's defaults were tuned on seeds 1-4; seeds 0 and 5-8 are held
out. Measured (numpy backend, 2-core CPU; within 1 px, max axis; relicgpu / OpenCV
on relicgpu's template; relicgpu's median time per pair, OpenCV's matchTemplate ~1.3 ms):
  noise 2-8:  seed 0 100% / 93.3% (69 ms), seed 5 100% / 90.0% (77 ms),
              seed 6 100% / 93.3% (72 ms), seed 7 100% / 96.7% (74 ms)
  noise 1-4:  seed 0 100% / 96.7%, seed 5 100% / 96.7%
  noise 8-16: seed 8 100% / 81.7%
  (before the one variance floor and the whole-overlap verification, noise 2-8:
  seeds 0, 5, 6, 7: 91.7%, 90.0%, 86.7%, 86.7%)
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np
from scipy import ndimage

# name of the loader in skimage.data -> file that ships inside the package
SAMPLES = {
    "astronaut": "astronaut.png", "camera": "camera.png", "coffee": "coffee.png", "chelsea": "chelsea.png",
    "coins": "coins.png", "hubble_deep_field": "hubble_deep_field.jpg", "rocket": "rocket.jpg",
    "moon": "moon.png", "immunohistochemistry": "ihc.png", "retina": "retina.jpg", "brick": "brick.png",
    "grass": "grass.png", "gravel": "gravel.png", "cell": "cell.png",
}


def load_samples() -> dict:
    import skimage.data
    here = os.path.dirname(skimage.data.__file__)
    out = {}
    for name, fname in SAMPLES.items():
        if not os.path.exists(os.path.join(here, fname)):
            continue  # this version of scikit-image would download it: skip
        img = getattr(skimage.data, name)()
        if img.ndim == 3:
            img = img[..., :3]
        # photographs larger than 640 px are scaled down, like a camera preview
        scale = 640.0 / max(img.shape[:2])
        if scale < 1:
            from skimage.transform import rescale
            img = (rescale(img, scale, channel_axis=2 if img.ndim == 3 else None, anti_aliasing=True) * 255)
            img = np.clip(np.rint(img), 0, 255).astype(np.uint8)
        out[name] = img
    return out


def _sample(img: np.ndarray, origin, shape, angle_deg: float) -> np.ndarray:
    """Crop of `shape` at `origin` of img, rotated by angle_deg about its centre:
    out[q] = img[origin + c + R(angle) (q - c)], bilinear."""
    h, w = shape
    c = np.array([(h - 1) / 2.0, (w - 1) / 2.0])
    qy, qx = np.mgrid[0:h, 0:w].astype(np.float64)
    a = np.deg2rad(angle_deg)
    ca, sa = np.cos(a), np.sin(a)
    dy, dx = qy - c[0], qx - c[1]
    sy = origin[0] + c[0] + ca * dy + sa * dx
    sx = origin[1] + c[1] - sa * dy + ca * dx
    chans = [img] if img.ndim == 2 else [img[..., k] for k in range(img.shape[2])]
    vals = [ndimage.map_coordinates(ch.astype(np.float64), [sy, sx], order=1, mode="reflect") for ch in chans]
    return vals[0] if img.ndim == 2 else np.stack(vals, -1)


def make_pair(img: np.ndarray, rng: np.random.Generator, noise=(2.0, 8.0)) -> dict:
    """A (left, right) pair cut from img with the truth needed to score it."""
    hs, ws = img.shape[:2]
    overlap = rng.uniform(0.2, 0.6)
    w = int(min(400, ws / (2.0 - overlap) - 2))
    shift_max = 0.05
    h = int(min(w, (hs - 2) / (1 + shift_max)))
    dx = int(round(w * (1 - overlap)))
    dy = int(round(rng.uniform(-shift_max, shift_max) * h))
    x0 = int(rng.integers(0, ws - (w + dx) + 1))
    y0 = int(rng.integers(max(0, -dy), hs - h - max(0, dy) + 1))
    angle = float(rng.uniform(-2.0, 2.0))
    left = _sample(img, (y0, x0), (h, w), 0.0)
    right = _sample(img, (y0 + dy, x0 + dx), (h, w), angle)
    gain, bias = rng.uniform(0.8, 1.25), rng.uniform(-25, 25)
    right = gain * right + bias
    s_left, s_right = rng.uniform(*noise), rng.uniform(*noise)
    left = left + rng.normal(0, s_left, left.shape)
    right = right + rng.normal(0, s_right, right.shape)
    to8 = lambda a: np.clip(np.rint(a), 0, 255).astype(np.uint8)  # noqa: E731
    return dict(left=to8(left), right=to8(right), origin_left=np.array([y0, x0], float),
                origin_right=np.array([y0 + dy, x0 + dx], float), shape=(h, w), angle=angle, overlap=overlap,
                gain=gain, bias=bias, noise=(s_left, s_right))


def true_right_point(pair: dict, left_point) -> np.ndarray:
    """Where the left crop's pixel left_point lies in the right crop."""
    h, w = pair["shape"]
    c = np.array([(h - 1) / 2.0, (w - 1) / 2.0])
    s = pair["origin_left"] + np.asarray(left_point, float)   # source coordinates
    d = s - pair["origin_right"] - c                           # = R(angle) (q - c)
    a = np.deg2rad(pair["angle"])
    ca, sa = np.cos(a), np.sin(a)
    r_inv = np.array([[ca, -sa], [sa, ca]])                    # inverse of [[ca, sa], [-sa, ca]]
    return c + r_inv @ d


def run(n_pairs: int, seed: int, backend_name: str, progress: bool = True, noise=(2.0, 8.0), params=None) -> dict:
    import cv2
    from tqdm import tqdm

    from relicgpu import mosaic
    from relicgpu.backends import resolve
    from relicgpu.mosaic.fcm import _feature_geometry

    backend = resolve(backend_name)
    samples = load_samples()
    names = sorted(samples)
    rng = np.random.default_rng(seed)
    params = params or mosaic.MosaicParams()
    # warm up kernels (compilation is not matching time)
    warm = make_pair(samples[names[0]], np.random.default_rng(12345))
    try:
        mosaic.register_pair(warm["left"], warm["right"], params, backend)
    except mosaic.MosaicError:
        pass

    rows = []
    for i in tqdm(range(n_pairs), desc="pairs", disable=not progress, file=sys.stderr):
        name = names[i % len(names)]
        pair = make_pair(samples[name], rng, noise)
        rec = dict(index=i, image=name, overlap=pair["overlap"], angle=pair["angle"])
        t0 = time.perf_counter()
        try:
            pm = mosaic.register_pair(pair["left"], pair["right"], params, backend)
        except mosaic.MosaicError as exc:  # a rejected pair counts as a miss
            pm, rec["error"] = None, str(exc)
        elapsed = time.perf_counter() - t0
        if pm is not None:
            centre, tw = tuple(int(v) for v in pm.left_point), pm.template_width
            found = pm.right_point
            entropy_err = float(np.abs(pm.entropy_point - true_right_point(pair, centre)).max())
            rec.update(accepted=True, corr=pm.correlation, margin=pm.margin, distinctness=pm.distinctness,
                       region_rank=pm.region_rank, entropy_rank=pm.entropy_rank, entropy_err_inf=entropy_err,
                       angle_found=pm.angle, timings=pm.timings)
        else:  # OpenCV gets the paper's feature region (or the middle of the band)
            pl = mosaic.prepare_image(pair["left"], params)
            try:
                region = mosaic.find_feature_region(pl, params, backend)
                centre, tw = region.centre, region.width
            except mosaic.MosaicError:
                tw, (c0, c1), (r0, r1) = _feature_geometry(pair["shape"][1], pair["shape"][0], params)
                centre = ((r0 + r1) // 2, (c0 + c1) // 2)
            found = np.full(2, np.inf)
            rec.update(accepted=False)
        truth = true_right_point(pair, centre)
        rec.update(template=tw, err=float(np.linalg.norm(found - truth)), err_inf=float(np.abs(found - truth).max()),
                   t_total=elapsed)

        # OpenCV on the same template, raw noisy gray crops
        gl = np.clip(np.rint(mosaic.to_gray(pair["left"])), 0, 255).astype(np.uint8)
        gr = np.clip(np.rint(mosaic.to_gray(pair["right"])), 0, 255).astype(np.uint8)
        cy, cx = centre
        tmpl = gl[cy - tw // 2:cy - tw // 2 + tw, cx - tw // 2:cx - tw // 2 + tw]
        t3 = time.perf_counter()
        res = cv2.matchTemplate(gr, tmpl, cv2.TM_CCOEFF_NORMED)
        _, _, _, (bx, by) = cv2.minMaxLoc(res)
        t4 = time.perf_counter()
        found_cv = np.array([by + tw // 2, bx + tw // 2], float)
        rec.update(err_cv=float(np.linalg.norm(found_cv - truth)), err_inf_cv=float(np.abs(found_cv - truth).max()),
                   t_cv=t4 - t3)
        rows.append(rec)
    return dict(rows=rows, backend=backend.name, seed=seed, pairs=n_pairs, noise=list(noise))


def summarise(result: dict) -> str:
    rows = result["rows"]
    n = len(rows)
    e = np.array([r["err"] for r in rows])
    ei = np.array([r["err_inf"] for r in rows])
    ec = np.array([r["err_cv"] for r in rows])
    eci = np.array([r["err_inf_cv"] for r in rows])
    acc = np.array([r["accepted"] for r in rows])
    tt = np.array([r["t_total"] for r in rows]) * 1e3
    tc = np.array([r["t_cv"] for r in rows]) * 1e3
    lines = [
        f"{n} pairs, seed {result['seed']}, backend {result['backend']}; overlap 20-60%, "
        f"noise sigma {result['noise'][0]:g}-{result['noise'][1]:g}, "
        f"gain 0.8-1.25, bias +-25, rotation +-2 deg",
        "",
        "| method | within 1 px (max axis) | within 1 px (euclid.) | within 2 px | median error px | "
        "time per pair (ms, median) |",
        "| --- | --- | --- | --- | --- | --- |",
        f"| relicgpu local entropy (3.4) | {np.mean(ei <= 1):.1%} | {np.mean(e <= 1):.1%} | {np.mean(e <= 2):.1%} | "
        f"{np.median(e):.2f} | {np.median(tt):.0f} (whole registration: preprocessing, feature region, "
        f"entropy map, search, checks) |",
        f"| OpenCV matchTemplate TM_CCOEFF_NORMED | {np.mean(eci <= 1):.1%} | {np.mean(ec <= 1):.1%} | "
        f"{np.mean(ec <= 2):.1%} | {np.median(ec):.2f} | {np.median(tc):.1f} (matchTemplate only) |",
        "",
        f"relicgpu accepted {acc.sum()}/{n} pairs and rejected {n - acc.sum()} with 'no overlap found'; "
        f"accepted but off by more than 1 px: {int(np.sum(acc & (ei > 1)))}, by more than 5 px: "
        f"{int(np.sum(acc & (e > 5)))}. OpenCV (no rejection) off by more than 5 px: {int(np.sum(ec > 5))}.",
    ]
    ok = [r for r in rows if r["accepted"]]
    if ok:
        ee = np.array([r["entropy_err_inf"] for r in ok])
        lines.append(f"Where the accepted placements came from: the paper's feature region (region 0) in "
                     f"{sum(r['region_rank'] == 0 for r in ok)}/{len(ok)}, the entropy match with the smallest "
                     f"coarse T in {sum(r['entropy_rank'] == 0 for r in ok)}/{len(ok)}; the entropy fine stage "
                     f"alone was within 1 px in {np.sum(ee <= 1)}/{len(ok)} (max axis; median {np.median(ee):.2f} px), "
                     f"after the refinement over the overlap {sum(r['err_inf'] <= 1 for r in ok)}/{len(ok)}.")
    bad = [r for r in rows if r["err_inf"] > 1]
    if bad:
        lines.append("relicgpu misses (pair: image, overlap, rotation, outcome):")
        lines += [f"  #{r['index']}: {r['image']}, overlap {r['overlap']:.0%}, rotation {r['angle']:+.2f} deg, "
                  f"{_miss(r)}" for r in bad]
    stages = ["preprocess", "feature_region", "entropy_map", "match", "verify"]
    timed = [r["timings"] for r in rows if "timings" in r]
    if timed:
        lines.append("relicgpu median stage times (ms): " + ", ".join(
            f"{s} {np.median([t[s] for t in timed]) * 1e3:.1f}" for s in stages))
    return "\n".join(lines)


def _miss(rec: dict) -> str:
    if not rec["accepted"]:
        return "rejected: " + rec["error"].split("no overlap found: ", 1)[-1]
    return (f"off {rec['err']:.1f} px (region {rec['region_rank']}, overlap correlation {rec['corr']:.2f}, "
            f"margin {rec['margin']:.2f}, angle found {rec['angle_found']:+.2f})")


def example(path: str, seed: int = 3) -> None:
    """docs/mosaic_example.png: three overlapping crops of a sample photograph (noise, gray-level
    change, rotation), the feature region and cross-shaped area found in each left image, and
    the stitched result."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from relicgpu import mosaic
    from relicgpu.io.files import atomic_write_bytes

    import skimage.data
    img = skimage.data.astronaut()
    rng = np.random.default_rng(seed)
    shape = (300, 230)
    specs = [((40, 10), 0.0, 1.0, 0.0), ((52, 150), 1.2, 0.85, 18.0), ((34, 282), -0.8, 1.1, -12.0)]
    parts = []
    for origin, angle, gain, bias in specs:
        crop = gain * _sample(img, origin, shape, angle) + bias + rng.normal(0, 3.0, shape + (3,))
        parts.append(np.clip(np.rint(crop), 0, 255).astype(np.uint8))
    result = mosaic.stitch(parts, backend="numpy")
    params = mosaic.MosaicParams()
    fig = plt.figure(figsize=(12, 7.2))
    for i, part in enumerate(parts):
        ax = fig.add_subplot(2, 3, i + 1)
        ax.imshow(part)
        ax.set_title(f"input {i + 1}" + (f" (rotated {specs[i][1]:+.1f} deg, gain {specs[i][2]:.2f})" if i else ""),
                     fontsize=9)
        ax.axis("off")
        if i < len(result.matches):
            m = result.matches[i]
            tw = m.template_width
            thick = min(tw, max(params.block, int(round(tw * params.cross_fraction))))
            cy, cx = m.left_point
            for h, w in [(thick, tw), (tw, thick)]:  # the two bars of the cross-shaped area
                ax.add_patch(plt.Rectangle((cx - w // 2, cy - h // 2), w, h, fill=False, ec="yellow", lw=1))
            ax.plot(cx, cy, "r+", ms=10)
        if i > 0:
            m = result.matches[i - 1]
            ax.plot(m.right_point[1], m.right_point[0], "c+", ms=10)
    ax = fig.add_subplot(2, 1, 2)
    ax.imshow(result.image)
    ax.set_title("stitched, feathered over the overlaps; image origins (row, col): "
                 + ", ".join(f"({o[0]:.1f}, {o[1]:.1f})" for o in result.offsets), fontsize=9)
    ax.axis("off")
    fig.suptitle("relicgpu mosaic: yellow, the cross-shaped feature area of each left image (red +, its centre); "
                 "cyan +, where it was found in the next image", fontsize=9)
    fig.tight_layout()
    import io
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=80)
    atomic_write_bytes(path, buf.getvalue())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pairs", type=int, default=60)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--backend", default="numpy")
    ap.add_argument("--noise", type=float, nargs=2, default=(2.0, 8.0), metavar=("LO", "HI"),
                    help="Gaussian noise sigma (gray levels) drawn from [LO, HI] per crop (default 2 8)")
    ap.add_argument("--json", help="also write the per-pair records here")
    ap.add_argument("--example", metavar="PNG", help="only draw the example figure (docs/mosaic_example.png)")
    args = ap.parse_args(argv)
    if args.example:
        example(args.example)
        return 0
    result = run(args.pairs, args.seed, args.backend, noise=tuple(args.noise))
    print(summarise(result))
    if args.json:
        from relicgpu.io.files import atomic_write_json
        atomic_write_json(args.json, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
