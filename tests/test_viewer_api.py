"""The viewer's JSON API through Flask's test client, its file serving under attack,
and waitress streaming server-sent events.

The workspace is made by hand: a box cut by two tilted planes into three pieces,
each piece moved by a random rigid motion and written as PLY, with an
assembly.json whose poses undo those motions. The pipeline stages are replaced
by small doubles computed from that known truth (the plumbing is under test
here); tests against the real relicgpu.prepare and relicgpu.assemble run when
those stages are installed.
"""
from __future__ import annotations

import base64
import http.client
import importlib.util
import json
import os
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("flask")
import trimesh  # noqa: E402

from relicgpu.io.load import load_fragment  # noqa: E402
from relicgpu.viewer.app import create_app, make_server, serve_in_thread  # noqa: E402
from relicgpu.viewer.workspace import Workspace  # noqa: E402

# --- the hand-made workspace -----------------------------------------------------------

EXTENTS = np.array([1.0, 0.6, 0.4])
# cut planes n.x = d, tilted so the cut faces are not axis aligned
PLANES = [(np.array([1.0, 0.25, 0.15]), -0.17), (np.array([1.0, -0.2, 0.3]), 0.18)]


def _rigid(rng) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    r = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                  [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                  [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = rng.uniform(-1.5, 1.5, size=3)
    return m


def _box_pieces():
    """The box cut by PLANES into three closed pieces (manifold3d, no shapely needed)."""
    import manifold3d

    box = manifold3d.Manifold.cube(tuple(EXTENTS), True).refine(8)
    pieces, rest = [], box
    for n, d in PLANES:
        n = n / np.linalg.norm(n)
        pieces.append(rest.trim_by_plane(tuple(-n), -d))  # keeps n.x <= d
        rest = rest.trim_by_plane(tuple(n), d)
    pieces.append(rest)
    out = []
    for p in pieces:
        mesh = p.to_mesh64()
        out.append(trimesh.Trimesh(np.asarray(mesh.vert_properties)[:, :3], np.asarray(mesh.tri_verts), process=False))
    return out


def _cut_polygon(n, d, samples=48):
    """The closed loop where plane n.x = d meets the box surface, evenly resampled."""
    n = n / np.linalg.norm(n)
    d = d / 1.0
    half = EXTENTS / 2
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * half
    pts = []
    for i in range(8):
        for j in range(i + 1, 8):
            a, b = corners[i], corners[j]
            if np.count_nonzero(a != b) != 1:
                continue
            fa, fb = a @ n - d * np.linalg.norm(n), b @ n - d * np.linalg.norm(n)
            if fa * fb < 0:
                pts.append(a + (b - a) * fa / (fa - fb))
    pts = np.array(pts)
    c = pts.mean(0)
    u = np.cross(n, [0, 0, 1.0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    order = np.argsort(np.arctan2((pts - c) @ v, (pts - c) @ u))
    loop = np.vstack([pts[order], pts[order][:1]])
    seg = np.linalg.norm(np.diff(loop, axis=0), axis=1)
    s = np.concatenate([[0], np.cumsum(seg)])
    t = np.linspace(0, s[-1], samples, endpoint=False)
    return np.stack([np.interp(t, s, loop[:, k]) for k in range(3)], axis=1)


def make_box_workspace(root: Path, case: str = "box", seed: int = 0, assembled: bool = True) -> dict:
    """Write a case of three box pieces; returns the truth the doubles need."""
    rng = np.random.default_rng(seed)
    case_dir = Path(root) / case
    frag_dir = case_dir / "fragments"
    frag_dir.mkdir(parents=True, exist_ok=True)
    names, poses = [], {}
    scatter = {}
    for i, piece in enumerate(_box_pieces()):
        name = f"piece_{i}"
        m = _rigid(rng)
        v = piece.vertices @ m[:3, :3].T + m[:3, 3]
        trimesh.Trimesh(v, piece.faces, process=False).export(frag_dir / f"{name}.ply")
        names.append(name)
        scatter[name] = m
        poses[name] = np.linalg.inv(m)  # carries the file's coordinates back into the object frame
    if assembled:
        pairs = [(names[0], names[1]), (names[1], names[2])]
        doc = {
            "version": 1,
            "fragments": [{"file": f"{n}.ply", "pose": poses[n].tolist(), "group": 0} for n in names],
            "matches": [{"a": a, "b": b, "transform": (np.linalg.inv(poses[a]) @ poses[b]).tolist(),
                         "score": 0.9 - 0.1 * k, "rmse": 0.001, "overlap": 0.8, "used": True}
                        for k, (a, b) in enumerate(pairs)]
                       + [{"a": names[0], "b": names[2], "transform": np.eye(4).tolist(), "score": 0.1,
                           "rmse": 0.05, "overlap": 0.1, "used": False}],
            "backend": "numpy", "engine": "local", "timings": {"total_s": 1.0},
        }
        (case_dir / "assembly").mkdir(exist_ok=True)
        (case_dir / "assembly" / "assembly.json").write_text(json.dumps(doc))
    return {"case": case, "dir": case_dir, "names": names, "poses": poses, "scatter": scatter}


class TruthPipeline:
    """Doubles of prepare / match_pair / assemble computed from the fixture's known geometry."""

    def __init__(self, truth: dict):
        self.truth = truth
        self.prepare_calls: list[str] = []
        self.match_calls: list[tuple] = []

    def prepare(self, fragment, scale):
        self.prepare_calls.append(fragment.name)
        m = self.truth["scatter"][fragment.name]
        inv = np.linalg.inv(m)
        v = fragment.vertices @ inv[:3, :3].T + inv[:3, 3]  # object frame
        tri = v[fragment.faces]
        centre = tri.mean(1)
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        face_region = np.zeros(len(fragment.faces), np.int64)
        contours = []
        for k, (n, d) in enumerate(PLANES):
            nn = n / np.linalg.norm(n)
            on_plane = (np.abs(centre @ nn - d) < 1e-6) & (np.abs(normal @ nn) > 0.999)
            if on_plane.any():
                region = len(contours) + 1
                face_region[on_plane] = region
                loop = _cut_polygon(n, d)
                contours.append(SimpleNamespace(points=loop @ m[:3, :3].T + m[:3, 3], region=region,
                                                feature_points=np.array([0, 12, 24, 36])))
        return SimpleNamespace(fragment=fragment, face_region=face_region,
                               region_is_fracture=np.array([False] + [True] * len(contours)),
                               contours=contours, timings={"segment": 0.001})

    def match_pair(self, pa, pb, heads, scale):
        self.match_calls.append((pa.fragment.name, pb.fragment.name, heads))
        poses = self.truth["poses"]
        t = np.linalg.inv(poses[pa.fragment.name]) @ poses[pb.fragment.name]
        return SimpleNamespace(transform=t, accepted=True, score=0.87, rmse=0.0012, overlap=0.74,
                               correspondences=np.array([[0, 0], [1, 47]]), contour_a=0, contour_b=0,
                               reason="fits", timings={"icp": 0.01})


@pytest.fixture
def box(tmp_path):
    ws = tmp_path / "ws"
    truth = make_box_workspace(ws)
    make_box_workspace(ws, case="other", seed=1, assembled=False)
    return ws, truth


@pytest.fixture
def client_and_pipeline(box):
    ws, truth = box
    pipe = TruthPipeline(truth)
    app = create_app(ws, prepare=pipe.prepare, match_pair=pipe.match_pair,
                     assemble=lambda frag_dir, out_dir, report: {"fragments": 3})
    return app.test_client(), pipe, truth


def _ok(client):
    r = client.get("/api/cases")
    assert r.status_code == 200, r.get_data(as_text=True)
    return r


# --- the API -------------------------------------------------------------------------------

def test_cases_listing(client_and_pipeline, tmp_path):
    client, _, _ = client_and_pipeline
    body = _ok(client).get_json()
    assert [c["id"] for c in body["cases"]] == ["box", "other"]
    assert [c["assembled"] for c in body["cases"]] == [True, False]
    assert all(c["fragments"] == 3 for c in body["cases"])
    assert body["single_case"] is False

    # a workspace that is itself a case
    single = create_app(tmp_path / "ws" / "box").test_client().get("/api/cases").get_json()
    assert single["single_case"] is True and [c["id"] for c in single["cases"]] == ["box"]


def test_fragments_poses_and_matches(client_and_pipeline):
    client, _, truth = client_and_pipeline
    body = client.get("/api/cases/box/fragments").get_json()
    assert [f["name"] for f in body["fragments"]] == truth["names"]
    assert body["assembled"] is True and body["assembly_error"] is None
    for f in body["fragments"]:
        assert f["placed"] and f["group"] == 0
        np.testing.assert_allclose(f["pose"], truth["poses"][f["name"]], atol=1e-12)
    other = client.get("/api/cases/other/fragments").get_json()
    assert other["assembled"] is False and all(f["pose"] is None for f in other["fragments"])

    matches = client.get("/api/cases/box/matches").get_json()["matches"]
    assert [(m["a"], m["b"], m["used"]) for m in matches] == [
        ("piece_0", "piece_1", True), ("piece_1", "piece_2", True), ("piece_0", "piece_2", False)]
    assert client.get("/api/cases/other/matches").get_json() == {"case": "other", "assembled": False, "matches": []}
    # how each is held: a chain of two used matches, no loop
    assert [(f["used_matches"], f["on_loop"]) for f in body["fragments"]] == [(1, False), (2, False), (1, False)]
    assert all(f["used_matches"] == 0 and not f["on_loop"] for f in other["fragments"])


def test_a_used_match_that_closes_a_loop_holds_every_fragment_on_it(box):
    ws, truth = box
    path = ws / "box" / "assembly" / "assembly.json"
    doc = json.loads(path.read_text())
    doc["matches"][2]["used"] = True
    path.write_text(json.dumps(doc))
    body = create_app(ws).test_client().get("/api/cases/box/fragments").get_json()
    assert [(f["used_matches"], f["on_loop"]) for f in body["fragments"]] == [(2, True), (2, True), (2, True)]


def test_mesh_is_the_loaded_fragment(client_and_pipeline):
    client, _, truth = client_and_pipeline
    body = client.get("/api/cases/box/fragments/piece_1/mesh").get_json()
    frag = load_fragment(truth["dir"] / "fragments" / "piece_1.ply")
    v = np.frombuffer(base64.b64decode(body["vertices"]), "<f4").reshape(-1, 3)
    f = np.frombuffer(base64.b64decode(body["faces"]), "<u4").reshape(-1, 3)
    assert body["n_vertices"] == len(frag.vertices) and body["n_faces"] == len(frag.faces)
    np.testing.assert_allclose(v, frag.vertices, atol=1e-6)
    np.testing.assert_array_equal(f, frag.faces)
    np.testing.assert_allclose(body["centroid"], frag.vertices.mean(0), atol=1e-9)


def test_contours_are_prepared_once_per_file(client_and_pipeline):
    client, pipe, truth = client_and_pipeline
    r = client.get("/api/cases/box/fragments/piece_1/contours")
    assert r.status_code == 200, r.get_json()
    body = r.get_json()
    mesh = client.get("/api/cases/box/fragments/piece_1/mesh").get_json()
    assert len(body["face_region"]) == mesh["n_faces"] == body["n_faces"]
    assert body["region_is_fracture"] == [False, True, True]  # the middle piece has both cuts
    assert [c["region"] for c in body["contours"]] == [1, 2] and all(c["fracture"] for c in body["contours"])
    assert len(body["contours"][0]["points"]) == 48 and body["contours"][0]["feature_points"] == [0, 12, 24, 36]
    # contour points lie on the fragment's surface (they are the edges of its cut faces)
    frag = load_fragment(truth["dir"] / "fragments" / "piece_1.ply")
    _, dist, _ = trimesh.proximity.closest_point(frag.to_trimesh(), np.array(body["contours"][1]["points"]))
    assert dist.max() < 1e-5

    client.get("/api/cases/box/fragments/piece_1/contours")
    assert pipe.prepare_calls == ["piece_1"]  # cached
    # a rewritten file is prepared again
    p = truth["dir"] / "fragments" / "piece_1.ply"
    st = p.stat()
    os.utime(p, ns=(st.st_atime_ns, st.st_mtime_ns + 10_000_000))
    client.get("/api/cases/box/fragments/piece_1/contours")
    assert pipe.prepare_calls == ["piece_1", "piece_1"]


def test_match_with_heads(client_and_pipeline):
    client, pipe, truth = client_and_pipeline
    r = client.post("/api/match", json={"case": "box", "a": "piece_0", "b": "piece_1", "heads": [0, 5, 0, 40]})
    assert r.status_code == 200, r.get_json()
    body = r.get_json()
    assert pipe.match_calls == [("piece_0", "piece_1", (0, 5, 0, 40))]
    assert body["accepted"] is True and body["heads"] == [0, 5, 0, 40]
    assert body["correspondences"] == [[0, 0], [1, 47]] and body["reason"] == "fits"
    expected = np.linalg.inv(truth["poses"]["piece_0"]) @ truth["poses"]["piece_1"]
    np.testing.assert_allclose(body["transform"], expected, atol=1e-12)
    # without heads: the automatic match
    r = client.post("/api/match", json={"case": "box", "a": "piece_1", "b": "piece_2"})
    assert r.status_code == 200 and pipe.match_calls[-1] == ("piece_1", "piece_2", None)


@pytest.mark.parametrize("method, url, kwargs, status, words", [
    ("get", "/api/cases/nope/fragments", {}, 404, "unknown case 'nope'"),
    ("get", "/api/cases/box/fragments/nope/mesh", {}, 404, "unknown fragment 'nope'"),
    ("get", "/api/cases/box/fragments/nope/contours", {}, 404, "unknown fragment 'nope'"),
    ("get", "/api/nothing", {}, 404, "not found"),
    ("delete", "/api/cases", {}, 405, "not allowed"),
    ("post", "/api/match", {"data": "{not json", "content_type": "application/json"}, 400, "malformed JSON"),
    ("post", "/api/match", {"data": "[1, 2]", "content_type": "application/json"}, 400, "must be an object"),
    ("post", "/api/match", {"data": "case=box", "content_type": "text/plain"}, 415, "Content-Type: application/json"),
    ("post", "/api/match", {"json": {"case": "box", "a": "piece_0", "b": "ghost"}}, 404, "unknown fragment 'ghost'"),
    ("post", "/api/match", {"json": {"case": "box", "a": "piece_0", "b": "piece_0"}}, 400, "two different"),
    ("post", "/api/match", {"json": {"case": "box", "a": "piece_0", "b": "piece_1", "heads": [0, 1]}}, 400, "list of 4 integers"),
    ("post", "/api/match", {"json": {"case": "box", "a": "piece_0", "b": "piece_1", "heads": [0, True, 0, 1]}}, 400, "list of 4 integers"),
    ("post", "/api/match", {"json": {"case": "box", "a": "piece_0", "b": "piece_1", "heads": [3, 0, 0, 0]}}, 400, "has 1 contours, not a contour 3"),
    ("post", "/api/match", {"json": {"case": "box", "a": "piece_0", "b": "piece_1", "heads": [0, 48, 0, 0]}}, 400, "has 48 points, not a point 48"),
    ("post", "/api/match", {"json": {"case": "box", "a": "piece_0", "b": "piece_1", "heads": [0, 0, 0, -1]}}, 400, "not a point -1"),
    ("post", "/api/match", {"json": {"case": "box", "a": "piece_0", "b": "piece_1", "pad": "x" * 70000}}, 413, "too large"),
    ("post", "/api/assemble", {"json": {"case": 7}}, 404, "unknown case 7"),
    ("get", "/api/progress?job=abc", {}, 400, "job must be an integer"),
    ("get", "/api/progress?job=99", {}, 404, "unknown job"),
])
def test_bad_requests_get_clear_4xx(client_and_pipeline, method, url, kwargs, status, words):
    client, pipe, _ = client_and_pipeline
    r = getattr(client, method)(url, **kwargs)
    assert r.status_code == status, r.get_data(as_text=True)
    assert r.is_json and words in r.get_json()["error"]
    assert not pipe.match_calls
    _ok(client)  # still answering


def test_failing_stage_is_a_json_500_and_the_server_lives(box):
    ws, truth = box

    def broken_prepare(fragment, scale):
        raise RuntimeError("segmentation blew up")

    client = create_app(ws, prepare=broken_prepare).test_client()
    r = client.get("/api/cases/box/fragments/piece_0/contours")
    assert r.status_code == 500 and "segmentation blew up" in r.get_json()["error"]
    _ok(client)


def test_bad_mesh_file_is_a_422_naming_the_file(box):
    ws, _ = box
    (ws / "box" / "fragments" / "broken.stl").write_bytes(b"solid x\nfacet normal nonsense\n")
    client = create_app(ws).test_client()
    r = client.get("/api/cases/box/fragments/broken/mesh")
    assert r.status_code == 422
    assert "broken.stl" in r.get_json()["error"] and str(ws) not in r.get_json()["error"]
    _ok(client)


def test_malformed_assembly_json_is_reported(box):
    ws, _ = box
    (ws / "box" / "assembly" / "assembly.json").write_text('{"fragments": [{"file": "piece_0.ply", "pose": [[1]]}]}')
    client = create_app(ws).test_client()
    body = client.get("/api/cases/box/fragments").get_json()
    assert body["assembled"] is False and "pose is not a 4x4 matrix" in body["assembly_error"]
    assert len(body["fragments"]) == 3
    r = client.get("/api/cases/box/matches")
    assert r.status_code == 422 and "assembly.json" in r.get_json()["error"]
    (ws / "box" / "assembly" / "assembly.json").write_text("{oops")
    assert "invalid JSON at line 1" in client.get("/api/cases/box/fragments").get_json()["assembly_error"]


def test_object_groups_from_groups_json_and_from_assembly(box):
    ws, _ = box
    client = create_app(ws).test_client()
    body = client.get("/api/cases/other/fragments").get_json()
    assert body["objects"] is None and all(f["object"] is None for f in body["fragments"])
    # `relicgpu group` output beside the fragments (names as files, stems, or paths)
    (ws / "other" / "groups.json").write_text(json.dumps({"version": 1, "method": "average", "fragments": [
        {"file": "piece_0.ply", "group": 1}, {"file": "piece_1", "group": 0},
        {"file": "/elsewhere/piece_2.ply", "group": 1}, {"file": "gone.ply", "group": 2}]}))
    body = client.get("/api/cases/other/fragments").get_json()
    assert {f["name"]: f["object"] for f in body["fragments"]} == {"piece_0": 1, "piece_1": 0, "piece_2": 1}
    assert body["objects"] == {"source": "groups.json", "count": 2, "method": "average"}
    assert any("gone.ply" in n for n in body["notes"])
    # assemble --group: "object" in assembly.json wins over any groups.json
    doc = json.loads((ws / "box" / "assembly" / "assembly.json").read_text())
    for k, e in enumerate(doc["fragments"]):
        e["object"] = k % 2
    (ws / "box" / "assembly" / "assembly.json").write_text(json.dumps(doc))
    (ws / "box" / "groups.json").write_text(json.dumps({"fragments": [{"file": "piece_0.ply", "group": 5}]}))
    body = client.get("/api/cases/box/fragments").get_json()
    assert [f["object"] for f in body["fragments"]] == [0, 1, 0]
    assert body["objects"]["source"] == "assembly/assembly.json" and body["objects"]["count"] == 2
    # a bad groups.json is a note naming it; the fragments still load
    (ws / "other" / "groups.json").write_text('{"fragments": [{"file": "piece_0.ply", "group": "a"}]}')
    body = client.get("/api/cases/other/fragments").get_json()
    assert body["objects"] is None and len(body["fragments"]) == 3
    assert any("other/groups.json" in n and "fragments[0].group" in n for n in body["notes"])
    (ws / "other" / "groups.json").write_text("{oops")
    body = client.get("/api/cases/other/fragments").get_json()
    assert any("other/groups.json: invalid JSON" in n for n in body["notes"])


def test_unknown_host_header_is_refused(client_and_pipeline):
    client, _, _ = client_and_pipeline
    r = client.get("/api/cases", headers={"Host": "attacker.example:8000"})
    assert r.status_code == 400 and "Host" in r.get_json()["error"]
    assert client.get("/api/cases", headers={"Host": "127.0.0.1:8000"}).status_code == 200
    assert client.get("/api/cases", headers={"Host": "[::1]:8000"}).status_code == 200


# --- serving nothing outside -----------------------------------------------------------------

def test_traversal_and_symlinks_are_refused(box, tmp_path, monkeypatch):
    ws, truth = box
    secret = tmp_path / "secret"
    secret.mkdir()
    (secret / "passwords.txt").write_text("hunter2")
    trimesh.creation.icosphere().export(secret / "outside.ply")
    (secret / "fragments").mkdir()
    trimesh.creation.icosphere().export(secret / "fragments" / "s.ply")
    # symlinks pointing out: a fragment file, a whole case, a case's fragments/ folder, an output file
    (ws / "box" / "fragments" / "leak.ply").symlink_to(secret / "outside.ply")
    (ws / "linked-case").symlink_to(secret)
    (ws / "half").mkdir()
    (ws / "half" / "fragments").symlink_to(secret / "fragments")
    (ws / "box" / "assembly" / "merged.stl").symlink_to(secret / "passwords.txt")
    # a symlink inside the workspace pointing inside is fine
    (ws / "box" / "fragments" / "alias.ply").symlink_to(ws / "box" / "fragments" / "piece_0.ply")

    vdir = tmp_path / "viewer"
    vdir.mkdir()
    (vdir / "index.html").write_text("<!doctype html><title>x</title>")
    (vdir / "main.js").write_text("export {};")
    (vdir / "evil.js").symlink_to(secret / "passwords.txt")
    three = vdir / "node_modules" / "three"
    (three / "build").mkdir(parents=True)
    (three / "build" / "three.module.js").write_text("export const REVISION = 'x';")
    (three / "package.json").write_text("{}")
    monkeypatch.setenv("RELICGPU_VIEWER_DIR", str(vdir))

    client = create_app(ws).test_client()
    cases = [c["id"] for c in client.get("/api/cases").get_json()["cases"]]
    assert cases == ["box", "other"]
    names = [f["name"] for f in client.get("/api/cases/box/fragments").get_json()["fragments"]]
    assert "leak" not in names and "alias" in names
    assert client.get("/api/cases/box/fragments/alias/mesh").status_code == 200
    assert client.get("/static/main.js").status_code == 200
    assert client.get("/vendor/three/build/three.module.js").status_code == 200
    assert client.get("/static/main.js").mimetype == "text/javascript"

    attempts = [
        "/api/cases/box/fragments/leak/mesh",
        "/api/cases/linked-case/fragments",
        "/api/cases/half/fragments",
        "/api/cases/box/files/merged.stl",
        "/api/cases/box/files/..%2F..%2Fsecret%2Fpasswords.txt",
        "/api/cases/box/files/../../secret/passwords.txt",
        "/api/cases/..%2Fsecret/fragments",
        "/api/cases/box/fragments/..%2F..%2F..%2Fsecret%2Foutside/mesh",
        "/api/cases/box/fragments/%2e%2e/mesh",
        "/static/evil.js",
        "/static/../secret/passwords.txt",
        "/static/%2e%2e/secret/passwords.txt",
        "/static/..%2fsecret%2fpasswords.txt",
        "/static/%2E%2E%2F%2E%2E%2Fetc%2Fpasswd",
        "/static//etc/passwd",
        "/static/%2Fetc%2Fpasswd",
        "/static/" + str(secret / "passwords.txt"),
        "/static/node_modules/three/package.json",
        "/vendor/three/package.json",
        "/vendor/three/build/../../../../secret/passwords.txt",
        "/vendor/three/build/%2e%2e/%2e%2e/%2e%2e/evil.js",
        "/vendor/three/build/..%5c..%5cpackage.json",
        "/static/C:/Windows/win.ini",
    ]
    for url in attempts:
        r = client.get(url, follow_redirects=True)  # werkzeug redirects '//' to '/', still inside /static/
        assert r.status_code in (400, 404), (url, r.status_code)
        assert b"hunter2" not in r.get_data() and b"icosphere" not in r.get_data(), url
    _ok(client)


def test_index_says_when_three_is_missing(box, tmp_path, monkeypatch):
    ws, _ = box
    vdir = tmp_path / "bare-viewer"
    vdir.mkdir()
    (vdir / "index.html").write_text("<!doctype html><title>x</title>")
    monkeypatch.setenv("RELICGPU_VIEWER_DIR", str(vdir))
    r = create_app(ws).test_client().get("/")
    assert r.status_code == 503 and b"npm install" in r.get_data()


def test_real_index_and_import_map():
    from relicgpu.viewer.app import viewer_dir
    if not (viewer_dir() / "node_modules" / "three").is_dir():
        pytest.skip("three.js not installed: run `npm install` in viewer/")
    client = create_app(Path(__file__).parent).test_client()
    page = client.get("/").get_data(as_text=True)
    imports = json.loads(page.split('<script type="importmap">')[1].split("</script>")[0])["imports"]
    for url in imports.values():
        target = url + "controls/OrbitControls.js" if url.endswith("/") else url
        assert client.get(target).status_code == 200, target
    for src in ("/static/main.js", "/static/scene.js", "/static/api.js", "/static/style.css"):
        assert client.get(src).status_code == 200, src


# --- background assembly and server-sent events ------------------------------------------

def test_every_url_of_api_js_is_a_route(box):
    """Each URL literal of the page's api.js (placeholders filled in, query dropped) is a
    route of the app for the method it is called with: POST for post(...), GET otherwise."""
    import re

    from relicgpu.viewer.app import viewer_dir
    from werkzeug.exceptions import HTTPException

    src = (viewer_dir() / "api.js").read_text(encoding="utf-8")
    calls = re.findall(r"""(\bpost\(\s*)?(['`])(/[^'`]*)\2""", src)
    urls = {("POST" if via_post else "GET", re.sub(r"\$\{[^}]*\}", "x", url).split("?")[0])
            for via_post, _, url in calls}
    assert {m for m, _ in urls} == {"GET", "POST"} and len(urls) >= 9, urls
    routes = create_app(box[0]).url_map.bind("localhost")
    for method, url in sorted(urls):
        try:
            endpoint, _ = routes.match(url, method=method)
        except HTTPException as exc:
            pytest.fail(f"api.js calls {method} {url}, not a route of the app ({exc.code})")
        assert endpoint.startswith("viewer.api_"), (method, url, endpoint)


def _events(text: str) -> list[dict]:
    return [json.loads(line[6:]) for line in text.splitlines() if line.startswith("data: ")]


def test_assemble_job_progress_and_busy(box):
    ws, _ = box
    release = threading.Event()
    seen_dirs = []

    def slow_assemble(frag_dir, out_dir, report):
        seen_dirs.append((frag_dir, out_dir))
        for i in range(3):
            report(stage="pairs", done=i + 1, total=3)
        release.wait(10)
        return {"fragments": 3, "placed": 3, "groups": 1}

    app = create_app(ws, assemble=slow_assemble)
    client = app.test_client()
    r = client.post("/api/assemble", json={"case": "other"})
    assert r.status_code == 202 and r.get_json()["state"] == "running"
    job_id = r.get_json()["job"]
    r2 = client.post("/api/assemble", json={"case": "box"})
    assert r2.status_code == 409 and "still running" in r2.get_json()["error"]
    assert client.get("/api/jobs").get_json()["job"]["state"] == "running"
    release.set()
    text = client.get(f"/api/progress?job={job_id}").get_data(as_text=True)  # ends with the final state
    events = _events(text)
    assert events[-1]["state"] == "done" and events[-1]["result"]["placed"] == 3
    assert seen_dirs == [(ws / "other" / "fragments", ws / "other" / "assembly")]
    assert client.get("/api/jobs").get_json()["job"]["state"] == "done"


def test_failed_assembly_is_reported_and_the_next_may_start(box):
    ws, _ = box

    def failing(frag_dir, out_dir, report):
        raise ValueError("no pair matched")

    app = create_app(ws, assemble=failing)
    client = app.test_client()
    job = client.post("/api/assemble", json={"case": "box"}).get_json()
    app.extensions["relicgpu.jobs"].join(5)
    last = _events(client.get(f"/api/progress?job={job['job']}").get_data(as_text=True))[-1]
    assert last["state"] == "failed" and "no pair matched" in last["error"]
    assert client.post("/api/assemble", json={"case": "box"}).status_code == 202
    assert _events(client.get("/api/progress").get_data(as_text=True))[-1]["state"] == "failed"


def test_waitress_streams_events_while_the_job_runs(box):
    ws, _ = box
    step = threading.Event()

    def stepping(frag_dir, out_dir, report):
        report(stage="pairs", done=1, total=2)
        step.wait(10)
        report(stage="pairs", done=2, total=2)
        return {"fragments": 3}

    app = create_app(ws, assemble=stepping)
    server, url = serve_in_thread(app)
    try:
        port = server.effective_port
        conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
        conn.request("POST", "/api/assemble", body=json.dumps({"case": "box"}), headers={"Content-Type": "application/json"})
        resp = conn.getresponse()
        assert resp.status == 202
        resp.read()
        conn.request("GET", "/api/progress")
        resp = conn.getresponse()
        assert resp.getheader("Content-Type").startswith("text/event-stream")
        first = None
        deadline = time.time() + 10
        while time.time() < deadline:  # the running state arrives before the job may finish
            line = resp.readline().decode()
            if line.startswith("data: "):
                first = json.loads(line[6:])
                if first["done"] == 1:
                    break
        assert first is not None and first["state"] == "running" and first["done"] == 1
        step.set()
        rest = _events(resp.read().decode())
        assert rest[-1]["state"] == "done"
        conn.close()
        # the server still answers plain requests
        conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
        conn.request("GET", "/api/cases")
        assert conn.getresponse().status == 200
    finally:
        step.set()
        server.close()


# --- the command line ------------------------------------------------------------------------

def test_cli_defaults_and_loud_warning(box, capsys):
    import argparse

    from relicgpu.errors import CliError
    from relicgpu.viewer.app import cli_add_arguments, cli_main

    p = argparse.ArgumentParser()
    cli_add_arguments(p)
    args = p.parse_args([str(box[0])])
    assert args.host == "127.0.0.1" and args.port == 8000
    with pytest.raises(CliError, match="no such directory"):
        cli_main(p.parse_args([str(box[0] / "missing")]))

    server = make_server(create_app(box[0]), "127.0.0.1", 0)
    server.close()
    assert "WARNING" not in capsys.readouterr().err
    app = create_app(box[0])
    server = make_server(app, "0.0.0.0", 0)
    server.close()
    err = capsys.readouterr().err
    assert "WARNING" in err and "reachable from other machines" in err
    # reached by other names: the Host check is off
    assert app.test_client().get("/api/cases", headers={"Host": "10.0.0.5:8000"}).status_code == 200


def test_viewer_never_uses_the_flask_debugger(box):
    app = create_app(box[0])
    assert app.debug is False
    src = (Path(__file__).parents[1] / "relicgpu" / "viewer" / "app.py").read_text()
    assert "app.run(" not in src and "debug=True" not in src


# --- against the real pipeline, once it is installed -------------------------------------------

needs_pipeline = pytest.mark.skipif(importlib.util.find_spec("relicgpu.pair.pipeline") is None,
                                    reason="relicgpu.pair.pipeline (prepare, match_pair) is not installed yet")


@needs_pipeline
def test_real_prepare_and_match_through_the_api(tmp_path, monkeypatch):
    """relicgpu.prepare and relicgpu.match_pair behind the API, on a synthetic broken slab."""
    synth = pytest.importorskip("relicgpu.synth")
    monkeypatch.setenv("RELICGPU_BACKEND", "numpy")
    result = synth.generate(shape="slab", pieces=2, seed=0)
    synth.write(result, tmp_path / "slab")
    client = create_app(tmp_path).test_client()
    names = [f["name"] for f in client.get("/api/cases/slab/fragments").get_json()["fragments"]]
    assert len(names) == 2
    bodies = {}
    for name in names:
        r = client.get(f"/api/cases/slab/fragments/{name}/contours")
        assert r.status_code == 200, r.get_json()
        body = bodies[name] = r.get_json()
        mesh = client.get(f"/api/cases/slab/fragments/{name}/mesh").get_json()
        assert len(body["face_region"]) == mesh["n_faces"]
        assert len(body["region_is_fracture"]) == max(body["face_region"]) + 1
        assert any(body["region_is_fracture"]) and body["contours"], f"{name}: no fracture contours"
        frag = load_fragment(tmp_path / "slab" / "fragments" / f"{name}.ply")
        for c in body["contours"]:
            _, dist, _ = trimesh.proximity.closest_point(frag.to_trimesh(), np.array(c["points"]))
            assert dist.max() < 0.01 * frag.size

    a, b = names
    heads = [0, 0, 0, len(bodies[b]["contours"][0]["points"]) - 1]
    r = client.post("/api/match", json={"case": "slab", "a": a, "b": b, "heads": heads})
    assert r.status_code == 200, r.get_json()
    m = r.get_json()
    assert m["heads"] == heads and isinstance(m["accepted"], bool) and m["reason"]
    r = client.post("/api/match", json={"case": "slab", "a": a, "b": b, "heads": [0, 0, 0, 10**6]})
    assert r.status_code == 400 and "head node out of range" in r.get_json()["error"]
    # the automatic match of two touching pieces: accepted, and the true pose
    m = client.post("/api/match", json={"case": "slab", "a": a, "b": b}).get_json()
    assert m["accepted"], m["reason"]
    fb = load_fragment(tmp_path / "slab" / "fragments" / f"{b}.ply")
    pose = {f.name: p for f, p in zip(result.fragments, result.poses)}
    expected = np.linalg.inv(pose[a]) @ pose[b]
    t = np.asarray(m["transform"])
    moved = fb.vertices @ t[:3, :3].T + t[:3, 3]
    true = fb.vertices @ expected[:3, :3].T + expected[:3, 3]
    assert np.sqrt(((moved - true) ** 2).sum(1).mean()) < 0.01 * fb.size


# --- a file of several bodies -------------------------------------------------------------

def test_each_body_of_a_file_is_its_own_fragment(box):
    """A file holding two bodies lists as two fragments, each with its own mesh, pose and contours."""
    ws, truth = box
    frag_dir = truth["dir"] / "fragments"
    small = trimesh.creation.box(extents=(0.3, 0.3, 0.3))
    big = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    big.apply_translation([4.0, 0, 0])
    trimesh.util.concatenate([small, big]).export(frag_dir / "two.ply")
    pose_1, pose_2 = np.eye(4), np.eye(4)
    pose_1[:3, 3], pose_2[:3, 3] = [1, 2, 3], [-4, 0, 0]
    doc = json.loads((truth["dir"] / "assembly" / "assembly.json").read_text())
    doc["fragments"] += [{"name": "two#1", "file": "two.ply", "pose": pose_1.tolist(), "group": 1},
                         {"name": "two#2", "file": "two.ply", "pose": pose_2.tolist(), "group": 2}]
    doc["matches"].append({"a": "two#1", "b": "two#2", "transform": np.eye(4).tolist(), "score": 0.2,
                           "rmse": 0.1, "overlap": 0.1, "used": False})
    (truth["dir"] / "assembly" / "assembly.json").write_text(json.dumps(doc))

    prepared = []
    client = create_app(ws, prepare=lambda f, scale: prepared.append(f.name) or SimpleNamespace(
        fragment=f, face_region=np.zeros(len(f.faces), np.int64), region_is_fracture=np.array([False]),
        contours=[], timings={})).test_client()

    def counted():  # /api/cases counts bodies without reading meshes where it can
        case = {c["id"]: c for c in client.get("/api/cases").get_json()["cases"]}["box"]
        return case["fragments"], case["fragments_exact"]

    n = len(truth["names"])
    assert counted() == (n + 2, True)  # two.ply's bodies from assembly.json
    listed = (truth["dir"] / "assembly" / "assembly.json").stat().st_mtime_ns
    os.utime(frag_dir / "two.ply", ns=(listed + 10**9, listed + 10**9))
    assert counted() == (n + 1, False)  # two.ply is newer than assembly.json: one, not known
    body = client.get("/api/cases/box/fragments").get_json()
    assert counted() == (n + 2, True)  # its meshes are read now
    by_name = {f["name"]: f for f in body["fragments"]}
    assert list(by_name) == truth["names"] + ["two#1", "two#2"]
    assert by_name["two#1"]["file"] == by_name["two#2"]["file"] == "two.ply"
    np.testing.assert_allclose(by_name["two#1"]["pose"], pose_1)
    np.testing.assert_allclose(by_name["two#2"]["pose"], pose_2)
    assert (by_name["two#1"]["group"], by_name["two#2"]["group"]) == (1, 2)
    assert ("two#1", "two#2", False) in [(m["a"], m["b"], m["used"])
                                          for m in client.get("/api/cases/box/matches").get_json()["matches"]]

    # the mesh of each body is that body (the sphere is the larger: #1), not the file's first
    for name, mesh in (("two#1", big), ("two#2", small)):
        r = client.get(f"/api/cases/box/fragments/{name.replace('#', '%23')}/mesh")
        assert r.status_code == 200, r.get_json()
        m = r.get_json()
        assert m["name"] == name and m["n_faces"] == len(mesh.faces)
        v = np.frombuffer(base64.b64decode(m["vertices"]), "<f4").reshape(-1, 3)
        np.testing.assert_allclose(v.mean(0), mesh.vertices.mean(0), atol=1e-5)
        c = client.get(f"/api/cases/box/fragments/{name.replace('#', '%23')}/contours").get_json()
        assert c["name"] == name and c["n_faces"] == len(mesh.faces)
    assert prepared == ["two#1", "two#2"]  # each body prepared on its own
    assert client.get("/api/cases/box/fragments/two/mesh").status_code == 404
