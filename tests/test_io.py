"""Loading: every fault a user can cause gives a FragmentError naming the file and the fault."""
import re

import numpy as np
import pytest
import trimesh

from relicgpu import FragmentError, load_fragment
from relicgpu.io.files import atomic_write_bytes
from relicgpu.io.fragment import fragment_from_arrays


def _box(**kw):
    return trimesh.creation.box(extents=(1, 2, 3), **kw)


@pytest.mark.parametrize("suffix", [".stl", ".ply", ".obj", ".off", ".glb"])
def test_each_format_loads(tmp_path, suffix):
    path = tmp_path / f"box{suffix}"
    _box().export(path)
    frag = load_fragment(path)
    assert frag.name == "box"
    assert frag.vertices.dtype == np.float64 and frag.faces.dtype == np.int32
    assert len(frag.faces) == 12
    assert frag.size == pytest.approx(np.sqrt(14))


def test_missing_file(tmp_path):
    with pytest.raises(FragmentError, match=r"nope\.ply: no such file"):
        load_fragment(tmp_path / "nope.ply")


def test_unknown_format(tmp_path):
    p = tmp_path / "scan.xyzw"
    p.write_text("1 2 3\n")
    with pytest.raises(FragmentError, match=r"scan\.xyzw: unknown format '\.xyzw'"):
        load_fragment(p)


def test_unreadable_file(tmp_path):
    p = tmp_path / "garbage.stl"
    p.write_bytes(b"\x00\x01 not an stl at all" * 3)
    with pytest.raises(FragmentError, match=r"garbage\.stl: (unreadable|the mesh has no faces)"):
        load_fragment(p)


def test_no_faces(tmp_path):
    p = tmp_path / "flat.off"
    p.write_text("OFF\n3 0 0\n0 0 0\n1 0 0\n0 1 0\n")
    with pytest.raises(FragmentError, match=r"flat\.off: .*(no faces|unreadable)"):
        load_fragment(p)


def test_nan_coordinates(tmp_path):
    p = tmp_path / "nan.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv nan 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n")
    with pytest.raises(FragmentError, match=r"nan\.obj: 1 vertices have NaN or infinite coordinates"):
        load_fragment(p)


def test_several_bodies_says_how_many(tmp_path):
    # issue 15: a file of several bodies no longer fails; load_fragment takes the largest and says so
    p = tmp_path / "two.stl"
    scene = trimesh.util.concatenate([_box(), _box().apply_translation([5, 0, 0]), _box().apply_translation([0, 9, 0])])
    scene.export(p)
    frag = load_fragment(p)
    assert len(frag.faces) == 12
    assert any(re.search(r"two\.stl: 3 bodies", n) for n in frag.notes)
    assert any(re.search(r"two\.stl: holds 3 bodies; using the largest", n) for n in frag.notes)


def test_degenerate_and_duplicate_faces_are_cleaned_with_a_warning():
    box = _box()
    faces = np.vstack([box.faces, box.faces[:2], [[0, 0, 1]], [[0, 1, 1]]])
    with pytest.warns(UserWarning, match="removed 2 degenerate and 2 duplicate faces"):
        frag = fragment_from_arrays("box", box.vertices, faces)
    assert len(frag.faces) == 12


def test_open_mesh_is_accepted_and_noted():
    box = _box()
    frag = fragment_from_arrays("open", box.vertices, box.faces[:-1])
    assert any("not watertight" in n for n in frag.notes)


def test_atomic_write_leaves_no_partial_file(tmp_path):
    target = tmp_path / "out.bin"
    atomic_write_bytes(target, b"first")
    assert target.read_bytes() == b"first"
    assert [p.name for p in tmp_path.iterdir()] == ["out.bin"]


def test_atomic_write_gives_the_usual_file_mode(tmp_path):
    import os
    target = tmp_path / "shared.txt"
    atomic_write_bytes(target, b"x")
    umask = os.umask(0)
    os.umask(umask)
    assert (target.stat().st_mode & 0o777) == (0o666 & ~umask)


