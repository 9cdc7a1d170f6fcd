"""Shared fixtures: the compute backends to test.

`backend` runs a test on every backend: numpy always; warp-cpu; warp-cuda:N for
each CUDA device (skipped where there is none); opencl:<platform> for each
OpenCL platform with a device (skipped where pyopencl or a platform is missing).
`device_backend` is the same list without numpy, for comparisons with the
numpy reference.
"""
from __future__ import annotations

import pytest

from relicgpu.backends import BackendError, get_backend


def _backend_names() -> list[str]:
    names = ["numpy", "warp-cpu"]
    cuda: list[str] = []
    try:
        import warp as wp

        from relicgpu.backends.warp import _quiet_warp

        _quiet_warp(wp)
        wp.init()
        cuda = [f"warp-cuda:{d.ordinal}" for d in wp.get_cuda_devices()]
    except Exception:
        pass
    names += cuda or ["warp-cuda:0"]
    platforms: list[str] = []
    try:
        from relicgpu.backends.opencl import platform_names

        platforms = platform_names()
    except Exception:
        pass
    names += [f"opencl:{p}" for p in platforms] or ["opencl"]
    return names


BACKEND_NAMES = _backend_names()


def _param(name: str):
    marks = [pytest.mark.cuda] if name.startswith("warp-cuda") else []
    return pytest.param(name, id=name.replace(" ", "_"), marks=marks)


def _load(name: str):
    try:
        return get_backend(name)
    except BackendError as exc:
        pytest.skip(str(exc))


@pytest.fixture(params=[_param(n) for n in BACKEND_NAMES])
def backend(request):
    return _load(request.param)


@pytest.fixture(params=[_param(n) for n in BACKEND_NAMES if n != "numpy"])
def device_backend(request):
    return _load(request.param)
