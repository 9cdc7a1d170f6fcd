"""Family 3 (flag matrix, batched LCS lengths): every backend against the reference,
and the reference against an independent LCS.

Tolerance: none. The device kernels turn each a_i into a float32 interval
[lo_i, hi_i] holding exactly the float32 b with float64 |a_i - b| < eps, so for
b values that are float32 numbers (a and eps any float64) flags and lengths must
equal the reference exactly, at exactly-eps distances too. For b values that are
not float32 numbers, a flag may differ only where b's rounding to float32 crosses
the eps boundary; that is checked cell by cell.
"""
from __future__ import annotations

import functools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from relicgpu.backends import numpy as ref


def _independent_lcs(a, b, eps) -> int:
    """Plain recursion over (i, j), no flag matrix: an oracle that shares no code with the reference."""
    a, b = [float(x) for x in a], [float(x) for x in b]

    @functools.lru_cache(maxsize=None)
    def best(i: int, j: int) -> int:
        if i == len(a) or j == len(b):
            return 0
        if abs(a[i] - b[j]) < eps:
            return 1 + best(i + 1, j + 1)
        return max(best(i + 1, j), best(i, j + 1))

    return best(0, 0)


def _pack(seqs):
    values = np.concatenate([np.asarray(s, np.float64) for s in seqs]) if seqs else np.zeros(0)
    offsets = np.concatenate([[0], np.cumsum([len(s) for s in seqs])]).astype(np.int64)
    return values, offsets


def _f32(x):
    return np.asarray(x, np.float32).astype(np.float64)


# --- the reference ------------------------------------------------------------

def test_reference_lcs_by_hand():
    assert ref.lcs_length([1, 2, 3], [1, 3], 0.5) == 2
    assert ref.lcs_length([1, 2, 3, 4], [4, 3, 2, 1], 0.1) == 1
    assert ref.lcs_length([], [1, 2], 0.5) == 0
    assert ref.lcs_length([1.0], [], 0.5) == 0
    assert ref.lcs_length([0.0], [0.5], 0.5) == 0  # strict: exactly eps apart is no match
    assert ref.lcs_length([0.0], [0.5], np.nextafter(0.5, 1)) == 1
    assert ref.lcs_length([0.0, 1.0, 0.0], [0.05, 0.05, 1.04, 0.02], 0.1) == 3


@settings(max_examples=200, deadline=None)
@given(st.lists(st.integers(-4, 4), max_size=9), st.lists(st.integers(-4, 4), max_size=9),
       st.sampled_from([0.5, 1.0, 1.5, 2.0]))
def test_reference_lcs_against_independent_recursion(a, b, eps):
    a = np.asarray(a, float) / 2
    b = np.asarray(b, float) / 2
    assert ref.lcs_length(a, b, eps) == _independent_lcs(a, b, eps)


def test_reference_batch_matches_single_pairs():
    rng = np.random.default_rng()
    seqs = [rng.random(rng.integers(0, 20)) for _ in range(6)]
    values, offsets = _pack(seqs)
    pairs = np.array([(i, j) for i in range(6) for j in range(6)])
    got = ref.lcs_lengths(values, offsets, values, offsets, pairs, 0.1)
    assert got.dtype == np.int32
    assert list(got) == [_independent_lcs(seqs[i], seqs[j], 0.1) for i, j in pairs]


# --- flags ----------------------------------------------------------------------

def test_flag_matrix_exactly_eps_apart(backend):
    rng = np.random.default_rng()
    for eps in (0.1, 1 / 3, 0.05, 1e-3, 2.0 ** -10):
        b = _f32(rng.uniform(-2, 2, 40))
        a = np.concatenate([b + eps, b - eps, np.nextafter(b + eps, np.inf), np.nextafter(b - eps, -np.inf),
                            np.nextafter(b + eps, -np.inf), np.nextafter(b - eps, np.inf), b, [0.0, -0.0]])
        got = backend.flag_matrix(a, b, eps)
        assert got.dtype == bool and got.shape == (len(a), len(b))
        np.testing.assert_array_equal(got, ref.flag_matrix(a, b, eps))


def test_flag_matrix_random_and_odd_values(backend):
    rng = np.random.default_rng()
    a = np.concatenate([rng.normal(size=300), [np.nan, np.inf, -np.inf, 1e300, -1e-300, 0.0]])
    b = _f32(np.concatenate([rng.normal(size=200), [np.nan, np.inf, -np.inf, 0.0, -0.0, 3e38]]))
    for eps in (0.05, 0.0, -1.0, 1e-30, np.inf):
        with np.errstate(invalid="ignore"):  # inf - inf in the reference
            want = ref.flag_matrix(a, b, eps)
            got = backend.flag_matrix(a, b, eps)
        np.testing.assert_array_equal(got, want)


