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
  fitted once on synthetic heaps that are not the benchmark's, see
  `fit_pair_model`) gives the odds that the two come from one object;
  average-linkage agglomerative clustering on 1 - p, cut where the mean p
  between two clusters falls below 0.7, so the number of groups is found, not
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

import csv
import dataclasses
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..backends import resolve
from ..errors import CliError
from ..io.files import atomic_write_bytes, atomic_write_json
from ..io.fragment import Fragment, FragmentError
from ..io.load import Batch, load_fragment, read_batch
from ..params import Params
from ..pair.segment import segment
from ..pair.verify import vertex_normals

DESCRIPTOR_NAMES = (
    "kmax_q25", "kmax_q50", "kmax_q75", "kmin_q25", "kmin_q50", "kmin_q75",
    "thickness_q25", "thickness_q50", "thickness_q75",
    "orig_roughness", "frac_roughness", "frac_height", "frac_share",
)
THICKNESS_RAYS = 160
CURVATURE_EDGES = 4.0  # quadric fit radius, x the fragment's median edge length
CURVATURE_SAMPLES = 300
MIN_WALL_HITS = 8  # rays reaching the far side of the original surface, else no thickness
# The features compared between two fragments (Descriptor.features), all unit-free: lengths as
# log(x / L), curvatures as asinh(k * L), L the heap's median fragment size. "relief_R" is the
# fracture relief at radius R x L (spectrum_at); "chord" the inward ray length to the first face of
# any kind (a solid's pieces have no wall: their rays end on a cut); "wall_share" the share of rays
# that end on the original surface again; "kmax_spread" and "curvedness_spread" the interquartile
# ranges of asinh(kmax L) and asinh(curvedness L) over the piece (how varied its surface is: a
# torso's piece spans a range, a capsule's is one radius); "shape_index_q50" the median |shape
# index| (1 sphere, 0.5 cylinder, 0 saddle) where the curvature radius is below L.
RELIEF_RADII = (0.02, 0.04, 0.08)
FEATURE_NAMES = ("log_thickness_q25", "log_thickness_q50", "log_thickness_q75", "kmax_q25", "kmax_q50",
                 "kmin_q50", "orig_roughness", "frac_roughness", "frac_height", "frac_share",
                 *(f"relief_{r:g}" for r in RELIEF_RADII), "log_chord_q25", "log_chord_q50", "log_chord_q75",
                 "wall_share", "kmax_spread", "curvedness_spread", "shape_index_q50", "curvedness_q50")
# Per quantity, the quartile interval [q25, q75] of each piece (Descriptor.intervals); the pair
# feature is the gap between the two pieces' intervals (0 where they overlap) over GAP_SCALES:
# pieces of one varied object overlap somewhere even when their medians lie apart. Scales set by
# hand once (the typical quartile width of a uniform object's pieces), not fitted.
GAP_NAMES = ("kmax", "kmin", "log_thickness", "log_chord", "shape_index", "curvedness")
GAP_SCALES = (0.02, 0.05, 0.02, 0.05, 0.05, 0.02)
SHAPE_INDEX_MIN_CURVEDNESS = 1.0  # x 1/L: flatter points have no meaningful shape index
# Per feature, how far apart two fragments of one object typically are: 1.4826 x the median
# absolute deviation from their object's median, pooled over the objects of synthetic heaps
# (`scripts/bench_group.py --fit 10 ... 29 40 ... 59`). A pair's z is its difference over this. Objects that
# are alike all over (a tube, a bowl) set these; pieces of a varied one (a torso's chest and
# limbs) lie many scales apart, which the interval gaps, the spreads and the leftover stage of
# `cluster` are for.
# Floored at SCALE_FLOOR: synthetic walls are exact, and a 1% difference (in log length or
# asinh curvature) is below what a scan resolves.
SCALE_FLOOR = 0.01
FEATURE_SCALES = (0.0100, 0.0100, 0.0100, 0.0100, 0.0100, 0.0336, 0.0513, 0.0359, 0.2470, 0.0700, 0.1638, 0.0770,
                  0.0764, 0.0325, 0.0100, 0.0100, 0.0556, 0.0159, 0.0534, 0.0100, 0.0100)
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
# intercept; class-balanced, L2 1.0, fitted by `scripts/bench_group.py --fit 10 ... 29 40 ... 59` on
# heaps of synthetic mixture seeds 10-29 and 40-59, scanned at one resolution (the benchmark scores
# seeds 0-4; seeds 30-39 served to diagnose failures, never to fit).
# Depends on relicgpu.pair.segment (which faces are fracture): refit when it changes. Two-fold (fitted on
# seeds 10-29, scored on 40-59, and the other way): mean ARI 0.971, min 0.791.
PAIR_WEIGHTS = (-0.338, 0.262, 0.195, 0.210, 0.200, 1.781, -0.099, -0.362, 0.101, 0.061, -0.261, 0.093, 0.128, 0.811,
                -0.070, 0.853, -0.076, 0.319, 0.326, 0.509, 0.370, -0.199, 0.788, -2.419, -2.457, -0.942, -1.950,
                -0.190, -0.076, 0.132, -2.207, -0.986, -1.652, 0.038, 0.187, -0.531, 0.253, 0.622, -0.249, -0.425,
                -1.056, -0.539, -1.041, 0.296, -0.172, 0.305, 0.319, -0.477, 0.176, -0.530, 2.752, 3.407, 0.861,
                2.447, 0.392, -0.264, -0.453, 2.070, 0.695, -0.336, -0.189, -0.064, 0.266, -0.813, -0.381, 0.233,
                0.476, 0.495, 0.641, 0.187, -0.967, -0.363, -1.159, -0.933, 0.222, -0.121, -0.361, -0.615, -1.248,
                -0.168, -0.722, 0.898, 9.119)
