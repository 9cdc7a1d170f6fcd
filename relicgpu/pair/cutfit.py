"""Two clouds matched on a flat or curved cut: the fits of `planar.polished_fits` verified, and the one taken where
its rims and face decide, or where they hold several alike, its skin across the seam."""
from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from .cloudmatch import (MIN_FACING, PLANE_RIVAL_DEG, PLANE_RIVAL_SLIDE, PLANE_RIVALS, REGION_OVERLAP,
                         REGION_RESIDUAL, RESIDUAL_SPACINGS, SKIN_RIVAL_DEG, SKIN_RIVALS, SKIN_RIVALS_ESTIMATED,
                         point_spacing, verify_clouds)
from .icp import axis_rotation
from ..params import Params
from .planar import RIM_HIT, apart, is_thin, polished_fits
from .prepare import Prepared
from .result import PairMatch
from . import seam
from .verify import index_cache

PLANE_RESIDUAL_FLOOR = 1e-5  # of the scale: a flat cut scanned without noise has no roughness to bound by
# A plane fit's turn in its plane is read off the rims, which a sparse cloud draws coarsely (voronoi-clean
# clouds: fits 2-4 degrees off, all of it in that turn, where the skin beside the seam continues the
# partner's 0.5-0.8 at the truth against 0.46-0.64). The fit is turned about a's cut normal by every
# SKIN_TURN_STEP degrees up to SKIN_TURN_DEG either way, and set at the mean of the turns whose skin
# continues within SKIN_TURN_WITHIN of the most (the share counts points: its peak is flat and noisy).
# The rims leave the slide in the plane loose too (fits 0.1-0.5 degrees but 1.1-2.8% of the size
# off): SKIN_SLIDE_ROUNDS times, the fit is slid along each of the plane's axes every SKIN_SLIDE_STEP
# up to SKIN_SLIDE (shares of the scale) either way and turned again up to SKIN_FINE_DEG, each move
# set so. Voronoi clouds, 192 pairs: 127 / 20 right / wrong -> 130 / 16 (docs/benchmarks.md).
SKIN_TURN_DEG = 6.0
SKIN_TURN_STEP = 0.5
SKIN_TURN_WITHIN = 0.05
SKIN_SLIDE = 0.03
SKIN_SLIDE_STEP = 0.0025
SKIN_SLIDE_ROUNDS = 2
SKIN_FINE_DEG = 2.0


def match_planes(pa: Prepared, pb: Prepared, params: Params, be, scale: float, timings: dict) -> PairMatch | None:
    """Two clouds matched on a flat or curved cut (`planar`): the best of `planar.polished_fits`, where it scores at
    least `Params.min_plane`, no fit turned more than PLANE_RIVAL_DEG from it or shifted more than PLANE_RIVAL_SLIDE
    scores PLANE_RIVALS of it, and it verifies (touching as a region fit does, facing as any cloud fit), each fit
    turned in its plane to where its skin across the seam continues most first (`turned_to_skin`). A best fit
    that verifies but has such a rival is a symmetric cut, or one of a few copies of the right fit slid or turned a
    little: of the fits scoring PLANE_RIVALS of it, the one whose skin continues the partner's most is taken as
    `pipeline._by_skin` takes a region fit (`_plane_by_skin`); else refused as ambiguous. None where no fit decides (the
    crease regions are tried)."""
    if params.min_plane is None or not (pa.planes and pb.planes):
        return None
    t0 = time.perf_counter()
    spacing = max(point_spacing(np.asarray(p.fragment.vertices, np.float64)) for p in (pa, pb))
    contact = params.contact_distance * scale
    fits = polished_fits(pa.planes, pb.planes, spacing, contact, scale, index_cache(be))
    timings = {**timings, "planes": time.perf_counter() - t0}
    if not fits or fits[0][0] < params.min_plane:
        return None
    score, transform, (ia, ib) = fits[0]
    centre = pb.planes[ib][0].frame[:3, 3]
    rival = max([s for s, t, _ in fits[1:] if apart(t, transform, PLANE_RIVAL_DEG, PLANE_RIVAL_SLIDE * scale, centre)],
                default=0.0)
    fit = _plane_fit(pa, pb, fits[0], params, be, scale, spacing, timings, f"{rival:.2f} at another pose")
    if fit is None or rival < PLANE_RIVALS * score:
        return fit
    cut = _cut_name(pa.planes[ia][0], pb.planes[ib][0])
    chosen = _plane_by_skin(pa, pb, [f for f in fits if f[0] >= PLANE_RIVALS * score], fit, params, be, scale,
                            spacing, timings)
    return chosen or replace(fit, accepted=False, score=0.0, reason=f"ambiguous: {cut} held {score:.2f} by the "
                             f"partner's and {rival:.2f} at another pose")


