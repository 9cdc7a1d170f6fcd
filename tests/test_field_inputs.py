"""Scans from the field (issue 15, items 1, 4 and 5): files of several bodies are split and
their crumbs dropped, unreadable files are skipped, every decision is written down, the
common formats load, and fragments of one stem but different files get distinct names."""
import json

import numpy as np
import pytest
import trimesh

from relicgpu import synth
from relicgpu.cli import main
from relicgpu.io.load import fragment_ids, load_fragment, load_fragments, read_batch


def _box(extents=(1, 2, 3), at=(0, 0, 0)):
    return trimesh.creation.box(extents=extents).apply_translation(at)


def _heap_mesh():
    """A main body, a crumb (0.1% of its area) and a second large body, in one mesh."""
    return trimesh.util.concatenate([_box(), _box((0.05, 0.05, 0.05), (4, 0, 0)), _box((1, 1, 2), (0, 6, 0))])


def _garbage(path):
    path.write_bytes(b"\x00\x01 not a mesh at all" * 3)
    return path


@pytest.fixture(scope="module")
def pair_dir(tmp_path_factory):
    """Two matching synthetic pieces (ply), the first with a crumb added, and an unreadable file."""
    d = tmp_path_factory.mktemp("pair")
    r = synth.generate("vase", pieces=2, seed=3, faces=600, progress=False)
    a, b = r.fragments
    crumb = _box((0.002, 0.002, 0.002), a.vertices.max(0) + 0.5)
    trimesh.util.concatenate([a.to_trimesh(), crumb]).export(d / "a.ply")
    b.to_trimesh().export(d / "b.ply")
    _garbage(d / "broken.stl")
    return d


# --- bodies and crumbs ------------------------------------------------------------------------

def test_bodies_become_fragments_and_crumbs_are_listed(tmp_path):
    p = tmp_path / "heap.ply"
    _heap_mesh().export(p)
    frags, skipped, notes = load_fragments(p)
    assert [f.name for f in frags] == ["heap#1", "heap#2"]
    assert all(f.file == "heap.ply" for f in frags)
    assert [len(f.faces) for f in frags] == [12, 12]
    assert frags[0].size == pytest.approx(np.sqrt(14)) and frags[1].size == pytest.approx(np.sqrt(6))
    assert len(skipped) == 1 and skipped[0]["file"] == "heap.ply" and skipped[0]["name"] == "heap#3"
    assert "crumb" in skipped[0]["reason"] and "heap.ply" in skipped[0]["reason"]
    assert len(notes) == 1 and "3 bodies: kept 2 (heap#1, heap#2), dropped 1 crumb" in notes[0]


def test_one_body_and_crumbs_keeps_the_plain_name(tmp_path):
    p = tmp_path / "shard.stl"
    trimesh.util.concatenate([_box(), _box((0.01, 0.01, 0.01), (3, 0, 0))]).export(p)
    frags, skipped, _ = load_fragments(p)
    assert [f.name for f in frags] == ["shard"] and [s["name"] for s in skipped] == ["shard#2"]


def test_load_fragment_uses_the_largest_body_and_says_so(tmp_path):
    p = tmp_path / "heap.obj"
    _heap_mesh().export(p)
    frag = load_fragment(p)
    assert frag.name == "heap#1" and len(frag.faces) == 12
    assert any("holds 3 bodies; using the largest" in n for n in frag.notes)


# --- formats -------------------------------------------------------------------------------

