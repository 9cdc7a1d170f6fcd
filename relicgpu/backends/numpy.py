"""The float64 NumPy reference for every kernel function of `base.Backend`.

This module is the specification: every other backend implements the same
functions with the same signatures and is tested against these on random and
adversarial inputs. Keep it plain and obviously right, not fast.
"""
from __future__ import annotations

import os

import numpy as np
from scipy.spatial import cKDTree

from ._prep import PpfVotes

name = "numpy"
# no device or thread state of its own: the local engine may fork workers that run it (`heap.engines`)
forks = True


# --- normals -----------------------------------------------------------------

def face_normals(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (F,3) and areas (F,) of triangles; a zero-area face gets a zero normal."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    if len(f) == 0:
        return np.zeros((0, 3)), np.zeros(0)
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    length = np.linalg.norm(cross, axis=1)
    normals = np.zeros_like(cross)
    ok = length > 0
    normals[ok] = cross[ok] / length[ok, None]
    return normals, 0.5 * length


def edge_angles(normals: np.ndarray, edge_faces: np.ndarray) -> np.ndarray:
    """Angle in radians between the normals of the two faces of every shared edge.

    atan2(|n0 x n1|, n0 . n1) keeps precision near 0 and pi; an edge next to a
    zero-area face has angle 0 (a degenerate face must not split a region).
    """
    n = np.asarray(normals, np.float64)
    e = np.asarray(edge_faces, np.int64).reshape(-1, 2)
    if len(e) == 0:
        return np.zeros(0)
    n0, n1 = n[e[:, 0]], n[e[:, 1]]
    angle = np.arctan2(np.linalg.norm(np.cross(n0, n1), axis=1), np.einsum("ij,ij->i", n0, n1))
    degenerate = ~(np.any(n0 != 0, axis=1) & np.any(n1 != 0, axis=1))
    angle[degenerate] = 0.0
    return angle


# --- curvature --------------------------------------------------------------

def contour_features(points: np.ndarray, k: int, stride: int) -> np.ndarray:
    """Per point of a closed contour (N,3), the columns
    [kcos, kappa, tau, chord_right, chord_left] as an (N,5) array.

    kcos  : k-cosine curvature (Eq. 13-16): over scales m = 1..k the cosine of the
            angle between a_m = P_i - P_{i+m} and b_m = P_i - P_{i-m}, averaged with
            weights w_m = 1 / (|a_m| + |b_m|) (nearer neighbourhoods weigh more).
            A zero vector gives cosine -1 (a straight, flat run); all-zero weights
            give equal weights. Range [-1, 1]: -1 straight, towards +1 a sharp turn.
    kappa : discrete curvature (Eq. 25) |r' x r''| / |r'|^3 with central differences
            at step s = stride over the local chord length h = (|P_{i+s}-P_i| + |P_i-P_{i-s}|)/2:
            r' = (P_{i+s}-P_{i-s})/(2h), r'' = (P_{i+s}-2P_i+P_{i-s})/h^2.
    tau   : discrete torsion (Eq. 26) (r' x r'') . r''' / |r' x r''|^2 with
            r''' = (P_{i+2s}-2P_{i+s}+2P_{i-s}-P_{i-2s})/(2h^3); 0 where r' x r'' = 0.
    chord_right, chord_left : |P_i - P_{i+s}|, |P_i - P_{i-s}| (Eq. 27-28 at scale s).
    Indices wrap around (the contour is closed), so length-1 contours are legal.
    """
    p = np.asarray(points, np.float64).reshape(-1, 3)
    n = len(p)
    out = np.zeros((n, 5))
    if n == 0:
        return out
    idx = np.arange(n)
    at = lambda off: p[(idx + off) % n]  # noqa: E731

    cos_sum = np.zeros(n)
    w_sum = np.zeros(n)
    for m in range(1, k + 1):
        a = p - at(m)
        b = p - at(-m)
        la, lb = np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1)
        ok = (la > 0) & (lb > 0)
        cos = np.full(n, -1.0)
        cos[ok] = np.einsum("ij,ij->i", a[ok], b[ok]) / (la[ok] * lb[ok])
        w = np.zeros(n)
        pos = (la + lb) > 0
        w[pos] = 1.0 / (la[pos] + lb[pos])
        cos_sum += w * cos
        w_sum += w
    # where every weight is zero (all neighbours coincide), equal weights of -1
    out[:, 0] = np.where(w_sum > 0, cos_sum / np.where(w_sum > 0, w_sum, 1), -1.0)

    s = stride
    right, left = at(s) - p, p - at(-s)
    lr, ll = np.linalg.norm(right, axis=1), np.linalg.norm(left, axis=1)
    h = 0.5 * (lr + ll)
    safe_h = np.where(h > 0, h, 1.0)
    d1 = (at(s) - at(-s)) / (2 * safe_h[:, None])
    d2 = (at(s) - 2 * p + at(-s)) / safe_h[:, None] ** 2
    d3 = (at(2 * s) - 2 * at(s) + 2 * at(-s) - at(-2 * s)) / (2 * safe_h[:, None] ** 3)
    c = np.cross(d1, d2)
    c_len = np.linalg.norm(c, axis=1)
    d1_len = np.linalg.norm(d1, axis=1)
    kappa = np.zeros(n)
    ok = (h > 0) & (d1_len > 0)
    kappa[ok] = c_len[ok] / d1_len[ok] ** 3
    tau = np.zeros(n)
    ok = (h > 0) & (c_len > 0)
    tau[ok] = np.einsum("ij,ij->i", c[ok], d3[ok]) / c_len[ok] ** 2
    out[:, 1], out[:, 2], out[:, 3], out[:, 4] = kappa, tau, lr, ll
    return out


