"""Fragment classification: sort a mixed heap of fragments into groups by object.

The paper's first module (sections 3.1 (1) and 3.2 step 2): before matching,
fragments of the same object are put into one group, so that matching runs
within groups. Two ways:

- unsupervised, `group(fragments)`: per-fragment descriptors that survive
  breakage (below); per pair of fragments and feature, how many within-object
  spreads apart they are (z, capped; FEATURE_SCALES), how far apart their
  quartile intervals of curvature, thickness and shape lie (0 where they
  overlap: a varied object's pieces overlap somewhere), plus whether the two
  have a fracture patch of one size and outline (the two sides of one cut do);
  a fixed logistic model over those, piecewise linear in each z (PAIR_WEIGHTS,
  fitted once on synthetic mixtures and corpus heaps that are not the
  benchmark's, see `fit_pair_model`) gives the odds that the two come from one
  object; average-linkage agglomerative clustering on 1 - p, cut where the mean
  p between two clusters falls below 1 - LINK_CUT, so the number of groups is found, not
  given (or given, or another cut); fragments left alone or in small groups are
  then clustered among themselves at a looser cut.
- supervised, `relicgpu train-classifier LABELS.csv`: a small PointNet over
  surface points (position in the fragment's principal frame, normal, fracture
  flag) joined with the descriptors, trained with torch; `relicgpu group
  --classifier WEIGHTS` then labels fragments by class.

Descriptors (lengths in units of a reference length: the heap's median fragment
size unsupervised, the training set's in a classifier), all of which a piece
keeps from its object whatever the cuts were:
  original surface: curvature distribution (principal curvatures from a quadric
    fitted over a few edges' radius at points drawn by area, signed: convex > 0;
    their quartiles, spread, |shape index| and curvedness), wall thickness (rays
    cast inward along the normals that meet the original surface again; the
    chord to the first face of any kind, and the share of rays that meet a
    wall: a solid's pieces end on their cuts), roughness (normal perturbation at
    triangle scale, from the segmentation);
  fracture surfaces: roughness (normal perturbation; RMS height about each
    patch's plane), share of the area, relief spectrum (RMS height about the
    local plane within a radius, interpolated to radii fixed within the heap), and
    the largest patches' areas and in-plane extents (for the pair match);
  colour: mean and spread of the vertex colours of the original surface, when
    every fragment's file has them.
The scan resolution (edge length) is deliberately not used: a scanner digitises
every fragment of a heap at one resolution, so it carries no object identity,
and on synthetic heaps it only tells objects apart through artefacts of how the
objects were meshed.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..cloud.triangulate import surface_of
from .describe import Descriptor, FEATURE_NAMES, GAP_NAMES, GAP_SCALES, describe_all

from ..io.fragment import Fragment, FragmentError
from ..io.load import Batch, read_batch

# Per feature, how far apart two fragments of one object typically are: 1.4826 x the median
# absolute deviation from their object's median, pooled over the objects of the fitting heaps
# (PAIR_WEIGHTS below). A pair's z is its difference over this. Objects that are alike all over
# (a tube, a bowl) set these; pieces of a varied one (a torso's chest and limbs) lie many scales
# apart, which the interval gaps, the spreads and the leftover stage of `cluster` are for.
# Floored at SCALE_FLOOR: a 1% difference (in log length or asinh curvature) is below what a
# scan resolves.
SCALE_FLOOR = 0.01
FEATURE_SCALES = (0.0346, 0.0144, 0.0108, 0.2434, 0.1297, 0.2928, 0.1024, 0.1016, 0.4108, 0.0713, 0.2320, 0.1868,
                  0.2284, 0.1477, 0.0473, 0.0332, 0.0510, 0.2441, 0.2701, 0.0501, 0.1299)
COLOUR_SCALE = 0.02
COLOUR_WEIGHT = -1.0  # logit per unit of the mean colour z (not fitted: no coloured training heaps)
Z_CAP = 8.0  # beyond this a feature says "different" no louder
Z_MISSING = 1.0  # z of a feature one of the two could not measure
# Each capped z enters the pair model as z, max(z - 1, 0), max(z - 3, 0): a piecewise-linear
# response per feature, so that one feature far apart (a sphere's shape index against a
# cylinder's) can outweigh many that agree.
Z_KNOTS = (1.0, 3.0)
# Fracture patches of two fragments "match" when area and both in-plane extents agree within
# exp(m); the pair feature is max(0, log(PATCH_TOLERANCE / m)) for the best-matching patches.
PATCH_TOLERANCE = 0.3
# Logistic model of "one object" over pair_inputs: per knot block (z, then max(z - t, 0) for t in
# Z_KNOTS) the z of FEATURE_NAMES then of the GAP_NAMES gaps, then the patch match, last the
# intercept; class-balanced, L2 1.0. Fitted by `scripts/bench_group.py --fit 10 ... 29 40 ... 59
# --fit-corpus FAMILY ...` on heaps of synthetic mixture seeds 10-29 and 40-59 (this project's
# generator, one scan resolution) together with corpus heaps (relicgpu.synth.corpus, 4 objects of
# one family, seeds 0-19) of ten of its twelve families, the fracture read as crease regions
# (describe._grouping_params); smooth-noisy and vessel-coarse were kept out of every fit and
# choice. Synth mixtures alone, read by roughness, had given a model at ARI 0.45 on corpus heaps
# (docs/benchmarks.md, "Grouping heaps of other fractures").
# Depends on relicgpu.pair.segment (which faces are fracture): refit when it changes.
PAIR_WEIGHTS = (-0.134, -0.957, 0.121, -0.238, -0.748, 0.111, -0.161, -0.264, -0.234, 0.071, 0.044, -0.206, -0.126,
                0.057, -1.218, -0.686, 0.002, -0.103, -0.065, 0.368, -0.093, 0.006, 0.324, -0.856, -1.042, 0.181,
                -1.039, 0.083, 0.980, -0.553, -0.015, 0.695, -0.508, -0.102, 0.236, 0.038, 0.195, -0.021, 0.095,
                0.178, -0.043, 0.935, 0.387, 0.119, 0.201, -0.264, -0.945, 0.128, 0.224, -0.147, 1.017, 1.208,
                -0.560, 1.291, 0.139, -0.137, 0.387, 0.212, 0.020, 0.571, 0.149, 0.020, 0.276, -0.324, 0.009, 0.151,
                -0.102, 0.279, 0.275, 0.213, -0.278, -0.210, 0.353, 0.676, -0.107, -0.322, -0.292, -0.204, -0.475,
                0.396, -0.397, 0.909, 9.165)
# Clusters merge while the mean probability of one object between them is above 1 - LINK_CUT
# (average linkage). Fragments left in groups of at most LEFTOVER_SIZE are then clustered among
# themselves at LEFTOVER_CUT: pieces unlike the rest of their own object (a torso's limb and its
# chest) find each other there rather than staying alone. LEFTOVER_* chosen with the synth-only
# model by two-fold on mixture seeds 10-29 and 40-59 (settings 2-5 / 0.8-0.95 within 0.01 of one
# another). LINK_CUT chosen with the model above, each corpus fracture kind left out of the fit in
# turn and scored on its families' heaps (mean ARI over the ten families 0.621 / 0.655 / 0.650 at
# 0.3 / 0.4 / 0.5; two-fold on the mixtures 0.894 / 0.897 / 0.901).
LINK_CUT = 0.4
LEFTOVER_SIZE = 3
LEFTOVER_CUT = 0.9


@dataclass(frozen=True)
class Grouping:
    names: list[str]
    labels: np.ndarray  # (n,) group per fragment, 0 the largest
    silhouette: float  # of the chosen split on 1 - p (nan for one group)
    scores: dict = field(default_factory=dict)  # extra figures of the method
    method: str = "average"
    timings: dict = field(default_factory=dict)
    files: list = field(default_factory=list)  # the file name of each fragment (default: its name)
    skipped: list = field(default_factory=list)  # files and crumbs left out while loading (io.Batch)
    notes: list = field(default_factory=list)  # other loading decisions

    @property
    def groups(self) -> list[list[str]]:
        return [[n for n, l in zip(self.names, self.labels) if l == g] for g in range(int(self.labels.max()) + 1)]

    def to_dict(self) -> dict:
        return {"version": 1, "method": self.method,
                "groups": self.groups,
                "fragments": [{"name": n, "file": f, "group": int(l)}
                              for n, f, l in zip(self.names, self.files or self.names, self.labels)],
                "silhouette": None if not np.isfinite(self.silhouette) else float(self.silhouette),
                "timings": {k: round(float(v), 4) for k, v in self.timings.items()},
                "skipped": list(self.skipped), "notes": list(self.notes)}


# --- unsupervised -------------------------------------------------------------

def silhouette(dist: np.ndarray, labels: np.ndarray) -> float:
    """Mean silhouette of a labelling over a full distance matrix (singletons score 0)."""
    ks = np.unique(labels)
    if len(ks) < 2 or len(ks) >= len(labels):
        return float("nan")
    mean_to = np.stack([dist[:, labels == k].sum(1) for k in ks], axis=1)
    counts = np.array([(labels == k).sum() for k in ks], np.float64)
    own = np.searchsorted(ks, labels)
    n_own = counts[own]
    a = mean_to[np.arange(len(labels)), own] / np.maximum(n_own - 1, 1)
    other = mean_to / counts[None]
    other[np.arange(len(labels)), own] = np.inf
    b = other.min(1)
    s = np.where(n_own > 1, (b - a) / np.maximum(np.maximum(a, b), 1e-300), 0.0)
    return float(s.mean())


def pair_z(values: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """(n, n, D) |x_i - x_j| / scale per feature, capped at Z_CAP; Z_MISSING where either is nan."""
    z = np.abs(values[:, None] - values[None]) / np.asarray(scales, np.float64)
    return np.where(np.isnan(z), Z_MISSING, np.minimum(z, Z_CAP))


def patch_match(descriptors: list[Descriptor]) -> np.ndarray:
    """(n, n) max(0, log(PATCH_TOLERANCE / m)), m the smallest over patch pairs of the largest
    |log ratio| of area and in-plane extents: > 0 where two fragments have a fracture patch of
    one size and outline, as the two sides of one cut have."""
    logs = [np.log(np.maximum(d.patches, 1e-300)) if d.patches is not None and len(d.patches) else None
            for d in descriptors]
    n = len(descriptors)
    m = np.full((n, n), np.inf)
    for i in range(n):
        for j in range(i + 1, n):
            if logs[i] is not None and logs[j] is not None:
                m[i, j] = m[j, i] = np.abs(logs[i][:, None] - logs[j][None]).max(axis=2).min()
    return np.log(np.maximum(PATCH_TOLERANCE / np.maximum(m, 1e-2), 1.0))


def interval_gaps(descriptors: list[Descriptor], ref_length: float) -> np.ndarray:
    """(n, n, len(GAP_NAMES)) the gap between two pieces' quartile intervals, 0 where they overlap
    (nan where either is unmeasured)."""
    iv = np.stack([d.intervals(ref_length) for d in descriptors])  # (n, G, 2)
    lo = np.maximum(iv[:, None, :, 0], iv[None, :, :, 0])
    hi = np.minimum(iv[:, None, :, 1], iv[None, :, :, 1])
    return np.maximum(lo - hi, 0.0)


def pair_inputs(descriptors: list[Descriptor], scales=None) -> tuple[np.ndarray, np.ndarray | None]:
    """The pair model's inputs without colour (n, n, N_PAIR_INPUTS): the capped z of each
    FEATURE_NAMES feature and of each GAP_NAMES gap, each expanded at Z_KNOTS, then the patch
    match; and the mean colour z (n, n) when every fragment has colour (else None)."""
    L = float(np.median([d.size for d in descriptors]))
    values = np.stack([d.features(L) for d in descriptors])
    k = len(FEATURE_NAMES)
    sc = np.asarray(FEATURE_SCALES if scales is None else scales, np.float64)
    gaps = interval_gaps(descriptors, L) / np.asarray(GAP_SCALES)
    z = np.concatenate([pair_z(values[:, :k], sc), np.where(np.isnan(gaps), Z_MISSING, np.minimum(gaps, Z_CAP))],
                       axis=2)
    x = np.concatenate([z, *(np.maximum(z - t, 0.0) for t in Z_KNOTS), patch_match(descriptors)[:, :, None]], axis=2)
    colour = None
    if values.shape[1] > k:
        colour = pair_z(values[:, k:], np.full(values.shape[1] - k, COLOUR_SCALE)).mean(axis=2)
    return x, colour


N_PAIR_INPUTS = (len(FEATURE_NAMES) + len(GAP_NAMES)) * (1 + len(Z_KNOTS)) + 1


def pair_features(descriptors: list[Descriptor], scales=None) -> np.ndarray:
    """(n, n, N_PAIR_INPUTS [+ 1 with colour]): pair_inputs, the colour z last when present."""
    x, colour = pair_inputs(descriptors, scales)
    return x if colour is None else np.concatenate([x, colour[:, :, None]], axis=2)


def same_object_probability(features: np.ndarray, weights=None) -> np.ndarray:
    """(n, n) probability (class-balanced odds) that two fragments come from one object, from
    pair_features."""
    w = np.asarray(PAIR_WEIGHTS if weights is None else weights, np.float64)
    k = len(w) - 1
    logit = features[:, :, :k] @ w[:-1] + w[-1]
    if features.shape[2] > k:  # colour
        logit += COLOUR_WEIGHT * features[:, :, k]
    p = 1.0 / (1.0 + np.exp(-np.clip(logit, -50, 50)))
    np.fill_diagonal(p, 1.0)
    return 0.5 * (p + p.T)


def fit_feature_scales(heaps) -> np.ndarray:
    """FEATURE_SCALES from known mixtures [(descriptors, labels)]: per feature, 1.4826 x the
    median absolute deviation of fragments from their object's median, floored at SCALE_FLOOR."""
    res = []
    for desc, labels in heaps:
        L = float(np.median([d.size for d in desc]))
        x = np.stack([d.features(L)[:len(FEATURE_NAMES)] for d in desc])
        lab = np.asarray(labels)
        for o in np.unique(lab):
            m = lab == o
            med = np.array([np.median(c[np.isfinite(c)]) if np.isfinite(c).any() else np.nan for c in x[m].T])
            res.append(x[m] - med)
    r = np.abs(np.vstack(res))
    return np.maximum([1.4826 * np.median(c[np.isfinite(c)]) if np.isfinite(c).any() else 1.0 for c in r.T],
                      SCALE_FLOOR)


