"""relicgpu: reassemble broken 3-D objects from fragment scans on GPU-portable kernels."""
from __future__ import annotations

from .io.fragment import Fragment, FragmentError
from .io.load import load_fragment

__version__ = "0.1.0"

__all__ = ["Fragment", "FragmentError", "load_fragment", "prepare", "match_pair", "assemble", "Params"]


def __getattr__(name):
    # Stages load on first use so that `import relicgpu` stays light.
    if name == "Params":
        from .params import Params
        return Params
    if name == "prepare":
        from .pair.prepare import prepare
        return prepare
    if name == "match_pair":
        from .pair.pipeline import match_pair
        return match_pair
    if name == "assemble":
        from .heap.assembly import assemble
        return assemble
    if name == "group":
        from .heap.grouping import group
        return group
    raise AttributeError(f"module 'relicgpu' has no attribute {name!r}")
