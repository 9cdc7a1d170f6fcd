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
def flag_matrix_kernel(
    thr: wp.array(dtype=wp.vec2),
    b: wp.array(dtype=wp.float32),
    flags: wp.array2d(dtype=wp.uint8),
):
    i, j = wp.tid()
    t = thr[i]
    flags[i, j] = wp.where(inside(b[j], t[0], t[1]), wp.uint8(1), wp.uint8(0))


@wp.kernel
def lcs_lengths_kernel(
    thr: wp.array(dtype=wp.vec2),  # (lo, hi) per a value
    a_off: wp.array(dtype=wp.int32),
    b_vals: wp.array(dtype=wp.float32),  # packed b values, padded with 64 extra entries
    b_off: wp.array(dtype=wp.int32),
    pairs: wp.array(dtype=wp.vec2i),
    carry: wp.array(dtype=wp.uint32),  # scratch: carry bits, word w of pair p at w * n_pairs + p
    n_pairs: int,
    out: wp.array(dtype=wp.int32),
):
    p = wp.tid()
    ia = pairs[p][0]
    ib = pairs[p][1]
    a0 = a_off[ia]
    m = a_off[ia + 1] - a0
    b0 = b_off[ib]
    n = b_off[ib + 1] - b0
    ones = ~wp.uint64(0)
    total = int(0)
    nblocks = (n + 63) // 64
    for blk in range(nblocks):
        base = b0 + blk * 64
        bb = vec64f()
        for k in range(64):
            bb[k] = b_vals[base + k]
        valid = n - blk * 64
        vmask = ones
        if valid < 64:
            vmask = (wp.uint64(1) << wp.uint64(valid)) - wp.uint64(1)
        v = ones
        cin_word = wp.uint32(0)
        cout_word = wp.uint32(0)
        for i in range(m):
            bit = wp.uint32(i % 32)
            if blk > 0 and bit == wp.uint32(0):
                cin_word = carry[(i // 32) * n_pairs + p]
            t = thr[a0 + i]
            lo = t[0]
            hi = t[1]
            mlo = row_mask(bb, 0, lo, hi)
            mhi = row_mask(bb, 32, lo, hi)
            mm = ((wp.uint64(mhi) << wp.uint64(32)) | wp.uint64(mlo)) & vmask
            cin = wp.uint64((cin_word >> bit) & wp.uint32(1))
            s = v + (v & mm) + cin
            cout = wp.where(s < v or (cin == wp.uint64(1) and s == v), wp.uint32(1), wp.uint32(0))
            v = s | (v & ~mm)
            cout_word = cout_word | (cout << bit)
            if bit == wp.uint32(31) or i == m - 1:
                if blk < nblocks - 1:
                    carry[(i // 32) * n_pairs + p] = cout_word
                cout_word = wp.uint32(0)
        total += wp.bit_count(~v)
    out[p] = total