def fit_pair_model(heaps, scales=None, l2: float = 1.0, iterations: int = 50) -> np.ndarray:
    """Class-balanced L2 logistic regression of "same object" over pair_inputs (no colour).

    heaps: [(descriptors, labels)] of known mixtures. Returns the weights, intercept last."""
    xs, ys = [], []
    for desc, labels in heaps:
        feats, _ = pair_inputs(desc, scales)
        lab = np.asarray(labels)
        iu = np.triu_indices(len(lab), 1)
        xs.append(feats[iu])
        ys.append(lab[iu[0]] == lab[iu[1]])
    x = np.hstack([np.vstack(xs), np.ones((sum(len(a) for a in xs), 1))])
    y = np.concatenate(ys).astype(np.float64)
    if y.min() == y.max():
        raise ValueError("the training heaps need pairs of one object and pairs of two")
    sample_w = np.where(y == 1, 0.5 / y.mean(), 0.5 / (1 - y.mean()))
    w = np.zeros(x.shape[1])
    for _ in range(iterations):  # Newton steps
        p = 1.0 / (1.0 + np.exp(-(x @ w)))
        hess = x.T @ (x * (sample_w * p * (1 - p))[:, None]) + l2 * np.eye(len(w))
        w -= np.linalg.solve(hess, x.T @ (sample_w * (p - y)) + l2 * w)
    return w


