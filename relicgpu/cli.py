"""The `relicgpu` command line.

Each subcommand lives in the module of its stage, which exposes
`cli_add_arguments(parser)` and `cli_main(args) -> int`; this file only routes. It
sits at the top of the import graph: it imports the stages, no stage imports it.
The viewer's commands (`view`, `demo`) need Flask, an extra: without it they say so.
"""
from __future__ import annotations

import argparse
import sys

from . import fusion_train, mosaic, synth
from .heap import run as heaprun
from .pair import match
from .backends import cli as backends_cli
from .cloud import triangulate
from .errors import CliError
from .io.fragment import FragmentError

try:
    from .viewer import app as viewer_app
    from . import demo
except ImportError as exc:  # the viewer extra (Flask) is not installed
    viewer_app = demo = exc

__all__ = ["COMMANDS", "main"]

# subcommand -> (module, one-line help); a module that could not be imported is its ImportError
COMMANDS = {
    "demo": (demo, "make a synthetic broken object, assemble it and open the viewer"),
    "synth": (synth, "break a solid into fragments with known poses"),
    "match": (match, "match two fragments (writes match.json and match.glb)"),
    "assemble": (heaprun, "match and assemble a directory of fragments"),
    "view": (viewer_app, "serve the browser viewer of a workspace"),
    "train-fusion": (fusion_train, "train the feature-fusion MLP with torch"),
    "group": (heaprun, "sort a heap of fragments into groups by object"),
    "train-classifier": (heaprun, "train the supervised fragment classifier"),
    "mosaic": (mosaic, "stitch overlapping photographs of a relic"),
    "mesh": (triangulate, "triangulate a point-cloud scan into a closed mesh"),
    "backends": (backends_cli, "list the compute backends available here"),
}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    command = next((a for a in argv if not a.startswith("-")), None)
    parser = _parser_for(command)
    args = parser.parse_args(argv)
    if getattr(args, "_missing", False):
        print(f"relicgpu {args._command}: this command is not available; install the matching extra", file=sys.stderr)
        return 2
    try:
        handler = getattr(args._module, "cli_main")
        result = handler(args) if handler.__code__.co_argcount == 1 else handler(args, args._command)
        return int(result or 0)
    except (FragmentError, CliError) as exc:
        print(f"relicgpu {args._command}: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


def _parser_for(command: str | None) -> argparse.ArgumentParser:
    if command not in COMMANDS:
        return build_parser_names_only()
    parser = argparse.ArgumentParser(prog="relicgpu")
    sub = parser.add_subparsers(dest="command")
    module, help_text = COMMANDS[command]
    p = sub.add_parser(command, help=help_text, description=help_text)
    p.set_defaults(_module=module, _command=command)
    if isinstance(module, ImportError):
        p.set_defaults(_missing=True)
        p.add_argument("rest", nargs=argparse.REMAINDER)
        print(f"note: {module}", file=sys.stderr)
        return parser
    add = getattr(module, "cli_add_arguments")
    add(p) if add.__code__.co_argcount == 1 else add(p, command)
    return parser


def build_parser_names_only() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="relicgpu", description="Reassemble broken 3-D objects from fragment scans.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name, (_, help_text) in COMMANDS.items():
        sub.add_parser(name, help=help_text)
    return parser


if __name__ == "__main__":
    sys.exit(main())
