"""Family 3: flag matrix and batched bit-parallel LCS lengths (Warp).

Flags: for row value a_i the host supplies a float32 interval (lo_i, hi_i) such
that b passes exactly when float64 |a_i - b| < eps (see relicgpu.backends._prep);
a cell is flagged when lo_i <= b_j <= hi_i.

LCS (Allison-Dix / Hyyro): the flag row of a_i is packed into 64-bit words M and
the row state V (ones where no match is used yet) advances as
V' = (V + (V & M)) | (V & ~M), the addition carrying across words; the LCS length
is the number of zero bits of V after the last row.

One thread per pair. The columns are walked in blocks of 64: a block's 64 b
values sit in registers while every row of a streams past, and the carry that
leaves a block at row i is stored (one bit per row) for the next block. So the
inner loop is 64 compares against registers, with no memory traffic beside one
(lo, hi) load per 64 cells.
"""
import warp as wp

wp.set_module_options({"enable_backward": False, "max_unroll": 64})

vec64f = wp.types.vector(length=64, dtype=wp.float32)


@wp.func
def inside(x: wp.float32, lo: wp.float32, hi: wp.float32) -> wp.bool:
    return x >= lo and x <= hi


@wp.func
def row_mask(bb: vec64f, base: int, lo: wp.float32, hi: wp.float32) -> wp.uint32:
    # four independent accumulators keep the OR chains short (instruction-level parallelism)
    m0 = wp.uint32(0)
    m1 = wp.uint32(0)
    m2 = wp.uint32(0)
    m3 = wp.uint32(0)
    for k in range(8):
        m0 = m0 | wp.where(inside(bb[base + k], lo, hi), wp.uint32(1) << wp.uint32(k), wp.uint32(0))
        m1 = m1 | wp.where(inside(bb[base + k + 8], lo, hi), wp.uint32(1) << wp.uint32(k + 8), wp.uint32(0))
        m2 = m2 | wp.where(inside(bb[base + k + 16], lo, hi), wp.uint32(1) << wp.uint32(k + 16), wp.uint32(0))
        m3 = m3 | wp.where(inside(bb[base + k + 24], lo, hi), wp.uint32(1) << wp.uint32(k + 24), wp.uint32(0))
    return (m0 | m1) | (m2 | m3)


@wp.kernel
def flag_matrix(
    thr: wp.array(dtype=wp.vec2),
    b: wp.array(dtype=wp.float32),
    flags: wp.array2d(dtype=wp.uint8),
):
    i, j = wp.tid()
    t = thr[i]
    flags[i, j] = wp.where(inside(b[j], t[0], t[1]), wp.uint8(1), wp.uint8(0))


@wp.func
def add_carry(x: wp.uint32, y: wp.uint32, cin: wp.uint32) -> wp.vec2ui:
    # (x + y + cin) mod 2^32 and its carry out, in 32-bit integer operations
    t = x + y
    s = t + cin
    c = wp.where(t < x or s < t, wp.uint32(1), wp.uint32(0))
    return wp.vec2ui(s, c)


@wp.kernel
def lcs_lengths(
    thr: wp.array(dtype=wp.vec2),  # (lo, hi) per a value
    a_off: wp.array(dtype=wp.int32),
    b_vals: wp.array(dtype=wp.float32),  # packed b values, padded with 64 extra entries
    b_off: wp.array(dtype=wp.int32),
    pairs: wp.array(dtype=wp.vec2i),
    carry: wp.array(dtype=wp.uint32),  # scratch: carry bits, word w of pair p at w * n_pairs + p
    n_pairs: int,
    out: wp.array(dtype=wp.int32),
):
    # The 64-bit row words are kept as two 32-bit halves: GPUs have no 64-bit
    # integer unit, and 32-bit masks let each flag cost one select and half an OR.
    p = wp.tid()
    ia = pairs[p][0]
    ib = pairs[p][1]
    a0 = a_off[ia]
    m = a_off[ia + 1] - a0
    b0 = b_off[ib]
    n = b_off[ib + 1] - b0
    ones = ~wp.uint32(0)
    total = int(0)
    nblocks = (n + 63) // 64
    for blk in range(nblocks):
        base = b0 + blk * 64
        bb = vec64f()
        for k in range(64):
            bb[k] = b_vals[base + k]
        valid = n - blk * 64
        mask_lo = ones
        mask_hi = ones
        if valid < 64:
            if valid < 32:
                mask_lo = (wp.uint32(1) << wp.uint32(valid)) - wp.uint32(1)
                mask_hi = wp.uint32(0)
            else:
                mask_hi = (wp.uint32(1) << wp.uint32(valid - 32)) - wp.uint32(1)
        v_lo = ones
        v_hi = ones
        cin_word = wp.uint32(0)
        cout_word = wp.uint32(0)
        t_next = wp.vec2()
        if m > 0:
            t_next = thr[a0]
        for i in range(m):
            bit = wp.uint32(i % 32)
            if blk > 0 and bit == wp.uint32(0):
                cin_word = carry[(i // 32) * n_pairs + p]
            # the next row's interval is loaded a row ahead: its latency hides behind 64 compares
            t = t_next
            if i + 1 < m:
                t_next = thr[a0 + i + 1]
            lo = t[0]
            hi = t[1]
            m_lo = row_mask(bb, 0, lo, hi) & mask_lo
            m_hi = row_mask(bb, 32, lo, hi) & mask_hi
            # V' = (V + (V & M)) | (V & ~M), carrying from the previous block's word
            r_lo = add_carry(v_lo, v_lo & m_lo, (cin_word >> bit) & wp.uint32(1))
            r_hi = add_carry(v_hi, v_hi & m_hi, r_lo[1])
            v_lo = r_lo[0] | (v_lo & ~m_lo)
            v_hi = r_hi[0] | (v_hi & ~m_hi)
            cout_word = cout_word | (r_hi[1] << bit)
            if bit == wp.uint32(31) or i == m - 1:
                if blk < nblocks - 1:
                    carry[(i // 32) * n_pairs + p] = cout_word
                cout_word = wp.uint32(0)
        total += wp.bit_count(~v_lo) + wp.bit_count(~v_hi)
    out[p] = total