def cluster(dist: np.ndarray, n_groups: int | None = None, distance: float = LINK_CUT,
            leftover_size: int = LEFTOVER_SIZE, leftover_cut: float = LEFTOVER_CUT) -> tuple[np.ndarray, float]:
    """Average-linkage clustering of a distance matrix (here 1 - p of one object), cut at
    `distance` (then the leftovers: fragments in groups of at most leftover_size, clustered among
    themselves at leftover_cut) or into `n_groups`: labels (0 = largest group) and their silhouette."""
    n = len(dist)
    if n == 1:
        return np.zeros(1, np.int64), float("nan")
    if n_groups is not None:
        labels = _average_linkage(dist, n_groups=min(int(n_groups), n))
    else:
        labels = _average_linkage(dist, distance=float(distance))
        _, inverse, sizes = np.unique(labels, return_inverse=True, return_counts=True)
        left = np.flatnonzero(sizes[inverse] <= leftover_size)
        if len(left) > 1 and leftover_cut > distance:
            labels[left] = labels.max() + 1 + _average_linkage(dist[np.ix_(left, left)], distance=leftover_cut)
    labels = _relabel_by_size(labels)
    return labels, silhouette(dist, labels)


def _average_linkage(dist, distance=None, n_groups=None):
    from scipy.cluster.hierarchy import fcluster, linkage
    from scipy.spatial.distance import squareform

    if len(dist) == 1:
        return np.zeros(1, np.int64)
    tree = linkage(squareform(dist, checks=False), method="average")
    if n_groups is not None:
        return np.asarray(fcluster(tree, n_groups, criterion="maxclust"), np.int64)
    return np.asarray(fcluster(tree, distance, criterion="distance"), np.int64)


