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

import numpy as np

from ..params import Params
from .regions import CUE_NAMES, RegionCues, _pair_medians, boundary_turn, crease_regions, region_cues
from ..topology import Topology, weighted_quantile
from .walls import WALL_END_MIN_FACES, band_shape, wall_end_labels, wall_thickness

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

NONPLANAR_MIN_SHARE = 0.01  # a skin of exact planes is grown again from regions that are not, of at least this area share
BOX_MIN_SHARE = 0.05  # exact planes of at least this share that meet another at a right angle or face opposite ways ...
BOX_DEG = 0.1  # ... within this many degrees (a CAD box: exactly; 0.5: 2 of 33 cells called boxes) are a box's skin faces
# A cap (`square_caps`): chosen on Voronoi cells of a 64-sided cylinder (12 cells, seeds 0-2, built in
# /tmp; the Blender cylinder held out): with the side reseeded, caps were fracture on 9 of 36 pieces, mean precision 0.866; with this 0.932
CAP_DEG = 1.0  # an exact plane is square to a skin face when their normals are within this of 90 degrees ...
CAP_SHARE = 0.9  # ... and a cap when so on this share of the skin faces along its shared rim ...
CAP_MIN_EDGES = 3  # ... of at least this many edges


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
