"""Point-pair-feature votes (Warp): per scene reference, the best (model point, angle bin)
cell of Drost's vote row and its total.

The host lays out the model pairs that vote (`_prep.PpfVotes.voting_model`): bucket k is
records start[k]:start[k + 1], at most bucket_cap of them, already spread over a larger
bucket, each (model point, angle, weight).

A thread owns one dense row of n_model * alpha_bins float64 cells in `rows` and takes the
scene references t, t + T, t + 2T, ... in turn. For a reference it walks the reference's
scene pairs in table order and, for each, the records of its key, adding each vote to its
cell: the same additions in the same order as the reference's bincount, so the totals
agree bit for bit (a vote's weight is a product of two float32 numbers, exact in float64).
No atomics; the result does not depend on thread timing.

The argmax is kept while voting: weights are >= 0, so a cell's total only grows, and the
first largest cell of the finished row is the one that, when it reached its final total,
beat the running best or tied it at a lower index (the best starts as cell 0 at total 0).
A cell that leaves zero is listed in `touched` (up to its width, one slot less than its
length); afterwards the listed cells are zeroed again, or the whole row where more were
touched, so the row is clean for the next reference at the cost of the votes, not of the
row.
"""
import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def angle_bin(m_alpha: wp.float32, s_alpha: wp.float32, shift: wp.float32, scale: wp.float32,
              alpha_bins: wp.int32) -> wp.int32:
    # float32 as in the reference: (alpha_m - alpha_s + pi) * bins / 2pi, floored, taken mod bins;
    # angles in [-pi, pi] land within one turn of the range, the rest take the slow way
    b = wp.int32(wp.floor(((m_alpha - s_alpha) + shift) * scale))
    if b < 0:
        b += alpha_bins
    elif b >= alpha_bins:
        b -= alpha_bins
    if b < 0 or b >= alpha_bins:
        b = ((b % alpha_bins) + alpha_bins) % alpha_bins
    return b


@wp.kernel
def ppf_votes(start: wp.array(dtype=wp.int32), last_key: wp.int64, model: wp.array(dtype=wp.vec3),
              s_offsets: wp.array(dtype=wp.int32), s_key: wp.array(dtype=wp.int64),
              s_alpha: wp.array(dtype=wp.float32), s_weight: wp.array(dtype=wp.float32), n_refs: wp.int32,
              alpha_bins: wp.int32, shift: wp.float32, scale: wp.float32, n_threads: wp.int32,
              rows: wp.array2d(dtype=wp.float64), touched: wp.array2d(dtype=wp.int32),
              best_cell: wp.array(dtype=wp.int32), best_votes: wp.array(dtype=wp.float64)):
    t = wp.tid()
    width = touched.shape[1] - 1
    row_len = rows.shape[1]
    r = t
    while r < n_refs:
        best_v = wp.float64(0.0)
        best_c = wp.int32(0)
        n_touched = wp.int32(0)
        for s in range(s_offsets[r], s_offsets[r + 1]):
            k = wp.min(s_key[s], last_key)
            a_s = s_alpha[s]
            ws = wp.float64(s_weight[s])
            for m in range(start[k], start[k + wp.int64(1)]):
                pair = model[m]
                c = wp.int32(pair[0]) * alpha_bins + angle_bin(pair[1], a_s, shift, scale, alpha_bins)
                old = rows[t, c]
                v = old + wp.float64(pair[2]) * ws
                rows[t, c] = v
                # listed whether new or not (a cell not new is overwritten by the next one), the
                # slot past the list a sink once it is full: no branch to mispredict
                touched[t, wp.min(n_touched, width)] = c
                n_touched += wp.where(old == wp.float64(0.0), 1, 0)
                if v > best_v or (v == best_v and c < best_c):
                    best_v = v
                    best_c = c
        if n_touched <= width:
            for j in range(n_touched):
                rows[t, touched[t, j]] = wp.float64(0.0)
        else:
            for j in range(row_len):
                rows[t, j] = wp.float64(0.0)
        best_cell[r] = best_c
        best_votes[r] = best_v
        r += n_threads
