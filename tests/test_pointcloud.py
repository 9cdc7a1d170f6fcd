"""relicgpu.cloud: point-cloud readers and triangulation into closed meshes."""
from __future__ import annotations

import importlib.util
import struct

import numpy as np
import pytest
import trimesh

from relicgpu.cloud import triangulate as pc
from relicgpu.cloud.points import choose_voxel, voxel_thin
from relicgpu.io.clouds import read_point_cloud
from relicgpu.io.fragment import FragmentError, count_bodies, is_watertight
from relicgpu.io.load import load_fragment


# --- helpers -----------------------------------------------------------------

def sphere_points(n=20000, radius=1.0, seed=0, noise=0.0):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    r = radius * (1.0 + rng.uniform(-noise, noise, (n, 1)))
    return d * r, d


def surface_points(mesh, n, seed=0, noise=0.0):
    """n points uniform on the surface, each moved by up to noise * size in a random direction."""
    p, _ = trimesh.sample.sample_surface(mesh, n, seed=seed)
    if noise:
        rng = np.random.default_rng(seed + 1)
        d = rng.normal(size=p.shape)
        d /= np.linalg.norm(d, axis=1)[:, None]
        p = p + d * rng.uniform(0.0, noise * float(np.linalg.norm(mesh.extents)), (len(p), 1))
    return p


def hausdorff(a: trimesh.Trimesh, b: trimesh.Trimesh, n=20000) -> float:
    """Symmetric Hausdorff distance, from n surface samples of each mesh to the other surface."""
    pa, _ = trimesh.sample.sample_surface(a, n, seed=11)
    pb, _ = trimesh.sample.sample_surface(b, n, seed=12)
    _, da, _ = trimesh.proximity.closest_point(b, pa)
    _, db, _ = trimesh.proximity.closest_point(a, pb)
    return float(max(da.max(), db.max()))


def assert_closed_outward_one_body(vertices, faces):
    import manifold3d as mf

    v, f = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
    assert is_watertight(f)
    assert count_bodies(v, f) == 1
    # every directed edge once, and its reverse once: a consistently wound closed manifold
    d = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    key, rkey = d[:, 0] * len(v) + d[:, 1], d[:, 1] * len(v) + d[:, 0]
    assert len(np.unique(key)) == len(key)
    assert np.isin(rkey, key).all()
    # outwards: positive enclosed volume
    vol = np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6.0
    assert vol > 0
    # no two vertices at one place (a pinched surface would have them)
    assert len(np.unique(v, axis=0)) == len(v)
    m = mf.Manifold(mf.Mesh64(np.ascontiguousarray(v), np.ascontiguousarray(f, np.uint64)))
    assert m.status() == mf.Error.NoError
    return vol


# --- readers -------------------------------------------------------------------

def test_xyz_reader_with_comments_commas_and_normals(tmp_path):
    pts, nrm = sphere_points(50)
    p3 = tmp_path / "a.xyz"
    p3.write_text("# scanner export\n\n" + "\n".join(f"{x} {y} {z}" for x, y, z in pts) + "\n")
    cloud = read_point_cloud(p3)
    assert np.allclose(cloud.points, pts) and cloud.normals is None
    p6 = tmp_path / "b.asc"
    p6.write_text("\n".join(",".join(f"{c:.17g}" for c in row) for row in np.hstack([pts, nrm])) + "\n")
    cloud = read_point_cloud(p6)
    assert np.allclose(cloud.points, pts) and np.allclose(cloud.normals, nrm)
    # six columns that are not unit normals (colours) are accepted and ignored, with a note
    p7 = tmp_path / "c.txt"
    p7.write_text("\n".join(f"{x} {y} {z} 200 10 30" for x, y, z in pts))
    cloud = read_point_cloud(p7)
    assert cloud.normals is None and any("not unit normals" in n for n in cloud.notes)


