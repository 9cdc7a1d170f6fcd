"""The pairwise pipeline: `prepare` one fragment (relicgpu.pair.prepare), `match_pair` two.

prepare: segment -> contours -> features -> fuse   (per fragment, cacheable)
match_pair: LCS coarse match per contour pair -> RANSAC poses -> ICP -> verify
"""
from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from ..backends import resolve
from .icp import (apply, batched_icp, distinct_poses, facing_poses, invert, ransac_poses, refine_point_to_plane,
                  same_fit, same_pose)
from ..io.fragment import is_cloud
from ..cloud.points import cloud_fragment
from ..cloud.wall_normals import wall_normals
from .lcs import circular_lcs
from ..params import Params, second_reading_params
from .cloudmatch import (AMBIGUOUS_SHARE, LOOSE_CURVED, LOOSE_FACING, LOOSE_OVERLAP, point_spacing, REGION_FACING,
                         REGION_OVERLAP, REGION_RESIDUAL, REGION_TURNS, SKIN_FITS, SKIN_RIVAL_DEG, SKIN_RIVALS,
                         SKIN_RIVALS_ESTIMATED, WIDE_SPREADS, cloud_params, cloud_sample, cloud_skin, curvedness,
                         majority_samples, thin_pick, thin_wall_fit, verify_clouds)
from .cutfit import match_planes
from .facets import facet_fits
from .prepare import Prepared, _ppf_table, _second_reading, prepare
from .ppf import vote_poses
from .result import PairMatch
from . import seam
from .fine import fine_stage
from .meshfit import BANDED, band_fit, skin_over_band, skin_pick, unseen_skin, verify_mesh
from .sheets import scanned_fit, sheet_fit
from .revolution import axes_meet, profiles_agree
from .skinhold import held_by_skin, on_axes, skin_continues
from .verify import index_cache, rim_agreement


def _main_patches(patches, params: Params):
    """The largest fracture patches of a fragment (those of a real share of its fracture area)."""
    if not patches:
        return []
    biggest = patches[0].area
    return [p for p in patches[: params.max_patches] if p.area >= params.min_patch_share * biggest]


def _as_prepared(x, params, backend, scale) -> Prepared:
    if isinstance(x, Prepared):
        if abs(x.scale - scale) <= 1e-9 * scale:
            return x
        x = x.fragment
    return prepare(x, params, backend, scale=scale)


# A fit found on the second segmentation only scores this share of its overlap: every pair tried
# twice is a second chance for a wrong fit to pass, so the assembly takes the first reading's
# matches first and weighs these less in its votes (corpus voronoi-clean, 5 pieces: 5 wrong fits
# of the second reading, scored alike with the right ones, split the object in two)
SECOND_READING_SCORE = 0.5
# a fit accepted on its outline with a residual over max_rmse, or on its rims facing too little
# (`meshfit.band_fit`), is less sure: the assembly weighs it this much
OUTLINE_SCORE = 0.5


def pair_scale(a, b, params: Params) -> float:
    if params.unit:
        return float(params.unit)
    fa = a.fragment if isinstance(a, Prepared) else a
    fb = b.fragment if isinstance(b, Prepared) else b
    return 0.5 * (fa.size + fb.size)


