"""Per-fragment descriptors that survive breakage (see relicgpu.heap.grouping): curvature
and wall thickness of the original surface, roughness, relief spectrum and patches of the
fracture surfaces, colour; and the matrix of their unit-free features over a heap."""
from __future__ import annotations

import dataclasses
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..backends import resolve
from ..cloud.triangulate import surface_of
from ..io.fragment import Fragment, FragmentError
from ..params import Params
from ..pair.denoise import denoised
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



# --- descriptors -------------------------------------------------------------


def _grouping_params(params) -> "Params":
    """The segmentation the grouping descriptors and the pair model were fitted on: crease
    regions ("regions"), whatever `Params.segmentation` the matcher is given. Fitted with each
    corpus fracture kind left out, it grouped those kinds' heaps at ARI 0.655 against 0.562 with
    Otsu's roughness split (docs/benchmarks.md, "Grouping heaps of other fractures")."""
    return dataclasses.replace(params or Params(), segmentation="regions")


def describe(fragment: Fragment, params=None, colours: np.ndarray | None = None) -> Descriptor:
    """The breakage-surviving descriptors of one fragment (a point cloud's: of `surface_of` it; a mesh
    noisy at its triangles' scale: of its smoothed copy, `pair.denoise`)."""
    fragment = surface_of(fragment)
    if _grouping_params(params).denoise:
        fragment = denoised(fragment)
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
