"""`relicgpu demo`: break a synthetic object, assemble it, and open the viewer on it.

The case goes to WORKSPACE/demo-<shape>-<pieces>p-s<seed>/ (fragments/ and
truth.json from relicgpu.synth, assembly/ from relicgpu.assemble). Fragments
made before with the same settings are reused (--fresh makes them again), and
the assembly is run again from its cache, so a second start is quick. The
viewer serves the whole WORKSPACE.
"""
from __future__ import annotations

import os
import sys
import threading
import time
from pathlib import Path

from . import synth
from .errors import CliError
from .viewer.app import bind, create_app, run_assembly, server_url

DEFAULT_WORKSPACE = "demo-workspace"
SHAPES = ("vase", "torso", "slab")


def case_name(shape: str, pieces: int, seed: int) -> str:
    return f"demo-{shape}-{pieces}p-s{seed}"


def make_case(workspace: Path, shape: str = "vase", pieces: int = 4, seed: int = 1, fresh: bool = False,
              log=print) -> Path:
    """Synthesize and assemble the demo case (or reuse it); returns the case directory."""
    case = Path(workspace) / case_name(shape, pieces, seed)
    frag_dir = case / "fragments"
    have_fragments = frag_dir.is_dir() and (case / "truth.json").is_file() and any(frag_dir.iterdir())
    if fresh or not have_fragments:
        log(f"breaking a synthetic {shape} into {pieces} pieces (seed {seed}) ...")
        t0 = time.perf_counter()
        result = synth.generate(shape=shape, pieces=pieces, seed=seed)
        synth.write(result, case)
        log(f"  {len(result.fragments)} fragments in {case / 'fragments'} ({time.perf_counter() - t0:.1f} s)")
    else:
        log(f"reusing the fragments in {frag_dir} (--fresh makes them again)")

    # Always assembled again: relicgpu.assemble keeps finished work in assembly/cache, keyed by
    # the code that made it, so a rerun is quick and never shows an answer of older code.
    log("assembling them with relicgpu.assemble ...")
    t0 = time.perf_counter()
    summary = run_assembly(frag_dir, case / "assembly", lambda **kw: None, progress=True)
    log(f"  {summary.get('placed', '?')} of {summary.get('fragments', '?')} fragments placed in "
        f"{summary.get('groups', '?')} group(s), {time.perf_counter() - t0:.1f} s; outputs in {case / 'assembly'}")
    return case


def _can_open_browser() -> bool:
    # Without a display, Python's webbrowser falls back to console browsers (lynx, w3m)
    # that would take over this terminal: only open one where a desktop is there.
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def cli_add_arguments(parser) -> None:
    parser.add_argument("--workspace", default=DEFAULT_WORKSPACE,
                        help=f"where the demo case is written and served from (default ./{DEFAULT_WORKSPACE})")
    parser.add_argument("--shape", default="vase", choices=SHAPES, help="the synthetic object (default vase)")
    parser.add_argument("--pieces", type=int, default=6, help="number of fragments (default 6)")
    parser.add_argument("--seed", type=int, default=1, help="random seed of the breakage (default 1)")
    parser.add_argument("--fresh", action="store_true", help="break the object again even if its fragments exist")
    parser.add_argument("--no-browser", action="store_true", help="only print the viewer's address")
    parser.add_argument("--no-serve", action="store_true", help="make and assemble the case, then exit")
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    parser.add_argument("--port", type=int, default=8000,
                        help="port (default 8000, or a free one when 8000 is taken; 0 picks a free one)")


def cli_main(args) -> int:
    if args.pieces < 2:
        raise CliError(f"--pieces must be at least 2, got {args.pieces}")
    if args.seed < 0:
        raise CliError(f"--seed must be non-negative, got {args.seed}")
    workspace = Path(args.workspace)
    if workspace.exists() and not workspace.is_dir():
        raise CliError(f"{workspace}: not a directory")
    workspace.mkdir(parents=True, exist_ok=True)

    def log(msg):
        print(msg, file=sys.stderr, flush=True)

    case = make_case(workspace, args.shape, args.pieces, args.seed, args.fresh, log)
    if args.no_serve:
        return 0

    app = create_app(workspace)
    try:
        server = bind(app, args.host, args.port)
    except CliError:
        if args.port != 8000:
            raise
        server = bind(app, args.host, 0)  # the default port is taken: any free one will do
    url = f"{server_url(server, args.host)}#case={case.name}"
    print(f"relicgpu viewer on {workspace.resolve()}\nopen {url}   (Ctrl+C stops)", flush=True)
    if not args.no_browser:
        if _can_open_browser():
            import webbrowser
            threading.Timer(0.5, webbrowser.open, args=(url,)).start()
        else:
            log("(no desktop here to open a browser in: open the address above yourself)")
    try:
        server.run()
    except KeyboardInterrupt:
        pass
    finally:
        server.close()
    return 0
