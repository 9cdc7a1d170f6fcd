/* Point-pair-feature votes (OpenCL): per scene reference, the best (model point, angle bin)
   cell of Drost's vote row and its total.

   The host lays out the model pairs that vote (`_prep.PpfVotes.voting_model`): bucket k
   is records start[k]:start[k + 1], at most bucket_cap of them, already spread over a
   larger bucket, each (model point, angle, weight).

   A work-item owns one dense row of n_model * alpha_bins REAL cells in `rows` and takes
   the scene references t, t + T, t + 2T, ... in turn. For a reference it walks the
   reference's scene pairs in table order and, for each, the records of its key, adding
   each vote to its cell: the reference's bincount additions in the same order (bit for
   bit where REAL is double: a vote's weight is a product of two float32 numbers, exact in
   double). No atomics; the result does not depend on timing.

   The argmax is kept while voting: weights are >= 0, so a cell's total only grows, and
   the first largest cell of the finished row is the one that, when it reached its final
   total, beat the running best or tied it at a lower index (the best starts as cell 0 at
   total 0). A cell that leaves zero is listed in `touched` (up to `width`, each work-item
   having width + 1 slots); afterwards the listed cells are zeroed again, or the whole row
   where more were touched, so the row is clean for the next reference at the cost of the
   votes, not of the row. */

#ifdef HAVE_FP64
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
typedef double REAL;
#else
typedef float REAL;
#endif

/* no fused multiply-adds: the angle bins must round as the reference's float32 steps do */
#pragma OPENCL FP_CONTRACT OFF

static inline int angle_bin(const float m_alpha, const float s_alpha, const float shift, const float scale,
                            const int alpha_bins)
{
    /* float32 as in the reference: (alpha_m - alpha_s + pi) * bins / 2pi, floored, taken mod
       bins; angles in [-pi, pi] land within one turn of the range, the rest take the slow way */
    const float d = m_alpha - s_alpha;
    const float x = d + shift;
    int b = (int)floor(x * scale);
    if (b < 0)
        b += alpha_bins;
    else if (b >= alpha_bins)
        b -= alpha_bins;
    if (b < 0 || b >= alpha_bins)
        b = ((b % alpha_bins) + alpha_bins) % alpha_bins;
    return b;
}

/* model: 3 floats per voting model pair (model point, angle, weight), bucket k at
   start[k]:start[k + 1] */
__kernel void ppf_votes(__global const int *start, const long last_key, __global const float *model,
                        __global const int *s_offsets, __global const long *s_key, __global const float *s_alpha,
                        __global const float *s_weight, const int n_refs, const int alpha_bins, const float shift,
                        const float scale, const int n_threads, const int row, __global REAL *rows,
                        const int width, __global int *touched, __global int *best_cell, __global REAL *best_votes)
{
    const int t = get_global_id(0);
    if (t >= n_threads)
        return;
    __global REAL *mine = rows + (long)t * row;
    __global int *listed = touched + (long)t * (width + 1);
    for (int r = t; r < n_refs; r += n_threads) {
        REAL best_v = 0;
        int best_c = 0, n_touched = 0;
        for (int s = s_offsets[r]; s < s_offsets[r + 1]; ++s) {
            const long k = min(s_key[s], last_key);
            const float a_s = s_alpha[s];
            const REAL ws = (REAL)s_weight[s];
            for (int m = start[k]; m < start[k + 1]; ++m) {
                const float3 pair = vload3(m, model);
                const int c = (int)pair.x * alpha_bins + angle_bin(pair.y, a_s, shift, scale, alpha_bins);
                const REAL old = mine[c];
                const REAL v = old + (REAL)pair.z * ws;
                mine[c] = v;
                /* listed whether new or not (a cell not new is overwritten by the next one), the
                   slot past the list a sink once it is full: no branch to mispredict */
                listed[min(n_touched, width)] = c;
                n_touched += old == 0;
                if (v > best_v || (v == best_v && c < best_c)) {
                    best_v = v;
                    best_c = c;
                }
            }
        }
        if (n_touched <= width)
            for (int j = 0; j < n_touched; ++j)
                mine[listed[j]] = 0;
        else
            for (int j = 0; j < row; ++j)
                mine[j] = 0;
        best_cell[r] = best_c;
        best_votes[r] = best_v;
    }
}
