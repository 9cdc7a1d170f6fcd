/* Family 4: ICP nearest neighbours and the reductions of the rigid fit (OpenCL).

   Nearest neighbours are exact. Small sets: brute force, targets staged through
   local memory in tiles. Large sets: a dense uniform grid (cells numbered
   x-fastest, a few cells per target at most); targets are counted into cells
   (atomics), the counts scanned (on the host) and the targets scattered so that
   each cell's points, and so each x-row of cells, are contiguous. Queries are
   sorted into the same cells. A query visits the shells of cells around its own
   cell, ring after ring, and stops once the best distance found is no larger
   than the distance to the nearest cell not visited yet: the true nearest.
   Ties go to the lowest target index. Search coordinates are float32 shifted by
   the target bounding-box centre; the returned distance is recomputed in REAL
   (double where the device has it) from the original coordinates, and the
   cross-covariance sums run in REAL. Points are packed xyz triples. */

#ifdef HAVE_FP64
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
typedef double REAL;
typedef double3 REAL3;
#else
typedef float REAL;
typedef float3 REAL3;
#endif

#define NO_ID 2147483647

static inline int3 cell_of(const float3 p, const float3 origin, const float inv_h, const int3 dims)
{
    /* clamp before the cast: a far query must not overflow the integer */
    const float3 q = floor((p - origin) * inv_h);
    return convert_int3(clamp(q, (float3)(0.0f), convert_float3(dims - 1)));
}

/* distance along one axis from q to the slab of a cell (targets all lie inside
   the grid), less a margin for the float32 rounding that placed them in cells */
static inline float axis_gap(const float q, const float origin, const float h, const int cell)
{
    const float lo = origin + (float)cell * h;
    const float gap = fmax(fmax(lo - q, q - (lo + h)), 0.0f);
    return fmax(gap - 1.0e-4f * h - 2.0e-7f * (fabs(q) + fabs(origin)), 0.0f);
}

static inline int cell_index(const int3 c, const int3 dims)
{
    return c.x + dims.x * (c.y + dims.y * c.z);
}

__kernel void bounds_partial(__global const REAL *points, const int n, const int threads,
                             __global REAL *lo, __global REAL *hi, __global int *bad)
{
    const int t = get_global_id(0);
    if (t >= threads) return;
    REAL3 a = (REAL3)(INFINITY), b = (REAL3)(-INFINITY);
    int nonfinite = 0;
    for (int i = t; i < n; i += threads) {
        const REAL3 p = vload3(i, points);
        if (isfinite(p.x) && isfinite(p.y) && isfinite(p.z)) {
            a = fmin(a, p);
            b = fmax(b, p);
        } else {
            ++nonfinite;
        }
    }
    vstore3(a, t, lo);
    vstore3(b, t, hi);
    bad[t] = nonfinite;
}

__kernel void shift_to_float32(__global const REAL *points, const int n, const REAL cx, const REAL cy, const REAL cz,
                               __global float *out)
{
    const int i = get_global_id(0);
    if (i >= n) return;
    const REAL3 p = vload3(i, points) - (REAL3)(cx, cy, cz);
    vstore3(convert_float3(p), i, out);
}

__kernel void grid_count(__global const float *points, const int n, const float ox, const float oy, const float oz,
                         const float inv_h, const int dx, const int dy, const int dz,
                         __global int *counts, __global int *occupied)
{
    const int i = get_global_id(0);
    if (i >= n) return;
    const int3 dims = (int3)(dx, dy, dz);
    const int3 c = cell_of(vload3(i, points), (float3)(ox, oy, oz), inv_h, dims);
    if (atomic_inc(&counts[cell_index(c, dims)]) == 0) atomic_inc(occupied);
}

