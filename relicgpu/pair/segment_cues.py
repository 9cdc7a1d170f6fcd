"""Fracture segmentation from region cues (issue 16, item 2): `segment` with `Params.segmentation
== "regions"` (`cue_labels`); the default is still the roughness vote, which is better on synth.

A fracture face is one that is not part of the original skin. Roughness alone fails on smooth or
flat breaks and on bumpy scanned skins, so the skin is found from the shape of the regions between
creases:

1. `crease_regions` splits the mesh at creases; `region_cues` describes each region.
2. `boundary_turn`: the turn across each region boundary between normals averaged a few rings into
   each side. `skin_from_seeds` grows the skin from the largest regions over boundaries gentler
   than `region_merge_deg` + `region_merge_noise` x the seed's roughness (the mesh's own noise),
   keeping the seed that grows most, a lone sharp-rimmed seed (a cut) discounted. A skin of exact
   planes (computed cuts: an inner Voronoi cell) is redone: a box's square faces, else the regions
   that are not exact planes (and caps square to them), else none (all fracture). docs/benchmarks.md,
   "Pieces that are nearly all fracture".
3. `region_fracture_prob`: regions outside the grown skin are fracture (bounded by creases too
   sharp to grow over), unless curved and as smooth as the skin (a vessel's inner face), or as
   smooth as the skin where the break is evidently rough (a slab's other sides), or, on a thin
   wall (`wall_thickness`), smooth and wider than a few walls (a vessel's bottom), or a lip: a long
   planar band curving within its plane (`band_shape`, `LIP_*`). Grown regions are fracture where
   the break is evidently rough and they are too. Logistic steps make it a graded likelihood,
   > 0.5 exactly on the fracture.
4. `wall_end_labels` (dense thin walls): where a rescan rounded the wall's ends so that the crease
   regions miss them, the fracture is the wall's ends (faces turned across the wall's axis,
   `wall_end_alignment`) less the lips (`end_lips`); where the crease regions cover the ends they
   stay, less regions mostly of lip faces. docs/benchmarks.md, "Vessels: lips and breaks".

Measured (scripts/bench_segment.py; thresholds fitted with corpus smooth-noisy, vessel-coarse and
the Blender cylinder held out) in the commit message that introduced the "regions" method.

The pieces:

crease partition (`crease_regions`)
    regions bounded by creases. A crease is an edge whose normal angle is sharp (> `crease_deg`),
    or whose 1-ring smoothed normals turn by more than `smooth_crease_deg` while the edge itself is
    not flat: a noisy rescan rounds a crease over a few faces, none of which is sharp alone; a
    coarse CAD strip across a thin wall is flat inside and must not be split by the smoothing.
    Measured upper bound (every region given its majority truth label; /tmp data of 146 pieces):
    area recall / precision 0.94-1.00 / 0.92-1.00 on the corpus's rough, smooth and voronoi
    families, 0.98 / 0.99 vessel clean and coarse, 0.69 / 0.96 vessel noisy (rounded wall bands
    merge into the skin), 0.97 / 1.00 Blender cube, 0.85-0.96 / 0.99 synth.
region cues (`region_cues`)
    per region, scale-free: area share, roughness relative to the largest region's (the skin's
    noise floor, estimated from the mesh itself), mean width (2 area / rim length) in edge lengths
    and in object sizes (a cut through a thin wall is a band one wall thick), flatness (length of
    the area-weighted mean normal: planar cuts are 1), and the share of the rim that is a sharp
    crease (fracture regions are bounded by sharp creases all round; skin regions meet each other
    through smooth transitions too).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..params import Params
from .topology import components, merge_small, ring_average, Topology, weighted_quantile

# Where the break is rough, regions at least this much (log units) smoother than the area-weighted
# median of the rough regions are skin too (`region_fracture_prob`): chosen on synth slabs and
# corpus rough-*/smooth-*, with voronoi-*, vessel-* and the Blender sets held out.
MODE_GAP = 1.0
# On a thin wall, a region outside the grown skin is a lip (where the wall ends on the original
# object, `region_fracture_prob`) when it is a long, planar band whose centre line curves within its
# plane; chosen on corpus vessel-clean / vessel-coarse (seeds 0-3) with voronoi-* and the Blender
# sets held out: lips measured length 12-46 walls, bend 1.7-34 walls, plane RMS 0.000-0.019 walls;
# break regions that long were 0.066-1.5 walls off their plane, or straight (bend 0.85-1.1 walls).
LIP_LENGTH_WALLS = 10.0  # a lip is longer than this many walls along its main axis ...
LIP_BEND_WALLS = 1.4  # ... curves by more than this many walls across it (a flat cut along a straight wall does not) ...
LIP_FLAT_WALLS = 0.03  # ... and its face centres lie within this many walls (RMS) of one plane
# Wall ends (`wall_end_labels`, dense thin walls): chosen on corpus vessel-noisy and vessel-clean
# (seeds 0-3), voronoi-* and the Blender sets held out. Face-level recall / precision of "end faces
# less lips" on vessel-noisy: 0.885 / 0.809 (the crease regions: 0.61 / 0.59); WALL_END_ALIGN 0.8:
# 0.856 / 0.825, 0.85: 0.901 / 0.796, 0.9: 0.942 / 0.744 (the skin faces it adds lie within a wall
# of the break: its labels' own blur)
WALL_END_MIN_FACES = 1000  # meshes with fewer faces (coarse) keep the crease regions alone
WALL_END_RADIUS = 5.0  # the wall's axis is taken over faces within this many walls ...
WALL_END_NEIGHBOURS = 64  # ... at most this many
WALL_END_ALIGN = 0.83  # a face is on the wall's end where |cos| between its normal and the wall's axis is below this
LIP_CORE_ALIGN = 0.8  # lips are found among the faces below this (a wider set breaks their planar runs) ...
LIP_GROW_RINGS = 5  # ... and grown this many edge steps through the wall's ends (their rounded rims)
WALL_END_SOFTNESS = 0.05  # width of the logistic step on that |cos|
END_FLAT_RADIUS = 4.0  # an end face is locally planar when the end faces within this many walls ...
END_FLAT_WALLS = 0.15  # ... lie within this many walls (RMS) of one plane; runs of such faces are lips when
END_LIP_LENGTH_WALLS = 15.0  # ... longer than this many walls (noisy lips 20-34, breaks' planar runs up to 16.5) ...
END_LIP_BEND_WALLS = 2.5  # ... curved by more than this many walls (lips 4-16, breaks up to 2.3) ...
END_LIP_FLAT_WALLS = 0.1  # ... and within this many walls of one plane (noisy lips 0.02-0.1)
WALL_END_COVERED = 0.72  # the crease regions are kept where their fracture covers this share of the ends

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
NONPLANAR_MIN_SHARE = 0.01  # a skin of exact planes is grown again from regions that are not, of at least this area share
BOX_MIN_SHARE = 0.05  # exact planes of at least this share that meet another at a right angle or face opposite ways ...
BOX_DEG = 0.1  # ... within this many degrees (a CAD box: exactly; 0.5: 2 of 33 cells called boxes) are a box's skin faces
# A cap (`square_caps`): chosen on Voronoi cells of a 64-sided cylinder (12 cells, seeds 0-2, built in
# /tmp; the Blender cylinder held out): with the side reseeded, caps were fracture on 9 of 36 pieces, mean precision 0.866; with this 0.932
CAP_DEG = 1.0  # an exact plane is square to a skin face when their normals are within this of 90 degrees ...
CAP_SHARE = 0.9  # ... and a cap when so on this share of the skin faces along its shared rim ...
CAP_MIN_EDGES = 3  # ... of at least this many edges

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


def grow_skin(region: np.ndarray, topo: Topology, turn: np.ndarray, seed: int, rough_ratio: np.ndarray,
              merge_deg: float, rough_max: float, relay: np.ndarray | None = None) -> np.ndarray:
    """The skin: the largest region, grown over neighbours that meet it gently and are no rougher.

    Grown from the skin outwards (never fracture to fracture first), and only through `relay`
    regions (large ones): a sliver on a rounded crease turns by half the crease to either side and
    would otherwise chain the fracture beyond it into the skin.

    Parameters
    ----------
    region : (F,) int region id per face, 0..R-1
    topo : the mesh's `Topology`
    turn : (E,) degrees, `boundary_turn`
    seed : the region grown from (the largest)
    rough_ratio : (R,) roughness relative to the seed's
    merge_deg : a neighbour joins when their shared boundary turns by less (median)
    rough_max : ... and its roughness ratio is below this
    relay : (R,) bool, regions that pass the growth on (default all)

    Returns
    -------
    (R,) bool, regions of the skin
    """
    pair, median = _pair_medians(region, topo, turn)
    skin = np.zeros(int(region.max()) + 1, bool)
    skin[seed] = True
    relay = np.ones(len(skin), bool) if relay is None else relay.copy()
    relay[seed] = True
    gentle = pair[(median < merge_deg) & (rough_ratio[pair].max(1) < rough_max)]
    for _ in range(len(skin)):
        front = skin & relay
        grow = np.concatenate([gentle[front[gentle[:, 0]] & ~skin[gentle[:, 1]], 1],
                               gentle[front[gentle[:, 1]] & ~skin[gentle[:, 0]], 0]])
        if not len(grow):
            break
        skin[grow] = True
    return skin


def skin_from_seeds(region: np.ndarray, topo: Topology, turn: np.ndarray, cues: RegionCues, params: Params,
                    seeds: int = 4, normals: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """The skin grown (`grow_skin`) from whichever of the largest regions grows the most area.

    The largest single region is not always skin: on a coarse CAD mesh one planar cut can outweigh
    each of the skin's facets, which are joined only by gentle turns. A seed bounded by sharp
    creases all round that grows over no large region (what a cut looks like) counts only
    `region_isolated_weight` of its area. The merge threshold is
    `region_merge_deg` plus `region_merge_noise` times the seed's roughness (the mesh's own noise floor).

    Where the skin so chosen is all exact planes (`RegionCues.exact_plane`: computed cuts, such
    as a Voronoi cell's facets), the skin is the piece's large exact planes that meet another at a
    right angle or face opposite ways (`box_facets`: a box's faces, a rounded block's) and what they
    grow over; where there are none, it is grown again from the largest regions that are not exact
    planes (at least `NONPLANAR_MIN_SHARE` of the area: a scanned or curved skin), and exact planes
    that meet that skin square all along their shared rim join it (`square_caps`, with `normals`:
    a cylinder's cap); where there are none either, the piece is all fracture (an empty skin: an
    inner cell of a many-piece break).

    Parameters
    ----------
    region : (F,) int region id per face, 0..R-1
    topo : the mesh's `Topology`
    turn : (E,) degrees, `boundary_turn`
    cues : the partition's `RegionCues`
    params : `Params`, its region_* fields
    seeds : at most this many seeds tried, largest first
    normals : (F, 3) unit face normals, or None (no caps joined)

    Returns
    -------
    skin : (R,) bool, possibly empty
    seed : the region the skin grew from (the largest region where the skin is empty)
    """
    share = cues.area / max(cues.area.sum(), 1e-300)
    relay = share >= params.region_relay_share
    order = np.argsort(-share)
    best, best_seed = _best_seed(region, topo, turn, cues, params, order[:seeds], relay)
    plane = cues.exact_plane()
    if not plane[best].all():
        return best, best_seed
    box = box_facets(cues, plane)
    if box.any():  # a box's faces and what they grow over (a rounded box's edges)
        skin = box.copy()
        for seed in np.flatnonzero(box):
            merge_deg = params.region_merge_deg + params.region_merge_noise * cues.roughness_deg[seed]
            skin |= grow_skin(region, topo, turn, int(seed), cues.rough_ratio(seed, params.region_noise_floor_deg),
                              merge_deg, params.region_rough_max, relay)
        return skin, int(np.flatnonzero(box)[np.argmax(share[box])])
    other = np.flatnonzero(~plane & (share >= NONPLANAR_MIN_SHARE))
    if len(other):
        skin, seed = _best_seed(region, topo, turn, cues, params, other[np.argsort(-share[other])][:seeds], relay)
        if normals is not None:
            skin |= square_caps(region, topo, normals, cues, skin, plane)
        return skin, seed
    return np.zeros(len(share), bool), int(order[0])


def square_caps(region: np.ndarray, topo: Topology, normals: np.ndarray, cues: RegionCues, skin: np.ndarray,
                plane: np.ndarray) -> np.ndarray:
    """(R,) bool: exact planes outside `skin` whose main normal is square (within `CAP_DEG`) to the
    normals of the skin faces along their shared rim, on at least `CAP_SHARE` of those faces: a
    cylinder's or prism's cap meets its side so; a cut meets the skin at a slant (square only where it
    passes through the axis)."""
    e0, e1 = topo.edge_faces[:, 0], topo.edge_faces[:, 1]
    r0, r1 = region[e0], region[e1]
    out = np.zeros(len(skin), bool)
    if cues.normal is None:
        return out
    cand = plane & ~skin
    pairs = [(r0[m], e1[m]) for m in [cand[r0] & skin[r1]]] + [(r1[m], e0[m]) for m in [cand[r1] & skin[r0]]]
    reg = np.concatenate([p[0] for p in pairs])
    face = np.concatenate([p[1] for p in pairs])
    if not len(reg):
        return out
    square = np.abs(np.einsum("kd,kd->k", normals[face], cues.normal[reg])) < np.sin(np.radians(CAP_DEG))
    n_all = np.bincount(reg, minlength=len(skin))
    n_square = np.bincount(reg, weights=square, minlength=len(skin))
    return (n_all >= CAP_MIN_EDGES) & (n_square >= CAP_SHARE * np.maximum(n_all, 1))


def _best_seed(region, topo, turn, cues, params, candidates, relay) -> tuple[np.ndarray, int]:
    """`skin_from_seeds`' choice among `candidates` (region ids, largest first; after the first, only
    relay regions): the grown skin (R,) bool of most (discounted) area and its seed."""
    share = cues.area / max(cues.area.sum(), 1e-300)
    sharp_all_round = cues.values[:, CUE_NAMES.index("rim_sharp_share")] >= params.region_sharp_rim
    best, best_seed, best_score = None, int(candidates[0]), -1.0
    for seed in candidates:
        if seed != candidates[0] and not relay[seed]:
            break
        merge_deg = params.region_merge_deg + params.region_merge_noise * cues.roughness_deg[seed]
        rough = cues.rough_ratio(seed, params.region_noise_floor_deg)
        skin = grow_skin(region, topo, turn, int(seed), rough, merge_deg, params.region_rough_max, relay)
        score = cues.area[skin].sum()
        if sharp_all_round[seed] and share[skin].sum() < share[seed] + params.region_relay_share:
            # grew over nothing large: a cut looks like this, a facet of the skin rarely
            score *= params.region_isolated_weight
        if score > best_score:
            best, best_seed, best_score = skin, int(seed), float(score)
    return best, best_seed


def box_facets(cues: RegionCues, plane: np.ndarray) -> np.ndarray:
    """(R,) bool: exactly planar regions of at least `BOX_MIN_SHARE` of the area that meet another
    such at a right angle or face opposite ways, within `BOX_DEG`: a box's faces do, a Voronoi
    cell's facets rarely (they meet at random angles)."""
    share = cues.area / max(cues.area.sum(), 1e-300)
    out = np.zeros(len(share), bool)
    idx = np.flatnonzero(plane & (share >= BOX_MIN_SHARE))
    if len(idx) < 2 or cues.normal is None:
        return out
    cos = cues.normal[idx] @ cues.normal[idx].T
    tol = np.sin(np.radians(BOX_DEG))
    out[idx] = ((np.abs(cos) < tol) | (cos < -np.cos(np.radians(BOX_DEG)))).any(1)
    return out


