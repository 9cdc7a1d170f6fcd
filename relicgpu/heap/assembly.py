"""Global multi-fragment assembly (issue 5): `relicgpu.assemble` and `relicgpu assemble DIR -o OUT`.

    load -> prepare every fragment at one common scale          (engine jobs, cached)
         -> screen: LCS lengths of all contour pairs at once    (one batched backend call, cached)
         -> top-k partners per fragment -> match_pair           (engine jobs, cached per pair)
         -> spanning forest of verified matches, best first,
            refusing merges that interpenetrate or break a closed loop
         -> joint refinement (ICP of each fragment against all its placed neighbours)
         -> assembly.json, assembly.glb, merged.stl

Every fragment is prepared at the same scale (the median fragment size, or
`Params.unit`) so that contour sampling steps and feature units agree between
all fragments; pair results are then comparable and cacheable.

Cache (OUT/cache or cache_dir): a file per prepared fragment, one for the screen
and one per matched pair, named by a hash of the fragment contents, the
parameters, the scale, the backend and the source of the pipeline stages, so a
result is reused only where it would be computed again identically. Files are
written atomically as soon as each job finishes: a run killed at any moment and
started again recomputes only what was not finished.
"""
from __future__ import annotations

import hashlib
import json
import math
import pickle
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..backends import numpy as numpy_backend, resolve
from .engines import Job, make_engine
from ..io.files import atomic_write_bytes, atomic_write_json
from ..io.fragment import Fragment, FragmentError
from ..io.load import Batch, read_batch
from ..pair.icp import apply, invert, kabsch
from .outputs import assembly_glb, closed_solid, merged_solid, write_outputs  # noqa: F401 (re-exported)
from ..params import Params
from ..pair.pipeline import match_pair, ppf_points, prepare, with_fragment
from ..pair.ppf import pair_table, vote_poses

CACHE_VERSION = 1
# Screening: each fragment keeps its TOP_K best partners by screening score; a pair
# is matched in full when it is among the top k of either fragment (see docs/design.md).
TOP_K = 8
# ... in heaps of more than ALL_PAIRS_UP_TO fragments; smaller heaps (one pot's sherds) have every
# pair matched. On Blender's 20-piece cylinder (flat Voronoi cuts) the screen kept 44 of the 70
# touching pairs at k = 8 and the assembly placed 0.85 of the pieces; every pair (190 against 108,
# 1.6x the assembly's time) placed 0.95 (docs/benchmarks.md).
ALL_PAIRS_UP_TO = 24
# The point-pair screen: fracture points per fragment, and the weight of the contour LCS score
# beside it (it only breaks ties: alone it ranks at chance). On a mix of four 10-piece objects
# (~4500 faces a piece) recall of touching pairs at k = 8 is 0.71 / 0.78 / 0.72 / 0.80 at 250 /
# 300 / 340 / 400 points, the votes cost 1.7 / 3.1 / 4.5 / 9.0 ms a pair on this CPU.
SCREEN_PPF_POINTS = 300
SCREEN_LCS_WEIGHT = 1e-3
# Two placements of a fragment agree when its fracture points move less than this RMS
# (a fraction of the working scale).
LOOP_TOLERANCE = 0.02
REFINE_ROUNDS = 10
# Interpenetration is judged only within this many penetration depths of the other surface.
PENETRATION_BAND = 3.0
# Two closed fragments clash when their intersection is thicker on average than CLASH_THICKNESS
# (a fraction of the working scale) and holds more than CLASH_MIN_VOLUME of the smaller one.
# Correctly placed synthetic neighbours (remeshed apart, scanner noise up to 0.005 of the object)
# overlap in a film at most 0.008 thick; one pushed 5% of the scale into its neighbour gives a
# median 0.02 (measured over vases, torsos and slabs of 5 and 10 pieces).
CLASH_THICKNESS = 0.01
CLASH_MIN_VOLUME = 0.002
# Recovery from a wrong match (`grow_forest`): rounds of leaving one implicated tree edge out,
# and the edges tried a round.
RECOVERY_ROUNDS = 3
MAX_SUSPECTS = 12

# --- the result --------------------------------------------------------------


@dataclass(frozen=True)
class MatchRecord:
    """A pair matched in full (b carried onto a): verified or not, used or not, and why."""
    a: int
    b: int
    transform: np.ndarray
    score: float
    rmse: float
    overlap: float
    penetration: float
    used: bool
    note: str  # why it is used or not: the forest's decision, or the verification's reason
    accepted: bool = True  # passed verification (relicgpu.pair.verify)

    def to_dict(self, names: list[str]) -> dict:
        """The assembly.json entry: ``accepted`` (verified), ``used``, and ``reason``."""
        def number(x):
            return float(x) if math.isfinite(float(x)) else None
        return {"a": names[self.a], "b": names[self.b], "transform": np.asarray(self.transform).tolist(),
                "score": number(self.score), "rmse": number(self.rmse), "overlap": number(self.overlap),
                "penetration": number(self.penetration), "accepted": bool(self.accepted),
                "used": bool(self.used), "reason": self.note}