def match_pair(a, b, params: Params | None = None, backend="auto", heads=None, scale: float | None = None) -> PairMatch:
    """Find the rigid transform carrying fragment b onto fragment a, or say there is none.

    a, b: Fragments or Prepared (prepared at the pair's scale, else prepared again).
    heads: optional (contour_a, point_a, contour_b, point_b), the head nodes picked by hand.

    Meshes are matched again on `Params.second_segmentation`'s reading (`Prepared.second`, or
    prepared here) where no fit passes, where the fit's rims disagree (`verify.rim_agreement`), or
    where it passed only in the band (`meshfit.band_fit`, `Params.second_when_banded`): its fit is
    taken where the first found none or its rims agree more; it scores `SECOND_READING_SCORE`. Two
    clouds with given normals that nothing matched are matched again on their points alone
    (`Params.points_alone`), and two without, or two thin walls' bands, with a thin wall's normals
    where a pick is one (`Params.wall_normals`; on thick pieces they find nothing): such fits score
    `SECOND_READING_SCORE` too."""
    params, be = params or Params(), resolve(backend)
    scale = float(scale or pair_scale(a, b, params))
    a, b = (_as_prepared(x, params, be, scale) for x in (a, b))
    result = _match_readings(a, b, params, be, heads, scale)
    fragments = [a.fragment, b.fragment]
    if (result.accepted or heads is not None or not all(is_cloud(f) for f in fragments)
            or len({f.normals is None for f in fragments}) > 1):
        return result
    given, thin = fragments[0].normals is not None, _bands(a, b)[2]
    # a thin wall's bands are read on its wall's normals: a plane fit blends its faces (vessel-noisy 14: 118 deg off)
    if given and params.points_alone and not all(thin):
        how, again = "on the points alone", match_pair(
            *(cloud_fragment(f.name, f.vertices, None, f.source, f.notes) for f in fragments), params, be, scale=scale)
    elif params.wall_normals and any(thin) and (params.points_alone or not given):
        how, again = "with a thin wall's normals", _on_wall_normals(fragments, params, be, scale)
    else:
        return result
    if not again.accepted:
        return replace(result, reason=f"{result.reason}; {how}: {again.reason}")
    why = ", the given normals set aside" if given else "; the clouds had none"
    return replace(again, score=SECOND_READING_SCORE * again.score, reason=f"{again.reason} ({how}{why})")


def _on_wall_normals(fragments, params: Params, be, scale: float) -> PairMatch:
    """Two clouds matched on a thin wall's normals (`cloud.wall_normals`); axes or profiles apart refused."""
    whole = replace(params, cloud_points=0)  # normals of its own: a cloud without scan normals is kept whole
    pa, pb = (prepare(cloud_fragment(f.name, f.vertices, wall_normals(f.vertices), f.source, f.notes), whole, be,
                      scale=scale) for f in fragments)
    found = _match_readings(pa, pb, params, be, None, scale)
    axes = [p.sample.axis and replace(p.sample.axis, thin=True) for p in (pa, pb)]  # read in `prepare`, as a wall's
    apart = found.accepted and (axes_meet(*axes, found.transform, scale, params.axis_apart) or profiles_agree(
        pa.fragment.vertices, pa.fragment.normals, axes[0], pb.fragment.vertices, pb.fragment.normals, axes[1],
        found.transform, scale))
    return replace(found, accepted=False, reason=f"a fit refused: {apart}") if apart else found


