"""`prepare` one fragment: segment -> contours -> features -> fuse (cacheable), and its surface
sample and point-pair tables; a cloud is prepared on its points (relicgpu.pair.cloudmatch)."""
from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass, field, replace

import numpy as np

from . import contour as contour_mod, features as features_mod, fusion as fusion_mod
from ..backends import resolve
from ..io.fragment import Fragment
from ..params import Params, second_reading_params
from .denoise import denoised
from .cloudmatch import STRICT_SPREADS, cloud_sample, plane_samples, region_samples
from ..cloud.points import even_subsample
from .ppf import PairTable, pair_table, smoothed_normals
from .segment import segment
from ..topology import ring_average
from .facets import flat_facets, grown_facets
from .verify import SurfaceSample, sample_spacing, vertex_normals
from .revolution import skin_axis
from .walls import wall_thickness

WALL_FACES = 4000  # the thin-wall checks' thickness is read on at most this many faces (`wall_thickness`)


@dataclass(frozen=True, eq=False)
class Contour:
    points: np.ndarray  # (N,3) closed loop, evenly resampled
    region: int  # the fracture region it bounds
    features: np.ndarray  # (N,5) raw [kcos, kappa, tau, chord_right, chord_left]
    fused: np.ndarray  # (N,) fused value per point
    feature_points: np.ndarray  # indices of curvature peaks (Eq. 17)


@dataclass(frozen=True, eq=False)
class Prepared:
    fragment: Fragment
    scale: float  # the length relative parameters were scaled by
    face_region: np.ndarray  # (F,)
    region_is_fracture: np.ndarray  # (R,)
    contours: list[Contour]
    sample: SurfaceSample
    patches: list = field(default_factory=list)  # fracture patches, largest first
    timings: dict = field(default_factory=dict)
    strict_sample: SurfaceSample | None = None  # clouds: the fracture picked strictly (cloudmatch.STRICT_SPREADS)
    regions: list = field(default_factory=list)  # clouds: (sample, patch) of each crease-bounded region
    second: "Prepared | None" = None  # meshes: prepared again with Params.second_segmentation
    planes: list = field(default_factory=list)  # clouds: (CutPlane, sample, roughness) of each candidate flat cut
    facets: list = field(default_factory=list)  # meshes: flat regions (`facets.Facet`), the same in every reading
    grown: list = field(default_factory=list)  # meshes: near-flat regions (`facets.grown_facets`), likewise

    @property
    def fracture_faces(self) -> np.ndarray:
        return self.region_is_fracture[self.face_region]