def region_fracture_prob(cues: RegionCues, skin: np.ndarray, seed: int, params: Params,
                         wall: float = np.inf, band: np.ndarray | None = None) -> np.ndarray:
    """Fracture likelihood per region in [0, 1] (> 0.5: fracture) from the grown skin and the cues.

    Parameters
    ----------
    cues : the partition's `RegionCues`
    skin : (R,) bool, the grown skin (`skin_from_seeds`)
    seed : its seed region
    wall : the wall's thickness relative to the size (`wall_thickness`): on a thin wall the
        fracture is a band about one wall wide, and wider flat regions are skin (a vessel's bottom)
    band : (R, 3) `band_shape` relative to the same size, or None: on a thin wall a long planar band
        whose centre line curves within its plane is a lip, skin (`LIP_*`); a break through the
        wall is a band too, but rough (off any one plane) or, where flat, cut along a straight wall
    params : `Params`, its region_* fields: outside the grown skin, regions are skin when curved and
        as smooth as the skin (a vessel's inner face), or, where the break is evidently rough, when
        as smooth as the skin or `MODE_GAP` smoother than the rough regions (a slab's other sides,
        its sharp-edged rims); the rest is fracture (bounded by creases
        too sharp to grow over)

    Returns
    -------
    (R,) float
    """
    rough = np.log(cues.rough_ratio(seed, params.region_noise_floor_deg))

    def step(x):
        return 1.0 / (1.0 + np.exp(-np.clip(x / params.region_softness, -50, 50)))

    def cue(name):
        return cues.values[:, CUE_NAMES.index(name)]
    rest = ~skin
    rough_share = cues.area[rest & (rough > params.region_context_rough)].sum() / max(cues.area[rest].sum(), 1e-300)
    rough_break = step(np.log((rough_share + 1e-6) / params.region_context_share))
    smooth = step(params.region_curved_rough - rough)
    curved = step(cue("log_unflatness") - params.region_curved_unflatness) * smooth
    # where the break is rough, a region nearer (in log roughness) the skin than the break's typical
    # roughness is skin: a slab's sharp-edged sides are a little rougher than its faces, far smoother than a cut
    broken = rest & (rough > params.region_context_rough)
    mode = float(weighted_quantile(rough[broken], cues.area[broken], 0.5)) if broken.any() else 0.0
    other_side = rough_break * step(max(params.region_context_smooth, mode - MODE_GAP) - rough)
    thin = float(wall < params.region_thin_wall)
    wide = thin * step(cue("log_width_size") - np.log(params.region_band_walls * wall + 1e-6)) * smooth
    lip = np.zeros_like(wide)
    if band is not None and thin:
        def log_walls(x):
            return np.log(np.maximum(x, 1e-9) / max(wall, 1e-12))
        lip = (step(log_walls(band[:, 0]) - np.log(LIP_LENGTH_WALLS))
               * step(log_walls(band[:, 1]) - np.log(LIP_BEND_WALLS))
               * step(np.log(LIP_FLAT_WALLS) - log_walls(band[:, 2])))
    prob = 1.0 - np.max([curved, other_side, wide, lip], axis=0)
    # grown skin: below 0.5, nearer it the rougher the region is than the seed; fracture where the
    # break is evidently rough and the region is too (a rough cut met at a shallow angle)
    grown = np.maximum(0.5 * step(rough - params.region_curved_rough),
                       rough_break * step(rough - params.region_grown_rough))
    return np.where(skin, grown, prob)


