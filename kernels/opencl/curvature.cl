/* Family 2: per-point contour features [kcos, kappa, tau, chord_right, chord_left]
   (OpenCL). Same formulas as relicgpu.backends.numpy.contour_features (Eq. 13-16,
   25-28); indices wrap around (closed contour). Points arrive as float32 shifted
   to their bounding-box centre. */

static inline int wrap_index(int i, int n)
{
    int j = i % n;
    return j < 0 ? j + n : j;
}

__kernel void contour_features(__global const float *points, const int n, const int k, const int stride,
                               __global float *out)
{
    const int i = get_global_id(0);
    if (i >= n) return;
    const float3 p = vload3(i, points);

    float cos_sum = 0.0f, w_sum = 0.0f;
    for (int m = 1; m <= k; ++m) {
        const float3 a = p - vload3(wrap_index(i + m, n), points);
        const float3 b = p - vload3(wrap_index(i - m, n), points);
        const float la = length(a), lb = length(b);
        const float c = (la > 0.0f && lb > 0.0f) ? dot(a, b) / (la * lb) : -1.0f;  /* zero vector: straight */
        if (la + lb > 0.0f) {
            const float w = 1.0f / (la + lb);
            cos_sum += w * c;
            w_sum += w;
        }
    }
    const float kcos = w_sum > 0.0f ? cos_sum / w_sum : -1.0f;

    const int s = stride;
    const float3 p_next = vload3(wrap_index(i + s, n), points);
    const float3 p_prev = vload3(wrap_index(i - s, n), points);
    const float lr = length(p_next - p), ll = length(p - p_prev);
    const float h = 0.5f * (lr + ll);
    float kappa = 0.0f, tau = 0.0f;
    if (h > 0.0f) {
        const float3 d1 = (p_next - p_prev) / (2.0f * h);
        const float3 d2 = (p_next - 2.0f * p + p_prev) / (h * h);
        const float3 d3 = (vload3(wrap_index(i + 2 * s, n), points) - 2.0f * p_next + 2.0f * p_prev
                           - vload3(wrap_index(i - 2 * s, n), points)) / (2.0f * h * h * h);
        const float3 c = cross(d1, d2);
        const float c_len = length(c), d1_len = length(d1);
        if (d1_len > 0.0f) kappa = c_len / (d1_len * d1_len * d1_len);
        if (c_len > 0.0f) tau = dot(c, d3) / (c_len * c_len);
    }
    __global float *o = out + (size_t)i * 5;
    o[0] = kcos;
    o[1] = kappa;
    o[2] = tau;
    o[3] = lr;
    o[4] = ll;
}
