"""Flat breaks matched by their rims: a plane that bounds each piece, laid on the partner's.

A flat cut (Voronoi cell fracture, a saw cut, a clean cleavage) holds nothing in its own plane:
laid face to face, the two cut faces fix the plane and leave its turn and slide to the outline,
which for a rounded solid is near an ellipse and fits at several turns (`cloudmatch`'s region
fits settle 2-13 degrees off and tie at half a turn). The skin beside the cut does not tie: at
the right pose it runs on across the seam with the same normal, point for point.

So each piece's candidate cut planes are found directly (`cut_planes`: many points coplanar with
their normals along the plane's, every other point of the piece behind it). The skin beside each
plane is carried along its own slope onto the plane (`CutPlane.rim`): the rim curve, each point
with the skin's normal there. For two planes put face to face the in-plane turn and slide are searched
(every RIM_TURN_STEP degrees, each refined by a 2-D ICP on the rims whose normals agree), and a
fit is scored by the share of rim points of either piece that land on the other's rim with the
same skin normal, times the share of the cut faces that overlap (`plane_fits`, `fit_score`).
The rims leave a near-elliptic cut a few degrees loose; the best distinct fits are polished on
the skin across the seam and scored again (`polished_fits`). `cutfit.match_planes` takes the
best where no other pose holds nearly as well, and calls the cut ambiguous otherwise.

A curved cut through thin parts (a smooth break through a pot's wall, a stem and leaves; boards)
is a few strips of points on one smooth surface that no plane holds, and the piece lies behind it
too. A plane's points are grown into a sheet, a height field over the plane (`_sheet`, kept where
a crease borders it), and searched as a plane is; each fit is then settled in 3-D (`_settled`),
as two sheets holding different parts of the cut tilt apart.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import seam
from ..cloud.points import local_pca
from .icp import apply, fit_rigid, invert, rotation_angle_deg

# A cut plane: at least MIN_PLANE_SHARE of a piece's points within PLANE_SPACINGS point spacings
# of it with normals within PLANE_DEG of its normal, and at most BEHIND_SHARE of the piece's
# points more than BEHIND_SPACINGS spacings in front of it (a cut leaves the piece on one side).
# A thin cut (`is_thin`: a bookshelf's boards 0.02 of its height cut across) holds fewer: at least
# MIN_THIN_SHARE.
MIN_PLANE_SHARE = 0.03
MIN_THIN_SHARE = 0.01
PLANE_SPACINGS = 1.0
PLANE_DEG = 12.0
BEHIND_SHARE = 0.01
BEHIND_SPACINGS = 3.0
MAX_PLANES = 4
# Of up to CANDIDATE_PLANES planes found (largest first), the curved cuts (`_sheet`) come first: a
# faceted convex skin (a pot's 48-sided wall) gives many planes the piece lies behind, and a cut
# through thin parts holds few points. Flat planes keep their order (promoted too, a vessel's thin
# lip was laid on the partner's half a turn off: corpus vessel-clean seeds 33 and 39 with normals).
CANDIDATE_PLANES = 8
PLANE_SEEDS = 400
# The rim: skin points within RIM_BAND spacings behind the plane, whose normal is not within
# RIM_FLAT (cosine) of the plane's (skin parallel to the cut never reaches it), carried along
# their own slope onto the plane (at most RIM_BAND spacings).
RIM_BAND = 4.0
RIM_FLAT = 0.9
# Normals estimated from the points round the crease off: a rim point's plane fit takes in the cut
# face, and its normal leans towards the plane's. Where the normals are estimated, each rim
# point's is fitted again over its RIM_NEIGHBOURS nearest skin points (off the plane) only.
RIM_NEIGHBOURS = 10
# A plane whose skin meets it square all round (median |cosine| of the skin's normals with the
# plane's under MIN_TILT) is a prism's end: its side continues across any plane square to it, so
# such a face stacks on a copy of itself as well as a cut does (a bookshelf's outer boards:
# medians 0.0; the cut planes of the corpus's voronoi-clean clouds 0.04-0.72).
MIN_TILT = 0.03
# Search and score: a start every RIM_TURN_STEP degrees, ICP_ROUNDS rounds of 2-D ICP pairing
# rim points whose normals agree within RIM_AGREE (cosine), gated from ICP_GATE spacings down
# to RIM_HIT; a rim point is held where the other's lies within RIM_HIT spacings with normals
# agreeing, a cut-face point where the other's lies within RIM_HIT spacings.
RIM_TURN_STEP = 10.0
ICP_ROUNDS = 8
ICP_GATE = 6.0
RIM_AGREE = 0.9
RIM_HIT = 1.5
MIN_RIM_POINTS = 12
# A thin cut (boards, leaves, a pot's wall cut across): the median of its face's points lies within
# THIN_CUT spacings of its rim (the corpus's Voronoi cut faces with normals, seeds 0-47: 1.5 and up;
# cuts across a bookshelf's boards and a plant 0.6-1.2, or 1.6-3.0 where a cut runs along a board).
# Laid on the partner's it touches mostly along the seam (`cutfit.match_planes`).
THIN_CUT = 1.3
# The POLISH best fits that differ by DISTINCT_DEG of turn or DISTINCT_SLIDE of shift (shares of
# the scale) are polished on the skin across the seam (`seam.seam_polish`: a flat face holds
# nothing in its own plane, the skin beside it does) and scored again.
POLISH = 6
DISTINCT_DEG = 3.0
DISTINCT_SLIDE = 0.02
# A curved cut (a smooth or wavy break through boards, a pot's wall, leaves) leaves a plane only
# part of its face. The plane's points are grown into a sheet, a height field of degree
# SHEET_DEGREE over the plane, over SHEET_ROUNDS rounds, each taking the free points within
# PLANE_SPACINGS of it with normals within PLANE_DEG of its own, up to SHEET_REACH of its extent
# past its points; the sheet replaces the plane where it holds SHEET_GROWTH times its points and
# the piece lies behind it (over the sheet's extent). A sheet's coefficients are fitted in
# coordinates scaled to its extent, each non-constant one held towards 0 by SHEET_RIDGE (a face
# of a few strips across boards leaves some directions unpinned).
SHEET_DEGREE = 3
SHEET_ROUNDS = 4
SHEET_REACH = 0.25
SHEET_GROWTH = 1.25
SHEET_RIDGE = 1e-3
# ... and where its border is a crease: of the points within SHEET_RING spacings of it, at least
# SHEET_CREASE turn more than SHEET_CREASE_DEG from the nearest sheet point (a patch of a convex
# skin, which the piece lies behind too, runs on smoothly: plant and bookshelf clouds cut smooth,
# seeds 0-3, skin sheets 0.62-0.88, cut sheets 0.90-1.00).
SHEET_RING = 2.0
SHEET_CREASE_DEG = 30.0
SHEET_CREASE = 0.95
# the height field's monomials x^i y^j: (T, 2) their exponents (i, j), degree by degree
_POWERS = np.array([(e - j, j) for e in range(SHEET_DEGREE + 1) for j in range(e + 1)])


@dataclass(frozen=True)
class CutPlane:
    frame: np.ndarray  # (4, 4): columns u, v, n (outward), origin; plane coordinates -> piece
    face: np.ndarray  # (K, 2) the cut face's points in plane coordinates
    rim: np.ndarray  # (R, 2) the rim in plane coordinates
    rim_normals: np.ndarray  # (R, 3) the skin's unit normals there, in plane coordinates
    indices: np.ndarray  # (K,) the cut face's points among the piece's
    bend: np.ndarray | None = None  # a curved cut's height over the plane: `height` coefficients

    def height(self, xy: np.ndarray) -> np.ndarray:
        """(K,) the cut's height over its plane at (K, 2) plane coordinates (0 for a flat cut)."""
        return np.zeros(len(xy)) if self.bend is None else _design(xy) @ self.bend

    def _to_piece(self, xy: np.ndarray) -> np.ndarray:
        return xy @ self.frame[:3, :2].T + self.height(xy)[:, None] * self.frame[:3, 2] + self.frame[:3, 3]

    @property
    def rim_points(self) -> np.ndarray:
        """(R, 3) the rim in the piece's frame."""
        return self._to_piece(self.rim)

    @property
    def rim_normals_3d(self) -> np.ndarray:
        """(R, 3) the skin's normals at the rim in the piece's frame."""
        return self.rim_normals @ self.frame[:3, :3].T

    @property
    def face_points(self) -> np.ndarray:
        """(K, 3) the cut face's points moved onto the plane, in the piece's frame."""
        return self._to_piece(self.face)