# --- flags and LCS ----------------------------------------------------------

def flag_matrix(a: np.ndarray, b: np.ndarray, eps: float) -> np.ndarray:
    """Eq. 33: flags[i, j] = |a_i - b_j| < eps (strict), as a bool (len(a), len(b)) array."""
    a = np.asarray(a, np.float64).ravel()
    b = np.asarray(b, np.float64).ravel()
    return np.abs(a[:, None] - b[None, :]) < eps


def lcs_length(a: np.ndarray, b: np.ndarray, eps: float) -> int:
    """Length of the longest common subsequence of a and b where a_i 'equals' b_j when flagged."""
    flags = flag_matrix(a, b, eps)
    m, n = flags.shape
    if m == 0 or n == 0:
        return 0
    prev = np.zeros(n + 1, np.int64)
    for i in range(m):
        cur = np.zeros(n + 1, np.int64)
        row = flags[i]
        for j in range(n):
            cur[j + 1] = prev[j] + 1 if row[j] else max(prev[j + 1], cur[j])
        prev = cur
    return int(prev[n])


def lcs_lengths(a_values, a_offsets, b_values, b_offsets, pairs, eps: float) -> np.ndarray:
    """Batched LCS lengths.

    Sequences are packed: sequence i of a is a_values[a_offsets[i]:a_offsets[i+1]]
    (likewise b); pairs (P,2) holds (i of a, j of b). Returns (P,) int32 lengths.
    """
    a_values = np.asarray(a_values, np.float64)
    b_values = np.asarray(b_values, np.float64)
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    out = np.zeros(len(pairs), np.int32)
    for p, (i, j) in enumerate(pairs):
        a = a_values[a_offsets[i]:a_offsets[i + 1]]
        b = b_values[b_offsets[j]:b_offsets[j + 1]]
        out[p] = lcs_length(a, b, eps)
    return out


# --- nearest neighbours and reductions (ICP) --------------------------------

