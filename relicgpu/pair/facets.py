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

A rescanned flat cut is flat only to within its noise: its faces meet at a few degrees, so its flat
components are crumbs, and a gently curved cut has none. `grown_facets` reads such a cut as the
faces grown from a seed face (largest first) while their normals stay within `GROW_DEG` of the
seed's and their centres within `GROW_GAP` of its plane; its fits, whose rounded outlines agree
less closely, are kept within `Params.grown_outline` and tried next.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree

from . import contour as contour_mod
from ..topology import components
from .seam import _frame

FLAT_DEG = 3.0  # a facet's faces meet at edges flatter than this
GROW_DEG = 10.0  # a grown facet's faces turn at most this far from its seed face's normal ...
GROW_GAP = 0.003  # ... and their centres lie within this of its plane (times the scale)
MIN_AREA = 0.01  # a facet's area at least this times the scale squared
MAX_BOW = 0.01  # ... its RMS distance to its plane at most this times the scale
AREA_RATIO = 0.5  # two facets laid together: the smaller at least this share of the larger
TURN_STEP_DEG = 2.0
COARSE = 3  # the turns are ranked at every third first, then beside the best
REACH_SLACK = 3.0  # facets whose outlines' mean distances from their centres differ more than this
# times the outline bound are not turned (a bound, loose: the sampling of the two outlines differs)
OUTLINE_STEP = 0.01  # outline points this far apart (times the scale)
FIELD_CELLS = 4  # the outline's distance field: nodes this many to an outline step
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
    step: float  # the outline's sampling step

    @cached_property
    def field(self) -> tuple[np.ndarray, np.ndarray, float]:
        """Distances to the outline on a grid around it: (lower corner (2,), (nx, ny) distances,
        node spacing). Exact at the nodes; read bilinearly between them (`_outline_distance`)."""
        h = self.step / FIELD_CELLS
        lo = self.outline.min(axis=0) - 2 * self.step
        n = np.ceil((self.outline.max(axis=0) + 2 * self.step - lo) / h).astype(int) + 1
        gx, gy = np.meshgrid(lo[0] + h * np.arange(n[0]), lo[1] + h * np.arange(n[1]), indexing="ij")
        d = cKDTree(self.outline).query(np.c_[gx.ravel(), gy.ravel()])[0]
        return lo, d.reshape(n).astype(np.float32), h

    @cached_property
    def radii(self) -> np.ndarray:
        """(K,) the outline's distances from the centre, ascending (the same at every turn)."""
        return np.sort(np.linalg.norm(self.outline, axis=1))

    @property
    def reach(self) -> float:
        """The outline's mean distance from the centre."""
        return float(self.radii.mean())

    @cached_property
    def tree(self) -> cKDTree:
        return cKDTree(self.outline)


def flat_facets(vertices: np.ndarray, faces: np.ndarray, seg, scale: float) -> list[Facet]:
    """The flat facets of a mesh (faces joined across edges flatter than `FLAT_DEG`), largest first.

    Parameters
    ----------
    vertices : (V, 3) float
    faces : (F, 3) int
    seg : the mesh's `segment.Segmentation` (normals, areas, topology, edge angles)
    scale : the working length
    """
    # a crease region can hold two cuts meeting at a shallow angle, which no single outline describes
    region = components(len(faces), seg.topology.edge_faces[seg.edge_angle < FLAT_DEG])
    return _facets(region, vertices, faces, seg, scale)


