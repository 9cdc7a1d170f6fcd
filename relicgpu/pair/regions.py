"""The crease partition and its region cues (steps 1-2 of relicgpu.pair.segment_cues):
regions bounded by creases, per-region scale-free cues, and the turn across region boundaries."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..topology import Topology, components, merge_small, ring_average

# Pieces that are nearly all fracture (`skin_from_seeds`): chosen on corpus voronoi/rough/smooth (8 pieces,
# seeds 0-2, 1500 faces), synth 10-piece breaks (seeds 0-1) and inner cells of a box cut by 12 random
# planes (seeds 0-59, the 33 with no box face left), the Blender sets held out. Cut facets are exact
# planes (a region: one facet, or a few met at a shallow angle; patch cover 0.96-1.00 on the cells); a
# curved or scanned skin is not (cover 0 where it is curved); a rounded block's faces and a jar's flat
# bottom are exact planes too (cover 0.95-1.00): the block's are found by the box cue.
PLANE_EDGE_DEG = 0.05  # faces meeting flatter than this (degrees) are one exact planar patch ...
PLANE_PATCH_SHARE = 0.05  # ... counted where it holds at least this share of its region's area ...
PLANE_PATCH_FACES = 3  # ... and this many faces (a coarse curved skin's quads are two coplanar triangles) ...
PLANE_COVER = 0.95  # ... and a region is made of exact planes where such patches cover this share of it (0.98: 29 of 33 cells)

CUE_NAMES = ("log_share", "largest", "log_rough_ratio", "log_width_edges", "log_width_size", "log_unflatness",
             "rim_sharp_share", "rim_mean_angle")


def smoothed_edge_angles(normals: np.ndarray, areas: np.ndarray, topo: Topology, rings: int = 1) -> np.ndarray:
    """Angle (degrees) between the ring-averaged normals of the two faces of each interior edge.

    Parameters
    ----------
    normals : (F, 3) unit face normals
    areas : (F,) face areas
    topo : the mesh's `Topology`
    rings : edge steps averaged over

    Returns
    -------
    (E,) degrees
    """
    n = ring_average(normals, areas, topo.edge_faces, rings)
    n /= np.maximum(np.linalg.norm(n, axis=1), 1e-12)[:, None]
    e0, e1 = topo.edge_faces[:, 0], topo.edge_faces[:, 1]
    return np.degrees(np.arccos(np.clip(np.einsum("ed,ed->e", n[e0], n[e1]), -1, 1)))


def crease_regions(normals: np.ndarray, areas: np.ndarray, topo: Topology, edge_angle: np.ndarray,
                   crease_deg: float = 35.0, smooth_crease_deg: float = 10.0, flat_deg: float = 2.0,
                   min_faces: int = 3, wide_rings: int = 2, wide_crease_deg: float = 10.0,
                   dense_faces: int = 1000, coarse_crease_deg: float = 30.0) -> np.ndarray:
    """Regions of faces between creases.

    Parameters
    ----------
    normals : (F, 3) unit face normals
    areas : (F,) face areas
    topo : the mesh's `Topology`
    edge_angle : (E,) degrees, normal angle of each interior edge
    crease_deg : an edge sharper than this is a crease
    smooth_crease_deg : ... as is one whose 1-ring smoothed normals turn by more (rounded creases) ...
    flat_deg : ... unless the edge itself is flatter than this
    min_faces : smaller regions join the neighbour they share most edges with
    wide_rings, wide_crease_deg : on meshes of at least `dense_faces` faces an edge whose
        `wide_rings`-ring smoothed normals turn by more is a crease too: a smoothing reconstruction
        rounds a crease over more faces than one ring sees (corpus smooth-noisy: the whole piece
        was one region)
    coarse_crease_deg : on meshes of fewer faces (coarse, CAD-like) a crease is an edge sharper than
        this, and the smoothed normals are not used: a coarse skin's facets turn by 15-30 degrees
        each, so every skin edge looked like a rounded crease (a coarse sphere fell apart into
        facets); corpus rough-coarse / smooth-coarse regions recall and precision went from
        0.78 / 0.52 and 0.56 / 0.56 to 0.90 / 0.86 and 0.68 / 0.93 (25: 0.80 / 0.94 on smooth-coarse,
        20: 0.79 / 0.47 on rough-coarse; 30 kept off that edge)

    Returns
    -------
    (F,) int64 region id per face, 0..R-1
    """
    smooth = smoothed_edge_angles(normals, areas, topo)
    if len(areas) >= dense_faces:
        smooth = np.maximum(smooth, smoothed_edge_angles(normals, areas, topo, wide_rings)
                            * (smooth_crease_deg / wide_crease_deg))
    else:  # coarse: the facets themselves turn by more than a rounded crease's faces do
        smooth = np.zeros_like(smooth)
        crease_deg = coarse_crease_deg
    keep = (edge_angle < crease_deg) & ((smooth < smooth_crease_deg) | (edge_angle < flat_deg))
    region = components(len(areas), topo.edge_faces[keep])
    return merge_small(region, topo.edge_faces, min_faces)


@dataclass(frozen=True)
class RegionCues:
    """Scale-free cues per region (rows follow region ids); `values[:, k]` is `CUE_NAMES[k]`."""
    values: np.ndarray  # (R, len(CUE_NAMES)) float
    area: np.ndarray  # (R,) region areas
    roughness_deg: np.ndarray  # (R,) area-weighted mean angle between a face's normal and its 1-ring's
    plane_cover: np.ndarray | None = None  # (R,) area share in exact planar patches (`PLANE_EDGE_DEG`, `PLANE_PATCH_SHARE`)
    normal: np.ndarray | None = None  # (R, 3) unit normal of each region's largest exact planar patch

    def exact_plane(self) -> np.ndarray:
        """(R,) bool: regions made of a few exact planes (`PLANE_COVER`), as a computed cut is (one
        facet, or a few met at a shallow angle) and a scanned or curved skin is not."""
        if self.plane_cover is None:
            return np.zeros(len(self.area), bool)
        return self.plane_cover >= PLANE_COVER

    def rough_ratio(self, ref: int, floor_deg: float) -> np.ndarray:
        """(R,) roughness relative to region `ref`'s (the noise floor), that taken at least `floor_deg`."""
        return (self.roughness_deg + 0.01) / max(float(self.roughness_deg[ref]), floor_deg)