def _frame(normal: np.ndarray, origin: np.ndarray) -> np.ndarray:
    frame = np.eye(4)
    frame[:3, 0], frame[:3, 1] = seam._frame(normal)
    frame[:3, 2], frame[:3, 3] = normal, origin
    return frame


def cut_planes(points: np.ndarray, normals: np.ndarray, spacing: float, estimated: bool = False) -> list[CutPlane]:
    """The planes that could be a flat cut of a piece: (N, 3) points, (N, 3) outward unit normals
    (`estimated` from the points, not scanned), the cloud's point spacing. Largest first, at most
    MAX_PLANES; each point on one plane only."""
    n = len(points)
    tol, cos = PLANE_SPACINGS * spacing, np.cos(np.radians(PLANE_DEG))
    free = np.ones(n, bool)
    seeds = np.random.default_rng(0).permutation(n)[:PLANE_SEEDS]
    height = np.abs(np.einsum("snk,sk->sn", points[None] - points[seeds, None], normals[seeds]))
    seed_planes = (height < tol) & ((normals @ normals[seeds].T).T > cos)  # (S, N): each seed's plane
    planes = []
    while len(planes) < CANDIDATE_PLANES:
        alive = free[seeds]
        seeds, seed_planes = seeds[alive], seed_planes[alive]
        if not len(seeds):
            break
        on = seed_planes & free[None]
        best = int(np.argmax(on.sum(1)))
        members = np.flatnonzero(on[best])
        if len(members) < MIN_THIN_SHARE * n:
            break
        small = len(members) < MIN_PLANE_SHARE * n
        was_free = free.copy()
        free[members] = False
        frame = _fitted_frame(points, normals, members)
        front = (points - frame[:3, 3]) @ frame[:3, 2]
        behind = np.mean(front > BEHIND_SPACINGS * spacing) <= BEHIND_SHARE
        members = np.flatnonzero((np.abs(front) < tol) & (normals @ frame[:3, 2] > cos))
        frame, bend = _frame(frame[:3, 2], points[members].mean(0)), None
        sheet = _sheet(points, normals, was_free, members, frame, spacing)
        if sheet is not None and len(sheet[0]) >= SHEET_GROWTH * len(members):
            (members, frame, bend), behind = sheet, True
            small = len(members) < MIN_PLANE_SHARE * n
            free[members] = False
        if not behind:
            continue
        plane = _plane(points, normals, members, frame, spacing, estimated, bend)
        if plane is not None and (not small or is_thin(plane, spacing)):
            planes.append(plane)
    return ([p for p in planes if p.bend is not None] + [p for p in planes if p.bend is None])[:MAX_PLANES]