def write_pcd(path, fields, sizes, types, rows, mode="ascii", counts=None, width=None, height=1, cut=0):
    n = len(rows)
    counts = counts or [1] * len(fields)
    head = ["# .PCD v0.7 - Point Cloud Data file format", "VERSION 0.7", "FIELDS " + " ".join(fields),
            "SIZE " + " ".join(map(str, sizes)), "TYPE " + " ".join(types), "COUNT " + " ".join(map(str, counts)),
            f"WIDTH {width or n}", f"HEIGHT {height}", "VIEWPOINT 0 0 0 1 0 0 0", f"POINTS {n}", f"DATA {mode}"]
    data = ("\n".join(head) + "\n").encode()
    if mode == "ascii":
        data += ("\n".join(" ".join(repr(float(c)) if t == "F" else str(int(c)) for c, t in
                                    zip(row, [t for t, k in zip(types, counts) for _ in range(k)])) for row in rows) + "\n").encode()
    else:
        codes = {("F", 4): "f", ("F", 8): "d", ("U", 1): "B", ("U", 4): "I", ("I", 4): "i"}
        fmt = "<" + "".join(codes[t, s] * k for t, s, k in zip(types, sizes, counts))
        body = b"".join(struct.pack(fmt, *[int(c) if fmt[1 + i] in "BIi" else float(c) for i, c in enumerate(row)])
                        for row in rows)
        data += body[: len(body) - cut]
    path.write_bytes(data)


def test_pcd_ascii_and_binary_with_normals_and_other_fields(tmp_path):
    pts, nrm = sphere_points(40)
    rgb = np.full((40, 1), 4278190335.0)
    rows = np.hstack([pts, rgb, nrm, np.ones((40, 2))])
    fields = ["x", "y", "z", "rgb", "normal_x", "normal_y", "normal_z", "curvature"]
    sizes = [4, 4, 4, 4, 4, 4, 4, 4]
    types = ["F", "F", "F", "U", "F", "F", "F", "F"]
    counts = [1, 1, 1, 1, 1, 1, 1, 2]
    for mode in ("ascii", "binary"):
        path = tmp_path / f"{mode}.pcd"
        write_pcd(path, fields, sizes, types, rows, mode, counts)
        cloud = read_point_cloud(path)
        assert np.allclose(cloud.points, pts, atol=1e-6), mode
        assert np.allclose(cloud.normals, nrm, atol=1e-6), mode


def test_pcd_organised_cloud_drops_nan_pixels(tmp_path):
    pts, _ = sphere_points(60)
    rows = pts.copy()
    rows[::7] = np.nan
    path = tmp_path / "grid.pcd"
    write_pcd(path, ["x", "y", "z"], [4, 4, 4], ["F", "F", "F"], rows, "binary", width=10, height=6)
    cloud = read_point_cloud(path)
    assert len(cloud.points) == 60 - len(rows[::7])
    assert any("dropped 9 NaN points" in n for n in cloud.notes)


