"""Segmentation of a fragment into fracture and original surface regions (Alg. 2, section 3.7.2).

The paper grows regions across edges whose face normals differ less than a
threshold, merges tiny regions into their neighbours and calls a region fracture
when its normal perturbation is large. Where a cut meets the original surface at
a shallow angle there is no crease to stop the growth, so here the normal
perturbation comes first: (1) per face, the angle between its normal and the
mean normal of its one-ring, averaged over a few rings (the surface's roughness
at the scale of its triangles), says fracture above a threshold; (2) regions grow
over edges between faces of the same class whose normal angle (the kernel) is
below the crease angle; (3) tiny regions merge into the neighbour they share most
edges with; a region's class is the area-weighted majority of its faces. A rough
fracture surface can break into several regions at its own sharp edges, so
neighbouring fracture regions are joined into one fracture patch, whose boundary
loops are the contours.

`Params.segmentation` picks how faces are classed: "roughness" (the above), "regions" (crease
regions and their shape, `segment_cues`), "union" (a face either calls fracture) or "hybrid" (the
union, less the pieces only the roughness vote calls fracture that are not well above the mesh's
own noise floor; crease regions alone on coarse meshes and where a thin wall's ends decide them).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..params import Params
from .segment_cues import cue_labels
from ..topology import Topology, components, merge_small, mesh_topology, otsu_split, ring_average, weighted_quantile


# "hybrid" (see _hybrid_labels): chosen on synth and corpus rough-*/smooth-*, voronoi-*, vessel-* and
# the Blender sets held out (docs/benchmarks.md, "Segmentation that holds on more families")
HYBRID_RATIO = 4.0  # a piece only the roughness vote calls fracture must be this many times the noise floor
HYBRID_FLOOR_DEG = 0.05  # the noise floor taken at least this (degrees)
# ... unless, its roughness measured with the rings kept inside it, it is smoother than this share of
# the floor and has at least this many faces (smaller pieces have too few neighbours inside): chosen
# on corpus vessel-clean, rough-clean/-noisy, smooth-noisy and synth (seeds 0-1), voronoi-* and the
# Blender sets held out; only-rough pieces of 10+ faces measured 0.00-0.03 of the floor on vessel
# bottoms, 0.6 and more on the rest
HYBRID_OWN_RATIO = 0.25
HYBRID_OWN_MIN_FACES = 20
HYBRID_MIN_FACES = 1000  # meshes with fewer faces (coarse, CAD-like) use the crease regions alone: a
# ring-averaged roughness there measures the facets' curvature, not the surface's roughness


@dataclass(frozen=True)
class Segmentation:
    face_region: np.ndarray  # (F,) int fracture patch / original region id per face
    region_is_fracture: np.ndarray  # (R,) bool
    face_facet: np.ndarray  # (F,) int region id before neighbouring fracture regions are joined
    face_roughness: np.ndarray  # (F,) degrees, normal perturbation
    face_fracture_prob: np.ndarray  # (F,) in [0, 1], > 0.5 exactly on fracture faces: its facet's share of faces
    # voted fracture (segmentation "roughness"), or the facet's cue likelihood ("regions", segment_cues)
    edge_angle: np.ndarray  # (E,) degrees, normal angle of each interior edge
    normals: np.ndarray  # (F,3)
    areas: np.ndarray  # (F,)
    topology: Topology

    @property
    def fracture_faces(self) -> np.ndarray:
        return self.region_is_fracture[self.face_region]


def face_roughness(normals: np.ndarray, areas: np.ndarray, edge_faces: np.ndarray, rings: int,
                   k: int = 1) -> np.ndarray:
    """Normal perturbation per face (degrees): the angle between a face's normal and the mean
    normal of its one-ring, averaged over the faces within `rings` edge-steps. At k edges' length
    (k > 1): the normal averaged over k - 1 rings against the one over 2k - 1, averaged over
    k * rings."""
    def unit(x):
        length = np.linalg.norm(x, axis=1)
        return x / np.where(length > 0, length, 1)[:, None]

    near = normals if k == 1 else unit(ring_average(normals, areas, edge_faces, k - 1))
    wide = unit(ring_average(normals, areas, edge_faces, 2 * k - 1))
    angle = np.degrees(np.arccos(np.clip(np.einsum("fd,fd->f", wide, near), -1, 1)))
    return ring_average(angle, areas, edge_faces, k * rings)


# The smoothest SMOOTHEST_SHARE of a mesh's area reading rougher than NOISY_FLOOR times the roughness
# floor (Params.roughness_threshold_deg) means noise dominates the normals at the mesh's resolution.
# Area quantiles at 0.2 on the fine scale: synth's noisy slabs and torsos at 20,000-42,000 faces a
# piece 2.7-3.7 deg; at 2,000-8,000 faces (where k = 1 anyway) 1.1-2.5; the real tombstone scans
# (30,000-40,000 faces) 0.4-0.7, corpus families 0.2-2.4.
SMOOTHEST_SHARE = 0.2
NOISY_FLOOR = 0.9


def working_roughness(v: np.ndarray, f: np.ndarray, normals: np.ndarray, areas: np.ndarray,
                      smooth_edges: np.ndarray, params: Params, scale: float) -> np.ndarray:
    """(F,) roughness of a mesh's (V, 3) vertices and (F, 3) faces: `face_roughness`, unless the
    mesh's median edge is shorter than params.roughness_spacing * scale and its smoothest area
    reads rough (SMOOTHEST_SHARE, NOISY_FLOOR). Then it is measured at that length: with k = the
    length over the median edge, rounded, each face's normal averaged over k - 1 rings is compared
    with the one averaged over 2k - 1 rings, and the angle averaged over k * params.roughness_rings
    rings. (F, 3) normals, (F,) areas and (E, 2) smooth_edges are the mesh's own.

    A face's normal perturbation is a slope at the scale of its edges, and a scanner's noise, a
    fixed length, tilts short edges more: on a 23,000-face synth slab piece with noise 0.05% of the
    size the skin read as fracture (precision 0.56-0.60; 0.97 without the noise). But a real break
    may be rough only at that fine scale: the tombstone scans' breaks, measured at the working
    length, all fell under the floor. So the coarse measure is kept for meshes whose smoothest
    part is itself rough: noise, not a break, is everywhere."""
    fine = face_roughness(normals, areas, smooth_edges, params.roughness_rings)
    edges = np.linalg.norm(v[f[:, [1, 2, 0]]] - v[f], axis=2)
    k = int(round(params.roughness_spacing * scale / max(float(np.median(edges)), 1e-300))) if len(f) else 1
    if k <= 1 or weighted_quantile(fine, areas, SMOOTHEST_SHARE) <= NOISY_FLOOR * params.roughness_threshold_deg:
        return fine
    return face_roughness(normals, areas, smooth_edges, params.roughness_rings, k)


def roughness_threshold(rough: np.ndarray, areas: np.ndarray, params: Params) -> float:
    """Fracture above this roughness: Otsu's split of the area-weighted log roughness (the
    smooth original surface and the rough fracture form two modes), never below the fixed floor.

    A fixed share of the smoothest surface as the noise floor failed on pieces that are mostly
    fracture (inner pieces of a 10-piece break: 50-86%), where that share is fracture too."""
    if len(rough) < 2 or areas.sum() <= 0:
        return params.roughness_threshold_deg
    return max(params.roughness_threshold_deg, float(np.exp(otsu_split(np.log(np.maximum(rough, 1e-3)), areas))))


def segment(vertices: np.ndarray, faces: np.ndarray, params: Params, scale: float, backend) -> Segmentation:
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    topo = mesh_topology(f)
    normals, areas = backend.face_normals(v, f)
    normals = np.asarray(normals, np.float64)
    areas = np.asarray(areas, np.float64)
    angle = np.degrees(np.asarray(backend.edge_angles(normals, topo.edge_faces), np.float64))

    smooth_edges = topo.edge_faces[angle < params.crease_angle_deg]
    rough = working_roughness(v, f, normals, areas, smooth_edges, params, scale)
    region, region_prob = _labels(params.segmentation, v, f, normals, areas, topo, angle, rough, params)
    region_is_fracture = region_prob > 0.5
    e0, e1 = topo.edge_faces[:, 0], topo.edge_faces[:, 1]
    # Neighbouring fracture regions form one fracture patch (one set of contours).
    fracture = region_is_fracture[region]
    same = (region[e0] == region[e1]) | (fracture[e0] & fracture[e1])
    patch = components(len(f), topo.edge_faces[same])
    patch_is_fracture = np.zeros(int(patch.max()) + 1, bool)
    patch_is_fracture[patch[fracture]] = True
    return Segmentation(patch, patch_is_fracture, region, rough, region_prob[region], angle, normals, areas, topo)


def _labels(method: str, v, f, normals, areas, topo, angle, rough, params):
    """Regions (F,) int and their fracture likelihood (R,) by `Params.segmentation`'s method."""
    if method == "regions":
        return cue_labels(v, f, normals, areas, topo, angle, params)
    if method == "hybrid":
        if len(f) < HYBRID_MIN_FACES:  # coarse: no neighbourhoods to measure roughness on
            return _labels("regions", v, f, normals, areas, topo, angle, rough, params)
        *regions, ends, lips = cue_labels(v, f, normals, areas, topo, angle, params, details=True)
        if ends:  # a thin wall's ends, rounded by a rescan: the roughness vote measures their curvature
            return tuple(regions)
        return _hybrid_labels(_labels("roughness", v, f, normals, areas, topo, angle, rough, params), tuple(regions),
                              rough, areas, topo.edge_faces,
                              (normals, angle < params.crease_angle_deg, params.roughness_rings), lips)
    if method == "roughness":
        return _roughness_labels(rough, areas, topo, angle, params)
    if method == "union":
        return _union_labels(*(_labels(m, v, f, normals, areas, topo, angle, rough, params)
                               for m in ("roughness", "regions")), topo.edge_faces)
    raise ValueError(f"unknown segmentation {method!r}")