def prepare(fragment: Fragment, params: Params | None = None, backend="auto", scale: float | None = None,
            with_second: bool = False, facets: list | None = None, grown: list | None = None) -> Prepared:
    """Segment a fragment, extract its fracture contours and their fused features.

    with_second: also prepare it on `Params.second_segmentation` (`Prepared.second`), as an
    assembly does once per fragment; `match_pair` prepares it itself, only where the first
    reading finds no fit, when it is not there.
    facets, grown: its flat and near-flat facets where another reading found them (they do not
    depend on the reading)."""
    params = params or Params()
    be = resolve(backend)
    scale = float(scale or params.unit or fragment.size)
    if scale <= 0:
        raise ValueError(f"{fragment.name}: fragment has no extent")
    if len(fragment.faces) == 0:
        return _prepare_cloud(fragment, params, scale)
    if params.denoise:
        fragment = denoised(fragment)
    timings = {}
    t0 = time.perf_counter()
    seg = segment(fragment.vertices, fragment.faces, params, scale, be)
    t1 = time.perf_counter()
    timings["segment"] = t1 - t0

    model = fusion_mod.load_model(params.fusion_weights)
    step = params.contour_step * scale
    contours = []
    for r in np.flatnonzero(seg.region_is_fracture):
        for loop in contour_mod.region_boundary_loops(fragment.faces, seg.face_region == r):
            pts = fragment.vertices[loop]
            if contour_mod.loop_length(pts) < params.min_contour_points * step:
                continue
            pts = contour_mod.resample_closed(pts, step)
            raw, f = features_mod.contour_features(pts, step, params.kcos_k, params.feature_stride, be)
            fused = fusion_mod.fuse(f, model)
            peaks = features_mod.feature_points(raw[:, 0], params.feature_peak_window)
            contours.append(Contour(pts, int(r), raw, fused, peaks))
    t2 = time.perf_counter()
    timings["contours+features"] = t2 - t1

    prob = sampling_prob(seg, params)
    sample = _surface_sample(fragment, seg, prob, params.icp_points, params.ppf_normal_radius * scale,
                             params.crease_angle_deg, params.face_sample_step * scale)
    centres, skin = fragment.vertices[fragment.faces].mean(1), ~seg.fracture_faces
    # read on every face, not the reading's skin: a coarse vessel's skin read as part fracture and
    # its band as skin leave under half of that skin facing another face (corpus vessel-coarse);
    # on a coarse mesh on its sides: the centres of a decimated wall's large faces stand off each
    # other's normals, and the distances between them vary too much to read a wall
    at, normals, weights = ((centres, seg.normals, seg.areas) if sample.sides is None
                            else (*sample.sides, np.ones(len(sample.sides[0]))))  # evenly spread
    wall = wall_thickness(at, normals, weights, np.ones(len(at), bool), at_most=WALL_FACES)
    axis = skin_axis(centres[skin], seg.normals[skin], seg.areas[skin], thin=wall < params.region_thin_wall)
    sample = replace(sample, outline=outline_points(fragment.vertices, fragment.faces, seg, params.outline_radius * scale,
                                                    params.outline_spread, 2 * params.icp_points),
                     wall=wall, axis=axis)
    patches = fracture_patches(fragment, seg, prob)
    if facets is None:
        facets = flat_facets(fragment.vertices, fragment.faces, seg, scale) if params.facet_outline > 0 else []
    if grown is None:
        grown = grown_facets(fragment.vertices, fragment.faces, seg, scale) if params.grown_outline > 0 else []
    timings["sample"] = time.perf_counter() - t2
    second, second_params = None, second_reading_params(params)
    if with_second and second_params is not None:
        second = prepare(fragment, second_params, be, scale, facets=facets, grown=grown)
        timings["second"] = sum(second.timings.values())
    return Prepared(fragment, scale, seg.face_region, seg.region_is_fracture, contours, sample, patches, timings,
                    second=second, facets=facets, grown=grown)


def _second_reading(p: Prepared, params: Params, be, scale: float) -> Prepared | None:
    """A mesh fragment's second reading: kept in `p`, else prepared now (None: a cloud, or no
    fragment to prepare)."""
    if p.second is not None:
        return p.second
    if p.fragment is None or len(p.fragment.faces) == 0:
        return None
    return prepare(p.fragment, second_reading_params(params), be, scale, facets=p.facets, grown=p.grown)


def with_fragment(prepared: Prepared, fragment) -> Prepared:
    """`prepared` (and its second reading) holding `fragment` (None: left out, to ship or store)."""
    second = None if prepared.second is None else replace(prepared.second, fragment=fragment)
    return replace(prepared, fragment=fragment, second=second)


def shipped(prepared: Prepared, fragment) -> Prepared:
    """`prepared` to send or store beside `fragment`, the fragment it was prepared from: left out where
    it holds that fragment itself (the receiver has it), kept where prepare read a thinned copy
    (`thinned_cloud`), which is what its matching reads."""
    return with_fragment(prepared, None) if prepared.fragment is fragment else prepared


def received(prepared: Prepared, fragment) -> Prepared:
    """A `shipped` prepared holding `fragment` again where it was left out."""
    return with_fragment(prepared, fragment) if prepared.fragment is None else prepared


def sampling_prob(seg, params: Params) -> np.ndarray:
    """(F,) fracture likelihood the fracture sample is drawn with: `face_fracture_prob` where at
    least `sample_min_prob` (0 elsewhere); where that likelihood-weighted area is under
    `sample_min_share` of the fragment's (segmentation found next to no fracture) 1 on every face,
    so that the whole surface is matched and verification decides."""
    prob = np.where(seg.face_fracture_prob >= params.sample_min_prob, seg.face_fracture_prob, 0.0)
    if (seg.areas * prob).sum() < params.sample_min_share * seg.areas.sum():
        return np.ones(len(prob))
    return prob