def test_ply_point_clouds_ascii_and_binary_go_through_load_fragment(tmp_path):
    pts, nrm = sphere_points(pc.MATCH_POINTS)
    header = ("ply\nformat {fmt} 1.0\ncomment points only\nelement vertex {n}\nproperty float x\nproperty float y\n"
              "property float z\nproperty float nx\nproperty float ny\nproperty float nz\nelement face 0\n"
              "property list uchar int vertex_indices\nend_header\n")
    table = np.hstack([pts, nrm]).astype("<f4")
    (tmp_path / "a.ply").write_bytes(header.format(fmt="ascii", n=len(pts)).encode()
                                     + "\n".join(" ".join(map(repr, r.tolist())) for r in table).encode() + b"\n")
    (tmp_path / "b.ply").write_bytes(header.format(fmt="binary_little_endian", n=len(pts)).encode() + table.tobytes())
    (tmp_path / "c.ply").write_bytes(header.format(fmt="binary_big_endian", n=len(pts)).encode()
                                     + table.astype(">f4").tobytes())
    for name in ("a", "b", "c"):
        cloud = read_point_cloud(tmp_path / f"{name}.ply")
        assert np.allclose(cloud.points, pts, atol=1e-6) and np.allclose(cloud.normals, nrm, atol=1e-6)
    frag = load_fragment(tmp_path / "b.ply")  # with normals: matched on its points
    assert frag.name == "b" and len(frag.faces) == 0 and np.allclose(frag.normals, nrm, atol=1e-6)
    (tmp_path / "d.ply").write_bytes(header.replace("property float nx\nproperty float ny\nproperty float nz\n", "")
                                     .format(fmt="binary_little_endian", n=len(pts)).encode()
                                     + pts.astype("<f4").tobytes())
    frag = load_fragment(tmp_path / "d.ply")  # without: meshed
    assert frag.name == "d" and len(frag.faces) > 0
    assert is_watertight(frag.faces) and count_bodies(frag.vertices, frag.faces) == 1
    assert any(f"triangulated {pc.MATCH_POINTS} points" in n for n in frag.notes)


def test_zero_normals_in_a_ply_take_their_nearest_point_s_and_mostly_zero_ones_are_ignored(tmp_path):
    """A scanner writes nx = ny = nz = 0 where it had no normal: a cloud matched on its points would
    use them as they are."""
    pts, nrm = sphere_points(400)
    header = ("ply\nformat binary_little_endian 1.0\nelement vertex {n}\nproperty float x\nproperty float y\n"
              "property float z\nproperty float nx\nproperty float ny\nproperty float nz\nend_header\n")
    some = nrm.copy()
    some[::10] = 0.0
    (tmp_path / "some.ply").write_bytes(header.format(n=400).encode() + np.hstack([pts, some]).astype("<f4").tobytes())
    cloud = read_point_cloud(tmp_path / "some.ply")
    assert np.allclose(np.linalg.norm(cloud.normals, axis=1), 1.0, atol=1e-6)
    assert (cloud.normals[::10] @ np.ones(3) != 0).all() and (np.einsum("ij,ij->i", cloud.normals, nrm) > 0.8).all()
    assert any("40 points have a zero normal; each takes its nearest point's" in n for n in cloud.notes)
    most = np.zeros_like(nrm)
    most[::10] = nrm[::10]
    (tmp_path / "most.ply").write_bytes(header.format(n=400).encode() + np.hstack([pts, most]).astype("<f4").tobytes())
    cloud = read_point_cloud(tmp_path / "most.ply")
    assert cloud.normals is None and any("360 of 400 normals are zero; normals ignored" in n for n in cloud.notes)


def test_a_cloud_with_normals_or_a_sparse_one_is_matched_on_its_points(tmp_path):
    """A cloud scanned with normals, sparse or dense, and one without normals with fewer points
    than a mesh for matching needs: not meshed, though each closes (a sphere); every point kept."""
    from relicgpu.cloud.points import CloudFragment

    for n in (3000, pc.MATCH_POINTS - 1, 2 * pc.MATCH_POINTS):
        pts, nrm = sphere_points(n)
        np.savetxt(tmp_path / "s.xyz", np.hstack([pts, nrm]))
        frag = load_fragment(tmp_path / "s.xyz")
        assert isinstance(frag, CloudFragment) and len(frag.faces) == 0 and len(frag.vertices) == n
        assert np.allclose(frag.normals, nrm)
        assert any(f"{n} points with normals; matched on its points and their normals" in m
                   for m in frag.notes), frag.notes
    np.savetxt(tmp_path / "s.xyz", pts[:3000])
    frag = load_fragment(tmp_path / "s.xyz")
    assert isinstance(frag, CloudFragment) and frag.normals is None and len(frag.vertices) == 3000
    assert any(f"3000 points, fewer than the {pc.MATCH_POINTS} a mesh for matching needs; matched on its points" in m
               for m in frag.notes), frag.notes


