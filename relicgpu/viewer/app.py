"""The viewer's Flask app: the three.js page of `viewer/` and a JSON API under /api/.

`create_app(workspace)` builds the app; `serve(app, host, port)` runs it under
waitress (never Flask's development server, so never its debugger);
`relicgpu view WORKSPACE` does both. See `relicgpu.viewer.workspace` for what a
workspace is. The API (all JSON; errors are `{"error": message}` with a 4xx or
5xx status):

    GET  /api/cases                               the cases of the workspace; "fragments" counts
                                                  bodies (as /fragments lists them) where known
                                                  without reading meshes: from meshes already read,
                                                  else from an assembly.json newer than the file;
                                                  a file known neither way counts one
                                                  ("fragments_exact": false then)
    GET  /api/cases/<case>/fragments              fragments (one per body: a file of several bodies
                                                  gives id#1, id#2, ...), poses, groups, object groups
    GET  /api/cases/<case>/fragments/<name>/mesh  that fragment's vertices/faces (base64 float32/uint32)
    GET  /api/cases/<case>/fragments/<name>/contours  segmentation and contours (relicgpu.prepare)
    GET  /api/cases/<case>/matches                the pair matches of assembly.json
    GET  /api/cases/<case>/files/<file>           assembly.json, assembly.glb or merged.stl
    POST /api/match      {"case", "a", "b", "heads": [ca, ia, cb, ib]}   re-match one pair
    POST /api/assemble   {"case"}                 start an assembly in the background
    GET  /api/jobs                                the latest job's state
    GET  /api/progress                            that state as server-sent events
"""
from __future__ import annotations

import base64
import ipaddress
import json
import math
import os
import sys
import threading
import time
import traceback
from collections import OrderedDict
from pathlib import Path

import numpy as np
from flask import Flask, Response, jsonify, request, send_file
from werkzeug.exceptions import HTTPException
from werkzeug.security import safe_join

from ..io import FragmentError, load_fragments
from .jobs import FINAL_STATES, JobBusy, JobRunner
from .workspace import AssemblyFileError, Workspace, WorkspaceError, split_entries

MAX_BODY_BYTES = 64 * 1024  # requests carry a few names and numbers
CACHE_FRAGMENTS = 128  # loaded meshes, and prepared fragments, kept in memory
SSE_TICK_S = 2.0
SSE_MAX_RATE_HZ = 10
LOOPBACK_NAMES = {"localhost", "127.0.0.1", "::1", "[::1]"}


def viewer_dir() -> Path:
    """The page's folder: `viewer/` at the repository root, or $RELICGPU_VIEWER_DIR."""
    env = os.environ.get("RELICGPU_VIEWER_DIR")
    return Path(env).resolve() if env else Path(__file__).resolve().parents[2] / "viewer"


class ApiError(Exception):
    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status = status
        self.message = message


# --- pipeline hooks ------------------------------------------------------------
# The stages are imported on first use; tests and embedders may pass their own.

def _default_prepare(fragment, scale):
    import relicgpu
    return relicgpu.prepare(fragment, scale=scale)


def _default_match_pair(prepared_a, prepared_b, heads, scale):
    import relicgpu
    # The same scale as the prepared fragments: match_pair then reuses them rather than preparing
    # again at the pair's own scale, so head indices picked on the shown contours mean the same points.
    return relicgpu.match_pair(prepared_a, prepared_b, heads=heads, scale=scale)


def run_assembly(fragments_dir: Path, out_dir: Path, report, progress=None) -> dict:
    """Assemble a case's fragments with relicgpu.assemble, writing its outputs to out_dir.

    progress: passed on to relicgpu.assemble (default: a callback feeding report; the
    terminal's tqdm bars when True).
    """
    import relicgpu

    report(stage="assembling", message=f"assembling {fragments_dir.parent.name}")
    result = relicgpu.assemble(fragments_dir, out_dir=out_dir,
                               progress=progress_callback(report) if progress is None else progress)
    stats = getattr(result, "stats", {}) or {}
    return {k: stats[k] for k in ("fragments", "placed", "groups", "accepted", "used") if k in stats} | {
        "timings": _timings(getattr(result, "timings", None))}