__kernel void grid_scatter(__global const float *points, const int n, const float ox, const float oy, const float oz,
                           const float inv_h, const int dx, const int dy, const int dz,
                           __global const int *starts, __global int *fill,
                           __global float *sorted_points, __global int *sorted_ids)
{
    const int i = get_global_id(0);
    if (i >= n) return;
    const int3 dims = (int3)(dx, dy, dz);
    const float3 p = vload3(i, points);
    const int b = cell_index(cell_of(p, (float3)(ox, oy, oz), inv_h, dims), dims);
    const int slot = starts[b] + atomic_inc(&fill[b]);
    vstore3(p, slot, sorted_points);
    sorted_ids[slot] = i;
}

__kernel void grid_query(__global const float *queries, __global const int *query_ids, const int n,
                         const float ox, const float oy, const float oz, const float h, const float inv_h,
                         const int dx, const int dy, const int dz,
                         __global const int *starts, __global const float *sorted_points,
                         __global const int *sorted_ids, const float reach2, __global int *out_idx)
{
    /* reach2: the squared reach, no point beyond it is looked for (3e38: none); NO_ID stays
       where no point lies within it */
    const int t = get_global_id(0);
    if (t >= n) return;
    const int3 dims = (int3)(dx, dy, dz);
    const float3 origin = (float3)(ox, oy, oz);
    const float3 q = vload3(t, queries);
    const int3 c = cell_of(q, origin, inv_h, dims);
    float best = reach2;
    int best_id = NO_ID;
    for (int r = 0;; ++r) {
        const int z0 = max(c.z - r, 0), z1 = min(c.z + r, dims.z - 1);
        const int y0 = max(c.y - r, 0), y1 = min(c.y + r, dims.y - 1);
        const int x0 = max(c.x - r, 0), x1 = min(c.x + r, dims.x - 1);
        for (int z = z0; z <= z1; ++z) {
            const bool z_face = z == c.z - r || z == c.z + r;
            const float dz = axis_gap(q.z, oz, h, z);
            for (int y = y0; y <= y1; ++y) {
                /* skip rows whose box is no nearer than the best so far (a tie may go
                   either way), and within a row keep only the cells that can be nearer */
                const float dy = axis_gap(q.y, oy, h, y);
                const float room = best - (dy * dy + dz * dz);
                if (!(room > 0.0f)) continue;
                const float reach = sqrt(room) + 1.0e-4f * h;
                const int xa = (int)clamp(floor((q.x - reach - ox) * inv_h), -1.0f, (float)dims.x);
                const int xb = (int)clamp(floor((q.x + reach - ox) * inv_h), -1.0f, (float)dims.x);
                const int row = dims.x * (y + dims.y * z);
                /* a row on the shell's faces is new from x0 to x1 (one contiguous run
                   of points); inside the shell only its two end cells are new */
                const bool face = z_face || y == c.y - r || y == c.y + r;
                for (int part = 0; part < 2; ++part) {
                    int lo = 1, hi = 0;
                    if (face) {
                        if (part == 0) { lo = max(x0, xa); hi = min(x1, xb); }
                    } else {
                        const int x = c.x - r + part * 2 * r;
                        if (x >= 0 && x < dims.x && x >= xa && x <= xb) { lo = x; hi = x; }
                    }
                    if (lo > hi) continue;
                    const int j1 = starts[row + hi + 1];
                    for (int j = starts[row + lo]; j < j1; ++j) {
                        const float3 d = vload3(j, sorted_points) - q;
                        const float d2 = dot(d, d);
                        const int k = sorted_ids[j];
                        if (d2 < best || (d2 == best && k < best_id)) { best = d2; best_id = k; }
                    }
                }
            }
        }
        /* distance from q to the nearest cell not visited yet */
        float bound = 3.0e38f;
        bool more = false;
        const float qa[3] = {q.x, q.y, q.z}, oa[3] = {ox, oy, oz};
        const int ca[3] = {c.x, c.y, c.z}, da[3] = {dx, dy, dz};
        for (int a = 0; a < 3; ++a) {
            if (ca[a] - r > 0) { bound = fmin(bound, qa[a] - (oa[a] + (float)(ca[a] - r) * h)); more = true; }
            if (ca[a] + r < da[a] - 1) { bound = fmin(bound, oa[a] + (float)(ca[a] + r + 1) * h - qa[a]); more = true; }
        }
        if (!more) break;
        if (bound > 0.0f && best <= bound * bound) break;
    }
    out_idx[query_ids[t]] = best_id;
}