def test_a_cloud_is_meshed_once_for_grouping_and_merged_stl(monkeypatch):
    """`surface_of` meshes a cloud once while it lives (`relicgpu group` asks twice), and says a
    cloud that closes into no solid is none each time it is asked."""
    from relicgpu.cloud.points import cloud_fragment

    calls = []
    real = pc.mesh_for_matching
    monkeypatch.setattr(pc, "mesh_for_matching", lambda *a, **k: calls.append(1) or real(*a, **k))
    pts, nrm = sphere_points(4000)
    ball = cloud_fragment("ball", pts, nrm)
    first = pc.surface_of(ball)
    assert pc.surface_of(ball) is first and len(calls) == 1
    assert_closed_outward_one_body(first.vertices, first.faces)
    assert pc.surface_of(cloud_fragment("ball", pts, nrm)) is not first and len(calls) == 2  # another cloud
    sheet = cloud_fragment("sheet", np.c_[np.random.default_rng(0).uniform(size=(3000, 2)), np.zeros(3000)])
    for _ in range(2):
        with pytest.raises(FragmentError, match="sheet"):
            pc.surface_of(sheet)
    assert len(calls) == 3


def test_npy_points_and_points_with_normals(tmp_path):
    pts, nrm = sphere_points(30)
    np.save(tmp_path / "a.npy", pts)
    np.save(tmp_path / "b.npy", np.hstack([pts, nrm]).astype(np.float32))
    assert np.allclose(read_point_cloud(tmp_path / "a.npy").points, pts)
    cloud = read_point_cloud(tmp_path / "b.npy")
    assert np.allclose(cloud.points, pts, atol=1e-6) and np.allclose(cloud.normals, nrm, atol=1e-6)


def _lines(n=30):
    pts, _ = sphere_points(n)
    return [f"{x:.6f} {y:.6f} {z:.6f}" for x, y, z in pts]


def _bad_xyz_columns(p):
    lines = _lines()
    lines[11] = "0.5 0.25"
    p.write_text("# header comment\n" + "\n".join(lines))
    return "line 13 has 2 columns, earlier lines have 3"


def _bad_xyz_first_line(p):
    p.write_text("\n".join(["1 2 3 4"] + _lines()))
    return "line 1 has 4 columns; expected 3 (x y z) or 6"


def _bad_xyz_text(p):
    lines = _lines()
    lines[4] = "0.1 abc 0.3"
    p.write_text("\n".join(lines))
    return "line 5, column 2: 'abc' is not a number"


def _bad_xyz_nan(p):
    lines = _lines()
    lines[20] = "0.1 nan 0.3"
    p.write_text("\n\n" + "\n".join(lines))
    return "1 points have NaN or infinite coordinates (first at line 23)"


def _bad_xyz_inf(p):
    lines = _lines()
    lines[2] = "inf 0 0"
    p.write_text("\n".join(lines))
    return "(first at line 3)"


def _too_few(p):
    p.write_text("\n".join(_lines(5)))
    return "too few points (5)"


def _empty(p):
    p.write_text("# nothing here\n")
    return "no points"


def _pcd_truncated(p):
    pts, _ = sphere_points(50)
    write_pcd(p, ["x", "y", "z"], [4, 4, 4], ["F", "F", "F"], pts, "binary", cut=7)
    return "truncated binary PCD: header declares 50 points of 12 bytes (600 bytes), the file holds 593"


def _pcd_compressed(p):
    p.write_bytes(b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 50\nHEIGHT 1\n"
                  b"POINTS 50\nDATA binary_compressed\n\x00\x00")
    return "'DATA binary_compressed' is unsupported"


def _pcd_no_z(p):
    p.write_bytes(b"VERSION 0.7\nFIELDS x y\nSIZE 4 4\nTYPE F F\nCOUNT 1 1\nWIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA ascii\n1 2\n")
    return "PCD has no 'z' field"