def grown_facets(vertices: np.ndarray, faces: np.ndarray, seg, scale: float) -> list[Facet]:
    """The near-flat facets of a mesh, largest first: from each face not yet taken, largest
    first, the faces reached across edges whose normals lie within `GROW_DEG` of the seed's and
    whose centres lie within `GROW_GAP` of its plane. Parameters as `flat_facets`."""
    centres = vertices[faces].mean(axis=1)
    turn, gap = np.cos(np.radians(GROW_DEG)), GROW_GAP * scale
    pairs = np.concatenate([seg.topology.edge_faces, seg.topology.edge_faces[:, ::-1]])
    s, t = pairs[np.argsort(pairs[:, 0], kind="stable")].T
    # the walk is sequential (each region takes its seed's plane), so it runs on Python lists:
    # numpy's per-call cost over thousands of small fronts was most of `prepare`'s time
    starts = np.searchsorted(s, np.arange(len(faces) + 1)).tolist()
    t, normals, centres_l = t.tolist(), seg.normals.tolist(), centres.tolist()
    region = [-1] * len(faces)
    for seed in np.argsort(-seg.areas, kind="stable").tolist():
        if region[seed] >= 0:
            continue
        region[seed] = seed
        nx, ny, nz = normals[seed]
        cx, cy, cz = centres_l[seed]
        stack = [seed]
        while stack:
            f = stack.pop()
            for g in t[starts[f]:starts[f + 1]]:
                if region[g] < 0:
                    mx, my, mz = normals[g]
                    px, py, pz = centres_l[g]
                    if (mx * nx + my * ny + mz * nz > turn
                            and abs((px - cx) * nx + (py - cy) * ny + (pz - cz) * nz) < gap):
                        region[g] = seed
                        stack.append(g)
    region = np.array(region)
    return _facets(region, vertices, faces, seg, scale)


def _facets(region: np.ndarray, vertices: np.ndarray, faces: np.ndarray, seg, scale: float) -> list[Facet]:
    """The facets of a (F,) labelling of the faces: the regions of at least MIN_AREA that bow at
    most MAX_BOW, with their outlines, largest first."""
    centres = vertices[faces].mean(axis=1)
    region = np.unique(region, return_inverse=True)[1]
    areas = np.bincount(region, weights=seg.areas)
    out = []
    for r in np.flatnonzero(areas >= MIN_AREA * scale ** 2):
        m = region == r
        area = float(seg.areas[m].sum())
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
        out.append(Facet(c, n, u, w, area, np.c_[pts @ u, pts @ w], OUTLINE_STEP * scale))
    return sorted(out, key=lambda f: -f.area)


# the last few fits asked for: `match_pair` asks again for every reading of the pair and every pick
# of its samples, and the facets are the same lists in each (`prepare(facets=, grown=)`)
_recent: dict = {}


def facet_fits(fa: list[Facet], fb: list[Facet], scale: float, max_outline: float,
               keep: int) -> list[tuple[float, np.ndarray]]:
    """Fits carrying b onto a that lay a facet of b face down on a facet of a of about its area,
    centres together, at the turn where their outlines agree best.

    Returns up to `keep` (outline distance over the scale, (4, 4) transform) with the distance at
    most `max_outline`, best first, leaving out fits whose outlines agree about as well at another
    turn (`RIVAL_DEG`, `RIVAL_RATIO`, `RIVAL_GAP`). The outline distance is the mean of the two
    ways' mean nearest-point distances in the common plane.
    """
    key = (id(fa), id(fb), scale, max_outline, keep)
    if key in _recent and _recent[key][0] is fa and _recent[key][1] is fb:
        return list(_recent[key][2])
    turns = np.radians(np.arange(0.0, 360.0, TURN_STEP_DEG))
    spin = np.exp(1j * turns)
    fits = []
    for P in fa:
        for Q in fb:
            # outlines that agree within d lie at mean distances from their centres within about
            # d, and a point's distance to an outline is at least its radius's distance to the
            # outline's radii: the outline distance at every turn is at least the mean such gap
            if (min(P.area, Q.area) < AREA_RATIO * max(P.area, Q.area)
                    or abs(P.reach - Q.reach) > REACH_SLACK * max_outline * scale
                    or 0.5 * (_radial_gap(P.radii, Q.radii) + _radial_gap(Q.radii, P.radii)) > max_outline * scale):
                continue
            # b's facet laid face down: its frame (u, w, n) becomes (u, -w, -n) in a's plane
            moved = np.outer(spin, Q.outline[:, 0] - 1j * Q.outline[:, 1])  # (T, K)
            # b's way, read from a's distance field, at every COARSE-th turn and then at the turns
            # beside the best few ranks the turns; the best three are measured exactly both ways
            one_way = np.full(len(turns), np.inf)
            one_way[::COARSE] = _outline_distance(P, moved[::COARSE]).mean(axis=1)
            near = (np.argsort(one_way)[:3, None] + np.arange(1 - COARSE, COARSE)) % len(turns)
            near = np.unique(near[np.isinf(one_way[near])])
            one_way[near] = _outline_distance(P, moved[near]).mean(axis=1)
            best = np.argsort(one_way)[:3]
            # read bilinearly, a field is within h / sqrt(2) of the exact distance (a lower bound
            # beyond the field): no turn here is within max_outline
            slack = (P.field[2] + Q.field[2]) / (2 * np.sqrt(2))
            if _field_both_ways(moved, P, Q, spin, best).min() - slack > max_outline * scale:
                continue
            both = [_both_ways(moved, P, t) for t in best]
            k = int(np.argmin(both))
            distance = both[k] / scale
            if distance > max_outline:
                continue
            # an outline that agrees as well at another turn (an ellipse, a square) fixes none
            apart = np.abs((turns - turns[best[k]] + np.pi) % (2 * np.pi) - np.pi) > np.radians(RIVAL_DEG)
            rival = int(np.flatnonzero(apart)[np.argmin(one_way[apart])])
            if _both_ways(moved, P, rival) / scale < max(RIVAL_RATIO * distance, distance + RIVAL_GAP):
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
    while len(_recent) >= 4:
        _recent.pop(next(iter(_recent)))
    _recent[key] = (fa, fb, fits[:keep])
    return fits[:keep]


