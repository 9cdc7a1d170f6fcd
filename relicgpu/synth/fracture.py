"""Breaking a solid: rough fractal cut surfaces (fBm of Perlin noise), each side of a cut
triangulated by its own grid, applied with manifold3d booleans until there are enough pieces."""
from __future__ import annotations

import math

import numpy as np

# Fracture surface: fBm of Perlin noise, RMS height `roughness` (object units).
FBM_MAX_OCTAVES = 6
FBM_WAVELENGTH = 0.2  # of the coarsest octave, in object units (object diagonal = 1)
# Pieces below this fraction of the mean piece volume make the cut be drawn again.
MIN_VOLUME_FRACTION = 0.10
MAX_CUT_ATTEMPTS = 60


def _fracture(obj, pieces, roughness, spacing, rng, bar):
    """Split the largest piece along a rough surface until there are `pieces` single bodies.

    Each cut is one rough surface (a random plane through the piece, displaced by
    fBm noise), but its two sides are triangulated apart: the piece is intersected
    with one cutter and differenced with another, two grids of the same surface at
    random rotations and offsets. So neighbours sample their common fracture at
    different points, as two scans would, and match up to the linear
    interpolation error of the grids, which grows with the finest octaves kept
    (measured over the three shapes, 2 pieces, with FBM_* as set here: RMS gap
    1e-3 to 1.8e-3 of the object size, at most 7e-3, at 4000 and at 20000 faces).
    Returns the pieces, the original id of the object's faces and the octave count.
    """
    object_id = obj.original_id()
    parts, volumes = [obj], [obj.volume()]
    min_volume = MIN_VOLUME_FRACTION * volumes[0] / pieces
    octaves = _octaves(spacing)
    for _ in range(pieces - 1):
        k = int(np.argmax(volumes))
        piece = parts[k]
        v, f, _ = _manifold_arrays(piece, object_id)
        centres = v[f].mean(axis=1)
        areas = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
        # Cut across the piece's longest extent (with a random tilt), so that pieces stay
        # compact like real sherds rather than long strips.
        mean = (centres * areas[:, None]).sum(0) / areas.sum()
        cov = ((centres - mean) * areas[:, None]).T @ (centres - mean)
        long_axis = np.linalg.eigh(cov)[1][:, -1]
        # LAPACK's sign of an eigenvector differs between CPUs (it broke the same seed into other
        # pieces on Intel and AMD hosts): fix it, so that a seed is one object everywhere
        long_axis = long_axis * np.sign(long_axis[np.argmax(np.abs(long_axis))])
        for attempt in range(MAX_CUT_ATTEMPTS):
            tilt = 0.6 if attempt < MAX_CUT_ATTEMPTS // 2 else 3.0  # then nearly any plane
            normal = long_axis + tilt * _random_unit(rng)
            normal /= np.linalg.norm(normal)
            origin = normal * _weighted_quantile(centres @ normal, areas, rng.uniform(0.3, 0.7))
            reach = float(np.linalg.norm(v - origin, axis=1).max()) + 3 * spacing
            height = _fbm(reach, octaves, roughness, rng)
            below = piece ^ _cutter(v, normal, origin, height, reach, spacing, rng)
            above = piece - _cutter(v, normal, origin, height, reach, spacing, rng)
            if below.is_empty() or above.is_empty():
                continue
            if below.volume() < min_volume or above.volume() < min_volume:
                continue
            if len(below.decompose()) != 1 or len(above.decompose()) != 1:
                continue
            break
        else:
            raise ValueError(f"could not cut a piece into two single bodies of at least {MIN_VOLUME_FRACTION:.0%} "
                             f"of the mean piece volume in {MAX_CUT_ATTEMPTS} tries; ask for fewer pieces")
        parts[k] = below
        volumes[k] = below.volume()
        parts.append(above)
        volumes.append(above.volume())
        bar.update(1)
    return parts, object_id, octaves


def _octaves(spacing):
    """fBm octaves whose wavelength spans at least 2.5 grid steps (finer ones a scan at
    this density could not show). Real fracture surfaces are rough down to the scan's
    resolution; with a high gain the finest octaves make them rougher than scanner noise
    at the scale of the triangles, which is what tells fracture from original surface."""
    n = 1
    while n < FBM_MAX_OCTAVES and FBM_WAVELENGTH / 2 ** n >= 2.5 * spacing:
        n += 1
    return n


def _cutter(points, normal, origin, height, reach, spacing, rng):
    """A closed box whose top face is the rough surface `height` over the plane through
    `origin` facing `normal`, triangulated on a grid of step `spacing` at a random
    rotation and offset. It covers `points` (the piece to cut) sideways and below,
    so piece ^ cutter and piece - cutter are the two sides of the surface."""
    import manifold3d as mf

    u0, w0 = _frame(normal)
    angle = rng.uniform(0.0, 2.0 * np.pi)
    u = math.cos(angle) * u0 + math.sin(angle) * w0
    w = np.cross(normal, u)
    rel = points - origin
    a, b, c = rel @ u, rel @ w, rel @ normal
    margin = 2 * spacing
    shift = rng.uniform(0.0, spacing, 2)
    ga, gb = np.meshgrid(a.min() - margin - shift[0] + spacing * np.arange(int((np.ptp(a) + 2 * margin) / spacing) + 3),
                         b.min() - margin - shift[1] + spacing * np.arange(int((np.ptp(b) + 2 * margin) / spacing) + 3),
                         indexing="ij")
    # The surface is a function of the unrotated plane coordinates, shared by both cutters of a cut.
    x = ga * math.cos(angle) - gb * math.sin(angle)
    y = ga * math.sin(angle) + gb * math.cos(angle)
    h = height(x, y)
    depth = max(-c.min(), -h.min(), 0.0) + margin  # the bottom lies under the piece and the surface
    local, tris = _heightfield_box(ga, gb, h, -depth)
    world = origin + local @ np.stack([u, w, normal])
    return mf.Manifold(mf.Mesh64(np.ascontiguousarray(world), np.ascontiguousarray(tris, np.uint64)))


