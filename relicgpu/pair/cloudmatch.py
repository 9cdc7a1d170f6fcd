"""Point-cloud fragments (no faces) prepared for matching on their points (issue 15 item 2).

A sparse scan (a few thousand points a piece) of a thin board or an open surface does not close
into a solid, so it has no mesh to segment. Its fracture points are picked by the roughness of
the normals around each point (`points.fracture_likelihood`), and the rest of the pipeline
(point-pair votes, ICP, verification) runs on them as on a mesh's fracture sample.

A clean break (a smooth or flat cut, as ceramics and Voronoi cell fracture make) is not rough,
so roughness does not find it; but it is bounded by a crease. Where the roughness picks find no
fit, a flat cut is tried (`planar`, `plane_samples`), then each smooth region between creases
(`crease_regions`) as the fracture in turn, and the fit whose two regions touch over the largest
share is kept (`REGION_OVERLAP`, `REGION_FACING`).
"""
from __future__ import annotations

import itertools

import numpy as np

from .icp import apply
from ..io.fragment import is_cloud
from ..params import Params
from ..cloud.points import estimate_normals, even_subsample, fracture_likelihood, local_pca
from . import seam
from .planar import RIM_HIT, CutPlane, cut_planes
from .ppf import smoothed_normals
from .verify import SurfaceSample, Verification, verify

# Roughness is read off plane fits over this many nearest points where the scan has no normals:
# fewer than the oriented normals use (CLOUD_NORMAL_NEIGHBOURS), so that a fit does not smooth a
# rough break into a plane (orientation does not matter to roughness).
ROUGHNESS_NEIGHBOURS = 6
# A second, strict pick of the fracture (the split this many robust spreads above the median
# roughness, not ROUGH_SPREADS) is tried when the first finds no fit: a thin wall's narrow break
# drowns in the skin points the first pick holds.
STRICT_SPREADS = 2.0
# ... and a third, wide pick (the split this many robust spreads above the median) when neither
# finds a fit: a large break (a third of a piece's points) lifts the median roughness, and the
# first pick held 35% of torso seed 2's second piece's break (70% at 0.5 spreads, 91% at 0).
# Fitted on synthetic pairs 0-9 without normals: torso seed 2 rejected (no start near the
# truth) -> right at 0.5 and at 0 spreads; no other pair changes (they are accepted before).
WIDE_SPREADS = 0.5
# Tried and dropped (issue 15): weighing each fracture point of a cloud without normals by its
# likelihood squared in the final polish. On synthetic pairs 0-9 it brought slab seed 0 from 2.77 to
# 0.58 degrees (8/10 -> 9/10 right), but on the held-out pairs 10-23 it put slabs 2.3-2.9 degrees
# off (12/14 right, 1 wrong -> 10/14, 3 wrong): over all 24 pairs 20 right, 2 wrong without it,
# 19 right, 3 wrong with it (docs/benchmarks.md, "Sparse clouds without normals").


