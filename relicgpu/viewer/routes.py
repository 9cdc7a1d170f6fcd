"""The viewer's routes: the page, its three.js, and the JSON API (listed in
relicgpu.viewer.app), as the Blueprint `bp`. Every route reads the app's
ViewerState, `current_app.extensions["relicgpu"]`."""
from __future__ import annotations

import json
import os
import time
from pathlib import Path

from flask import Blueprint, Response, current_app, jsonify, request, send_file
from werkzeug.security import safe_join

from ..heap.support import held_by
from .jobs import FINAL_STATES, JobBusy
from .serialize import b64, match_to_json, prepared_to_json, sse
from .state import ApiError, ViewerState
from .workspace import AssemblyFileError

SSE_TICK_S = 2.0
SSE_MAX_RATE_HZ = 10

bp = Blueprint("viewer", __name__)


def _state() -> ViewerState:
    return current_app.extensions["relicgpu"]


def _json_body() -> dict:
    if not request.is_json:
        raise ApiError(415, "send the request body as JSON (Content-Type: application/json)")
    try:
        body = json.loads(request.get_data(cache=False, as_text=False) or b"")
    except (ValueError, UnicodeDecodeError) as exc:
        raise ApiError(400, f"malformed JSON body: {exc}") from None
    if not isinstance(body, dict):
        raise ApiError(400, "the JSON body must be an object")
    return body


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


# -- the page ------------------------------------------------------------------------

@bp.get("/")
def index():
    """The page, or a 503 page saying how to install three.js when it is missing."""
    st = _state()
    page = st.page_dir / "index.html"
    if not page.is_file():
        raise ApiError(500, f"the viewer page is missing: {page}")
    if not (st.three_dir / "build" / "three.module.js").is_file():
        return Response(
            "<!doctype html><meta charset=utf-8><title>relicgpu viewer</title>"
            "<p>three.js is not installed: run <code>npm install</code> in the <code>viewer/</code> folder.</p>",
            status=503, mimetype="text/html")
    return send_file(page, mimetype="text/html", max_age=0)


@bp.get("/static/<path:filename>")
def static_file(filename):
    """A file of the page's folder (never node_modules/)."""
    if filename.split("/", 1)[0] == "node_modules":
        raise ApiError(404, f"not found: {request.path}")
    return _send_inside(_state().page_dir, filename)


@bp.get("/vendor/three/<path:filename>")
def vendor_three(filename):
    """A three.js module: build/ or examples/jsm/ of node_modules/three."""
    if not (filename.startswith("build/") or filename.startswith("examples/jsm/")):
        raise ApiError(404, f"not found: {request.path}")
    return _send_inside(_state().three_dir, filename)


# -- the API -------------------------------------------------------------------------

@bp.get("/api/cases")
def api_cases():
    """The workspace's cases, its capabilities and the latest job."""
    st = _state()
    ws = st.ws
    out = []
    for case in ws.cases().values():
        count, exact = st.fragment_count(case)
        out.append({
            "id": case.id,
            "fragments": count,
            "fragments_exact": exact,
            "assembled": ws.assembly_file(case, "assembly.json") is not None,
            "truth": (case.path / "truth.json").is_file(),
        })
    latest = st.jobs.latest()
    return jsonify(workspace=ws.name, single_case=ws.is_single_case(), cases=out,
                   capabilities=st.capabilities, job=latest.snapshot() if latest else None)


@bp.get("/api/cases/<case_id>/fragments")
def api_fragments(case_id):
    """A case's fragments with their poses, groups, object groups and how the assembly holds each."""
    st = _state()
    ws = st.ws
    case = st.case_or_404(case_id)
    entries = st.entries_of(case)
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
    where = {name: k for k, name in enumerate(entries)}
    # (a match naming a fragment no longer in the workspace holds nothing here)
    used, on_loop = held_by(len(where), [(where[m["a"]], where[m["b"]]) for m in
                                         (assembly.matches if assembly else [])
                                         if m["used"] and m["a"] in where and m["b"] in where])
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
            "used_matches": used[i],  # how the assembly holds it (relicgpu.heap.support)
            "on_loop": on_loop[i],
        })
    return jsonify(case=case.id, fragments=frags, assembled=assembly is not None,
                   assembly_error=error, notes=notes,
                   assembly=(assembly.meta if assembly else None),
                   objects=({"source": objects.source, "count": objects.count, "method": objects.method}
                            if objects else None),
                   files=[n for n in ("assembly.json", "assembly.glb", "merged.stl")
                          if ws.assembly_file(case, n) is not None],
                   capabilities=st.capabilities)