# Clusters merge while the mean probability of one object between them is above 1 - LINK_CUT
# (average linkage). Fragments left in groups of at most LEFTOVER_SIZE are then clustered among
# themselves at LEFTOVER_CUT: pieces unlike the rest of their own object (a torso's limb and its
# chest) find each other there rather than staying alone. Chosen with the model below by two-fold
# on seeds 10-29 and 40-59 (fitted on one half, scored on the other): mean ARI 0.971 (min 0.791) at
# 0.3 / 3 / 0.9; 0.960 (min 0.667) at 0.4; 0.968 at 0.25; 0.952 at 0.5; single linkage weighted
# 0.967, complete 0.922-0.944; leftover settings 2-5 / 0.8-0.95 within 0.01 of one another.
LINK_CUT = 0.3
LEFTOVER_SIZE = 3
LEFTOVER_CUT = 0.9
CLASSIFIER_POINTS = 256
SPECTRUM_RADII = tuple(2.0 ** np.arange(-7.0, -1.4, 0.5))  # x the fragment size: where the spectrum is measured
SPECTRUM_SAMPLES = 120
PATCHES = 8


@dataclass(frozen=True)
class Descriptor:
    """Raw geometry of one fragment, in the fragment's own units (see the module docstring)."""
    name: str
    kmax: np.ndarray  # (Q,) area-weighted quantiles 25/50/75 of the larger normal curvature, 1/length
    kmin: np.ndarray  # (Q,) same for the smaller
    thickness: np.ndarray  # (3,) quantiles 25/50/75 of wall thickness, length (nan when unmeasured)
    orig_roughness: float  # degrees
    frac_roughness: float  # degrees
    frac_height: float  # RMS height of fracture patches about their planes, length
    frac_share: float  # fracture area / total area
    size: float  # bounding-box diagonal
    colour: np.ndarray | None = None  # (6,) mean and std of RGB in [0, 1] on the original surface
    frac_spectrum: np.ndarray | None = None  # (len(SPECTRUM_RADII),) RMS height of the fracture surface about
    #   its local plane within each radius SPECTRUM_RADII x size, length; nan where unmeasured
    patches: np.ndarray | None = None  # (P, 3) fracture patches, largest first: area, the two in-plane extents
    chord: np.ndarray | None = None  # (3,) quantiles 25/50/75 of the inward ray length to the first face of any kind
    wall_share: float = float("nan")  # share of inward rays whose first hit is the original surface (a wall)
    curvatures: np.ndarray | None = None  # (m, 2) principal curvatures (kmax, kmin) at points drawn by area

    def vector(self, ref_length: float) -> np.ndarray:
        """Unit-free feature vector for the classifier: curvatures as asinh(k * L), lengths as
        log(x / L) (an unmeasured wall thickness as the fragment's size), then the shape measures
        of FEATURE_NAMES' tail."""
        L = float(ref_length)
        thick = np.log(np.maximum(np.nan_to_num(self.thickness, nan=self.size), 1e-6 * L) / L)
        chord = np.log(np.maximum(np.nan_to_num(self.chord, nan=self.size), 1e-6 * L) / L)
        si, cv = self.shape_measures(L)
        v = [np.arcsinh(self.kmax * L), np.arcsinh(self.kmin * L), thick,
             [np.log1p(self.orig_roughness), np.log1p(self.frac_roughness),
              np.log(max(self.frac_height, 1e-6 * L) / L), self.frac_share],
             chord, [np.nan_to_num(self.wall_share, nan=0.0)], np.nan_to_num(si, nan=0.0), cv]
        if self.colour is not None:
            v.append(self.colour)
        return np.concatenate([np.asarray(x, np.float64).ravel() for x in v])

    def shape_measures(self, ref_length: float) -> tuple[np.ndarray, np.ndarray]:
        """Quartiles 25/50/75 of |shape index| (over points whose curvedness is at least
        SHAPE_INDEX_MIN_CURVEDNESS / L; nan when fewer than 10) and of asinh(curvedness L)."""
        L = float(ref_length)
        k = self.curvatures if self.curvatures is not None else np.stack([self.kmax, self.kmin], axis=1)
        k1, k2 = k[:, 0], k[:, 1]
        curvedness = np.sqrt(0.5 * (k1 * k1 + k2 * k2))
        q = (0.25, 0.5, 0.75)
        curved = curvedness * L >= SHAPE_INDEX_MIN_CURVEDNESS
        si = np.abs(2 / np.pi * np.arctan2(k1 + k2, k1 - k2))
        si_q = np.quantile(si[curved], q) if curved.sum() >= 10 else np.full(3, np.nan)
        return si_q, np.quantile(np.arcsinh(curvedness * L), q)

    def features(self, ref_length: float) -> np.ndarray:
        """The unit-free features of FEATURE_NAMES (nan where unmeasured), then the mean colour
        when the fragment has one."""
        L = float(ref_length)
        log = lambda x: np.log(x / L) if np.isfinite(x) and x > 0 else np.nan
        kmax, kmin = np.arcsinh(self.kmax * L), np.arcsinh(self.kmin * L)
        si, cv = self.shape_measures(L)
        chord = self.chord if self.chord is not None else np.full(3, np.nan)
        values = [*(log(t) for t in self.thickness), kmax[0], kmax[1], kmin[1],
                  np.log1p(self.orig_roughness), np.log1p(self.frac_roughness),
                  np.log(max(self.frac_height, 1e-6 * L) / L), self.frac_share,
                  *(log(spectrum_at(self, r * L)) for r in RELIEF_RADII),
                  *(log(c) for c in chord), self.wall_share,
                  np.log(kmax[2] - kmax[0] + 0.02), np.log(cv[2] - cv[0] + 0.02), si[1], cv[1]]
        if self.colour is not None:
            values += list(self.colour[:3])
        return np.array(values, np.float64)

    def intervals(self, ref_length: float) -> np.ndarray:
        """(len(GAP_NAMES), 2) the quartile interval [q25, q75] of each GAP_NAMES quantity,
        unit-free as in features (nan where unmeasured)."""
        L = float(ref_length)
        log = lambda x: np.log(np.where(np.asarray(x) > 0, x, np.nan) / L)
        si, cv = self.shape_measures(L)
        chord = self.chord if self.chord is not None else np.full(3, np.nan)
        rows = [np.arcsinh(self.kmax * L), np.arcsinh(self.kmin * L), log(self.thickness), log(chord), si, cv]
        return np.array([[r[0], r[2]] for r in rows], np.float64)


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