def _match_readings(a, b, params: Params, be, heads, scale: float) -> PairMatch:
    """`match_pair` on the fragments as they are (Fragments or Prepared), every reading asked."""
    t_start = time.perf_counter()
    pa, pb = (_as_prepared(x, params, be, scale) for x in (a, b))
    params = cloud_params(params, (pa.fragment, pb.fragment), scale)
    timings = {"prepare": time.perf_counter() - t_start}
    clouds = is_cloud(pa.fragment) or is_cloud(pb.fragment)
    # two readings' fits at different poses are weighed by how their rims meet the partner's creases:
    # a reading that takes a patch of skin for the break can pass a wrong fit of that patch, and the
    # right fit puts the outlines of the common break together, whichever reading found it; a fit
    # whose crease points on the other surface mostly lie on its creases (above 0) is taken as it is
    rim_index, contact = index_cache(be), params.contact_distance * scale
    rims = None if heads is not None or clouds else (
        lambda t: rim_agreement(pa.sample, pb.sample, t, contact, rim_index))
    result = _match_prepared(pa, pb, params, be, heads, scale, timings)
    if clouds and heads is None:
        result = skin_continues(pa, pb, params, scale, result)
        if result.accepted:
            # a loose fit its skin does not hold, or one laying the axes apart, is refused: the others are tried
            result = on_axes(pa, pb, params, scale, held_by_skin(pa, pb, params, be, scale, result))
            if result.accepted:
                return result  # a cloud has no second reading
    if heads is None and second_reading_params(params) is not None:
        first_rims = rims(result.transform) if result.accepted and rims is not None else None
        unsure = params.second_when_banded and result.accepted and result.reason.startswith(BANDED)
        if not result.accepted or (first_rims is not None and (first_rims <= 0 or unsure)):
            # the fracture as the second segmentation reads it (a segmentation that misreads one
            # family reads another right, docs/benchmarks.md): where the first found no fit, one
            # whose rims do not mostly meet the other's creases, or one that passed only in the band
            seconds = [_second_reading(p, params, be, scale) for p in (pa, pb)]
            second = None if None in seconds else _match_prepared(*seconds, params, be, None, scale, dict(timings))
            second_rims = None
            if second is not None and second.accepted and result.accepted and not same_pose(
                    result.transform, second.transform, params.contact_distance * scale):
                second_rims = rims(second.transform)
            if second is not None and second.accepted and (
                    not result.accepted or (second_rims is not None and second_rims > first_rims)):
                refused = unseen_skin(pa.sample, pb.sample, second.transform, params, scale)
                why = "" if not result.accepted else (
                    f"; its rims agree {second_rims:.2f}, the first reading's fit {first_rims:.2f}")
                if refused is None:
                    return replace(second, score=SECOND_READING_SCORE * second.score,
                                   reason=f"{second.reason} ({params.second_segmentation} segmentation{why})")
                if not result.accepted:
                    result = replace(result, reason=f"{result.reason}; the {params.second_segmentation} reading's "
                                                    f"fit: {refused}")
    if not (result.accepted or heads is not None or pa.strict_sample is None or pb.strict_sample is None):
        result = skin_continues(pa, pb, params, scale, _match_strict(pa, pb, params, be, scale, timings, result))
        if not result.accepted:
            result = _match_regions(pa, pb, params, be, scale, timings, result)
        if not result.accepted:
            result = _match_majority(pa, pb, params, be, scale, timings, result)
            if result.accepted:
                return on_axes(pa, pb, params, scale, result)  # not polished on the skin: an inner seam is break
        if not result.accepted:
            result = _match_thin(pa, pb, params, be, scale, timings, result)
    return on_axes(pa, pb, params, scale, held_by_skin(pa, pb, params, be, scale, result)) if clouds else result


def _match_strict(pa: Prepared, pb: Prepared, params: Params, be, scale: float, timings: dict,
                  result: PairMatch) -> PairMatch:
    """Two clouds matched on their strictly picked fracture, then on a wide pick
    (`cloudmatch.WIDE_SPREADS`) where that finds nothing (result: the first pick's, kept where
    neither finds a fit)."""
    # sparse clouds: fracture picked strictly (fewer skin points) can find a contact the wider
    # pick's votes missed (a thin wall's narrow break), and a wide pick one where the first pick
    # holds too little of a large break; the fit must still pass on the first pick (where the first
    # pick holds a point of both: a piece with no point over its median roughness picks none)
    found = (pa.strict_sample, pb.strict_sample)
    strict = _match_prepared(replace(pa, sample=found[0]), replace(pb, sample=found[1]), params, be,
                             None, scale, dict(timings))
    if not strict.accepted:
        found = [cloud_sample(p.fragment.vertices, getattr(p.fragment, "normals", None), params, scale, WIDE_SPREADS)
                 for p in (pa, pb)]
        strict = _match_prepared(replace(pa, sample=found[0]), replace(pb, sample=found[1]), params, be, None, scale,
                                 dict(timings))
    if not strict.accepted:
        return result
    first = (pa.sample, pb.sample) if len(pa.sample.fracture) and len(pb.sample.fracture) else found
    ver = verify_clouds(*first, strict.transform, be, params.contact_distance * scale,
                        params.max_rmse * scale, params.min_overlap, params.penetration_depth * scale)
    score = ver.overlap * (1.0 - ver.penetration) if ver.accepted else 0.0
    return replace(strict, accepted=ver.accepted, score=score, rmse=ver.rmse, overlap=ver.overlap,
                   penetration=ver.penetration, reason=ver.reason if ver.accepted else result.reason)


