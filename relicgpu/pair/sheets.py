"""Boards broken across: starts from one pair of break points framed by their boards (issue 15).

A board about one point spacing thick (a bookshelf's 0.02 boards at 2,500 points a piece)
breaks as a strip a point or two wide along each broken board. Point-pair votes over such strips
are led by the boards' own narrow faces (strips too), and the fits they start are laid half a
turn off or face on face; the right pose is among none of them (bookshelves cut rough, seeds
0-11: 1 of 12 right). But one break point of each piece, with its break normal and the normal of
its board's skin beside it, fixes a pose up to the board's side: the frames
(break normal, board normal, their cross product) of a's point and of b's, b's break normal
turned to face a's. `sheet_starts` makes those poses for every pair of framed break points,
keeps the ones under which most of b's break lands on a's facing it and then most of b's skin
runs on along a's (the same normal, a board continued), and `sheet_fit` takes the one whose
skin beside the seam continues the partner's most among those that verify as a thin cut does
(`cloudmatch.thin_wall_fit`'s checks), each as it is, polished point to plane on the break, and
polished on the skin across the seam, its gate widened at first and not (`seam.seam_polish`: on
some pairs it slides the true pose off its strips; on others it is what brings a start there; the
widened gate draws some starts a percent along their strips, the usual one holds them; a pick
read off creases, mostly not break, is polished with the widened gate alone: the usual one there
let fits a degree or more off read their skin higher).

A scanned piece whose skin reads as rough as its break (`points.bulk_reads_rough`: a plant's
leaves and stem faceted at about a point spacing) picks no break by roughness; its break strip is
read off its creases instead (`crease_sample`) and started so against a partner whose pick holds its
break (`crease_fit`).

Two sherds of a wheel-made vessel share its axis of revolution, which scanned normals hold: where
nothing else fits them, they are started with one axis laid on the other (`revolution.axis_starts`:
a turn about it and a slide along it left), their breaks read as the points whose normals turn off
the axis's radius (`band_sample`), fitted as boards' starts are (`axis_fit`), and checked as sherds
of one vessel, on their seam's length rather than their picks' overlap (`axis_check`).
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..cloud.points import bulk_reads_rough, even_subsample
from .cloudmatch import PICK_SKIN_NEAR, RIM_HIT, THIN_WIDE_GATE, thin_cut_check, thin_pick, verify_clouds
from .icp import distinct_poses, refine_point_to_plane
from .revolution import axis_starts, band_points, firm, profile_tilts
from .ppf import smoothed_normals
from . import seam
from .verify import SurfaceSample

# A break point is framed by the mean normal of its SKIN_NEIGHBOURS nearest skin points (signs
# made to agree), kept where that mean, less its part along the break normal, is at least
# MIN_BOARD long (a board's face, not a corner's mix).
SKIN_NEIGHBOURS = 8
MIN_BOARD = 0.5
# Poses are scored on up to SCORE_BREAK of b's break points (landing within a contact of a's,
# normals facing under FACING), the best SCORE_KEEP again on up to SCORE_SKIN of b's skin points
# (within a contact of a's, normals within ALONG: a board run on), and the STARTS best by the sum,
# distinct, are verified. Bookshelves of 0.02 boards cut rough (seeds 0-5) and smooth (seeds 0, 2;
# `.dev/s44/sheet2.py`): a start within 8 degrees of the truth among the 16 in 7 of 8 pairs.
# At most ANCHORS framed points a piece are paired (spread evenly): bookshelves at 2,500 points
# pick 110-230, a dense cloud's pick up to `Params.icp_points` would make millions of poses.
ANCHORS = 400
SCORE_BREAK = 60
SCORE_SKIN = 400
SCORE_KEEP = 300
STARTS = 16
FACING = -0.5
ALONG = 0.7
CONTACT_SPACINGS = 1.5
POLISH_ROUNDS = 20
# Each start is polished on the skin across the seam with the gate widened (`seam.seam_polish`'s
# wide_gate) and with the usual gate: bookshelves cut smooth and rough (seeds 0-11), the widened
# gate alone left shelf02-smooth seed 2 slid 1.1% along its strips, where the usual one holds it
# (`.dev/s48/cands2.py`; docs/benchmarks.md).
BOARD_GATES = (THIN_WIDE_GATE, 0.0)
# A scanned piece whose skin reads as rough as its break (a plant's faceted leaves and stem beside
# a pot wall broken smooth) has its break strip read off its creases instead: the points whose
# normal turns more than CREASE_COS (60 degrees) from at least CREASE_SHARE of their
# CREASE_NEIGHBOURS nearest points' (a strip across a board turns 90 degrees from both faces).
CREASE_NEIGHBOURS = 12
CREASE_COS = 0.5
CREASE_SHARE = 0.3
# ... a pick that holds the leaves' rims and the pot's lip as well as the break (a tenth of it is
# break) ranks the right start lower: CREASE_STARTS distinct starts are verified from it (plant-smooth
# seeds 0, 3 and 10: the first start within 8 degrees at distinct ranks 29-64).
CREASE_STARTS = 64
# starts of two pieces' axes laid on each other (`axis_fit`) ...
AXIS_STARTS = 16
# ... and the interpenetration such a fit may have (`cloudmatch.cloud_penetration`): a sherd laid
# on the other's surface of revolution where the two overlap shares its wall. Right fits of clouds
# with scanned normals reach 0.005 (`cloudmatch.MAX_PENETRATION`'s measurement); vessel-noisy clouds
# 6-29: the right axis fits 0.000-0.003, the four wrong ones that verified 0.021-0.029.
AXIS_INSIDE = 0.01
# ... and the skin near its seam that continues the partner's, in units of the scale squared (each
# point a spacing squared): a seam along a break, not a touch at a corner. Vessel-noisy clouds 6-53,
# every axis start and polish whose skin continues at all: right fits 0.008-0.034 (median 0.020),
# those over 10 degrees off 0.001-0.022 (median 0.008, 95% under 0.016).
AXIS_SEAM = 0.016
# ... and of the free skin points near the seam, at least AXIS_SKIN continuing the partner's: the
# same starts over the seam bar, right fits 0.54-0.89, those 3-10 degrees off 0.34-0.83 (a quarter
# under 0.52; `cloudmatch.THIN_PICK_SKIN`'s 0.3 is a board's, whose right fits reach 0.43).
AXIS_SKIN = 0.5


def board_frames(sample: SurfaceSample) -> tuple[np.ndarray, np.ndarray]:
    """Each break point's frame: columns (break normal, board normal, their cross product).

    Returns
    -------
    frames : (F, 3, 3) float, rotations whose columns are the frame's axes
    which : (F,) int, the break points (of `sample.fracture`) framed; a point with no board beside
        it (no skin near, or skin normals that do not agree) has none
    """
    from scipy.spatial import cKDTree

    n = sample.fracture_normals
    on_break = cKDTree(sample.fracture).query(sample.surface)[0] <= 1e-9 * max(np.ptp(sample.surface), 1e-300)
    skin, skin_normals = sample.surface[~on_break], sample.normals[~on_break]
    if len(skin) == 0 or len(n) == 0:
        return np.zeros((0, 3, 3)), np.zeros(0, np.int64)
    _, j = cKDTree(skin).query(sample.fracture, k=min(SKIN_NEIGHBOURS, len(skin)))
    near = skin_normals[j.reshape(len(n), -1)]
    near = near * np.sign(np.einsum("pkd,pd->pk", near, near[:, 0]) + 1e-12)[:, :, None]
    board = near.mean(axis=1)
    board -= np.einsum("pd,pd->p", board, n)[:, None] * n
    length = np.linalg.norm(board, axis=1)
    which = np.flatnonzero(length >= MIN_BOARD)
    board = board[which] / length[which, None]
    frames = np.stack([n[which], board, np.cross(n[which], board)], axis=2)
    return frames, which


def _spread(sample: SurfaceSample, frames: np.ndarray, which: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    keep = even_subsample(sample.fracture[which], ANCHORS) if len(which) > ANCHORS else np.arange(len(which))
    return frames[keep], which[keep]


def sheet_starts(a: SurfaceSample, b: SurfaceSample, contact: float, count: int = STARTS) -> np.ndarray:
    """(K, 4, 4) poses carrying b onto a, best first: one for each pair of framed break points
    and each side of a's board (b's frame turned onto a's with its break normal reversed), scored
    as the module says, at most `count` distinct ones."""
    from scipy.spatial import cKDTree

    fa, ia = _spread(a, *board_frames(a))
    fb, ib = _spread(b, *board_frames(b))
    if len(ia) == 0 or len(ib) == 0:
        return np.zeros((0, 4, 4))
    flip = np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])  # break normal reversed, either board side
    targets = np.concatenate([fa @ f for f in flip])  # (2Fa, 3, 3)
    anchors = np.concatenate([a.fracture[ia]] * 2)
    rot = np.einsum("aij,bkj->abik", targets, fb).reshape(-1, 3, 3)  # target frame @ b's frame transposed
    shift = (anchors[:, None, :] - np.einsum("abij,bj->abi", rot.reshape(len(targets), len(ib), 3, 3),
                                             b.fracture[ib])).reshape(-1, 3)

    def landed(points, normals, tree, target_normals, rows, facing):
        out = np.zeros(len(rows))
        for s in range(0, len(rows), 4000):
            r = rows[s:s + 4000]
            moved = np.einsum("pij,qj->pqi", rot[r], points) + shift[r, None]
            d, j = tree.query(moved.reshape(-1, 3), distance_upper_bound=contact)
            j = np.minimum(j, len(target_normals) - 1)
            cos = np.einsum("ij,ij->i", np.einsum("pij,qj->pqi", rot[r], normals).reshape(-1, 3), target_normals[j])
            hit = (d < contact) & ((cos < FACING) if facing else (cos > ALONG))
            out[s:s + 4000] = hit.reshape(len(r), -1).sum(axis=1)
        return out

    step = max(1, len(b.fracture) // SCORE_BREAK)
    score = landed(b.fracture[::step], b.fracture_normals[::step], cKDTree(a.fracture), a.fracture_normals,
                   np.arange(len(rot)), True)
    top = np.argsort(-score, kind="stable")[:SCORE_KEEP]
    step = max(1, len(b.surface) // SCORE_SKIN)
    score = score[top] + landed(b.surface[::step], b.normals[::step], cKDTree(a.surface), a.normals, top, False)
    poses = np.tile(np.eye(4), (len(top), 1, 1))
    poses[:, :3, :3], poses[:, :3, 3] = rot[top], shift[top]
    order = np.argsort(-score, kind="stable")
    return poses[distinct_poses(poses, order, count, 2.0 * contact)]


def crease_sample(points: np.ndarray, normals: np.ndarray, sample: SurfaceSample, params, scale: float
                  ) -> SurfaceSample:
    """`sample` with its fracture points those of the (N, 3) points whose (N, 3) scanned unit normals
    turn from their neighbours' as a board's broken strip does (CREASE_SHARE), at most
    `Params.icp_points` spread evenly."""
    from scipy.spatial import cKDTree

    k = min(CREASE_NEIGHBOURS + 1, len(points))
    _, idx = cKDTree(points).query(points, k=k)
    turned = np.abs(np.einsum("nkd,nd->nk", normals[idx[:, 1:]], normals)) < CREASE_COS
    pick = np.flatnonzero(turned.mean(axis=1) >= CREASE_SHARE)
    return _with_break(sample, points[pick], normals[pick], params, scale)


def sheet_fit(skins, samples, spacing: float, params, scale: float, backend, index_of, count: int = STARTS,
              gates: tuple | None = None):
    """The fit of two boards' breaks from `sheet_starts` whose skin beside the seam continues the
    partner's most, among those that verify as `cloudmatch.thin_wall_fit`'s do (`starts_fit`):
    (transform, Verification, reason) or None. Arguments as `thin_wall_fit`'s."""
    a, b = samples
    found = starts_fit(sheet_starts(a, b, CONTACT_SPACINGS * spacing, count), skins, samples, spacing, params, scale,
                       backend, index_of, gates)
    return None if found is None else (*found[:2], f"accepted (boards' breaks framed by their boards: {found[2]} "
                                                   f"of {found[3]} skin points near the seam continue the partner's)")


