"""The viewer's Flask app: the three.js page of `viewer/` and a JSON API under /api/.

`create_app(workspace)` builds the app (its request guards and error handlers here,
the routes in `relicgpu.viewer.routes`, their shared state in
`relicgpu.viewer.state`, the JSON in `relicgpu.viewer.serialize`);
`make_server(app, host, port)` runs it under
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
                                                  gives id#1, id#2, ...), poses, groups, object groups,
                                                  how the assembly holds each (used_matches, on_loop)
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

import errno
import ipaddress
import os
import sys
import threading
import traceback
from pathlib import Path

from flask import Flask, Response, jsonify, request
from werkzeug.exceptions import HTTPException

from ..errors import CliError
from .hooks import default_match_pair, default_prepare, pipeline_available, run_assembly
from .routes import bp
from .state import ApiError, ViewerState
from .workspace import Workspace, WorkspaceError

__all__ = ["create_app", "viewer_dir", "make_server", "serve_in_thread", "server_url", "bind",
           "is_loopback", "run_assembly", "cli_add_arguments", "cli_main"]

MAX_BODY_BYTES = 64 * 1024  # requests carry a few names and numbers
LOOPBACK_NAMES = {"localhost", "127.0.0.1", "::1", "[::1]"}


def viewer_dir() -> Path:
    """The page's folder.

    Returns
    -------
    Path
        $RELICGPU_VIEWER_DIR when set; else the page an installed wheel carries
        (relicgpu/viewer/page/, with the three.js modules it imports); else `viewer/`
        at the root of the source checkout this package is imported from.
    """
    env = os.environ.get("RELICGPU_VIEWER_DIR")
    if env:
        return Path(env).resolve()
    here = Path(__file__).resolve().parent
    if (here / "page" / "index.html").is_file():
        return here / "page"
    return here.parents[1] / "viewer"


def create_app(workspace, *, prepare=None, match_pair=None, assemble=None, trusted_hosts=None) -> Flask:
    """The viewer app of one workspace.

    Every fragment of a case is prepared at one scale, the median fragment size of the case
    (the scale relicgpu's group stages use), so its contours are those the head nodes index.

    Parameters
    ----------
    workspace : Workspace or path
        The cases to serve (see relicgpu.viewer.workspace).
    prepare : callable, optional
        prepare(fragment, scale) -> Prepared; default relicgpu.prepare.
    match_pair : callable, optional
        match_pair(prepared_a, prepared_b, heads, scale) -> PairMatch; default relicgpu.match_pair.
    assemble : callable, optional
        assemble(fragments_dir, out_dir, report) -> summary dict; default `run_assembly`.
    trusted_hosts : iterable of str, optional
        The Host header names accepted (default: loopback names only, which stops
        DNS-rebinding pages from reaching the API); make_server() turns the check off for a
        non-loopback host, which users reach by names the app cannot know.

    Returns
    -------
    Flask
        The app, its ViewerState in ``app.extensions["relicgpu"]`` (also its workspace,
        host check and job runner under "relicgpu.workspace", "relicgpu.hosts",
        "relicgpu.jobs").
    """
    ws = workspace if isinstance(workspace, Workspace) else Workspace(workspace)
    app = Flask("relicgpu.viewer", static_folder=None)
    app.config.update(MAX_CONTENT_LENGTH=MAX_BODY_BYTES, JSON_SORT_KEYS=False, DEBUG=False,
                      PROPAGATE_EXCEPTIONS=False)
    app.json.sort_keys = False

    hooks = {
        "prepare": prepare or default_prepare,
        "match_pair": match_pair or default_match_pair,
        "assemble": assemble or run_assembly,
    }
    capabilities = {
        "prepare": prepare is not None or pipeline_available("relicgpu.pair.pipeline"),
        "match": match_pair is not None or pipeline_available("relicgpu.pair.pipeline"),
        "assemble": assemble is not None or pipeline_available("relicgpu.heap.assembly"),
    }
    state = ViewerState(ws, viewer_dir(), hooks, capabilities)
    hosts = {"trusted": set(LOOPBACK_NAMES) if trusted_hosts is None else set(trusted_hosts)}
    app.extensions["relicgpu"] = state
    app.extensions["relicgpu.workspace"] = ws
    app.extensions["relicgpu.hosts"] = hosts
    app.extensions["relicgpu.jobs"] = state.jobs
    _add_guards(app, hosts)
    app.register_blueprint(bp)
    return app


def _add_guards(app: Flask, hosts: dict) -> None:
    """The Host check, the security headers and the JSON error answers."""

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


# --- serving ---------------------------------------------------------------------

def is_loopback(host: str) -> bool:
    """Whether host (a name or an address, IPv6 in brackets or not) is this machine only."""
    if host in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def make_server(app: Flask, host: str = "127.0.0.1", port: int = 8000, threads: int = 8):
    """A waitress server bound to host:port, not yet running.

    Parameters
    ----------
    app : Flask
        From create_app.
    host : str
        The address to listen on; a non-loopback one prints a warning and turns the app's
        Host check off.
    port : int
        0 picks any free port (server.effective_port).
    threads : int
        Waitress worker threads.

    Returns
    -------
    waitress.server.BaseWSGIServer
        server.run() serves, server.close() stops.
    """
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
    """The http:// address a browser on this machine opens for a server bound to host."""
    port = server.effective_port
    shown = "127.0.0.1" if host in ("0.0.0.0", "") else ("[::1]" if host == "::" else host)
    if ":" in shown and not shown.startswith("["):
        shown = f"[{shown}]"
    return f"http://{shown}:{port}/"


def bind(app: Flask, host: str, port: int):
    """make_server, with a port that cannot be bound raised as a one-line CliError."""
    try:
        return make_server(app, host, port)
    except OSError as exc:
        raise CliError(f"cannot listen on {host}:{port} ({exc.strerror or exc}); "
                       "pass another --port, or --port 0 for any free one") from None


def cli_add_arguments(parser) -> None:
    """The arguments of `relicgpu view` (workspace, --host, --port) on an argparse parser."""
    parser.add_argument("workspace", help="a directory of cases (or one case: a directory holding fragments/)")
    parser.add_argument("--host", default="127.0.0.1",
                        help="address to listen on (default 127.0.0.1, this machine only)")
    parser.add_argument("--port", type=int, default=8000, help="port (default 8000; 0 picks a free one)")


def cli_main(args) -> int:
    """`relicgpu view`: serve a workspace until Ctrl+C; returns the exit status."""
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
    """Start the app in a daemon thread.

    Parameters
    ----------
    app : Flask
        From create_app.
    host : str
        The address to listen on.
    port : int
        0 picks any free port.

    Returns
    -------
    tuple
        (server, url); server.close() stops it.
    """
    server = make_server(app, host, port)
    t = threading.Thread(target=_run_until_closed, args=(server,), name="relicgpu-viewer", daemon=True)
    t.start()
    return server, server_url(server, host)


def _run_until_closed(server) -> None:
    """`server.run()` until `server.close()`: closed from another thread, its sockets leave the
    loop's select() with EBADF, which is how it ends, not an error."""
    try:
        server.run()
    except OSError as exc:
        if exc.errno != errno.EBADF:
            raise