def _match_majority(pa: Prepared, pb: Prepared, params: Params, be, scale: float, timings: dict,
                    result: PairMatch) -> PairMatch:
    """Two clouds matched last on `cloudmatch.majority_samples` (an inner piece of a many-piece
    break is mostly break; the first pick holds a tenth of it): result kept where no fit passes.

    Every fit is verified and the one touching most kept, and the skin beside the seam is not asked
    (`skinhold.skin_continues`): beside an inner piece's seam lie its other breaks, which do not run
    on into the partner's. The Blender cube's inner shards at 20,000 points: right fits 0.3-0.6
    degrees off were refused with 8-9 of 219-246 points continuing, and shards 15 and 16 passed a
    fit 5.2 degrees off (overlap 0.127) before the right one (0.137; docs/benchmarks.md)."""
    found = majority_samples([p.fragment for p in (pa, pb)], params, scale)
    if found is None:
        return result
    ma, mb = replace(pa, sample=found[0]), replace(pb, sample=found[1])
    fit = _match_prepared(ma, mb, params, be, None, scale, dict(timings), every=True)
    why = " (on the rough class of a piece that is mostly break)"
    return replace(fit, reason=fit.reason + why) if fit.accepted else result


def _match_thin(pa: Prepared, pb: Prepared, params: Params, be, scale: float, timings: dict,
                result: PairMatch, bands: tuple | None = None) -> PairMatch:
    """Two clouds whose picks are thin walls' bands (`cloudmatch.thin_pick`) matched on them as a thin
    cut is (`cloudmatch.thin_wall_fit`), then from starts framed by their boards (`sheets.sheet_fit`),
    then, with scanned normals, with a rough-skinned piece's break read off its creases or from one
    axis of revolution laid on the other (`sheets.scanned_fit`): result kept where no fit passes. A
    fit laying the pieces' axes apart (`revolution.axes_meet`) lets the next path try (vessel-noisy
    seed 52: a boards' fit 17 degrees off). bands: `_bands` of the pair where the caller has it."""
    t0, (spacing, skins, thin) = time.perf_counter(), bands or _bands(pa, pb)
    found, index_of, samples, apart = None, index_cache(be), [pa.sample, pb.sample], []

    def laid_on_axes(fit):  # as `skinhold.on_axes` refuses it at the end, and why kept in `apart`
        apart.append(fit is not None and axes_meet(pa.sample.axis, pb.sample.axis, fit[0], scale, params.axis_apart))
        return None if apart[-1] else fit
    if all(thin):
        fits, index_of = _candidate_fits(pa, pb, params, be, None, scale, dict(timings))
        found = laid_on_axes(thin_wall_fit(skins, samples, [t for t, *_ in fits], spacing, params, scale, be, index_of))
        found = found or laid_on_axes(sheet_fit(skins, samples, spacing, params, scale, be, index_of))
    scanned = [getattr(p.fragment, "normals", None) for p in (pa, pb)]
    if found is None and all(n is not None for n in scanned):
        found = scanned_fit([np.asarray(p.fragment.vertices, np.float64) for p in (pa, pb)], scanned, skins,
                            samples, spacing, params, scale, be, index_of)
    if found is None:
        return replace(result, reason=next(filter(None, apart), result.reason))
    (transform, ver, reason), timings = found, {**timings, "seam": time.perf_counter() - t0}
    return PairMatch(transform, True, ver.overlap * (1.0 - ver.penetration), ver.rmse, ver.overlap,
                     ver.penetration, np.zeros((0, 2), np.int64), -1, -1, reason, timings)


def _bands(pa: Prepared, pb: Prepared):
    """The pair's point spacing (absolute), each cloud's `cloud_skin`, and whether each pick is a thin
    wall's band (`cloudmatch.thin_pick`)."""
    spacing = max(point_spacing(np.asarray(p.fragment.vertices, np.float64)) for p in (pa, pb))
    skins = [cloud_skin(p.fragment, p.sample) for p in (pa, pb)]
    return spacing, skins, [thin_pick(skin, p.sample, spacing) for (skin, _), p in zip(skins, (pa, pb))]


def _boards_before_regions(pa: Prepared, pb: Prepared, params: Params, be, scale: float, timings: dict,
                           fit: PairMatch) -> PairMatch:
    """A crease regions' fit of two scanned clouds whose picks are both thin walls' bands gives way to
    the thin paths' fit (`_match_thin`) where they find one: a board's narrow faces are crease regions
    too, and laid on each other they pass at a quarter or half turn (bookshelves cut rough and smooth,
    a Blender cube's thin shards; docs/benchmarks.md)."""
    if (not fit.accepted or any(getattr(p.fragment, "normals", None) is None for p in (pa, pb))
            or not all((bands := _bands(pa, pb))[2])):
        return fit
    thin = _match_thin(pa, pb, params, be, scale, timings, replace(fit, accepted=False), bands)
    return thin if thin.accepted else fit