def starts_fit(starts: np.ndarray, skins, samples, spacing: float, params, scale: float, backend, index_of,
               gates: tuple | None = None, check=None):
    """Of the (K, 4, 4) `starts`, each as it is, polished point to plane on the break, and polished on
    the skin across the seam with its gate widened as each of `gates` (default BOARD_GATES) says, the
    one that passes `check` (a transform -> (Verification, continuing, near) or None; default: verified
    as a thin cut is, `cloudmatch.thin_cut_check`) whose skin beside the seam continues the partner's
    most: (transform, Verification, continuing, near) or None."""
    gates = BOARD_GATES if gates is None else gates
    a, b = samples
    contact = params.contact_distance * scale
    if len(starts) == 0:
        return None
    check = check or (lambda transform: thin_cut_check(a, b, transform, spacing, params, scale, backend, index_of))
    pointwise = refine_point_to_plane(b.fracture, a.fracture, a.fracture_normals, starts, backend, POLISH_ROUNDS,
                                      2.0 * spacing, index_of(a.fracture), facing=(b.fracture_normals,
                                                                                   a.fracture_normals, FACING))
    polished = [seam.seam_polish(a.fracture, a.fracture_normals, b.fracture, *skins, s, contact, scale,
                                 index_of(a.fracture), wide)[0] for wide in gates for s in starts]
    best = None
    for transform in [*starts, *pointwise, *polished]:
        passed = check(transform)
        if passed is None:
            continue
        ver, continues, near = passed
        if best is None or continues * best[2] > best[1] * near:
            best = (transform, continues, near, ver)
    if best is None:
        return None
    transform, continues, near, ver = best
    return transform, ver, continues, near


