"""All tunable parameters of the pipeline in one frozen dataclass.

Lengths are fractions of the working scale (`Params.unit`, or when that is None
the size of the fragments at hand: the mean bounding-box diagonal of a pair, the
median of a group), so the same defaults serve a unit-size synthetic object and a
scan in millimetres. Angles are in degrees.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, replace


SEGMENTATIONS = ("roughness", "regions", "union", "hybrid")  # the methods Params.segmentation names


@dataclass(frozen=True)
class Params:
    # scale: the length all relative lengths below are fractions of; None = from the fragments
    unit: float | None = None

    # a mesh whose vertices are noisy at its triangles' scale is matched on a smoothed copy
    # (`pair.denoise`: told from the mesh itself; exact and coarse meshes never are)
    denoise: bool = True

    # segmentation (Alg. 2)
    roughness_rings: int = 3         # neighbourhood (edge steps) for the normal perturbation of a face
    roughness_spacing: float = 0.02  # ... at this length at least, on finer meshes (segment.working_roughness)
    roughness_threshold_deg: float = 3.0  # fracture is rougher than this (and than Otsu's split of the roughness)
    crease_angle_deg: float = 50.0   # region growing stops at edges whose normals differ more
    vote_rings: int = 2              # fracture/original by a vote of the faces this many edge-steps around
    min_region_faces: int = 12       # smaller regions are merged into their neighbour ...
    min_region_share: float = 0.01   # ... as are regions with less than this share of the faces
    # "roughness": Otsu split of the roughness + vote (above); "regions": crease regions, skin grown
    # from the largest over gentle boundaries, the rest by shape cues (segment_cues, issue 16 item 2);
    # "union": both, a face's fracture likelihood the larger of the two (faces either finds are candidates);
    # "hybrid": the union less rough-only pieces near the mesh's own noise floor, crease regions alone
    # on coarse meshes (segment.py). Neither wins everywhere (docs/benchmarks.md, "Two segmentations,
    # verification decides"): a mesh pair is matched on `segmentation` first and, where that finds no
    # fit, on `second_segmentation` (None: not at all)
    segmentation: str = "roughness"  # one of SEGMENTATIONS
    second_segmentation: str | None = "hybrid"  # one of SEGMENTATIONS, or None
    # ... and where the first reading's fit passed only in the band (accepted on its outline, skin
    # or rims: `meshfit.band_fit`), the less sure acceptances; its rims decide between the two
    # readings' fits as where the first fit's rims do not agree (docs/benchmarks.md, "A fit
    # accepted in the band asks the second reading")
    second_when_banded: bool = True
    region_merge_deg: float = 35.0   # regions join the skin across boundaries turning less than this ...
    region_merge_noise: float = 2.0  # ... plus this many times the skin's roughness (degrees) ...
    region_rough_max: float = 3.0    # ... unless rougher than this many times the skin
    region_noise_floor_deg: float = 0.5   # the skin's roughness taken at least this in such ratios
    region_relay_share: float = 0.1  # only regions with this area share pass the growth on (or seed it)
    region_sharp_rim: float = 0.95   # a seed with this share of its rim sharp (> 35 deg), grown over no large region ...
    region_isolated_weight: float = 0.5  # ... competes with this share of its area (a cut looks like that)
    region_curved_unflatness: float = -2.0  # outside regions curved beyond this (log(1 - flatness)) ...
    region_curved_rough: float = 0.6  # ... and not rougher (log ratio to the skin) than this are skin
    region_context_rough: float = 0.6  # when regions rougher than this (log ratio) ...
    region_context_share: float = 0.05  # ... cover this share of the non-skin area, the break is rough:
    region_context_smooth: float = 0.2  # ... regions smoother than this (log ratio) are skin then
    region_grown_rough: float = 0.8  # grown regions rougher than this (log ratio) are fracture where the break is rough
    region_thin_wall: float = 0.04   # skin facing itself across less than this (of the size) is a thin wall ...
    region_band_walls: float = 2.5   # ... whose fracture is a band: smooth regions wider than this many walls are skin
    region_softness: float = 0.15    # log-unit width of the logistic steps grading the likelihood

    # contours
    contour_step: float = 0.008      # resampling step along contours
    min_contour_points: int = 24     # shorter loops are dropped

    # features (Eq. 13-28)
    kcos_k: int = 4                  # k of the k-cosine neighbourhood, in contour points
    feature_stride: int = 8          # difference step for curvature, torsion and chords, in points (features.py)
    feature_peak_window: int = 5     # half-width of the window a curvature peak must top (Eq. 17)

    # fusion (Eq. 29-32)
    fusion_weights: str | None = None  # path of an .npz; None = the weights shipped with relicgpu

    # coarse match (Eq. 33, Alg. 4)
    lcs_eps: float = 0.25            # flag threshold on fused values (standardised units)
    ransac_iterations: int = 400
    ransac_inlier: float = 0.02      # correspondence inlier distance for the LCS pose
    hypotheses: int = 6              # coarse poses handed to ICP per pair
    ppf_points: int = 800            # fracture points voting with point-pair features (0 turns these starts off)
    ppf_normal_radius: float = 0.04  # ... their normals: plane fits over this radius
    ppf_distance_step: float = 0.03  # ... feature quantisation: distance ...
    ppf_angle_step_deg: float = 12.0  # ... and angles
    ppf_starts: int = 24             # ... poses kept (best-voted reference points)
    ppf_max_distance: float = 0.2    # ... only pairs of points nearer than this vote (0: all pairs)
    max_patches: int = 3             # fracture patches per fragment tried face to face ...
    min_patch_share: float = 0.15    # ... if at least this share of the largest patch's area
    patch_turns: int = 12            # turns about the common normal tried per patch pair
    facet_outline: float = 0.005     # flat facets laid face down whose outlines agree within this
    facet_starts: int = 3            # ... are verified first, at most this many a pair (`facets`; 0: off)
    grown_outline: float = 0.008     # near-flat facets (rescanned or gently curved cuts) whose outlines
    # agree within this are verified next, as many (`facets.grown_facets`; 0: off)
    screen_points: int = 400         # points per start in the short batched ICP that ranks starts
    screen_iterations: int = 10      # ... for every start
    screen_keep: int = 24            # the best starts then run ...
    screen_more_iterations: int = 30  # ... this many rounds more
    screen_reject: float = 0.1       # pairs farther than this are left out of the ranking fits
    screen_trim: float = 0.05        # ... as are those farther than 3x this quantile of the distances

    # ICP (Eq. 34-35, Alg. 5)
    cloud_points: int = 6000         # a cloud with normals is matched on at most this many points, spread evenly (0: all)
    icp_points: int = 1500           # fracture points sampled per fragment ...
    sample_min_prob: float = 0.2     # ... from faces of at least this fracture likelihood, weighted by it
    sample_min_share: float = 0.02   # under this likelihood-weighted area share: the whole surface, uniformly
    face_sample_step: float = 0.015  # faces with an edge over twice this add points inside (SurfaceSample.sides)
    icp_iterations: int = 40
    icp_tolerance: float = 1e-5      # stop when the mean distance d changes less than this
    verify_at_most: int = 6          # fits verified per pair, best-touching first, until one is accepted
    plane_iterations: int = 20       # point-to-plane polish after ICP (stops early when converged)
    icp_reject: float = 0.03         # nearest pairs farther than this are not used in the fit
    icp_trim: float = 0.2            # ... nor those farther than 3x this quantile of the distances
    # ... nor, between two fine meshes (median edge under `facing_edge`), pairs whose normals face
    # each other less than this cosine (None: no such test): a rescanned break's skin beside it
    fine_facing: float | None = -0.7
    facing_edge: float = 0.015

    # verification
    contact_distance: float = 0.01   # a point within this of the other fracture surface is in contact
    min_overlap: float = 0.12        # share of either fracture sample in contact (partial contacts: 0.12-0.5)
    max_rmse: float = 0.0028         # RMS point-to-plane distance over the contact
    max_penetration: float = 0.06    # share of surface points deeper than penetration_depth inside the other
    penetration_depth: float = 0.015
    # meshes (clouds: cloudmatch.MIN_FACING, no sunk-surface check): at least this share of the
    # surfaces' touching points must face each other, and at most this share of either surface
    # may sink deeper than penetration_depth into the other, contact zone included. Fitted on the
    # fits match_pair verifies on the synth, rough and smooth families (scripts/bench_verify.py):
    # right fits face 0.25-0.91 and sink at most 0.0085 (a coarse smooth one 0.011 in an
    # assembly), wrong ones that pass the checks above mostly face under 0.015
    # (docs/benchmarks.md, "Verification that rejects a wrong fit")
    min_facing: float = 0.06
    max_surface_penetration: float = 0.02
    # a rescanned (noisy, smoothed, decimated) break does not mate as closely as a clean one: its
    # right fits' residuals reach 0.0031-0.0041 (docs/benchmarks.md, "Noisy and smooth breaks").
    # A mesh fit that passes every check but the residual, with a residual up to residual_band
    # times max_rmse, is accepted where the two outlines agree (`verify.rim_agreement` on points
    # where the surface turns within outline_radius by more than outline_spread, the middle
    # eigenvalue of the normal tensor there) by at least min_outline (None: never)
    residual_band: float = 1.6
    min_outline: float | None = 0.3
    # ... with the skin beside the seam continuing the partner's (`seam.skin_continuation`) by at
    # least outline_skin: a flat break turned half a turn keeps a symmetric outline but lays its
    # sides across the partner's (None: not asked)
    outline_skin: float | None = 0.1
    # ... or where the skin beside the seam continues the partner's (`seam.skin_continuation`) by
    # at least min_skin (None: never). Clouds: the fit of two curved crease regions whose skin
    # continues most, at least this much, is taken (`pipeline._by_skin`; None: never)
    min_skin: float | None = 0.2
    # of a mesh pair's fits that pass (or, where none does, that the residual band passes), the
    # one whose skin beside the seam continues the partner's most, by at least skin_pick and more
    # than the first's, is taken: a flat or smooth break passes at several turns alike, and only
    # the right one carries the skin on across the seam (None: the first that passes)
    skin_pick: float | None = 0.2
    # a fit of two thin walls (both under region_thin_wall) is refused where, of at least
    # `meshfit.WALL_SKIN_NEAR` free skin points near the partner's, under wall_skin continue its
    # surface (`seam.skin_points`): a break through a wall leaves both skins running on across the
    # seam; a wall laid along a wall, or turned across it, leaves them beside the partner's (None: never)
    wall_skin: float | None = 0.15
    # any mesh fit is refused where, of at least `meshfit.WALL_SKIN_NEAR` points of the reading's
    # skin free beside its seam (`seam.skin_points(skin_only=True)`), under seam_skin continue the
    # partner's surface: a flat break laid on its partner turned or slid leaves its skin beside the
    # partner's (clean Voronoi pieces' wrong fits 0.00-0.02, right ones 0.12 and up). The reading's
    # skin only: at the right fit of an inner piece or of a shard, the other breaks beside the seam
    # continue nothing (Blender shards' right fits 0.01-0.4 over all points) (None: never)
    seam_skin: float | None = 0.05
    # a fit of two pieces whose skins each turn firmly about an axis (`revolution`: thin walls, and
    # thicker pieces that are plainly surfaces of revolution) is refused where it carries one axis
    # more than `revolution.AXIS_DEG` or axis_apart (of the scale) off the other: a wheel-made
    # vessel's sherds share one (None: never)
    axis_apart: float | None = 0.1
    # a mesh fit that passes every check but facing is accepted where its rims meet the
    # partner's creases (`verify.rim_agreement`) by at least facing_rims: a thin wall's narrow
    # band faces over fewer points than its skins touch side by side (None: never)
    facing_rims: float | None = 0.4
    # clouds: a flat cut whose rim and face the partner's hold by at least min_plane
    # (`planar.fit_score`), with no fit at another turn close (`cutfit.match_planes`), is
    # taken before the crease regions are tried (None: never)
    min_plane: float | None = 0.3
    # clouds scanned without normals that nothing matched, where a pick is a thin wall's band, are
    # matched once more with a thin wall's normals (`cloud.wall_normals`: each face's own, the break
    # strip's between them); such a fit is refused where the pieces' axes of revolution do not meet
    # or their walls tilt apart (a sherd laid upside down), and weighs `pipeline.SECOND_READING_SCORE`
    # of its score in the assembly
    wall_normals: bool = True
    # clouds with given normals that nothing matched are matched once more on their points alone (as
    # scanned without normals, `wall_normals` included): normals a program fitted to the points are
    # blended over creases and across thin walls, where the points alone are read for what they are;
    # two thin walls' bands (`cloudmatch.thin_pick`) are asked `wall_normals` alone
    points_alone: bool = True
    outline_radius: float = 0.05
    outline_spread: float = 0.12
    # assembly: a verified match whose sharp creases meet the partner's (`verify.rim_agreement` of
    # its fit at least rim_priority; None: off) weighs forest.RIM_WEIGHT more in the assembly
    # graph (docs/benchmarks.md, "Matches whose outlines agree are joined first")
    rim_priority: float | None = 0.15
    # assembly: fragments and groups no pairwise match placed are matched against the merged
    # surface of each placed group they are candidates of (`heap.grow`)
    grow_groups: bool = True
    # assembly: two groups of at least two fragments each that look like pieces of different
    # objects (the mean, over their fragment pairs, of `heap.grouping`'s p(one object) under this)
    # are not joined: a wrong match between two objects of a mixed heap has nothing else to
    # contradict it. Under every single object's least such mean (0.073, the Blender cube;
    # docs/benchmarks.md, "Mixed heaps: groups that look like two objects"); None: not asked
    apart_below: float | None = 0.05
    # assembly: rounds in which the placed fragments of each group are settled together on all the
    # neighbours they touch (`heap.settle`, one solve a round; 0: the poses of the pose graph as they are)
    settle_rounds: int = 30

    def with_(self, **changes) -> "Params":
        return replace(self, **changes)

    def to_dict(self) -> dict:
        return asdict(self)


DEFAULT = Params()


def with_segmentations(params: Params, first: str | None = None, second: str | None = None) -> Params:
    """`params` with `segmentation` = first and `second_segmentation` = second where given (second
    "none": no second reading), as the benchmark scripts' --segmentation / --second-segmentation."""
    if first:
        params = params.with_(segmentation=first)
    if second:
        params = params.with_(second_segmentation=None if second == "none" else second)
    return params


