"""Accepted cloud fits read against the skin across their seam (issue 15).

A fresh break leaves the skin on its two sides continuous, so an accepted fit of two clouds is
checked and polished on that skin (`seam`): refused where the skin beside the seam does not
continue the partner's (`skin_continues`), and polished on it (`held_by_skin`) where the break
leaves the fit loose or where the polished fit continues the skin clearly better (a smooth cut
through a board slides along itself by half the board's thickness: bookshelf boards 0.04 cut
smooth, 1.2-1.8% of the size off, 0.1-0.2% once polished).
"""
from __future__ import annotations

import time
from dataclasses import replace

from ..params import Params
from . import seam
from .cloudmatch import MIN_PICK_SKIN, PICK_SKIN_NEAR, THIN_WIDE_GATE, cloud_skin, verify_clouds
from .prepare import Prepared
from .result import PairMatch
from .revolution import axes_meet
from .verify import index_cache

# A fit that its break holds is replaced by its polish on the skin where the share of the free
# skin points near the seam that continue the partner's rises by at least SKIN_GAIN: bookshelf
# boards 0.04 cut smooth, seeds 0, 1, 6, 7 (fits slid 1.2-1.8% of the size), 0.10-0.34 -> 0.39-0.81.
# A loose fit's usual polish gives way to the wide gate's by the same margin.
SKIN_GAIN = 0.1
# A loose fit is set by the skin across its seam; where its polish is held there by fewer than
# LOOSE_HELD skin points it is set by nothing and refused: Voronoi clouds without normals cut flat,
# matched on roughness picks of skin, held by 8-25 points at 30-146 degrees off; of the right
# loose fits recorded in the bench runs (68: slabs, vessels, boards, smooth and Voronoi cuts) the
# fewest were held by 49.
LOOSE_HELD = 30


def skin_continues(pa: Prepared, pb: Prepared, params: Params, scale: float, result: PairMatch) -> PairMatch:
    """An accepted cloud fit of the roughness picks, refused where the skin beside its seam does
    not continue the partner's (`cloudmatch.MIN_PICK_SKIN`): a face laid on a face with the rims
    apart passes the picks' bars on a sparse cloud."""
    if not result.accepted:
        return result
    continues, near = seam.skin_points(pa.sample, pb.sample, result.transform, params.contact_distance * scale, scale)
    if near < PICK_SKIN_NEAR or continues >= MIN_PICK_SKIN * near:
        return result
    return replace(result, accepted=False, score=0.0, reason=f"the skin beside its seam does not continue the "
                   f"partner's ({continues} of {near} points near it, under {MIN_PICK_SKIN:.2f})")


def on_axes(pa: Prepared, pb: Prepared, params: Params, scale: float, result: PairMatch) -> PairMatch:
    """An accepted cloud fit, refused where it does not carry one piece's axis of revolution onto the
    other's (`revolution.axes_meet`, the axes read off scanned normals in `prepare`), as meshes'
    fits are: a vessel's sherd laid half a turn off on its band passes on a sparse cloud's skin."""
    apart = result.accepted and axes_meet(pa.sample.axis, pb.sample.axis, result.transform, scale, params.axis_apart)
    return replace(result, accepted=False, score=0.0, reason=apart) if apart else result


def held_by_skin(pa: Prepared, pb: Prepared, params: Params, be, scale: float, result: PairMatch) -> PairMatch:
    """An accepted cloud fit polished on the skin across the seam (`seam.seam_polish`), where the
    polished fit passes verification too. Where the break leaves the fit loose (`seam.looseness`
    under `seam.LOOSE`: a thin board's narrow band) the usual polish is taken, and the polish with
    the skin's gate widened at first instead where its skin continues the partner's by SKIN_GAIN
    more; elsewhere, of the two polishes, the one whose skin continues the partner's most, where
    that beats the fit's own by SKIN_GAIN (result: kept otherwise). A loose fit whose polish is held by
    fewer than LOOSE_HELD skin points is refused."""
    if not result.accepted or "seam" in result.timings or not (len(pa.sample.fracture) and len(pb.sample.fracture)):
        return result  # held by its skin already (`_by_skin`), or found on a pick of its own (`_match_strict`)
    index_of = index_cache(be)
    contact = params.contact_distance * scale
    index = index_of(pa.sample.fracture)
    loose = seam.looseness(pb.sample.fracture, pa.sample.fracture, pa.sample.fracture_normals, result.transform,
                           contact, index) < seam.LOOSE

    def share(transform):
        continues, near = seam.skin_points(pa.sample, pb.sample, transform, contact, scale)
        return continues / near if near >= PICK_SKIN_NEAR else 0.0

    t0 = time.perf_counter()
    skins = cloud_skin(pa.fragment, pa.sample), cloud_skin(pb.fragment, pb.sample)
    best, bar = None, None  # bar: the share a polish must reach, read once one verifies
    for wide in (0.0, THIN_WIDE_GATE) if loose else (THIN_WIDE_GATE, 0.0):
        if loose and wide and best is None:
            break  # a loose fit whose usual polish does not hold and verify is kept as it is
        transform, held = seam.seam_polish(pa.sample.fracture, pa.sample.fracture_normals, pb.sample.fracture,
                                           *skins, result.transform, contact, scale, index, wide)
        if not held:
            continue  # no skin point held it: the break's own polish again
        ver = verify_clouds(pa.sample, pb.sample, transform, be, contact, params.max_rmse * scale, params.min_overlap,
                            params.penetration_depth * scale, index_of)
        if not ver.accepted:
            continue
        gain = share(transform)
        if bar is None:
            bar = 0.0 if loose else share(result.transform) + SKIN_GAIN
        if gain >= bar:
            best, bar = (transform, held, ver), gain + (SKIN_GAIN if loose else 0.0)
    timings = {**result.timings, "seam": time.perf_counter() - t0}
    if best is None:
        return replace(result, timings=timings) if loose else result
    transform, held, ver = best
    if loose and held < LOOSE_HELD:
        return replace(result, accepted=False, score=0.0, timings=timings, reason=f"unsettled: loose on its break, "
                       f"and the skin across the seam holds it at {held} points (under {LOOSE_HELD})")
    why = "loose on its break" if loose else f"slid on its break: its skin continues the partner's {bar:.2f}"
    # a cloud fit scores its overlap less its interpenetration (no reading or outline weight)
    return replace(result, transform=transform, score=ver.overlap * (1.0 - ver.penetration), rmse=ver.rmse,
                   overlap=ver.overlap, penetration=ver.penetration, timings=timings,
                   reason=f"{result.reason} ({why}: the skin across the seam held it, {held} points)")
