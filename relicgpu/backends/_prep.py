"""Host-side preparation shared by the float32 device backends (Warp, OpenCL).

The kernels see float32 data. Two things keep them faithful to the float64
reference in `relicgpu.backends.numpy`:

* Geometry is shifted to its bounding-box centre before the cast to float32,
  so differences of nearby points keep their precision far from the origin.
* The flag test `|a_i - b_j| < eps` is turned, for each a_i, into an interval
  of float32 values `lo_i <= b <= hi_i` that holds exactly for the float32 b
  where the float64 test holds. Rounding in float64 is monotone, so for a fixed
  a_i the b that pass are one contiguous run of float32 values; its ends are
  found by binary search over the ordered float32 bit patterns. The kernels then
  compare b against [lo_i, hi_i] and agree with the reference bit for bit
  whenever the b values are float32 numbers (a and eps may be any float64).
"""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

_POOL: ThreadPoolExecutor | None = None


def thread_pool() -> ThreadPoolExecutor:
    """A small shared pool for host-side array work (numpy releases the GIL on large arrays)."""
    global _POOL
    if _POOL is None:
        _POOL = ThreadPoolExecutor(max_workers=max(1, min(8, os.cpu_count() or 1)), thread_name_prefix="relicgpu-host")
    return _POOL