def test_obj_with_a_missing_mtl(tmp_path):
    p = tmp_path / "tet.obj"
    p.write_text("mtllib nowhere.mtl\nusemtl stone\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n"
                 "f 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
    frag = load_fragment(p)
    assert frag.name == "tet" and frag.file == "tet.obj" and len(frag.faces) == 4


def test_ply_with_colours_and_normals(tmp_path):
    box = _box()
    box.visual.vertex_colors = np.random.default_rng(0).integers(0, 255, (len(box.vertices), 4))
    p = tmp_path / "painted.ply"
    p.write_bytes(box.export(file_type="ply", vertex_normal=True))
    header = p.read_bytes()[:600]
    assert b"property uchar red" in header and b"property float nx" in header
    frag = load_fragment(p)
    assert len(frag.faces) == 12 and frag.size == pytest.approx(np.sqrt(14))


@pytest.mark.parametrize("kind", ["stl", "stl_ascii"])
def test_binary_and_ascii_stl(tmp_path, kind):
    p = tmp_path / "box.stl"
    p.write_bytes(_box().export(file_type=kind) if kind == "stl" else _box().export(file_type=kind).encode())
    assert p.read_bytes().startswith(b"solid") == (kind == "stl_ascii")
    frag = load_fragment(p)
    assert len(frag.faces) == 12 and frag.size == pytest.approx(np.sqrt(14))


def test_glb_scene_of_two_meshes_gives_two_fragments(tmp_path):
    scene = trimesh.Scene()
    scene.add_geometry(_box(), geom_name="big")
    scene.add_geometry(trimesh.creation.icosphere(subdivisions=2, radius=0.8), geom_name="ball",
                       transform=trimesh.transformations.translation_matrix([5, 0, 0]))
    p = tmp_path / "scene.glb"
    scene.export(p)
    batch = read_batch([p])
    assert sorted(f.name for f in batch.fragments) == ["scene#1", "scene#2"]
    assert {f.file for f in batch.fragments} == {"scene.glb"}
    centres = sorted(float(f.vertices.mean(0)[0]) for f in batch.fragments)
    assert centres == pytest.approx([0.0, 5.0], abs=1e-6)  # the node transforms are applied
    assert sorted(len(f.faces) for f in batch.fragments) == [12, 320]


def test_las_without_a_reader_is_skipped_with_a_reason(tmp_path):
    pytest.importorskip("trimesh")
    try:
        import laspy  # noqa: F401
        pytest.skip("laspy is installed")
    except ImportError:
        pass
    _box().export(tmp_path / "a.ply")
    (tmp_path / "scan.las").write_bytes(b"LASF" + bytes(200))
    batch = read_batch(tmp_path)
    assert [s["file"] for s in batch.skipped] == ["scan.las"] and "laspy" in batch.skipped[0]["reason"]


# --- batches and names ---------------------------------------------------------------------

def test_an_unreadable_file_is_skipped_not_fatal(tmp_path):
    _box().export(tmp_path / "a.ply")
    _box(at=(5, 0, 0)).export(tmp_path / "b.off")
    _garbage(tmp_path / "c.stl")
    batch = read_batch(tmp_path)
    assert [f.name for f in batch.fragments] == ["a", "b"]
    assert len(batch.skipped) == 1 and batch.skipped[0]["file"] == "c.stl"
    assert "c.stl" in batch.skipped[0]["reason"]
    assert batch.messages()[0].startswith("skipped: ") and "c.stl" in batch.messages()[0]


def test_duplicate_stems_get_distinct_names(tmp_path):
    for name in ("a.ply", "a.obj", "b.stl"):
        _box().export(tmp_path / name)
    batch = read_batch(tmp_path)
    assert [(f.name, f.file) for f in batch.fragments] == [("a.obj", "a.obj"), ("a.ply", "a.ply"), ("b", "b.stl")]
    assert fragment_ids(["x/a.ply", "y/a.ply", "x/c.ply"]) == ["x/a.ply", "y/a.ply", "c"]


def test_assemble_writes_skipped_and_notes(pair_dir, tmp_path):
    from relicgpu.heap.assembly import assemble

    out = tmp_path / "out"
    files = sorted(pair_dir.iterdir())
    result = assemble(files, backend="numpy", progress=False, out_dir=out)
    assert result.names == ["a", "b"]
    doc = json.loads((out / "assembly.json").read_text())
    assert [(f["name"], f["file"]) for f in doc["fragments"]] == [("a", "a.ply"), ("b", "b.ply")]
    assert {s["file"] for s in doc["skipped"]} == {"a.ply", "broken.stl"}
    assert any(s.get("name") == "a#2" and "crumb" in s["reason"] for s in doc["skipped"])
    assert any("a.ply: 2 bodies" in n for n in doc["notes"])


# --- the command line ----------------------------------------------------------------------

def test_cli_assemble_exit_code_2_only_below_two_fragments(tmp_path, capsys):
    _box().export(tmp_path / "a.ply")
    _garbage(tmp_path / "b.stl")
    assert main(["assemble", str(tmp_path), "-o", str(tmp_path / "out"), "--backend", "numpy", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[0].startswith("skipped: ") and "b.stl" in err[0]
    assert "only 1 fragment(s) could be read" in err[-1]
    assert main(["group", str(tmp_path), "-o", str(tmp_path / "g"), "--quiet"]) == 2


def test_cli_group_skips_and_records(pair_dir, tmp_path, capsys):
    assert main(["group", str(pair_dir), "-o", str(tmp_path / "g"), "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "skipped: " in err and "broken.stl" in err and "crumb" in err
    doc = json.loads((tmp_path / "g" / "groups.json").read_text())
    assert sorted((f["name"], f["file"]) for f in doc["fragments"]) == [("a", "a.ply"), ("b", "b.ply")]
    assert {s["file"] for s in doc["skipped"]} == {"a.ply", "broken.stl"}
    assert doc["notes"]


def test_cli_group_describes_a_sparse_cloud_by_its_surface_and_skips_one_with_none(tmp_path, capsys):
    """A sparse cloud is matched on its points, but grouped on the surface it closes into; a cloud
    that closes into no solid (an open sheet) is left out of the groups, and said so."""
    d = tmp_path / "heap"
    d.mkdir()
    r = synth.generate("vase", pieces=2, seed=3, faces=600, progress=False)
    a, b = r.fragments
    a.to_trimesh().export(d / "a.ply")
    points, _ = trimesh.sample.sample_surface(b.to_trimesh(), 2500, seed=0)
    np.savetxt(d / "b.xyz", points)
    sheet = np.c_[np.random.default_rng(0).uniform(size=(2500, 2)), np.zeros(2500)]
    np.savetxt(d / "sheet.xyz", sheet)
    assert main(["group", str(d), "-o", str(tmp_path / "g"), "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "sheet.xyz" in err and "not grouped" in err
    doc = json.loads((tmp_path / "g" / "groups.json").read_text())
    assert sorted(f["name"] for f in doc["fragments"]) == ["a", "b"]
    assert [s["file"] for s in doc["skipped"]] == ["sheet.xyz"]
    assert any("matched on its points" in n for n in doc["notes"])


def test_cli_match_uses_the_largest_body_and_stops_on_unreadable(pair_dir, tmp_path, capsys):
    out = tmp_path / "m"
    assert main(["match", str(pair_dir / "a.ply"), str(pair_dir / "b.ply"), "-o", str(out),
                 "--backend", "numpy"]) == 0
    assert "using the largest" in capsys.readouterr().err
    doc = json.loads((out / "match.json").read_text())
    assert any("using the largest" in n for n in doc["notes"])
    assert main(["match", str(pair_dir / "a.ply"), str(pair_dir / "broken.stl"), "-o", str(tmp_path / "m2"),
                 "--backend", "numpy"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "broken.stl" in err[0] and err[0].startswith("relicgpu match: ")


# --- faceless clouds, open meshes and big meshes in the outputs (issue 15, items 2 and 3) ----------

def _slab_halves_as_clouds(d, n=2500):
    """The two halves of a synthetic slab, as n points each sampled from their surfaces (.xyz)."""
    r = synth.generate("slab", pieces=2, seed=0, faces=2000, progress=False)
    for k, f in enumerate(r.fragments):
        points, _ = trimesh.sample.sample_surface(f.to_trimesh(), n, seed=k)
        np.savetxt(d / f"half_{k}.xyz", points)
    return d


@pytest.fixture
def faceless(tmp_path, monkeypatch):
    """Clouds that load as CloudFragments: the triangulation is made to fail, as it does on sparse,
    thin or open scans."""
    from relicgpu.cloud import triangulate as pointcloud
    from relicgpu.io.fragment import FragmentError

    def no_solid(*a, label="", **k):
        raise FragmentError(f"{label}: no closed surface found (test)")

    monkeypatch.setattr(pointcloud, "triangulate", no_solid)
    d = tmp_path / "clouds"
    d.mkdir()
    return _slab_halves_as_clouds(d)


def test_cli_assemble_and_match_run_on_faceless_clouds(faceless, tmp_path, capsys):
    from relicgpu.cloud.points import CloudFragment

    assert all(isinstance(load_fragment(p), CloudFragment) for p in faceless.iterdir())
    out = tmp_path / "out"
    assert main(["assemble", str(faceless), "-o", str(out), "--backend", "numpy", "--quiet"]) == 0
    doc = json.loads((out / "assembly.json").read_text())
    assert [f["name"] for f in doc["fragments"]] == ["half_0", "half_1"]
    assert doc["matches"] and all("accepted" in m and m["reason"] for m in doc["matches"])
    scene = trimesh.load(out / "assembly.glb", force="scene")
    assert sorted(scene.geometry) == ["half_0", "half_1"]
    assert all(isinstance(g, trimesh.PointCloud) and len(g.vertices) == 2500 for g in scene.geometry.values())
    placed = [f for f in doc["fragments"] if f["pose"] is not None]
    if placed:  # joined: merged.stl has nothing to hold, and says why
        assert not (out / "merged.stl").exists()
        assert sum("a point cloud (no faces); left out of merged.stl" in n for n in doc["notes"]) == 2

    capsys.readouterr()
    assert main(["match", str(faceless / "half_0.xyz"), str(faceless / "half_1.xyz"), "-o", str(tmp_path / "m"),
                 "--backend", "numpy"]) == 0
    err = capsys.readouterr().err
    assert ("no match" in err or "match:" in err) and "matched on its points" in err
    doc = json.loads((tmp_path / "m" / "match.json").read_text())
    assert isinstance(doc["accepted"], bool) and doc["reason"]
    scene = trimesh.load(tmp_path / "m" / "match.glb", force="scene")
    assert all(isinstance(g, trimesh.PointCloud) for g in scene.geometry.values())


def test_merged_stl_caps_holes_and_says_what_it_could_not_close():
    from relicgpu.heap.outputs import cap_holes, merged_solid
    from relicgpu.cloud.points import cloud_fragment

    sphere = trimesh.creation.icosphere(subdivisions=3)
    centres = sphere.triangles_center
    holes = (np.linalg.norm(centres - [0, 0, 1], axis=1) < 0.3) | (np.linalg.norm(centres - [1, 0, 0], axis=1) < 0.3)
    open_sphere = fragment_from_arrays_quiet("open", sphere.vertices, sphere.faces[~holes])
    v, f, n = cap_holes(open_sphere.vertices, open_sphere.faces)
    assert n == 2 and trimesh.Trimesh(v, f, process=False).is_watertight
    box = fragment_from_arrays_quiet("box", _box().vertices, _box().faces)
    # a strip: its boundary is not a set of simple loops, so it cannot be capped into a solid
    strip = fragment_from_arrays_quiet("strip", [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], [[0, 1, 2], [1, 3, 2]])
    cloud = cloud_fragment("pts", np.c_[np.random.default_rng(0).normal(size=(50, 2)), np.zeros(50)])  # flat: no solid
    shift = np.eye(4)
    shift[:3, 3] = [5, 0, 0]
    v, f, notes = merged_solid([open_sphere, box], [np.eye(4), shift])
    merged = trimesh.Trimesh(v, f, process=False)
    assert merged.is_watertight and merged.body_count == 2
    assert notes == ["the merged solid holds 2 separate shells: fragments whose bounding boxes do not overlap "
                     "are written side by side, not united",
                     "open: open mesh; 2 hole(s) capped to make it a closed solid in merged.stl"]
    near = np.eye(4)
    near[:3, 3] = [0.5, 0, 0]  # boxes that overlap are united into one shell
    v, f, notes = merged_solid([box, box], [np.eye(4), near])
    merged = trimesh.Trimesh(v, f, process=False)
    assert merged.is_watertight and merged.body_count == 1 and notes == []
    assert np.isclose(merged.volume, 1.5 * _box().volume)
    v, f, notes = merged_solid([box, strip, cloud], [np.eye(4), shift, shift])
    assert len(f) == 12 + 2 and not trimesh.Trimesh(v, f, process=False).is_watertight
    assert any(n.startswith("strip: ") and "not watertight" in n for n in notes)
    assert any(n.startswith("pts: a point cloud (no faces); left out of merged.stl (") for n in notes), notes


def test_merged_stl_holds_the_surface_a_point_cloud_closes_into(tmp_path):
    """A cloud matched on its points (scanned with normals) is meshed for merged.stl, as it would
    have been meshed for matching; clouds alone make a merged.stl too."""
    from relicgpu.heap.outputs import merged_solid, write_merged
    from relicgpu.cloud.points import cloud_fragment

    d = np.random.default_rng(1).normal(size=(3000, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    ball = cloud_fragment("ball", d, d)
    box = fragment_from_arrays_quiet("box", _box().vertices, _box().faces)
    shift = np.eye(4)
    shift[:3, 3] = [5, 0, 0]
    v, f, notes = merged_solid([box, ball], [np.eye(4), shift])
    merged = trimesh.Trimesh(v, f, process=False)
    assert merged.is_watertight and merged.body_count == 2
    ball_volume = merged.volume - _box().volume
    assert abs(ball_volume / (4 / 3 * np.pi) - 1) < 0.05, ball_volume
    assert any(n.startswith("ball: a point cloud; meshed into ") and n.endswith(" faces for merged.stl")
               for n in notes), notes
    notes = []
    assert write_merged(tmp_path / "merged.stl", [ball, ball], [np.eye(4), shift], notes)
    merged = trimesh.load(tmp_path / "merged.stl")
    assert merged.is_watertight and merged.body_count == 2, notes


def fragment_from_arrays_quiet(name, v, f):
    import warnings

    from relicgpu.io.fragment import fragment_from_arrays
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fragment_from_arrays(name, np.asarray(v, float), np.asarray(f))


def test_big_meshes_are_thinned_at_load_and_written_in_full(tmp_path, capsys):
    from relicgpu.heap.assembly import Assembly
    from relicgpu.heap.outputs import write_outputs

    sphere = trimesh.creation.icosphere(subdivisions=7)  # 327,680 faces
    sphere.vertices *= 1 + 0.002 * np.random.default_rng(0).normal(size=(len(sphere.vertices), 1))
    sphere.export(tmp_path / "big.ply")
    _box((1, 1, 1), (3, 0, 0)).export(tmp_path / "small.ply")
    frags, _, _ = load_fragments(tmp_path / "big.ply", thin_above=100_000)
    (frag,) = frags
    err = capsys.readouterr().err
    assert "thinning" in err and "327,680 ->" in err
    assert 75_000 <= len(frag.faces) <= 125_000 and frag.thinned_from == 327_680
    assert any("327680 faces thinned to" in n and "the outputs carry the original mesh" in n for n in frag.notes)
    assert np.abs(np.linalg.norm(frag.vertices, axis=1) - 1).max() < 0.02  # still the sphere
    small = load_fragment(tmp_path / "small.ply")
    result = Assembly(["big", "small"], [np.eye(4), np.eye(4)], [0, 0], [], {}, "numpy", "local")
    write_outputs(result, [frag, small], tmp_path / "out")
    scene = trimesh.load(tmp_path / "out" / "assembly.glb", force="scene")
    assert len(scene.geometry["big"].faces) == 327_680
    merged = trimesh.load(tmp_path / "out" / "merged.stl", force="mesh")
    assert len(merged.faces) >= 327_680 + 12


def test_repeated_notes_are_one_line_a_kind():
    from relicgpu.io.load import Batch

    notes = [f"f{i}.ply: the mesh is not watertight (open boundary); accepted, as scans often are" for i in range(45)]
    notes += [f"g{i}.ply: {i + 2} bodies: kept 1 (g{i}), dropped {i + 1} crumb(s) under 1% of the largest body's area"
              for i in range(3)]
    skipped = [{"file": f"h{i}.stl", "reason": f"h{i}.stl: unreadable STL file (ValueError: bad)"} for i in range(2)]
    lines = Batch([], skipped, notes).messages()
    assert len(lines) == 3
    assert lines[0] == "skipped: h0.stl: unreadable STL file (ValueError: bad) (and 1 more like it: h1.stl; " \
                       "all listed in the JSON output)"
    assert lines[1].startswith("note: f0.ply: the mesh is not watertight") and "and 44 more like it: f1.ply, f2.ply" in lines[1]
    assert lines[2].startswith("note: g0.ply: 2 bodies") and "and 2 more like it" in lines[2]


# --- LAS/LAZ point clouds (issue 15, item 4) -----------------------------------------------------

def _write_las(path, points, normals=None, names=("NormalX", "NormalY", "NormalZ")):
    """A LAS (or, by its suffix, LAZ) file of points at 0.1 mm resolution, with normals as extra dimensions."""
    laspy = pytest.importorskip("laspy")
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.offsets = points.min(0)
    header.scales = [1e-4, 1e-4, 1e-4]
    if normals is not None:
        header.add_extra_dims([laspy.ExtraBytesParams(name=n, type=np.float32) for n in names])
    las = laspy.LasData(header)
    las.x, las.y, las.z = points.T
    if normals is not None:
        for n, column in zip(names, normals.T):
            las[n] = column.astype(np.float32)
    las.write(str(path))
    return path


def _slab_half_points(n=2500):
    r = synth.generate("slab", pieces=2, seed=0, faces=2000, progress=False)
    mesh = r.fragments[0].to_trimesh()
    points, face = trimesh.sample.sample_surface(mesh, n, seed=0)
    return points * 100 + [5000.0, -300.0, 12.0], mesh.face_normals[face]  # millimetres, far from the origin


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_las_and_laz_clouds_read_their_points_and_normals(tmp_path, suffix):
    from relicgpu.io.las import read_las
    from relicgpu.io.clouds import read_point_cloud

    laspy = pytest.importorskip("laspy")
    if suffix == ".laz" and not laspy.LazBackend.detect_available():
        pytest.skip("no LAZ backend (lazrs) installed")
    points, normals = _slab_half_points()
    path = _write_las(tmp_path / f"scan{suffix}", points, normals)
    got, got_normals, notes = read_las(path)
    assert got.dtype == np.float64 and got.shape == points.shape and notes == []
    assert np.abs(got - points).max() <= 0.5e-4 + 1e-9  # to the file's resolution
    assert np.abs(got_normals - normals).max() < 1e-6  # stored as float32, made unit again
    cloud = read_point_cloud(path)
    assert np.array_equal(cloud.points, got) and cloud.normals is not None
    frag = load_fragment(path)
    assert frag.file == f"scan{suffix}" and frag.name == "scan"
    assert np.allclose(frag.vertices.mean(0), points.mean(0), atol=0.05 * np.ptp(points, 0).max())


def test_las_normals_named_nx_ny_nz_or_absent(tmp_path):
    from relicgpu.io.las import read_las

    points, normals = _slab_half_points(500)
    _, got, _ = read_las(_write_las(tmp_path / "n.las", points, normals, ("nx", "ny", "nz")))
    assert np.abs(got - normals).max() < 1e-6
    pts, got, notes = read_las(_write_las(tmp_path / "plain.las", points))
    assert got is None and notes == [] and len(pts) == 500
    bad = normals.copy()
    bad[3] = 0
    _, got, notes = read_las(_write_las(tmp_path / "zero.las", points, bad))
    assert got is None and len(notes) == 1 and "zero.las" in notes[0] and "ignored" in notes[0]


def test_a_corrupt_las_is_one_line_naming_it_and_a_batch_skips_it(tmp_path):
    from relicgpu.io.fragment import FragmentError

    pytest.importorskip("laspy")
    points, normals = _slab_half_points()
    good = _write_las(tmp_path / "good.las", points, normals)
    data = good.read_bytes()
    (tmp_path / "cut.las").write_bytes(data[:len(data) // 2])  # truncated: half its points missing
    (tmp_path / "noise.las").write_bytes(b"LASF" + bytes(200))
    for name in ("cut.las", "noise.las"):
        with pytest.raises(FragmentError) as err:
            load_fragment(tmp_path / name)
        message = str(err.value)
        assert "\n" not in message and message.startswith(str(tmp_path / name) + ": unreadable LAS file")
    _box((30, 40, 50), (5000, 0, 0)).export(tmp_path / "box.ply")
    batch = read_batch(tmp_path)
    assert sorted(f.file for f in batch.fragments) == ["box.ply", "good.las"]
    assert sorted(s["file"] for s in batch.skipped) == ["cut.las", "noise.las"]
    assert all(s["reason"].startswith(str(tmp_path / s["file"])) for s in batch.skipped)


def test_a_union_too_big_for_memory_is_written_as_separate_shells_and_says_so(monkeypatch):
    from relicgpu.heap import outputs

    box = fragment_from_arrays_quiet("box", _box().vertices, _box().faces)
    near = np.eye(4)
    near[:3, 3] = [0.5, 0, 0]
    monkeypatch.setattr(outputs, "UNION_MEMORY", 24 * outputs.UNION_BYTES_PER_FACE - 1)  # one face short
    v, f, notes = outputs.merged_solid([box, box], [np.eye(4), near])
    assert len(f) == 24 and trimesh.Trimesh(v, f, process=False).body_count == 2  # both whole, not united
    assert len(notes) == 1 and notes[0].startswith("box, box: not united in merged.stl")
    assert "24 faces" in notes[0] and "not one watertight solid" in notes[0]
    monkeypatch.setattr(outputs, "UNION_MEMORY", 24 * outputs.UNION_BYTES_PER_FACE)  # fits: one solid
    v, f, notes = outputs.merged_solid([box, box], [np.eye(4), near])
    merged = trimesh.Trimesh(v, f, process=False)
    assert notes == [] and merged.is_watertight and np.isclose(merged.volume, 1.5 * _box().volume)


def test_a_union_whose_sheets_touch_at_an_edge_is_written_closed(monkeypatch):
    from relicgpu.heap import outputs

    box = fragment_from_arrays_quiet("box", _box().vertices, _box().faces)
    corner = np.eye(4)
    corner[:3, 3] = [1, 2, 0]  # the two boxes touch along one edge: four faces meet there, by position
    v, f, notes = outputs.merged_solid([box, box], [np.eye(4), corner])
    merged = trimesh.Trimesh(v, f)  # welded by position, as an STL reader does
    assert notes == [] and len(f) == 24 and merged.is_watertight and np.isclose(merged.volume, 2 * _box().volume)
    # without the two copies of the edge moved apart the file is not closed, and says so
    monkeypatch.setattr(outputs, "separate_pinches", lambda vertices, faces: np.array(vertices))
    v0, f0, notes = outputs.merged_solid([box, box], [np.eye(4), corner])
    assert np.array_equal(f0, f) and not trimesh.Trimesh(v0, f0).is_watertight
    assert 0 < np.abs(v - v0).max() < 1e-4  # a hair
    assert len(notes) == 1 and notes[0].startswith("box, box: their union is not closed as merged.stl stores it")
    assert notes[0].endswith("so merged.stl is not watertight there")


def test_a_cloud_whose_normals_point_inward_is_turned_outward_and_matches():
    from relicgpu import match_pair
    from relicgpu.cloud.points import cloud_fragment
    from relicgpu.pair.icp import invert, rotation_angle_deg
    from relicgpu.synth import corpus

    r = corpus.generate("rough-clean", pieces=2, seed=0, faces=4000)
    clouds = []
    for k, (f, sign) in enumerate(zip(r.fragments, (1.0, -1.0))):
        points, face = trimesh.sample.sample_surface(f.to_trimesh(), 2500, seed=k)
        clouds.append(cloud_fragment(f.name, points, sign * f.to_trimesh().face_normals[face], source=f"{f.name}.ply"))
    assert not clouds[0].notes
    assert clouds[1].notes == (f"{r.fragments[1].name}.ply: the given normals point into the solid; turned outward",)
    m = match_pair(*clouds, backend="numpy")
    true = invert(r.poses[0]) @ r.poses[1]
    assert m.accepted and rotation_angle_deg(m.transform[:3, :3] @ true[:3, :3].T) < 2.0


def test_a_cloud_whose_normals_are_signed_at_random_is_turned_outward_point_by_point():
    """Normals exported unoriented (a plane fit's sign is arbitrary): a global turn cannot mend
    them; each is turned to the side the views from around the cloud see it from, as estimated
    normals are, and the pair matches."""
    from relicgpu import match_pair
    from relicgpu.cloud.points import cloud_fragment
    from relicgpu.pair.icp import invert, rotation_angle_deg
    from relicgpu.synth import corpus

    r = corpus.generate("rough-clean", pieces=2, seed=0, faces=4000)
    rng = np.random.default_rng(3)
    clouds, signs = [], []
    for k, f in enumerate(r.fragments):
        points, face = trimesh.sample.sample_surface(f.to_trimesh(), 2500, seed=k)
        true = f.to_trimesh().face_normals[face]
        sign = rng.choice([-1.0, 1.0], (len(points), 1)) if k == 1 else np.ones((len(points), 1))
        clouds.append(cloud_fragment(f.name, points, sign * true, source=f"{f.name}.ply"))
        signs.append(np.einsum("ij,ij->i", clouds[-1].normals, true))
    assert not clouds[0].notes and np.all(signs[0] > 0)
    assert len(clouds[1].notes) == 1 and clouds[1].notes[0].endswith("turned outward point by point"), clouds[1].notes
    assert np.mean(signs[1] < 0) < 0.02  # as the visibility votes turn a plane fit's
    m = match_pair(*clouds, backend="numpy")
    true = invert(r.poses[0]) @ r.poses[1]
    assert m.accepted and rotation_angle_deg(m.transform[:3, :3] @ true[:3, :3].T) < 2.0