def region_cues(vertices: np.ndarray, normals: np.ndarray, areas: np.ndarray, topo: Topology,
                edge_angle: np.ndarray, region: np.ndarray, crease_deg: float = 35.0) -> RegionCues:
    """The cues of the module docstring for every region of a partition.

    Parameters
    ----------
    vertices : (V, 3)
    normals : (F, 3) unit face normals
    areas : (F,) face areas
    topo : the mesh's `Topology`
    edge_angle : (E,) degrees
    region : (F,) int region id per face, 0..R-1
    crease_deg : rim edges sharper than this count as sharp

    Returns
    -------
    RegionCues
    """
    n_reg = int(region.max()) + 1
    e0, e1 = topo.edge_faces[:, 0], topo.edge_faces[:, 1]
    r0, r1 = region[e0], region[e1]
    inside = r0 == r1
    v = np.asarray(vertices, np.float64)
    edge_len = np.linalg.norm(v[topo.edge_vertices[:, 0]] - v[topo.edge_vertices[:, 1]], axis=1)
    h = float(np.median(edge_len)) if len(edge_len) else 1.0
    size = float(np.linalg.norm(v.max(0) - v.min(0)))
    area = np.bincount(region, weights=areas, minlength=n_reg)
    skin = int(np.argmax(area))
    rough = _region_roughness(normals, areas, topo.edge_faces[inside], region, area)
    largest = np.zeros(n_reg)
    largest[skin] = 1
    rim_len, rim_sharp, rim_angle = _rim_sums(r0[~inside], r1[~inside], edge_len[~inside], edge_angle[~inside],
                                              crease_deg, n_reg)
    width = 2 * area / np.maximum(rim_len, 1e-12)
    mean_normal = np.stack([np.bincount(region, weights=areas * normals[:, k], minlength=n_reg) for k in range(3)], 1)
    flatness = np.linalg.norm(mean_normal, axis=1) / np.maximum(area, 1e-300)
    values = np.stack([
        np.log(area / max(area.sum(), 1e-300) + 1e-6), largest,
        np.log((rough + 0.01) / max(rough[skin], 0.05)),
        np.log(width / h + 1e-3), np.log(width / max(size, 1e-12) + 1e-6),
        np.log(1 - np.minimum(flatness, 1) + 1e-4),
        rim_sharp / np.maximum(rim_len, 1e-12), rim_angle / np.maximum(rim_len, 1e-12)], 1)
    # exact planar patches: faces joined across edges flatter than PLANE_EDGE_DEG inside the region
    patch = components(len(areas), topo.edge_faces[inside & (edge_angle < PLANE_EDGE_DEG)])
    patch_area = np.bincount(patch, weights=areas)
    big = (patch_area[patch] >= PLANE_PATCH_SHARE * area[region]) & (np.bincount(patch)[patch] >= PLANE_PATCH_FACES)
    cover = np.bincount(region, weights=areas * big, minlength=n_reg) / np.maximum(area, 1e-300)
    # each region's main plane: the normal of its largest patch (a rounded rim tilts the mean normal)
    main = np.full(n_reg, -1)
    order = np.argsort(patch_area[patch], kind="stable")
    main[region[order]] = order  # the last write per region is a face of its largest patch
    return RegionCues(values, area, rough, cover, normals[main])


