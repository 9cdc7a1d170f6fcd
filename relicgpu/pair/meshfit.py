"""Verification of a mesh pair's fit: the checks of `verify` with `Params`' bounds, and the
residual band where a rescanned break's outline or skin speaks for it (`outline_fit`)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..params import Params
from . import seam
from .verify import rim_agreement, verify


def verify_mesh(a, b, transform: np.ndarray, be, params: Params, scale: float, index_of, max_rmse: float):
    """`verify` of a mesh pair's fit with `params`' checks, the residual bound `max_rmse` (of the scale)."""
    return verify(a, b, transform, be, params.contact_distance * scale, max_rmse * scale, params.min_overlap,
                  params.penetration_depth * scale, params.max_penetration, index_of, min_facing=params.min_facing,
                  max_surface_penetration=params.max_surface_penetration)


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
    skin = None
    if outlines:
        agree = rim_agreement(replace(a, creases=a.outline), replace(b, creases=b.outline), transform, contact,
                              index_of)
        if agree >= params.min_outline:
            skin = seam.skin_continuation(a, b, transform, contact, scale) if params.outline_skin is not None else None
            if skin is None or skin >= params.outline_skin:
                return replace(ver, reason=f"accepted on its outline (outlines agree {agree:.2f}; {failed.reason})")
    if params.min_skin is not None:
        skin = seam.skin_continuation(a, b, transform, contact, scale) if skin is None else skin
        if skin >= params.min_skin:
            return replace(ver, reason=f"accepted on its skin (the skin beside the seam continues {skin:.2f}; "
                                       f"{failed.reason})")
    return None
