"""The `relicgpu` command line.

Each subcommand lives in the module of its stage, which exposes
`cli_add_arguments(parser)` and `cli_main(args) -> int`; this file only routes. It
sits at the top of the import graph: no stage imports it. Modules are imported by
name, only the one asked for (a `relicgpu synth` never loads Flask, and `--help` is
quick); tests/test_layout.py checks that nothing imports this module back.
"""
from __future__ import annotations

import argparse
import importlib
import sys

from .errors import CliError
from .io.fragment import FragmentError

__all__ = ["COMMANDS", "main"]

# subcommand -> (module, one-line help)
COMMANDS = {
    "demo": ("relicgpu.demo", "make a synthetic broken object, assemble it and open the viewer"),
    "synth": ("relicgpu.synth.command", "break a solid into fragments with known poses"),
    "match": ("relicgpu.pair.match", "match two fragments (writes match.json and match.glb)"),
    "assemble": ("relicgpu.heap.run", "match and assemble a directory of fragments"),
    "view": ("relicgpu.viewer.app", "serve the browser viewer of a workspace"),
    "train-fusion": ("relicgpu.fusion_train", "train the feature-fusion MLP with torch"),
    "group": ("relicgpu.heap.run", "sort a heap of fragments into groups by object"),
    "train-classifier": ("relicgpu.heap.run", "train the supervised fragment classifier"),
    "mosaic": ("relicgpu.mosaic.command", "stitch overlapping photographs of a relic"),
    "mesh": ("relicgpu.cloud.triangulate", "triangulate a point-cloud scan into a closed mesh"),
    "backends": ("relicgpu.backends.cli", "list the compute backends available here"),
}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    command = next((a for a in argv if not a.startswith("-")), None)
    parser = _parser_for(command)
    args = parser.parse_args(argv)
    if getattr(args, "_missing", False):
        print(f"relicgpu {args._command}: module {args._module} is not available; install the matching extra", file=sys.stderr)
        return 2
    try:
        handler = getattr(importlib.import_module(args._module), "cli_main")
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
    try:
        mod = importlib.import_module(module)
    except ImportError as exc:  # an extra (Flask for the viewer) is not installed
        p.set_defaults(_missing=True)
        p.add_argument("rest", nargs=argparse.REMAINDER)
        print(f"note: {exc}", file=sys.stderr)
        return parser
    add = getattr(mod, "cli_add_arguments")
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
