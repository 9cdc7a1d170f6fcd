"""Flat facets laid outline to outline: starts for flat cuts.

A flat cut (a Voronoi cell's face, Blender's Cell Fracture, a clean saw cut) leaves the same
polygon on both pieces. Laid face down on each other, two such facets agree along their whole
outline at one turn and one slide only; a facet of skin, or another cut, does not. The point-pair
votes see a flat facet as one plane, which fixes neither turn nor slide, and the patch starts
(centres face to face at `patch_turns` turns) rank the turns by the fracture sample, which a flat
cut read as skin does not hold. Here every flat region of either piece (faces joined across
edges flatter than `FLAT_DEG`), fracture or not, is a facet; each pair of facets of about one
area is registered in its plane by its outline, and the fits whose outlines agree within
`Params.facet_outline` are tried first.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from . import contour as contour_mod
from ..topology import components
from .seam import _frame

FLAT_DEG = 3.0  # a facet's faces meet at edges flatter than this
MIN_AREA = 0.01  # a facet's area at least this times the scale squared
MAX_BOW = 0.01  # ... its RMS distance to its plane at most this times the scale
AREA_RATIO = 0.5  # two facets laid together: the smaller at least this share of the larger
TURN_STEP_DEG = 2.0
REACH_SLACK = 3.0  # facets whose outlines' mean distances from their centres differ more than this
# times the outline bound are not turned (a bound, loose: the sampling of the two outlines differs)
OUTLINE_STEP = 0.01  # outline points this far apart (times the scale)
# a fit is ambiguous where the outlines agree at a turn over RIVAL_DEG away within RIVAL_RATIO
# times its distance, or RIVAL_GAP of the scale more
RIVAL_DEG = 10.0
RIVAL_RATIO = 2.0
RIVAL_GAP = 0.003


@dataclass(frozen=True, eq=False)
class Facet:
    """A flat region: its area-weighted centre, unit normal (outward), an in-plane
    frame (u, w) with u x w = normal, area, and its outline in that frame."""
    centre: np.ndarray  # (3,)
    normal: np.ndarray  # (3,)
    u: np.ndarray  # (3,)
    w: np.ndarray  # (3,)
    area: float
    outline: np.ndarray  # (K, 2) points along the region's boundary loops, in (u, w)

    @property
    def reach(self) -> float:
        """The outline's mean distance from the centre (the same at every turn)."""
        return float(np.mean(np.linalg.norm(self.outline, axis=1)))


def flat_facets(vertices: np.ndarray, faces: np.ndarray, seg, scale: float) -> list[Facet]:
    """The flat facets of a mesh, largest first.

    Parameters
    ----------
    vertices : (V, 3) float
    faces : (F, 3) int
    seg : the mesh's `segment.Segmentation` (normals, areas, topology, edge angles)
    scale : the working length
    """
    # faces joined across edges flatter than FLAT_DEG: a crease region can hold two cuts meeting at
    # a shallow angle, which no single outline describes
    region = components(len(faces), seg.topology.edge_faces[seg.edge_angle < FLAT_DEG])
    centres = vertices[faces].mean(axis=1)
    out = []
    for r in np.unique(region):
        m = region == r
        area = float(seg.areas[m].sum())
        if area < MIN_AREA * scale ** 2:
            continue
        c = (centres[m] * seg.areas[m, None]).sum(0) / area
        n = (seg.normals[m] * seg.areas[m, None]).sum(0)
        if np.linalg.norm(n) == 0:
            continue
        n /= np.linalg.norm(n)
        corners = vertices[np.unique(faces[m])]
        if np.sqrt(np.mean(((corners - c) @ n) ** 2)) > MAX_BOW * scale:
            continue
        loops = [contour_mod.resample_closed(vertices[loop], OUTLINE_STEP * scale)
                 for loop in contour_mod.region_boundary_loops(faces, m)]
        loops = [p for p in loops if len(p) >= 3]
        if not loops:
            continue
        pts = np.vstack(loops) - c
        u, w = _frame(n)
        out.append(Facet(c, n, u, w, area, np.c_[pts @ u, pts @ w]))
    return sorted(out, key=lambda f: -f.area)


def facet_fits(fa: list[Facet], fb: list[Facet], scale: float, max_outline: float,
               keep: int) -> list[tuple[float, np.ndarray]]:
    """Fits carrying b onto a that lay a facet of b face down on a facet of a of about its area,
    centres together, at the turn where their outlines agree best.

    Returns up to `keep` (outline distance over the scale, (4, 4) transform) with the distance at
    most `max_outline`, best first, leaving out fits whose outlines agree about as well at another
    turn (`RIVAL_DEG`, `RIVAL_RATIO`, `RIVAL_GAP`). The outline distance is the mean of the two
    ways' mean nearest-point distances in the common plane.
    """
    turns = np.radians(np.arange(0.0, 360.0, TURN_STEP_DEG))
    rot = np.stack([np.stack([np.cos(turns), -np.sin(turns)], -1), np.stack([np.sin(turns), np.cos(turns)], -1)], 1)
    fits = []
    reach_b = [Q.reach for Q in fb]
    for P in fa:
        tree, reach = None, P.reach
        for Q, reach_q in zip(fb, reach_b):
            # outlines that agree within d lie at mean distances from their centres within about d
            if (min(P.area, Q.area) < AREA_RATIO * max(P.area, Q.area)
                    or abs(reach - reach_q) > REACH_SLACK * max_outline * scale):
                continue
            if tree is None:
                tree = cKDTree(P.outline)
            # b's facet laid face down: its frame (u, w, n) becomes (u, -w, -n) in a's plane
            q = Q.outline * np.array([1.0, -1.0])
            moved = np.einsum("tij,kj->tki", rot, q)  # (T, K, 2)
            one_way = tree.query(moved.reshape(-1, 2))[0].reshape(len(turns), -1).mean(axis=1)
            best = np.argsort(one_way)[:3]
            both = [_both_ways(one_way, moved, P, t) for t in best]
            k = int(np.argmin(both))
            distance = both[k] / scale
            if distance > max_outline:
                continue
            # an outline that agrees as well at another turn (an ellipse, a square) fixes none
            apart = np.abs((turns - turns[best[k]] + np.pi) % (2 * np.pi) - np.pi) > np.radians(RIVAL_DEG)
            rival = int(np.flatnonzero(apart)[np.argmin(one_way[apart])])
            if _both_ways(one_way, moved, P, rival) / scale < max(RIVAL_RATIO * distance, distance + RIVAL_GAP):
                continue
            t = turns[best[k]]
            e1 = np.cos(t) * P.u + np.sin(t) * P.w
            e2 = np.sin(t) * P.u - np.cos(t) * P.w
            rotation = np.c_[e1, e2, -P.normal] @ np.c_[Q.u, Q.w, Q.normal].T
            transform = np.eye(4)
            transform[:3, :3] = rotation
            transform[:3, 3] = P.centre - rotation @ Q.centre
            fits.append((float(distance), transform))
    fits.sort(key=lambda f: f[0])
    return fits[:keep]


def _both_ways(one_way: np.ndarray, moved: np.ndarray, P: Facet, t: int) -> float:
    """The outline distance at turn t, given b's way (T,) at every turn and b's outline moved (T, K, 2)."""
    return 0.5 * (float(one_way[t]) + float(cKDTree(moved[t]).query(P.outline)[0].mean()))