def _match_regions(pa: Prepared, pb: Prepared, params: Params, be, scale: float, timings: dict,
                   result: PairMatch) -> PairMatch:
    """Two clouds matched with each crease-bounded region of a against each of b as the fracture
    (a clean break is no rougher than the skin). Of the accepted fits of two curved regions, the one whose
    skin runs on into the partner's across the seam (`seam.skin_continuation`, at least `Params.min_skin`)
    wins where no fit at another turn continues nearly as well (`_by_skin`); else the one whose regions
    touch over the largest share, where both regions curve (`LOOSE_CURVED`) and no fit at another pose
    touches nearly as widely: a symmetric break cannot tell them apart, and a guess is worse than no
    answer (result: kept where none wins). Where no fit passing the region bars wins on its skin, fits
    touching and facing less (`cloudmatch.LOOSE_OVERLAP`, `LOOSE_FACING`: a smooth cut's region holds
    skin beyond a shallow rim) may, on their skin alone, where both regions curve."""
    planar = match_planes(pa, pb, params, be, scale, timings)
    if planar is not None:
        return planar
    # a flat break fits its partner at one turn only, which its outline alone decides
    turns = params.with_(patch_turns=REGION_TURNS)
    contact = params.contact_distance * scale
    accepted, loose = [], []  # (overlap, transform, verification, region sample a, region sample b, residual bound,
    # index_of) of fits passing the region bars, and the looser ones
    curved = [[curvedness(s.fracture) >= LOOSE_CURVED for s, *_ in p.regions] for p in (pa, pb)]
    for (sa, patch_a, rough_a), curved_a in zip(pa.regions, curved[0]):
        for (sb, patch_b, rough_b), curved_b in zip(pb.regions, curved[1]):
            fits, index_of = _candidate_fits(replace(pa, sample=sa, patches=[patch_a]),
                                             replace(pb, sample=sb, patches=[patch_b]), turns, be, None, scale,
                                             dict(timings))
            bound = REGION_RESIDUAL * np.hypot(rough_a, rough_b)
            for transform, *_ in fits:
                ver = verify_clouds(sa, sb, transform, be, contact, bound, LOOSE_OVERLAP,
                                    params.penetration_depth * scale, index_of, min_facing=LOOSE_FACING)
                fit = (ver.overlap, transform, ver, sa, sb, bound, index_of)
                if ver.accepted and ver.overlap >= REGION_OVERLAP and ver.facing >= REGION_FACING:
                    accepted.append(fit)
                    loose.append(fit)
                elif ver.accepted and curved_a and curved_b:
                    loose.append(fit)
    scanned = all(getattr(p.fragment, "normals", None) is not None for p in (pa, pb))
    rivals_share = SKIN_RIVALS if scanned else SKIN_RIVALS_ESTIMATED
    accepted.sort(key=lambda x: -x[0])
    loose.sort(key=lambda x: -x[0])
    by_skin = _by_skin(accepted, params, be, scale, timings, rivals_share) if accepted else None
    if by_skin is None and len(loose) > len(accepted):
        by_skin = _by_skin(loose, params, be, scale, timings, rivals_share, LOOSE_OVERLAP, LOOSE_FACING)
    if by_skin is not None:
        return _boards_before_regions(pa, pb, params, be, scale, timings, by_skin)
    if not accepted:
        return result
    overlap, transform, ver, sa, sb, *_ = accepted[0]
    rivals = [o for o, t, *_ in accepted[1:] if not same_pose(t, transform, contact)]
    fit = PairMatch(transform, True, overlap * (1.0 - ver.penetration), ver.rmse, overlap, ver.penetration,
                    np.zeros((0, 2), np.int64), -1, -1, "accepted (crease regions)", timings)
    bends = curvedness(sa.fracture), curvedness(sb.fracture)
    if min(bends) < LOOSE_CURVED:
        # a flat region holds neither the turn nor the slide of a fit in its plane, so the widest touch
        # is a guess there (flat faces of the skin laid on each other: a Blender cube's, boards')
        return replace(fit, accepted=False, score=0.0, reason="unsettled: crease regions touch widest where one is "
                       f"flat (curvedness {bends[0]:.3f} and {bends[1]:.3f}), which holds no turn or slide")
    if rivals and rivals[0] >= AMBIGUOUS_SHARE * overlap:
        return replace(fit, accepted=False, score=0.0, reason="ambiguous: crease regions fit at two poses alike "
                       f"(overlap {overlap:.2f} and {rivals[0]:.2f})")
    return _boards_before_regions(pa, pb, params, be, scale, timings, fit)