def cue_labels(vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray, areas: np.ndarray, topo: Topology,
               edge_angle: np.ndarray, params: Params, details: bool = False) -> tuple:
    """Crease regions and their fracture likelihood (`Params.segmentation == "regions"`).

    Parameters
    ----------
    vertices : (V, 3)
    faces : (F, 3) int
    normals : (F, 3) unit face normals
    areas : (F,) face areas
    topo : the mesh's `Topology`
    edge_angle : (E,) degrees
    params : `Params`
    details : also return whether the wall's ends decided (`wall_end_labels`) and the lip faces

    Returns
    -------
    region : (F,) int64 region id per face, 0..R-1
    prob : (R,) fracture likelihood in [0, 1] (> 0.5: fracture)
    ends : bool, only with `details`: the labels are the wall's ends less lips, not the crease regions'
    lips : (F,) bool or None (not a dense thin wall), only with `details`: faces of the wall's lips
    """
    region = crease_regions(normals, areas, topo, edge_angle)
    cues = region_cues(vertices, normals, areas, topo, edge_angle, region)
    turn = boundary_turn(normals, areas, topo, region)
    skin, seed = skin_from_seeds(region, topo, turn, cues, params, normals=normals)
    centers = np.asarray(vertices, np.float64)[faces].mean(1)
    wall = wall_thickness(centers, normals, areas, skin[region])
    band = None
    if np.isfinite(wall):
        size = float(np.linalg.norm(centers.max(0) - centers.min(0)))  # as `wall_thickness` measures it
        band = band_shape(centers, areas, region) / max(size, 1e-300)
    prob = region_fracture_prob(cues, skin, seed, params, wall, band)
    ends, lips = False, None
    if wall < params.region_thin_wall and len(faces) >= WALL_END_MIN_FACES:
        size = float(np.linalg.norm(centers.max(0) - centers.min(0)))
        region, prob, lips, ends = wall_end_labels(centers, normals, areas, topo, region, prob, wall * size)
    return (region, prob, ends, lips) if details else (region, prob)