def crease_fit(points, normals, skins, samples, spacing: float, params, scale: float, backend, index_of):
    """`sheet_fit` (CREASE_STARTS starts) of two scanned clouds, one whose skin reads as rough as its
    break (`points.bulk_reads_rough`) matched on its creases (`crease_sample`) against the other,
    whose skin does not, on its pick: (transform, Verification, reason) or None.

    Parameters
    ----------
    points, normals : the two pieces' (N_i, 3) points and scanned unit normals
    skins, samples, spacing, ... : as `sheet_fit`'s
    """
    rough = [bulk_reads_rough(p, n) for p, n in zip(points, normals)]
    if rough[0] == rough[1]:
        return None
    i = rough.index(True)
    samples = list(samples)
    samples[i] = crease_sample(points[i], normals[i], samples[i], params, scale)
    if not thin_pick(skins[i][0], samples[i], spacing):
        return None
    found = sheet_fit(skins, samples, spacing, params, scale, backend, index_of, CREASE_STARTS, (THIN_WIDE_GATE,))
    return None if found is None else (*found[:2], f"{found[2]} ({'ab'[i]}'s break read off its creases)")


def axis_fit(points, normals, skins, samples, spacing: float, params, scale: float, backend, index_of):
    """Two scanned clouds whose skins turn firmly about axes (`SurfaceSample.axis`, `revolution.firm`):
    the starts that lay one axis on the other (`revolution.axis_starts`, AXIS_STARTS voted by the
    picks' break points and as many by the bands', `band_sample`) fitted on the bands as boards'
    starts are (`starts_fit`) and checked on the picks as sherds of one vessel (`axis_check`):
    (transform, Verification, reason) or None. Arguments as `crease_fit`'s."""
    if any(s.axis is None or not firm(s.axis, scale) for s in samples):
        return None
    a, b = samples
    bands = [band_sample(p, n, s, params, scale) for p, n, s in zip(points, normals, samples)]
    starts = np.concatenate([axis_starts(x.fracture, x.fracture_normals, x.axis, y.fracture, y.fracture_normals,
                                         y.axis, params.contact_distance * scale, AXIS_STARTS)
                             for x, y in (samples, bands)])
    found = starts_fit(starts, skins, bands, spacing, params, scale, backend, index_of, check=lambda transform: (
        axis_check(points, normals, a, b, transform, spacing, params, scale, backend, index_of)))
    return None if found is None else (*found[:2], f"accepted (axis laid on axis: {found[2]} of {found[3]} skin "
                                                   f"points near the seam continue the partner's)")


