"""JSON for the viewer's API: prepared fragments, pair matches, timings and
server-sent events, with arrays as short lists or base64 (no Flask here)."""
from __future__ import annotations

import base64
import json
import math

import numpy as np


def b64(array, dtype) -> str:
    """An array's bytes as base64 text.

    Parameters
    ----------
    array : array_like, any shape
        The values; written C-contiguous in `dtype`.
    dtype : str or numpy.dtype
        The wire type, e.g. "<f4" for vertices, "<u4" for faces.

    Returns
    -------
    str
        ASCII base64 of the raw little-endian bytes.
    """
    return base64.b64encode(np.ascontiguousarray(array, dtype=dtype).tobytes()).decode("ascii")


def round_points(points, scale: float) -> list:
    """Coordinates rounded to about 1e-7 of the fragment size: short JSON, nothing visible lost.

    Parameters
    ----------
    points : array_like, (n, 3)
        Coordinates.
    scale : float
        The fragment's size; a non-positive one keeps 7 decimals.

    Returns
    -------
    list
        Nested lists of floats, (n, 3).
    """
    decimals = int(max(0, 7 - math.floor(math.log10(scale)))) if scale > 0 else 7
    return np.round(np.asarray(points, np.float64), decimals).tolist()


def finite_or_none(x):
    """float(x) when it is a finite number, else None (JSON has no NaN)."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def timings_to_json(t) -> dict:
    """A stage's timings dict with its finite numbers only; {} for anything but a dict."""
    if not isinstance(t, dict):
        return {}
    return {str(k): finite_or_none(v) for k, v in t.items() if finite_or_none(v) is not None}


def prepared_to_json(name: str, prepared) -> dict:
    """A prepared fragment's segmentation and contours, as /contours answers.

    Parameters
    ----------
    name : str
        The fragment's name in its case.
    prepared : relicgpu.pair.pipeline.Prepared
        Its `fragment`, `face_region` (n_faces,), `region_is_fracture` (n_regions,)
        and `contours` (each with `region`, `points` (m, 3), `feature_points` (k,)).

    Returns
    -------
    dict
        name, n_faces, face_region, region_is_fracture, contours (index, region,
        fracture, points, feature_points) and timings.
    """
    frag = prepared.fragment
    face_region = np.asarray(prepared.face_region).astype(np.int64)
    fracture = np.asarray(prepared.region_is_fracture).astype(bool)
    contours = []
    for i, c in enumerate(prepared.contours):
        region = int(c.region)
        fp = getattr(c, "feature_points", None)
        contours.append({
            "index": i,
            "region": region,
            "fracture": bool(fracture[region]) if 0 <= region < len(fracture) else None,
            "points": round_points(c.points, frag.size),
            "feature_points": [] if fp is None else np.asarray(fp).astype(np.int64).tolist(),
        })
    return {
        "name": name,
        "n_faces": int(len(face_region)),
        "face_region": face_region.tolist(),
        "region_is_fracture": fracture.tolist(),
        "contours": contours,
        "timings": timings_to_json(getattr(prepared, "timings", None)),
    }


def match_to_json(a: str, b: str, heads, m) -> dict:
    """One pair match, as POST /api/match answers.

    Parameters
    ----------
    a, b : str
        The two fragments' names.
    heads : sequence of 4 int or None
        The head nodes asked for, [contour_a, point_a, contour_b, point_b].
    m : relicgpu.pair.result.PairMatch
        The match: `transform` (4, 4), `correspondences` (k, 2), `accepted`, `score`,
        `rmse`, `overlap`, `contour_a`, `contour_b`, `reason`, `timings`.

    Returns
    -------
    dict
        The fields above; non-finite numbers (and a non-finite transform) as None.
    """
    transform = np.asarray(m.transform, np.float64)
    corr = np.asarray(getattr(m, "correspondences", np.zeros((0, 2))))
    return {
        "a": a,
        "b": b,
        "heads": list(heads) if heads is not None else None,
        "accepted": bool(m.accepted),
        "score": finite_or_none(m.score),
        "rmse": finite_or_none(m.rmse),
        "overlap": finite_or_none(m.overlap),
        "transform": transform.tolist() if np.isfinite(transform).all() else None,
        "contour_a": None if m.contour_a is None else int(m.contour_a),
        "contour_b": None if m.contour_b is None else int(m.contour_b),
        "correspondences": corr.astype(np.int64).reshape(-1, 2).tolist(),
        "reason": str(getattr(m, "reason", "")),
        "timings": timings_to_json(getattr(m, "timings", None)),
    }


def sse(obj, event_id=None) -> str:
    """One server-sent event carrying obj as JSON (with an id line when event_id is given)."""
    head = f"id: {event_id}\n" if event_id is not None else ""
    return f"{head}data: {json.dumps(obj)}\n\n"