def progress_callback(report):
    """A `progress` argument for relicgpu.assemble, for when it calls progress(stage, done, total).

    (A plain truthy value to an assemble that only draws tqdm bars on a terminal.)"""
    def progress(*args, **kwargs):
        stage = kwargs.get("stage", args[0] if args and isinstance(args[0], str) else None)
        nums = [a for a in args if isinstance(a, (int, float)) and not isinstance(a, bool)]
        done = kwargs.get("done", nums[0] if len(nums) >= 1 else None)
        total = kwargs.get("total", nums[1] if len(nums) >= 2 else None)
        report(stage=stage, done=done, total=total, message=kwargs.get("message"))
    return progress


def _pipeline_available(module: str) -> bool:
    import importlib.util
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):
        return False


# --- caches --------------------------------------------------------------------

class _Cache:
    """A small LRU keyed by (path, mtime, size): a rewritten file is a new key.

    compute() runs once per key even when several requests ask at the same time.
    """

    def __init__(self, limit: int) -> None:
        self._limit = limit
        self._data: OrderedDict = OrderedDict()
        self._lock = threading.Lock()
        self._key_locks: dict = {}

    def peek(self, key, default=None):
        """The value kept for key, else default (never computes)."""
        with self._lock:
            return self._data.get(key, default)

    def get(self, key, compute):
        with self._lock:
            if key in self._data:
                self._data.move_to_end(key)
                return self._data[key]
            key_lock = self._key_locks.setdefault(key, threading.Lock())
        with key_lock:
            with self._lock:
                if key in self._data:
                    return self._data[key]
            try:
                value = compute()
            except BaseException:
                with self._lock:
                    self._key_locks.pop(key, None)
                raise
            with self._lock:
                self._key_locks.pop(key, None)
                self._data[key] = value
                self._data.move_to_end(key)
                while len(self._data) > self._limit:
                    self._data.popitem(last=False)
            return value


def _assembly_bodies(path: Path | None) -> dict[str, tuple[int, int]]:
    """file -> (fragments assembly.json lists from it, assembly.json's mtime in ns); empty
    where there is no readable assembly.json. Cheap: no mesh is read."""
    if path is None:
        return {}
    try:
        mtime = path.stat().st_mtime_ns
        items = json.loads(path.read_text(encoding="utf-8")).get("fragments")
    except (OSError, ValueError, AttributeError):
        return {}
    out: dict[str, tuple[int, int]] = {}
    for item in items if isinstance(items, list) else []:
        file = item.get("file") if isinstance(item, dict) else None
        if isinstance(file, str):
            out[file] = (out.get(file, (0, mtime))[0] + 1, mtime)
    return out


def _file_key(path: Path):
    st = path.stat()
    return (str(path), st.st_mtime_ns, st.st_size)


# --- JSON helpers ----------------------------------------------------------------

def _b64(array, dtype) -> str:
    return base64.b64encode(np.ascontiguousarray(array, dtype=dtype).tobytes()).decode("ascii")


def _round(points: np.ndarray, scale: float) -> list:
    """Coordinates rounded to about 1e-7 of the fragment size: short JSON, nothing visible lost."""
    decimals = int(max(0, 7 - math.floor(math.log10(scale)))) if scale > 0 else 7
    return np.round(np.asarray(points, np.float64), decimals).tolist()


def _finite_or_none(x):
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def _timings(t) -> dict:
    if not isinstance(t, dict):
        return {}
    return {str(k): _finite_or_none(v) for k, v in t.items() if _finite_or_none(v) is not None}


def prepared_to_json(name: str, prepared) -> dict:
    frag = prepared.fragment
    face_region = np.asarray(prepared.face_region).astype(np.int64)
    fracture = np.asarray(prepared.region_is_fracture).astype(bool)
    contours = []
    for i, c in enumerate(prepared.contours):
        region = int(c.region)
        fp = getattr(c, "feature_points", None)
        contours.append({
            "index": i,
            "region": region,
            "fracture": bool(fracture[region]) if 0 <= region < len(fracture) else None,
            "points": _round(c.points, frag.size),
            "feature_points": [] if fp is None else np.asarray(fp).astype(np.int64).tolist(),
        })
    return {
        "name": name,
        "n_faces": int(len(face_region)),
        "face_region": face_region.tolist(),
        "region_is_fracture": fracture.tolist(),
        "contours": contours,
        "timings": _timings(getattr(prepared, "timings", None)),
    }


