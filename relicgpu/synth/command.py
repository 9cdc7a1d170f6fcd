"""`relicgpu synth`: break solids into OUT (fragments/, truth.json, labels.npz)."""
from __future__ import annotations

import sys
import time
from pathlib import Path

from ..errors import CliError
from ..io.fragment import FragmentError
from .generator import generate
from .truth import write_many


def cli_add_arguments(parser) -> None:
    parser.add_argument("out", metavar="OUT", help="output directory (fragments/, truth.json, labels.npz)")
    parser.add_argument("--shape", default="vase",
                        help="vase, torso, slab, or the path of a closed mesh file; a comma list cycles over --objects "
                             "(default: vase)")
    parser.add_argument("--pieces", type=int, default=2, help="number of fragments per object (default: 2)")
    parser.add_argument("--seed", type=int, default=0, help="random seed; object k uses seed + k (default: 0)")
    parser.add_argument("--faces", type=int, default=4000,
                        help="about this many faces per fragment; vertices are about half (default: 4000)")
    parser.add_argument("--noise", type=float, default=0.0,
                        help="scanner noise along normals, standard deviation as a fraction of the object size "
                             "(default: 0)")
    parser.add_argument("--roughness", type=float, default=0.02,
                        help="RMS height of the fracture surfaces as a fraction of the object size (default: 0.02)")
    parser.add_argument("--no-scatter", action="store_true", help="leave the pieces in place (truth poses = identity)")
    parser.add_argument("--objects", type=int, default=1,
                        help="break this many objects into the same OUT, named o0_..., o1_... (default: 1)")
    parser.add_argument("--prefix", default="", help="prefix of the fragment names; an existing OUT with another "
                                                     "prefix gets this object added (default: none)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar or summary")


def cli_main(args) -> int:
    if args.objects < 1:
        raise CliError(f"--objects must be at least 1, got {args.objects}")
    shapes = [args.shape] if Path(args.shape).exists() else [s.strip() for s in args.shape.split(",") if s.strip()]
    if not shapes:
        raise CliError("--shape is empty")
    results, prefixes = [], []
    start = time.perf_counter()
    try:
        for k in range(args.objects):
            results.append(generate(shapes[k % len(shapes)], pieces=args.pieces, seed=args.seed + k, faces=args.faces,
                                    noise=args.noise, roughness=args.roughness, scatter=not args.no_scatter,
                                    progress=None if not args.quiet else False))
            prefixes.append(args.prefix if args.objects == 1 else f"{args.prefix}o{k}_")
        write_many(results, args.out, prefixes)
    except FragmentError:
        raise
    except ValueError as exc:
        raise CliError(str(exc)) from None
    if not args.quiet:
        n = sum(len(r.fragments) for r in results)
        pairs = sum(len(r.touching) for r in results)
        print(f"wrote {n} fragments of {len(results)} object(s) to {Path(args.out) / 'fragments'}, "
              f"{pairs} touching pairs, truth in {Path(args.out) / 'truth.json'} "
              f"({time.perf_counter() - start:.2f} s)", file=sys.stderr)
    return 0