def _pcd_ascii_text(p):
    pts, _ = sphere_points(30)
    write_pcd(p, ["x", "y", "z"], [4, 4, 4], ["F", "F", "F"], pts, "ascii")
    lines = p.read_text().splitlines()
    lines[15] = "0.1 0.2 zz"
    p.write_text("\n".join(lines))
    return "line 16, column 3: 'zz' is not a number"


def _ply_truncated(p):
    pts, _ = sphere_points(40)
    p.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 40\nproperty float x\nproperty float y\n"
                  b"property float z\nend_header\n" + pts.astype("<f4").tobytes()[:-5])
    return "truncated binary PLY: header declares 40 vertices of 12 bytes (480 bytes), the file holds 475"


def _npy_truncated(p):
    np.save(p, sphere_points(40)[0])
    p.write_bytes(p.read_bytes()[:-20])
    return "unreadable or truncated .npy file"


def _npy_shape(p):
    np.save(p, np.zeros((40, 4)))
    return ".npy array has shape (40, 4); expected (N, 3) points or (N, 6)"


MALFORMED = {
    "columns.xyz": _bad_xyz_columns, "first.xyz": _bad_xyz_first_line, "text.asc": _bad_xyz_text,
    "nan.txt": _bad_xyz_nan, "inf.xyz": _bad_xyz_inf, "few.xyz": _too_few, "empty.xyz": _empty,
    "trunc.pcd": _pcd_truncated, "compressed.pcd": _pcd_compressed, "noz.pcd": _pcd_no_z,
    "text.pcd": _pcd_ascii_text, "trunc.ply": _ply_truncated, "trunc.npy": _npy_truncated, "shape.npy": _npy_shape,
}


@pytest.mark.parametrize("name", sorted(MALFORMED))
def test_malformed_files_name_the_file_and_the_fault(tmp_path, name):
    path = tmp_path / name
    expected = MALFORMED[name](path)
    with pytest.raises(FragmentError) as info:
        load_fragment(path)
    message = str(info.value)
    assert message.startswith(str(path)), message
    assert expected in message, message


def test_flat_points_are_refused():
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(size=(500, 2)), np.zeros(500)]
    with pytest.raises(FragmentError, match="span no volume"):
        pc.triangulate(pts, label="flat.xyz")


# --- triangulation -------------------------------------------------------------

def test_sphere_gives_a_closed_outward_single_body_within_one_percent():
    pts, _ = sphere_points(20000, noise=0.001)
    res = pc.triangulate(pts)
    vol = assert_closed_outward_one_body(res.vertices, res.faces)
    assert abs(vol / (4 / 3 * np.pi) - 1) < 0.01
    size = 2 * np.sqrt(3)
    mesh = trimesh.Trimesh(res.vertices, res.faces, process=False)
    # distances to the true sphere: of the mesh's surface, and of the sphere's points to the mesh
    on_mesh, _ = trimesh.sample.sample_surface(mesh, 50000, seed=3)
    assert np.abs(np.linalg.norm(on_mesh, axis=1) - 1).max() < 0.01 * size
    on_sphere, _ = sphere_points(20000, seed=5)
    _, d, _ = trimesh.proximity.closest_point(mesh, on_sphere)
    assert d.max() < 0.01 * size
    assert mesh.euler_number == 2


def test_box_gives_a_closed_single_body_within_one_percent():
    box = trimesh.creation.box((1.0, 0.7, 0.4))
    res = pc.triangulate(surface_points(box, 15000, noise=0.001))
    vol = assert_closed_outward_one_body(res.vertices, res.faces)
    assert abs(vol / box.volume - 1) < 0.02
    mesh = trimesh.Trimesh(res.vertices, res.faces, process=False)
    assert hausdorff(mesh, box) < 0.01 * np.linalg.norm(box.extents)


