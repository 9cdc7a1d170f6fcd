"""Verification of a candidate fit (new; the paper returns its fit unchecked).

A fit is accepted only when the two fracture surfaces really touch over a real
share of their area (overlap), closely (RMS residual over the contact), and
neither fragment's surface dips into the other's solid (interpenetration, with
the sign taken from the nearest vertex normal of the other fragment).

Two more checks (issue 16 item 3) separate right fits from wrong ones on fractures of other
generators, where a wrong fit lays a flat skin against a flat break, or skin against skin:
touching surfaces must face each other (`facing_share`), and no surface may sink into the
other's solid, the contact zone included (`surface_penetration`). `fit_cues` measures these and
the other cues tried (scripts/bench_verify.py; docs/benchmarks.md has the figures).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .icp import apply
from .revolution import Axis


@dataclass(frozen=True)
class Verification:
    overlap: float  # share of the smaller fracture sample in contact
    rmse: float  # RMS distance over contact points (absolute units)
    penetration: float  # share of surface samples deeper than the tolerance inside the other fragment
    accepted: bool
    reason: str
    facing: float = 1.0  # share of the surfaces' contact points whose outward normals face each other


@dataclass(frozen=True)
class SurfaceSample:
    """Points of a fragment used by ICP and verification."""
    fracture: np.ndarray  # (P,3) points on fracture surfaces
    fracture_region: np.ndarray  # (P,) the fracture patch of each of those points
    fracture_normals: np.ndarray  # (P,3) outward unit normals there
    surface: np.ndarray  # (Q,3) points of the whole surface
    normals: np.ndarray  # (Q,3) outward unit normals at `surface`
    fracture_plane_normals: np.ndarray | None = None  # (P,3) normals of local plane fits at `fracture`
    fracture_weight: np.ndarray | None = None  # (P,) fracture likelihood in (0, 1] matching weighs by; None: 1
    creases: np.ndarray | None = None  # (K,3) points along the mesh's sharp edges (`rim_agreement`); None: clouds
    outline: np.ndarray | None = None  # (K,3) points where the surface turns at a working length
    # (`prepare.outline_points`); None: clouds
    wall: float = np.inf  # the wall's thickness relative to the piece's size where it is a shell
    # (`walls.wall_thickness`), else inf
    axis: Axis | None = None  # the skin's axis of revolution (`revolution.skin_axis`), else None
    # (Q',3) points and normals on which another surface's points near it read their side of this
    # one (`surface_penetration`): a coarse mesh's vertices and points inside its large faces; None: `surface`
    sides: tuple[np.ndarray, np.ndarray] | None = None
    surface_weight: np.ndarray | None = None  # (Q,) fracture likelihood at `surface` (meshes); None: clouds

    def weights(self) -> np.ndarray:
        """(P,) weight of each fracture point: `fracture_weight`, or 1 where none was given (clouds)."""
        return np.ones(len(self.fracture)) if self.fracture_weight is None else self.fracture_weight

    def side_sample(self) -> tuple[np.ndarray, np.ndarray]:
        """(Q',3) points and their (Q',3) outward normals to read a side on: `sides`, else `surface`."""
        return self.sides if self.sides is not None else (self.surface, self.normals)


def side_of(points: np.ndarray, surface: np.ndarray, normals: np.ndarray, index_of) -> tuple[np.ndarray, np.ndarray]:
    """(N,) signed distance of each of (N,3) points along the outward normal (M,3) of the nearest
    of (M,3) `surface` points (negative: inside), and (N,) the distance to that point."""
    idx, dist = index_of(surface).query(points)
    idx = np.asarray(idx, np.int64)
    return np.einsum("ij,ij->i", points - surface[idx], normals[idx]), np.asarray(dist)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray, face_normals: np.ndarray, areas: np.ndarray) -> np.ndarray:
    n = np.zeros_like(vertices)
    weighted = face_normals * areas[:, None]
    for c in range(3):
        np.add.at(n, faces[:, c], weighted)
    length = np.linalg.norm(n, axis=1)
    return n / np.where(length > 0, length, 1)[:, None]


def verify(a: SurfaceSample, b: SurfaceSample, transform: np.ndarray, backend, contact: float,
           max_rmse: float, min_overlap: float, depth: float, max_penetration: float | None,
           index_of=None, mutual: bool = False, min_facing: float = 0.0,
           max_surface_penetration: float = 1.0) -> Verification:
    """Check b moved by `transform` against a (all lengths absolute).

    The overlap is the larger of the two fracture samples' shares in contact (a partial contact
    covers a part of one side), or with `mutual` the smaller (both sides must touch: fracture
    samples picked from a sparse cloud's roughness hold skin, which a wrong fit can put on a
    strip of the other's fracture).

    index_of: optional function from one of the samples' point arrays to its nearest-neighbour
    index (kept by a caller that verifies several transforms of one pair); every query here
    goes to a's or b's own, unmoved, points.

    min_facing: the least share of the surfaces' contact points whose outward normals face each
    other (`facing_share`); touching pieces meet face to face, a wrong fit puts one piece's skin
    along the other's from behind or side by side (0: not checked).

    max_surface_penetration: the largest share of either surface sample deeper than `depth`
    inside the other anywhere within 3 depths of it, the contact zone included
    (`surface_penetration`; 1: not checked). `max_penetration` leaves the contact zone out, so
    a wrong fit that sinks one fracture surface into the other's solid passes it; None: not
    measured (the result's penetration is NaN; clouds measure theirs their own way)."""
    if index_of is None:
        index_of = backend.nearest_index
    inv = np.linalg.inv(transform)
    b_frac = apply(transform, b.fracture)
    i_ba, d_ba = index_of(a.fracture).query(b_frac)
    i_ab, d_ab = index_of(b.fracture).query(apply(inv, a.fracture))  # distances and pairs as in a's frame
    d_ba, d_ab = np.asarray(d_ba, np.float64), np.asarray(d_ab, np.float64)
    in_b, in_a = d_ba < contact, d_ab < contact
    overlap = float((min if mutual else max)(in_b.mean(), in_a.mean()))
    # residual: distance to the other surface's tangent plane (two samplings of one surface
    # never share points, so point-to-point distances would measure the sampling, not the fit)
    plane_b = np.einsum("ij,ij->i", b_frac - a.fracture[np.asarray(i_ba)], a.fracture_normals[np.asarray(i_ba)])
    b_normals = b.fracture_normals @ transform[:3, :3].T
    plane_a = np.einsum("ij,ij->i", a.fracture - b_frac[np.asarray(i_ab)], b_normals[np.asarray(i_ab)])
    both = np.concatenate([plane_b[in_b], plane_a[in_a]])
    rmse = float(np.sqrt(np.mean(both ** 2))) if len(both) else float("inf")

    penetration = float("nan")
    if max_penetration is not None:
        pen_b = _inside_share(apply(transform, b.surface), a, depth, contact, index_of)
        # a's surface in b's frame is the same check with b fixed
        pen_a = _inside_share(apply(inv, a.surface), b, depth, contact, index_of)
        penetration = float(max(pen_a, pen_b))
    facing = facing_share(a, b, transform, contact, index_of) if min_facing > 0 else 1.0
    sunk = surface_penetration(a, b, transform, depth, index_of) if max_surface_penetration < 1.0 else 0.0

    if overlap < min_overlap:
        return Verification(overlap, rmse, penetration, False, f"overlap {overlap:.2f} below {min_overlap:.2f}", facing)
    if rmse > max_rmse:
        return Verification(overlap, rmse, penetration, False, f"residual {rmse:.4g} above {max_rmse:.4g}", facing)
    if max_penetration is not None and penetration > max_penetration:
        return Verification(overlap, rmse, penetration, False,
                            f"interpenetration {penetration:.3f} above {max_penetration:.3f}", facing)
    if facing < min_facing:
        return Verification(overlap, rmse, penetration, False, f"facing {facing:.2f} below {min_facing:.2f}", facing)
    if sunk > max_surface_penetration:
        return Verification(overlap, rmse, penetration, False,
                            f"surfaces sunk into each other {sunk:.3f} above {max_surface_penetration:.3f}", facing)
    return Verification(overlap, rmse, penetration, True, "accepted", facing)


def _inside_share(points: np.ndarray, other: SurfaceSample, depth: float, contact: float, index_of) -> float:
    """Share of `points` (outside the contact zone) lying deeper than `depth` behind the nearest
    surface point of `other`, by that point's outward normal, and where `other` has sides
    (`SurfaceSample.sides`) behind the nearest of those too."""
    if len(points) == 0:
        return 0.0
    if len(other.fracture):
        _, d = index_of(other.fracture).query(points)
        points = points[np.asarray(d) > 2 * contact]  # the contact zone touches by design
        if len(points) == 0:
            return 0.0
    # inside where the vertices and, on a coarse mesh, the sides (`side_sample`) both say so: beside
    # a coarse corner the nearest vertex's normal, the mean of the faces meeting there, reads the
    # neighbourhood as inside (corpus voronoi-clean and tetra-clean decimated: right fits refused);
    # at up to 8 depths the points inside a coarse mesh's faces read a thin wall's far face (corpus
    # vessel-coarse seed 1, 5 pieces, pieces 3-4 at their true pose: 0.15 inside instead of 0.02)
    signed, dist = side_of(points, other.surface, other.normals, index_of)
    # far from the other surface the nearest normal says nothing about inside or outside
    inside = (signed < -depth) & (dist < 8 * depth)
    if other.sides is not None and inside.any():
        signed, dist = side_of(points[inside], *other.sides, index_of)
        inside[inside] = (signed < -depth) & (dist < 8 * depth)
    return float(np.sum(inside)) / len(points)


def surface_penetration(a: SurfaceSample, b: SurfaceSample, transform: np.ndarray, depth: float, index_of) -> float:
    """The larger share of either surface sample (b's moved by `transform`) lying deeper than
    `depth` behind the nearest surface point of the other, by that point's outward normal,
    counting only points within 3 depths of it (farther, the nearest normal says little)."""
    def one_way(points, other):
        signed, dist = side_of(points, *other.side_sample(), index_of)
        return float(np.mean((signed < -depth) & (dist < 3 * depth))) if len(points) else 0.0

    return max(one_way(apply(transform, b.surface), a), one_way(apply(np.linalg.inv(transform), a.surface), b))


def facing_share(a: SurfaceSample, b: SurfaceSample, transform: np.ndarray, contact: float, index_of) -> float:
    """Share of b's surface points (moved by `transform`) within `contact` of a's surface whose
    outward normal is opposed to that of the nearest point of a (cosine below -0.5); 1 where
    the surfaces do not touch (the overlap check speaks then)."""
    idx, dist = index_of(a.surface).query(apply(transform, b.surface))
    touching = np.asarray(dist) < contact
    if not touching.any():
        return 1.0
    cos = np.einsum("ij,ij->i", (b.normals @ transform[:3, :3].T)[touching], a.normals[np.asarray(idx)[touching]])
    return float(np.mean(cos < -0.5))


def sample_spacing(points: np.ndarray) -> float:
    """Median distance from each of (N, 3) points to its nearest other one (0 under two points)."""
    if len(points) < 2:
        return 0.0
    from scipy.spatial import cKDTree

    return float(np.median(cKDTree(points).query(points, k=2)[0][:, 1]))


def in_contact(moved: np.ndarray, dist: np.ndarray, idx: np.ndarray, target: np.ndarray,
               target_normals: np.ndarray | None, contact: float, reach: float) -> np.ndarray:
    """(...,) bool: moved points (..., 3) that lie on the target surface, given the distance (...)
    and index (...) of their nearest target point (M, 3): nearer than `contact`, or, where
    `target_normals` (M, 3) are given, nearer than `reach` and within `contact` of that point's
    tangent plane.

    Two samplings of one surface never share points: where the target's spacing exceeds
    `contact` (a flat break decimated to large triangles, a sparse sample) a point lying on the
    surface between samples is farther than `contact` from every one, and point distances alone
    count the sampling, not the contact (reach: the target's spacing)."""
    near = dist < contact
    if target_normals is None or reach <= contact:
        return near
    plane = np.abs(np.einsum("...d,...d->...", moved - target[idx], target_normals[idx]))
    return near | ((dist < reach) & (plane < contact))


def index_cache(backend):
    """A function from a point array to its nearest-neighbour index on `backend`, each built once
    (the `index_of` the checks here take)."""
    indexes: dict = {}  # keyed by id, the array kept alive beside its index

    def index_of(points: np.ndarray):
        if id(points) not in indexes:
            indexes[id(points)] = (points, backend.nearest_index(points))
        return indexes[id(points)][1]
    return index_of


def rim_agreement(a: SurfaceSample, b: SurfaceSample, transform: np.ndarray, contact: float, index_of) -> float:
    """How well the sharp creases of the two surfaces coincide where they touch (b moved by
    `transform`): crease points lying on the other surface (`icp.in_contact`) that also lie on
    one of its creases, less those that do not, over all crease points of both; 0 where neither
    sample has creases.

    Two pieces meet over a shared break whose outline is a crease on both: at the right fit
    their rims coincide. A wrong fit that lays a break on a flat skin face, or a break turned on
    its partner, puts one piece's rim across the middle of the other's face."""
    if a.creases is None or b.creases is None or not (len(a.creases) and len(b.creases)):
        return 0.0

    def signed(points, other: SurfaceSample) -> float:
        idx, dist = index_of(other.surface).query(points)
        on = in_contact(points, np.asarray(dist), np.asarray(idx, np.int64), other.surface, other.normals, contact,
                        sample_spacing(other.surface))
        _, gap = index_of(other.creases).query(points[on])
        matched = int(np.sum(np.asarray(gap) < max(contact, sample_spacing(other.creases))))
        return 2 * matched - int(on.sum())

    total = signed(apply(transform, b.creases), a) + signed(apply(np.linalg.inv(transform), a.creases), b)
    return total / (len(a.creases) + len(b.creases))


def surface_weights(sample: SurfaceSample, reach: float, index_of) -> np.ndarray:
    """(Q,) fracture likelihood at each of the sample's surface points: that of the nearest
    fracture point where one lies within `reach`, else 0 (skin)."""
    if len(sample.fracture) < 2:
        return np.zeros(len(sample.surface))
    from scipy.spatial import cKDTree

    # the fracture sample is sparser than the surface's where it covers much: reach its spacing
    spacing = float(np.median(cKDTree(sample.fracture).query(sample.fracture, k=2)[0][:, 1]))
    idx, d = index_of(sample.fracture).query(sample.surface)
    near = np.asarray(d) < max(reach, 1.5 * spacing)
    return np.where(near, sample.weights()[np.asarray(idx, np.int64)], 0.0)


def fit_cues(a: SurfaceSample, b: SurfaceSample, transform: np.ndarray, backend, contact: float, depth: float,
             index_of=None) -> dict:
    """Every measured cue of a fit (b moved by `transform` onto a), for choosing thresholds
    (scripts/bench_verify.py); lengths absolute, shares in [0, 1]."""
    if index_of is None:
        index_of = backend.nearest_index
    inv = np.linalg.inv(transform)
    out = {}
    # fracture samples in contact: plain and weighted by the likelihood, each side
    b_frac = apply(transform, b.fracture)
    i_ba, d_ba = index_of(a.fracture).query(b_frac)
    i_ab, d_ab = index_of(b.fracture).query(apply(inv, a.fracture))
    in_b, in_a = np.asarray(d_ba) < contact, np.asarray(d_ab) < contact
    wa, wb = a.weights(), b.weights()
    out["overlap_a"], out["overlap_b"] = float(in_a.mean()), float(in_b.mean())
    out["woverlap_a"] = float((wa * in_a).sum() / max(wa.sum(), 1e-12))
    out["woverlap_b"] = float((wb * in_b).sum() / max(wb.sum(), 1e-12))
    # likelihood of the contact on both sides (skin on fracture scores low)
    pair_w = np.concatenate([np.minimum(wb[in_b], wa[np.asarray(i_ba)[in_b]]),
                             np.minimum(wa[in_a], wb[np.asarray(i_ab)[in_a]])])
    out["contact_likelihood"] = float(pair_w.mean()) if len(pair_w) else 0.0
    # whole surfaces: touching, facing, skin against skin, interpenetration everywhere
    reach = 2 * contact
    sw_a, sw_b = surface_weights(a, reach, index_of), surface_weights(b, reach, index_of)
    b_surf = apply(transform, b.surface)
    idx, dist = index_of(a.surface).query(b_surf)
    idx, dist = np.asarray(idx, np.int64), np.asarray(dist)
    touch = dist < contact
    out["touch_b"] = float(touch.mean())
    b_n = b.normals @ transform[:3, :3].T
    cos = np.einsum("ij,ij->i", b_n[touch], a.normals[idx[touch]])
    out["facing"] = float(np.mean(cos < -0.5)) if touch.any() else 1.0
    out["skin_touch"] = float(np.mean(np.maximum(sw_b[touch], sw_a[idx[touch]]) < 0.2)) if touch.any() else 0.0
    out["skin_touch_b"] = float(np.sum(touch & (np.maximum(sw_b, sw_a[idx]) < 0.2)) / len(touch))
    out["pen_all"] = surface_penetration(a, b, transform, depth, index_of)
    out["pen_any"] = float(max(_inside_share(b_surf, a, depth, contact, index_of),
                               _inside_share(apply(inv, a.surface), b, depth, contact, index_of)))
    return out
