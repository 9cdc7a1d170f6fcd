"""Family 4: ICP nearest neighbours and the reductions of the rigid fit (Warp).

Nearest neighbours are exact. Small sets: brute force over all targets. Large
sets: a dense uniform grid (cells numbered x-fastest, at most a few cells per
target); targets are counted into cells (atomics), the counts scanned and the
targets scattered so that each cell's points, and so each x-row of cells, are
contiguous. Queries are sorted into the same cells so that neighbouring threads
read the same cells. A query visits the shells of cells around its own cell,
ring after ring, and stops once the best distance found is no larger than the
distance from the query to the nearest cell not yet visited, so the answer is
the true nearest. Ties go to the lowest target index, so results do not depend
on thread timing.

Search coordinates are float32, shifted by the target bounding-box centre; the
distance returned is recomputed in float64 from the original coordinates.
The cross-covariance sums run in float64 (a float32 sum of a million terms
loses three to four digits).
"""
import warp as wp

wp.set_module_options({"enable_backward": False})

@wp.func
def cell_of(p: wp.vec3, origin: wp.vec3, inv_h: float, dims: wp.vec3i) -> wp.vec3i:
    # clamp before the cast: a far query must not overflow the integer
    q = (p - origin) * inv_h
    return wp.vec3i(
        int(wp.clamp(wp.floor(q[0]), 0.0, float(dims[0] - 1))),
        int(wp.clamp(wp.floor(q[1]), 0.0, float(dims[1] - 1))),
        int(wp.clamp(wp.floor(q[2]), 0.0, float(dims[2] - 1))),
    )


@wp.func
def axis_gap(q: float, origin: float, h: float, cell: int) -> float:
    # distance along one axis from q to the slab of a cell (targets all lie inside
    # the grid), less a margin for the float32 rounding that placed them in cells
    lo = origin + float(cell) * h
    gap = wp.max(wp.max(lo - q, q - (lo + h)), 0.0)
    return wp.max(gap - 1.0e-4 * h - 2.0e-7 * (wp.abs(q) + wp.abs(origin)), 0.0)


@wp.func
def cell_index(x: int, y: int, z: int, dims: wp.vec3i) -> int:
    return x + dims[0] * (y + dims[1] * z)


@wp.kernel
def bounds_partial(
    points: wp.array(dtype=wp.vec3d),
    n: int,
    lo: wp.array(dtype=wp.vec3d),
    hi: wp.array(dtype=wp.vec3d),
    bad: wp.array(dtype=wp.int32),
):
    # per thread: bounds of a strided share of the points, and a count of non-finite ones
    t = wp.tid()
    stride = lo.shape[0]
    big = wp.float64(1.0e308)
    a = wp.vec3d(big, big, big)
    b = wp.vec3d(-big, -big, -big)
    nonfinite = int(0)
    i = t
    while i < n:
        p = points[i]
        if wp.isfinite(p):
            a = wp.min(a, p)
            b = wp.max(b, p)
        else:
            nonfinite += 1
        i += stride
    lo[t] = a
    hi[t] = b
    bad[t] = nonfinite


