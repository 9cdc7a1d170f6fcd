"""Coarse matching by the longest common subsequence of fused values (section 3.9.1,
Eq. 33, Alg. 4), on the host: the full table and its backtrack for the chosen pairs.

Two points 'match' when their fused values differ by less than eps (the flag
matrix of Eq. 33). The paper has the user pick the head nodes; here the match is
circular instead (the second sequence is doubled, so every rotation of it is a
stretch of the doubled one) and runs in both directions, since the contours of
two mating fragments run opposite ways. Head nodes picked by hand remain an
option (the viewer's interactive step).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def lcs_table(flags: np.ndarray) -> np.ndarray:
    """The LCS table L (m+1, n+1) of a flag matrix (m, n).

    L[i][j] = max(L[i-1][j], L[i][j-1], flag * (L[i-1][j-1] + 1)); along a row that is
    a running maximum, so each row is two vectorised steps.
    """
    m, n = flags.shape
    table = np.zeros((m + 1, n + 1), np.int32)
    for i in range(m):
        prev = table[i]
        x = np.maximum(prev[1:], np.where(flags[i], prev[:-1] + 1, 0))
        np.maximum.accumulate(x, out=table[i + 1, 1:])
    return table


def lcs_backtrack(flags: np.ndarray, table: np.ndarray) -> np.ndarray:
    """One longest common subsequence as (K,2) index pairs (i into rows, j into columns), in order."""
    i, j = flags.shape
    out = []
    while i > 0 and j > 0:
        if flags[i - 1, j - 1] and table[i, j] == table[i - 1, j - 1] + 1:
            out.append((i - 1, j - 1))
            i -= 1
            j -= 1
        elif table[i - 1, j] >= table[i, j - 1]:
            i -= 1
        else:
            j -= 1
    return np.array(out[::-1], np.int64).reshape(-1, 2)


@dataclass(frozen=True)
class LcsMatch:
    pairs: np.ndarray  # (K,2) indices into the original a and b sequences
    length: int
    reversed_b: bool


def circular_lcs(a: np.ndarray, b: np.ndarray, eps: float, backend, head_a: int | None = None,
                 head_b: int | None = None) -> list[LcsMatch]:
    """LCS correspondences of a against b, forward and with b reversed.

    Without heads the match is circular (b doubled, each b point used at most once);
    with heads both sequences start at their head nodes and the match is linear.
    """
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    m, n = len(a), len(b)
    if m == 0 or n == 0:
        return []
    out = []
    for rev in (False, True):
        b_idx = np.arange(n)[::-1] if rev else np.arange(n)
        a_idx = np.arange(m)
        if head_a is not None and head_b is not None:
            a_idx = np.roll(a_idx, -head_a)
            b_idx = np.roll(b_idx, -int(np.flatnonzero(b_idx == head_b)[0]))
        else:
            b_idx = np.concatenate([b_idx, b_idx])
        flags = np.asarray(backend.flag_matrix(a[a_idx], b[b_idx], eps), bool)
        table = lcs_table(flags)
        path = lcs_backtrack(flags, table)
        pairs = np.stack([a_idx[path[:, 0]], b_idx[path[:, 1]]], axis=1) if len(path) else np.zeros((0, 2), np.int64)
        if len(pairs):  # a point of b used twice (doubled b): keep its first use
            _, first = np.unique(pairs[:, 1], return_index=True)
            pairs = pairs[np.sort(first)]
        out.append(LcsMatch(pairs, len(pairs), rev))
    return out