# Crease-bounded regions of a cloud: neighbours (CREASE_NEIGHBOURS nearest, nearer than
# CREASE_REACH point spacings: not across a thin wall) join where their normals turn less than
# CREASE_DEG; without scanned normals the estimated ones round a crease off, so points whose
# neighbourhood strays from a plane more than CREASE_VARIATION times the cloud's median (the
# noise floor of its own smooth surface) are left out as crease points instead.
CREASE_NEIGHBOURS = 8
CREASE_REACH = 4.0
CREASE_DEG = 20.0
CREASE_VARIATION = 6.0
# Regions of at least this share of the points are tried as fracture, at most REGIONS of them
# (largest first) a fragment.
MIN_REGION_SHARE = 0.03
REGIONS = 3
# A fit between two regions is accepted when it passes `verify` with both regions touching over
# at least REGION_OVERLAP of their points, REGION_FACING of the touching surfaces facing each
# other, and a residual of at most REGION_RESIDUAL times the two regions' roughness combined
# (`roughness`, root of the summed squares: two samplings of one surface differ by their noise;
# two skin patches laid on each other by their shapes too). Fitted on the corpus's clean
# rough/smooth/voronoi/vessel pairs of seeds 0-5 with normals: right region fits 0.50-0.63
# overlap, facing 0.77-0.95, residual 0.72-1.37 roughnesses; skin on skin (nested vessel walls,
# patches of a pebble) overlap 0.13-0.60, facing 0.50-0.99, residual 1.39-3.17 (1.74 and up at
# overlaps over 0.41).
REGION_OVERLAP = 0.4
REGION_FACING = 0.85
REGION_RESIDUAL = 1.6
REGION_TURNS = 36  # turns about the common normal tried for two regions put face to face
# Two accepted region fits at different poses whose overlaps are within this ratio make the
# pair ambiguous (a near-symmetric flat break: the outline of an ellipse fits at two turns).
AMBIGUOUS_SHARE = 0.9
# ... but the skin beside a break's seam runs on into the partner's at one turn only: of the
# SKIN_FITS widest-touching fits of two curved regions, the one whose skin continues most (at least
# Params.min_skin) wins where every fit turned more than SKIN_RIVAL_DEG from it continues less
# than SKIN_RIVALS times as much (`pipeline._by_skin`).
SKIN_FITS = 8
SKIN_RIVAL_DEG = 15.0
SKIN_RIVALS = 0.6
# Normals estimated from the points see less of the skin beside a seam: there a rival turn must
# continue less than this share (corpus clouds without normals, smooth and voronoi pairs 0-287:
# at 0.6 the rule gave 10 more right and 5 more wrong, at 0.3 10 more right and none wrong;
# docs/benchmarks.md).
SKIN_RIVALS_ESTIMATED = 0.3
# A smooth curved cut's crease region often holds skin beyond a shallow rim, so its right fit
# touches over less of it than REGION_OVERLAP and faces less than REGION_FACING. Where no fit
# passing those bars wins on its skin, fits touching over LOOSE_OVERLAP and facing LOOSE_FACING
# may, by the same skin rule (never by their overlap). Set by replaying the recorded region fits
# of the corpus's clean clouds, seeds 0-35 (docs/benchmarks.md); end to end there 96 -> 99 right
# with normals and 56 -> 61 without, on seeds 36-71 94 -> 100 and 55 -> 59, none more wrong.
LOOSE_OVERLAP = 0.1
LOOSE_FACING = 0.6
# ... and only between regions that curve (`curvedness` at least LOOSE_CURVED): two flat regions
# hold a fit in neither its slide nor its turn in their plane, which the skin alone then settles
# a few degrees off (voronoi cuts, 0.002-0.004; the smooth cuts' regions 0.04-0.16; flat cuts are
# `planar`'s to match). Nor is a fit taken on its regions' touch alone where one is flat
# (`pipeline._match_regions`): all eight such fits of the Blender cube's shards, the thin objects
# and the corpus's clouds (with normals and without) were wrong.
LOOSE_CURVED = 0.02
# A fit found on the roughness picks is refused where, of at least PICK_SKIN_NEAR free skin
# points near the partner's, under MIN_PICK_SKIN continue its surface (`seam.skin_points`): such
# a fit lays a face on a face with the rims apart. Set on the corpus's clean clouds without
# normals (docs/benchmarks.md): wrong fits 37-172 degrees off 0.01-0.08 (7 of 8 under 0.05), right
# fits 0.12-0.87; held out, the corpus with normals (right 0.28 and up) and relicgpu.synth's
# clouds (right 0.11 and up).
MIN_PICK_SKIN = 0.05
PICK_SKIN_NEAR = 20
# Flat cuts (`planar`, `cutfit.match_planes`): the best polished fit of the candidate cut
# planes is taken where no fit turned PLANE_RIVAL_DEG from it, or moving b's plane PLANE_RIVAL_SLIDE
# (a share of the scale) from where it puts it, scores PLANE_RIVALS of it. Set on the corpus's
# voronoi-clean clouds with normals, seeds 0-35 (docs/benchmarks.md): right fits' best rivals
# 0.10-0.95 of them, the two wrong best fits' 0.98 and 0.99.
PLANE_RIVAL_DEG = 5.0
PLANE_RIVAL_SLIDE = 0.05
PLANE_RIVALS = 0.95


