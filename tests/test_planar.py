"""Flat cuts found and laid on each other (`relicgpu.pair.planar`), on clouds made here."""
import numpy as np
import trimesh

from relicgpu.backends import resolve
from relicgpu.pair import planar
from relicgpu.pair.cloudmatch import plane_samples
from relicgpu.pair.verify import index_cache
from relicgpu.params import Params
from relicgpu.pair.cloudmatch import point_spacing
from relicgpu.pair.icp import rotation_angle_deg

NORMAL = np.array([0.3, -0.5, 0.81])
NORMAL = NORMAL / np.linalg.norm(NORMAL)
OFFSET = 0.12  # the cut misses the centre, so the skin's tilt along the rim has no symmetry


def _cloud(mesh, seed, points=2500):
    p, face = trimesh.sample.sample_surface(mesh, points, seed=seed)
    return p, mesh.face_normals[face]


def _halves():
    """An ellipsoid (axes 1, 0.7, 0.5) cut by an oblique plane (manifold3d): the (N, 3) points and
    outward normals of the piece below it and of the piece above it."""
    import manifold3d

    solid = manifold3d.Manifold.sphere(1.0, 160).scale([1.0, 0.7, 0.5])

    def mesh(part):
        m = part.to_mesh()
        return trimesh.Trimesh(np.asarray(m.vert_properties)[:, :3], np.asarray(m.tri_verts))

    below = mesh(solid.trim_by_plane(list(-NORMAL), -OFFSET))
    above = mesh(solid.trim_by_plane(list(NORMAL), OFFSET))
    return _cloud(below, 1), _cloud(above, 2)


def _turn(axis, degrees):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    t = np.radians(degrees)
    return np.eye(3) + np.sin(t) * k + (1 - np.cos(t)) * k @ k


def test_the_cut_is_found_with_its_rim_and_a_prism_end_is_not():
    (points, normals), _ = _halves()
    spacing = point_spacing(points)
    planes = planar.cut_planes(points, normals, spacing)
    assert planes, "no plane found"
    cut = planes[0]
    assert cut.frame[:3, 2] @ NORMAL > 0.999  # outward: away from the piece, towards its partner
    assert abs(cut.frame[:3, 3] @ NORMAL - OFFSET) < spacing
    assert not planar.is_thin(cut, spacing)  # a solid's cut: its face reaches far from its rim
    # the rim lies on the ellipsoid: x^2 + (y / 0.7)^2 + (z / 0.5)^2 = 1, within a few spacings
    rim = cut.rim_points
    level = np.sqrt(rim[:, 0] ** 2 + (rim[:, 1] / 0.7) ** 2 + (rim[:, 2] / 0.5) ** 2)
    assert np.median(np.abs(level - 1.0)) < 2 * spacing, np.median(np.abs(level - 1.0))
    # every face of a box meets its neighbours square: each is a prism's end, none a cut
    box_points, box_normals = _cloud(trimesh.creation.box([1.0, 0.6, 0.4]), 3)
    assert planar.cut_planes(box_points, box_normals, point_spacing(box_points)) == []


def test_a_turned_and_moved_partner_is_laid_back_on_its_cut():
    (pa, na), (pb, nb) = _halves()
    turn = _turn([0.2, 1.0, -0.4], 130.0)
    shift = np.array([2.0, -1.0, 0.5])
    moved, moved_normals = pb @ turn.T + shift, nb @ turn.T
    truth = np.eye(4)
    truth[:3, :3], truth[:3, 3] = turn.T, -turn.T @ shift  # carries the moved piece back
    spacing = max(point_spacing(pa), point_spacing(moved))
    a = planar.cut_planes(pa, na, spacing)[0]
    b = planar.cut_planes(moved, moved_normals, spacing)[0]
    # the rims alone leave a near-elliptic cut a few degrees loose in its turn ...
    score, best = planar.plane_fits(a, b, spacing)[0]
    assert rotation_angle_deg(best[:3, :3] @ truth[:3, :3].T) < 8.0
    # ... the skin across the seam holds it
    params, scale = Params(), 2.0
    planes = [plane_samples(p, n, params, scale)[:1] for p, n in ((pa, na), (moved, moved_normals))]
    score, best, _ = planar.polished_fits(*planes, spacing, params.contact_distance * scale, scale,
                                          index_cache(resolve("numpy")))[0]
    assert rotation_angle_deg(best[:3, :3] @ truth[:3, :3].T) < 1.0
    gap = np.linalg.norm(moved @ best[:3, :3].T + best[:3, 3] - pb, axis=1)
    assert np.sqrt(np.mean(gap ** 2)) < spacing
    assert score > 0.5, score
    # half a turn about the cut's normal the rims and faces hold far less
    flip = np.eye(4)
    flip[:3, :3] = _turn(NORMAL, 180.0)
    flip[:3, 3] = OFFSET * NORMAL - flip[:3, :3] @ (OFFSET * NORMAL)
    assert planar.fit_score(a, b, flip @ truth, spacing) < 0.5 * planar.fit_score(a, b, truth, spacing)