@dataclass
class Assembly:
    names: list[str]
    poses: list  # 4x4 arrays (file coordinates -> the group's frame) or None when unplaced
    groups: list[int]  # group per fragment; 0 is the largest group, unplaced fragments have their own
    matches: list[MatchRecord]  # the verified matches
    timings: dict
    backend: str
    engine: str
    stats: dict = field(default_factory=dict)  # counts for reports (not written to assembly.json)
    screen_scores: np.ndarray | None = None  # (n,n) screening score of every fragment pair
    candidates: list = field(default_factory=list)  # (i, j) pairs that got the full match
    files: list = field(default_factory=list)  # the file name of each fragment (default: its name)
    skipped: list = field(default_factory=list)  # files and crumbs left out while loading, with why
    notes: list = field(default_factory=list)  # other loading decisions (files split into fragments)
    rejected: list = field(default_factory=list)  # MatchRecords of the candidates that failed verification

    @property
    def n_groups(self) -> int:
        return len(set(self.groups))

    def group_members(self) -> dict[int, list[int]]:
        out: dict[int, list[int]] = {}
        for i, g in enumerate(self.groups):
            out.setdefault(g, []).append(i)
        return out

    def to_dict(self) -> dict:
        return {
            "version": 1,
            "fragments": [{"name": name, "file": file, "pose": None if pose is None else np.asarray(pose).tolist(),
                           "group": int(g)}
                          for name, file, pose, g in zip(self.names, self.files or self.names, self.poses, self.groups)],
            # every candidate pair matched in full: verified or not, used or not, and why
            "matches": [m.to_dict(self.names) for m in self.matches + self.rejected],
            "backend": self.backend,
            "engine": self.engine,
            "timings": {k: round(float(v), 4) for k, v in self.timings.items()},
            "skipped": list(self.skipped),
            "notes": list(self.notes),
        }

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2) + "\n"


# --- hashing and the cache ---------------------------------------------------

# The sources a cached match depends on (globs under relicgpu/): the pair stages, the parameters,
# this module and the backends.
_STAGE_MODULES = ("pair/*", "params", "heap/assembly", "backends/__init__", "backends/_prep", "backends/numpy",
                  "backends/warp", "backends/opencl")