def _by_skin(accepted: list, params: Params, be, scale: float, timings: dict, rivals_share: float,
             min_overlap: float = REGION_OVERLAP, min_facing: float = REGION_FACING) -> PairMatch | None:
    """The region fit (of `_match_regions`' accepted list, widest touching first) whose skin
    continues the partner's best, polished on that skin (`seam.seam_polish`), where it continues by
    at least `Params.min_skin`, every fit at another turn (over SKIN_RIVAL_DEG) continues less than
    `rivals_share` times as much, and the polished fit verifies (touching over `min_overlap`,
    facing `min_facing`); None otherwise. Fits of two curved regions only (`LOOSE_CURVED`): flat faces of
    skin laid on each other continue the skin wherever the faces beside them lie in one plane."""
    accepted = [f for f in accepted if min(curvedness(f[3].fracture), curvedness(f[4].fracture)) >= LOOSE_CURVED]
    if params.min_skin is None or not accepted:
        return None
    contact = params.contact_distance * scale
    poses = [fit[1] for fit in accepted]
    distinct = [accepted[k] for k in distinct_poses(poses, range(len(accepted)), SKIN_FITS, contact)]
    skins = [seam.skin_continuation(sa, sb, t, contact, scale) for _, t, _, sa, sb, *_ in distinct]
    won = seam.skin_winner(skins, [fit[1] for fit in distinct], params.min_skin, rivals_share, SKIN_RIVAL_DEG)
    if won is None:
        return None
    best = won[0]
    transform = distinct[best][1]
    _, _, _, sa, sb, bound, index_of = distinct[best]
    t0 = time.perf_counter()
    free = [seam.free_surface(sa.surface, sa.normals, apply(transform, sb.surface), contact),
            seam.free_surface(sb.surface, sb.normals, apply(invert(transform), sa.surface), contact)]
    transform, held = seam.seam_polish(sa.fracture, sa.fracture_normals, sb.fracture, free[0], free[1], transform,
                                       contact, scale, index_of(sa.fracture))
    after = seam.skin_continuation(sa, sb, transform, contact, scale)
    timings = {**timings, "seam": time.perf_counter() - t0}
    ver = verify_clouds(sa, sb, transform, be, contact, bound, min_overlap, params.penetration_depth * scale,
                        index_of, min_facing=min_facing)
    if not ver.accepted:
        return None
    touching = f" touching over {ver.overlap:.2f} of them" if ver.overlap < REGION_OVERLAP else ""
    return PairMatch(transform, True, ver.overlap * (1.0 - ver.penetration), ver.rmse, ver.overlap, ver.penetration,
                     np.zeros((0, 2), np.int64), -1, -1, f"accepted (crease regions{touching}; its skin continues the "
                     f"partner's {skins[best]:.2f} across the seam, {after:.2f} once held by it, {held} points)",
                     timings)