def test_a_ring_keeps_its_hole():
    torus = trimesh.creation.torus(1.0, 0.3)
    res = pc.triangulate(surface_points(torus, 15000))
    assert_closed_outward_one_body(res.vertices, res.faces)
    mesh = trimesh.Trimesh(res.vertices, res.faces, process=False)
    assert mesh.euler_number == 0  # genus 1
    assert hausdorff(mesh, torus) < 0.01 * np.linalg.norm(torus.extents)


def test_a_small_hole_in_the_scan_is_closed_over_with_a_note():
    pts, _ = sphere_points(20000, seed=4)
    pts = pts[pts[:, 2] < 0.99]  # a cap of radius 0.14 left unscanned
    res = pc.triangulate(pts)
    assert_closed_outward_one_body(res.vertices, res.faces)
    assert any("alpha grown" in n for n in res.notes)
    mesh = trimesh.Trimesh(res.vertices, res.faces, process=False)
    on_mesh, _ = trimesh.sample.sample_surface(mesh, 30000, seed=3)
    assert np.abs(np.linalg.norm(on_mesh, axis=1) - 1).max() < 0.01 * 2 * np.sqrt(3)


def test_thinning_keeps_large_clouds_under_max_points():
    pts, _ = sphere_points(60000, noise=0.0005)
    voxel = choose_voxel(pts, 20000)
    thin = voxel_thin(pts, voxel)
    assert 0.8 * 20000 < len(thin) <= 20000
    res = pc.triangulate(pts, max_points=20000)
    assert res.n_input == 60000 and res.n_meshed == len(thin) and res.voxel == voxel
    assert_closed_outward_one_body(res.vertices, res.faces)
    assert np.abs(np.linalg.norm(res.vertices, axis=1) - 1).max() < 0.01 * 2 * np.sqrt(3)


def test_decimate_keeps_a_closed_surface_within_its_tolerance():
    from relicgpu.cloud.refine import closed_manifold_fault, decimate

    sphere = trimesh.creation.icosphere(5)  # 20,480 faces
    v, f, tolerance = decimate(sphere.vertices + 1000.0, sphere.faces, 3000)  # far from the origin
    assert closed_manifold_fault(v, f) is None
    assert 1000 < len(f) <= 3000 and 0 < tolerance < 0.05
    assert np.abs(np.linalg.norm(v - 1000.0, axis=1) - 1).max() <= tolerance + 1e-4
    assert decimate(sphere.vertices, sphere.faces, 30000)[1].shape == sphere.faces.shape  # small enough
    assert decimate(sphere.vertices, sphere.faces[:-1], 3000) is None  # open: not a closed manifold


def test_points_far_from_the_body_are_left_out():
    pts, _ = sphere_points(15000)
    stray = np.array([[3.0, 0.0, 0.0], [3.01, 0.0, 0.0], [0.0, -4.0, 0.5]])
    res = pc.triangulate(np.vstack([pts, stray]))
    assert_closed_outward_one_body(res.vertices, res.faces)
    assert np.linalg.norm(res.vertices, axis=1).max() < 1.01


# --- command line --------------------------------------------------------------

def test_mesh_command_writes_a_closed_mesh_beside_the_cloud(tmp_path, capsys):
    from relicgpu.cli import main

    pts, _ = sphere_points(8000)
    cloud = tmp_path / "scan.xyz"
    cloud.write_text("\n".join(f"{x} {y} {z}" for x, y, z in pts))
    out = tmp_path / "scan_mesh.ply"
    assert main(["mesh", str(cloud), "-o", str(out), "--quiet"]) == 0
    frag = load_fragment(out)
    assert is_watertight(frag.faces) and count_bodies(frag.vertices, frag.faces) == 1
    assert "faces from 8000 points" in capsys.readouterr().out
    assert main(["mesh", str(cloud), "-o", str(out), "--faces", "4000", "--quiet"]) == 0  # decimated
    few = load_fragment(out)
    assert len(few.faces) <= 4000 and is_watertight(few.faces) and count_bodies(few.vertices, few.faces) == 1
    assert main(["mesh", str(cloud), "--quiet"]) == 0  # default output name
    assert (tmp_path / "scan_mesh.ply").exists()
    assert main(["mesh", str(cloud), "-o", str(cloud)]) == 2
    assert "refusing to overwrite an input" in capsys.readouterr().err
    assert main(["mesh", str(cloud), "-o", str(tmp_path / "x.vtk")]) == 2
    assert "unknown mesh format" in capsys.readouterr().err
    assert main(["mesh", str(tmp_path / "missing.pcd")]) == 2
    assert "missing.pcd: no such file" in capsys.readouterr().err