def _relabel_by_size(labels):
    ks, first, counts = np.unique(labels, return_index=True, return_counts=True)
    order = sorted(range(len(ks)), key=lambda i: (-counts[i], first[i]))
    remap = {ks[i]: r for r, i in enumerate(order)}
    return np.array([remap[l] for l in labels], np.int64)


def group_fragments(fragments: list[Fragment], n_groups: int | None = None, distance: float | None = None,
                    params=None, progress: bool = False) -> Grouping:
    """Unsupervised grouping of a heap (see the module docstring)."""
    if not fragments:
        raise FragmentError("no fragments to group")
    t0 = time.perf_counter()
    surfaces, skipped = [], []
    for fr in fragments:  # a point cloud that does not close has no surface to describe: left out, said so
        try:
            surfaces.append(surface_of(fr))
        except FragmentError as exc:
            skipped.append({"file": fr.file, "reason": f"{exc}; not grouped"})
    if not surfaces:
        raise FragmentError(f"no fragments to group ({skipped[0]['reason']})")
    desc = describe_all(surfaces, params, progress)
    t1 = time.perf_counter()
    p = heap_probability(desc)
    labels, sil = cluster(1.0 - p, n_groups, LINK_CUT if distance is None else distance)
    t2 = time.perf_counter()
    return Grouping([fr.name for fr in surfaces], labels, sil, {}, "average",
                    {"describe": t1 - t0, "cluster": t2 - t1}, [fr.file for fr in surfaces], skipped)