@wp.kernel
def shift_to_float32(points: wp.array(dtype=wp.vec3d), centre: wp.vec3d, out: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    p = points[i] - centre
    out[i] = wp.vec3(wp.float32(p[0]), wp.float32(p[1]), wp.float32(p[2]))


@wp.kernel
def grid_count(
    points: wp.array(dtype=wp.vec3),
    origin: wp.vec3,
    inv_h: float,
    dims: wp.vec3i,
    counts: wp.array(dtype=wp.int32),
    occupied: wp.array(dtype=wp.int32),
):
    i = wp.tid()
    c = cell_of(points[i], origin, inv_h, dims)
    old = wp.atomic_add(counts, cell_index(c[0], c[1], c[2], dims), 1)
    if old == 0:
        wp.atomic_add(occupied, 0, 1)


@wp.kernel
def grid_scatter(
    points: wp.array(dtype=wp.vec3),
    origin: wp.vec3,
    inv_h: float,
    dims: wp.vec3i,
    starts: wp.array(dtype=wp.int32),
    fill: wp.array(dtype=wp.int32),
    sorted_points: wp.array(dtype=wp.vec3),
    sorted_ids: wp.array(dtype=wp.int32),
):
    i = wp.tid()
    p = points[i]
    c = cell_of(p, origin, inv_h, dims)
    b = cell_index(c[0], c[1], c[2], dims)
    slot = starts[b] + wp.atomic_add(fill, b, 1)
    sorted_points[slot] = p
    sorted_ids[slot] = i


@wp.kernel
def grid_query(
    queries: wp.array(dtype=wp.vec3),  # sorted by cell, so neighbouring threads share cells
    query_ids: wp.array(dtype=wp.int32),
    origin: wp.vec3,
    h: float,
    inv_h: float,
    dims: wp.vec3i,
    starts: wp.array(dtype=wp.int32),
    sorted_points: wp.array(dtype=wp.vec3),
    sorted_ids: wp.array(dtype=wp.int32),
    reach2: float,  # squared reach: no point beyond it is looked for (3e38: none)
    out_idx: wp.array(dtype=wp.int32),
):
    t = wp.tid()
    q = queries[t]
    c = cell_of(q, origin, inv_h, dims)
    best = reach2
    best_id = int(2147483647)  # kept where no point lies within reach
    r = int(0)
    while True:
        z0 = wp.max(c[2] - r, 0)
        z1 = wp.min(c[2] + r, dims[2] - 1)
        y0 = wp.max(c[1] - r, 0)
        y1 = wp.min(c[1] + r, dims[1] - 1)
        x0 = wp.max(c[0] - r, 0)
        x1 = wp.min(c[0] + r, dims[0] - 1)
        for z in range(z0, z1 + 1):
            z_face = z == c[2] - r or z == c[2] + r
            dz = axis_gap(q[2], origin[2], h, z)
            for y in range(y0, y1 + 1):
                # skip rows whose box is no nearer than the best so far (a tie may go
                # either way), and within a row keep only the cells that can be nearer
                dy = axis_gap(q[1], origin[1], h, y)
                room = best - (dy * dy + dz * dz)
                if room > 0.0:
                    reach = wp.sqrt(room) + 1.0e-4 * h
                    xa = int(wp.clamp(wp.floor((q[0] - reach - origin[0]) * inv_h), -1.0, float(dims[0])))
                    xb = int(wp.clamp(wp.floor((q[0] + reach - origin[0]) * inv_h), -1.0, float(dims[0])))
                    row = dims[0] * (y + dims[1] * z)
                    # a row on the shell's faces is new from x0 to x1 (one contiguous run
                    # of points); inside the shell only its two end cells are new
                    face = z_face or y == c[1] - r or y == c[1] + r
                    for part in range(2):
                        lo = int(1)
                        hi = int(0)
                        if face:
                            if part == 0:
                                lo = wp.max(x0, xa)
                                hi = wp.min(x1, xb)
                        else:
                            x = c[0] - r + part * 2 * r
                            if x >= 0 and x < dims[0] and x >= xa and x <= xb:
                                lo = x
                                hi = x
                        if lo <= hi:
                            for j in range(starts[row + lo], starts[row + hi + 1]):
                                d = sorted_points[j] - q
                                d2 = wp.dot(d, d)
                                k = sorted_ids[j]
                                if d2 < best or (d2 == best and k < best_id):
                                    best = d2
                                    best_id = k
        # distance from q to the nearest cell not visited yet
        bound = float(3.0e38)
        more = False
        for a in range(3):
            if c[a] - r > 0:
                bound = wp.min(bound, q[a] - (origin[a] + float(c[a] - r) * h))
                more = True
            if c[a] + r < dims[a] - 1:
                bound = wp.min(bound, origin[a] + float(c[a] + r + 1) * h - q[a])
                more = True
        if not more:
            break
        if bound > 0.0 and best <= bound * bound:
            break
        r += 1
    out_idx[query_ids[t]] = best_id


@wp.kernel
def brute_query(
    queries: wp.array(dtype=wp.vec3),
    targets: wp.array(dtype=wp.vec3),
    out_idx: wp.array(dtype=wp.int32),
):
    t = wp.tid()
    q = queries[t]
    best = float(3.0e38)
    best_id = int(0)
    for j in range(targets.shape[0]):
        d = targets[j] - q
        d2 = wp.dot(d, d)
        if d2 < best:
            best = d2
            best_id = j
    out_idx[t] = best_id


@wp.kernel
def exact_distance(
    source: wp.array(dtype=wp.vec3d),
    target: wp.array(dtype=wp.vec3d),
    idx: wp.array(dtype=wp.int32),
    out: wp.array(dtype=wp.float64),
):
    t = wp.tid()
    if idx[t] == 2147483647:  # none within the query's reach (_prep.NO_POINT)
        out[t] = wp.float64(wp.inf)
        return
    d = source[t] - target[idx[t]]
    out[t] = wp.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])


@wp.kernel
def weighted_sums_partial(
    s: wp.array(dtype=wp.vec3d),
    t: wp.array(dtype=wp.vec3d),
    w: wp.array(dtype=wp.float64),
    n: int,
    out: wp.array2d(dtype=wp.float64),
):
    # per thread: [sum w, sum w*s (3), sum w*t (3)]
    k = wp.tid()
    stride = out.shape[0]
    ws = wp.float64(0.0)
    ss = wp.vec3d()
    ts = wp.vec3d()
    i = k
    while i < n:
        wi = w[i]
        ws += wi
        ss += wi * s[i]
        ts += wi * t[i]
        i += stride
    out[k, 0] = ws
    for a in range(3):
        out[k, 1 + a] = ss[a]
        out[k, 4 + a] = ts[a]


@wp.kernel
def covariance_partial(
    s: wp.array(dtype=wp.vec3d),
    t: wp.array(dtype=wp.vec3d),
    w: wp.array(dtype=wp.float64),
    cs: wp.vec3d,
    ct: wp.vec3d,
    n: int,
    out: wp.array2d(dtype=wp.float64),
):
    k = wp.tid()
    stride = out.shape[0]
    h = wp.mat33d()
    i = k
    while i < n:
        h += w[i] * wp.outer(s[i] - cs, t[i] - ct)
        i += stride
    for a in range(3):
        for b in range(3):
            out[k, 3 * a + b] = h[a, b]