def nearest_neighbors(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each source point, the index (int32) of its nearest target point and the distance.

    Ties may resolve to any of the equally near points. An empty target is an error.
    """
    return nearest_index(target).query(source)


def nearest_index(target: np.ndarray) -> "NearestIndex":
    """The target prepared once for many nearest-neighbour queries (an ICP's rounds):
    `nearest_index(t).query(s)` is `nearest_neighbors(s, t)`."""
    dst = np.asarray(target, np.float64).reshape(-1, 3)
    if len(dst) == 0:
        raise ValueError("nearest_neighbors: the target point set is empty")
    if not np.isfinite(dst).all():
        raise ValueError("nearest_neighbors: points with NaN or infinite coordinates")
    return NearestIndex(cKDTree(dst))


def query_threads() -> int:
    """Threads for a k-d tree query: all cores, unless the process was given fewer (a Ray
    worker runs with OMP_NUM_THREADS=1; sixteen workers each starting sixteen threads
    per query ran at half speed)."""
    try:
        return max(1, int(os.environ["OMP_NUM_THREADS"]))
    except (KeyError, ValueError):
        return -1


class NearestIndex:
    def __init__(self, tree: cKDTree):
        self.tree = tree

    def query(self, source: np.ndarray, within: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        src = np.asarray(source, np.float64).reshape(-1, 3)
        if len(src) == 0:
            return np.zeros(0, np.int32), np.zeros(0)
        if not np.isfinite(src).all():
            raise ValueError("nearest_neighbors: points with NaN or infinite coordinates")
        workers = query_threads() if len(src) >= 2048 else 1
        dist, idx = self.tree.query(src, k=1, workers=workers,
                                    distance_upper_bound=np.inf if within is None else float(within))
        return idx.astype(np.int32), dist


def cross_covariance(source: np.ndarray, target: np.ndarray, weights: np.ndarray | None = None):
    """Weighted centroids of source and target (paired row by row) and the 3x3 cross-covariance
    H = sum_i w_i (s_i - cs)(t_i - ct)^T that the Kabsch fit takes. Returns (cs, ct, H, wsum).
    """
    s = np.asarray(source, np.float64).reshape(-1, 3)
    t = np.asarray(target, np.float64).reshape(-1, 3)
    w = np.ones(len(s)) if weights is None else np.asarray(weights, np.float64).ravel()
    wsum = float(w.sum())
    if wsum <= 0:
        return np.zeros(3), np.zeros(3), np.zeros((3, 3)), 0.0
    cs = (w[:, None] * s).sum(0) / wsum
    ct = (w[:, None] * t).sum(0) / wsum
    h = ((s - cs) * w[:, None]).T @ (t - ct)
    return cs, ct, h, wsum


# --- point-pair-feature votes ------------------------------------------------

def ppf_votes(model_start, model_ref, model_alpha, model_weight, scene_key, scene_ref, scene_alpha, scene_weight,
              n_refs: int, n_model: int, alpha_bins: int, bucket_cap: int) -> tuple[np.ndarray, np.ndarray]:
    """Per scene reference, the first largest cell of its vote row (`ppf_vote_rows`) and its
    total: (n_refs,) int64 cells (model point * alpha_bins + angle bin), (n_refs,) float64."""
    votes = ppf_vote_rows(model_start, model_ref, model_alpha, model_weight, scene_key, scene_ref, scene_alpha,
                          scene_weight, n_refs, n_model, alpha_bins, bucket_cap)
    best = votes.argmax(axis=1)
    return best.astype(np.int64), votes[np.arange(len(votes)), best].astype(np.float64)


def ppf_vote_rows(model_start, model_ref, model_alpha, model_weight, scene_key, scene_ref, scene_alpha,
                  scene_weight, n_refs: int, n_model: int, alpha_bins: int, bucket_cap: int) -> np.ndarray:
    """Drost's votes as a dense (n_refs, n_model * alpha_bins) array: every scene pair (key,
    ref, alpha) votes for (model point, angle bin) with the model pairs of its key,
    model_start[key]:model_start[key + 1] (a key past the last is an empty bucket). A bucket of
    `found` > bucket_cap pairs votes with bucket_cap of them, lo + i * found // bucket_cap for
    i < bucket_cap. The bin of a vote is floor((model_alpha - scene_alpha + pi) * alpha_bins /
    2pi) mod alpha_bins, in float32; its weight the model pair's times the scene pair's (1 where
    None). Summed by bincount, in vote order: int64 counts where neither table is weighted."""
    b = PpfVotes(model_start, model_ref, model_alpha, model_weight, scene_key, scene_ref, scene_alpha, scene_weight,
                 n_refs, n_model, alpha_bins, bucket_cap, group=False)
    cap = b.bucket_cap
    key = np.minimum(b.s_key, len(b.start) - 2)
    lo = b.start[key]
    found = b.start[key + 1] - lo
    counts = np.minimum(found, cap)
    total = int(counts.sum())
    first = np.cumsum(counts) - counts  # each scene pair's first vote
    match = np.arange(total, dtype=np.int64) + np.repeat(lo - first, counts)
    capped = np.flatnonzero(found > cap)
    if len(capped):
        spread = np.arange(cap)
        match[first[capped][:, None] + spread] = lo[capped][:, None] + spread * found[capped][:, None] // cap
    shift, scale = b.angle_constants()
    alpha = b.m_alpha[match] - np.repeat(b.s_alpha, counts)
    abin = np.floor((alpha + shift) * scale).astype(np.int64) % b.alpha_bins
    cell = (np.repeat(b.s_ref, counts).astype(np.int64) * b.n_model + b.m_ref[match]) * b.alpha_bins + abin
    weight = None
    if b.m_weight is not None or b.s_weight is not None:
        weight = np.ones(total)
        if b.m_weight is not None:
            weight *= b.m_weight[match]
        if b.s_weight is not None:
            weight *= np.repeat(b.s_weight, counts)
    return np.bincount(cell, weight, minlength=b.n_refs * b.row).reshape(b.n_refs, b.row)


# --- the mosaic's kernels: LED box mean and block entropy ---------------------

def led(image: np.ndarray, half: int) -> np.ndarray:
    """Eq. 4 in float64: the (2A+1)^2 box sum of `image` (zeros outside) over (2A+1)^2."""
    e = np.asarray(image, np.float64)
    k = 2 * half + 1
    padded = np.pad(e, half + 1)[:-1, :-1]  # one leading zero row/col for the integral image
    s = padded.cumsum(0).cumsum(1)
    h, w = e.shape
    total = s[k:k + h, k:k + w] - s[:h, k:k + w] - s[k:k + h, :w] + s[:h, :w]
    return total / (k * k)


def block_entropy(levels: np.ndarray, block: int, n_levels: int) -> np.ndarray:
    """Eq. 8 in float64 for every block x block block: out[y, x] = 1 - sum_l P_l^2 of
    levels[y:y+block, x:x+block], where a level v counts max(0, 1 - |v - l|) in bin l
    (a plain histogram for integer levels); shape (H-block+1, W-block+1)."""
    q = np.asarray(levels, np.float64)
    h, w = q.shape
    oh, ow = h - block + 1, w - block + 1
    sq = np.zeros((oh, ow))
    for lv in range(n_levels):
        member = np.clip(1.0 - np.abs(q - lv), 0.0, None)
        s = np.pad(member, ((1, 0), (1, 0))).cumsum(0).cumsum(1)
        count = s[block:, block:] - s[:oh, block:] - s[block:, :ow] + s[:oh, :ow]
        sq += count * count
    return 1.0 - sq / float(block * block) ** 2