def _plane_fit(pa: Prepared, pb: Prepared, fit: tuple, params: Params, be, scale: float, spacing: float,
               timings: dict, rivals: str) -> PairMatch | None:
    """A plane fit (score, transform, (ia, ib)) of `planar.polished_fits` verified; None where it fails."""
    score, transform, (ia, ib) = fit
    (plane_a, sa, rough_a), (plane_b, sb, rough_b) = pa.planes[ia], pb.planes[ib]
    contact = params.contact_distance * scale
    transform = turned_to_skin(plane_a, sa, sb, transform, contact, scale)
    # the planes lie face to face and each piece behind its own: beside the cut the skin touches across
    # the seam side by side (facing 0.69-0.79 at voronoi-clean clouds' true poses, where region fits
    # need REGION_FACING), so only the clouds' own facing bar; a thin cut's fit touches mostly along
    # the seam, where the cut face meets the partner's skin edge-on (facing 0.35-0.7 at a bookshelf's
    # true pose), and its face is a few points wide (two samplings lie up to RIM_HIT spacings apart,
    # and its roughness, over strips a point or two wide, tells nothing of theirs)
    thin = is_thin(plane_a, spacing) and is_thin(plane_b, spacing)
    bound = max(REGION_RESIDUAL * np.hypot(rough_a, rough_b), PLANE_RESIDUAL_FLOOR * scale,
                RESIDUAL_SPACINGS * spacing if thin else 0.0)
    ver = verify_clouds(sa, sb, transform, be, max(contact, RIM_HIT * spacing) if thin else contact, bound,
                        REGION_OVERLAP, params.penetration_depth * scale, index_cache(be),
                        min_facing=0.0 if thin else MIN_FACING)
    if not ver.accepted:
        return None
    return PairMatch(transform, True, ver.overlap * (1.0 - ver.penetration), ver.rmse, ver.overlap, ver.penetration,
                     np.zeros((0, 2), np.int64), -1, -1, _accepted(plane_a, plane_b, score, rivals), timings)


def _accepted(plane_a, plane_b, score: float, rivals: str) -> str:
    return f"accepted ({_cut_name(plane_a, plane_b)}: its rim and face held {score:.2f} by the partner's, {rivals})"


def _cut_name(plane_a, plane_b) -> str:
    return "a flat cut" if plane_a.bend is None and plane_b.bend is None else "a curved cut"


def _plane_by_skin(pa: Prepared, pb: Prepared, tied: list, first: PairMatch, params: Params, be, scale: float,
                   spacing: float, timings: dict) -> PairMatch | None:
    """Of plane fits held alike by their rims and faces (`tied`, best first; `first`: the best one as `_plane_fit`
    made it), the one whose skin continues the partner's most across the seam (`seam.skin_continuation`), where it
    continues by at least `Params.min_skin`, every fit turned over SKIN_RIVAL_DEG from it continues less than
    SKIN_RIVALS (SKIN_RIVALS_ESTIMATED without scanned normals) times as much, and it verifies; None otherwise."""
    if params.min_skin is None:
        return None
    contact = params.contact_distance * scale
    skins = [seam.skin_continuation(pa.planes[ia][1], pb.planes[ib][1], t, contact, scale) for _, t, (ia, ib) in tied]
    scanned = all(getattr(p.fragment, "normals", None) is not None for p in (pa, pb))
    won = seam.skin_winner(skins, [t for _, t, _ in tied], params.min_skin,
                           SKIN_RIVALS if scanned else SKIN_RIVALS_ESTIMATED, SKIN_RIVAL_DEG)
    if won is None:
        return None
    best, rival = won
    alike = max(s for k, (s, *_) in enumerate(tied) if k != best)
    rivals = (f"{alike:.2f} at another pose; its skin continues the partner's {skins[best]:.2f} across the seam, "
              f"{rival:.2f} at another turn")
    if best == 0:  # the best fit, moved and verified already
        score, _, (ia, ib) = tied[0]
        return replace(first, reason=_accepted(pa.planes[ia][0], pb.planes[ib][0], score, rivals))
    return _plane_fit(pa, pb, tied[best], params, be, scale, spacing, timings, rivals)


def turned_to_skin(plane_a, sa, sb, transform: np.ndarray, contact: float, scale: float) -> np.ndarray:
    """The (4, 4) fit carrying b onto a moved in a's cut plane to where the skin beside the seam (SurfaceSamples sa,
    sb) continues the partner's most (`seam.skin_continuation`): turned about a's cut normal through the centre of
    a's cut face (SKIN_TURN_DEG, SKIN_TURN_STEP), then SKIN_SLIDE_ROUNDS times slid along each of the plane's axes
    (SKIN_SLIDE, SKIN_SLIDE_STEP) and turned again (SKIN_FINE_DEG), each move set at the mean of the moves whose skin
    continues within SKIN_TURN_WITHIN of the most; the fit as it is where no skin lies near the seam."""
    axis, centre = plane_a.frame[:3, 2], plane_a.face_points.mean(axis=0)

    def moved(fit: np.ndarray, degrees: float = 0.0, slide: np.ndarray = np.zeros(3)) -> np.ndarray:
        move = np.eye(4)
        move[:3, :3] = axis_rotation(axis, np.radians(degrees))
        move[:3, 3] = centre - move[:3, :3] @ centre + slide
        return move @ fit

    def best(fit: np.ndarray, steps: np.ndarray, move) -> np.ndarray:
        skins = np.array([seam.skin_continuation(sa, sb, move(fit, x), contact, scale) for x in steps])
        return fit if skins.max() <= 0.0 else move(fit, float(steps[skins >= skins.max() - SKIN_TURN_WITHIN].mean()))

    def turns(limit: float) -> np.ndarray:
        return np.arange(-limit, limit + 1e-9, SKIN_TURN_STEP)

    transform = best(transform, turns(SKIN_TURN_DEG), moved)
    slides = np.arange(-SKIN_SLIDE, SKIN_SLIDE + 1e-9, SKIN_SLIDE_STEP) * scale
    for _ in range(SKIN_SLIDE_ROUNDS if SKIN_SLIDE > 0 else 0):
        for direction in plane_a.frame[:3, :2].T:
            transform = best(transform, slides, lambda fit, x: moved(fit, 0.0, x * direction))
        transform = best(transform, turns(SKIN_FINE_DEG), moved)
    return transform