# --- descriptors -------------------------------------------------------------


def _grouping_params(params) -> "Params":
    """The segmentation the grouping descriptors and the pair model were fitted on:
    Otsu's roughness split, whatever `Params.segmentation` the matcher is given ("union"
    and "regions" add region cues; the pair model has not been refitted on those labels)."""
    return dataclasses.replace(params or Params(), segmentation="roughness")


def describe(fragment: Fragment, params=None, colours: np.ndarray | None = None) -> Descriptor:
    """The breakage-surviving descriptors of one fragment."""
    v = np.asarray(fragment.vertices, np.float64)
    f = np.asarray(fragment.faces, np.int64)
    if len(f) < 4:
        raise FragmentError(f"{fragment.source or fragment.name}: too few faces ({len(f)}) to describe")
    size = fragment.size
    seg = segment(v, f, _grouping_params(params), size, resolve("numpy"))
    frac = seg.fracture_faces
    areas, fn = seg.areas, seg.normals
    total = float(areas.sum())
    orig = ~frac
    if not orig.any():  # all fracture (a tiny chip): describe it as one surface
        orig = np.ones(len(f), bool)

    vn = vertex_normals(v, f, fn, areas)
    edges = np.linalg.norm(v[f] - v[np.roll(f, 1, axis=1)], axis=2)
    kmax, kmin = _quadric_curvatures(v, f, vn, orig, areas, CURVATURE_EDGES * float(np.median(edges)))
    q = (0.25, 0.5, 0.75)
    kmax_q = np.quantile(kmax, q)
    kmin_q = np.quantile(kmin, q)

    thickness, chord, wall_share = _wall_thickness(v, f, fn, areas, orig)
    orig_rough = float(np.average(seg.face_roughness[orig], weights=areas[orig] + 1e-300))
    if frac.any():
        frac_rough = float(np.average(seg.face_roughness[frac], weights=areas[frac] + 1e-300))
        frac_height = _patch_height(v, f, seg.face_region, frac, areas)
    else:
        frac_rough, frac_height = 0.0, 0.0
    colour = None
    if colours is not None and len(colours) == len(v):
        used = np.zeros(len(v), bool)
        used[f[orig].ravel()] = True
        c = np.asarray(colours, np.float64)[used, :3]
        c = c / 255.0 if c.max() > 1.0 else c
        colour = np.concatenate([c.mean(0), c.std(0)])
    spectrum = _fracture_spectrum(v, f, frac, areas, size)
    patches = _fracture_patches(v, f, seg.face_region, frac, areas)
    return Descriptor(fragment.name, kmax_q, kmin_q, thickness, orig_rough, frac_rough, frac_height,
                      float(areas[frac].sum() / total) if total > 0 else 0.0, size, colour,
                      spectrum, patches, chord, wall_share, np.stack([kmax, kmin], axis=1))


