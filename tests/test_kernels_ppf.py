"""Family 8 (point-pair-feature votes): the reference against plain loops, every backend
against the reference on random and adversarial tables, and `vote_poses` on a surface pair.

Tolerance: unweighted votes are counts and must equal the reference exactly, cell and total.
Weighted totals: within 1e-5 relative, and the chosen cell must hold the row's largest
total (a tie may go to another cell only where totals agree within that). A backend that
sums in doubles adds the votes in the reference's order, so there they are equal too.
"""
from __future__ import annotations

import numpy as np
import pytest

from relicgpu.backends import numpy as ref
from relicgpu.pair.icp import apply, axis_rotation
from relicgpu.pair.ppf import pair_table, vote_poses


def _loops(start, m_ref, m_alpha, m_w, s_key, s_ref, s_alpha, s_w, n_refs, n_model, bins, cap):
    """Drost's votes by plain loops over pairs, into a dict per row: an oracle sharing no code
    with the reference (bins in float32, as specified)."""
    rows = [dict() for _ in range(n_refs)]
    last = len(start) - 2
    for s in range(len(s_key)):
        k = min(int(s_key[s]), last)
        lo, found = int(start[k]), int(start[k + 1]) - int(start[k])
        for i in range(min(found, cap)):
            j = lo + (i * found // cap if found > cap else i)
            x = (np.float32(m_alpha[j]) - np.float32(s_alpha[s]) + np.float32(np.pi)) * np.float32(bins / (2 * np.pi))
            cell = int(m_ref[j]) * bins + int(np.floor(x)) % bins
            w = (1.0 if m_w is None else float(m_w[j])) * (1.0 if s_w is None else float(s_w[s]))
            rows[int(s_ref[s])][cell] = rows[int(s_ref[s])].get(cell, 0.0) + w
    best, total = [], []
    for row in rows:
        top = max(row.values(), default=0.0)
        best.append(min([c for c, v in row.items() if v == top], default=0) if top > 0 else 0)
        total.append(top)
    return np.array(best), np.array(total)


def _random_tables(rng, n_model=9, n_refs=6, bins=6, keys=15, max_bucket=20, pairs=80, weighted=False):
    sizes = rng.integers(0, max_bucket, keys + 1) * (rng.random(keys + 1) < 0.7)
    start = np.concatenate([[0], np.cumsum(sizes)])
    m = int(start[-1])
    m_ref = rng.integers(0, n_model, m)
    m_alpha = rng.uniform(-np.pi, np.pi, m).astype(np.float32)
    s_ref = np.sort(rng.integers(0, n_refs, pairs))
    s_key = rng.integers(0, keys + 5, pairs)
    s_alpha = rng.uniform(-np.pi, np.pi, pairs).astype(np.float32)
    m_w = rng.random(m).astype(np.float32) if weighted else None
    s_w = rng.random(pairs).astype(np.float32) if weighted else None
    return [start, m_ref, m_alpha, m_w, s_key, s_ref, s_alpha, s_w, n_refs, n_model, bins]


def _assert_agrees(be, args, exact=None):
    """be.ppf_votes(*args) against the reference under the module's tolerance."""
    got, total = (np.asarray(x) for x in be.ppf_votes(*args))
    rows = ref.ppf_vote_rows(*args)
    want, want_total = ref.ppf_votes(*args)
    assert got.shape == total.shape == (args[8],)
    weighted = args[3] is not None or args[7] is not None
    if exact is None:
        exact = not weighted or getattr(be, "real", np.float64) == np.float64
    if exact:
        np.testing.assert_array_equal(got, want)
        np.testing.assert_array_equal(total, want_total)
        return
    tol = 1e-5 * (np.abs(want_total) + 1e-6)
    assert np.all(np.abs(total - want_total) <= tol)
    assert np.all(np.abs(rows[np.arange(len(got)), got] - want_total) <= tol)


# --- the reference ------------------------------------------------------------

@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("weighted", [False, True])
def test_reference_against_plain_loops(seed, weighted):
    rng = np.random.default_rng(seed)
    args = _random_tables(rng, weighted=weighted) + [int(rng.integers(1, 8))]
    best, total = ref.ppf_votes(*args)
    want, want_total = _loops(*args)
    assert best.dtype == np.int64 and total.dtype == np.float64
    np.testing.assert_allclose(total, want_total, rtol=1e-12)
    if not weighted:
        np.testing.assert_array_equal(best, want)
    rows = ref.ppf_vote_rows(*args)
    assert rows.shape == (args[8], args[9] * args[10])
    np.testing.assert_array_equal(best, rows.argmax(axis=1))


def test_reference_by_hand():
    # one model bucket (key 0) of three pairs, on points 0, 1, 1, all in angle bin 2 of 4: cells 2, 6, 6
    start = np.array([0, 3, 3])
    m_ref, m_alpha = np.array([0, 1, 1]), np.array([0.1, 0.2, 0.3], np.float32)
    # cap 2 keeps pairs 0 * 3 // 2 = 0 and 1 * 3 // 2 = 1: cells 2 and 6 tie, the first wins
    for cap, want, votes in ((3, 6, 4.0), (2, 2, 2.0)):
        best, total = ref.ppf_votes(start, m_ref, m_alpha, None, [0, 0, 5], [0, 0, 0], np.zeros(3, np.float32),
                                    None, 1, 2, 4, cap)
        assert list(best) == [want] and list(total) == [votes]  # key 5 is past the last: no votes


# --- every backend against the reference --------------------------------------

@pytest.mark.parametrize("seed", range(4))
def test_random_tables(backend, seed):
    rng = np.random.default_rng(100 + seed)
    for weighted in (False, True):
        args = _random_tables(rng, n_model=40, n_refs=25, bins=12, keys=60, max_bucket=60, pairs=2000,
                              weighted=weighted)
        _assert_agrees(backend, args + [int(rng.integers(1, 40))])


def _surface_tables(seed, weighted):
    rng = np.random.default_rng(seed)
    pts, nrm = _rough_sheet(rng, 500)
    w = rng.random(500) if weighted else None
    model = pair_table(pts[:300], nrm[:300], 0.03, max_distance=0.2, weights=None if w is None else w[:300])
    scene = pair_table(pts[200:], -nrm[200:], 0.03, reference_stride=3, sort=False,
                       weights=None if w is None else w[200:])
    return model, scene


@pytest.mark.parametrize("weighted", [False, True])
def test_pair_tables_of_a_surface(backend, weighted):
    model, scene = _surface_tables(3, weighted)
    assert np.all(np.diff(scene.ref) >= 0)  # an unsorted table is grouped by reference already
    for cap in (32, 3):
        _assert_agrees(backend, [model.start, model.ref, model.alpha, model.weight, scene.key, scene.ref, scene.alpha,
                                 scene.weight, len(scene.references), model.n_points, 30, cap])


def _adversarial():
    rng = np.random.default_rng(7)
    base = _random_tables(rng, weighted=True) + [4]
    cases = {}
    empty = list(base)
    empty[0] = np.zeros(len(base[0]), np.int64)  # every bucket empty
    empty[1], empty[2], empty[3] = np.zeros(0, np.int64), np.zeros(0, np.float32), np.zeros(0, np.float32)
    cases["every bucket empty"] = empty
    past = list(base)
    past[4] = np.full(len(base[4]), 2**40)  # every key past the model's last
    past[4][::2] = len(base[0]) - 2  # ... or at it
    cases["keys past the last"] = past
    big = list(base)
    big[0] = np.array([0, 0, 500, 500, 1000])  # two buckets of 500 pairs, cap 1 and 7 below
    big[1], big[2], big[3] = rng.integers(0, 9, 1000), rng.uniform(-np.pi, np.pi, 1000).astype(np.float32), None
    big[4] = rng.integers(0, 4, len(base[4]))
    cases["buckets past the cap"] = big
    one = list(base)
    one[5], one[8] = np.zeros(len(base[5]), np.int64), 1
    cases["one reference"] = one
    zero = list(base)
    zero[7] = np.zeros(len(base[7]), np.float32)
    cases["scene weights zero"] = zero
    unsorted = list(base)
    order = rng.permutation(len(base[4]))
    for i in (4, 5, 6, 7):
        unsorted[i] = base[i][order]
    cases["scene references out of order"] = unsorted
    # ties: every vote of a scene pair in a cell of its own, one vote each (bins 1: cell = model point)
    ties = [np.arange(41), rng.permutation(40), np.zeros(40, np.float32), None,
            rng.permutation(40), np.repeat(np.arange(10), 4), np.zeros(40, np.float32), None, 10, 40, 1, 4]
    cases["duplicate maxima"] = ties
    none = list(base)
    none[4], none[5], none[6], none[7] = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float32),
                                          np.zeros(0, np.float32))
    cases["no scene pairs"] = none
    zero_refs = list(none)
    zero_refs[8] = 0
    cases["no references"] = zero_refs
    return cases