def axis_check(points, normals, a: SurfaceSample, b: SurfaceSample, transform: np.ndarray, spacing: float, params,
               scale: float, backend, index_of) -> tuple | None:
    """An axis fit (b moved by the (4, 4) `transform`) checked as two sherds of one vessel are: their
    picks verified without the overlap and facing checks (the break shared along a thin band, the
    picks holding lips and bases too), at most AXIS_INSIDE of either sunk in the other, at least
    AXIS_SKIN of the free skin points near the seam continuing the partner's over at least
    AXIS_SEAM of the scale squared (`seam.skin_points`, each point standing for a spacing squared),
    and the walls beside the seam not tilting in opposite senses (`revolution.profile_tilts`: laid
    upside down): (Verification, continuing, near) or None. points, normals: the two pieces' (N_i, 3)
    points and scanned unit normals."""
    contact = params.contact_distance * scale
    ver = verify_clouds(a, b, transform, backend, max(contact, RIM_HIT * spacing), params.max_rmse * scale, 0.0,
                        params.penetration_depth * scale, index_of, min_facing=0.0)
    if not ver.accepted or ver.penetration > AXIS_INSIDE:
        return None
    continues, near = seam.skin_points(a, b, transform, contact, scale)
    if near < PICK_SKIN_NEAR or continues < AXIS_SKIN * near or continues * spacing ** 2 < AXIS_SEAM * scale ** 2:
        return None
    tilts = profile_tilts(points[0], normals[0], points[1], normals[1], a.axis, b.axis, transform, scale)
    return None if tilts[0] * tilts[1] < 0 else (ver, continues, near)


def band_sample(points: np.ndarray, normals: np.ndarray, sample: SurfaceSample, params, scale: float
                ) -> SurfaceSample:
    """`sample` with its fracture points those of the (N, 3) points whose (N, 3) scanned unit normals
    turn off its axis's radius (`revolution.band_points`: a wall's cut, and its lip), at most
    `Params.icp_points` spread evenly."""
    return _with_break(sample, *band_points(points, normals, sample.axis), params, scale)


def _with_break(sample: SurfaceSample, points: np.ndarray, normals: np.ndarray, params, scale: float) -> SurfaceSample:
    pick = even_subsample(points, params.icp_points)
    return replace(sample, fracture=points[pick], fracture_normals=normals[pick],
                   fracture_region=np.zeros(len(pick), np.int64), fracture_weight=None,
                   fracture_plane_normals=smoothed_normals(points[pick], normals[pick],
                                                           params.ppf_normal_radius * scale))


def scanned_fit(points, normals, skins, samples, spacing: float, params, scale: float, backend, index_of):
    """`crease_fit`, else `axis_fit`: the thin paths' last fits, of two clouds scanned with normals."""
    args = points, normals, skins, samples, spacing, params, scale, backend, index_of
    return crease_fit(*args) or axis_fit(*args)
