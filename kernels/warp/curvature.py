"""Family 2: per-point contour features [kcos, kappa, tau, chord_right, chord_left] (Warp).

Same formulas as relicgpu.backends.numpy.contour_features (Eq. 13-16, 25-28):
k-cosine with weights 1 / (|a_m| + |b_m|), discrete curvature and torsion by
central differences at step `stride` over the local chord length h, and the two
chords. Indices wrap around (closed contour).

This family computes in float64: second and third differences at a small step
cancel most of the leading digits (float32 would leave about three significant
digits of kappa and one of tau on a 1000-point contour), and contours are small.
"""
import warp as wp

wp.set_module_options({"enable_backward": False})

ZERO = wp.constant(wp.float64(0.0))
ONE = wp.constant(wp.float64(1.0))
TWO = wp.constant(wp.float64(2.0))
HALF = wp.constant(wp.float64(0.5))


@wp.func
def wrap(i: int, n: int) -> int:
    j = i % n
    if j < 0:
        j += n
    return j


@wp.kernel
def contour_features(
    points: wp.array(dtype=wp.vec3d),
    k: int,
    stride: int,
    out: wp.array2d(dtype=wp.float64),
):
    i = wp.tid()
    n = points.shape[0]
    p = points[i]

    cos_sum = ZERO
    w_sum = ZERO
    for m in range(1, k + 1):
        a = p - points[wrap(i + m, n)]
        b = p - points[wrap(i - m, n)]
        la = wp.length(a)
        lb = wp.length(b)
        cm = -ONE  # a zero vector counts as a straight run
        if la > ZERO and lb > ZERO:
            cm = wp.dot(a, b) / (la * lb)
        if la + lb > ZERO:
            w = ONE / (la + lb)
            cos_sum += w * cm
            w_sum += w
    kcos = -ONE
    if w_sum > ZERO:
        kcos = cos_sum / w_sum

    s = stride
    p_next = points[wrap(i + s, n)]
    p_prev = points[wrap(i - s, n)]
    lr = wp.length(p_next - p)
    ll = wp.length(p - p_prev)
    h = HALF * (lr + ll)
    kappa = ZERO
    tau = ZERO
    if h > ZERO:
        d1 = (p_next - p_prev) / (TWO * h)
        d2 = (p_next - TWO * p + p_prev) / (h * h)
        d3 = (points[wrap(i + 2 * s, n)] - TWO * p_next + TWO * p_prev - points[wrap(i - 2 * s, n)]) / (TWO * h * h * h)
        c = wp.cross(d1, d2)
        c_len = wp.length(c)
        d1_len = wp.length(d1)
        if d1_len > ZERO:
            kappa = c_len / (d1_len * d1_len * d1_len)
        if c_len > ZERO:
            tau = wp.dot(c, d3) / (c_len * c_len)
    out[i, 0] = kcos
    out[i, 1] = kappa
    out[i, 2] = tau
    out[i, 3] = lr
    out[i, 4] = ll