def heap_probability(descriptors: list[Descriptor]) -> np.ndarray:
    """(n, n) probability of one object for every pair of a heap's fragments."""
    return same_object_probability(pair_features(descriptors))


def group(fragments, n_groups: int | None = None, **kw) -> list[list[str]]:
    """Fragments (a list, or a directory) -> groups of fragment names, largest first."""
    return group_fragments(_load(fragments).fragments, n_groups, **kw).groups


def adjusted_rand_index(truth, pred) -> float:
    """Hubert-Arabie adjusted Rand index of two labellings."""
    from scipy.special import comb

    _, t = np.unique(np.asarray(truth), return_inverse=True)
    _, p = np.unique(np.asarray(pred), return_inverse=True)
    table = np.zeros((t.max() + 1, p.max() + 1))
    np.add.at(table, (t, p), 1)
    n = len(t)
    sum_cells = comb(table, 2).sum()
    sum_rows, sum_cols = comb(table.sum(1), 2).sum(), comb(table.sum(0), 2).sum()
    expected = sum_rows * sum_cols / comb(n, 2)
    top = 0.5 * (sum_rows + sum_cols)
    if top == expected:
        return 1.0
    return float((sum_cells - expected) / (top - expected))


def _load(fragments_or_dir) -> Batch:
    """A directory, a list of files and Fragments, or a Batch -> a Batch (io.read_batch): a file
    that cannot be read is skipped, a file of several bodies split, crumbs dropped."""
    return read_batch(fragments_or_dir)