def _surface_sample(fragment: Fragment, seg, prob: np.ndarray, n_points: int, plane_radius: float,
                    crease_angle: float, step: float = 0.0) -> SurfaceSample:
    """An even subsample of the vertices of faces of fracture likelihood prob (F,) > 0 (each
    weighted by the largest likelihood of its faces), of all vertices (with normals), and of
    points along the edges sharper than `crease_angle` degrees; and where faces have an edge
    longer than 2 `step`, the surface read for sides (`SurfaceSample.sides`): the vertices and
    points inside those faces (`face_points`; 0: none)."""
    v, f = fragment.vertices, fragment.faces
    normals = vertex_normals(v, f, seg.normals, seg.areas)
    frac_faces = np.flatnonzero(prob > 0)
    frac_faces = frac_faces[np.argsort(prob[frac_faces], kind="stable")]  # the likeliest face assigned last
    vertex_weight = np.zeros(len(v))
    np.maximum.at(vertex_weight, f[frac_faces].ravel(), np.repeat(prob[frac_faces], 3))
    vertex_region = np.full(len(v), -1)
    vertex_region[f[frac_faces].ravel()] = np.repeat(seg.face_region[frac_faces], 3)
    oriented = np.flatnonzero(np.linalg.norm(normals, axis=1) > 0.5)  # a vertex of degenerate faces has no normal
    frac = oriented[vertex_weight[oriented] > 0]
    # spread evenly over space, not drawn at random: the same sample up to units (issue 15)
    frac = frac[even_subsample(v[frac], n_points)]
    surf = oriented[even_subsample(v[oriented], 2 * n_points)]
    plane_normals = smoothed_normals(v[frac], normals[frac], plane_radius)
    sharp = seg.topology.edge_vertices[seg.edge_angle > crease_angle]
    creases = crease_points(v, sharp, sample_spacing(v[surf]), 2 * n_points)
    sample = SurfaceSample(v[frac], vertex_region[frac], normals[frac], v[surf], normals[surf], plane_normals,
                           fracture_weight=vertex_weight[frac], creases=creases, surface_weight=vertex_weight[surf])
    inner, face = face_points(v, f, step) if step > 0 else (np.zeros((0, 3)), np.zeros(0, np.int64))
    inner, face = (x[np.linalg.norm(seg.normals[face], axis=1) > 0.5] for x in (inner, face))  # a sliver has none
    if not len(inner):
        return sample
    points, point_normals = np.vstack([v[oriented], inner]), np.vstack([normals[oriented], seg.normals[face]])
    keep = even_subsample(points, 2 * n_points)
    return replace(sample, sides=(points[keep], point_normals[keep]))


