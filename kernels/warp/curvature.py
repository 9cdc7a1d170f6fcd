"""Family 2: per-point contour features [kcos, kappa, tau, chord_right, chord_left] (Warp).

Same formulas as relicgpu.backends.numpy.contour_features (Eq. 13-16, 25-28):
k-cosine with weights 1 / (|a_m| + |b_m|), discrete curvature and torsion by
central differences at step `stride` over the local chord length h, and the two
chords. Indices wrap around (closed contour). Points arrive as float32 shifted
to their bounding-box centre.
"""
import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def wrap(i: int, n: int) -> int:
    j = i % n
    if j < 0:
        j += n
    return j


@wp.kernel
def contour_features_kernel(
    points: wp.array(dtype=wp.vec3),
    k: int,
    stride: int,
    out: wp.array2d(dtype=wp.float32),
):
    i = wp.tid()
    n = points.shape[0]
    p = points[i]

    cos_sum = float(0.0)
    w_sum = float(0.0)
    for m in range(1, k + 1):
        a = p - points[wrap(i + m, n)]
        b = p - points[wrap(i - m, n)]
        la = wp.length(a)
        lb = wp.length(b)
        cm = float(-1.0)  # a zero vector counts as a straight run
        if la > 0.0 and lb > 0.0:
            cm = wp.dot(a, b) / (la * lb)
        if la + lb > 0.0:
            w = 1.0 / (la + lb)
            cos_sum += w * cm
            w_sum += w
    kcos = float(-1.0)
    if w_sum > 0.0:
        kcos = cos_sum / w_sum

    s = stride
    p_next = points[wrap(i + s, n)]
    p_prev = points[wrap(i - s, n)]
    lr = wp.length(p_next - p)
    ll = wp.length(p - p_prev)
    h = 0.5 * (lr + ll)
    kappa = float(0.0)
    tau = float(0.0)
    if h > 0.0:
        d1 = (p_next - p_prev) / (2.0 * h)
        d2 = (p_next - 2.0 * p + p_prev) / (h * h)
        d3 = (points[wrap(i + 2 * s, n)] - 2.0 * p_next + 2.0 * p_prev - points[wrap(i - 2 * s, n)]) / (2.0 * h * h * h)
        c = wp.cross(d1, d2)
        c_len = wp.length(c)
        d1_len = wp.length(d1)
        if d1_len > 0.0:
            kappa = c_len / (d1_len * d1_len * d1_len)
        if c_len > 0.0:
            tau = wp.dot(c, d3) / (c_len * c_len)
    out[i, 0] = kcos
    out[i, 1] = kappa
    out[i, 2] = tau
    out[i, 3] = lr
    out[i, 4] = ll