def _heightfield_box(ga, gb, height, bottom):
    """Vertices (local a, b, c) and outward triangles of the solid under a height field."""
    na, nb = ga.shape[0] - 1, ga.shape[1] - 1
    idx = np.arange((na + 1) * (nb + 1)).reshape(na + 1, nb + 1)
    top = np.c_[ga.ravel(), gb.ravel(), height.ravel()]
    p00, p10, p01, p11 = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel()
    top_tris = np.concatenate([np.c_[p00, p10, p11], np.c_[p00, p11, p01]])
    # The top's boundary, counter-clockwise seen from +c, without repeated corners.
    ring = np.concatenate([idx[:, 0], idx[-1, 1:], idx[-2::-1, -1], idx[0, -2:0:-1]])
    n_top, n_ring = len(top), len(ring)
    bottom_ring = np.c_[top[ring, 0], top[ring, 1], np.full(n_ring, bottom)]
    centre = np.array([[ga.mean(), gb.mean(), bottom]])
    verts = np.vstack([top, bottom_ring, centre])
    t = ring
    bk = n_top + np.arange(n_ring)
    t1, b1 = np.roll(t, -1), np.roll(bk, -1)
    c = np.full(n_ring, n_top + n_ring)
    side = np.concatenate([np.c_[t, bk, b1], np.c_[t, b1, t1]])
    cap = np.c_[c, b1, bk]
    return verts, np.concatenate([top_tris, side, cap])


def _fbm(reach, octaves, roughness, rng, gain=0.8):
    """A random fractal height function h(x, y) over [-reach, reach]^2: Perlin noise
    octaves of halving wavelength, scaled to an RMS height of `roughness`."""
    layers, norm = [], 0.0
    for octave in range(octaves):
        wavelength = FBM_WAVELENGTH / 2 ** octave
        n = int(2 * reach / wavelength) + 3
        angles = rng.uniform(0, 2 * np.pi, (n, n))
        layers.append((wavelength, gain ** octave, np.stack([np.cos(angles), np.sin(angles)], axis=-1),
                       rng.uniform(0, 1, 2)))
        norm += gain ** (2 * octave)
    # 0.2157: the standard deviation of one octave of this Perlin noise (measured over 2e6 points).
    scale = roughness / (0.2157 * math.sqrt(norm))

    def height(x, y):
        total = np.zeros(np.shape(x))
        if roughness == 0:
            return total
        for wavelength, amp, grads, offset in layers:
            gx = np.clip((x + reach) / wavelength + offset[0], 0, grads.shape[0] - 1.001)
            gy = np.clip((y + reach) / wavelength + offset[1], 0, grads.shape[1] - 1.001)
            total += amp * _perlin(gx, gy, grads)
        return total * scale

    return height


def _perlin(x, y, grads):
    xi, yi = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    xf, yf = x - xi, y - yi

    def dot(ix, iy, dx, dy):
        g = grads[ix, iy]
        return g[..., 0] * dx + g[..., 1] * dy

    n00, n10 = dot(xi, yi, xf, yf), dot(xi + 1, yi, xf - 1, yf)
    n01, n11 = dot(xi, yi + 1, xf, yf - 1), dot(xi + 1, yi + 1, xf - 1, yf - 1)
    u = xf * xf * xf * (xf * (xf * 6 - 15) + 10)
    v = yf * yf * yf * (yf * (yf * 6 - 15) + 10)
    lower, upper = n00 + u * (n10 - n00), n01 + u * (n11 - n01)
    return lower + v * (upper - lower)


def _manifold_arrays(solid, object_id):
    """Vertices, triangles and per-triangle fracture flags (not from the original object) of a Manifold."""
    mesh = solid.to_mesh64()
    v = np.array(mesh.vert_properties, np.float64)[:, :3]
    f = np.array(mesh.tri_verts, np.int64)
    run_index = np.asarray(mesh.run_index, np.int64)
    run_ids = np.asarray(mesh.run_original_id)
    fracture = np.repeat(run_ids != object_id, np.diff(run_index) // 3)  # run_index counts tri_verts entries
    return v, f, fracture


def _random_unit(rng, dim=3):
    while True:
        x = rng.normal(size=dim)
        n = np.linalg.norm(x)
        if n > 1e-6:
            return x / n


def _frame(normal):
    """Two unit vectors completing `normal` to a right-handed orthonormal frame (u, w, normal)."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(helper, normal)
    u /= np.linalg.norm(u)
    return u, np.cross(normal, u)


def _weighted_quantile(values, weights, q):
    order = np.argsort(values)
    cum = np.cumsum(weights[order])
    return float(values[order][np.searchsorted(cum, q * cum[-1])])
