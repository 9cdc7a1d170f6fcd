"""Every backend present implements `relicgpu.backends.base.Backend`: each member of the
Protocol, with the Protocol's signature (parameter names, kinds and defaults). The Warp
and OpenCL kernel sources name their kernels alike."""
from __future__ import annotations

import importlib.resources
import inspect
import re

import numpy as np

from relicgpu.backends import base
from relicgpu.backends import numpy as ref


def _methods(protocol) -> list[str]:
    return sorted(name for name, value in vars(protocol).items() if not name.startswith("_") and callable(value))


def _params(fn, drop_self: bool) -> list[tuple]:
    params = list(inspect.signature(fn).parameters.values())[1 if drop_self else 0:]
    return [(p.name, p.kind, p.default) for p in params]


def _check(obj, protocol) -> None:
    for name in protocol.__annotations__:
        assert hasattr(obj, name), f"{obj!r} has no {name}"
    for name in _methods(protocol):
        assert callable(getattr(obj, name, None)), f"{obj!r} has no {name}"
        assert _params(getattr(obj, name), False) == _params(getattr(protocol, name), True), \
            f"{obj!r}.{name}: signature differs from the Protocol's"
    assert isinstance(obj, protocol)


def test_protocol_declares_every_kernel_function():
    assert base.Backend.__annotations__ == {"name": "str"}
    assert _methods(base.Backend) == sorted(
        ["face_normals", "edge_angles", "contour_features", "flag_matrix", "lcs_lengths", "nearest_neighbors",
         "nearest_index", "cross_covariance", "led", "block_entropy", "ppf_votes"])
    for fn in [getattr(base.Backend, name) for name in _methods(base.Backend)] + [base.NearestIndex.query]:
        assert "Parameters\n" in fn.__doc__ and "Returns\n" in fn.__doc__, fn.__name__  # numpydoc, with shapes


def test_every_backend_present_satisfies_the_protocol(backend):
    _check(backend, base.Backend)
    target = np.random.default_rng(0).random((10, 3))
    _check(backend.nearest_index(target), base.NearestIndex)


def test_the_reference_is_the_numpy_module():
    _check(ref, base.Backend)
    assert ref.name == "numpy"


def test_warp_and_opencl_kernels_have_the_same_names():
    warp = importlib.resources.files("relicgpu.kernels.warp")
    opencl = importlib.resources.files("relicgpu.kernels.opencl")
    sources = sorted(p.name[:-3] for p in opencl.iterdir() if p.name.endswith(".cl"))
    assert sources == sorted(p.name[:-3] for p in warp.iterdir() if p.name.endswith(".py") and p.name != "__init__.py")
    for name in sources:
        cl = re.findall(r"__kernel\s+void\s+(\w+)", opencl.joinpath(name + ".cl").read_text())
        wp = re.findall(r"@wp\.kernel\s*(?:\([^)]*\))?\s*def\s+(\w+)", warp.joinpath(name + ".py").read_text())
        assert cl and sorted(cl) == sorted(wp), name