def _match_prepared(pa: Prepared, pb: Prepared, params: Params, be, heads, scale: float, timings: dict,
                    every: bool = False) -> PairMatch:
    """match_pair on prepared fragments: coarse poses, ICP, verification (timings: added to). every:
    clouds verify every fit and keep the one that passes with the most overlap less penetration."""
    t_start = time.perf_counter() - timings["prepare"]
    fits, index_of = _candidate_fits(pa, pb, params, be, heads, scale, timings)
    t1 = time.perf_counter()
    # verify the best-touching fits first; clouds stop at the first accepted, meshes verify them all
    # and `meshfit.skin_pick` chooses among those that pass (where none does: that the band passes)
    clouds = is_cloud(pa.fragment) or is_cloud(pb.fragment)
    picking = not clouds and params.skin_pick is not None
    best, passed, banded = None, [], []  # (transform, verification, ca, cb, pairs) each
    for transform, ca, cb, pairs in fits:
        if any(same_fit(transform, fit[0], scale) for fit in passed):
            continue  # refined to a fit already passed: it would pass alike
        if clouds:  # mutual overlap, facing, interpenetration near the other surface only
            ver = verify_clouds(pa.sample, pb.sample, transform, be, params.contact_distance * scale,
                                params.max_rmse * scale, params.min_overlap, params.penetration_depth * scale, index_of)
        else:
            ver = verify_mesh(pa.sample, pb.sample, transform, be, params, scale, index_of, params.max_rmse)
            if not ver.accepted and (picking or not (passed or banded)):
                outline = band_fit(pa.sample, pb.sample, transform, be, params, scale, index_of, ver)
                if outline is not None:
                    banded.append((transform, outline, ca, cb, pairs))
        rank = (ver.accepted, ver.overlap - ver.penetration)
        if best is None or rank > best[0]:
            best = (rank, transform, ver, ca, cb, pairs)
        if ver.accepted:
            passed.append((transform, ver, ca, cb, pairs))
            if not (picking or every):
                break
    over = None
    if passed and not every:
        best = (None, *skin_pick(pa.sample, pb.sample, params, scale, passed))
        over = skin_over_band(pa.sample, pb.sample, params, scale, best[1:], banded) if picking else None
    timings["icp+verify"] += time.perf_counter() - t1
    timings["total"] = time.perf_counter() - t_start

    if best is None:
        reason = "no fracture contours" if not (pa.contours and pb.contours) else "no consistent LCS correspondences"
        return PairMatch(np.eye(4), False, 0.0, float("inf"), 0.0, 0.0, np.zeros((0, 2), np.int64), -1, -1,
                         reason, timings)
    _, transform, ver, ca, cb, pairs = best
    weight = 1.0
    if over is not None or (not ver.accepted and banded):
        # no fit passed every check, or one that did lays its skin across the partner's; one passed
        # all but the residual (or facing) in the band
        transform, ver, ca, cb, pairs = over or skin_pick(pa.sample, pb.sample, params, scale, banded)
        weight = OUTLINE_SCORE
    score = weight * ver.overlap * (1.0 - ver.penetration) if ver.accepted else 0.0
    return PairMatch(transform, ver.accepted, score, ver.rmse, ver.overlap, ver.penetration,
                     pairs, ca, cb, ver.reason, timings)


