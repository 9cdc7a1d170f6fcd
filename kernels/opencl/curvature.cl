/* Family 2: per-point contour features [kcos, kappa, tau, chord_right, chord_left]
   (OpenCL). Same formulas as relicgpu.backends.numpy.contour_features (Eq. 13-16,
   25-28); indices wrap around (closed contour). Computed in REAL, double where the
   device has it: second and third differences at a small step cancel most leading
   digits, and float32 would leave about three significant digits of kappa. */

#ifdef HAVE_FP64
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
typedef double REAL;
typedef double3 REAL3;
#else
typedef float REAL;
typedef float3 REAL3;
#endif

static inline int wrap_index(int i, int n)
{
    int j = i % n;
    return j < 0 ? j + n : j;
}

__kernel void contour_features(__global const REAL *points, const int n, const int k, const int stride,
                               __global REAL *out)
{
    const int i = get_global_id(0);
    if (i >= n) return;
    const REAL3 p = vload3(i, points);

    REAL cos_sum = 0, w_sum = 0;
    for (int m = 1; m <= k; ++m) {
        const REAL3 a = p - vload3(wrap_index(i + m, n), points);
        const REAL3 b = p - vload3(wrap_index(i - m, n), points);
        const REAL la = length(a), lb = length(b);
        const REAL c = (la > 0 && lb > 0) ? dot(a, b) / (la * lb) : -1;  /* zero vector: straight */
        if (la + lb > 0) {
            const REAL w = 1 / (la + lb);
            cos_sum += w * c;
            w_sum += w;
        }
    }
    const REAL kcos = w_sum > 0 ? cos_sum / w_sum : -1;

    const int s = stride;
    const REAL3 p_next = vload3(wrap_index(i + s, n), points);
    const REAL3 p_prev = vload3(wrap_index(i - s, n), points);
    const REAL lr = length(p_next - p), ll = length(p - p_prev);
    const REAL h = 0.5 * (lr + ll);
    REAL kappa = 0, tau = 0;
    if (h > 0) {
        const REAL3 d1 = (p_next - p_prev) / (2 * h);
        const REAL3 d2 = (p_next - 2 * p + p_prev) / (h * h);
        const REAL3 d3 = (vload3(wrap_index(i + 2 * s, n), points) - 2 * p_next + 2 * p_prev
                           - vload3(wrap_index(i - 2 * s, n), points)) / (2 * h * h * h);
        const REAL3 c = cross(d1, d2);
        const REAL c_len = length(c), d1_len = length(d1);
        if (d1_len > 0) kappa = c_len / (d1_len * d1_len * d1_len);
        if (c_len > 0) tau = dot(c, d3) / (c_len * c_len);
    }
    __global REAL *o = out + (size_t)i * 5;
    o[0] = kcos;
    o[1] = kappa;
    o[2] = tau;
    o[3] = lr;
    o[4] = ll;
}