def _fitted_frame(points: np.ndarray, normals: np.ndarray, members: np.ndarray) -> np.ndarray:
    centre = points[members].mean(0)
    _, _, vt = np.linalg.svd(points[members] - centre, full_matrices=False)
    return _frame(vt[2] * np.sign(vt[2] @ normals[members].mean(0)), centre)


def _design(xy: np.ndarray, d: int | None = None) -> np.ndarray:
    """(K, T) the monomials of `_POWERS` at (K, 2) xy, or their derivative by x (d = 0) or y (d = 1)."""
    table = xy[:, None, :] ** np.arange(SHEET_DEGREE + 1)[None, :, None]  # (K, degree + 1, 2), integer powers
    if d is None:
        return table[:, _POWERS[:, 0], 0] * table[:, _POWERS[:, 1], 1]
    lowered = _POWERS.copy()
    lowered[:, d] = np.maximum(lowered[:, d] - 1, 0)
    return _POWERS[:, d] * table[:, lowered[:, 0], 0] * table[:, lowered[:, 1], 1]


def _bend(xy: np.ndarray, z: np.ndarray) -> np.ndarray:
    """(T,) coefficients of the height field of degree SHEET_DEGREE through heights (K,) z at
    (K, 2) xy (ridge-held, fitted on coordinates scaled to their extent)."""
    unit = max(float(np.abs(xy).max()), 1e-12)
    design = _design(xy / unit)
    ridge = np.full(design.shape[1], SHEET_RIDGE * len(xy))
    ridge[0] = 0.0
    coef = np.linalg.solve(design.T @ design + np.diag(ridge), design.T @ z)
    return coef / unit ** _POWERS.sum(1)