def match_to_json(a: str, b: str, heads, m) -> dict:
    transform = np.asarray(m.transform, np.float64)
    corr = np.asarray(getattr(m, "correspondences", np.zeros((0, 2))))
    return {
        "a": a,
        "b": b,
        "heads": list(heads) if heads is not None else None,
        "accepted": bool(m.accepted),
        "score": _finite_or_none(m.score),
        "rmse": _finite_or_none(m.rmse),
        "overlap": _finite_or_none(m.overlap),
        "transform": transform.tolist() if np.isfinite(transform).all() else None,
        "contour_a": None if m.contour_a is None else int(m.contour_a),
        "contour_b": None if m.contour_b is None else int(m.contour_b),
        "correspondences": corr.astype(np.int64).reshape(-1, 2).tolist(),
        "reason": str(getattr(m, "reason", "")),
        "timings": _timings(getattr(m, "timings", None)),
    }


# --- the app ---------------------------------------------------------------------

def create_app(workspace, *, prepare=None, match_pair=None, assemble=None, trusted_hosts=None) -> Flask:
    """The viewer app of one workspace.

    prepare(fragment, scale) -> Prepared, match_pair(prepared_a, prepared_b, heads, scale) -> PairMatch
    and assemble(fragments_dir, out_dir, report) -> summary dict default to the relicgpu stages.
    Every fragment of a case is prepared at one scale, the median fragment size of the case (the
    scale relicgpu's group stages use), so its contours are those the head nodes index.
    trusted_hosts: the Host header names accepted (default: loopback names only, which stops
    DNS-rebinding pages from reaching the API); make_server() turns the check off for a
    non-loopback host, which users reach by names the app cannot know.
    """
    ws = workspace if isinstance(workspace, Workspace) else Workspace(workspace)
    vdir = viewer_dir()
    three_dir = vdir / "node_modules" / "three"

    app = Flask("relicgpu.viewer", static_folder=None)
    app.config.update(MAX_CONTENT_LENGTH=MAX_BODY_BYTES, JSON_SORT_KEYS=False, DEBUG=False,
                      PROPAGATE_EXCEPTIONS=False)
    app.json.sort_keys = False
    app.extensions["relicgpu.workspace"] = ws
    hosts = {"trusted": set(LOOPBACK_NAMES) if trusted_hosts is None else set(trusted_hosts)}
    app.extensions["relicgpu.hosts"] = hosts

    hooks = {
        "prepare": prepare or _default_prepare,
        "match_pair": match_pair or _default_match_pair,
        "assemble": assemble or run_assembly,
    }
    capabilities = {
        "prepare": prepare is not None or _pipeline_available("relicgpu.pipeline"),
        "match": match_pair is not None or _pipeline_available("relicgpu.pipeline"),
        "assemble": assemble is not None or _pipeline_available("relicgpu.assembly"),
    }
    meshes = _Cache(CACHE_FRAGMENTS)
    prepared_cache = _Cache(CACHE_FRAGMENTS)
    scales: dict = {}
    scales_lock = threading.Lock()
    compute_slots = threading.BoundedSemaphore(max(1, min(2, os.cpu_count() or 1)))
    jobs = JobRunner()
    app.extensions["relicgpu.jobs"] = jobs

    # -- request guards ------------------------------------------------------------

    @app.before_request
    def _check_host():
        trusted = hosts["trusted"]
        if trusted is None:
            return None
        host = (request.host or "").lower()
        name = host.rsplit(":", 1)[0] if not host.endswith("]") else host
        if name not in trusted:
            raise ApiError(400, f"unexpected Host header {request.host!r}; the viewer answers only on {sorted(trusted)}")
        return None

    @app.after_request
    def _headers(resp: Response):
        resp.headers.setdefault("X-Content-Type-Options", "nosniff")
        resp.headers.setdefault("Referrer-Policy", "no-referrer")
        resp.headers.setdefault("X-Frame-Options", "DENY")
        if request.path.startswith("/api/"):
            resp.headers.setdefault("Cache-Control", "no-store")
        return resp

    @app.errorhandler(ApiError)
    def _api_error(exc: ApiError):
        return jsonify(error=exc.message), exc.status

    @app.errorhandler(HTTPException)
    def _http_error(exc: HTTPException):
        messages = {
            404: f"not found: {request.path}",
            405: f"method {request.method} not allowed on {request.path}",
            413: f"request body too large (limit {MAX_BODY_BYTES} bytes)",
        }
        return jsonify(error=messages.get(exc.code, exc.description or exc.name)), exc.code

    @app.errorhandler(Exception)
    def _internal_error(exc: Exception):
        traceback.print_exc()
        return jsonify(error=f"internal error: {type(exc).__name__}: {exc}"), 500

    # -- lookups -------------------------------------------------------------------

    def case_or_404(case_id):
        case = ws.case(case_id)
        if case is None:
            raise ApiError(404, f"unknown case {case_id!r}")
        return case

    def file_fragments(entry):
        """The fragments of an entry's file (io.load_fragments: one per body), loaded once."""
        def load():
            try:
                return load_fragments(entry.path, name=entry.name)[0]
            except FragmentError as exc:
                raise ApiError(422, str(exc).replace(str(ws.root) + os.sep, "")) from None
        return meshes.get(_file_key(entry.path), load)

    def body_names(entry):
        try:
            return [f.name for f in file_fragments(entry)]
        except ApiError:  # unreadable: the file's own entry stays, its mesh request says why
            return None

    def entries_of(case):
        """One entry per fragment of a case: per body of each file (files are read once)."""
        return split_entries(ws.fragments(case), body_names)

    def entry_or_404(case, name):
        entries = entries_of(case)
        if not isinstance(name, str) or name not in entries:
            raise ApiError(404, f"unknown fragment {name!r} in case {case.id!r}")
        return entries[name]

    def fragment_of(entry):
        return file_fragments(entry)[entry.body]

    def fragment_count(case) -> tuple[int, bool]:
        """(fragments of a case, exact): its bodies, counted without reading a mesh (see the
        module docstring for /api/cases); exact is False where a file's bodies are unknown."""
        files = ws.fragments(case).values()
        listed = _assembly_bodies(ws.assembly_file(case, "assembly.json"))
        count, exact = 0, True
        for e in files:
            key = _file_key(e.path)
            loaded = meshes.peek(key)
            if loaded is not None:
                count += len(loaded)
            elif e.file in listed and listed[e.file][1] >= key[1]:
                count += listed[e.file][0]
            else:
                count, exact = count + 1, False
        return count, exact

    def case_scale(case) -> float:
        files = list(ws.fragments(case).values())
        key = tuple(_file_key(e.path) for e in files)  # stat only: no mesh reloads once known
        with scales_lock:
            if key in scales:
                return scales[key]
        sizes = []
        for e in files:
            try:
                sizes += [f.size for f in file_fragments(e)]
            except ApiError:
                continue
        scale = float(np.median(sizes)) if sizes else 1.0
        with scales_lock:
            if len(scales) > 256:
                scales.clear()
            scales[key] = scale
        return scale

    def prepared_of(case, entry):
        if not capabilities["prepare"]:
            raise ApiError(503, "relicgpu.prepare is not available in this installation")
        frag = fragment_of(entry)
        scale = case_scale(case)

        def compute():
            with compute_slots:
                return hooks["prepare"](frag, scale)
        return prepared_cache.get(_file_key(entry.path) + (entry.body, scale), compute)

    def json_body() -> dict:
        if not request.is_json:
            raise ApiError(415, "send the request body as JSON (Content-Type: application/json)")
        try:
            body = json.loads(request.get_data(cache=False, as_text=False) or b"")
        except (ValueError, UnicodeDecodeError) as exc:
            raise ApiError(400, f"malformed JSON body: {exc}") from None
        if not isinstance(body, dict):
            raise ApiError(400, "the JSON body must be an object")
        return body

    # -- the page ------------------------------------------------------------------

    @app.get("/")
    def index():
        page = vdir / "index.html"
        if not page.is_file():
            raise ApiError(500, f"the viewer page is missing: {page}")
        if not (three_dir / "build" / "three.module.js").is_file():
            return Response(
                "<!doctype html><meta charset=utf-8><title>relicgpu viewer</title>"
                "<p>three.js is not installed: run <code>npm install</code> in the <code>viewer/</code> folder.</p>",
                status=503, mimetype="text/html")
        return send_file(page, mimetype="text/html", max_age=0)

    @app.get("/static/<path:filename>")
    def static_file(filename):
        if filename.split("/", 1)[0] == "node_modules":
            raise ApiError(404, f"not found: {request.path}")
        return _send_inside(vdir, filename)

    @app.get("/vendor/three/<path:filename>")
    def vendor_three(filename):
        if not (filename.startswith("build/") or filename.startswith("examples/jsm/")):
            raise ApiError(404, f"not found: {request.path}")
        return _send_inside(three_dir, filename)

    # -- the API -------------------------------------------------------------------

    @app.get("/api/cases")
    def api_cases():
        out = []
        for case in ws.cases().values():
            count, exact = fragment_count(case)
            out.append({
                "id": case.id,
                "fragments": count,
                "fragments_exact": exact,
                "assembled": ws.assembly_file(case, "assembly.json") is not None,
                "truth": (case.path / "truth.json").is_file(),
            })
        latest = jobs.latest()
        return jsonify(workspace=ws.name, single_case=ws.is_single_case(), cases=out,
                       capabilities=capabilities, job=latest.snapshot() if latest else None)

    @app.get("/api/cases/<case_id>/fragments")
    def api_fragments(case_id):
        case = case_or_404(case_id)
        entries = entries_of(case)
        assembly, error, notes = None, None, []
        try:
            assembly = ws.read_assembly(case, entries)
        except AssemblyFileError as exc:
            error = str(exc)
        if assembly is not None:
            notes = list(assembly.notes)
        objects = None
        try:
            objects = ws.read_object_groups(case, entries, assembly)
        except AssemblyFileError as exc:
            notes.append(str(exc))
        if objects is not None:
            notes.extend(objects.notes)
        frags = []
        for i, e in enumerate(entries.values()):
            pose = assembly.poses.get(e.name) if assembly else None
            frags.append({
                "index": i,
                "name": e.name,
                "file": e.file,
                "body": e.body,
                "bytes": e.path.stat().st_size,
                "pose": pose,
                "group": assembly.groups.get(e.name) if assembly else None,
                "object": objects.groups.get(e.name) if objects else None,
                "placed": pose is not None,
            })
        return jsonify(case=case.id, fragments=frags, assembled=assembly is not None,
                       assembly_error=error, notes=notes,
                       assembly=(assembly.meta if assembly else None),
                       objects=({"source": objects.source, "count": objects.count, "method": objects.method}
                                if objects else None),
                       files=[n for n in ("assembly.json", "assembly.glb", "merged.stl")
                              if ws.assembly_file(case, n) is not None],
                       capabilities=capabilities)

    @app.get("/api/cases/<case_id>/fragments/<name>/mesh")
    def api_mesh(case_id, name):
        case = case_or_404(case_id)
        frag = fragment_of(entry_or_404(case, name))
        return jsonify(name=name, n_vertices=len(frag.vertices), n_faces=len(frag.faces),
                       size=frag.size, centroid=frag.vertices.mean(axis=0).tolist(),
                       vertices=_b64(frag.vertices, "<f4"), faces=_b64(frag.faces, "<u4"),
                       notes=[n.replace(str(ws.root) + os.sep, "") for n in frag.notes])

    @app.get("/api/cases/<case_id>/fragments/<name>/contours")
    def api_contours(case_id, name):
        case = case_or_404(case_id)
        entry = entry_or_404(case, name)
        return jsonify(prepared_to_json(name, prepared_of(case, entry)))

    @app.get("/api/cases/<case_id>/matches")
    def api_matches(case_id):
        case = case_or_404(case_id)
        try:
            assembly = ws.read_assembly(case, entries_of(case))
        except AssemblyFileError as exc:
            raise ApiError(422, str(exc)) from None
        if assembly is None:
            return jsonify(case=case.id, assembled=False, matches=[])
        return jsonify(case=case.id, assembled=True, matches=assembly.matches)

    @app.get("/api/cases/<case_id>/files/<filename>")
    def api_case_file(case_id, filename):
        case = case_or_404(case_id)
        p = ws.assembly_file(case, filename)
        if p is None:
            raise ApiError(404, f"no file {filename!r} in case {case.id!r} (one of assembly.json, assembly.glb, merged.stl once assembled)")
        return send_file(p, as_attachment=filename != "assembly.json", max_age=0)

    @app.post("/api/match")
    def api_match():
        if not capabilities["match"]:
            raise ApiError(503, "relicgpu.match_pair is not available in this installation")
        body = json_body()
        case = case_or_404(body.get("case"))
        a_name, b_name = body.get("a"), body.get("b")
        ea, eb = entry_or_404(case, a_name), entry_or_404(case, b_name)
        if ea.name == eb.name:
            raise ApiError(400, "a and b must be two different fragments")
        heads = body.get("heads")
        if heads is not None:
            if (not isinstance(heads, list) or len(heads) != 4
                    or not all(isinstance(h, int) and not isinstance(h, bool) for h in heads)):
                raise ApiError(400, "heads must be a list of 4 integers [contour_a, point_a, contour_b, point_b]")
        pa, pb = prepared_of(case, ea), prepared_of(case, eb)
        if heads is not None:
            for (ci, pi), prep, nm in (((heads[0], heads[1]), pa, ea.name), ((heads[2], heads[3]), pb, eb.name)):
                if not 0 <= ci < len(prep.contours):
                    raise ApiError(400, f"head node out of range: fragment {nm!r} has {len(prep.contours)} contours, "
                                        f"not a contour {ci}")
                n = len(prep.contours[ci].points)
                if not 0 <= pi < n:
                    raise ApiError(400, f"head node out of range: contour {ci} of fragment {nm!r} has {n} points, "
                                        f"not a point {pi}")
            heads = tuple(heads)
        with compute_slots:
            result = hooks["match_pair"](pa, pb, heads, case_scale(case))
        return jsonify(match_to_json(ea.name, eb.name, heads, result))

    @app.post("/api/assemble")
    def api_assemble():
        if not capabilities["assemble"]:
            raise ApiError(503, "relicgpu.assemble is not available in this installation")
        body = json_body()
        case = case_or_404(body.get("case"))
        if not ws.fragments(case):
            raise ApiError(400, f"case {case.id!r} has no fragment files in fragments/")

        def work(report):
            report(stage="starting", message=f"{len(ws.fragments(case))} fragments")
            return hooks["assemble"](case.fragments_dir, case.assembly_dir, report)

        try:
            job = jobs.start(case.id, work)
        except JobBusy as exc:
            raise ApiError(409, str(exc)) from None
        return jsonify(job.snapshot()), 202

    @app.get("/api/jobs")
    def api_jobs():
        latest = jobs.latest()
        return jsonify(job=latest.snapshot() if latest else None)

    @app.get("/api/progress")
    def api_progress():
        latest = jobs.latest()
        job_arg = request.args.get("job")
        if job_arg is not None:
            try:
                latest = jobs.get(int(job_arg))
            except ValueError:
                raise ApiError(400, f"job must be an integer, not {job_arg!r}") from None
            if latest is None:
                raise ApiError(404, f"unknown job {job_arg!r}")

        def stream(job):
            yield "retry: 2000\n\n"
            if job is None:
                yield _sse({"state": "idle", "job": None})
                return
            # The latest state on every change, at most SSE_MAX_RATE_HZ times a second, and
            # at least every SSE_TICK_S (the elapsed time moves on while a stage runs).
            while True:
                snap = job.snapshot()
                yield _sse(snap, event_id=snap["seq"])
                if snap["state"] in FINAL_STATES:
                    return
                time.sleep(1.0 / SSE_MAX_RATE_HZ)
                jobs.wait(job, snap["seq"], SSE_TICK_S)

        return Response(stream(latest), mimetype="text/event-stream",
                        headers={"Cache-Control": "no-store", "X-Accel-Buffering": "no"})

    return app