ADVERSARIAL = _adversarial()


@pytest.mark.parametrize("case", list(ADVERSARIAL))
@pytest.mark.parametrize("cap", [1, 7])
def test_adversarial_tables(backend, case, cap):
    args = list(ADVERSARIAL[case])
    args[11] = cap
    for m_w, s_w in ((None, None), (args[3], args[7])):
        _assert_agrees(backend, args[:3] + [m_w] + args[4:7] + [s_w] + args[8:])


def test_adversarial_cases_reach_what_they_name():
    rows = ref.ppf_vote_rows(*ADVERSARIAL["duplicate maxima"])
    assert np.all((rows == rows.max(axis=1, keepdims=True)).sum(axis=1) >= 2)
    assert not ref.ppf_vote_rows(*ADVERSARIAL["every bucket empty"]).any()
    assert ref.ppf_vote_rows(*ADVERSARIAL["keys past the last"]).any()
    _, total = ref.ppf_votes(*ADVERSARIAL["scene weights zero"])
    assert np.all(total == 0)


def test_rows_are_clean_for_the_next_reference(backend):
    """A device row serves reference after reference: cells touched by one must be zero for the
    next, when exactly as many cells were touched as the list of touched cells holds (8 of a
    64-cell row) and when more were. Model bucket k holds one pair voting for cell k."""
    bins, n_model = 8, 8
    start = np.arange(65)
    m_ref = np.arange(64) // bins
    m_alpha = (-np.pi + (np.arange(64) % bins + 0.5) * 2 * np.pi / bins).astype(np.float32)
    fill = list(range(8)) + [0, 1, 2]  # 8 new cells, then cells seen already
    overflow = list(range(21))
    groups = [fill, [7, 63, 63], overflow, [5, 40, 40]]  # the checks tie with a leftover cell
    keys = [g for g in groups for _ in range(8)]  # 8 references each: one thread's next is 8 on
    s_key = np.concatenate(keys)
    s_ref = np.repeat(np.arange(32), [len(k) for k in keys])
    args = [start, m_ref, m_alpha, None, s_key, s_ref, np.zeros(len(s_key), np.float32), None, 32, n_model, bins, 4]
    best, total = ref.ppf_votes(*args)
    assert list(best[8:16]) == [63] * 8 and list(best[24:]) == [40] * 8 and set(total[8:16]) == {2.0}
    _assert_agrees(backend, args)