def _sheet(points, normals, free, members, frame, spacing):
    """The plane's `members` (indices) grown into a curved sheet: (members, frame, bend), or None
    where the piece does not lie behind it or it is too small to fit."""
    tol, cos = PLANE_SPACINGS * spacing, np.cos(np.radians(PLANE_DEG))
    terms = len(_POWERS)
    for _ in range(SHEET_ROUNDS):
        if len(members) < 3 * terms:
            return None
        local = (points - frame[:3, 3]) @ frame[:3, :3]
        bend = _bend(local[members, :2], local[members, 2])
        lo, hi = local[members, :2].min(0), local[members, :2].max(0)
        reach = SHEET_REACH * float((hi - lo).max())
        near = np.flatnonzero(free & np.all((local[:, :2] > lo - reach) & (local[:, :2] < hi + reach), 1))
        xy = local[near, :2]
        slope = np.stack([-_design(xy, d) @ bend for d in (0, 1)] + [np.ones(len(near))], 1)
        along = np.einsum("ij,ij->i", normals[near] @ frame[:3, :3], slope) / np.linalg.norm(slope, axis=1)
        grown = near[(np.abs(local[near, 2] - _design(xy) @ bend) < tol) & (along > cos)]
        if np.array_equal(grown, members):
            break
        members = grown
    if len(members) < 3 * terms:
        return None
    frame = _fitted_frame(points, normals, members)
    local = (points - frame[:3, 3]) @ frame[:3, :3]
    bend = _bend(local[members, :2], local[members, 2])
    lo, hi = local[members, :2].min(0), local[members, :2].max(0)
    over = local[np.all((local[:, :2] > lo) & (local[:, :2] < hi), 1)]
    front = over[:, 2] - _design(over[:, :2]) @ bend
    if np.sum(front > BEHIND_SPACINGS * spacing) > BEHIND_SHARE * len(points):
        return None
    return (members, frame, bend) if _creased(points, normals, members, spacing) else None


def _creased(points: np.ndarray, normals: np.ndarray, members: np.ndarray, spacing: float) -> bool:
    """Whether the points' `members` (indices) are bordered by a crease (SHEET_CREASE)."""
    from scipy.spatial import cKDTree

    inside = np.zeros(len(points), bool)
    inside[members] = True
    distance, nearest = cKDTree(points[members]).query(points[~inside], distance_upper_bound=SHEET_RING * spacing)
    ring = np.isfinite(distance)
    if not ring.any():
        return False
    turn = np.einsum("ij,ij->i", normals[~inside][ring], normals[members][nearest[ring]])
    return bool(np.mean(turn < np.cos(np.radians(SHEET_CREASE_DEG))) >= SHEET_CREASE)


def _plane(points, normals, members, frame, spacing, estimated=False, bend=None) -> CutPlane | None:
    local = (points - frame[:3, 3]) @ frame[:3, :3]
    if bend is not None:  # heights over the sheet
        local[:, 2] -= _design(local[:, :2]) @ bend
    local_normals = normals @ frame[:3, :3]
    skin = np.ones(len(points), bool)
    skin[members] = False
    band = skin & (local[:, 2] < 0) & (local[:, 2] > -RIM_BAND * spacing)
    if estimated:
        local_normals[band] = _skin_normals(local[band], local_normals[band],
                                            local[skin & (local[:, 2] < -PLANE_SPACINGS * spacing)])
    near = band & (np.abs(local_normals[:, 2]) < RIM_FLAT)
    p, m = local[near], local_normals[near]
    # along the skin towards the plane: e_z less its part along the normal
    slope = np.stack([-m[:, 2] * m[:, 0], -m[:, 2] * m[:, 1], 1.0 - m[:, 2] ** 2], 1)
    step = np.minimum(-p[:, 2] / slope[:, 2], RIM_BAND * spacing)
    rim = p[:, :2] + step[:, None] * slope[:, :2]
    if len(rim) < MIN_RIM_POINTS or np.median(np.abs(m[:, 2])) < MIN_TILT:
        return None
    return CutPlane(frame, local[members, :2], rim, m, members, bend)