def fragment_hash(fragment: Fragment) -> str:
    """Content hash of a fragment's geometry (the cleaned arrays a file loads into)."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(fragment.vertices, np.float64).tobytes())
    h.update(np.ascontiguousarray(fragment.faces, np.int64).tobytes())
    return h.hexdigest()[:32]


def code_fingerprint(params: Params) -> str:
    """Hash of the source of the pipeline stages and of the fusion weights: a cached result
    is reused only when the code that made it is the code that would make it again."""
    h = hashlib.sha256()
    base = Path(__file__).parents[1]
    for mod in _STAGE_MODULES:
        paths = sorted(base.glob(f"{mod}.py"))
        for p in paths:
            h.update(p.read_bytes())
        if not paths:
            h.update(b"-")
    weights = Path(params.fusion_weights) if params.fusion_weights else base / "data" / "fusion_default.npz"
    h.update(weights.read_bytes() if weights.exists() else b"hand-weighted")
    return h.hexdigest()[:16]


class Cache:
    """Results on disk under `root`, named by content keys; None root = no cache."""

    def __init__(self, root, params: Params, scale: float, backend_name: str):
        self.root = Path(root) if root else None
        ident = {"cache": CACHE_VERSION, "code": code_fingerprint(params), "params": params.to_dict(),
                 "scale": repr(float(scale)), "backend": backend_name}
        self.salt = hashlib.sha256(json.dumps(ident, sort_keys=True).encode()).hexdigest()[:16]
        self.hits = 0
        self.writes = 0

    def _key(self, *parts: str) -> str:
        return hashlib.sha256("|".join((self.salt,) + parts).encode()).hexdigest()[:32]

    def _path(self, kind: str, key: str, suffix: str) -> Path | None:
        return None if self.root is None else self.root / kind / f"{key}{suffix}"

    def get_prepared(self, fragment: Fragment, h: str):
        path = self._path("prepared", self._key("prepared", h), ".pkl")
        if path is None or not path.exists():
            return None
        try:
            with open(path, "rb") as fh:
                prepared = pickle.load(fh)
            prepared = with_fragment(prepared, fragment)
        except Exception:  # an unreadable or stale file: compute again
            return None
        self.hits += 1
        return prepared

    def put_prepared(self, h: str, prepared) -> None:
        path = self._path("prepared", self._key("prepared", h), ".pkl")
        if path is not None:
            # the fragment itself is not stored: it is what the key was made from
            atomic_write_bytes(path, pickle.dumps(with_fragment(prepared, None), protocol=5))
            self.writes += 1

    def get_pair(self, ha: str, hb: str) -> dict | None:
        path = self._path("pairs", self._key("pair", ha, hb), ".json")
        if path is None or not path.exists():
            return None
        try:
            doc = json.loads(path.read_text())
        except (OSError, ValueError):
            return None
        self.hits += 1
        return doc

    def put_pair(self, ha: str, hb: str, doc: dict) -> None:
        path = self._path("pairs", self._key("pair", ha, hb), ".json")
        if path is not None:
            atomic_write_json(path, doc)
            self.writes += 1

    def get_array(self, name: str, *parts: str) -> np.ndarray | None:
        path = self._path("screen", self._key(name, *parts), ".npy")
        if path is None or not path.exists():
            return None
        try:
            arr = np.load(path, allow_pickle=False)
        except (OSError, ValueError):
            return None
        self.hits += 1
        return arr

    def put_array(self, name: str, arr: np.ndarray, *parts: str) -> None:
        path = self._path("screen", self._key(name, *parts), ".npy")
        if path is not None:
            import io as _io
            buf = _io.BytesIO()
            np.save(buf, arr, allow_pickle=False)
            atomic_write_bytes(path, buf.getvalue())
            self.writes += 1


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


def ppf_support(pairs, tables: dict, params: Params, scale: float) -> list[tuple[int, int, float]]:
    """(i, j, support of the best pose cluster carrying j onto i) for each pair."""
    out = []
    for i, j in pairs:
        votes = vote_poses(tables[i][0], tables[j][1], 2 * params.ppf_distance_step * scale, keep=1)
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
    pairs, needs, params, scale = payload
    tables = {k: screen_tables(p.sample, params, scale) for k, p in zip(needs, prepared)}
    return ppf_support(pairs, tables, params, scale)


# --- engine jobs (module level, so Ray workers import them by name) -------------

def _match_job(payload, *prepared):
    """Match a chunk of pairs; payload = (pairs, needs, params, backend, scale)."""
    pairs, needs, params, backend_name, scale = payload
    be = resolve(backend_name)
    by_index = dict(zip(needs, prepared))
    out = []
    for i, j in pairs:
        try:
            m = match_pair(by_index[i], by_index[j], params, be, scale=scale)
            doc = _pair_doc(m)
        except Exception as exc:  # one bad pair must not sink a run of thousands; reported, not cached
            doc = {"accepted": False, "transform": np.eye(4).tolist(), "score": 0.0, "rmse": float("inf"),
                   "overlap": 0.0, "penetration": 0.0, "reason": f"error: {type(exc).__name__}: {exc}",
                   "error": True, "timings": {}}
        out.append((i, j, doc))
    return out


def _pair_doc(m) -> dict:
    return {"accepted": bool(m.accepted), "transform": np.asarray(m.transform, np.float64).tolist(),
            "score": float(m.score), "rmse": float(m.rmse), "overlap": float(m.overlap),
            "penetration": float(m.penetration), "contour_a": int(m.contour_a), "contour_b": int(m.contour_b),
            "reason": m.reason, "timings": {k: float(v) for k, v in m.timings.items()}}


# --- the assembly graph ----------------------------------------------------------

_inv, _apply = invert, apply  # short names for the graph code below


def _pose_gap(points: np.ndarray, t1: np.ndarray, t2: np.ndarray) -> float:
    """RMS distance between points moved by t1 and by t2."""
    return float(np.sqrt(np.mean(np.sum((_apply(t1, points) - _apply(t2, points)) ** 2, axis=1))))


def _bbox(points: np.ndarray) -> np.ndarray:
    return np.stack([points.min(axis=0), points.max(axis=0)])


@dataclass(frozen=True)
class Edge:
    a: int
    b: int
    transform: np.ndarray  # carries b onto a
    score: float


def grow_forest(n: int, edges: list[Edge], samples: list, params: Params, scale: float, backend,
                solids: list | None = None) -> tuple[list, list[int], dict[tuple[int, int], str]]:
    """Spanning forest of verified matches, best first, that recovers from a wrong match.

    Each group keeps poses in its own frame. An edge between two groups merges them
    when (1) the verified edges between the two groups that agree with its placement
    outweigh (by score) those that agree on any one other placement (wrong matches scatter:
    summed together, three wrong ones outvoted a right one) and (2) no fragment of one group then
    interpenetrates a fragment of the other: by the volume of their intersection where both
    are closed solids (`solids`, manifold3d), else by `penetration` of the surface samples.
    An edge inside a group is used when it agrees with the placement the group already
    has (a closed loop), refused otherwise.

    A wrong match scored above the right ones is used first, and the right ones that
    contradict it (a loop far from identity, or a placement that interpenetrates) are then
    refused. So when edges were refused, each used tree edge those refusals implicate
    (`_suspects`) is in turn left out and the forest grown again; the forest whose used edges
    close the most loops (`_support`: loops closed, then summed score of the used edges) is kept
    where it closes more loops than the current one, and that is repeated up to RECOVERY_ROUNDS
    times (one wrong match a round). Right matches agree with one another around loops; a wrong
    one is kept where fewer than two loops contradict it (one against one cannot be told apart),
    and a match is never dropped for tree edges alone: leaving out a right match that refused
    interpenetrating wrong ones would let them all join, closing no loop.
    Returns poses (4x4 or None), group label per fragment, and a note per edge.
    """
    solids = solids or [None] * n
    memo: dict = {}  # clash verdicts by relative placement: the regrown forests test the same ones
    current = _grow(n, edges, samples, params, scale, backend, solids, memo)
    dropped: dict[tuple[int, int], str] = {}
    for _ in range(RECOVERY_ROUNDS):
        base = _support(edges, current[2])
        best = None
        for s in _suspects(edges, current[1], current[2]):
            kept = [e for e in edges if (e.a, e.b) != (s.a, s.b) and (e.a, e.b) not in dropped]
            trial = _grow(n, kept, samples, params, scale, backend, solids, memo)
            got = _support(kept, trial[2])
            if got[0] > base[0] and (best is None or got > best[0]):
                best = (got, s, trial)
        if best is None:
            break
        got, s, current = best
        dropped[(s.a, s.b)] = (f"refused: contradicted by the other matches (without it they close {got[0]} "
                               f"loop(s), with it {base[0]})")
    pose, group, notes = current
    notes.update(dropped)
    return pose, group, notes


def _support(edges: list[Edge], notes: dict) -> tuple[int, float]:
    """The loops closed (matches that agree with the others around a loop) and the summed score
    of the used edges."""
    loops = sum(notes.get((e.a, e.b)) == "used: closes a loop" for e in edges)
    return loops, float(sum(e.score for e in edges if notes.get((e.a, e.b), "").startswith("used")))


def _suspects(edges: list[Edge], group: list[int], notes: dict) -> list[Edge]:
    """The used tree edges a refusal implicates, most implicated first (at most MAX_SUSPECTS):
    for an edge refused inside one group, the tree path between its ends (a loop that does
    not close); for one refused between groups (an interpenetration, or other matches that
    disagree), every tree edge of the two groups it would have joined."""
    tree = [e for e in edges if notes.get((e.a, e.b)) == "used: spanning tree"]
    adjacent: dict[int, list[Edge]] = {}
    for e in tree:
        adjacent.setdefault(e.a, []).append(e)
        adjacent.setdefault(e.b, []).append(e)
    blame: dict[tuple[int, int], float] = {}
    for r in edges:
        if not notes.get((r.a, r.b), "").startswith("refused"):
            continue
        if group[r.a] == group[r.b]:
            implicated = _tree_path(adjacent, r.a, r.b)
        else:
            implicated = [e for e in tree if group[e.a] in (group[r.a], group[r.b])]
        for e in implicated:
            blame[(e.a, e.b)] = blame.get((e.a, e.b), 0.0) + r.score
    order = sorted(tree, key=lambda e: (-blame.get((e.a, e.b), 0.0), e.a, e.b))
    return [e for e in order if (e.a, e.b) in blame][:MAX_SUSPECTS]


def _tree_path(adjacent: dict[int, list[Edge]], start: int, goal: int) -> list[Edge]:
    """The edges of the tree path from start to goal (empty where none)."""
    back: dict[int, Edge | None] = {start: None}
    todo = [start]
    while todo and goal not in back:
        node = todo.pop()
        for e in adjacent.get(node, []):
            other = e.b if e.a == node else e.a
            if other not in back:
                back[other] = e
                todo.append(other)
    path, node = [], goal
    while back.get(node) is not None:
        e = back[node]
        path.append(e)
        node = e.b if e.a == node else e.a
    return path


def _grow(n: int, edges: list[Edge], samples: list, params: Params, scale: float, backend, solids: list,
          memo: dict) -> tuple[list, list[int], dict[tuple[int, int], str]]:
    """One greedy spanning forest of `edges` (see `grow_forest`)."""
    group = list(range(n))
    members = {i: [i] for i in range(n)}
    pose = [np.eye(4) for _ in range(n)]
    notes: dict[tuple[int, int], str] = {}
    tol = LOOP_TOLERANCE * scale
    ordered = sorted(edges, key=lambda e: (-e.score, e.a, e.b))

    def implied(e: Edge) -> np.ndarray:
        """The move of b's group frame into a's group frame implied by e."""
        return pose[e.a] @ e.transform @ _inv(pose[e.b])

    for k, e in enumerate(ordered):
        ga, gb = group[e.a], group[e.b]
        if ga == gb:
            predicted = _inv(pose[e.a]) @ pose[e.b]
            gap = _pose_gap(samples[e.b].fracture, predicted, e.transform)
            notes[(e.a, e.b)] = "used: closes a loop" if gap <= tol else f"refused: disagrees with a closed loop by {gap / scale:.3f}"
            continue
        move = implied(e)
        between = [f if group[f.a] == ga else Edge(f.b, f.a, _inv(f.transform), f.score)
                   for f in ordered[k:]  # the edges not yet decided (those refused before have no vote)
                   if {group[f.a], group[f.b]} == {ga, gb}]

        def agrees(m: np.ndarray, g: Edge) -> bool:
            """Whether edge g agrees with placing gb by move m."""
            return _pose_gap(samples[g.b].fracture, _inv(pose[g.a]) @ m @ pose[g.b], g.transform) <= tol

        agreeing = [agrees(move, g) for g in between]
        agree = sum(g.score for g, ok in zip(between, agreeing) if ok)
        others = [g for g, ok in zip(between, agreeing) if not ok]
        # wrong matches scatter: each rival placement is weighed alone, not all disagreeing matches together
        rival = max((sum(h.score for h in others if agrees(m, h)) for m in map(implied, others)), default=0.0)
        if rival > agree:
            notes[(e.a, e.b)] = "refused: other matches between the two groups agree on another placement"
            continue
        clash = _first_clash(members[ga], members[gb], pose, move, samples, params, scale, backend, solids, memo)
        if clash is not None:
            p, q, what = clash
            notes[(e.a, e.b)] = f"refused: fragments {p} and {q} would interpenetrate ({what})"
            continue
        for q in members[gb]:
            pose[q] = move @ pose[q]
            group[q] = ga
        members[ga] = sorted(members[ga] + members.pop(gb))
        notes[(e.a, e.b)] = "used: spanning tree"
    return pose, group, notes


def _first_clash(ga: list[int], gb: list[int], pose, move, samples, params: Params, scale: float, backend,
                 solids: list, memo: dict | None = None):
    """The first pair (p in ga, q in gb) that interpenetrates after gb moves by `move`, with a note
    (memo: verdicts kept by pair and relative placement, for forests grown again)."""
    depth = params.penetration_depth * scale
    boxes_a = {p: _bbox(_apply(pose[p], samples[p].surface)) for p in ga}
    for q in gb:
        tq = move @ pose[q]
        box_q = _bbox(_apply(tq, samples[q].surface))
        for p in ga:
            box_p = boxes_a[p]
            if np.any(box_q[0] > box_p[1] + depth) or np.any(box_p[0] > box_q[1] + depth):
                continue
            rel = _inv(pose[p]) @ tq
            key = (p, q, np.round(rel / [1, 1, 1, scale], 7).tobytes())
            if memo is not None and key in memo:
                if memo[key] is not None:
                    return p, q, memo[key]
                continue
            what = _clash(p, q, rel, samples, params, scale, backend, solids)
            if memo is not None:
                memo[key] = what
            if what is not None:
                return p, q, what
    return None


def _clash(p: int, q: int, rel: np.ndarray, samples, params: Params, scale: float, backend, solids: list):
    """Why fragments p and q (q moved by `rel` into p's frame) interpenetrate, or None."""
    if solids[p] is not None and solids[q] is not None:
        share, thickness = overlap_volume(solids[p], solids[q], rel)
        if share > CLASH_MIN_VOLUME and thickness > CLASH_THICKNESS * scale:
            return f"{100 * share:.1f}% of the smaller volume shared, {thickness / scale:.3f} thick"
        return None
    pen = penetration(samples[p], samples[q], rel, backend, params.penetration_depth * scale)
    return f"{100 * pen:.1f}% of surface points inside" if pen > params.max_penetration else None


def overlap_volume(a, b, transform: np.ndarray) -> tuple[float, float]:
    """The solid shared by solids a and b (b moved by `transform`): its volume over the smaller
    volume, and its mean thickness 2V/A (a thin film of area S has volume S t and area 2S)."""
    shared = a ^ b.transform(np.asarray(transform, np.float64)[:3, :])
    volume, area = shared.volume(), shared.surface_area()
    return float(volume / min(a.volume(), b.volume())), float(2 * volume / area) if area > 0 else 0.0


def penetration(a, b, transform: np.ndarray, backend, depth: float) -> float:
    """Share of surface samples of either fragment (b moved by `transform`) that lie deeper
    than `depth` inside the other: the signed distance along the nearest sample's outward
    normal, as in relicgpu.pair.verify, but only for points within PENETRATION_BAND * depth of
    the other surface. The sign of a far point is not to be trusted (its nearest sample
    may be a rim or the far side of a thin wall): without the band, correctly placed
    neighbours on synthetic vases, slabs and torsos score up to 0.26; with it at most 0.02.
    """
    def one_way(points, target):
        idx, dist = backend.nearest_neighbors(points, target.surface)
        idx = np.asarray(idx, np.int64)
        signed = np.einsum("ij,ij->i", points - target.surface[idx], target.normals[idx])
        near = np.asarray(dist, np.float64) < PENETRATION_BAND * depth
        return float(np.mean((signed < -depth) & near)) if len(points) else 0.0

    return max(one_way(_apply(transform, b.surface), a), one_way(_apply(_inv(transform), a.surface), b))


def refine_poses(pose: list, group: list[int], used: list[Edge], samples: list,
                 rounds: int = REFINE_ROUNDS) -> list:
    """Joint refinement of all poses against all used matches at once (a pose-graph average).

    Each used match (a, b, T) says where a fragment should sit relative to its neighbour.
    In a tree these all hold already; around closed loops they disagree a little, and the
    spanning tree alone puts the whole disagreement on the last edge. Here each fragment
    in turn (index order, a few rounds; each group's lowest-index fragment fixed) takes the
    rigid pose that best fits its fracture points to where its neighbours' matches put
    them, weighted by match score: a Gauss-Seidel least-squares solve over the pose graph,
    measured in point positions rather than in angles.
    (Measured on synthetic 10-piece objects with per-match errors of 0.5 deg and 0.003:
    this halves the rotation RMSE, where ICP of each fragment against its placed
    neighbours' fracture points did not, being biased by the independent remeshing.)
    """
    pose = [None if p is None else np.array(p) for p in pose]
    neighbours: dict[int, list] = {}
    for e in used:
        neighbours.setdefault(e.a, []).append((e.b, _inv(e.transform), e.score))
        neighbours.setdefault(e.b, []).append((e.a, e.transform, e.score))
    anchors = {min(i for i in range(len(group)) if group[i] == g) for g in set(group)}
    for _ in range(rounds):
        for i in sorted(neighbours):
            if i in anchors or pose[i] is None or len(neighbours[i]) < 2:
                continue
            src = samples[i].fracture
            if len(src) < 3:
                continue
            target = np.concatenate([_apply(pose[j] @ t, src) for j, t, _ in neighbours[i]])
            weights = np.repeat([max(w, 1e-6) for _, _, w in neighbours[i]], len(src))
            cs, ct, h, _ = numpy_backend.cross_covariance(np.tile(src, (len(neighbours[i]), 1)), target, weights)
            pose[i] = kabsch(cs, ct, h)
    return pose


# --- the whole job -----------------------------------------------------------------

def _load(fragments_or_dir) -> Batch:
    """The fragments of a directory, a list of files and Fragments, or a Batch (see io.read_batch):
    a file that cannot be read is skipped, not fatal; no fragment at all is."""
    batch = read_batch(fragments_or_dir)
    if not batch.fragments:
        why = f" ({batch.skipped[0]['reason']})" if batch.skipped else ""
        raise FragmentError(f"no fragments to assemble{why}")
    seen: dict[str, str] = {}
    for f in batch.fragments:
        if f.name in seen:
            raise FragmentError(f"{f.source or f.name}: two fragments are named {f.name!r} "
                                f"(also {seen[f.name]}); names must be unique")
        seen[f.name] = f.source or f.name
    return batch


def common_scale(fragments: list[Fragment], params: Params) -> float:
    """The one working scale of a group: Params.unit, else the median fragment size."""
    if params.unit:
        return float(params.unit)
    sizes = [f.size for f in fragments]
    scale = float(np.median(sizes))
    if not scale > 0:
        raise FragmentError("the fragments have no extent (all sizes are zero)")
    return scale


def _bar(total: int, show: bool, desc: str):
    from tqdm import tqdm
    return tqdm(total=total, desc=desc, unit="pair" if "match" in desc else "frag", file=sys.stderr,
                disable=not show, leave=False, dynamic_ncols=True)


def assemble(fragments_or_dir, params: Params | None = None, backend="auto", engine="local", workers=None,
             cache_dir=None, progress=True, out_dir=None, address: str | None = None,
             top_k: int | None = None, gpus_per_task: float | None = None, objects=None) -> "Assembly":
    """Match and assemble a directory (or list, or io.Batch) of fragments.

    Files that cannot be read are skipped and crumbs dropped (io.read_batch); the result's
    `skipped` and `notes` say which. Returns an Assembly; with out_dir, also writes assembly.json, assembly.glb and the
    merged STL(s) there, and caches finished work in out_dir/cache (or cache_dir).
    engine: "local" or "ray" (address: a Ray cluster to join, else a local one starts;
    gpus_per_task: GPUs a Ray task takes where there are GPUs, default 1).
    top_k: partners per fragment matched in full (None: every pair in heaps of at most
    ALL_PAIRS_UP_TO fragments, else TOP_K).
    objects: optional class per fragment (relicgpu.heap.grouping's labels): only pairs within one
    class are matched, in one run over the whole heap (one engine, all pairs in parallel).
    """
    params = params or Params()
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    batch = _load(fragments_or_dir)
    fragments = batch.fragments
    n = len(fragments)
    timings["load"] = batch.seconds  # also when the caller read the files (the command line does)
    be = resolve(backend)
    backend_name = be.name
    scale = common_scale(fragments, params)
    if cache_dir is None and out_dir is not None:
        cache_dir = Path(out_dir) / "cache"
    cache = Cache(cache_dir, params, scale, backend_name)
    hashes = [fragment_hash(f) for f in fragments]
    show = bool(progress) and sys.stderr.isatty()
    stats: dict = {"fragments": n, "scale": scale}

    t0 = time.perf_counter()
    eng = make_engine(engine, workers, address, be, gpus_per_task)
    timings["engine"] = time.perf_counter() - t0  # starting (or joining) Ray
    try:
        # 1. prepare every fragment at the common scale
        t0 = time.perf_counter()
        prepared: list = [cache.get_prepared(f, h) for f, h in zip(fragments, hashes)]
        todo = [i for i in range(n) if prepared[i] is None]
        bar = _bar(len(todo), show, "prepare")

        def took_prepared(job, result):
            i = job.payload[0]
            prepared[i] = with_fragment(result, fragments[i])
            cache.put_prepared(hashes[i], prepared[i])
            bar.update(1)

        eng.map(_prepare_one, [Job((i, params, backend_name, scale), (i,)) for i in todo],
                {i: fragments[i] for i in todo}, took_prepared)
        bar.close()
        timings["prepare"] = time.perf_counter() - t0
        stats["contours"] = int(sum(len(p.contours) for p in prepared))

        # 2. screen all contour pairs in one batched call
        t0 = time.perf_counter()
        lcs = cache.get_array("screen", *hashes)
        if lcs is None or lcs.shape != (n, n):
            lcs = screen(prepared, params, be).scores
            cache.put_array("screen", lcs, *hashes)
        # the contour LCS ranks partners at chance on many-piece heaps; the point-pair votes
        # of each fragment pair (small tables, all pairs) rank them
        support = cache.get_array("screen-ppf", *hashes)
        if support is None or support.shape != (n, n):
            support = np.zeros((n, n))

            def took_support(job, result):
                for i, j, v in result:
                    support[i, j] = support[j, i] = v

            eng.map(_ppf_screen_job, [Job((pairs, needs, params, scale), needs)
                                      for pairs, needs in _screen_blocks(n, eng.parallelism)],
                    {i: prepared[i] for i in range(n)}, took_support)
            cache.put_array("screen-ppf", support, *hashes)
        scores = normalised_support(support) + SCREEN_LCS_WEIGHT * lcs
        if objects is not None:
            objects = np.asarray(objects)
            if objects.shape != (n,):
                raise ValueError(f"objects: one class per fragment expected, got {objects.shape} for {n}")
            scores = np.where(objects[:, None] == objects[None, :], scores, 0.0)
        if top_k is None:
            top_k = n - 1 if n <= ALL_PAIRS_UP_TO else TOP_K
        candidates = select_candidates(scores, top_k)
        timings["screen"] = time.perf_counter() - t0
        stats["candidates"] = len(candidates)
        stats["pairs"] = n * (n - 1) // 2

        # 3. full match of the candidates
        t0 = time.perf_counter()
        docs: dict[tuple[int, int], dict] = {}
        for i, j in candidates:
            doc = cache.get_pair(hashes[i], hashes[j])
            if doc is not None:
                docs[(i, j)] = doc
        todo_pairs = [p for p in candidates if p not in docs]
        stats["pairs_from_cache"] = len(candidates) - len(todo_pairs)
        chunk = 1 if eng.name == "local" else max(1, min(8, math.ceil(len(todo_pairs) / (4 * eng.parallelism))))
        jobs = []
        for s in range(0, len(todo_pairs), chunk):
            part = todo_pairs[s:s + chunk]
            needs = tuple(sorted({k for p in part for k in p}))
            jobs.append(Job((part, needs, params, backend_name, scale), needs))
        bar = _bar(len(todo_pairs), show, "match")
        errors = []

        def took_pairs(job, result):
            for i, j, doc in result:
                docs[(i, j)] = doc
                if doc.get("error"):
                    errors.append(f"{fragments[i].name} / {fragments[j].name}: {doc['reason']}")
                else:
                    cache.put_pair(hashes[i], hashes[j], doc)
                bar.update(1)

        eng.map(_match_job, jobs, {i: prepared[i] for i in range(n)}, took_pairs)
        bar.close()
        timings["match"] = time.perf_counter() - t0
        stats["errors"] = errors
    finally:
        eng.close()

    # 4. the assembly graph
    t0 = time.perf_counter()
    edges = [Edge(i, j, np.asarray(d["transform"], np.float64), float(d["score"]))
             for (i, j), d in sorted(docs.items()) if d["accepted"]]
    samples = [p.sample for p in prepared]
    joined = sorted({k for e in edges for k in (e.a, e.b)})
    solids = [closed_solid(fragments[i]) if i in joined else None for i in range(n)]
    pose, group, notes = grow_forest(n, edges, samples, params, scale, be, solids)
    used = [e for e in edges if notes[(e.a, e.b)].startswith("used")]
    timings["assemble"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    pose = refine_poses(pose, group, used, samples)
    timings["refine"] = time.perf_counter() - t0

    names = [f.name for f in fragments]
    poses, groups = _finish_groups(pose, group)
    matches = [_record(e.a, e.b, docs[(e.a, e.b)], notes[(e.a, e.b)]) for e in edges]
    rejected = [_record(i, j, d, f"not verified: {d['reason']}") for (i, j), d in sorted(docs.items())
                if not d["accepted"]]
    stats.update(accepted=len(edges), used=len(used), cache_hits=cache.hits, cache_writes=cache.writes,
                 groups=len(set(groups)), placed=sum(p is not None for p in poses))
    timings["total"] = time.perf_counter() - t_start
    result = Assembly(names, poses, groups, matches, timings, backend_name, eng.name, stats, scores, candidates,
                      [f.file for f in fragments], list(batch.skipped), list(batch.notes), rejected)
    if out_dir is not None:
        t0 = time.perf_counter()
        write_outputs(result, fragments, out_dir, progress=show)
        result.timings["write"] = time.perf_counter() - t0
        result.timings["total"] = time.perf_counter() - t_start
        atomic_write_bytes(Path(out_dir) / "assembly.json", result.to_json().encode())
    return result


def _record(a: int, b: int, doc: dict, note: str) -> MatchRecord:
    """A MatchRecord from a pair's match document and the decision on it (`note`)."""
    return MatchRecord(a, b, np.asarray(doc["transform"], np.float64), float(doc["score"]), float(doc["rmse"]),
                       float(doc["overlap"]), float(doc["penetration"]), note.startswith("used"), note,
                       bool(doc["accepted"]))


def _prepare_one(payload, fragment):
    """Prepare one fragment; the fragment is left out of the result (the caller has it)."""
    _, params, backend_name, scale = payload
    return with_fragment(prepare(fragment, params, resolve(backend_name), scale=scale, with_second=True), None)


def _finish_groups(pose: list, group: list[int]) -> tuple[list, list[int]]:
    """Number groups (largest first, then by lowest fragment index), express each group's poses
    in the frame of its lowest-index fragment, and leave fragments that joined nothing unplaced."""
    n = len(group)
    members: dict[int, list[int]] = {}
    for i, g in enumerate(group):
        members.setdefault(g, []).append(i)
    order = sorted(members.values(), key=lambda m: (-len(m), m[0]))
    poses: list = [None] * n
    groups = [0] * n
    for label, m in enumerate(order):
        anchor = _inv(pose[m[0]])
        for i in m:
            groups[i] = label
            poses[i] = anchor @ pose[i] if len(m) > 1 else None
    return poses, groups