def crease_regions(points: np.ndarray, normals: np.ndarray, given: bool) -> list[np.ndarray]:
    """Smooth regions between the creases of a cloud, largest first, each at least
    MIN_REGION_SHARE of the points: a list of index arrays into the (N, 3) points, whose
    (N, 3) outward unit normals are scanned (`given`) or estimated."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    n = len(points)
    k = min(CREASE_NEIGHBOURS, n - 1)
    if k < 1:
        return []
    d, nb = cKDTree(points).query(points, k=k + 1)
    keep = np.ones(n, bool)
    if not given:
        values = local_pca(points, CREASE_NEIGHBOURS)[0]
        variation = values[:, 0] / np.maximum(values.sum(1), 1e-300)
        keep = variation < CREASE_VARIATION * max(float(np.median(variation)), 1e-12)
    i, j = np.repeat(np.arange(n), k), nb[:, 1:].ravel()
    near = d[:, 1:].ravel() < CREASE_REACH * float(np.median(d[:, 1]))
    smooth = np.einsum("ij,ij->i", normals[i], normals[j]) > np.cos(np.radians(CREASE_DEG))
    link = keep[i] & keep[j] & near & smooth
    _, label = connected_components(coo_matrix((np.ones(link.sum()), (i[link], j[link])), shape=(n, n)),
                                    directed=False)
    sizes = np.bincount(label)
    return [np.flatnonzero(label == r) for r in np.argsort(-sizes, kind="stable")
            if sizes[r] >= MIN_REGION_SHARE * n]


def curvedness(points: np.ndarray) -> float:
    """How far (N, 3) points stray from their plane: the spread across it over the spread along
    its longest direction (0 for a flat patch)."""
    if len(points) < 3:
        return 0.0
    spread = np.linalg.eigvalsh(np.cov(points.T))
    return float(np.sqrt(max(spread[0], 0.0) / max(spread[2], 1e-300)))


def roughness(points: np.ndarray) -> float:
    """How far (N, 3) points stray from a plane at the scale contact is measured at: the median
    RMS distance of each point's ROUGHNESS_FIT nearest points from their plane fit, and at least
    ROUGHNESS_FLOOR of their spacing."""
    if len(points) < ROUGHNESS_FIT:
        return 0.0
    measured = float(np.sqrt(np.median(np.maximum(local_pca(points, ROUGHNESS_FIT)[0][:, 0], 0.0))))
    return max(measured, ROUGHNESS_FLOOR * point_spacing(points))


def _region_sample(points: np.ndarray, normals: np.ndarray, region: np.ndarray, surf: np.ndarray, params: Params,
                   scale: float) -> tuple[SurfaceSample, float] | None:
    """A SurfaceSample taking the (N, 3) points' `region` (indices) as its fracture and `surf` as
    its surface, and the region's `roughness` (None where its normals cancel)."""
    idx = region[even_subsample(points[region], params.icp_points)]
    if np.linalg.norm(normals[region].mean(0)) == 0:
        return None
    plane_normals = smoothed_normals(points[idx], normals[idx], params.ppf_normal_radius * scale)
    return (SurfaceSample(points[idx], np.zeros(len(idx), np.int64), normals[idx], points[surf], normals[surf],
                          plane_normals), roughness(points[idx]))


def region_samples(points: np.ndarray, given_normals: np.ndarray | None, params: Params,
                   scale: float) -> list[tuple[SurfaceSample, tuple[np.ndarray, np.ndarray], float]]:
    """Up to REGIONS samples of a cloud's (N, 3) points, each taking one `crease_regions` region
    as its fracture (`cloud_sample`'s surface), with the region's centre and mean normal (a
    patch: starts put two of them face to face) and its `roughness`."""
    points = np.asarray(points, np.float64)
    normals = estimate_normals(points, given_normals)
    surf = even_subsample(points, 2 * params.icp_points)
    out = []
    for region in crease_regions(points, normals, given_normals is not None)[:REGIONS]:
        made = _region_sample(points, normals, region, surf, params, scale)
        if made is not None:
            mean = normals[region].mean(0)
            out.append((made[0], (points[region].mean(0), mean / np.linalg.norm(mean)), made[1]))
    return out


