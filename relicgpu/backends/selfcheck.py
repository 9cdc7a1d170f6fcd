"""Self-check before trust: every kernel family of a backend against the NumPy reference.

A compiler can get a kernel wrong on one CPU and right on the next (PoCL's LLVM 14
folded 16-wide float compares wrongly for CPUs without AVX-512: LCS lengths off in
49 of 64 pairs). So before a backend is used in a process, `run(backend)` feeds
each family small inputs chosen to reach the places where kernels go wrong (LCS
sequences crossing 64-column words, nearest-neighbour ties and exact hits, faces of
zero area, point-pair buckets past their cap and angles on bin edges) and compares
with `relicgpu.backends.numpy` under the tolerances the kernel tests use. It takes
well under a second once the kernels are compiled.

`run` returns {family: None or what disagreed}; `relicgpu.backends.get_backend`
refuses a backend with any disagreement.
"""
from __future__ import annotations

import functools

import numpy as np

import relicgpu.backends.numpy as ref

from ..topology import mesh_topology

FAMILIES = ("normals", "curvature", "flags", "lcs", "nearest", "covariance", "mosaic", "ppf")

LCS_LENGTHS = (1, 63, 64, 65, 127, 129, 200)
LCS_EPS = 0.1


def _first_bad(ok: np.ndarray, got, want) -> str:
    i = int(np.flatnonzero(~np.asarray(ok).ravel())[0])
    g, w = np.asarray(got).ravel(), np.asarray(want).ravel()
    return f"{int((~np.asarray(ok)).sum())} of {np.asarray(ok).size} values wrong (e.g. {g[i].item()!r} for {w[i].item()!r})"


def _disagreement(ok, got, want) -> str | None:
    return None if np.all(ok) else _first_bad(ok, got, want)


# --- inputs, made once per process ---------------------------------------------------

@functools.lru_cache(maxsize=None)
def _mesh():
    """A bumpy sheet far from the origin plus faces of zero area (collinear, repeated vertex)."""
    rng = np.random.default_rng(1)
    n = 9
    x, y = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n), indexing="ij")
    z = 0.05 * np.sin(7 * x) * np.cos(5 * y) + 0.002 * rng.random(x.shape)
    v = np.stack([x.ravel(), y.ravel(), z.ravel()], 1) * 40.0 + [300.0, -200.0, 50.0]
    i = (np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None, :]).ravel()
    f = np.concatenate([np.stack([i, i + n, i + 1], 1), np.stack([i + 1, i + n, i + n + 1], 1)])
    degenerate = np.array([[0, 1, 2], [0, 0, 1], [5, 5, 5]])  # collinear grid points, repeated vertices
    f = np.concatenate([f, degenerate]).astype(np.int32)
    return v, f, mesh_topology(f).edge_faces


@functools.lru_cache(maxsize=None)
def _curve():
    """A closed wobbly curve, then a run of identical points and an exactly straight run."""
    t = np.linspace(0, 2 * np.pi, 160, endpoint=False)
    c = np.stack([np.cos(t) * (3 + 0.4 * np.sin(5 * t)), np.sin(t) * 3, 0.7 * np.sin(3 * t)], 1)
    same = np.tile([[1.0, 2.0, 3.0]], (12, 1))
    line = np.stack([np.arange(24.0), 2 * np.arange(24.0), np.zeros(24)], 1)
    return c, same, line


@functools.lru_cache(maxsize=None)
def _lcs_case():
    """Sequences whose lengths straddle 64-column words, with float32 values: random ones
    and ones of three levels (long common runs carry across words). Exact answers."""
    rng = np.random.default_rng(2)
    seqs = [rng.random(n) for n in LCS_LENGTHS]
    seqs += [rng.integers(0, 3, n) / 3.0 for n in LCS_LENGTHS[1:]]
    seqs = [np.asarray(s, np.float32).astype(np.float64) for s in seqs]
    values = np.concatenate(seqs)
    offsets = np.concatenate([[0], np.cumsum([len(s) for s in seqs])]).astype(np.int64)
    k = len(seqs)
    pairs = np.array([(i, j) for i in range(k) for j in range(k) if (i < len(LCS_LENGTHS)) == (j < len(LCS_LENGTHS))],
                     np.int32)
    want = ref.lcs_lengths(values, offsets, values, offsets, pairs, LCS_EPS)
    return values, offsets, pairs, want