def _fracture_spectrum(v, f, frac, areas, size, radii=None, samples=SPECTRUM_SAMPLES):
    """Per radius r x size: the median over sampled points of the masked faces (`frac`) of the RMS
    distance of those face centres within that radius from their best-fit plane: a rough-surface
    spectrum (how the relief grows with the window, which a cut keeps wherever the piece came from)."""
    from scipy.spatial import cKDTree

    radii = SPECTRUM_RADII if radii is None else radii
    out = np.full(len(radii), np.nan)
    idx = np.flatnonzero(frac)
    if len(idx) < 12:
        return out
    centres = v[f[idx]].mean(axis=1)
    tree = cKDTree(centres)
    rng = np.random.default_rng(len(f))
    pick = rng.choice(len(idx), min(samples, len(idx)), replace=False, p=areas[idx] / areas[idx].sum())
    for k, r in enumerate(radii):
        hoods = [nb for nb in tree.query_ball_point(centres[pick], r * size) if len(nb) >= 6]
        if len(hoods) < 5:
            continue
        # covariance of each neighbourhood from its sums (shifted by the sample point for precision)
        cov = np.empty((len(hoods), 3, 3))
        for j, nb in enumerate(hoods):
            c = centres[nb] - centres[nb[0]]
            m = c.mean(0)
            cov[j] = c.T @ c / len(c) - np.outer(m, m)
        out[k] = float(np.median(np.sqrt(np.maximum(np.linalg.eigvalsh(cov)[:, 0], 0.0))))
    return out


def spectrum_at(d: "Descriptor", radius: float) -> float:
    """The relief of a fragment's fracture surface at an absolute radius: its spectrum
    interpolated in log-log (nan outside the radii it was measured at)."""
    spectrum = d.frac_spectrum
    if spectrum is None:
        return float("nan")
    r = np.log(np.asarray(SPECTRUM_RADII) * d.size)
    ok = np.isfinite(spectrum) & (spectrum > 0)
    x = np.log(radius)
    if ok.sum() < 2 or not r[ok][0] <= x <= r[ok][-1]:
        return float("nan")
    return float(np.exp(np.interp(x, r[ok], np.log(spectrum[ok]))))


def _patch_moments(v, f, face_region, frac, areas):
    """Per fracture patch (of 6 faces or more): its face areas, face centres, their area-weighted
    mean and covariance."""
    centres = v[f].mean(axis=1)
    for r in np.unique(face_region[frac]):
        m = face_region == r
        if m.sum() < 6:
            continue
        w, c = areas[m], centres[m]
        mu = (c * w[:, None]).sum(0) / w.sum()
        yield w, c, mu, ((c - mu) * w[:, None]).T @ (c - mu) / w.sum()


def _fracture_patches(v, f, face_region, frac, areas, top=PATCHES):
    """(P, 3) the largest fracture patches: area and the spreads (2 sigma) of their faces along
    the two in-plane principal axes; the other side of the same cut has about the same."""
    rows = []
    for w, _, _, cov in _patch_moments(v, f, face_region, frac, areas):
        ev = np.linalg.eigvalsh(cov)
        rows.append((float(w.sum()), 2 * np.sqrt(max(ev[2], 0.0)), 2 * np.sqrt(max(ev[1], 0.0))))
    rows.sort(key=lambda t: -t[0])
    return np.array(rows[:top], np.float64).reshape(-1, 3)


def _quadric_curvatures(v, f, vn, face_mask, areas, radius, samples=CURVATURE_SAMPLES):
    """Principal curvatures (convex > 0) at vertices of the masked faces drawn by area: a quadric
    height field fitted over the masked surface's vertices within `radius` whose normals agree
    with the centre's (not the far side of a thin wall); (kmax, kmin), each (m,).

    The fit over a few edges' radius averages out the scan noise that a per-edge estimate
    amplifies differently on differently tessellated parts of one object."""
    from scipy.spatial import cKDTree

    sub = f[face_mask]
    touch_other = np.zeros(len(v), bool)  # the crease to a fracture: its normals average two surfaces
    touch_other[f[~face_mask].ravel()] = True
    ids = np.unique(sub)
    if (~touch_other[ids]).sum() >= 8:
        ids = ids[~touch_other[ids]]
    weight = np.zeros(len(v))
    for c in range(3):
        np.add.at(weight, sub[:, c], areas[face_mask] / 3)
    w = weight[ids]
    if len(ids) < 8 or w.sum() <= 0:
        return np.zeros(1), np.zeros(1)
    rng = np.random.default_rng(len(f))
    pick = rng.choice(ids, min(samples, len(ids)), replace=False, p=w / w.sum())
    pts, nrm = v[ids], vn[ids]
    tree = cKDTree(pts)
    kmax, kmin = [], []
    for c, hood in zip(pick, tree.query_ball_point(v[pick], radius)):
        n = vn[c]
        hood = np.asarray(hood)
        hood = hood[nrm[hood] @ n > 0.5]
        if len(hood) < 8:
            continue
        t1 = np.cross(n, (1.0, 0.0, 0.0) if abs(n[0]) < 0.9 else (0.0, 1.0, 0.0))
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(n, t1)
        d = pts[hood] - v[c]
        x, y, h = d @ t1, d @ t2, d @ n
        a = np.stack([x * x, x * y, y * y, x, y, np.ones_like(x)], axis=1)
        coef = np.linalg.lstsq(a, h, rcond=None)[0]
        k = -np.linalg.eigvalsh(np.array([[2 * coef[0], coef[1]], [coef[1], 2 * coef[2]]]))
        kmax.append(k.max())
        kmin.append(k.min())
    if not kmax:
        return np.zeros(1), np.zeros(1)
    return np.array(kmax), np.array(kmin)


