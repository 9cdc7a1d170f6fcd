"""`relicgpu mosaic LEFT RIGHT [MORE ...] -o OUT.png`."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from ..backends import BackendError, resolve
from ..errors import CliError
from ..io.files import ensure_not_input
from .params import MosaicParams
from .stitching import _FORMATS, save_image, stitch


def cli_add_arguments(parser) -> None:
    parser.add_argument("images", nargs="+", metavar="IMAGE",
                        help="overlapping photographs in order, left to right (LEFT RIGHT [MORE ...])")
    parser.add_argument("-o", "--output", required=True, metavar="OUT.png", help="the stitched image")
    parser.add_argument("--backend", default="auto", help="numpy, warp-cpu, warp-cuda[:N], opencl[:PLATFORM] or auto")
    parser.add_argument("--vertical", action="store_true", help="the images run top to bottom")
    parser.add_argument("--min-overlap", type=float, default=MosaicParams.min_overlap,
                        help="smallest overlap as a fraction of the image width (default %(default)s)")


def cli_main(args) -> int:
    if len(args.images) < 2:
        raise CliError("give at least two images (LEFT RIGHT [MORE ...])")
    if not 0.05 <= args.min_overlap <= 0.95:
        raise CliError(f"--min-overlap must be between 0.05 and 0.95, got {args.min_overlap}")
    out = Path(args.output)
    if out.suffix.lower() not in _FORMATS:
        raise CliError(f"{out}: unknown image suffix; use one of {', '.join(sorted(_FORMATS))}")
    ensure_not_input(out, args.images)
    try:
        backend = resolve(args.backend)
    except BackendError as exc:
        raise CliError(str(exc)) from None
    params = replace(MosaicParams(), min_overlap=args.min_overlap)
    result = stitch([Path(x) for x in args.images], backend=backend, params=params, vertical=args.vertical,
                    progress=True)
    save_image(out, result.image)
    for name, (row, col), angle in zip(args.images, result.offsets, result.angles):
        print(f"{name}: origin at row {row:.1f}, col {col:.1f}, rotated {angle:+.2f} deg")
    print(f"wrote {out} ({result.image.shape[1]}x{result.image.shape[0]} px, backend {backend.name})")
    return 0