def plane_samples(points: np.ndarray, given_normals: np.ndarray | None, params: Params,
                  scale: float) -> list[tuple[CutPlane, SurfaceSample, float]]:
    """The planes that could be a flat cut of a cloud's (N, 3) points (`planar.cut_planes`), each
    with a SurfaceSample taking its points as the fracture and the plane's points' `roughness`."""
    points = np.asarray(points, np.float64)
    normals = estimate_normals(points, given_normals)
    surf = even_subsample(points, 2 * params.icp_points)
    out = []
    for plane in cut_planes(points, normals, point_spacing(points), given_normals is None):
        made = _region_sample(points, normals, plane.indices, surf, params, scale)
        if made is not None:
            out.append((plane, *made))
    return out


def cloud_likelihood(points: np.ndarray, given_normals: np.ndarray | None, spreads: float | None = None,
                     majority: bool = False) -> np.ndarray:
    """(N,) fracture likelihood of a cloud's (N, 3) points, from the scan's own (N, 3) normals
    where it has them, else from the normals of small local plane fits (spreads, majority: as for
    `points.fracture_likelihood`)."""
    rough_normals = given_normals if given_normals is not None else local_pca(points, ROUGHNESS_NEIGHBOURS)[1][:, :, 0]
    return fracture_likelihood(points, rough_normals, spreads=spreads, majority=majority)


def fracture_points(points: np.ndarray, given_normals: np.ndarray | None, params: Params,
                    spreads: float | None = None, likelihood: np.ndarray | None = None,
                    majority: bool = False) -> np.ndarray:
    """Indices of a cloud's fracture points: those of fracture likelihood >= 0.5 (`cloud_likelihood`
    of the (N, 3) points and optional (N, 3) normals, unless given), at most params.icp_points
    spread evenly."""
    if likelihood is None:
        likelihood = cloud_likelihood(points, given_normals, spreads, majority)
    fracture = np.flatnonzero(likelihood >= 0.5)
    return fracture[even_subsample(points[fracture], params.icp_points)]


def cloud_sample(points: np.ndarray, given_normals: np.ndarray | None, params: Params,
                 scale: float, spreads: float | None = None, majority: bool = False) -> SurfaceSample:
    """The sample a cloud is matched on.

    Parameters
    ----------
    points : (N, 3) array
    given_normals : (N, 3) outward unit normals of the scan, or None (estimated and oriented)
    params : Params (icp_points, ppf_normal_radius)
    scale : the length relative parameters are fractions of
    spreads : how strictly fracture is picked (`points.fracture_likelihood`; None: its default)
    majority : pick the rough class where it is most of the piece (`points.fracture_likelihood`;
        no fracture points where it is not)

    Returns
    -------
    SurfaceSample whose fracture points are `fracture_points`, and whose surface is up to
    2 * icp_points of all.
    """
    points = np.asarray(points, np.float64)
    normals = estimate_normals(points, given_normals)
    fracture = fracture_points(points, given_normals, params, spreads, majority=majority)
    surf = even_subsample(points, 2 * params.icp_points)
    plane_normals = smoothed_normals(points[fracture], normals[fracture], params.ppf_normal_radius * scale)
    return SurfaceSample(points[fracture], np.zeros(len(fracture), np.int64), normals[fracture], points[surf],
                         normals[surf], plane_normals)


def majority_samples(fragments, params: Params, scale: float) -> list[SurfaceSample] | None:
    """The samples two cloud fragments are matched on last: each piece's rough class where it is
    most of the piece (`cloud_sample(majority=True)`), its wide pick (WIDE_SPREADS) where its bulk
    reads smooth; None where neither reads mostly rough or one picks nothing."""
    def sample(f, **pick):
        return cloud_sample(f.vertices, getattr(f, "normals", None), params, scale, **pick)

    found = [sample(f, majority=True) for f in fragments]
    if not any(len(s.fracture) for s in found):
        return None
    found = [s if len(s.fracture) else sample(f, spreads=WIDE_SPREADS) for s, f in zip(found, fragments)]
    return found if all(len(s.fracture) for s in found) else None


