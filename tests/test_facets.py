"""Flat facets laid outline to outline (`relicgpu.pair.facets`), on meshes made here."""
import numpy as np
import pytest

from relicgpu.backends import resolve
from relicgpu.pair.facets import facet_fits, flat_facets
from relicgpu.pair.icp import apply, axis_rotation, rotation_angle_deg
from relicgpu.pair.segment import segment
from relicgpu.params import Params

NORMAL = np.array([0.3, -0.5, 0.81])
NORMAL = NORMAL / np.linalg.norm(NORMAL)


def _mesh(part):
    m = part.to_mesh()
    return np.asarray(m.vert_properties, np.float64)[:, :3], np.asarray(m.tri_verts, np.int64)


def _pieces():
    """A rounded block (a box less its corners, so that no face is square) cut by an oblique plane:
    (vertices, faces) of the piece below the plane and of the piece above it."""
    import manifold3d

    solid = manifold3d.Manifold.cube([1.0, 0.7, 0.5], True) ^ manifold3d.Manifold.sphere(0.62, 96).scale([1.0, 0.8, 0.9])
    return _mesh(solid.trim_by_plane(list(-NORMAL), -0.05)), _mesh(solid.trim_by_plane(list(NORMAL), 0.05))


def _pose(seed):
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    T = np.eye(4)
    T[:3, :3] = axis_rotation(axis / np.linalg.norm(axis), rng.uniform(0.5, 3.0))
    T[:3, 3] = rng.normal(size=3)
    return T


def _facets(v, f, scale):
    seg = segment(v, f, Params(), scale, resolve("numpy"))
    return flat_facets(v, f, seg, scale)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_flat_cut_is_laid_back_on_its_partner_first(seed):
    (va, fa), (vb, fb) = _pieces()
    pose = _pose(seed)  # b scattered: the right fit carries it back, inv(pose)
    vb = apply(pose, vb)
    scale = 1.0
    facets_a, facets_b = _facets(va, fa, scale), _facets(vb, fb, scale)
    # the cut is one flat facet on each piece (the block's flat sides are facets too)
    cut_a = [f for f in facets_a if f.normal @ NORMAL > 0.999]
    assert len(cut_a) == 1, [f.normal for f in facets_a]
    fits = facet_fits(facets_a, facets_b, scale, 0.01, 3)
    assert fits, "no facet pair agrees"
    distance, T = fits[0]
    truth = np.linalg.inv(pose)
    assert distance < 0.005
    assert rotation_angle_deg(T[:3, :3] @ truth[:3, :3].T) < 2.0
    rms = np.sqrt(np.mean(np.sum((apply(T, vb) - apply(truth, vb)) ** 2, axis=1)))
    assert rms < 0.01, rms


def test_outlines_that_differ_give_no_fit():
    import manifold3d

    (va, fa), _ = _pieces()
    # a piece cut square by a plane through a triangular prism: its cut is a triangle of about the
    # rounded block's cut area, which no turn lays on that outline
    prism = manifold3d.Manifold.cylinder(1.0, 0.62, 0.62, 3).trim_by_plane([0.0, 0.0, -1.0], -0.5)
    vp, fp = _mesh(prism)
    facets_a, facets_p = _facets(va, fa, 1.0), _facets(vp, fp, 1.0)
    assert facets_p
    cut_a = [f for f in facets_a if f.normal @ NORMAL > 0.999]
    assert facet_fits(cut_a, facets_p, 1.0, 0.01, 3) == []


def test_an_outline_that_agrees_at_a_half_turn_gives_no_fit():
    import manifold3d

    # an ellipsoid cut by a plane: the cut's outline is an ellipse, the same at a half turn
    solid = manifold3d.Manifold.sphere(1.0, 160).scale([1.0, 0.7, 0.5])
    (va, fa), (vb, fb) = (_mesh(solid.trim_by_plane(list(-NORMAL), -0.12)),
                          _mesh(solid.trim_by_plane(list(NORMAL), 0.12)))
    facets_a, facets_b = _facets(va, fa, 1.0), _facets(vb, fb, 1.0)
    assert any(f.normal @ NORMAL > 0.999 for f in facets_a)
    assert facet_fits(facets_a, facets_b, 1.0, 0.01, 3) == []


def test_the_distance_field_is_within_its_bound_of_the_exact_distance():
    from scipy.spatial import cKDTree

    from relicgpu.pair.facets import Facet, _outline_distance

    rng = np.random.default_rng(0)
    # a star-shaped outline with a sharp notch (adversarial for a grid: kinks between nodes)
    t = np.linspace(0, 2 * np.pi, 90, endpoint=False)
    r = 0.3 + 0.1 * np.sin(5 * t) * (t < 5.0)
    outline = np.c_[r * np.cos(t), r * np.sin(t)]
    f = Facet(np.zeros(3), np.array([0, 0, 1.0]), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), 0.3, outline, 0.02)
    h = f.field[2]
    inside = rng.uniform(-0.35, 0.35, (4000, 2))
    beyond = rng.uniform(-2.0, 2.0, (4000, 2))
    exact = cKDTree(outline).query(inside)[0]
    read = _outline_distance(f, inside[:, 0] + 1j * inside[:, 1])
    assert np.abs(read - exact).max() <= h / np.sqrt(2) + 1e-6
    assert np.abs(read - exact).mean() < 0.1 * h  # and far closer on the whole
    exact = cKDTree(outline).query(beyond)[0]
    assert np.all(_outline_distance(f, beyond[:, 0] + 1j * beyond[:, 1]) <= exact + h / np.sqrt(2) + 1e-6)


def test_a_rescanned_flat_cut_is_one_grown_facet():
    """A Voronoi cut rescanned (noisy samples, a smoothing reconstruction, decimation): its faces
    meet at a few degrees, so its flat components are parts of it; grown from its largest face it
    is one facet."""
    import trimesh

    from relicgpu.pair.facets import grown_facets
    from relicgpu.synth import corpus

    result = corpus.generate("voronoi-noisy", 2, 0, 3000)
    for fragment, fracture in zip(result.fragments, result.fracture_faces):
        mesh = trimesh.Trimesh(fragment.vertices, fragment.faces, process=False)
        normal = (mesh.face_normals[fracture] * mesh.area_faces[fracture, None]).sum(0)
        normal /= np.linalg.norm(normal)
        cut_area = mesh.area_faces[fracture].sum()
        scale = 1.0
        seg = segment(fragment.vertices, fragment.faces, Params(), scale, resolve("numpy"))
        along = np.cos(np.radians(3.0))
        flat = [f.area / cut_area for f in flat_facets(fragment.vertices, fragment.faces, seg, scale)
                if f.normal @ normal > along]
        grown = [f.area / cut_area for f in grown_facets(fragment.vertices, fragment.faces, seg, scale)
                 if f.normal @ normal > along]
        assert max(flat, default=0.0) < 0.8, flat
        assert len(grown) == 1 and grown[0] > 0.9, grown