def _region_roughness(normals, areas, inside_edges, region, region_area) -> np.ndarray:
    """(R,) area-weighted mean angle (degrees) between a face's normal and its 1-ring mean normal,
    the ring taken inside the region (a crease at its rim is not roughness)."""
    mean = ring_average(normals, areas, inside_edges, 1)
    mean /= np.maximum(np.linalg.norm(mean, axis=1), 1e-12)[:, None]
    angle = np.degrees(np.arccos(np.clip(np.einsum("fd,fd->f", mean, normals), -1, 1)))
    return np.bincount(region, weights=areas * angle, minlength=len(region_area)) / np.maximum(region_area, 1e-300)


def _rim_sums(ra, rb, length, angle, crease_deg, n_reg):
    """Per region: rim length, length of its sharp part, and the length-weighted sum of rim angles."""
    both = np.concatenate([ra, rb])

    def total(w):
        return np.bincount(both, weights=np.concatenate([w, w]), minlength=n_reg)
    return total(length), total(length * (angle > crease_deg)), total(length * angle)


def boundary_turn(normals: np.ndarray, areas: np.ndarray, topo: Topology, region: np.ndarray,
                  rings: int = 3) -> np.ndarray:
    """Turn (degrees) across each interior edge between normals averaged within each side's own region.

    The average spans `rings` edge steps, a band a few edge lengths wide: a crease rounded by a
    rescan turns by its full angle across it, a crease-detector split of a smooth skin only by the
    skin's curvature and noise at that width.

    Parameters
    ----------
    normals : (F, 3) unit face normals
    areas : (F,) face areas
    topo : the mesh's `Topology`
    region : (F,) int region id per face
    rings : edge steps averaged over on each side

    Returns
    -------
    (E,) degrees; 0 inside a region
    """
    e0, e1 = topo.edge_faces[:, 0], topo.edge_faces[:, 1]
    side = ring_average(normals, areas, topo.edge_faces[region[e0] == region[e1]], rings)
    side /= np.maximum(np.linalg.norm(side, axis=1), 1e-12)[:, None]
    turn = np.degrees(np.arccos(np.clip(np.einsum("ed,ed->e", side[e0], side[e1]), -1, 1)))
    return np.where(region[e0] == region[e1], 0.0, turn)


def _pair_medians(region, topo, values):
    """(P, 2) neighbouring region pairs (low id first) and the (P,) median of `values` over their shared edges."""
    ra, rb = region[topo.edge_faces[:, 0]], region[topo.edge_faces[:, 1]]
    cross = ra != rb
    if not cross.any():  # one region (a closed surface without creases): no pairs
        return np.zeros((0, 2), np.int64), np.zeros(0)
    lo, hi, val = np.minimum(ra, rb)[cross], np.maximum(ra, rb)[cross], values[cross]
    order = np.lexsort((val, hi, lo))
    lo, hi, val = lo[order], hi[order], val[order]
    start = np.flatnonzero(np.concatenate([[True], (lo[1:] != lo[:-1]) | (hi[1:] != hi[:-1])]))
    count = np.diff(np.concatenate([start, [len(lo)]]))
    median = 0.5 * (val[start + (count - 1) // 2] + val[start + count // 2])
    return np.stack([lo[start], hi[start]], 1), median