def _wall_thickness(v, f, fn, areas, orig, rays=THICKNESS_RAYS):
    """Rays from original-surface face centres inward along the negative normal (Moller-Trumbore
    on every face): quantiles 25/50/75 of the wall thickness (over the rays whose first hit is
    the original surface again; nan when fewer than MIN_WALL_HITS are), the same of the length
    to the first hit of any kind (the chord), and the share of rays that met a wall."""
    cand = np.flatnonzero(orig)
    if len(cand) == 0:
        return np.full(3, np.nan), np.full(3, np.nan), float("nan")
    rng = np.random.default_rng(len(f))
    pick = rng.choice(cand, min(rays, len(cand)), replace=False, p=areas[cand] / areas[cand].sum())
    tri = v[f]
    origin = tri[pick].mean(axis=1)
    direction = -fn[pick]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    eps = 1e-9 * max(1.0, float(np.abs(v).max()))
    hits = np.full(len(pick), np.nan)
    wall = np.zeros(len(pick), bool)
    chunk = max(1, 2_000_000 // len(f))
    for s in range(0, len(pick), chunk):
        o, d = origin[s:s + chunk, None, :], direction[s:s + chunk, None, :]
        p = np.cross(d, e2[None])
        det = np.einsum("rfk,fk->rf", p, e1)
        inv = 1.0 / np.where(np.abs(det) > 1e-300, det, np.inf)
        tvec = o - tri[None, :, 0]
        u = np.einsum("rfk,rfk->rf", tvec, p) * inv
        qv = np.cross(tvec, e1[None])
        w = np.einsum("rfk,rk->rf", qv, d[:, 0]) * inv
        t = np.einsum("rfk,fk->rf", qv, e2) * inv
        ok = (u >= 0) & (w >= 0) & (u + w <= 1) & (t > eps)
        ok[np.arange(len(o)), pick[s:s + chunk]] = False  # the face the ray starts on
        t = np.where(ok, t, np.inf)
        first = t.argmin(axis=1)
        best = t[np.arange(len(o)), first]
        # a wall is what a ray crosses to the original surface's far side; a fracture face first
        # means the piece was cut there (a solid's chord ends where the cut fell)
        hits[s:s + chunk] = np.where(np.isfinite(best), best, np.nan)
        wall[s:s + chunk] = np.isfinite(best) & orig[first]
    q = (0.25, 0.5, 0.75)
    chord = np.quantile(hits[np.isfinite(hits)], q) if np.isfinite(hits).any() else np.full(3, np.nan)
    thickness = np.quantile(hits[wall], q) if wall.sum() >= MIN_WALL_HITS else np.full(3, np.nan)
    return thickness, chord, float(wall.mean())


def _patch_height(v, f, face_region, frac, areas):
    """Area-weighted RMS distance of fracture face centres from their patch's best-fit plane."""
    num = den = 0.0
    for w, c, mu, cov in _patch_moments(v, f, face_region, frac, areas):
        normal = np.linalg.eigh(cov)[1][:, 0]
        h = (c - mu) @ normal
        num += float((w * h * h).sum())
        den += float(w.sum())
    return float(np.sqrt(num / den)) if den > 0 else 0.0


def _colours_of(fragment: Fragment):
    """Vertex colours from the fragment's file, when it has them (else None)."""
    if not fragment.source or not Path(fragment.source).is_file():
        return None
    try:
        import trimesh
        mesh = trimesh.load(fragment.source, force="mesh", process=False)
        vc = getattr(mesh.visual, "vertex_colors", None)
        if getattr(mesh.visual, "kind", None) != "vertex" or vc is None or len(vc) != len(fragment.vertices):
            return None
        return np.asarray(vc, np.float64)
    except Exception:  # a colour we cannot read is no colour; the geometry was loaded already
        return None


def describe_all(fragments: list[Fragment], params=None, progress: bool = False) -> list[Descriptor]:
    colours = [_colours_of(fr) for fr in fragments]
    if any(c is None for c in colours):  # colour only counts when every fragment has it
        colours = [None] * len(fragments)
    it = zip(fragments, colours)
    if progress:
        from tqdm import tqdm
        it = tqdm(list(it), desc="describe", unit="frag", file=sys.stderr, leave=False)
    return [describe(fr, params, c) for fr, c in it]


def descriptor_matrix(descriptors: list[Descriptor], ref_length: float | None = None) -> tuple[np.ndarray, float]:
    """(n, D) unit-free descriptors and the reference length used (default: median fragment size)."""
    L = float(ref_length or np.median([d.size for d in descriptors]))
    return np.stack([d.vector(L) for d in descriptors]), L


def standardise(x: np.ndarray) -> np.ndarray:
    """Robust z-scores per column: (x - median) / (1.4826 MAD), the MAD floored by the std / 4 and
    by 1e-9 (a column constant over the heap carries nothing)."""
    med = np.median(x, axis=0)
    mad = 1.4826 * np.median(np.abs(x - med), axis=0)
    spread = np.maximum(np.maximum(mad, 0.25 * x.std(axis=0)), 1e-9)
    return (x - med) / spread


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
    desc = describe_all(fragments, params, progress)
    t1 = time.perf_counter()
    p = heap_probability(desc)
    labels, sil = cluster(1.0 - p, n_groups, LINK_CUT if distance is None else distance)
    t2 = time.perf_counter()
    return Grouping([fr.name for fr in fragments], labels, sil, {}, "average",
                    {"describe": t1 - t0, "cluster": t2 - t1}, [fr.file for fr in fragments])


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


# --- supervised: a small PointNet ------------------------------------------------

def point_features(fragment: Fragment, ref_length: float, n_points: int = CLASSIFIER_POINTS,
                   rng: np.random.Generator | None = None, params=None, copies: int = 1) -> np.ndarray:
    """(copies, n_points, 7) area-weighted surface samples: position in the fragment's principal
    frame (over ref_length), face normal in that frame, fracture flag; independent samples."""
    rng = rng or np.random.default_rng(0)
    v, f = np.asarray(fragment.vertices, np.float64), np.asarray(fragment.faces, np.int64)
    seg = segment(v, f, _grouping_params(params), fragment.size, resolve("numpy"))
    return np.stack([_sample_points(v, f, seg, ref_length, n_points, rng) for _ in range(copies)])


def _sample_points(v, f, seg, ref_length, n_points, rng):
    p = seg.areas / seg.areas.sum()
    idx = rng.choice(len(f), n_points, p=p)
    r1, r2 = rng.random((2, n_points))
    s = np.sqrt(r1)
    tri = v[f[idx]]
    pts = (1 - s)[:, None] * tri[:, 0] + (s * (1 - r2))[:, None] * tri[:, 1] + (s * r2)[:, None] * tri[:, 2]
    centre = (v[f].mean(1) * seg.areas[:, None]).sum(0) / seg.areas.sum()
    _, vec = np.linalg.eigh(np.cov((pts - centre).T))
    frame = vec[:, ::-1]
    local = (pts - centre) @ frame
    # the sign of each axis: the side holding the third moment's weight (skewness > 0)
    signs = np.sign(np.sum(local ** 3, axis=0))
    signs[signs == 0] = 1
    signs[2] = signs[0] * signs[1] * np.linalg.det(frame)  # keep a rotation
    frame = frame * signs
    local = (pts - centre) @ frame
    normals = seg.normals[idx] @ frame
    return np.hstack([local / ref_length, normals, seg.fracture_faces[idx, None].astype(np.float64)])


def _net(n_desc: int, n_classes: int):
    import torch.nn as nn

    class PointNetClassifier(nn.Module):
        def __init__(self):
            super().__init__()
            self.point = nn.Sequential(nn.Conv1d(7, 32, 1), nn.BatchNorm1d(32), nn.ReLU(),
                                       nn.Conv1d(32, 64, 1), nn.BatchNorm1d(64), nn.ReLU(),
                                       nn.Conv1d(64, 128, 1), nn.BatchNorm1d(128), nn.ReLU())
            self.head = nn.Sequential(nn.Linear(128 + n_desc, 64), nn.BatchNorm1d(64), nn.ReLU(),
                                      nn.Dropout(0.2), nn.Linear(64, n_classes))

        def forward(self, pts, desc):
            import torch
            g = self.point(pts.transpose(1, 2)).max(dim=2).values
            return self.head(torch.cat([g, desc], dim=1))

    return PointNetClassifier()


@dataclass
class Classifier:
    classes: list[str]
    ref_length: float
    desc_mean: np.ndarray
    desc_std: np.ndarray
    state: dict  # torch state dict
    history: list = field(default_factory=list)  # mean training loss per epoch
    timings: dict = field(default_factory=dict)

    def save(self, path) -> None:
        import io as _io
        import torch
        buf = _io.BytesIO()
        torch.save({"version": 1, "classes": self.classes, "ref_length": self.ref_length,
                    "desc_mean": self.desc_mean.tolist(), "desc_std": self.desc_std.tolist(),
                    "state": self.state}, buf)
        atomic_write_bytes(path, buf.getvalue())

    @staticmethod
    def load(path) -> "Classifier":
        import torch
        try:
            d = torch.load(path, map_location="cpu", weights_only=True)
            return Classifier(list(d["classes"]), float(d["ref_length"]), np.asarray(d["desc_mean"]),
                              np.asarray(d["desc_std"]), d["state"])
        except FileNotFoundError:
            raise FragmentError(f"{path}: no such file") from None
        except Exception as exc:
            raise FragmentError(f"{path}: not a relicgpu classifier ({exc})") from None

    def predict(self, fragments: list[Fragment], params=None) -> tuple[list[str], np.ndarray]:
        """Class name per fragment and the class probabilities (n, C)."""
        import torch
        desc = describe_all(fragments, params)
        x = np.stack([d.vector(self.ref_length) for d in desc])
        if x.shape[1] != len(self.desc_mean):
            raise FragmentError(f"the classifier was trained with {len(self.desc_mean)} descriptors, these "
                                f"fragments give {x.shape[1]} (colour present in one and not the other?)")
        pts = np.stack([point_features(fr, self.ref_length, params=params)[0] for fr in fragments])
        net = _net(x.shape[1], len(self.classes))
        net.load_state_dict(self.state)
        net.eval()
        with torch.no_grad():
            logits = net(torch.as_tensor(pts, dtype=torch.float32),
                         torch.as_tensor((x - self.desc_mean) / self.desc_std, dtype=torch.float32))
            prob = torch.softmax(logits, 1).numpy()
        return [self.classes[k] for k in prob.argmax(1)], prob


def train_classifier(fragments: list[Fragment], labels: list[str], epochs: int = 120, seed: int = 0,
                     params=None, progress: bool = False, copies: int = 4) -> Classifier:
    """Train the PointNet classifier on labelled fragments (torch, CPU or CUDA)."""
    import torch

    if len(fragments) != len(labels) or not fragments:
        raise FragmentError("need one label per fragment and at least one fragment")
    classes = sorted(set(labels))
    if len(classes) < 2:
        raise FragmentError(f"need at least two classes to train, got {classes}")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # a net this small runs fastest on one thread, above all on a shared CPU
    try:
        return _train(fragments, labels, classes, epochs, seed, params, progress, copies)
    finally:
        torch.set_num_threads(threads)


def _train(fragments, labels, classes, epochs, seed, params, progress, copies) -> Classifier:
    import torch

    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    desc = describe_all(fragments, params, progress)
    x, L = descriptor_matrix(desc)
    mean, std = x.mean(0), np.maximum(x.std(0), 1e-6)
    xs = (x - mean) / std
    y = np.array([classes.index(l) for l in labels])
    # a few independent point samples per fragment: the sampling itself is an augmentation
    pts = np.stack([point_features(fr, L, rng=rng, params=params, copies=copies)
                    for fr in fragments])  # (n, copies, P, 7)
    timings = {"features": time.perf_counter() - t0}
    t0 = time.perf_counter()
    net = _net(x.shape[1], len(classes))
    opt = torch.optim.AdamW(net.parameters(), lr=2e-3, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, epochs)
    pts_t = torch.as_tensor(pts, dtype=torch.float32)
    xs_t = torch.as_tensor(xs, dtype=torch.float32)
    y_t = torch.as_tensor(y)
    n = len(fragments)
    batch = min(32, n)
    history = []
    bar = range(epochs)
    if progress:
        from tqdm import tqdm
        bar = tqdm(bar, desc="train", unit="epoch", file=sys.stderr, leave=False)
    for _ in bar:
        net.train()
        order = torch.randperm(n)
        total = 0.0
        for s in range(0, n - (n % batch if n > batch and n % batch == 1 else 0), batch):
            b = order[s:s + batch]
            if len(b) < 2:
                continue
            c = torch.randint(0, copies, (len(b),))
            p = pts_t[b, c].clone()
            # mirror-free augmentation: flip two principal axes together, jitter, scale +-5%
            flip = torch.where(torch.rand(len(b), 1, 2) < 0.5, -1.0, 1.0)
            p[:, :, [0, 1]] *= flip
            p[:, :, [3, 4]] *= flip
            p[:, :, :3] = p[:, :, :3] * (1 + 0.05 * (2 * torch.rand(len(b), 1, 1) - 1))
            p[:, :, :3] += 0.002 * torch.randn_like(p[:, :, :3])
            d = xs_t[b] + 0.05 * torch.randn_like(xs_t[b])
            loss = torch.nn.functional.cross_entropy(net(p, d), y_t[b], label_smoothing=0.05)
            opt.zero_grad()
            loss.backward()
            opt.step()
            total += float(loss.detach()) * len(b)
        sched.step()
        history.append(total / n)
    state = {k: v.detach().cpu() for k, v in net.state_dict().items()}
    timings["train"] = time.perf_counter() - t0
    return Classifier(classes, L, mean, std, state, history, timings)


def read_labels_csv(path) -> tuple[list[Path], list[str]]:
    """LABELS.csv: rows `file,label` (a header row `file,label` is skipped); files relative to the csv."""
    p = Path(path)
    try:
        rows = list(csv.reader(p.read_text().splitlines()))
    except FileNotFoundError:
        raise FragmentError(f"{p}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise FragmentError(f"{p}: unreadable ({exc})") from None
    files, labels = [], []
    for line, row in enumerate(rows, 1):
        if not row or not "".join(row).strip() or row[0].startswith("#"):
            continue
        if line == 1 and [c.strip().lower() for c in row[:2]] == ["file", "label"]:
            continue
        if len(row) != 2 or not row[0].strip() or not row[1].strip():
            raise FragmentError(f"{p}: line {line}: expected `file,label`, got {','.join(row)!r}")
        f = Path(row[0].strip())
        files.append(f if f.is_absolute() else p.parent / f)
        labels.append(row[1].strip())
    if not files:
        raise FragmentError(f"{p}: no labelled files")
    return files, labels


# --- CLI ------------------------------------------------------------------------------

def cli_add_arguments(parser, name="group") -> None:
    if name == "train-classifier":
        parser.add_argument("labels", metavar="LABELS.csv", help="rows `file,label` (paths relative to the csv)")
        parser.add_argument("-o", "--out", default=None,
                            help="weights file to write (default: classifier.pt beside LABELS.csv)")
        parser.add_argument("--epochs", type=int, default=120, help="training epochs (default: 120)")
        parser.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
        parser.add_argument("--quiet", action="store_true", help="no progress bar or summary")
        return
    parser.add_argument("directory", metavar="DIR", help="directory of fragment meshes")
    parser.add_argument("-o", "--out", required=True, help="output directory (groups.json)")
    parser.add_argument("--groups", type=int, default=None, help="number of groups (default: found)")
    parser.add_argument("--distance", type=float, default=None,
                        help=f"cut the tree where the mean probability of one object between two clusters "
                             f"falls below 1 - DISTANCE (default: {LINK_CUT})")
    parser.add_argument("--classifier", default=None, metavar="WEIGHTS",
                        help="classify with weights from `relicgpu train-classifier` instead of clustering")
    parser.add_argument("--quiet", action="store_true", help="no progress bar or summary")


def cli_main(args, name="group") -> int:
    log = (lambda *a: None) if args.quiet else (lambda *a: print(*a, file=sys.stderr))
    if name == "train-classifier":
        if args.epochs < 1:
            raise CliError(f"--epochs must be at least 1, got {args.epochs}")
        files, labels = read_labels_csv(args.labels)
        out = Path(args.out) if args.out else Path(args.labels).parent / "classifier.pt"
        if out.resolve() in {f.resolve() for f in files} or out.resolve() == Path(args.labels).resolve():
            raise CliError(f"{out}: the weights file must not be an input")
        fragments = [load_fragment(f) for f in files]
        t0 = time.perf_counter()
        clf = train_classifier(fragments, labels, args.epochs, args.seed, progress=not args.quiet)
        clf.save(out)
        pred, _ = clf.predict(fragments)
        acc = float(np.mean([p == l for p, l in zip(pred, labels)]))
        log(f"{len(fragments)} fragments, {len(clf.classes)} classes; training accuracy {acc:.3f}, "
            f"final loss {clf.history[-1]:.3f} ({time.perf_counter() - t0:.1f} s); wrote {out}")
        return 0

    src = Path(args.directory)
    if not src.is_dir():
        raise CliError(f"{src}: not a directory")
    if Path(args.out).resolve() == src.resolve():
        raise CliError(f"{args.out}: the output directory must not be the input directory")
    if args.groups is not None and args.groups < 1:
        raise CliError(f"--groups must be at least 1, got {args.groups}")
    batch = _load(src)
    for line in batch.messages():  # every file or crumb left out, even with --quiet
        print(line, file=sys.stderr)
    batch.require(2)
    fragments = batch.fragments
    if args.classifier:
        clf = Classifier.load(args.classifier)
        pred, prob = clf.predict(fragments)
        classes = sorted(set(pred), key=lambda c: (-pred.count(c), c))
        doc = {"version": 1, "method": "classifier", "classes": classes,
               "groups": [[fr.name for fr, p in zip(fragments, pred) if p == c] for c in classes],
               "fragments": [{"name": fr.name, "file": fr.file, "group": classes.index(p), "label": p,
                              "probability": float(pr.max())} for fr, p, pr in zip(fragments, pred, prob)]}
    else:
        if args.distance is not None and not 0.0 < args.distance < 1.0:
            raise CliError(f"--distance must lie between 0 and 1, got {args.distance}")
        doc = group_fragments(fragments, args.groups, args.distance, progress=not args.quiet).to_dict()
    doc.update(skipped=batch.skipped, notes=batch.notes)
    atomic_write_json(Path(args.out) / "groups.json", doc)
    sizes = [len(x) for x in doc["groups"]]
    log(f"{len(fragments)} fragments in {len(sizes)} group(s) of sizes {sizes}; wrote {Path(args.out) / 'groups.json'}")
    return 0