# --- the issue's check: synthetic fragments, sampled, meshed again, matched -------

def _have(module: str, attr: str | None = None) -> bool:
    try:
        if importlib.util.find_spec(module) is None:
            return False
        mod = importlib.import_module(module)
    except ImportError:
        return False
    return attr is None or hasattr(mod, attr)


needs_synth = pytest.mark.skipif(not _have("relicgpu.synth", "generate"), reason="relicgpu.synth is not installed yet")
needs_pipeline = pytest.mark.skipif(not _have("relicgpu.pair.pipeline", "match_pair"),
                                    reason="relicgpu.pair.pipeline.match_pair is not installed yet")


@needs_synth
def test_a_dense_cloud_of_a_fragment_loads_within_one_percent_of_its_size(tmp_path):
    """Issue 15: 60,000 points, noise 0.05% of the size; meshed dense and decimated. Measured: 0.80%
    of the largest side, 1.36% when the cloud was thinned before meshing."""
    from relicgpu import synth

    source = synth.generate("torso", pieces=2, seed=0, progress=False).fragments[0].to_trimesh()
    side = float(source.extents.max())
    pts, _ = trimesh.sample.sample_surface(source, 60000, seed=1)
    pts = pts + np.random.default_rng(2).normal(size=pts.shape) * 0.0005 * side
    np.save(tmp_path / "torso.npy", pts)
    frag = load_fragment(tmp_path / "torso.npy")
    assert len(frag.faces) <= pc.MATCH_FACES and any("decimated" in n for n in frag.notes), frag.notes
    assert_closed_outward_one_body(frag.vertices, frag.faces)
    assert hausdorff(frag.to_trimesh(), source, n=20000) < 0.01 * side


_remeshed: dict = {}


def _remeshed_pair(shape, seed, n_points=40000):
    """A synthetic broken object, and its two fragments sampled (n_points, noise up to 0.1% of size)
    and meshed again as load_fragment does (`triangulate.mesh_for_matching`)."""
    key = (shape, seed, n_points)
    if key not in _remeshed:
        _remeshed[key] = _make_remeshed_pair(*key)
    return _remeshed[key]


def _make_remeshed_pair(shape, seed, n_points):
    from relicgpu import synth
    from relicgpu.io.fragment import Fragment

    result = synth.generate(shape, pieces=2, seed=seed, progress=False)
    remeshed = []
    for i, frag in enumerate(result.fragments):
        pts = surface_points(frag.to_trimesh(), n_points, seed=10 + i, noise=0.001)
        res = pc.mesh_for_matching(pts)
        remeshed.append(Fragment(frag.name, res.vertices, res.faces, None, res.notes))
    return result, remeshed


def _angle_deg(r):
    return float(np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1))))