def _outline_distance(P: Facet, z: np.ndarray) -> np.ndarray:
    """Distances from points z (complex, any shape) in P's plane to P's outline: its distance field
    read bilinearly; beyond the field, a lower bound (the way to the field's edge, which is farther
    from the outline than that, and the edge's distance less that way)."""
    lo, d, h = P.field
    x, y = (z.real - lo[0]) / h, (z.imag - lo[1]) / h
    cx, cy = np.clip(x, 0, d.shape[0] - 1), np.clip(y, 0, d.shape[1] - 1)
    ix, iy = np.minimum(cx.astype(int), d.shape[0] - 2), np.minimum(cy.astype(int), d.shape[1] - 2)
    fx, fy = cx - ix, cy - iy
    near = ((d[ix, iy] * (1 - fx) + d[ix + 1, iy] * fx) * (1 - fy)
            + (d[ix, iy + 1] * (1 - fx) + d[ix + 1, iy + 1] * fx) * fy)
    out = h * np.hypot(x - cx, y - cy)
    return np.maximum(near - out, out)


def _field_both_ways(moved: np.ndarray, P: Facet, Q: Facet, spin: np.ndarray, t: np.ndarray) -> np.ndarray:
    """`_both_ways` at turns t (m,) read from the two distance fields: a's outline carried into b's
    frame is conj(p) * spin at the turn's spin, as b's (u, -w) turned by spin lands in a's."""
    back = np.conj(P.outline[:, 0] + 1j * P.outline[:, 1])[None, :] * spin[t, None]
    return 0.5 * (_outline_distance(P, moved[t]).mean(axis=1) + _outline_distance(Q, back).mean(axis=1))


def _radial_gap(r: np.ndarray, s: np.ndarray) -> float:
    """The mean over radii r of the distance to the nearest of the ascending radii s."""
    i = np.clip(np.searchsorted(s, r), 1, len(s) - 1)
    return float(np.minimum(np.abs(r - s[i - 1]), np.abs(r - s[i])).mean())


def _both_ways(moved: np.ndarray, P: Facet, t: int) -> float:
    """The outline distance at turn t (exact, nearest points both ways), b's outline moved (T, K) complex."""
    q = np.c_[moved[t].real, moved[t].imag]
    return 0.5 * (float(P.tree.query(q)[0].mean()) + float(cKDTree(q).query(P.outline)[0].mean()))