def _skin_normals(points: np.ndarray, normals: np.ndarray, skin: np.ndarray) -> np.ndarray:
    """(R, 3) unit normals of (R, 3) points fitted over their RIM_NEIGHBOURS nearest (S, 3) skin
    points, turned to their (R, 3) old normals' side (kept where the skin is too sparse)."""
    if len(skin) < RIM_NEIGHBOURS or not len(points):
        return normals
    fitted = local_pca(skin, RIM_NEIGHBOURS, queries=points)[1][:, :, 0]
    return fitted * np.where(np.einsum("ij,ij->i", fitted, normals) < 0, -1.0, 1.0)[:, None]


def _flipped(plane: CutPlane) -> CutPlane:
    """The plane seen from the other side (v and n reversed): how a partner's face lies on it."""
    frame = plane.frame.copy()
    frame[:3, 1:3] *= -1.0
    flip = np.array([1.0, -1.0])
    bend = None
    if plane.bend is not None:  # h'(x, y) = -h(x, -y)
        bend = -plane.bend * (-1.0) ** _POWERS[:, 1]
    return CutPlane(frame, plane.face * flip, plane.rim * flip, plane.rim_normals * np.array([1.0, -1.0, -1.0]),
                    plane.indices, bend)


def is_thin(plane: CutPlane, spacing: float) -> bool:
    """Whether the median point of the plane's cut face lies within THIN_CUT spacings of its rim."""
    from scipy.spatial import cKDTree

    return bool(np.median(cKDTree(plane.rim).query(plane.face)[0]) <= THIN_CUT * spacing)


def _rotation(theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s], [s, c]])


def _procrustes(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray]:
    cs, ct = source.mean(0), target.mean(0)
    s, t = source - cs, target - ct
    theta = np.arctan2(np.sum(s[:, 0] * t[:, 1] - s[:, 1] * t[:, 0]), np.sum(s * t))
    return theta, ct - _rotation(theta) @ cs


def _trees(plane: CutPlane):
    from scipy.spatial import cKDTree

    return cKDTree(plane.rim_points), cKDTree(plane.face_points)


def _shares(source: CutPlane, target: CutPlane, trees, transform: np.ndarray, hit: float) -> tuple[float, float]:
    """Of source's rim points moved by the (4, 4) transform, the share within `hit` of target's rim
    with the skin's normals agreeing; of its cut face, the share within `hit` of target's."""
    rotation, shift = transform[:3, :3], transform[:3, 3]
    d, k = trees[0].query(source.rim_points @ rotation.T + shift, distance_upper_bound=hit)
    held = np.isfinite(d)
    held[held] = np.einsum("ij,ij->i", source.rim_normals_3d[held] @ rotation.T,
                           target.rim_normals_3d[k[held]]) > RIM_AGREE
    face = np.isfinite(trees[1].query(source.face_points @ rotation.T + shift, distance_upper_bound=hit)[0])
    return float(held.mean()), float(face.mean())


def fit_score(a: CutPlane, b: CutPlane, transform: np.ndarray, spacing: float, trees=None) -> float:
    """How well piece b's cut plane, moved by the (4, 4) transform carrying b onto a, lies on a's:
    the smaller share of either rim held by the other's (within RIM_HIT spacings, the skin's
    normals agreeing), times the smaller share of either cut face over the other's."""
    ta, tb = trees if trees is not None else (_trees(a), _trees(b))
    hit = RIM_HIT * spacing
    rim_b, face_b = _shares(b, a, ta, transform, hit)
    rim_a, face_a = _shares(a, b, tb, np.linalg.inv(transform), hit)
    return min(rim_a, rim_b) * min(face_a, face_b)