def _sse(obj, event_id=None) -> str:
    head = f"id: {event_id}\n" if event_id is not None else ""
    return f"{head}data: {json.dumps(obj)}\n\n"


def _send_inside(root: Path, relpath: str):
    """send_file for root/relpath; 404 for '..', absolute paths, and symlinks leaving root."""
    joined = safe_join(str(root), relpath)
    if joined is None:
        raise ApiError(404, f"not found: {request.path}")
    p = Path(joined)
    try:
        real = p.resolve()
        ok = real.is_relative_to(root.resolve()) and real.is_file()
    except (OSError, RuntimeError):
        ok = False
    if not ok:
        raise ApiError(404, f"not found: {request.path}")
    mimetype = "text/javascript" if real.suffix in (".js", ".mjs") else None
    return send_file(real, mimetype=mimetype, max_age=0)


# --- serving ---------------------------------------------------------------------

def is_loopback(host: str) -> bool:
    if host in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def make_server(app: Flask, host: str = "127.0.0.1", port: int = 8000, threads: int = 8):
    """A waitress server bound to host:port (port 0: any free port), not yet running."""
    from waitress.server import create_server

    server = create_server(app, host=host, port=port, threads=threads,
                           ident="relicgpu-viewer", clear_untrusted_proxy_headers=True)
    if not is_loopback(host):
        app.extensions["relicgpu.hosts"]["trusted"] = None  # users reach it by names we cannot know
        bar = "!" * 78
        print(f"{bar}\nWARNING: relicgpu viewer listening on {host}:{server.effective_port}, reachable from other machines.\n"
              "Anyone who can reach it can read every mesh of this workspace and start assemblies;\n"
              f"there is no authentication. Use --host 127.0.0.1 unless you mean this.\n{bar}",
              file=sys.stderr, flush=True)
    return server


