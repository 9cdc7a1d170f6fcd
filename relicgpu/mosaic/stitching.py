"""Stitching: each image placed against the one before (`stitch`), composited with
feathered blending; image files read and written."""
from __future__ import annotations

import io as _io
from pathlib import Path

import numpy as np
from scipy import ndimage

from ..backends import resolve
from ..io.files import atomic_write_bytes
from .params import Mosaic, MosaicError, MosaicParams
from .register import register_pair


def _rot(angle_deg: float) -> np.ndarray:
    """R(angle) acting on (row, col) vectors, as used by _sample_box."""
    a = np.deg2rad(angle_deg)
    return np.array([[np.cos(a), np.sin(a)], [-np.sin(a), np.cos(a)]])


def composite(images: list, transforms: list) -> tuple[np.ndarray, np.ndarray]:
    """Blend images placed by (A, t) (image pixel p lands at A p + t, (row, col)) into one
    canvas, each weighted by its distance to its own border (feathering over the overlaps).
    Returns the canvas (dtype of the inputs) and the canvas position of each image origin."""
    colour = any(np.asarray(im).ndim == 3 for im in images)
    arrs = []
    for im in images:
        a = np.asarray(im)
        if a.ndim == 3 and a.shape[2] == 4:
            a = a[..., :3]
        if colour and a.ndim == 2:
            a = np.repeat(a[..., None], 3, 2)
        arrs.append(a)
    dtype = arrs[0].dtype
    corners = []
    for a, (m, t) in zip(arrs, transforms):
        h, w = a.shape[:2]
        c = np.array([[0, 0], [0, w - 1], [h - 1, 0], [h - 1, w - 1]], np.float64)
        corners.append(c @ m.T + t)
    allc = np.concatenate(corners)
    lo = np.floor(allc.min(0) + 1e-6)  # an origin at -4.0000001 is at -4
    size = (np.ceil(allc.max(0) - 1e-6) - lo + 1).astype(int)
    shape = (size[0], size[1]) + ((3,) if colour else ())
    acc = np.zeros(shape)
    wsum = np.zeros(tuple(size))
    for a, (m, t), c in zip(arrs, transforms, corners):
        h, w = a.shape[:2]
        t = t - lo
        y0, x0 = np.maximum(np.floor(c.min(0) - lo + 1e-6), 0).astype(int)
        y1, x1 = np.minimum(np.ceil(c.max(0) - lo - 1e-6).astype(int) + 1, size)
        yy, xx = np.mgrid[y0:y1, x0:x1].astype(np.float64)
        inv = np.linalg.inv(m)
        sy = inv[0, 0] * (yy - t[0]) + inv[0, 1] * (xx - t[1])
        sx = inv[1, 0] * (yy - t[0]) + inv[1, 1] * (xx - t[1])
        weight = np.minimum.reduce([sy + 0.5, h - 0.5 - sy, sx + 0.5, w - 0.5 - sx])
        weight = np.clip(weight, 0.0, None)
        chans = [a] if a.ndim == 2 else [a[..., k] for k in range(a.shape[2])]
        vals = [ndimage.map_coordinates(ch.astype(np.float64), [sy, sx], order=1, mode="nearest") for ch in chans]
        v = vals[0] if a.ndim == 2 else np.stack(vals, -1)
        wv = weight if a.ndim == 2 else weight[..., None]
        acc[y0:y1, x0:x1] += wv * v
        wsum[y0:y1, x0:x1] += weight
    out = acc / np.maximum(wsum if not colour else wsum[..., None], 1e-12)
    if np.issubdtype(dtype, np.integer):
        info = np.iinfo(dtype)
        out = np.clip(np.rint(out), info.min, info.max).astype(dtype)
    origins = np.array([t - lo for _, t in transforms])
    return out, origins


def stitch(images, backend="auto", params: MosaicParams | None = None, vertical: bool = False,
           progress: bool = False) -> Mosaic:
    """Stitch a left-to-right sequence of overlapping photographs (arrays or paths);
    `vertical=True` for a top-to-bottom one. Each image is placed against the one before it."""
    be = resolve(backend)
    p = params or MosaicParams()
    names, arrays = [], []
    for i, im in enumerate(images):
        if isinstance(im, (str, Path)):
            names.append(str(im))
            arrays.append(load_image(im))
        else:
            names.append(f"image {i}")
            arrays.append(np.asarray(im))
    if len(arrays) < 2:
        raise MosaicError("a mosaic needs at least two images")
    for n, a in zip(names, arrays):
        if a.ndim not in (2, 3) or min(a.shape[:2]) < 1:
            raise MosaicError(f"{n}: not an image (array of shape {a.shape})")
    work = [np.swapaxes(a, 0, 1) if vertical else a for a in arrays]
    pairs = range(len(work) - 1)
    if progress:
        from tqdm import tqdm
        pairs = tqdm(pairs, desc="mosaic", unit="pair", leave=False)
    matches = []
    m, t = np.eye(2), np.zeros(2)
    transforms = [(m, t)]
    for i in pairs:
        pm = register_pair(work[i], work[i + 1], p, be, names=(names[i], names[i + 1]))
        matches.append(pm)
        r = _rot(pm.angle)
        # right pixel q -> left frame: left_point + R (q - right_point) -> mosaic: m(.) + t
        t = m @ (pm.left_point - r @ pm.right_point) + t
        m = m @ r
        transforms.append((m, t))
    canvas, origins = composite(work, transforms)
    angles = np.array([np.rad2deg(np.arctan2(mm[0, 1], mm[0, 0])) for mm, _ in transforms])
    if vertical:
        canvas = np.swapaxes(canvas, 0, 1)
        origins = origins[:, ::-1]
        angles = -angles
    return Mosaic(origins, canvas, angles, matches)


def load_image(path) -> np.ndarray:
    """An image file as uint8/uint16 gray or RGB; faults become MosaicError naming the file."""
    from PIL import Image, UnidentifiedImageError
    path = Path(path)
    if not path.exists():
        raise MosaicError(f"{path}: no such file")
    if path.is_dir():
        raise MosaicError(f"{path}: is a directory, not an image")
    try:
        with Image.open(path) as im:
            im.load()
            if im.mode in ("I;16", "I;16B", "I;16L"):
                arr = np.asarray(im, np.uint16)
            elif im.mode in ("L", "RGB"):
                arr = np.asarray(im)
            elif im.mode in ("1", "LA", "I", "F"):
                arr = np.asarray(im.convert("L"))
            else:
                arr = np.asarray(im.convert("RGB"))
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as exc:
        raise MosaicError(f"{path}: cannot read as an image ({exc})") from None
    if min(arr.shape[:2]) < 1:
        raise MosaicError(f"{path}: empty image")
    return arr


_FORMATS = {".png": "PNG", ".jpg": "JPEG", ".jpeg": "JPEG", ".tif": "TIFF", ".tiff": "TIFF", ".bmp": "BMP",
            ".webp": "WEBP"}


def save_image(path, image: np.ndarray) -> None:
    """Write an image atomically; the format comes from the suffix."""
    from PIL import Image
    path = Path(path)
    fmt = _FORMATS.get(path.suffix.lower())
    if fmt is None:
        raise MosaicError(f"{path}: unknown image suffix; use one of {', '.join(sorted(_FORMATS))}")
    arr = np.asarray(image)
    if fmt != "PNG" and arr.dtype == np.uint16:
        arr = (arr // 257).astype(np.uint8)
    buf = _io.BytesIO()
    Image.fromarray(arr).save(buf, format=fmt)
    atomic_write_bytes(path, buf.getvalue())
