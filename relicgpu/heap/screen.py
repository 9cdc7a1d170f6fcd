"""Screening the pairs of a heap: LCS lengths of every contour pair at once (bit-parallel), the
point-pair vote support of each pair, and the top-k partners of each fragment matched in full."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..backends import resolve
from ..params import Params
from ..pair.prepare import ppf_points
from ..pair.ppf import pair_table, vote_poses


# The point-pair screen: fracture points per fragment, and the weight of the contour LCS score
# beside it (it only breaks ties: alone it ranks at chance). On a mix of four 10-piece objects
# (~4500 faces a piece) recall of touching pairs at k = 8 is 0.71 / 0.78 / 0.72 / 0.80 at 250 /
# 300 / 340 / 400 points, the votes cost 1.7 / 3.1 / 4.5 / 9.0 ms a pair on this CPU.
SCREEN_PPF_POINTS = 300
SCREEN_LCS_WEIGHT = 1e-3


# --- screening -----------------------------------------------------------------

def lcs_lengths_bitparallel(a_values, a_offsets, b_values, b_offsets, pairs, eps: float,
                            chunk: int = 16384) -> np.ndarray:
    """Batched LCS lengths, equal to `relicgpu.backends.numpy.lcs_lengths` (same packed
    arguments and flag rule |a_i - b_j| < eps in float64), computed bit-parallel.

    The row recurrence of the LCS table holds for any flag matrix, so the bit-vector
    algorithm of Allison-Dix / Hyyro works unchanged: one bit per column of b,
    V <- (V + (V & M)) | (V & ~M) per row with M the row's flags, and the length is
    the count of zero bits of V at the end. Flags of a row come from prefix masks of
    b's values in sorted order: the b with |a - b| < eps are one run of that order
    (fl(a - b) is monotone in b), found by bisection with the exact test.
    """
    a_values = np.ascontiguousarray(a_values, np.float64).ravel()
    b_values = np.ascontiguousarray(b_values, np.float64).ravel()
    a_off = np.asarray(a_offsets, np.int64).ravel()
    b_off = np.asarray(b_offsets, np.int64).ravel()
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    out = np.zeros(len(pairs), np.int32)
    if len(pairs) == 0:
        return out
    if (pairs < 0).any() or pairs[:, 0].max() >= len(a_off) - 1 or pairs[:, 1].max() >= len(b_off) - 1:
        raise ValueError("lcs_lengths: pair indices out of range")
    eps = float(eps)
    a_len, b_len = np.diff(a_off), np.diff(b_off)

    # All b values in one global order; a b value passes a row's test when its global
    # position lies in [first_pass(a), first_fail_above(a)).
    order = np.argsort(b_values, kind="stable")
    s = b_values[order]
    glob = np.empty(len(b_values), np.int64)
    glob[order] = np.arange(len(b_values))
    lo_g = _first_true(lambda av, bv: (av - bv) < eps, a_values, s)
    hi_g = _first_true(lambda av, bv: ~((av - bv) > -eps), a_values, s)
    hi_g = np.maximum(hi_g, lo_g)

    # Per b sequence: its values' global positions in sorted order (searchable per sequence
    # through the combined key seq * (N+1) + position), and prefix masks in that order.
    n_total = len(b_values) + 1
    seq_of = np.repeat(np.arange(len(b_len)), b_len)
    keys = np.sort(seq_of * n_total + glob)
    words = np.maximum(1, (b_len + 63) // 64)
    # sequences grouped by the power of two of their word count, one mask table per class
    klass = np.ceil(np.log2(words)).astype(np.int64)
    pair_class = klass[pairs[:, 1]]
    for k in np.unique(pair_class):
        w = int(2 ** k)
        seqs = np.flatnonzero(klass == k)
        table, t_base = _prefix_masks(b_values, b_off, seqs, w)
        sel = np.flatnonzero(pair_class == k)
        sel = sel[np.argsort(a_len[pairs[sel, 0]], kind="stable")]  # similar row counts together
        for start in range(0, len(sel), chunk):
            idx = sel[start:start + chunk]
            out[idx] = _bitparallel_chunk(pairs[idx], a_off, a_len, b_off, b_len, lo_g, hi_g, keys, n_total,
                                          table, t_base, w)
    return out


def _first_true(pred, a: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Per a value, the first index k of the sorted array s with pred(a, s[k]) true
    (len(s) where none is); pred must be monotone (false then true) along s."""
    lo = np.zeros(len(a), np.int64)
    hi = np.full(len(a), len(s), np.int64)
    while True:
        open_ = np.flatnonzero(lo < hi)
        if len(open_) == 0:
            return lo
        mid = (lo[open_] + hi[open_]) // 2
        ok = pred(a[open_], s[mid])
        hi[open_[ok]] = mid[ok]
        lo[open_[~ok]] = mid[~ok] + 1