def wall_end_alignment(centers: np.ndarray, normals: np.ndarray, areas: np.ndarray, wall: float) -> np.ndarray:
    """(F,) |cos| between each face's normal and the wall's axis around it: the dominant direction
    (principal eigenvector of the area-weighted sum of n n^T) of the normals of the faces within
    `WALL_END_RADIUS` walls (at most `WALL_END_NEIGHBOURS`). On a thin wall both skins' normals lie
    along that axis (|cos| near 1); the wall's end, a lip or a break, turns across it (near 0).
    `wall` is in object units."""
    k = min(WALL_END_NEIGHBOURS, len(centers))
    dist, near = cKDTree(centers).query(centers, k=k, distance_upper_bound=WALL_END_RADIUS * wall)
    ok = np.isfinite(dist)
    near = np.where(ok, near, np.arange(len(centers))[:, None])
    w = np.where(ok, areas[near], 0.0)
    nn = normals[near]  # (F, k, 3)
    m = np.einsum("fk,fki,fkj->fij", w, nn, nn)
    _, vec = np.linalg.eigh(m)
    return np.abs(np.einsum("fd,fd->f", normals, vec[:, :, 2]))


def end_lips(centers: np.ndarray, areas: np.ndarray, topo: Topology, end: np.ndarray, wall: float) -> np.ndarray:
    """(F,) bool, the end faces that belong to a lip: runs (edge-connected) of end faces that are
    locally planar (`END_FLAT_*`) and, as a whole, long, curved within their plane and flat
    (`END_LIP_*`, `band_shape`). `wall` is in object units."""
    lip = np.zeros(len(centers), bool)
    idx = np.flatnonzero(end)
    if len(idx) < 3:
        return lip
    c, a = centers[idx], areas[idx]
    k = min(32, len(idx))
    dist, near = cKDTree(c).query(c, k=k, distance_upper_bound=END_FLAT_RADIUS * wall)
    ok = np.isfinite(dist)
    near = np.where(ok, near, np.arange(len(idx))[:, None])
    w = np.where(ok, a[near], 0.0)
    w = w / np.maximum(w.sum(1, keepdims=True), 1e-300)
    d = c[near] - np.einsum("fk,fkd->fd", w, c[near])[:, None]
    cov = np.einsum("fk,fki,fkj->fij", w, d, d)
    planar = np.zeros(len(centers), bool)
    planar[idx] = np.sqrt(np.maximum(np.linalg.eigvalsh(cov)[:, 0], 0)) < END_FLAT_WALLS * wall
    e0, e1 = topo.edge_faces[:, 0], topo.edge_faces[:, 1]
    run = components(len(centers), topo.edge_faces[planar[e0] & planar[e1]])
    shape = band_shape(centers, areas, run) / max(wall, 1e-300)
    lip_run = ((shape[:, 0] > END_LIP_LENGTH_WALLS) & (shape[:, 1] > END_LIP_BEND_WALLS)
               & (shape[:, 2] < END_LIP_FLAT_WALLS))
    return planar & lip_run[run]