def in_chunks(fn, n: int, min_chunk: int = 16384) -> list:
    """fn(start, stop) over [0, n) in a few chunks on the thread pool (inline when small).
    `fn` must not itself use the pool (its workers would wait on themselves)."""
    workers = thread_pool()._max_workers
    parts = max(1, min(workers, n // min_chunk))
    if parts == 1:
        return [fn(0, n)]
    edges = np.linspace(0, n, parts + 1).astype(int)
    return list(thread_pool().map(lambda k: fn(edges[k], edges[k + 1]), range(parts)))


def parallel_copy(dst: np.ndarray, src: np.ndarray) -> None:
    """dst[...] = src, split over threads (a single-threaded copy runs far below memory bandwidth)."""
    in_chunks(lambda a, b: np.copyto(dst[a:b], src[a:b]), len(src), min_chunk=65536)

# float32 bit patterns mapped to unsigned keys whose order is the order of the values
_KEY_NEG_INF = 0x007FFFFF  # key of -inf
_KEY_POS_INF = 0xFF800000  # key of +inf


def _keys_to_float32(keys: np.ndarray) -> np.ndarray:
    k = keys.astype(np.uint32)
    bits = np.where(k & 0x80000000, k & 0x7FFFFFFF, ~k).astype(np.uint32)
    return bits.view(np.float32)


def _float32_to_keys(values: np.ndarray) -> np.ndarray:
    bits = np.ascontiguousarray(values, np.float32).view(np.uint32)
    return np.where(bits & 0x80000000, ~bits, bits | 0x80000000).astype(np.int64)


def _search_keys(pred, a: np.ndarray) -> np.ndarray:
    """Smallest key k in [key(-inf), key(+inf)] with pred(a, float32(k)) true, for an
    up-set predicate, by binary search over all float32 keys; key(+inf) + 1 where none is."""
    below = np.full(len(a), _KEY_NEG_INF - 1, np.int64)  # pred false here (sentinel)
    above = np.full(len(a), _KEY_POS_INF + 1, np.int64)  # pred true here (sentinel)
    while True:
        open_ = np.nonzero(above - below > 1)[0]
        if len(open_) == 0:
            return above
        mid = (below[open_] + above[open_]) // 2
        ok = pred(a[open_], _keys_to_float32(mid).astype(np.float64))
        above[open_[ok]] = mid[ok]
        below[open_[~ok]] = mid[~ok]


def _boundary(pred, a: np.ndarray, guess: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First float32 b where the up-set predicate pred(a, b) holds: (values, found).

    The float64 guess rounded to float32 is almost always the boundary or one
    float32 beside it, so two evaluations settle most values: at the guess g, and
    at the neighbour on the side the answer must lie (below g if pred(g) holds,
    above otherwise). The rest (huge or tiny values, NaN, odd eps) are found by
    binary search over all float32 keys; `found` is False where no b qualifies."""
    g = guess.astype(np.float32)
    p_g = pred(a, g.astype(np.float64))
    side = np.where(p_g, np.float32(-np.inf), np.float32(np.inf))
    nb = np.nextafter(g, side)
    p_nb = pred(a, nb.astype(np.float64))
    at_g = p_g & ~p_nb & (nb < g)  # g holds, the float32 below does not
    at_nb = ~p_g & p_nb & (nb > g)  # g fails, the float32 above holds
    value = np.where(at_nb, nb, g)
    found = at_g | at_nb
    rest = np.nonzero(~found)[0]
    if len(rest):
        keys = _search_keys(pred, a[rest])
        inside = keys <= _KEY_POS_INF
        value[rest[inside]] = _keys_to_float32(keys[inside])
        found[rest[inside]] = True
    return value, found


def flag_intervals(a_values, eps: float) -> tuple[np.ndarray, np.ndarray]:
    """Per value a_i, float32 (lo_i, hi_i) with: for every float32 b,
    lo_i <= b <= hi_i  exactly when  float64 |a_i - b| < eps. An empty set gives
    (+inf, -inf), which no b passes."""
    a = np.ascontiguousarray(a_values, np.float64).ravel()
    eps = float(eps)
    if len(a) > 32768:  # independent per value: split over threads
        parts = in_chunks(lambda i, j: _flag_intervals(a[i:j], eps), len(a), min_chunk=16384)
        return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
    return _flag_intervals(a, eps)


def _flag_intervals(a: np.ndarray, eps: float) -> tuple[np.ndarray, np.ndarray]:
    with np.errstate(all="ignore"):
        # |x| < eps  <=>  x < eps and x > -eps; fl(a - b) falls as b grows.
        lo, has_lo = _boundary(lambda av, b: (av - b) < eps, a, a - eps)
        # the largest b with a - b > -eps is the float32 below the first b where it fails
        stop, has_stop = _boundary(lambda av, b: ~((av - b) > -eps), a, a + eps)
    hi = np.where(has_stop, np.nextafter(stop, np.float32(-np.inf)), np.float32(np.inf))
    # no b passes: lo missing, or the b where a - b > -eps fails comes first
    empty = ~has_lo | (has_stop & (stop <= lo))
    lo[empty] = np.inf
    hi[empty] = -np.inf
    return lo, hi


def nn_target(target) -> np.ndarray:
    """A nearest-neighbour target as contiguous (N,3) float64; an empty target is an error."""
    dst = np.ascontiguousarray(np.asarray(target, np.float64).reshape(-1, 3))
    if len(dst) == 0:
        raise ValueError("nearest_neighbors: the target point set is empty")
    return dst


def nn_source(source) -> np.ndarray:
    """Query points as contiguous (N,3) float64; NaN or infinite coordinates are an error."""
    src = np.ascontiguousarray(np.asarray(source, np.float64).reshape(-1, 3))
    if not np.isfinite(src).all():
        raise ValueError("nearest_neighbors: points with NaN or infinite coordinates")
    return src


def check_offsets(values: np.ndarray, offsets, what: str) -> np.ndarray:
    off = np.asarray(offsets, np.int64).ravel()
    if len(off) == 0 or off[0] < 0 or np.any(np.diff(off) < 0) or off[-1] > len(values):
        raise ValueError(f"lcs_lengths: {what} offsets must be non-decreasing and within the {len(values)} values")
    return off


def check_pairs(pairs, n_a: int, n_b: int) -> np.ndarray:
    p = np.asarray(pairs, np.int64).reshape(-1, 2)
    if len(p) and (p.min(0) < 0).any() or len(p) and (p[:, 0].max() >= n_a or p[:, 1].max() >= n_b):
        raise ValueError(f"lcs_lengths: pair indices out of range ({n_a} a-sequences, {n_b} b-sequences)")
    return p


def bounding_box(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) of an (N,3) array, column by column: numpy's axis-0 reduction of an
    (N,3) array is some 25x slower than three strided column reductions."""
    lo = np.array([points[:, k].min() for k in range(points.shape[1])])
    hi = np.array([points[:, k].max() for k in range(points.shape[1])])
    return lo, hi


def centred_float32(points: np.ndarray) -> np.ndarray:
    """(N,3) float32 points shifted by their bounding-box centre, computed in float64.

    The centre is rounded to a multiple of a power of two near a sixteenth of the
    extent, so points on a coarse grid (integers, halves, ...) stay exact: faces
    that are exactly degenerate in float64 stay exactly degenerate in float32."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    if len(p) == 0:
        return np.zeros((0, 3), np.float32)
    centre = np.zeros(3)
    q = p if np.isfinite(p).all() else p[np.isfinite(p).all(1)]
    if len(q):
        lo, hi = bounding_box(q)
        extent = float((hi - lo).max())
        step = 2.0 ** np.floor(np.log2(extent / 16)) if extent > 0 else 1.0
        centre = np.round(0.5 * (lo + hi) / step) * step
    return np.ascontiguousarray(p - centre, np.float32)


# --- checks shared by the device backends (the reference raises on the same faults) ---

def check_faces(faces: np.ndarray, n_vertices: int, what: str = "faces") -> np.ndarray:
    f = np.asarray(faces)
    if f.size == 0:
        return np.zeros((0, 3), np.int32)
    f = f.reshape(-1, 3)
    if not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"face_normals: {what} must be integer vertex indices")
    if f.min() < 0 or f.max() >= n_vertices:
        raise IndexError(f"face_normals: {what} refer to vertex {int(f.max()) if f.max() >= n_vertices else int(f.min())}"
                         f" but there are {n_vertices} vertices")
    return np.ascontiguousarray(f, np.int32)


def check_edge_faces(edge_faces, n_faces: int) -> np.ndarray:
    e = np.asarray(edge_faces)
    if e.size == 0:
        return np.zeros((0, 2), np.int32)
    e = e.reshape(-1, 2)
    if e.min() < 0 or e.max() >= n_faces:
        raise IndexError(f"edge_angles: edge_faces refer to faces outside 0..{n_faces - 1}")
    return np.ascontiguousarray(e, np.int32)


# --- LCS batch preparation ------------------------------------------------------

class LcsBatch:
    """Everything a device needs for one lcs_lengths call, in kernel layout.

    thr (A,2) float32 flag intervals per a value; a_off, b_off int32 offsets;
    b32 float32 b values followed by 64 NaN (a block may read past the last
    sequence; NaN never passes a flag test); pairs (P,2) int32 ordered by b then a
    so that neighbouring threads share a b block; order maps them back;
    max_rows the longest a sequence used."""

    def __init__(self, a_values, a_offsets, b_values, b_offsets, pairs, eps, sort_pairs: bool):
        a = np.asarray(a_values, np.float64).ravel()
        b = np.asarray(b_values, np.float64).ravel()
        a_off = check_offsets(a, a_offsets, "a")
        b_off = check_offsets(b, b_offsets, "b")
        p = check_pairs(pairs, len(a_off) - 1, len(b_off) - 1)
        if len(a_off) > 1 and a_off[-1] >= 2**31 or len(b_off) > 1 and b_off[-1] >= 2**31:
            raise ValueError("lcs_lengths: more than 2^31 values in one batch")
        self.n_pairs = len(p)
        lo, hi = flag_intervals(a, eps)
        self.thr = np.ascontiguousarray(np.stack([lo, hi], 1), np.float32).reshape(-1, 2)
        if len(self.thr) == 0:
            self.thr = np.zeros((1, 2), np.float32)
        self.b32 = np.full(len(b) + 64, np.nan, np.float32)
        self.b32[: len(b)] = b
        self.a_off = a_off.astype(np.int32)
        self.b_off = b_off.astype(np.int32)
        if sort_pairs and len(p) > 1:
            self.order = np.lexsort((p[:, 0], p[:, 1]))
            p = p[self.order]
        else:
            self.order = None
        self.pairs = np.ascontiguousarray(p, np.int32).reshape(-1, 2)
        rows = a_off[1:] - a_off[:-1]
        self.max_rows = int(rows[p[:, 0]].max()) if len(p) else 0

    def carry_words(self) -> int:
        return max(1, (self.max_rows + 31) // 32 * self.n_pairs)

    def unsort(self, lengths: np.ndarray) -> np.ndarray:
        lengths = np.asarray(lengths, np.int32)
        if self.order is None:
            return lengths
        out = np.empty_like(lengths)
        out[self.order] = lengths
        return out


# --- uniform grid sizing ----------------------------------------------------------

MAX_CELLS_PER_POINT = 4


NO_POINT = 2147483647  # the grid search's index where no point lies within a query's reach


def grid_reach2(within: float | None, extent: np.ndarray) -> float:
    """The squared reach of a float32 grid search for `NearestIndex.query(within=)`: widened by
    more than float32's rounding of coordinates shifted to the target's box (a point within
    `within` is always found; one a little beyond may be too), 3e38 where there is none."""
    if within is None:
        return 3.0e38
    reach = float(within) * (1 + 1e-5) + 1e-6 * (float(np.linalg.norm(extent)) + float(within))
    return min(reach * reach, 3.0e38)


def beyond_reach(idx: np.ndarray, n: int) -> np.ndarray:
    """(s,) int32 indices of a grid search, NO_POINT (none within reach) as n, as a k-d tree gives."""
    return np.where(idx == NO_POINT, np.int32(n), idx).astype(np.int32)


def grid_dims(extent: np.ndarray, h: float) -> np.ndarray:
    return (np.floor(np.asarray(extent, np.float64) / h).astype(np.int64) + 1).astype(np.int64)


def choose_cell_size(extent: np.ndarray, n: int, occupied_at) -> float:
    """Cell size of a dense grid over a target set of bounding-box `extent`, aiming at
    about three targets per occupied cell with at most MAX_CELLS_PER_POINT cells per target.

    Starts from the coarsest size that suits a volume, a surface or a curve of this
    extent (the largest of the three), measures the occupancy with
    `occupied_at(h) -> number of occupied cells`, and where cells are crowded
    refines by the dimension the occupancy itself reveals."""
    e = np.asarray(extent, np.float64)
    top = float(e.max()) if len(e) else 0.0
    if n <= 1 or top <= 0:
        return 1.0 if top <= 0 else top
    budget = MAX_CELLS_PER_POINT * n + 64

    def fits(h: float) -> bool:
        return float(np.prod(grid_dims(e, h).astype(np.float64))) <= budget

    # the finest cell size the budget allows
    h_min = max(float(np.cbrt(np.prod(np.maximum(e, top * 1e-9)) / budget)), top * 1e-9)
    while not fits(h_min):
        h_min *= 1.05
    s = np.sort(e)[::-1]
    h = max(np.cbrt(s[0] * s[1] * s[2] / n), np.sqrt(s[0] * s[1] / n), s[0] / n, h_min)
    rho0 = n / max(occupied_at(h), 1)
    h_fine = max(h / 4, h_min)
    if rho0 <= 4.0 or h_fine > 0.9 * h:
        return float(h)
    rho1 = n / max(occupied_at(h_fine), 1)
    dim = float(np.clip(np.log(rho0 / max(rho1, 1e-9)) / np.log(h / h_fine), 1.0, 3.0))
    return float(max(h * (3.0 / rho0) ** (1.0 / dim), h_min))


# --- point-pair-feature votes -----------------------------------------------------

def _optional_weight(weight, n: int, what: str) -> np.ndarray | None:
    if weight is None:
        return None
    w = np.ascontiguousarray(weight, np.float32).ravel()
    if len(w) != n:
        raise ValueError(f"ppf_votes: {len(w)} {what} weights for {n} pairs")
    if not (np.isfinite(w).all() and (w >= 0).all()):
        raise ValueError(f"ppf_votes: {what} weights must be finite and >= 0")
    return w


class PpfVotes:
    """The inputs of one `ppf_votes` call, checked and in the kernels' dtypes.

    start (K+2,) int64; m_ref int32, m_alpha float32, m_weight float32 or None (M,);
    s_key int64, s_ref int32, s_alpha float32, s_weight float32 or None (S,);
    n_refs, n_model, alpha_bins, bucket_cap ints. With `group`, the scene's pairs are
    ordered by reference (a stable sort: each reference's votes keep their order, so a
    row sums in the reference's order) and s_offsets (n_refs+1,) int64 bounds each
    reference's pairs."""

    def __init__(self, model_start, model_ref, model_alpha, model_weight, scene_key, scene_ref, scene_alpha,
                 scene_weight, n_refs: int, n_model: int, alpha_bins: int, bucket_cap: int, group: bool = True):
        self.n_refs, self.n_model = int(n_refs), int(n_model)
        self.alpha_bins, self.bucket_cap = int(alpha_bins), int(bucket_cap)
        if self.n_refs < 0 or self.n_model < 1 or self.alpha_bins < 1 or self.bucket_cap < 1:
            raise ValueError("ppf_votes: n_refs >= 0, n_model, alpha_bins and bucket_cap >= 1 expected")
        if self.n_model >= 2**24 or self.n_model * self.alpha_bins >= 2**31:
            raise ValueError("ppf_votes: n_model below 2^24 and n_model * alpha_bins below 2^31 expected")
        self.start = np.ascontiguousarray(model_start, np.int64).ravel()
        self.m_ref = np.ascontiguousarray(model_ref, np.int32).ravel()
        self.m_alpha = np.ascontiguousarray(model_alpha, np.float32).ravel()
        m = len(self.m_ref)
        if len(self.m_alpha) != m:
            raise ValueError(f"ppf_votes: {len(self.m_alpha)} model angles for {m} model pairs")
        if len(self.start) < 2 or self.start[0] < 0 or self.start[-1] > m or np.any(np.diff(self.start) < 0):
            raise ValueError("ppf_votes: model_start must rise from >= 0 to at most the model's pair count")
        if m and (self.m_ref.min() < 0 or self.m_ref.max() >= self.n_model):
            raise ValueError(f"ppf_votes: model references outside 0..{self.n_model - 1}")
        self.m_weight = _optional_weight(model_weight, m, "model")
        self.s_key = np.ascontiguousarray(scene_key, np.int64).ravel()
        self.s_ref = np.ascontiguousarray(scene_ref, np.int32).ravel()
        self.s_alpha = np.ascontiguousarray(scene_alpha, np.float32).ravel()
        s = len(self.s_key)
        if max(m, s) >= 2**31:
            raise ValueError("ppf_votes: at most 2^31 - 1 pairs a table")
        if len(self.s_ref) != s or len(self.s_alpha) != s:
            raise ValueError("ppf_votes: scene_key, scene_ref and scene_alpha differ in length")
        if s and (self.s_key.min() < 0 or self.s_ref.min() < 0 or self.s_ref.max() >= self.n_refs):
            raise ValueError(f"ppf_votes: negative scene keys or scene references outside 0..{self.n_refs - 1}")
        self.s_weight = _optional_weight(scene_weight, s, "scene")
        self.s_offsets = None
        if group:
            if s > 1 and np.any(self.s_ref[1:] < self.s_ref[:-1]):
                order = np.argsort(self.s_ref, kind="stable")
                self.s_key, self.s_ref, self.s_alpha = self.s_key[order], self.s_ref[order], self.s_alpha[order]
                self.s_weight = None if self.s_weight is None else self.s_weight[order]
            self.s_offsets = np.searchsorted(self.s_ref, np.arange(self.n_refs + 1)).astype(np.int64)

    @property
    def row(self) -> int:
        """Cells of one reference's vote row (model point, angle bin)."""
        return self.n_model * self.alpha_bins

    def angle_constants(self) -> tuple[np.float32, np.float32]:
        """The float32 shift and scale of the angle bin: floor((alpha + pi) * bins / 2pi)."""
        return np.float32(np.pi), np.float32(self.alpha_bins / (2 * np.pi))

    @property
    def touched_width(self) -> int:
        """Cells a thread lists as touched before it zeroes its whole row instead (an eighth);
        its list has one slot more, a sink for the writes past a full list."""
        return max(1, self.row // 8)

    def rows_in_flight(self, wanted: int, budget_bytes: int, cell_bytes: int = 8) -> int:
        """Threads, each with a scratch row and a touched list (a thread takes references t,
        t+T, ...): at most `wanted`, what `budget_bytes` holds and what the reference's dense
        (n_refs, row) float64 votes would take, at least one."""
        per_thread = self.row * cell_bytes + 4 * (self.touched_width + 1)
        return max(1, min(wanted, budget_bytes // per_thread, self.n_refs * self.row * 8 // per_thread))

    def voting_model(self) -> tuple[np.ndarray, np.ndarray]:
        """The model pairs that vote, bucket by bucket: (K+2,) int32 starts and (V,3) float32
        records (model point, angle, weight: 1 where None), bucket k holding its first
        min(found, cap) pairs or, past the cap, pairs lo + i * found // cap in order. A vote
        then reads consecutive records instead of pairs strewn over a large bucket (a cache
        miss each, in three arrays). The point is held as a float, exact below 2^24."""
        found = np.diff(self.start)
        counts = np.minimum(found, self.bucket_cap)
        starts = np.zeros(len(self.start), np.int64)
        np.cumsum(counts, out=starts[1:])
        i = np.arange(int(starts[-1]), dtype=np.int64) - np.repeat(starts[:-1], counts)
        f = np.repeat(found, counts)
        j = np.repeat(self.start[:-1], counts) + np.where(f > self.bucket_cap, i * f // self.bucket_cap, i)
        rec = np.empty((len(j), 3), np.float32)
        rec[:, 0] = self.m_ref[j]
        rec[:, 1] = self.m_alpha[j]
        rec[:, 2] = 1.0 if self.m_weight is None else self.m_weight[j]
        return starts.astype(np.int32), rec

    def scene_weight_or_ones(self) -> np.ndarray:
        return np.ones(len(self.s_key), np.float32) if self.s_weight is None else self.s_weight