def test_rim_normals_estimated_from_the_points_are_fitted_on_the_skin_alone():
    """Normals estimated from the points round a crease off (a plane fit across it takes in the
    cut face); fitted again over the skin alone, the rim's normals are the skin's."""
    from relicgpu.cloud.points import estimate_normals

    (points, normals), _ = _halves()
    estimated = estimate_normals(points)
    spacing = point_spacing(points)
    scanned = planar.cut_planes(points, normals, spacing)[0]
    rounded = planar.cut_planes(points, estimated, spacing)[0]
    refitted = planar.cut_planes(points, estimated, spacing, estimated=True)[0]

    def error(plane):  # median angle between the rim normals and the true skin normals near each rim point
        from scipy.spatial import cKDTree

        skin = np.flatnonzero(normals @ NORMAL < 0.9)
        _, near = cKDTree(points[skin]).query(plane.rim_points)
        cos = np.einsum("ij,ij->i", plane.rim_normals_3d, normals[skin][near])
        return float(np.median(np.degrees(np.arccos(np.clip(cos, -1, 1)))))

    assert error(scanned) < 4.0
    assert error(refitted) < 0.6 * error(rounded), (error(refitted), error(rounded))


def _shelf_halves():
    """A bookshelf of boards 0.04 thick (`relicgpu.synth.thin.bookshelf`) cut by an oblique plane:
    each half as 2,500 points with outward normals."""
    from relicgpu.synth import thin

    solid = thin.bookshelf(0.04)
    normal = np.array([0.45, 0.8, 0.4]) / np.linalg.norm([0.45, 0.8, 0.4])
    offset = float(normal @ [0.42, 0.15, 0.48])
    halves = []
    for k, part in enumerate((solid.trim_by_plane(list(-normal), -offset), solid.trim_by_plane(list(normal), offset))):
        assert len(part.decompose()) == 1
        m = part.to_mesh()
        halves.append(_cloud(trimesh.Trimesh(np.asarray(m.vert_properties)[:, :3], np.asarray(m.tri_verts)), 10 + k))
    return halves


def test_a_cut_through_thin_boards_is_matched_on_its_plane():
    """The cut of a bookshelf is its boards' cross-sections (a few percent of the points). Laid on
    the partner's, each half lies behind its plane and touches the other only at the seam, where
    the boards' skin runs on and their cut faces meet the partner's skin edge-on: such a fit is not
    refused for the share of its contact that faces (about 0.6 here; `planar.is_thin`)."""
    (pa, na), (pb, nb) = _shelf_halves()
    spacing = point_spacing(pa)
    assert planar.is_thin(planar.cut_planes(pa, na, spacing)[0], spacing)
    _assert_matched(pa, na, pb, nb, "a flat cut")


def _assert_matched(pa, na, pb, nb, how):
    """The second half, turned and moved, is matched onto the first (`how` in the reason) within 2
    degrees and 1% of the size (1)."""
    from relicgpu import match_pair
    from relicgpu.cloud.points import cloud_fragment

    turn, shift = _turn([0.6, -0.2, 1.0], 75.0), np.array([1.5, 0.5, -1.0])
    a = cloud_fragment("a", pa, na)
    b = cloud_fragment("b", pb @ turn.T + shift, nb @ turn.T)
    m = match_pair(a, b, Params(), backend="numpy")
    assert m.accepted and how in m.reason, m.reason
    assert rotation_angle_deg(m.transform[:3, :3] @ turn) < 2.0
    placed = b.vertices @ m.transform[:3, :3].T + m.transform[:3, 3]
    assert np.sqrt(np.mean(np.sum((placed - pb) ** 2, axis=1))) < 0.01


def _plant_halves(seed=0):
    """A potted plant (`relicgpu.synth.thin.plant`: a pot with soil, a stem, six thin leaves; the
    size 1) cut in two by a smooth curved cut (`thin.cut_in_two`): each half as 2,500 points with
    outward normals, scanned with noise 0.05% of the size."""
    from relicgpu.synth import thin

    rng = np.random.default_rng(seed)
    parts = thin.cut_in_two(thin.plant(rng), "smooth", rng)
    halves = []
    for k, part in enumerate(parts):
        m = part.to_mesh()
        p, n = _cloud(trimesh.Trimesh(np.asarray(m.vert_properties)[:, :3], np.asarray(m.tri_verts)), 100 * seed + k)
        halves.append((p + np.random.default_rng(7 * seed + k).normal(size=p.shape) * 0.0005, n))
    return halves


def test_a_curved_cut_through_a_plant_is_matched_on_its_sheet():
    """A smooth cut through a plant's pot wall, stem and leaves is a few strips of points on one
    curved surface: no plane holds it, the piece lies behind it. Grown from a plane into a height
    field over it (`planar._sheet`), it is laid on the partner's as a flat cut is."""
    (pa, na), (pb, nb) = _plant_halves()
    spacing = point_spacing(pa)
    sheets = [p for p in planar.cut_planes(pa, na, spacing) if p.bend is not None]
    assert sheets and planar.is_thin(sheets[0], spacing)
    _assert_matched(pa, na, pb, nb, "a curved cut")