@functools.lru_cache(maxsize=None)
def _points():
    """Targets on a grid (equidistant ties), duplicated points, sources on targets,
    midway between them, and far outside."""
    rng = np.random.default_rng(3)
    g = np.stack(np.meshgrid(*[np.arange(6.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
    target = np.concatenate([g, g[:20], rng.random((300, 3)) * 5])
    source = np.concatenate([g[::7], g[:-1] + 0.5, rng.random((400, 3)) * 5, [[40.0, -30.0, 9.0]]])
    return source + 100.0, target + 100.0


# --- the families ------------------------------------------------------------------

def _check_normals(be) -> str | None:
    v, f, edge_faces = _mesh()
    n, a = be.face_normals(v, f)
    n_ref, a_ref = ref.face_normals(v, f)
    p = v[f]
    edge = np.sqrt(np.max([np.sum((p[:, i] - p[:, (i + 1) % 3]) ** 2, 1) for i in range(3)], axis=0))
    size = np.linalg.norm(v.max(0) - v.min(0))
    bad = _disagreement(np.abs(a - a_ref) <= 1e-5 * size * edge + 1e-5 * a_ref, a, a_ref)
    if bad:
        return "face areas: " + bad
    pos = a_ref > 0
    err = np.linalg.norm(n - n_ref, axis=1)
    ok = np.where(pos, err <= 1e-5 * size * edge / np.where(pos, a_ref, 1) + 1e-5, np.all(n == 0, 1) & (a == 0))
    if not ok.all():
        return "face normals: " + _first_bad(ok, err, np.zeros_like(err))
    ang, ang_ref = be.edge_angles(n_ref, edge_faces), ref.edge_angles(n_ref, edge_faces)
    bad = _disagreement(np.abs(ang - ang_ref) <= 1e-4, ang, ang_ref)
    return "edge angles: " + bad if bad else None


def _check_curvature(be) -> str | None:
    fp64 = getattr(be, "real", np.float64) == np.float64
    tol = 1e-9 if fp64 else 1e-3
    for pts, k, stride in zip(_curve(), (4, 3, 3), (8, 1, 2)):
        got, want = be.contour_features(pts, k, stride), ref.contour_features(pts, k, stride)
        if got.shape != want.shape:
            return f"contour features: shape {got.shape} for {want.shape}"
        ok = np.abs(got - want) <= tol * (np.abs(want) + 1)
        ok[:, 2] |= np.abs(want[:, 1]) < 1e-3  # torsion is ill-conditioned where curvature vanishes
        bad = _disagreement(ok, got, want)
        if bad:
            return "contour features: " + bad
    return None


def _check_flags(be) -> str | None:
    values, _, _, _ = _lcs_case()
    b = np.concatenate([values[200:450], [0.375, 0.625, 0.4]]).astype(np.float32).astype(np.float64)
    a = np.concatenate([values[:200], b[-3:] + LCS_EPS, b[-3:] - LCS_EPS])  # at eps, to float64 rounding
    got, want = be.flag_matrix(a, b, LCS_EPS), ref.flag_matrix(a, b, LCS_EPS)
    return _disagreement(got == want, got, want)


def _check_lcs(be) -> str | None:
    values, offsets, pairs, want = _lcs_case()
    got = np.asarray(be.lcs_lengths(values, offsets, values, offsets, pairs, LCS_EPS))
    return _disagreement(got == want, got, want)


def _check_nearest(be) -> str | None:
    source, target = _points()
    big_source, big_target = _grid_points()  # past every backend's brute-force bound: its grid search
    index = be.nearest_index(big_target)
    reach = 0.3  # (a third of the gap between the surfaces' points, most sources beyond it)
    for what, (idx, d), (s, t) in (("nearest_neighbors", be.nearest_neighbors(source, target), (source, target)),
                                   ("nearest_index", be.nearest_index(target).query(source), (source, target)),
                                   ("grid search", index.query(big_source), (big_source, big_target)),
                                   ("grid search within reach", index.query(big_source, within=reach),
                                    (big_source, big_target))):
        size = np.linalg.norm(t.max(0) - t.min(0))
        _, d_ref = ref.nearest_neighbors(s, t)
        idx, d = np.asarray(idx), np.asarray(d)
        if what.endswith("reach"):  # (len(t), inf) allowed past the reach only
            out = ~np.isfinite(d)
            if np.any(out & (d_ref < reach)) or np.any(idx[out] != len(t)):
                return f"{what}: points within reach left out"
            idx, d, d_ref, s = idx[~out], d[~out], d_ref[~out], s[~out]
        if idx.shape != d_ref.shape or (len(idx) and (idx.min() < 0 or idx.max() >= len(t))):
            return f"{what}: indices out of range"
        bad = _disagreement(np.abs(d - d_ref) <= 1e-6 * size, d, d_ref)
        if bad:
            return f"{what} distances: " + bad
        true_d = np.linalg.norm(s - t[idx], axis=1)
        bad = _disagreement(np.abs(true_d - d_ref) <= 1e-6 * size, true_d, d_ref)
        if bad:
            return f"{what} indices (not a nearest point): " + bad
    return None


def _grid_points():
    """6,000 targets on a sphere of radius 10 and 10,000 sources on and off it (60M pairs)."""
    rng = np.random.default_rng(5)
    target = rng.normal(size=(6000, 3))
    target = 10.0 * target / np.linalg.norm(target, axis=1, keepdims=True)
    source = target[rng.integers(0, 6000, 10000)] + rng.normal(size=(10000, 3)) * np.repeat([0.05, 3.0], 5000)[:, None]
    return source + 50.0, target + 50.0


def _check_covariance(be) -> str | None:
    rng = np.random.default_rng(4)
    s = rng.random((500, 3)) * 10 + 50
    t = s @ np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]]).T + [1.0, -2.0, 3.0] + 1e-3 * rng.random((500, 3))
    w = rng.random(500)
    w[::5] = 0
    fp64 = getattr(be, "real", np.float64) == np.float64
    tol = 1e-9 if fp64 else 1e-4
    for weights in (None, w):
        got, want = be.cross_covariance(s, t, weights), ref.cross_covariance(s, t, weights)
        for name, g, x, scale in zip(("source centroid", "target centroid", "covariance", "weight sum"),
                                     got, want, (60.0, 60.0, np.abs(want[2]).max(), want[3])):
            bad = _disagreement(np.abs(np.asarray(g) - x) <= tol * scale, g, x)
            if bad:
                return f"cross_covariance {name}: " + bad
    return None


def _check_mosaic(be) -> str | None:
    rng = np.random.default_rng(5)
    img = rng.random((37, 45)).astype(np.float32)
    got, want = be.led(img, 3), ref.led(img, 3)
    bad = _disagreement(np.abs(got - want) <= 1e-5, got, want)
    if bad:
        return "local edge density: " + bad
    levels = rng.integers(0, 16, (30, 41)).astype(np.float64)
    got, want = be.block_entropy(levels, 7, 16), ref.block_entropy(levels, 7, 16)
    bad = _disagreement(np.abs(got - want) <= 1e-4, got, want)
    return "block entropy: " + bad if bad else None


@functools.lru_cache(maxsize=None)
def _ppf_case():
    """Point-pair tables of few points and bins (ties in every row): empty buckets, buckets
    past the cap, scene keys past the model's last (one far past 2^31), angles on bin edges,
    scene references out of order and one without pairs, weights with zeros. Returns the
    arguments of ppf_votes but the weights, the two weight arrays, and the cap."""
    rng = np.random.default_rng(6)
    n_model, n_refs, alpha_bins, cap, keys = 7, 9, 5, 6, 12
    sizes = np.array([0, 3, 40, 1, 0, 6, 7, 13, 2, 0, 25, 4, 0])[:keys + 1]
    start = np.concatenate([[0], np.cumsum(sizes)])
    m = int(start[-1])
    m_ref = rng.integers(0, n_model, m).astype(np.int32)
    edges = (np.arange(-alpha_bins, alpha_bins + 1) * (2 * np.pi / alpha_bins)).astype(np.float32)
    m_alpha = np.where(rng.random(m) < 0.3, rng.choice(edges, m), rng.uniform(-np.pi, np.pi, m)).astype(np.float32)
    s_ref = rng.permutation(np.repeat(np.arange(n_refs - 1), 14)).astype(np.int32)  # reference 8 has none
    s = len(s_ref)
    s_key = rng.integers(0, keys + 4, s).astype(np.int64)
    s_key[::17] = 2**40
    s_alpha = np.where(rng.random(s) < 0.3, 0.0, rng.uniform(-np.pi, np.pi, s)).astype(np.float32)
    m_weight = rng.random(m).astype(np.float32)
    m_weight[::3] = 0
    s_weight = rng.random(s).astype(np.float32)
    s_weight[s_ref == 2] = 0  # a row of zero totals
    return (start, m_ref, m_alpha, s_key, s_ref, s_alpha, n_refs, n_model, alpha_bins), m_weight, s_weight, cap


@functools.lru_cache(maxsize=None)
def _ppf_reuse_case():
    """References that touch exactly as many cells as a device's list of touched cells holds (8
    of a 64-cell row), or more, each followed (in one thread's turn, 8 references on) by one
    that ties with a cell left over if the row was not cleaned. Bucket k votes for cell k."""
    start = np.arange(65)
    m_ref, m_alpha = np.arange(64) // 8, (-np.pi + (np.arange(64) % 8 + 0.5) * np.pi / 4).astype(np.float32)
    keys = [g for g in ([*range(8), 0, 1, 2], [7, 63, 63], [*range(21)], [5, 40, 40]) for _ in range(8)]
    s_key = np.concatenate(keys)
    s_ref = np.repeat(np.arange(32), [len(k) for k in keys])
    return start, m_ref, m_alpha, s_key, s_ref, np.zeros(len(s_key), np.float32), 32, 8, 8


def _check_ppf(be) -> str | None:
    (start, m_ref, m_alpha, s_key, s_ref, s_alpha, n_refs, n_model, bins), m_w, s_w, cap = _ppf_case()
    reuse = _ppf_reuse_case()
    cases = [(label, (start, m_ref, m_alpha, mw, s_key, s_ref, s_alpha, sw, n_refs, n_model, bins, cap))
             for label, mw, sw in (("unweighted", None, None), ("weighted", m_w, s_w), ("model-weighted", m_w, None))]
    cases.append(("rows reused", (*reuse[:3], None, *reuse[3:6], None, *reuse[6:], 4)))
    for label, args in cases:
        got, total = (np.asarray(x) for x in be.ppf_votes(*args))
        rows = ref.ppf_vote_rows(*args)
        want, want_total = rows.argmax(axis=1), rows.max(axis=1)
        if got.shape != want.shape or got.min() < 0 or got.max() >= rows.shape[1]:
            return f"ppf_votes ({label}): cells out of range"
        if args[3] is None and args[7] is None:
            bad = _disagreement(got == want, got, want) or _disagreement(total == want_total, total, want_total)
        else:  # float sums: the chosen cell must hold the row's largest total (ties may go either way)
            tol = 1e-5 * (np.abs(want_total) + 1e-6)
            chosen = rows[np.arange(len(rows)), got]
            bad = (_disagreement(np.abs(total - want_total) <= tol, total, want_total)
                   or _disagreement(np.abs(chosen - want_total) <= tol, chosen, want_total))
        if bad:
            return f"ppf_votes ({label}): " + bad
    return None


_CHECKS = {"normals": _check_normals, "curvature": _check_curvature, "flags": _check_flags, "lcs": _check_lcs,
           "nearest": _check_nearest, "covariance": _check_covariance, "mosaic": _check_mosaic, "ppf": _check_ppf}


def check_family(backend, family: str) -> str | None:
    """None when `backend` agrees with the reference on `family`, else what disagreed
    (an exception inside a kernel counts as a disagreement)."""
    try:
        return _CHECKS[family](backend)
    except Exception as exc:  # a kernel that fails to build or run is as untrustworthy as a wrong one
        return f"{type(exc).__name__}: {exc}"


def run(backend) -> dict[str, str | None]:
    """{family: None if it agrees with the NumPy reference, else what disagreed}."""
    return {family: check_family(backend, family) for family in FAMILIES}