@bp.get("/api/cases/<case_id>/fragments/<name>/mesh")
def api_mesh(case_id, name):
    """One fragment's vertices and faces (base64 float32 / uint32)."""
    st = _state()
    case = st.case_or_404(case_id)
    frag = st.fragment_of(st.entry_or_404(case, name))
    return jsonify(name=name, n_vertices=len(frag.vertices), n_faces=len(frag.faces),
                   size=frag.size, centroid=frag.vertices.mean(axis=0).tolist(),
                   vertices=b64(frag.vertices, "<f4"), faces=b64(frag.faces, "<u4"),
                   notes=[n.replace(str(st.ws.root) + os.sep, "") for n in frag.notes])


@bp.get("/api/cases/<case_id>/fragments/<name>/contours")
def api_contours(case_id, name):
    """One fragment's segmentation and contours, prepared at its case's scale."""
    st = _state()
    case = st.case_or_404(case_id)
    entry = st.entry_or_404(case, name)
    return jsonify(prepared_to_json(name, st.prepared_of(case, entry)))


@bp.get("/api/cases/<case_id>/matches")
def api_matches(case_id):
    """The pair matches of a case's assembly.json."""
    st = _state()
    case = st.case_or_404(case_id)
    try:
        assembly = st.ws.read_assembly(case, st.entries_of(case))
    except AssemblyFileError as exc:
        raise ApiError(422, str(exc)) from None
    if assembly is None:
        return jsonify(case=case.id, assembled=False, matches=[])
    return jsonify(case=case.id, assembled=True, matches=assembly.matches)


@bp.get("/api/cases/<case_id>/files/<filename>")
def api_case_file(case_id, filename):
    """assembly.json, assembly.glb or merged.stl of a case."""
    st = _state()
    case = st.case_or_404(case_id)
    p = st.ws.assembly_file(case, filename)
    if p is None:
        raise ApiError(404, f"no file {filename!r} in case {case.id!r} (one of assembly.json, assembly.glb, merged.stl once assembled)")
    return send_file(p, as_attachment=filename != "assembly.json", max_age=0)


@bp.post("/api/match")
def api_match():
    """Match one pair again, from head nodes picked on the page or from scratch."""
    st = _state()
    if not st.capabilities["match"]:
        raise ApiError(503, "relicgpu.match_pair is not available in this installation")
    body = _json_body()
    case = st.case_or_404(body.get("case"))
    a_name, b_name = body.get("a"), body.get("b")
    ea, eb = st.entry_or_404(case, a_name), st.entry_or_404(case, b_name)
    if ea.name == eb.name:
        raise ApiError(400, "a and b must be two different fragments")
    heads = body.get("heads")
    if heads is not None:
        if (not isinstance(heads, list) or len(heads) != 4
                or not all(isinstance(h, int) and not isinstance(h, bool) for h in heads)):
            raise ApiError(400, "heads must be a list of 4 integers [contour_a, point_a, contour_b, point_b]")
    pa, pb = st.prepared_of(case, ea), st.prepared_of(case, eb)
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
    with st.compute_slots:
        result = st.hooks["match_pair"](pa, pb, heads, st.case_scale(case))
    return jsonify(match_to_json(ea.name, eb.name, heads, result))


@bp.post("/api/assemble")
def api_assemble():
    """Start assembling a case in the background (202 with the job; 409 while one runs)."""
    st = _state()
    if not st.capabilities["assemble"]:
        raise ApiError(503, "relicgpu.assemble is not available in this installation")
    body = _json_body()
    case = st.case_or_404(body.get("case"))
    ws = st.ws
    if not ws.fragments(case):
        raise ApiError(400, f"case {case.id!r} has no fragment files in fragments/")
    assemble = st.hooks["assemble"]

    def work(report):
        report(stage="starting", message=f"{len(ws.fragments(case))} fragments")
        return assemble(case.fragments_dir, case.assembly_dir, report)

    try:
        job = st.jobs.start(case.id, work)
    except JobBusy as exc:
        raise ApiError(409, str(exc)) from None
    return jsonify(job.snapshot()), 202


@bp.get("/api/jobs")
def api_jobs():
    """The latest job's state."""
    latest = _state().jobs.latest()
    return jsonify(job=latest.snapshot() if latest else None)


@bp.get("/api/progress")
def api_progress():
    """A job's state (?job=N, default the latest) as server-sent events until it ends."""
    jobs = _state().jobs
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
            yield sse({"state": "idle", "job": None})
            return
        # The latest state on every change, at most SSE_MAX_RATE_HZ times a second, and
        # at least every SSE_TICK_S (the elapsed time moves on while a stage runs).
        while True:
            snap = job.snapshot()
            yield sse(snap, event_id=snap["seq"])
            if snap["state"] in FINAL_STATES:
                return
            time.sleep(1.0 / SSE_MAX_RATE_HZ)
            jobs.wait(job, snap["seq"], SSE_TICK_S)

    return Response(stream(latest), mimetype="text/event-stream",
                    headers={"Cache-Control": "no-store", "X-Accel-Buffering": "no"})