#define TILE 128

__kernel void brute_query(__global const float *queries, const int n, __global const float *targets, const int m,
                          __global int *out_idx)
{
    __local float tile[3 * TILE];
    const int t = get_global_id(0);
    const int lid = get_local_id(0), lsz = get_local_size(0);
    const float3 q = t < n ? vload3(t, queries) : (float3)(0.0f);
    float best = 3.0e38f;
    int best_id = 0;
    for (int base = 0; base < m; base += TILE) {
        const int count = min(TILE, m - base);
        barrier(CLK_LOCAL_MEM_FENCE);
        for (int k = lid; k < 3 * count; k += lsz) tile[k] = targets[3 * base + k];
        barrier(CLK_LOCAL_MEM_FENCE);
        for (int j = 0; j < count; ++j) {
            const float3 d = vload3(j, tile) - q;
            const float d2 = dot(d, d);
            if (d2 < best) { best = d2; best_id = base + j; }
        }
    }
    if (t < n) out_idx[t] = best_id;
}

__kernel void exact_distance(__global const REAL *source, __global const REAL *target, __global const int *idx,
                             const int n, __global REAL *out)
{
    const int t = get_global_id(0);
    if (t >= n) return;
    if (idx[t] == NO_ID) { out[t] = (REAL)INFINITY; return; }  /* none within the query's reach */
    const REAL3 d = vload3(t, source) - vload3(idx[t], target);
    out[t] = sqrt(d.x * d.x + d.y * d.y + d.z * d.z);
}

/* per work-item: [sum w, sum w*s (3), sum w*t (3)] over a strided share */
__kernel void weighted_sums_partial(__global const REAL *s, __global const REAL *tt, __global const REAL *w,
                                    const int n, const int threads, __global REAL *out)
{
    const int k = get_global_id(0);
    if (k >= threads) return;
    REAL ws = 0;
    REAL3 ss = (REAL3)(0), ts = (REAL3)(0);
    for (int i = k; i < n; i += threads) {
        const REAL wi = w[i];
        ws += wi;
        ss += wi * vload3(i, s);
        ts += wi * vload3(i, tt);
    }
    __global REAL *o = out + (size_t)k * 7;
    o[0] = ws;
    o[1] = ss.x; o[2] = ss.y; o[3] = ss.z;
    o[4] = ts.x; o[5] = ts.y; o[6] = ts.z;
}

__kernel void covariance_partial(__global const REAL *s, __global const REAL *tt, __global const REAL *w,
                                 const REAL csx, const REAL csy, const REAL csz,
                                 const REAL ctx, const REAL cty, const REAL ctz,
                                 const int n, const int threads, __global REAL *out)
{
    const int k = get_global_id(0);
    if (k >= threads) return;
    const REAL3 cs = (REAL3)(csx, csy, csz), ct = (REAL3)(ctx, cty, ctz);
    REAL3 r0 = (REAL3)(0), r1 = (REAL3)(0), r2 = (REAL3)(0);
    for (int i = k; i < n; i += threads) {
        const REAL3 a = w[i] * (vload3(i, s) - cs);
        const REAL3 b = vload3(i, tt) - ct;
        r0 += a.x * b;
        r1 += a.y * b;
        r2 += a.z * b;
    }
    __global REAL *o = out + (size_t)k * 9;
    o[0] = r0.x; o[1] = r0.y; o[2] = r0.z;
    o[3] = r1.x; o[4] = r1.y; o[5] = r1.z;
    o[6] = r2.x; o[7] = r2.y; o[8] = r2.z;
}