def face_points(vertices: np.ndarray, faces: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Points on the faces with an edge longer than 2 `step`, off their corners: a barycentric grid
    of m = ceil(longest edge / step) parts a side, edges included (two faces share those).

    A coarse mesh's vertices stand too far apart for a fine partner's points to read their side of
    it on the nearest one's normal: its skin beside the seam reads as sunk.

    Returns
    -------
    points : (M, 3) float
    face : (M,) int, the face each lies on
    """
    tri = vertices[faces]
    longest = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(1)
    big = np.flatnonzero(longest > 2 * step)
    parts = np.ceil(longest[big] / step).astype(np.int64)
    points, face = [np.zeros((0, 3))], [np.zeros(0, np.int64)]
    for m in np.unique(parts):
        i, j = np.meshgrid(np.arange(m + 1), np.arange(m + 1), indexing="ij")
        bary = np.c_[i.ravel(), j.ravel(), m - i.ravel() - j.ravel()] / m
        bary = bary[(bary[:, 2] >= 0) & ((bary > 0).sum(1) >= 2)]  # corners are the vertices
        these = big[parts == m]
        points.append(np.einsum("kc,fcd->fkd", bary, tri[these]).reshape(-1, 3))
        face.append(np.repeat(these, len(bary)))
    return np.vstack(points), np.concatenate(face)


def outline_points(vertices: np.ndarray, faces: np.ndarray, seg, radius: float, spread: float,
                   n_points: int) -> np.ndarray:
    """(K, 3) centres of the faces where the surface turns within `radius` (at most n_points,
    spread evenly): the middle eigenvalue of the area-weighted tensor of the face normals within
    about `radius` (in edge steps) is above `spread` (two planes meeting at an angle t give
    sin^2(t / 2), so 0.12 is about 41 degrees). Unlike the edges sharper than the crease angle,
    this finds a crease that a rescan rounded over several faces (`verify.rim_agreement` on these
    points weighs a fit by its outline where noise hides the sharp edges)."""
    v, f = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
    edges = seg.topology.edge_vertices
    if len(f) == 0 or len(edges) == 0 or radius <= 0:
        return np.zeros((0, 3))
    step = float(np.median(np.linalg.norm(v[edges[:, 0]] - v[edges[:, 1]], axis=1)))
    rings = int(np.clip(np.ceil(radius / max(step, 1e-300)), 1, 12))
    n = seg.normals
    tensor = ring_average((n[:, :, None] * n[:, None, :]).reshape(-1, 9), seg.areas, seg.topology.edge_faces, rings)
    middle = np.linalg.eigvalsh(tensor.reshape(-1, 3, 3))[:, 1]
    centres = v[f[middle > spread]].mean(axis=1)
    return centres[even_subsample(centres, n_points)] if len(centres) else np.zeros((0, 3))


def crease_points(vertices: np.ndarray, edges: np.ndarray, step: float, n_points: int) -> np.ndarray:
    """(K, 3) points along (E, 2) vertex-index edges of (V, 3) vertices, about `step` apart along
    each edge and at most `n_points`, spread evenly (`even_subsample`)."""
    if len(edges) == 0 or step <= 0:
        return np.zeros((0, 3))
    p, q = vertices[edges[:, 0]], vertices[edges[:, 1]]
    parts = np.maximum(1, np.ceil(np.linalg.norm(q - p, axis=1) / step).astype(np.int64))
    edge = np.repeat(np.arange(len(edges)), parts)
    t = (np.arange(len(edge)) - np.repeat(np.cumsum(parts) - parts, parts) + 0.5) / np.repeat(parts, parts)
    points = p[edge] + t[:, None] * (q[edge] - p[edge])
    return points[even_subsample(points, n_points)]


def thinned_cloud(fragment, points: int):
    """A cloud scanned with normals and of more than `points` points (0: no limit) as that many
    spread evenly over it (`even_subsample`), with their normals: what it is matched on. The local
    fits that read a cloud (fracture likelihood, the skin's quadrics) span a fixed number of
    neighbours, so they read a dense scan at a finer scale than they were made for; thinned, a
    dense scan reads as a sparse one (docs/benchmarks.md, "Dense clouds with normals matched on
    their points, thinned"). A cloud without normals is kept whole: thinned, thin boards' clouds of
    12,000 points were accepted at a wrong pose more often (2 of 6 against 1)."""
    given = getattr(fragment, "normals", None)
    keep = even_subsample(fragment.vertices, points) if points and given is not None else None
    if keep is None or len(keep) == len(fragment.vertices):
        return fragment
    return replace(fragment, vertices=fragment.vertices[keep], normals=given[keep])


def _prepare_cloud(fragment, params: Params, scale: float) -> Prepared:
    """A fragment given as points (a `pointcloud.CloudFragment`, or any Fragment without faces),
    sampled by `cloudmatch.cloud_sample`; no contours or patches (no surface to cut), so
    matching runs on point-pair votes and ICP alone."""
    t0 = time.perf_counter()
    fragment = thinned_cloud(fragment, params.cloud_points)
    given = getattr(fragment, "normals", None)
    sample = cloud_sample(fragment.vertices, given, params, scale)
    if given is not None:  # read as a solid's (`revolution.firm`): a thin board's normals hold loose axes
        sample = replace(sample, axis=skin_axis(fragment.vertices, given, np.ones(len(given)), thin=False))
    strict = cloud_sample(fragment.vertices, given, params, scale, STRICT_SPREADS)
    regions = [(s, Patch(0, centre, normal, 1.0), rough) for s, (centre, normal), rough in
               region_samples(fragment.vertices, given, params, scale)]
    planes = plane_samples(fragment.vertices, given, params, scale)
    no_faces = np.zeros(0, np.int64)
    return Prepared(fragment, scale, no_faces, np.zeros(0, bool), [], sample, [],
                    {"cloud": time.perf_counter() - t0}, strict, regions, planes=planes)


@dataclass(frozen=True)
class Patch:
    """A fracture patch: its area-weighted centre and mean outward normal."""
    region: int
    centre: np.ndarray
    normal: np.ndarray
    area: float


def fracture_patches(fragment: Fragment, seg, prob: np.ndarray | None = None) -> list[Patch]:
    """The fracture facets (regions between creases, before neighbouring fracture regions are
    joined): one per cut a fragment met, each a candidate contact with one neighbour. Faces count
    by area times fracture likelihood prob (F,) (default: the segmentation's hard labels)."""
    prob = seg.fracture_faces.astype(np.float64) if prob is None else prob
    centres = fragment.vertices[fragment.faces].mean(axis=1)
    weight = seg.areas * prob
    out = []
    for r in np.unique(seg.face_facet[weight > 0]):
        m = (seg.face_facet == r) & (weight > 0)
        w = weight[m]
        n = (seg.normals[m] * w[:, None]).sum(0)
        if w.sum() <= 0 or np.linalg.norm(n) == 0:
            continue
        out.append(Patch(int(r), (centres[m] * w[:, None]).sum(0) / w.sum(), n / np.linalg.norm(n), float(w.sum())))
    return sorted(out, key=lambda p: -p.area)


def _ppf_index(sample: SurfaceSample, n: int) -> np.ndarray:
    """Indices of up to n fracture points spread over the sample."""
    return np.linspace(0, len(sample.fracture) - 1, min(n, len(sample.fracture))).astype(np.int64)


def ppf_points(sample: SurfaceSample, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Up to n fracture points spread over the sample, with their plane-fit normals: (n,3) each."""
    idx = _ppf_index(sample, n)
    normals = sample.fracture_plane_normals if sample.fracture_plane_normals is not None else sample.fracture_normals
    return sample.fracture[idx], normals[idx]


def ppf_weights(sample: SurfaceSample, n: int) -> np.ndarray:
    """(n,) weights of `ppf_points`' points: fracture likelihoods over the largest (only ratios count)."""
    w = sample.weights()[_ppf_index(sample, n)]
    return w / (w.max() if len(w) else 1.0)


_PPF_TABLES: dict = {}  # (points digest, settings) -> table: a fragment meets many partners


def _ppf_table(sample: SurfaceSample, params: Params, scale: float, role: str) -> PairTable:
    """The point-pair table of a fragment's fracture sample, as model (a) or as scene (b: normals
    flipped, every third point a reference), built once per fragment and kept for a few. Keyed by
    content, not identity: an engine's worker gets a fresh copy of a fragment with every job."""
    points, normals = ppf_points(sample, params.ppf_points)
    weights = ppf_weights(sample, params.ppf_points)
    key = (hashlib.blake2b(points.tobytes() + normals.tobytes() + weights.tobytes(), digest_size=16).digest(),
           role, params.ppf_points, params.ppf_distance_step * scale, params.ppf_angle_step_deg,
           params.ppf_max_distance * scale)
    table = _PPF_TABLES.pop(key, None)  # re-inserted last: the least recently used goes first
    if table is None:
        step = params.ppf_distance_step * scale
        reach = params.ppf_max_distance * scale if params.ppf_max_distance > 0 else None
        if role == "model":
            table = pair_table(points, normals, step, params.ppf_angle_step_deg, max_distance=reach, weights=weights)
        else:
            table = pair_table(points, -normals, step, params.ppf_angle_step_deg, reference_stride=3, sort=False,
                               max_distance=reach, weights=weights)
        while len(_PPF_TABLES) >= 12:
            _PPF_TABLES.pop(next(iter(_PPF_TABLES)))
    _PPF_TABLES[key] = table
    return table