def _candidate_fits(pa: Prepared, pb: Prepared, params: Params, be, heads, scale: float, timings: dict):
    """The fits of a pair to verify, best-touching first: coarse poses (LCS, point-pair votes,
    patches face to face), ranked by a short ICP, then the best few refined. Returns the list of
    (transform, contour_a, contour_b, lcs pairs) and the nearest-neighbour index function of the
    pair's point sets (timings: "coarse" and "icp+verify" set)."""
    t0 = time.perf_counter()
    if heads is not None:
        ca, ia, cb, ib = (int(h) for h in heads)
        if not (0 <= ca < len(pa.contours) and 0 <= cb < len(pb.contours)):
            raise ValueError(f"head contour out of range: {ca} of {len(pa.contours)}, {cb} of {len(pb.contours)}")
        if not (0 <= ia < len(pa.contours[ca].points) and 0 <= ib < len(pb.contours[cb].points)):
            raise ValueError("head point out of range for its contour")
        contour_pairs = [(ca, cb, ia, ib)]
    else:
        contour_pairs = [(i, j, None, None) for i in range(len(pa.contours)) for j in range(len(pb.contours))]

    rng = np.random.default_rng(12345)
    inlier = params.ransac_inlier * scale
    # Coarse poses, three sources: the paper's LCS over fused contour values (RANSAC over its
    # correspondences), point-pair-feature votes, and fracture patches put face to face at a sweep of turns.
    starts, origins = [], []  # (4,4) poses; (source, contour_a, contour_b, lcs pairs)
    for ca, cb, ha, hb in contour_pairs:
        A, B = pa.contours[ca], pb.contours[cb]
        for m in circular_lcs(A.fused, B.fused, params.lcs_eps, be, ha, hb):
            if m.length < 3:
                continue
            src, dst = B.points[m.pairs[:, 1]], A.points[m.pairs[:, 0]]
            for pose, count in ransac_poses(src, dst, params.ransac_iterations, inlier, rng, keep=2):
                starts.append(pose)
                origins.append(("lcs", ca, cb, m.pairs))
    if heads is None and params.ppf_points > 0:
        # point-pair-feature votes: finds contacts that cover only part of each fracture surface
        model = _ppf_table(pa.sample, params, scale, "model")
        scene = _ppf_table(pb.sample, params, scale, "scene")
        for pose, votes in vote_poses(model, scene, 2 * params.ppf_distance_step * scale, keep=params.ppf_starts,
                                      backend=be):
            starts.append(pose)
            origins.append(("ppf", -1, -1, np.zeros((0, 2), np.int64)))
    if heads is None:
        for P in _main_patches(pa.patches, params):
            for Q in _main_patches(pb.patches, params):
                for pose in facing_poses(P.centre, P.normal, Q.centre, Q.normal, params.patch_turns):
                    starts.append(pose)
                    origins.append(("patch", -1, -1, np.zeros((0, 2), np.int64)))
    index_of = index_cache(be)  # nearest-neighbour indexes of the pair's own point sets

    w_a, w_b = pa.sample.weights(), pb.sample.weights()
    candidates = []
    if starts:
        # rank every start by a short batched ICP on a small sample, keep the best few. The screen
        # fits only the nearest twentieth of the points (screen_trim): its reject distance is wide
        # for starts 20 degrees off, and a contact of an eighth of b's fracture, nearest fifth
        # trimmed in, was dragged off by the rest of b bending away (a true start lost its share)
        every = max(1, len(pb.sample.fracture) // params.screen_points)
        sub_b, sub_w = pb.sample.fracture[::every], w_b[::every]
        reject, floor = params.screen_reject * scale, params.contact_distance * scale
        poses, share = batched_icp(sub_b, pa.sample.fracture, np.array(starts), be, params.screen_iterations,
                                   reject, floor, trim=params.screen_trim, index=index_of(pa.sample.fracture),
                                   weights=sub_w, target_weights=w_a)
        # the most promising starts go on longer (a start can be 20 degrees off)
        keep = np.argsort(-share, kind="stable")[: params.screen_keep]
        poses, share = batched_icp(sub_b, pa.sample.fracture, poses[keep], be, params.screen_more_iterations,
                                   reject, floor, trim=params.screen_trim, index=index_of(pa.sample.fracture),
                                   weights=sub_w, target_weights=w_a)
        order = distinct_poses(poses, np.argsort(-share, kind="stable"), params.hypotheses, 0.02 * scale)
        candidates = [(share[k], poses[k], *origins[keep[k]][1:]) for k in order]
    timings["coarse"] = time.perf_counter() - t0

    t1 = time.perf_counter()
    fits = []
    if candidates:
        polished, best_first = fine_stage(pa, pb, np.array([c[1] for c in candidates]), params, be, scale,
                                          index_of(pa.sample.fracture), params.verify_at_most)
        fits = [(polished[i], *candidates[k][2:]) for i, k in enumerate(best_first)]
    if heads is None and params.facet_starts > 0:
        # facets whose outlines agree go first, flat ones before near-flat ones: the ranking above
        # scores them by a fracture sample that a flat cut read as skin lacks (`facets`)
        kinds = ((pa.facets, pb.facets, params.facet_outline), (pa.grown, pb.grown, params.grown_outline))
        laid = [t for fa, fb, bound in kinds if bound > 0 and fa and fb
                for _, t in facet_fits(fa, fb, scale, bound, params.facet_starts)]
        if laid:
            polished = refine_point_to_plane(pb.sample.fracture, pa.sample.fracture, pa.sample.fracture_normals,
                                             np.array(laid), be, params.plane_iterations,
                                             params.contact_distance * scale, index_of(pa.sample.fracture),
                                             pb.sample.weights(), pa.sample.weights())
            fits = [(T, -1, -1, np.zeros((0, 2), np.int64)) for T in polished] + fits
    timings["icp+verify"] = time.perf_counter() - t1
    return fits, index_of