def server_url(server, host: str) -> str:
    port = server.effective_port
    shown = "127.0.0.1" if host in ("0.0.0.0", "") else ("[::1]" if host == "::" else host)
    if ":" in shown and not shown.startswith("["):
        shown = f"[{shown}]"
    return f"http://{shown}:{port}/"


def bind(app: Flask, host: str, port: int):
    from ..cli import CliError
    try:
        return make_server(app, host, port)
    except OSError as exc:
        raise CliError(f"cannot listen on {host}:{port} ({exc.strerror or exc}); "
                       "pass another --port, or --port 0 for any free one") from None


def cli_add_arguments(parser) -> None:
    parser.add_argument("workspace", help="a directory of cases (or one case: a directory holding fragments/)")
    parser.add_argument("--host", default="127.0.0.1",
                        help="address to listen on (default 127.0.0.1, this machine only)")
    parser.add_argument("--port", type=int, default=8000, help="port (default 8000; 0 picks a free one)")


def cli_main(args) -> int:
    from ..cli import CliError
    try:
        ws = Workspace(args.workspace)
    except WorkspaceError as exc:
        raise CliError(str(exc)) from None
    if not (viewer_dir() / "node_modules" / "three" / "build" / "three.module.js").is_file():
        print(f"note: three.js is not installed; run `npm install` in {viewer_dir()} (the page will say so)",
              file=sys.stderr)
    app = create_app(ws)
    server = bind(app, args.host, args.port)
    cases = ws.cases()
    print(f"relicgpu viewer: {ws.root} ({len(cases)} case{'s' if len(cases) != 1 else ''})", file=sys.stderr)
    print(f"open {server_url(server, args.host)}   (Ctrl+C stops)", flush=True)
    try:
        server.run()
    except KeyboardInterrupt:
        pass
    finally:
        server.close()
    return 0


def serve_in_thread(app: Flask, host: str = "127.0.0.1", port: int = 0):
    """Start the app in a daemon thread; returns (server, url). server.close() stops it."""
    server = make_server(app, host, port)
    t = threading.Thread(target=server.run, name="relicgpu-viewer", daemon=True)
    t.start()
    return server, server_url(server, host)
