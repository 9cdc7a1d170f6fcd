"""Verification of a mesh pair's fit: the checks of `verify` with `Params`' bounds; the residual
band where a rescanned break's outline or skin speaks for it (`outline_fit`); a thin wall's fit
that faces too little, taken where its rims meet the partner's creases (`rims_fit`); `band_fit`
asks the one that a refused fit's reason calls for. `skin_pick` chooses among fits that pass alike,
`skin_over_band` between the one chosen and those passing in the band on their skin; `unseen_skin`
asks a second reading's fit for skin that continues across its seam as the first reading sees it."""
from __future__ import annotations

from dataclasses import replace
from functools import cache

import numpy as np

from ..params import Params
from . import seam
from .revolution import axes_meet
from .verify import rim_agreement, verify


# A thin-walled pair's fit is judged on its skin (`Params.wall_skin`) where at least this many free
# skin points lie near the partner's: on coarse meshes (few vertices to sample) right fits of corpus
# vessels have up to 22 with next to none continuing (seeds 10-23); at 30 the rule still refuses 11
# of the 12 wrong fits the forest used that it refused at 20 (seeds 10-15; docs/benchmarks.md,
# "Thin walls: the skins run on") ...
WALL_SKIN_NEAR = 30
# ... and where the fit lays under this share of the smaller break on the partner's. A two-piece
# vessel's right fit covers all of it, and at the scale of a piece that large the skin's quadrics
# bend away within their reach (corpus vessel-clean seed 14: 7 of 97 continue); no wrong fit of
# the corpus vessels' 8-piece objects covered as much.
WALL_SKIN_WHOLE = 0.9
# how the reasons of the fits `band_fit` accepts begin (`pipeline.match_pair` asks the second reading of them)
ON_OUTLINE, ON_SKIN, ON_RIMS = BANDED = ("accepted on its outline", "accepted on its skin", "accepted on its rims")
# A fit that passes gives way to one passing in the band whose skin beside the seam continues the
# partner's at least this many times as much (`skin_over_band`).
SKIN_OVER = 2.0


def verify_mesh(a, b, transform: np.ndarray, be, params: Params, scale: float, index_of, max_rmse: float):
    """`verify` of a mesh pair's fit with `params`' checks, the residual bound `max_rmse` (of the
    scale), `axis_apart`'s, `seam_skin`'s, and for two thin walls `wall_skin`'s."""
    ver = verify(a, b, transform, be, params.contact_distance * scale, max_rmse * scale, params.min_overlap,
                 params.penetration_depth * scale, params.max_penetration, index_of, min_facing=params.min_facing,
                 max_surface_penetration=params.max_surface_penetration)
    apart = ver.accepted and axes_meet(a.axis, b.axis, transform, scale, params.axis_apart)
    if apart:
        return replace(ver, accepted=False, reason=apart)
    if not ver.accepted:
        return ver
    contact = params.contact_distance * scale
    if (params.wall_skin is not None and max(a.wall, b.wall) < params.region_thin_wall
            and ver.overlap < WALL_SKIN_WHOLE):
        refused = _skin_refusal(a, b, transform, contact, scale, params.wall_skin, False, "a thin wall's seam")
        if refused:
            return replace(ver, accepted=False, reason=refused)
    refused = _seam_refusal(a, b, transform, params, scale)
    return replace(ver, accepted=False, reason=refused) if refused else ver


def _seam_refusal(a, b, transform: np.ndarray, params: Params, scale: float) -> str | None:
    """Why a fit is refused on the skin beside its seam (`Params.seam_skin`; the skin as the
    samples' reading takes it: an inner piece's other breaks beside the seam run on into
    nothing), or None."""
    if params.seam_skin is None:
        return None
    return _skin_refusal(a, b, transform, params.contact_distance * scale, scale, params.seam_skin, True, "the seam")


def unseen_skin(a, b, transform: np.ndarray, params: Params, scale: float) -> str | None:
    """Why a fit is refused where neither the skin as the samples' reading takes it nor all the
    free surface beside its seam continues the partner's (each under `Params.seam_skin`), or None.
    Asked of a fit of the second reading with the first reading's samples: the second takes most
    of a rescanned piece for break, so that its own skin rule sees no skin beside a seam; the
    first misreads breaks as skin, which the free surface as a whole corrects."""
    skin = _seam_refusal(a, b, transform, params, scale)
    if skin is None:
        return None
    free = _skin_shortfall(a, b, transform, params.contact_distance * scale, scale, params.seam_skin, False)
    return None if free is None else f"{skin}, nor does its free surface ({free[0]} of {free[1]} points near it)"


def _skin_refusal(a, b, transform: np.ndarray, contact: float, scale: float, share: float, skin_only: bool,
                  where: str) -> str | None:
    """The reason a fit is refused where `_skin_shortfall` says so, else None."""
    short = _skin_shortfall(a, b, transform, contact, scale, share, skin_only)
    if short is None:
        return None
    return f"the skin beside {where} does not continue the partner's ({short[0]} of {short[1]} points near it)"


def _skin_shortfall(a, b, transform: np.ndarray, contact: float, scale: float, share: float,
                    skin_only: bool) -> tuple[int, int] | None:
    """(continuing, near) where at least WALL_SKIN_NEAR free points beside a fit's seam lie near the
    partner's surface and under `share` of them continue it (`seam.skin_points`), else None."""
    continues, near = seam.skin_points(a, b, transform, contact, scale, skin_only=skin_only)
    return (continues, near) if near >= WALL_SKIN_NEAR and continues < share * near else None