def cloud_skin(fragment, sample: SurfaceSample, below: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """The skin of a cloud fragment's surface sample: its (K, 3) points of fracture likelihood
    (`cloud_likelihood` over all the fragment's points) under `below`, and their (K, 3) normals."""
    from scipy.spatial import cKDTree

    points = np.asarray(fragment.vertices, np.float64)
    likelihood = cloud_likelihood(points, getattr(fragment, "normals", None))
    _, nearest = cKDTree(points).query(sample.surface)
    skin = likelihood[nearest] < below
    return sample.surface[skin], sample.normals[skin]


def fracture_roughness(points: np.ndarray, given_normals: np.ndarray | None, params: Params) -> float:
    """How far a cloud's fracture sample (`fracture_points`) strays from a plane at the scale the
    contact is measured at: the median RMS distance of each sample point's ROUGHNESS_FIT nearest
    sample points from their plane fit (noise and the break's own relief together)."""
    return roughness(np.asarray(points, np.float64)[fracture_points(points, given_normals, params)])


# Two samplings of a rough break, a point spacing apart, never share points: the residual to the
# other's tangent planes and the gap between touching points grow with the spacing. A sparse
# cloud's spacing (about 1% of its size at 2,500 points) is far coarser than a mesh's sample, so
# the verification's contact distance and residual limit are at least these many spacings.
CONTACT_SPACINGS = 1.0
RESIDUAL_SPACINGS = 0.4
# ... and at least this many times the two fracture samples' roughness combined
# (`fracture_roughness`, root of the summed squares), measured over ROUGHNESS_FIT points: the
# residual of right fits is 0.68-1.03 times it on 22 synthetic pairs without normals, the noise
# of a scan and the relief of its break raise both alike.
RESIDUAL_ROUGHNESS = 1.15
ROUGHNESS_FIT = 8
# A cloud sampled off an exact surface, without a scanner's noise, reads a flat or smooth break as
# roughness 0, and every residual bound read off it as 0: a right fit's residual is never 0 (two
# samplings, a fit a fraction of a degree off). No roughness reads under this share of the point
# spacing, under what noise of 0.05% of the size reads (the cut planes of a Voronoi corpus pair of
# 2,500 points a piece: 0.039-0.046 spacings). Without it, the corpus's clouds without normals and
# without noise were right 17 of 48 against 26 with noise (docs/benchmarks.md).
ROUGHNESS_FLOOR = 0.025
# Where two clouds' surfaces touch after a fit, at least this share of the touching points must
# face each other (`verify.facing_share`, normals oriented by visibility). Measured on 24
# synthetic pairs without normals and 24 with: right fits 0.51-0.92, gross wrong fits (60-160
# degrees off) that pass overlap and residual 0.17-0.44.
MIN_FACING = 0.475


def point_spacing(points: np.ndarray) -> float:
    """The median distance from each of the (N, 3) points to its nearest other point."""
    from scipy.spatial import cKDTree

    if len(points) < 2:
        return 0.0
    d, _ = cKDTree(points).query(points, k=2)
    return float(np.median(d[:, 1]))


def cloud_params(params: Params, fragments, scale: float) -> Params:
    """params with the verification's contact distance and residual limit raised to the point
    spacing of the pair's clouds, and the residual limit to their fracture roughness
    (fragments without faces; a pair of meshes keeps params)."""
    clouds = [f for f in fragments if is_cloud(f)]
    if not clouds:
        return params
    spacing = max(point_spacing(np.asarray(f.vertices, np.float64)) for f in clouds) / scale
    roughness = np.hypot(*[fracture_roughness(f.vertices, getattr(f, "normals", None), params) / scale
                           for f in (clouds * 2)[:2]])
    return params.with_(contact_distance=max(params.contact_distance, CONTACT_SPACINGS * spacing),
                        max_rmse=max(params.max_rmse, RESIDUAL_SPACINGS * spacing, RESIDUAL_ROUGHNESS * roughness))


# Interpenetration of two clouds: a point of one surface sample counts as inside the other when
# it lies deeper than the penetration depth behind the nearest surface point of the other, by
# that point's normal, within PENETRATION_REACH depths of it (verify's mesh check reaches 8:
# a sparse cloud's estimated normals are wrong on a thin wall's band and a crease's side, and
# 5-8 depths away such a normal put right fits' skin "inside": slab seed 2 and vase seed 3 at
# 0.068 and 0.079, above verify's 0.06). Outside the contact zone only, as verify's. At most
# MAX_PENETRATION of either sample may lie inside. Measured on synthetic pairs 0-9 (every fit
# of the main, strict and wide picks, and the true pose): right fits 0.000-0.007 without normals
# (0.006-0.079 at 8 depths), 0.000-0.005 with; of 102 wrong fits without normals 18 above 0.03
# and 11 above 0.06 (27 and 15 at 8 depths, where right fits reach 0.079).
PENETRATION_REACH = 3.0
MAX_PENETRATION = 0.03


def cloud_penetration(a: SurfaceSample, b: SurfaceSample, transform: np.ndarray, depth: float, contact: float,
                      index_of) -> float:
    """The larger share of either surface sample (b's moved by the (4, 4) `transform`), outside
    the contact zone (farther than 2 * contact from the other's fracture sample), lying deeper
    than `depth` behind the nearest surface point of the other and within PENETRATION_REACH
    depths of it (lengths absolute; index_of: nearest-neighbour index of a sample's points)."""
    def one_way(points, other):
        if len(points) == 0:
            return 0.0
        if len(other.fracture):
            _, d = index_of(other.fracture).query(points)
            points = points[np.asarray(d) > 2 * contact]
        if len(points) == 0:
            return 0.0
        idx, dist = index_of(other.surface).query(points)
        idx = np.asarray(idx, np.int64)
        signed = np.einsum("ij,ij->i", points - other.surface[idx], other.normals[idx])
        return float(np.sum((signed < -depth) & (np.asarray(dist) < PENETRATION_REACH * depth))) / len(points)

    return max(one_way(apply(transform, b.surface), a), one_way(apply(np.linalg.inv(transform), a.surface), b))


def verify_clouds(a: SurfaceSample, b: SurfaceSample, transform: np.ndarray, backend, contact: float,
                  max_rmse: float, min_overlap: float, depth: float, index_of=None,
                  min_facing: float = MIN_FACING) -> Verification:
    """`verify.verify` for a pair of clouds (mutual overlap, facing), its interpenetration
    measured by `cloud_penetration` (at most MAX_PENETRATION) instead (lengths absolute)."""
    if index_of is None:
        index_of = backend.nearest_index
    ver = verify(a, b, transform, backend, contact, max_rmse, min_overlap, depth, None, index_of, mutual=True,
                 min_facing=min_facing)
    penetration = cloud_penetration(a, b, transform, depth, contact, index_of)
    if not ver.accepted and not ver.reason.startswith("facing"):
        return Verification(ver.overlap, ver.rmse, penetration, False, ver.reason, ver.facing)
    if penetration > MAX_PENETRATION:
        return Verification(ver.overlap, ver.rmse, penetration, False,
                            f"interpenetration {penetration:.3f} above {MAX_PENETRATION:.3f}", ver.facing)
    return Verification(ver.overlap, ver.rmse, penetration, ver.accepted, ver.reason, ver.facing)


# A thin wall's break (a vessel's sherd, a pot's wall) picks as a band a spacing or two wide:
# its median point lies within THIN_PICK spacings of the skin (corpus vessel-clean clouds with
# normals, seeds 0-23: 1.1-3.0, 2.3 or less on both pieces in 20 of 24 pairs; rough, smooth and
# Voronoi cuts, seeds 0-11: 0.8-6.5, both under 2.3 in none). Two such bands touch over a strip,
# the cut meeting the partner's skin edge-on there, as a thin flat cut does (`cutfit.match_planes`):
# a fit of them is polished on the skin across the seam, verified without the facing check, with
# contact counted within RIM_HIT spacings, and kept where at least
# THIN_PICK_SKIN of the free skin points near the partner's continue it (vessel-clean seeds 3-22,
# polished: right fits 0.43-0.87, wrong ones that verify 0.00-0.18; unpolished the right ones
# drop to 0.08 where the fit is a few degrees off).
THIN_PICK = 2.3
THIN_PICK_SKIN = 0.3
# Each fit is polished with the skin's gate widened to a contact distance at first
# (`seam.seam_polish`'s wide_gate: a start 3.3 degrees off, a 5-piece vessel's sherd pair at its
# heap's scale, polishes to 1.1 degrees, where the usual gate leaves it 6.0 off), then, where that
# does not pass, as usual.
THIN_WIDE_GATE = 1.0
# A board's own narrow face (a shelf's front edge, a strip a spacing or two wide) picks as a band
# too, and two such strips laid on each other look like a thin cut; but a cut's normals vary over
# the seam and a board's face has one normal. A fit is not taken where, on both sides, at least
# ONE_FACE of the picked points in contact lie within ONE_FACE_DEG of one normal (bookshelves of
# boards 0.02 cut rough, given normals, seeds 0-11: the nine thin-wall fits accepted half a turn
# off 0.93-1.00 on both sides, the right thin-wall fits of all shelves 0.05-0.24).
ONE_FACE = 0.6
ONE_FACE_DEG = 2.0


def thin_pick(skin: np.ndarray, sample: SurfaceSample, spacing: float) -> bool:
    """Whether a cloud's fracture sample is a thin wall's band: its median point within THIN_PICK
    spacings (absolute) of the (K, 3) `skin` points (`cloud_skin`)."""
    from scipy.spatial import cKDTree

    if not (len(skin) and len(sample.fracture)):
        return False
    return bool(np.median(cKDTree(skin).query(sample.fracture)[0]) <= THIN_PICK * spacing)


def thin_wall_fit(skins, samples, fits, spacing: float, params: Params, scale: float, backend, index_of):
    """The first of `fits` ((4, 4) transforms carrying b onto a) of two thin walls' bands that,
    polished on the skin across the seam (`seam.seam_polish`), verifies as a thin cut and
    continues the partner's skin (THIN_PICK_SKIN): (transform, Verification, reason) or None.
    `skins`: each piece's `cloud_skin`; `samples`: their SurfaceSamples; `spacing`: absolute."""
    a, b = samples
    contact = params.contact_distance * scale
    for transform, wide in itertools.product(fits, (THIN_WIDE_GATE, 0.0)):
        polished, held = seam.seam_polish(a.fracture, a.fracture_normals, b.fracture, *skins, transform, contact,
                                          scale, index_of(a.fracture), wide)
        passed = thin_cut_check(a, b, polished, spacing, params, scale, backend, index_of)
        if passed is not None:
            ver, continues, near = passed
            return polished, ver, (f"accepted (thin walls' bands: {continues} of {near} skin points near the seam "
                                   f"continue the partner's once the skin across it held the fit, {held} points)")
    return None


def thin_cut_check(a: SurfaceSample, b: SurfaceSample, transform: np.ndarray, spacing: float, params: Params,
                   scale: float, backend, index_of) -> tuple[Verification, int, int] | None:
    """A fit of two thin walls' bands (b moved by the (4, 4) `transform`) checked as a thin cut: verified
    without the facing check, contact within RIM_HIT spacings (absolute `spacing`), its picks in contact
    not on one flat face on both sides (`one_face_seam`), and at least THIN_PICK_SKIN of the free skin
    points near the partner's continuing it: (Verification, continuing, near) or None."""
    contact = params.contact_distance * scale
    reach = max(contact, RIM_HIT * spacing)
    ver = verify_clouds(a, b, transform, backend, reach, params.max_rmse * scale, params.min_overlap,
                        params.penetration_depth * scale, index_of, min_facing=0.0)
    if not ver.accepted or one_face_seam(a, b, transform, reach, index_of):
        return None
    continues, near = seam.skin_points(a, b, transform, contact, scale)
    return (ver, continues, near) if near >= PICK_SKIN_NEAR and continues >= THIN_PICK_SKIN * near else None


def one_face_seam(a: SurfaceSample, b: SurfaceSample, transform: np.ndarray, contact: float, index_of) -> bool:
    """Whether the fracture points of a and of b (b moved by the (4, 4) `transform`) in contact
    (within `contact`) each lie mostly (ONE_FACE) within ONE_FACE_DEG of one normal: two flat faces
    of the objects laid on each other, not a break."""
    def one_face(normals: np.ndarray) -> bool:
        if len(normals) < 5:
            return False
        alike = np.abs(normals @ normals.T) > np.cos(np.radians(ONE_FACE_DEG))
        return bool(alike.sum(axis=1).max() >= ONE_FACE * len(normals))

    _, d_ba = index_of(a.fracture).query(apply(transform, b.fracture))
    _, d_ab = index_of(b.fracture).query(apply(np.linalg.inv(transform), a.fracture))
    return (one_face(a.fracture_normals[np.asarray(d_ab) < contact])
            and one_face(b.fracture_normals[np.asarray(d_ba) < contact]))