def wall_end_labels(centers: np.ndarray, normals: np.ndarray, areas: np.ndarray, topo: Topology, region: np.ndarray,
                    prob: np.ndarray, wall: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    """Fracture on a dense thin wall: the crease regions' where their fracture covers most of the
    wall's ends (`WALL_END_COVERED` of the area of the ends less lips), less regions mostly of lip
    faces (a lip rounded a little, its rims too soft for `LIP_*`), else the wall's ends
    (`wall_end_alignment`) less its lips (`end_lips`).

    A rescan rounds the wall's end over a face or two (corpus vessel-noisy: edges 0.7-1.4 walls
    long), so no crease bounds the band and the crease regions merged it into the skin (they
    covered 0.46-0.69 of the ends there, 0.75-0.96 on vessel-clean but for one piece, 0.38); the
    turn of the normals across the wall finds it whatever the creases. Where sharp creases bound
    the band the crease regions are better: they also find a cut met at a slant, whose normal
    stays within `WALL_END_ALIGN` of the wall's axis.

    Parameters
    ----------
    centers, normals, areas : (F, 3), (F, 3), (F,) face centroids, unit normals, areas
    topo : the mesh's `Topology`
    region : (F,) crease region per face; prob : (R,) their likelihood (`region_fracture_prob`)
    wall : the wall's thickness, object units

    Returns
    -------
    pieces : (F,) int64, the crease regions, or, where the ends decide, split where a face's end /
        lip class changes
    prob : (P,) fracture likelihood per piece (> 0.5: fracture)
    lips : (F,) bool, the lip faces
    ends : whether the ends decided
    """
    align = wall_end_alignment(centers, normals, areas, wall)
    p_end = 1.0 / (1.0 + np.exp(-np.clip((WALL_END_ALIGN - align) / WALL_END_SOFTNESS, -50, 50)))
    end = p_end > 0.5
    lip = end_lips(centers, areas, topo, align < LIP_CORE_ALIGN, wall)
    e0, e1 = topo.edge_faces[:, 0], topo.edge_faces[:, 1]
    lip |= end & (ring_average(lip.astype(np.float64), np.ones(len(lip)), topo.edge_faces[end[e0] & end[e1]],
                               LIP_GROW_RINGS) > 0)
    ends = end & ~lip
    if areas[ends & (prob[region] > 0.5)].sum() >= WALL_END_COVERED * areas[ends].sum():
        # the crease regions see the band; a region mostly of lip faces is skin (a lip rounded a little)
        n_reg = len(prob)
        lip_share = np.bincount(region, weights=areas * lip, minlength=n_reg) / np.maximum(
            np.bincount(region, weights=areas, minlength=n_reg), 1e-300)
        return region, np.where(lip_share > 0.5, np.minimum(prob, 1.0 - lip_share), prob), lip, False
    face_p = np.where(lip, 0.0, p_end)
    frac = face_p > 0.5
    same = (region[e0] == region[e1]) & (frac[e0] == frac[e1]) & (lip[e0] == lip[e1])
    pieces = components(len(centers), topo.edge_faces[same])
    n = int(pieces.max()) + 1
    piece_p = np.bincount(pieces, weights=areas * face_p, minlength=n) / np.maximum(
        np.bincount(pieces, weights=areas, minlength=n), 1e-300)
    return pieces, piece_p, lip, True


def wall_thickness(centers: np.ndarray, normals: np.ndarray, areas: np.ndarray, skin: np.ndarray,
                   neighbours: int = 24) -> float:
    """The wall's thickness relative to the piece's size where the skin faces a parallel opposite
    face nearby (a vessel's inner and outer faces), else inf.

    Parameters
    ----------
    centers : (F, 3) face centroids
    normals : (F, 3) unit face normals
    areas : (F,) face areas
    skin : (F,) bool, faces of the grown skin
    neighbours : nearest faces searched for the opposite one

    Returns
    -------
    float: the area-weighted median distance, along the normal, from a skin face to the nearest
    face turned the other way, over the skin faces that have one, divided by the bounding-box
    diagonal; inf when less than half of the skin has one or the thickness varies (quartiles more
    than a factor 2 apart)
    """
    size = float(np.linalg.norm(centers.max(0) - centers.min(0))) if len(centers) else 0.0
    if not skin.any() or size <= 0 or len(centers) < 4:
        return np.inf
    idx = np.flatnonzero(skin)
    _, near = cKDTree(centers).query(centers[idx], k=min(neighbours, len(centers)))
    gap = np.einsum("fkd,fd->fk", centers[idx][:, None] - centers[near], normals[idx])
    opposite = (np.einsum("fkd,fd->fk", normals[near], normals[idx]) < -0.7) & (gap > 0)
    depth = np.where(opposite, gap, np.inf).min(1)
    has = np.isfinite(depth) & (depth > 1e-3 * size)
    if areas[idx][has].sum() < 0.5 * areas[idx].sum():
        return np.inf
    q25, q50, q75 = weighted_quantile(depth[has], areas[idx][has], [0.25, 0.5, 0.75])
    return float(q50) / size if q75 < 2 * q25 else np.inf  # a wall is about as thick everywhere


def band_shape(centers: np.ndarray, areas: np.ndarray, region: np.ndarray) -> np.ndarray:
    """Per region, the extent of its face centroids along their principal axes and their spread off
    the best-fit plane (object units).

    Parameters
    ----------
    centers : (F, 3) face centroids
    areas : (F,) face areas
    region : (F,) int region id per face, 0..R-1

    Returns
    -------
    (R, 3) float: length (extent along the main axis), bend (extent along the second axis: how far
    a band's centre line curves within its plane) and flat_rms (area-weighted RMS distance of the
    centroids from the plane)
    """
    n_reg = int(region.max()) + 1
    w = np.maximum(np.bincount(region, weights=areas, minlength=n_reg), 1e-300)
    mean = np.stack([np.bincount(region, weights=areas * centers[:, k], minlength=n_reg)
                     for k in range(3)], 1) / w[:, None]
    d = centers - mean[region]
    cov = np.zeros((n_reg, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            cov[:, i, j] = cov[:, j, i] = np.bincount(region, weights=areas * d[:, i] * d[:, j], minlength=n_reg) / w
    val, vec = np.linalg.eigh(cov)  # ascending: vec[..., 0] is the plane's normal, vec[..., 2] the main axis
    out = np.zeros((n_reg, 3))
    for col, axis in ((0, 2), (1, 1)):
        t = np.einsum("fd,fd->f", d, vec[region, :, axis])
        hi, lo = np.full(n_reg, -np.inf), np.full(n_reg, np.inf)
        np.maximum.at(hi, region, t)
        np.minimum.at(lo, region, t)
        out[:, col] = hi - lo
    out[:, 2] = np.sqrt(np.maximum(val[:, 0], 0))
    return out
