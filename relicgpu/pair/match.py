"""`relicgpu match A B -o OUT`: match two fragment files; writes OUT/match.json and
OUT/match.glb (b moved onto a, two colours).

A file of several bodies is matched by its largest body (crumbs and other bodies left
out); the terminal and match.json's "notes" say so. A file that cannot be read stops
the command with exit code 2 and one line naming the file and the fault."""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from ..backends import BackendError, resolve
from ..errors import CliError
from ..io.files import atomic_write_bytes, atomic_write_json, ensure_not_input, grouped_lines
from ..io.load import load_fragment
from ..io.fragment import is_cloud
from ..io.glb import scene_glb
from ..params import Params
from .pipeline import match_pair, pair_scale
from .prepare import prepare

COLOURS = [(214, 120, 72, 255), (72, 140, 214, 255)]


def cli_add_arguments(parser) -> None:
    parser.add_argument("a", help="the fixed fragment (mesh file)")
    parser.add_argument("b", help="the fragment to move onto a")
    parser.add_argument("-o", "--out", required=True, help="output directory (created)")
    parser.add_argument("--backend", default="auto", help="numpy, warp-cpu, warp-cuda[:N], opencl[:PLATFORM] or auto")
    parser.add_argument("--quiet", action="store_true", help="no progress or timings on stderr")


def cli_main(args) -> int:
    log = (lambda *a: None) if args.quiet else (lambda *a: print(*a, file=sys.stderr))
    out = Path(args.out)
    for name in ("match.json", "match.glb"):
        ensure_not_input(out / name, [args.a, args.b])
    t0 = time.perf_counter()
    a = load_fragment(args.a)
    b = load_fragment(args.b)
    for line in grouped_lines("note", list(a.notes + b.notes)):
        log(line)
    log(f"loaded {a.name} ({_size(a)}) and {b.name} ({_size(b)}) in {time.perf_counter() - t0:.2f} s")
    try:
        backend = resolve(args.backend)
    except BackendError as exc:
        raise CliError(str(exc)) from None
    params = Params()
    scale = pair_scale(a, b, params)
    log(f"backend {backend.name}; preparing fragments ...")
    pa = prepare(a, params, backend, scale=scale)
    pb = prepare(b, params, backend, scale=scale)
    if not (is_cloud(a) or is_cloud(b)):  # a cloud is matched on its points: it has no contours
        log(f"  {a.name}: {len(pa.contours)} fracture contours; {b.name}: {len(pb.contours)}")
    result = match_pair(pa, pb, params, backend, scale=scale)
    for stage, t in {**pa.timings, **result.timings}.items():
        log(f"  {stage:>18}: {1000 * t:8.1f} ms")
    verdict = "match" if result.accepted else "no match"
    log(f"{verdict}: overlap {result.overlap:.2f}, rmse {result.rmse:.4g}, penetration {result.penetration:.3f} ({result.reason})")
    doc = {"version": 1, "a": a.source, "b": b.source, "backend": backend.name, **result.to_dict(),
           "notes": list(a.notes + b.notes)}
    atomic_write_json(out / "match.json", doc)
    atomic_write_bytes(out / "match.glb", pair_glb(a, b, result.transform if result.accepted else np.eye(4)))
    log(f"wrote {out / 'match.json'} and {out / 'match.glb'}")
    return 0


def _size(fragment) -> str:
    return f"{len(fragment.vertices)} {'points' if is_cloud(fragment) else 'vertices'}"


def pair_glb(a, b, transform: np.ndarray) -> bytes:
    """Both fragments in two colours, b moved by `transform` (point clouds as points)."""
    return scene_glb([(a, COLOURS[0], np.eye(4)), (b, COLOURS[1], transform)])