def outline_fit(a, b, transform: np.ndarray, be, params: Params, scale: float, index_of, failed):
    """The verification of a fit refused only for its residual (`failed`), accepted where its
    residual lies within `residual_band` times the bound and the two outlines agree by at least
    `min_outline` (with the skin beside the seam continuing the partner's by `outline_skin`), or
    the skin continues by at least `min_skin` (`Params`); None otherwise. A rescanned break's
    right fit mates less closely than a clean one's, and its sharp edges are rounded away; where
    the surfaces turn at a working length the two pieces' outlines still meet, and the skins on
    both sides of the seam still run on. A flat break turned half a turn keeps a symmetric
    outline, but lays its sides across the partner's."""
    outlines = params.min_outline is not None and a.outline is not None and b.outline is not None
    if not outlines and params.min_skin is None:
        return None
    if failed.rmse > params.residual_band * params.max_rmse * scale:
        return None  # out of the band: no second verification needed to know
    ver = verify_mesh(a, b, transform, be, params, scale, index_of, params.residual_band * params.max_rmse)
    if not ver.accepted:
        return None
    contact = params.contact_distance * scale
    skin = cache(lambda: seam.skin_continuation(a, b, transform, contact, scale))  # asked at most once
    if outlines:
        agree = rim_agreement(replace(a, creases=a.outline), replace(b, creases=b.outline), transform, contact,
                              index_of)
        if agree >= params.min_outline and (params.outline_skin is None or skin() >= params.outline_skin):
            return replace(ver, reason=f"{ON_OUTLINE} (outlines agree {agree:.2f}; {failed.reason})")
    if params.min_skin is not None and skin() >= params.min_skin:
        return replace(ver, reason=f"{ON_SKIN} (the skin beside the seam continues {skin():.2f}; "
                                   f"{failed.reason})")
    return None


def rims_fit(a, b, transform: np.ndarray, be, params: Params, scale: float, index_of, failed):
    """The verification of a fit refused only for facing too little (`failed`), accepted where its
    rims meet the partner's creases by at least `Params.facing_rims`; None otherwise. A thin
    wall's break is a narrow band: at the right fit the skins beside the seam touch side by side
    over more points than the band does face to face (coarse vessels face 0.01-0.04), but the
    band's sharp rims lie on the partner's (0.41-0.52, where wrong fits refused for facing reach
    0.35; `docs/benchmarks.md`)."""
    if params.facing_rims is None:
        return None
    agree = rim_agreement(a, b, transform, params.contact_distance * scale, index_of)
    if agree < params.facing_rims:
        return None
    ver = verify_mesh(a, b, transform, be, replace(params, min_facing=0.0), scale, index_of, params.max_rmse)
    if not ver.accepted:
        return None
    return replace(ver, reason=f"{ON_RIMS} (rims agree {agree:.2f}; {failed.reason})")


def band_fit(a, b, transform: np.ndarray, be, params: Params, scale: float, index_of, failed):
    """`outline_fit` of a fit refused for its residual, `rims_fit` of one refused for facing, else None."""
    if failed.reason.startswith("residual"):
        return outline_fit(a, b, transform, be, params, scale, index_of, failed)
    if failed.reason.startswith("facing"):
        return rims_fit(a, b, transform, be, params, scale, index_of, failed)
    return None


def skin_pick(a, b, params: Params, scale: float, passed: list) -> tuple:
    """Of the fits that passed ((transform, verification, ...) each, best-touching first), the
    first, or the one whose skin beside the seam continues the partner's most
    (`seam.skin_continuation`) where that is at least `Params.skin_pick` and more than the
    first's. A flat break passes at several turns, a smooth one at several slides: only at the
    right one does the skin run on across the seam (docs/benchmarks.md, "Fits that pass alike:
    the skin picks")."""
    first = passed[0]
    if params.skin_pick is None or len(passed) == 1:
        return first
    contact = params.contact_distance * scale
    skins = [seam.skin_continuation(a, b, fit[0], contact, scale) for fit in passed]
    k = int(np.argmax(skins))
    if skins[k] < params.skin_pick or skins[k] <= skins[0]:
        return first
    transform, ver, *rest = passed[k]
    return (transform, replace(ver, reason=f"{ver.reason} (of {len(passed)} fits that pass, the skin beside its "
                                           f"seam continues most: {skins[k]:.2f}, the first's {skins[0]:.2f})"), *rest)


def skin_over_band(a, b, params: Params, scale: float, chosen: tuple, banded: list) -> tuple | None:
    """Of the fits passing in the band (`band_fit`; (transform, verification, ...) each), the one
    whose skin beside the seam continues the partner's most, where that is at least
    `Params.min_skin` and SKIN_OVER times the chosen passing fit's (`chosen`); None otherwise. On
    a noisy rescan every fit of a flat break lies near the residual bound, on either side of it:
    a break laid half a turn off on the partner's passed where the right fit, a little rougher,
    fell in the band; only the right one carries the skin on across the seam (docs/benchmarks.md)."""
    if params.min_skin is None or not banded:
        return None
    contact = params.contact_distance * scale
    skins = [seam.skin_continuation(a, b, fit[0], contact, scale) for fit in banded]
    k = int(np.argmax(skins))
    if skins[k] < params.min_skin:
        return None
    own = seam.skin_continuation(a, b, chosen[0], contact, scale)
    if skins[k] < SKIN_OVER * own:
        return None
    transform, ver, *rest = banded[k]
    return (transform, replace(ver, reason=f"{ver.reason}; its skin continues {skins[k]:.2f}, that of a fit "
                                           f"that passes {own:.2f}"), *rest)