def test_degenerate_faces_do_not_depend_on_units_or_origin():
    # issue 15 item 3: the zero-area cut is relative to the mesh's own size, not to 1 unit or the origin
    sphere = trimesh.creation.icosphere(subdivisions=5)  # faces ~0.04 across: at 1e-3 the old absolute cut took them
    v = sphere.vertices
    n = len(v)
    mid = 0.5 * (v[0] + v[1])  # a flat triangle: a vertex on the middle of an edge
    near = v[2] + 1e-15  # a sliver: twice its area under 1e-14 of the size squared
    verts = np.vstack([v, mid, near])
    extra = [[0, 1, n], [2, n + 1, 3], [4, 4, 5]]
    faces = np.vstack([sphere.faces, extra])
    kept = []
    for scale, shift in ((1.0, 0.0), (1e-3, 400.0), (1e3, -2e4)):
        with pytest.warns(UserWarning, match="degenerate"):
            frag = fragment_from_arrays("s", verts * scale + shift, faces)
        np.testing.assert_allclose((frag.vertices - shift) / scale, v, atol=1e-6)
        kept.append(frag.faces)
    assert len(kept[0]) == len(sphere.faces)  # the three added faces dropped, every real one kept
    for f in kept[1:]:
        np.testing.assert_array_equal(f, kept[0])


def test_unique_rows_on_spans_that_overflow_int64():
    # rows spanning more than 2**63 (the bit patterns of floats, as is_closed welds positions) must
    # not overflow into the one-key path: a box's 8 distinct corners were taken for 2
    from relicgpu.io.fragment import unique_rows
    from relicgpu.heap.outputs import is_closed

    box = trimesh.creation.box()
    first, inverse, counts = unique_rows(np.ascontiguousarray(box.vertices).view(np.int64))
    assert len(first) == 8 and (counts == 1).all()
    rows = np.array([[np.iinfo(np.int64).min, 0], [np.iinfo(np.int64).max, 0], [np.iinfo(np.int64).min, 0]])
    first, inverse, counts = unique_rows(rows)
    assert inverse.tolist() == [0, 1, 0] and counts.tolist() == [2, 1]
    assert is_closed(box.vertices, box.faces) and not is_closed(box.vertices, box.faces[1:])
    assert not is_closed(box.vertices, box.faces[:, ::-1])  # inside out: negative volume


def _signed_volume(v, f):
    return float(np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum()) / 6.0


def test_a_mesh_wound_inside_out_is_turned_outward_and_says_so(tmp_path):
    box = _box()
    trimesh.Trimesh(box.vertices, box.faces[:, ::-1]).export(tmp_path / "inside_out.ply")
    frag = load_fragment(tmp_path / "inside_out.ply")
    assert _signed_volume(frag.vertices, frag.faces) == pytest.approx(6.0)
    assert any("faces wound inward" in n and "inside_out.ply" in n for n in frag.notes)
    box.export(tmp_path / "right.ply")
    assert not any("wound" in n for n in load_fragment(tmp_path / "right.ply").notes)


def test_a_patch_wound_the_other_way_is_rewound_with_its_neighbours():
    sphere = trimesh.creation.icosphere(subdivisions=3)
    faces = sphere.faces.copy()
    patch = sphere.triangles_center[:, 2] > 0.5
    faces[patch] = faces[patch][:, ::-1]
    frag = fragment_from_arrays("patchy", sphere.vertices, faces)
    assert any("wound inconsistently" in n for n in frag.notes)
    mesh = trimesh.Trimesh(frag.vertices, frag.faces, process=False)
    assert mesh.is_winding_consistent and mesh.volume > 0


def test_sheets_meeting_at_an_edge_and_open_sheets_keep_their_winding():
    # two boxes sharing an edge (four faces on it) and a lone square wound either way
    both = trimesh.util.concatenate([_box(), _box().apply_translation((1, 2, 0))])
    both.merge_vertices()
    edges, counts = np.unique(np.sort(both.edges, axis=1), axis=0, return_counts=True)
    assert counts.max() == 4
    frag = fragment_from_arrays("edge", both.vertices, both.faces)
    assert not any("wound" in n for n in frag.notes)
    square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0.0]]), np.array([[0, 2, 1], [0, 3, 2]])
    assert np.array_equal(fragment_from_arrays("sheet", *square).faces, square[1])


def test_a_piece_scanned_inside_out_still_matches_its_partner(tmp_path):
    from relicgpu import match_pair
    from relicgpu.pair.icp import invert, rotation_angle_deg
    from relicgpu.synth import corpus

    r = corpus.generate("rough-clean", 2, 1, 3000)
    a, b = r.fragments
    a.to_trimesh().export(tmp_path / "a.ply")
    trimesh.Trimesh(b.vertices, b.faces[:, ::-1], process=False).export(tmp_path / "b.ply")
    m = match_pair(load_fragment(tmp_path / "a.ply"), load_fragment(tmp_path / "b.ply"), backend="numpy")
    true = invert(r.poses[0]) @ r.poses[1]
    assert m.accepted and rotation_angle_deg(m.transform[:3, :3] @ true[:3, :3].T) < 1.0  # 180 wound inward