def test_flag_matrix_float64_b_differs_only_at_the_rounding_boundary(backend):
    rng = np.random.default_rng()
    a, b, eps = rng.random(400), rng.random(300), 0.05
    got, want = backend.flag_matrix(a, b, eps), ref.flag_matrix(a, b, eps)
    b32 = _f32(b)
    # cells where rounding b to float32 could move |a - b| across eps
    ambiguous = np.abs(np.abs(a[:, None] - b[None, :]) - eps) <= 2 * np.abs(b - b32)[None, :] + 1e-16
    assert np.all((got == want) | ambiguous)


def test_flag_matrix_empty(backend):
    assert backend.flag_matrix(np.zeros(0), np.ones(3), 0.1).shape == (0, 3)
    assert backend.flag_matrix(np.ones(4), np.zeros(0), 0.1).shape == (4, 0)


# --- batched LCS -------------------------------------------------------------------

LENGTHS = [0, 1, 2, 31, 32, 33, 63, 64, 65, 127, 128, 129, 200]


def test_lcs_lengths_word_boundaries(backend):
    rng = np.random.default_rng()
    seqs = [_f32(rng.random(n)) for n in LENGTHS]
    values, offsets = _pack(seqs)
    pairs = np.array([(i, j) for i in range(len(seqs)) for j in range(len(seqs))])
    pairs = pairs[rng.permutation(len(pairs))]
    got = backend.lcs_lengths(values, offsets, values, offsets, pairs, 0.1)
    want = ref.lcs_lengths(values, offsets, values, offsets, pairs, 0.1)
    assert got.dtype == np.int32 and got.shape == (len(pairs),)
    np.testing.assert_array_equal(got, want)


def test_lcs_lengths_exactly_eps_and_repeats(backend):
    rng = np.random.default_rng()
    eps = 0.125
    base = _f32(rng.integers(0, 16, 150) / 16)  # many values exactly eps (and 2 eps) apart
    b_seqs = [base, base[::-1], _f32(base + eps), base[:1], base[:0]]
    a_seqs = [base + eps, base - eps, np.nextafter(base + eps, -np.inf), base, base[40:41]]
    a_values, a_offsets = _pack(a_seqs)
    b_values, b_offsets = _pack(b_seqs)
    pairs = np.array([(i, j) for i in range(5) for j in range(5)] + [(0, 0), (3, 1), (0, 0)])
    got = backend.lcs_lengths(a_values, a_offsets, b_values, b_offsets, pairs, eps)
    np.testing.assert_array_equal(got, ref.lcs_lengths(a_values, a_offsets, b_values, b_offsets, pairs, eps))


def test_lcs_lengths_random_batch(backend):
    rng = np.random.default_rng()
    a_seqs = [_f32(rng.random(rng.integers(0, 260))) for _ in range(9)]
    b_seqs = [_f32(rng.random(rng.integers(0, 260))) for _ in range(7)]
    a_values, a_offsets = _pack(a_seqs)
    b_values, b_offsets = _pack(b_seqs)
    pairs = rng.integers(0, [9, 7], size=(40, 2))
    eps = float(rng.uniform(0.01, 0.2))
    got = backend.lcs_lengths(a_values, a_offsets, b_values, b_offsets, pairs, eps)
    np.testing.assert_array_equal(got, ref.lcs_lengths(a_values, a_offsets, b_values, b_offsets, pairs, eps))


def test_lcs_lengths_long_uneven_pair(backend):
    rng = np.random.default_rng()
    a, b = _f32(rng.random(700)), _f32(rng.random(333))  # many words and many carry words
    values, offsets = _pack([a, b])
    pairs = np.array([[0, 1], [1, 0]])
    got = backend.lcs_lengths(values, offsets, values, offsets, pairs, 0.02)
    want = ref.lcs_length(a, b, 0.02)
    assert list(got) == [want, want]


def test_lcs_lengths_no_pairs(backend):
    values, offsets = _pack([np.ones(3)])
    assert backend.lcs_lengths(values, offsets, values, offsets, np.zeros((0, 2), np.int64), 0.1).shape == (0,)


def test_lcs_lengths_bad_pair_is_an_error(device_backend):
    values, offsets = _pack([np.ones(3)])
    with pytest.raises(ValueError):
        device_backend.lcs_lengths(values, offsets, values, offsets, np.array([[0, 1]]), 0.1)


def test_flag_matrix_many_rows(backend):
    # enough a values that the host splits the interval search over threads
    rng = np.random.default_rng()
    a = rng.normal(size=40000)
    b = _f32(np.concatenate([rng.normal(size=40), a[:10] + 0.05, a[10:20] - 0.05]))
    np.testing.assert_array_equal(backend.flag_matrix(a, b, 0.05), ref.flag_matrix(a, b, 0.05))