def test_bad_inputs_are_refused(backend):
    args = _random_tables(np.random.default_rng(9), weighted=True) + [4]
    negative = list(args)
    negative[3] = -args[3]
    with pytest.raises(ValueError):
        backend.ppf_votes(*negative)
    outside = list(args)
    outside[5] = args[5] + args[8]
    with pytest.raises(ValueError):
        backend.ppf_votes(*outside)


# --- through vote_poses --------------------------------------------------------

def _rough_sheet(rng, n):
    xy = rng.uniform(-0.5, 0.5, (n, 2))
    k, ph, amp = rng.normal(0, 6, (6, 2)), rng.uniform(0, 2 * np.pi, 6), 0.04 / np.arange(1, 7)
    z = (amp * np.sin(xy @ k.T + ph)).sum(1)
    normals = np.column_stack([-(amp * np.cos(xy @ k.T + ph)) @ k, np.ones(n)])
    return np.column_stack([xy, z]), normals / np.linalg.norm(normals, axis=1, keepdims=True)


@pytest.mark.parametrize("weighted", [False, True])
def test_vote_poses_alike_on_every_backend(device_backend, weighted):
    """Two thirds of a rough sheet each, sharing the middle third, b moved away: the same
    poses and supports from every backend as from the reference."""
    rng = np.random.default_rng(11)
    pts, nrm = _rough_sheet(rng, 900)
    a, b = pts[:, 0] < 1 / 6, pts[:, 0] > -1 / 6
    turn = np.eye(4)
    turn[:3, :3], turn[:3, 3] = axis_rotation(np.array([0.0, 0.6, 0.8]), 1.1), [0.3, -0.2, 0.5]
    inv = np.linalg.inv(turn)
    w = rng.random(900) if weighted else None
    model = pair_table(pts[a], nrm[a], 0.03, weights=None if w is None else w[a])
    scene = pair_table(apply(inv, pts[b]), -nrm[b] @ inv[:3, :3].T, 0.03, reference_stride=3, sort=False,
                       weights=None if w is None else w[b])
    want = vote_poses(model, scene, 0.06, keep=10)
    got = vote_poses(model, scene, 0.06, keep=10, backend=device_backend)
    assert len(want) >= 3 and len(got) == len(want)
    for (p, v), (q, u) in zip(got, want):
        np.testing.assert_allclose(p, q, atol=1e-9)
        assert v == pytest.approx(u, rel=1e-5)
