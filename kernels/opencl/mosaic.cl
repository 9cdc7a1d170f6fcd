// OpenCL kernels of the image mosaic (paper sections 3.3.2 and 3.4).
// The float64 specification is relicgpu.backends.numpy (led, block_entropy);
// OpenCLBackend.led and OpenCLBackend.block_entropy launch these.
// Global size is (width, height) rounded up to whole work-groups: get_global_id(0) is the
// column, and every kernel checks its bounds.

#define MOSAIC_MAX_LEVELS 64

// LED (Eq. 4), pass 1: sum of src over columns x-A..x+A (zeros outside the image).
__kernel void led_rows(__global const float *src, const int height, const int width,
                       const int radius, __global float *out)
{
    const int x = get_global_id(0);
    const int y = get_global_id(1);
    if (x >= width || y >= height) return;
    const int lo = max(x - radius, 0);
    const int hi = min(x + radius, width - 1);
    float s = 0.0f;
    for (int c = lo; c <= hi; ++c) s += src[y * width + c];
    out[y * width + x] = s;
}

// LED (Eq. 4), pass 2: sum of the row sums over rows y-A..y+A, times 1/(2A+1)^2.
__kernel void led_cols(__global const float *rows, const int height, const int width,
                       const int radius, const float scale, __global float *out)
{
    const int x = get_global_id(0);
    const int y = get_global_id(1);
    if (x >= width || y >= height) return;
    const int lo = max(y - radius, 0);
    const int hi = min(y + radius, height - 1);
    float s = 0.0f;
    for (int r = lo; r <= hi; ++r) s += rows[r * width + x];
    out[y * width + x] = s * scale;
}

// Local entropy (Eq. 8) of the block x block block whose top-left is (y, x):
// 1 - sum_l P(l)^2 over the levels 0..n_levels-1 (n_levels <= 64). Levels are reals in
// [0, n_levels-1]: v adds 1 - frac(v) to bin floor(v) and frac(v) to the next one.
// The output is (height-block+1) x (width-block+1).
__kernel void block_entropy(__global const float *levels, const int height, const int width,
                            const int block, const int n_levels, __global float *out)
{
    const int out_w = width - block + 1;
    const int out_h = height - block + 1;
    const int x = get_global_id(0);
    const int y = get_global_id(1);
    if (x >= out_w || y >= out_h) return;
    float counts[MOSAIC_MAX_LEVELS];
    for (int l = 0; l < n_levels; ++l) counts[l] = 0.0f;
    for (int dy = 0; dy < block; ++dy) {
        for (int dx = 0; dx < block; ++dx) {
            const float v = levels[(y + dy) * width + x + dx];
            const int lo = min((int)floor(v), n_levels - 1);
            const float f = v - (float)lo;
            counts[lo] += 1.0f - f;
            if (f > 0.0f) counts[lo + 1] += f;
        }
    }
    float s = 0.0f;
    for (int l = 0; l < n_levels; ++l) s += counts[l] * counts[l];
    const float n = (float)(block * block);
    out[y * out_w + x] = 1.0f - s / (n * n);
}