def _check_issue(shape, seed):
    """The issue's check: within 1% of size (Hausdorff) of the source, and matched at the true pose."""
    from relicgpu.pair.pipeline import match_pair

    result, (a, b) = _remeshed_pair(shape, seed)
    for frag, again in zip(result.fragments, (a, b)):
        assert_closed_outward_one_body(again.vertices, again.faces)
        assert hausdorff(again.to_trimesh(), frag.to_trimesh(), n=10000) < 0.01 * frag.size, frag.name
    truth = np.linalg.inv(result.poses[0]) @ result.poses[1]  # carries b onto a
    m = match_pair(a, b, backend="numpy")
    assert m.accepted, m.reason
    assert _angle_deg(m.transform[:3, :3].T @ truth[:3, :3]) < 2.0
    # b's own vertices within 1% of its size (RMS) of their true place: a translation alone
    # would grow with the distance of the fragment from its origin
    v = result.fragments[1].vertices
    rms = np.sqrt(np.mean(np.sum((v @ (m.transform[:3, :3] - truth[:3, :3]).T + m.transform[:3, 3] - truth[:3, 3]) ** 2,
                                 axis=1)))
    assert rms < 0.01 * result.fragments[1].size, rms / result.fragments[1].size


@needs_synth
@needs_pipeline
@pytest.mark.parametrize("shape", ["vase", "torso", "slab"])
def test_synth_fragments_meshed_again_stay_within_one_percent_and_match_at_the_true_pose(shape):
    _check_issue(shape, 0)


@pytest.mark.slow
@needs_synth
@needs_pipeline
@pytest.mark.parametrize("seed", [1, 2])
@pytest.mark.parametrize("shape", ["vase", "torso", "slab"])
def test_issue_check_on_more_seeds(shape, seed):
    _check_issue(shape, seed)


@needs_synth
def test_refinement_makes_the_remeshed_surface_follow_the_source_normals():
    """Without step 7 the boundary of the Delaunay tetrahedra holds triangles standing across the
    surface, which the segmentation takes for rough fracture surface. (Faces at the slab's creases
    may be compared with the other side's normal, hence no bound near zero.)"""
    from relicgpu import synth

    frag = synth.generate("slab", pieces=2, seed=0, progress=False).fragments[0]
    source = frag.to_trimesh()
    pts = surface_points(source, 40000, seed=10, noise=0.001)
    share = {}
    for refine in (False, True):
        res = pc.triangulate(pts, max_points=pc.MATCH_POINTS, refine=refine)
        assert_closed_outward_one_body(res.vertices, res.faces)
        mesh = trimesh.Trimesh(res.vertices, res.faces, process=False)
        _, _, tri = trimesh.proximity.closest_point(source, mesh.triangles_center)
        cos = np.einsum("ij,ij->i", mesh.face_normals, source.face_normals[tri])
        share[refine] = float(mesh.area_faces[cos < np.cos(np.radians(45))].sum() / mesh.area)
    # measured: 1.5% of the area turned more than 45 degrees before, 0.45% after
    assert share[True] < 0.5 * share[False], share


@pytest.mark.parametrize("suffix", [".xyz", ".npy"])
def test_zero_normal_rows_in_a_text_or_npy_cloud_are_filled_not_read_as_colours(tmp_path, suffix):
    """Rows 0 0 0 among unit normals are normals a scanner did not have; colours are not unit vectors."""
    pts, nrm = sphere_points(400)
    some = nrm.copy()
    some[::10] = 0.0
    p = tmp_path / f"some{suffix}"
    np.savetxt(p, np.hstack([pts, some])) if suffix == ".xyz" else np.save(p, np.hstack([pts, some]))
    cloud = read_point_cloud(p)
    assert cloud.normals is not None and np.allclose(np.linalg.norm(cloud.normals, axis=1), 1.0, atol=1e-6)
    assert (np.einsum("ij,ij->i", cloud.normals, nrm) > 0.8).all()
    assert any("40 points have a zero normal" in n for n in cloud.notes)
    colours = np.random.default_rng(0).integers(0, 256, size=(400, 3)).astype(float)
    colours[::10] = 0.0
    q = tmp_path / f"colours{suffix}"
    np.savetxt(q, np.hstack([pts, colours])) if suffix == ".xyz" else np.save(q, np.hstack([pts, colours]))
    cloud = read_point_cloud(q)
    assert cloud.normals is None and any("not unit normals (colours?)" in n for n in cloud.notes)