def _prefix_masks(b_values, b_off, seqs, w: int):
    """For each sequence j in seqs: (n_j+1, w) uint64 masks, row r = bits of its r smallest values."""
    lengths = (b_off[seqs + 1] - b_off[seqs]) + 1
    base = np.full(len(b_off) - 1, -1, np.int64)
    starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    base[seqs] = starts
    table = np.zeros((int(lengths.sum()), w), np.uint64)
    one = np.uint64(1)
    for j, t0 in zip(seqs, starts):
        seq = b_values[b_off[j]:b_off[j + 1]]
        order = np.argsort(seq, kind="stable")
        onehot = np.zeros((len(seq), w), np.uint64)
        onehot[np.arange(len(seq)), order // 64] = np.left_shift(one, (order % 64).astype(np.uint64))
        table[t0 + 1:t0 + 1 + len(seq)] = np.bitwise_or.accumulate(onehot, axis=0)
    return table, base


def _bitparallel_chunk(pairs, a_off, a_len, b_off, b_len, lo_g, hi_g, keys, n_total, table, t_base, w):
    P = len(pairs)
    ai, bj = pairs[:, 0], pairs[:, 1]
    rows = a_len[ai]
    m_max = int(rows.max())
    seq_key = bj * n_total
    seq_start = np.searchsorted(keys, seq_key)  # where sequence j's keys begin
    base = t_base[bj]
    full = np.uint64(0xFFFFFFFFFFFFFFFF)
    v = np.full((w, P), full, np.uint64)  # word-major: the carry loop runs over contiguous rows
    for r in range(m_max):
        live = rows > r
        idx = slice(None) if live.all() else np.flatnonzero(live)
        pos = a_off[ai[idx]] + r
        lo = np.searchsorted(keys, seq_key[idx] + lo_g[pos]) - seq_start[idx]
        hi = np.searchsorted(keys, seq_key[idx] + hi_g[pos]) - seq_start[idx]
        mask = np.ascontiguousarray((table[base[idx] + hi] & ~table[base[idx] + lo]).T)
        vv = v[:, idx]
        u = vv & mask
        total = vv + u  # multi-word addition: carries run from word 0 upwards
        carry = total[0] < vv[0]
        for k in range(1, w):
            col = total[k]
            c1 = col < vv[k]
            col += carry
            carry = c1 | (col < carry)
        v[:, idx] = total | (vv & ~mask)
    # LCS length = zero bits among the first n columns
    bits = np.unpackbits(np.ascontiguousarray(v.T).view(np.uint8), axis=1, bitorder="little").reshape(P, w * 64)
    valid = np.arange(w * 64)[None, :] < b_len[bj][:, None]
    return (valid & (bits == 0)).sum(axis=1).astype(np.int32)


@dataclass(frozen=True)
class ScreenResult:
    scores: np.ndarray  # (n,n) symmetric: best normalised LCS length over the contour pairs of two fragments
    contour_pairs: int  # contour pairs scored (each in both directions)


def screen_sequences(prepared: list) -> tuple[list[np.ndarray], np.ndarray]:
    """The fused sequence of every contour of every fragment (rounded to float32, so that
    all backends flag them identically) and the fragment of each."""
    seqs, owner = [], []
    for f, p in enumerate(prepared):
        for c in p.contours:
            seqs.append(np.asarray(c.fused, np.float32).astype(np.float64))
            owner.append(f)
    return seqs, np.asarray(owner, np.int64)


def screen(prepared: list, params: Params, backend) -> ScreenResult:
    """Score every fragment pair by its best contour-pair LCS, all in one batched call.

    a-side: each contour once; b-side: each contour doubled (a circular match is a
    stretch of the doubled sequence), forward and reversed (mating contours run
    opposite ways). A contour pair's score is its LCS length, at most the shorter
    length, over the shorter length.
    """
    n = len(prepared)
    seqs, owner = screen_sequences(prepared)
    scores = np.zeros((n, n))
    if len(seqs) == 0:
        return ScreenResult(scores, 0)
    lengths = np.array([len(s) for s in seqs], np.int64)
    a_values = np.concatenate(seqs)
    a_offsets = np.concatenate([[0], np.cumsum(lengths)])
    doubled = []
    for s in seqs:
        doubled += [np.concatenate([s, s]), np.concatenate([s[::-1], s[::-1]])]
    b_values = np.concatenate(doubled)
    b_offsets = np.concatenate([[0], np.cumsum(np.repeat(2 * lengths, 2))])
    s_idx, t_idx = np.triu_indices(len(seqs), k=1)
    cross = owner[s_idx] != owner[t_idx]
    s_idx, t_idx = s_idx[cross], t_idx[cross]
    pairs = np.empty((2 * len(s_idx), 2), np.int64)
    pairs[0::2, 0] = pairs[1::2, 0] = s_idx
    pairs[0::2, 1] = 2 * t_idx
    pairs[1::2, 1] = 2 * t_idx + 1
    lcs = batched_lcs_lengths(backend, a_values, a_offsets, b_values, b_offsets, pairs, params.lcs_eps)
    lcs = np.asarray(lcs, np.int64).reshape(-1, 2).max(axis=1)
    shorter = np.minimum(lengths[s_idx], lengths[t_idx])
    norm = np.minimum(lcs, shorter) / shorter
    fa, fb = owner[s_idx], owner[t_idx]
    np.maximum.at(scores, (fa, fb), norm)
    scores = np.maximum(scores, scores.T)
    return ScreenResult(scores, int(len(s_idx)))


def batched_lcs_lengths(backend, a_values, a_offsets, b_values, b_offsets, pairs, eps):
    """backend.lcs_lengths, except on the NumPy reference (a plain double loop, the
    specification) where the equal bit-parallel version above runs instead."""
    if getattr(backend, "name", "") == "numpy":
        return lcs_lengths_bitparallel(a_values, a_offsets, b_values, b_offsets, pairs, eps)
    return backend.lcs_lengths(a_values, a_offsets, b_values, b_offsets, pairs, eps)


def select_candidates(scores: np.ndarray, k: int) -> list[tuple[int, int]]:
    """Pairs (i<j) where j is among i's k best-scored partners or i among j's."""
    n = len(scores)
    keep = set()
    for i in range(n):
        partners = [j for j in range(n) if j != i and scores[i, j] > 0]
        partners.sort(key=lambda j: (-scores[i, j], j))
        for j in partners[:k]:
            keep.add((min(i, j), max(i, j)))
    return sorted(keep)


def screen_tables(sample, params: Params, scale: float, n_points: int = SCREEN_PPF_POINTS):
    """A fragment's small point-pair tables (model, scene) for the screen."""
    pts, nrm = ppf_points(sample, n_points)
    step = params.ppf_distance_step * scale
    return (pair_table(pts, nrm, step, params.ppf_angle_step_deg),
            pair_table(pts, -nrm, step, params.ppf_angle_step_deg, reference_stride=3, sort=False))


def ppf_support(pairs, tables: dict, params: Params, scale: float, backend=None) -> list[tuple[int, int, float]]:
    """(i, j, support of the best pose cluster carrying j onto i) for each pair (votes on `backend`,
    None: the NumPy reference)."""
    out = []
    for i, j in pairs:
        votes = vote_poses(tables[i][0], tables[j][1], 2 * params.ppf_distance_step * scale, keep=1, backend=backend)
        out.append((i, j, float(votes[0][1]) if votes else 0.0))
    return out


def normalised_support(support: np.ndarray) -> np.ndarray:
    """Support over the geometric mean of the two fragments' best supports: a fragment with a
    large fracture surface gathers more votes from every partner."""
    best = support.max(axis=1)
    return support / np.maximum(np.sqrt(np.outer(best, best)), 1e-12)


def _screen_blocks(n: int, parallelism: int) -> list[tuple[list[tuple[int, int]], tuple[int, ...]]]:
    """Split the pairs i<j into blocks of rows x columns, so that a job builds the tables of
    only the fragments its block touches."""
    per_side = 1 if parallelism <= 1 else max(1, min(n, math.ceil(math.sqrt(8 * parallelism))))
    bounds = np.linspace(0, n, per_side + 1).astype(int)
    blocks = []
    for a in range(per_side):
        for b in range(a, per_side):
            rows, cols = range(bounds[a], bounds[a + 1]), range(bounds[b], bounds[b + 1])
            pairs = [(i, j) for i in rows for j in cols if i < j]
            if pairs:
                blocks.append((pairs, tuple(sorted({k for p in pairs for k in p}))))
    return blocks


def _ppf_screen_job(payload, *prepared):
    pairs, needs, params, scale, backend_name = payload
    tables = {k: screen_tables(p.sample, params, scale) for k, p in zip(needs, prepared)}
    return ppf_support(pairs, tables, params, scale, resolve(backend_name))