def second_reading_params(params: Params) -> Params | None:
    """The `Params` of a mesh pair's second reading (`second_segmentation` as the segmentation;
    `pipeline.match_pair` says where it is asked), or None where there is no second reading."""
    if params.second_segmentation in (None, params.segmentation):
        return None
    return params.with_(segmentation=params.second_segmentation, second_segmentation=None)


def parse_assignments(items) -> dict:
    """Params fields from NAME=VALUE strings (the benchmark scripts' --set), each value of its
    field's type ("None" for None; a field unset by default takes a number or a name).

    Raises ValueError naming the item where NAME is not a Params field or VALUE does not parse."""
    default = Params()
    changes = {}
    for item in items:
        name, _, value = item.partition("=")
        if name not in Params.__dataclass_fields__ or not value:
            raise ValueError(f"{item!r}: expected NAME=VALUE with NAME a Params field")
        current = getattr(default, name)
        try:
            if value == "None":
                changes[name] = None
            elif isinstance(current, bool):
                if value.lower() not in ("1", "true", "yes", "0", "false", "no"):
                    raise ValueError(value)
                changes[name] = value.lower() in ("1", "true", "yes")
            elif current is not None:
                changes[name] = type(current)(value)
            else:
                try:
                    changes[name] = float(value)
                except ValueError:
                    changes[name] = value
        except ValueError:
            raise ValueError(f"{item!r}: {name} must be {type(current).__name__}") from None
    return changes
