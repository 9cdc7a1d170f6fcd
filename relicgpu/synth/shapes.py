"""The unbroken solids: a vase, a torso, a slab, or a closed mesh file, normalised to a
bounding-box diagonal of 1 and centred on the origin (`make_shape`)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..io.fragment import FragmentError, is_watertight
from ..io.load import load_fragment

SHAPES = ("vase", "torso", "slab")


def make_shape(shape: str = "vase", seed: int = 0, detail: float | None = 0.015,
               _rng: np.random.Generator | None = None):
    """The unbroken object as a manifold3d.Manifold, normalised (bbox diagonal 1, centred).

    Built-in shapes vary a little with `seed` (proportions within about 10%), so
    that objects of different seeds are different objects; they are tessellated
    into triangles of about detail^2 / 2 (object units). A file is used as is
    (refined to `detail` when one is given).
    """
    rng = _rng if _rng is not None else np.random.default_rng(np.random.SeedSequence(int(seed)).spawn(5)[0])
    if shape == "vase":
        solid = _vase(rng, detail * 1.96)  # the factors: measured, for triangles of detail^2 / 2
    elif shape == "torso":
        solid = _torso(rng, detail * 2.0)
    elif shape == "slab":
        solid = _slab(rng, detail * 1.33)
    else:
        solid = _normalise(_solid_from_file(shape))
        return (solid.refine_to_length(detail * 1.3) if detail else solid).as_original()
    return _normalise(solid).as_original()


def _jitter(rng, value, rel=0.08):
    return value * (1.0 + rng.uniform(-rel, rel))


def _vase(rng, edge):
    """A pot: a smooth profile revolved, walls and bottom about 5% of the height thick."""
    import manifold3d as mf

    foot, belly, neck, lip = _jitter(rng, 0.16), _jitter(rng, 0.33), _jitter(rng, 0.13), _jitter(rng, 0.18)
    s_belly = _jitter(rng, 0.42, 0.15)
    ctrl_s = [0.0, 0.06, s_belly, 0.80, 0.90, 1.0]
    ctrl_r = [foot, foot * 1.15, belly, neck, neck * 1.06, lip]
    height, wall = 1.0, 0.05
    z = np.linspace(0.0, height, int(np.clip(1.6 / edge, 32, 400)))
    r_out, slope = _pchip(np.array(ctrl_s), np.array(ctrl_r), z / height)
    slope = slope / height
    r_in = r_out - wall * np.sqrt(1.0 + slope ** 2)  # horizontal offset giving a normal thickness `wall`
    inner = z >= wall
    polygon = np.vstack([[0.0, 0.0], np.c_[r_out, z], np.c_[r_in[inner], z[inner]][::-1], [0.0, wall]])
    segments = 4 * int(np.clip(2 * np.pi * belly / edge / 4, 12, 128))
    return mf.Manifold.revolve(mf.CrossSection([polygon]), segments)


def _torso(rng, edge):
    """A rounded body: chest, belly, hips, shoulders and neck blended by a smooth union.

    The blended signed distance is star-shaped about a point of the chest, so the
    surface is found along rays from it and a geodesic sphere is moved onto it:
    always one closed, non-self-intersecting manifold.
    """
    import manifold3d as mf

    j = lambda v: _jitter(rng, v)
    ellipsoids = [
        ((0.0, 0.0, 0.30), (j(0.40), j(0.24), j(0.30))),   # chest
        ((0.0, 0.10, 0.30), (j(0.30), j(0.15), j(0.20))),  # chest plate
        ((0.0, 0.02, -0.02), (j(0.32), j(0.22), j(0.28))),  # belly
        ((0.0, -0.01, -0.32), (j(0.36), j(0.24), j(0.20))),  # hips
    ]
    shoulder = j(0.38)
    capsules = [
        ((-shoulder, 0.0, 0.45), (shoulder, 0.0, 0.45), j(0.13)),  # shoulders
        ((0.0, 0.0, 0.50), (0.0, 0.0, j(0.72)), j(0.09)),  # neck
    ]
    blend = 0.08
    centre = np.array([0.0, 0.0, -0.08])

    def sdf(p):
        d = None
        for c, r in ellipsoids:
            q = (p - c) / np.asarray(r)
            k0 = np.sqrt((q * q).sum(axis=-1))
            q = q / np.asarray(r)
            k1 = np.sqrt((q * q).sum(axis=-1))
            e = k0 * (k0 - 1.0) / np.maximum(k1, 1e-12)  # a bound of the ellipsoid's distance (Quilez)
            d = e if d is None else _smooth_min(d, e, blend)
        for a, b, r in capsules:
            a, b = np.asarray(a), np.asarray(b)
            ab = b - a
            t = np.clip(((p - a) @ ab) / (ab @ ab), 0.0, 1.0)
            x = p - (a + t[..., None] * ab)
            e = np.sqrt((x * x).sum(axis=-1)) - r
            d = _smooth_min(d, e, blend)
        return d

    sphere = mf.Manifold.sphere(1.0, 4 * int(np.clip(2 * np.pi * 0.6 / edge / 4, 24, 150)))
    mesh = sphere.to_mesh64()
    dirs = np.asarray(mesh.vert_properties)[:, :3]
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    radius = _outermost_root(sdf, dirs, centre, t_max=1.2)
    verts = centre + radius[:, None] * dirs
    return mf.Manifold(mf.Mesh64(np.ascontiguousarray(verts), np.array(mesh.tri_verts, np.uint64, order="C")))


def _pchip(x, y, t):
    """Monotone cubic (Fritsch-Carlson) interpolation of (x, y) at t: values and derivatives."""
    h = np.diff(x)
    delta = np.diff(y) / h
    d = np.zeros_like(y)
    for k in range(1, len(x) - 1):
        if delta[k - 1] * delta[k] > 0:
            w1, w2 = 2 * h[k] + h[k - 1], h[k] + 2 * h[k - 1]
            d[k] = (w1 + w2) / (w1 / delta[k - 1] + w2 / delta[k])
    d[0], d[-1] = delta[0], delta[-1]
    k = np.clip(np.searchsorted(x, t, side="right") - 1, 0, len(x) - 2)
    s = (t - x[k]) / h[k]
    h00, h10, h01, h11 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, -2 * s**3 + 3 * s**2, s**3 - s**2
    value = h00 * y[k] + h10 * h[k] * d[k] + h01 * y[k + 1] + h11 * h[k] * d[k + 1]
    dh00, dh10, dh01, dh11 = 6 * s**2 - 6 * s, 3 * s**2 - 4 * s + 1, -6 * s**2 + 6 * s, 3 * s**2 - 2 * s
    deriv = (dh00 * y[k] + dh01 * y[k + 1]) / h[k] + dh10 * d[k] + dh11 * d[k + 1]
    return value, deriv


def _smooth_min(a, b, k):
    h = np.maximum(k - np.abs(a - b), 0.0) / k
    return np.minimum(a, b) - h * h * k * 0.25


def _outermost_root(f, dirs, centre, t_max, steps=32, iters=22):
    """Per ray centre + t * dir, the largest t in (0, t_max) where f goes from inside (<0) to outside."""
    ts = np.linspace(t_max, 0.0, steps)
    values = f(centre + ts[None, :, None] * dirs[:, None, :])  # (rays, steps)
    inside = values < 0
    if not inside.any(axis=1).all():
        raise RuntimeError("torso: a ray from the centre misses the body")
    k = inside.argmax(axis=1)  # first sample inside, coming from outside
    lo, hi = ts[k], ts[np.maximum(k - 1, 0)]
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        inside = f(centre + mid[:, None] * dirs) < 0
        lo = np.where(inside, mid, lo)
        hi = np.where(inside, hi, mid)
    return 0.5 * (lo + hi)


def _slab(rng, edge):
    """A thick tile (about 1 x 0.66 x 0.08), bent slightly like a roof tile."""
    import manifold3d as mf

    size = (1.0, _jitter(rng, 0.66), _jitter(rng, 0.08))
    bend_x, bend_y, twist = _jitter(rng, 0.28), _jitter(rng, 0.06), rng.uniform(-0.04, 0.04)
    box = mf.Manifold.cube(size, True).refine_to_length(edge)

    def bend(p):
        p = np.array(p, np.float64, copy=True)
        x, y = p[:, 0], p[:, 1]
        p[:, 2] += bend_x * x * x + bend_y * y * y + twist * x * y
        return p

    return box.warp_batch(bend)


def _solid_from_file(path) -> "object":
    import manifold3d as mf

    p = Path(path)
    if not p.exists():
        raise FragmentError(f"{p}: no such file; --shape takes vase, torso, slab or the path of a closed mesh")
    frag = load_fragment(p)
    # Merge coincident vertices (STL stores every triangle apart) before checking closure.
    v, inverse = np.unique(frag.vertices, axis=0, return_inverse=True)
    f = inverse.reshape(-1)[frag.faces.astype(np.int64)]
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
    if len(f) == 0 or not is_watertight(f):
        open_edges = _count_bad_edges(f)
        raise FragmentError(f"{p}: the mesh is not watertight ({open_edges} open or non-manifold edges); "
                            f"synth needs a closed solid")
    solid = mf.Manifold(mf.Mesh64(np.ascontiguousarray(v, np.float64), np.ascontiguousarray(f, np.uint64)))
    if solid.status() != mf.Error.NoError or solid.is_empty():
        raise FragmentError(f"{p}: manifold3d rejects the mesh ({solid.status().name}); synth needs a closed, "
                            f"consistently oriented solid")
    if solid.volume() < 0:
        solid = mf.Manifold(mf.Mesh64(np.ascontiguousarray(v, np.float64), np.ascontiguousarray(f[:, ::-1], np.uint64)))
    if solid.volume() <= 0:
        raise FragmentError(f"{p}: the closed mesh encloses no volume")
    return solid


def _count_bad_edges(faces) -> int:
    if len(faces) == 0:
        return 0
    f = np.asarray(faces, np.int64)
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return int(np.count_nonzero(counts != 2))


def _normalise(solid):
    x0, y0, z0, x1, y1, z1 = solid.bounding_box()
    lo, hi = np.array([x0, y0, z0]), np.array([x1, y1, z1])
    scale = 1.0 / float(np.linalg.norm(hi - lo))
    centre = 0.5 * (lo + hi)
    m = np.zeros((3, 4))
    m[:, :3] = np.eye(3) * scale
    m[:, 3] = -centre * scale
    return solid.transform(m)
