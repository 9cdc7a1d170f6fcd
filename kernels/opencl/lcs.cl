/* Family 3: flag matrix and batched bit-parallel LCS lengths (OpenCL).

   Flags: for row value a_i the host supplies a float32 interval thr[i] = (lo, hi)
   such that b passes exactly when float64 |a_i - b| < eps (relicgpu.backends._prep);
   a cell is flagged when lo <= b_j <= hi.

   LCS (Allison-Dix / Hyyro): each flag row is packed into 64-bit words M and the
   row state V advances as V' = (V + (V & M)) | (V & ~M), the addition carrying
   across words; the LCS length is the number of zero bits of V at the end.
   One work-item per pair; columns are walked in blocks of 64 held in registers
   while the rows stream past; the carry leaving a block at row i is kept (one
   bit per row) in `carry` for the next block. */

#define INSIDE(x, lo, hi) ((uint)(((x) >= (lo)) & ((x) <= (hi))))

__kernel void flag_matrix(__global const float2 *thr, __global const float *b,
                          const int n_rows, const int n_cols, __global uchar *flags)
{
    const int j = get_global_id(0);
    const int i = get_global_id(1);
    if (i >= n_rows || j >= n_cols) return;
    const float2 t = thr[i];
    flags[(size_t)i * n_cols + j] = (uchar)INSIDE(b[j], t.x, t.y);
}

#if RELIC_VECTOR_MASKS == 16
/* CPU devices: 16 compares as one vector operation, folded into 16 bits. Only where the
   device compiles 16-wide float compares right: PoCL's LLVM 14 gets this fold wrong for
   CPUs without AVX-512 (haswell, znver3), so the host picks the width by self-check. */
static inline uint mask16(const float16 b, const float lo, const float hi)
{
    const int16 in = (b >= (float16)(lo)) & (b <= (float16)(hi));
    const int16 w = in & (int16)(1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024, 2048, 4096, 8192, 16384, 32768);
    const int8 s8 = w.lo | w.hi;
    const int4 s4 = s8.lo | s8.hi;
    const int2 s2 = s4.lo | s4.hi;
    return (uint)(s2.x | s2.y);
}
#define BLOCK_DECL float16 q0, q1, q2, q3
#define BLOCK_LOAD(src) (q0 = vload16(0, src), q1 = vload16(1, src), q2 = vload16(2, src), q3 = vload16(3, src))
#define ROW_MASK(lo, hi) ((((ulong)(mask16(q2, lo, hi) | (mask16(q3, lo, hi) << 16))) << 32) \
                          | (ulong)(mask16(q0, lo, hi) | (mask16(q1, lo, hi) << 16)))
#elif RELIC_VECTOR_MASKS == 8
/* CPU devices with 8-wide float vectors (AVX2): 8 compares as one operation, 8 bits. */
static inline uint mask8(const float8 b, const float lo, const float hi)
{
    const int8 in = (b >= (float8)(lo)) & (b <= (float8)(hi));
    const int8 w = in & (int8)(1, 2, 4, 8, 16, 32, 64, 128);
    const int4 s4 = w.lo | w.hi;
    const int2 s2 = s4.lo | s4.hi;
    return (uint)(s2.x | s2.y);
}
#define BLOCK_DECL float8 q0, q1, q2, q3, q4, q5, q6, q7
#define BLOCK_LOAD(src) (q0 = vload8(0, src), q1 = vload8(1, src), q2 = vload8(2, src), q3 = vload8(3, src), \
                         q4 = vload8(4, src), q5 = vload8(5, src), q6 = vload8(6, src), q7 = vload8(7, src))
#define MASK32(a, b, c, d, lo, hi) \
    (mask8(a, lo, hi) | (mask8(b, lo, hi) << 8) | (mask8(c, lo, hi) << 16) | (mask8(d, lo, hi) << 24))
#define ROW_MASK(lo, hi) ((((ulong)MASK32(q4, q5, q6, q7, lo, hi)) << 32) | (ulong)MASK32(q0, q1, q2, q3, lo, hi))
#else
/* GPUs (and CPUs where no vector width passes the self-check): one compare pair per
   lane-cell; four OR chains for instruction-level parallelism. */
static inline uint row_mask32(const float *bb, const float lo, const float hi)
{
    uint m0 = 0, m1 = 0, m2 = 0, m3 = 0;
#pragma unroll
    for (int k = 0; k < 8; ++k) {
        m0 |= INSIDE(bb[k], lo, hi) << k;
        m1 |= INSIDE(bb[k + 8], lo, hi) << (k + 8);
        m2 |= INSIDE(bb[k + 16], lo, hi) << (k + 16);
        m3 |= INSIDE(bb[k + 24], lo, hi) << (k + 24);
    }
    return (m0 | m1) | (m2 | m3);
}
static inline void load_block(float *bb, __global const float *src)
{
#pragma unroll
    for (int k = 0; k < 64; ++k) bb[k] = src[k];
}
#define BLOCK_DECL float bb[64]
#define BLOCK_LOAD(src) load_block(bb, src)
#define ROW_MASK(lo, hi) ((((ulong)row_mask32(bb + 32, lo, hi)) << 32) | (ulong)row_mask32(bb, lo, hi))
#endif

__kernel void lcs_lengths(__global const float2 *thr,    /* (lo, hi) per a value */
                          __global const int *a_off,
                          __global const float *b_vals,  /* padded with 64 extra entries */
                          __global const int *b_off,
                          __global const int2 *pairs,
                          __global uint *carry,          /* word w of pair p at w * n_pairs + p */
                          const int n_pairs,
                          __global int *out)
{
    const int p = get_global_id(0);
    if (p >= n_pairs) return;
    const int2 pr = pairs[p];
    const int a0 = a_off[pr.x], m = a_off[pr.x + 1] - a0;
    const int b0 = b_off[pr.y], n = b_off[pr.y + 1] - b0;
    const int nblocks = (n + 63) / 64;
    int total = 0;
    for (int blk = 0; blk < nblocks; ++blk) {
        BLOCK_DECL;
        BLOCK_LOAD(b_vals + b0 + blk * 64);
        const int valid = n - blk * 64;
        const ulong vmask = valid >= 64 ? ~(ulong)0 : (((ulong)1 << valid) - 1);
        ulong v = ~(ulong)0;
        uint cin_word = 0, cout_word = 0;
        float2 t_next = m > 0 ? thr[a0] : (float2)(0.0f);
        for (int i = 0; i < m; ++i) {
            const uint bit = i & 31;
            if (blk > 0 && bit == 0) cin_word = carry[(size_t)(i >> 5) * n_pairs + p];
            /* the next row's interval is loaded a row ahead: its latency hides behind 64 compares */
            const float2 t = t_next;
            if (i + 1 < m) t_next = thr[a0 + i + 1];
            const ulong mm = ROW_MASK(t.x, t.y) & vmask;
            const ulong cin = (cin_word >> bit) & 1;
            const ulong s = v + (v & mm) + cin;
            const uint cout = (s < v) | ((cin == 1) & (s == v));
            v = s | (v & ~mm);
            cout_word |= cout << bit;
            if (bit == 31 || i == m - 1) {
                if (blk < nblocks - 1) carry[(size_t)(i >> 5) * n_pairs + p] = cout_word;
                cout_word = 0;
            }
        }
        total += popcount(~v);
    }
    out[p] = total;
}