def _union_labels(first: tuple, second: tuple, edge_faces: np.ndarray,
                  split: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Two segmentations' (regions (F,), likelihoods (R,)) overlaid: regions are the connected
    pieces where both agree (and `split`, (F,), is the same), a piece's likelihood the larger of its
    two (a face either method calls fracture is a candidate; matching weighs it by its likelihood,
    verification decides)."""
    (r1, p1), (r2, p2) = first, second
    same = (r1[edge_faces[:, 0]] == r1[edge_faces[:, 1]]) & (r2[edge_faces[:, 0]] == r2[edge_faces[:, 1]])
    if split is not None:
        same &= split[edge_faces[:, 0]] == split[edge_faces[:, 1]]
    region = components(len(r1), edge_faces[same])
    prob = np.zeros(int(region.max()) + 1)
    prob[region] = np.maximum(p1[r1], p2[r2])
    return region, prob


def _hybrid_labels(first: tuple, second: tuple, rough: np.ndarray, areas: np.ndarray,
                   edge_faces: np.ndarray, own: tuple | None = None,
                   lips: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The roughness vote's and the crease regions' (regions (F,), likelihoods (R,)) overlaid as
    in `_union_labels`, except that a piece only the roughness vote calls fracture keeps the
    crease regions' (low) likelihood unless it is at least `HYBRID_RATIO` times rougher than the
    noise floor, the area-weighted median roughness of the faces both call skin.

    Otsu's split always finds two classes: on a bumpy scanned skin, or a curved one (synth's
    torso), its upper class is skin a little rougher than the rest; a true rough break stands well
    above the floor (synth at noise 0: 2.6-12x on vase and torso pieces, 58-75x on slabs).

    `own` = (normals (F, 3), smooth (E,) bool edges below the crease angle, rings): a piece of at
    least `HYBRID_OWN_MIN_FACES` faces whose roughness, measured with the rings kept inside it, is
    below `HYBRID_OWN_RATIO` times the floor keeps the crease regions' likelihood too. The rings of
    `rough` reach over gentle creases: a vessel's flat bottom took the curvature of the wall it meets
    (4.0-4.3x the floor on corpus vessel-clean) though flat. `lips` (F,) bool: a piece mostly of a
    thin wall's lip faces (`segment_cues.wall_end_labels`) keeps it too: the vote measures a rounded
    lip's curvature as roughness.
    Returns (F,) int64 pieces, (P,) likelihoods."""
    (r1, p1), (r2, p2) = first, second
    region, prob = _union_labels(first, second, edge_faces, lips)
    both_skin = (p1[r1] <= 0.5) & (p2[r2] <= 0.5)
    floor = HYBRID_FLOOR_DEG
    if both_skin.any():
        floor = max(float(weighted_quantile(rough[both_skin], areas[both_skin], 0.5)), HYBRID_FLOOR_DEG)
    n = int(region.max()) + 1
    mean_rough = np.bincount(region, weights=areas * rough, minlength=n) / np.maximum(
        np.bincount(region, weights=areas, minlength=n), 1e-300)
    only_rough = np.zeros(n, bool)
    only_rough[region] = (p2[r2] <= 0.5) & (p1[r1] > 0.5)
    if own is not None and only_rough.any():
        normals, smooth, rings = own
        e0, e1 = edge_faces[:, 0], edge_faces[:, 1]
        inside = face_roughness(normals, areas, edge_faces[smooth & (region[e0] == region[e1])], rings)
        own_rough = np.bincount(region, weights=areas * inside, minlength=n) / np.maximum(
            np.bincount(region, weights=areas, minlength=n), 1e-300)
        big = np.bincount(region, minlength=n) >= HYBRID_OWN_MIN_FACES
        mean_rough = np.where(big & (own_rough < HYBRID_OWN_RATIO * floor), 0.0, mean_rough)
    if lips is not None:
        lip_share = np.bincount(region, weights=areas * lips, minlength=n) / np.maximum(
            np.bincount(region, weights=areas, minlength=n), 1e-300)
        mean_rough = np.where(lip_share > 0.5, 0.0, mean_rough)
    regions_prob = np.zeros(n)
    regions_prob[region] = p2[r2]
    return region, np.where(only_rough & (mean_rough < HYBRID_RATIO * floor), regions_prob, prob)


def _roughness_labels(rough, areas, topo, angle, params):
    """Regions and their fracture likelihood from the roughness: Otsu's split, a vote of the faces
    around, regions grown over same-class edges below the crease angle, small ones merged; a
    region's likelihood is the area share of its faces voted fracture. Returns (F,) region, (R,) share."""
    smooth_edges = topo.edge_faces[angle < params.crease_angle_deg]
    is_fracture = rough > roughness_threshold(rough, areas, params)
    # a vote of the faces around: single rough faces on a smooth surface (and the reverse) flip
    is_fracture = ring_average(is_fracture.astype(np.float64), areas, smooth_edges, params.vote_rings) > 0.5
    e0, e1 = topo.edge_faces[:, 0], topo.edge_faces[:, 1]
    joins = (is_fracture[e0] == is_fracture[e1]) & (angle < params.crease_angle_deg)
    region = components(len(areas), topo.edge_faces[joins])
    region = merge_small(region, topo.edge_faces, max(params.min_region_faces, int(params.min_region_share * len(areas))))
    n_regions = int(region.max()) + 1
    frac_area = np.bincount(region, weights=areas * is_fracture, minlength=n_regions)
    all_area = np.bincount(region, weights=areas, minlength=n_regions)
    return region, frac_area / np.where(all_area > 0, all_area, 1)
