"""Segmentation: the per-face fracture likelihood and the region cues (issue 16, item 2)."""
import numpy as np

from relicgpu import synth
from relicgpu.backends import numpy as ref
from relicgpu.params import Params
from relicgpu.segment import mesh_topology, segment
from relicgpu.segment_cues import CUE_NAMES, crease_regions, region_cues


def _box_cut_by_plane():
    import manifold3d as m3d
    box = m3d.Manifold.cube([1.0, 0.6, 0.4], center=True).refine(6)
    mesh = box.trim_by_plane([1.0, 0.0, 0.0], 0.0).to_mesh()
    return np.asarray(mesh.vert_properties[:, :3], np.float64), np.asarray(mesh.tri_verts, np.int64)


def _mesh_basics(v, f):
    topo = mesh_topology(f)
    normals, areas = ref.face_normals(v, f)
    normals, areas = np.asarray(normals, np.float64), np.asarray(areas, np.float64)
    angle = np.degrees(np.asarray(ref.edge_angles(normals, topo.edge_faces), np.float64))
    return topo, normals, areas, angle


def test_fracture_likelihood_is_in_unit_range_and_agrees_with_the_labels():
    r = synth.generate("slab", pieces=2, seed=1, faces=2000, noise=0.0005)
    frag = r.fragments[0]
    seg = segment(frag.vertices, frag.faces, Params(), frag.size, ref)
    p = seg.face_fracture_prob
    assert p.shape == (len(frag.faces),)
    assert np.all((p >= 0) & (p <= 1))
    assert np.array_equal(p > 0.5, seg.fracture_faces)
    truth = r.fracture_faces[0]
    assert p[truth].mean() > p[~truth].mean() + 0.5


def test_crease_regions_of_a_cut_box_are_its_six_faces():
    v, f = _box_cut_by_plane()
    topo, normals, areas, angle = _mesh_basics(v, f)
    region = crease_regions(normals, areas, topo, angle)
    assert region.max() + 1 == 6
    for k in range(6):
        assert np.allclose(normals[region == k], normals[region == k][0], atol=1e-9)


def test_region_cues_are_scale_free():
    v, f = _box_cut_by_plane()
    topo, normals, areas, angle = _mesh_basics(v, f)
    region = crease_regions(normals, areas, topo, angle)
    cues = region_cues(v, normals, areas, topo, angle, region).values
    assert cues.shape == (6, len(CUE_NAMES))
    big = 1000.0 * v + 5.0
    topo2, normals2, areas2, angle2 = _mesh_basics(big, f)
    cues2 = region_cues(big, normals2, areas2, topo2, angle2, region).values
    assert np.allclose(cues, cues2, atol=1e-6)
    rim_sharp = cues[:, CUE_NAMES.index("rim_sharp_share")]
    assert np.allclose(rim_sharp, 1.0)  # every face of a box is bounded by 90-degree creases
    assert cues[:, CUE_NAMES.index("largest")].sum() == 1