def plane_fits(a: CutPlane, b: CutPlane, spacing: float) -> list[tuple[float, np.ndarray]]:
    """Fits of piece b's cut plane face to face on piece a's, one per start turn (every
    RIM_TURN_STEP degrees, refined by a 2-D ICP on the rims): (`fit_score`, (4, 4) transform
    carrying b onto a), best first."""
    from scipy.spatial import cKDTree

    flipped = _flipped(b)
    rim_tree = cKDTree(a.rim)
    trees = (_trees(a), _trees(b))
    hit = RIM_HIT * spacing
    settle = (cKDTree(target := np.vstack([a.face_points, a.rim_points])), target)
    fits = []
    for start in np.radians(np.arange(0.0, 360.0, RIM_TURN_STEP)):
        rot = _rotation(start)
        shift = a.face.mean(0) - rot @ flipped.face.mean(0)
        for gate in np.geomspace(ICP_GATE * spacing, hit, ICP_ROUNDS):
            moved = flipped.rim @ rot.T + shift
            normals = np.column_stack([flipped.rim_normals[:, :2] @ rot.T, flipped.rim_normals[:, 2]])
            d, k = rim_tree.query(moved, distance_upper_bound=gate)
            ok = np.isfinite(d)
            ok[ok] = np.einsum("ij,ij->i", normals[ok], a.rim_normals[k[ok]]) > RIM_AGREE
            if ok.sum() < MIN_RIM_POINTS:
                break
            theta, shift = _procrustes(flipped.rim[ok], a.rim[k[ok]])
            rot = _rotation(theta)
        local = np.eye(4)
        local[:2, :2], local[:2, 3] = rot, shift
        transform = a.frame @ local @ np.linalg.inv(flipped.frame)
        if a.bend is not None or b.bend is not None:
            transform = _settled(b, transform, settle, spacing)
        fits.append((fit_score(a, b, transform, spacing, trees), transform))
    fits.sort(key=lambda f: -f[0])
    return fits


def _settled(b: CutPlane, transform: np.ndarray, target, spacing: float) -> np.ndarray:
    """A fit of a curved cut (b onto a by the (4, 4) transform, found in the planes of the two
    sheets, which tilt apart where they hold different parts of the cut) settled in 3-D: a
    point-to-point ICP of b's face and rim onto a's (target: (tree, points)), gated as the rims'."""
    tree, points = target
    source = np.vstack([b.face_points, b.rim_points])
    for gate in np.geomspace(ICP_GATE * spacing, RIM_HIT * spacing, ICP_ROUNDS):
        moved = apply(transform, source)
        d, k = tree.query(moved, distance_upper_bound=gate)
        ok = np.isfinite(d)
        if ok.sum() < MIN_RIM_POINTS:
            break
        transform = fit_rigid(moved[ok], points[k[ok]]) @ transform
    return transform


def apart(p: np.ndarray, q: np.ndarray, degrees: float, slide: float, centre: np.ndarray) -> bool:
    """Whether two (4, 4) poses differ by more than `degrees` of turn, or move the (3,) `centre`
    to places more than `slide` apart."""
    return (rotation_angle_deg(p[:3, :3] @ q[:3, :3].T) > degrees
            or np.linalg.norm((p[:3, :3] - q[:3, :3]) @ centre + p[:3, 3] - q[:3, 3]) > slide)


def polished_fits(planes_a: list, planes_b: list, spacing: float, contact: float, scale: float, index_of) -> list:
    """Fits of every candidate cut plane of piece b on every one of a (`plane_fits`; planes_a,
    planes_b: (CutPlane, SurfaceSample of its points, roughness) each), the POLISH best that
    differ by DISTINCT_DEG of turn or DISTINCT_SLIDE of shift (shares of `scale`) polished on the
    skin across the seam (`seam.seam_polish`, `contact` absolute) and scored again:
    [(score, (4, 4) transform carrying b onto a, (ia, ib))], best first."""
    fits = [(score, transform, (ia, ib)) for ia, (plane_a, *_) in enumerate(planes_a)
            for ib, (plane_b, *_) in enumerate(planes_b) for score, transform in plane_fits(plane_a, plane_b, spacing)]
    fits.sort(key=lambda f: -f[0])
    taken, polished = [], []
    for _, transform, (ia, ib) in fits:
        if len(taken) == POLISH:
            break
        (plane_a, sa, _), (plane_b, sb, _) = planes_a[ia], planes_b[ib]
        if not all(apart(transform, t, DISTINCT_DEG, DISTINCT_SLIDE * scale, plane_b.frame[:3, 3]) for t in taken):
            continue
        taken.append(transform)
        free = [seam.free_surface(sa.surface, sa.normals, apply(transform, sb.surface), contact),
                seam.free_surface(sb.surface, sb.normals, apply(invert(transform), sa.surface), contact)]
        transform, _ = seam.seam_polish(sa.fracture, sa.fracture_normals, sb.fracture, free[0], free[1], transform,
                                        contact, scale, index_of(sa.fracture))
        polished.append((fit_score(plane_a, plane_b, transform, spacing), transform, (ia, ib)))
    polished.sort(key=lambda f: -f[0])
    return polished
