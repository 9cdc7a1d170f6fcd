"""Shared fixtures: the compute backends to test.

`backend` runs a test on every backend: numpy always; warp-cpu; warp-cuda:N for
each CUDA device (skipped where there is none); opencl:<platform> for each
OpenCL platform with a device (skipped where pyopencl or a platform is missing).
`device_backend` is the same list without numpy, for comparisons with the
numpy reference.

A backend that loads but fails its self-check (wrong answers) fails its tests; it is
never skipped. RELICGPU_REQUIRE_BACKENDS (comma-separated names; `opencl` stands for
every OpenCL platform) turns "not available" skips of those backends into failures.
"""
from __future__ import annotations

import os

import pytest

from relicgpu.backends import BackendError, BackendRefused, get_backend

REQUIRED = [n.strip() for n in os.environ.get("RELICGPU_REQUIRE_BACKENDS", "").split(",") if n.strip()]


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


def _required(name: str) -> bool:
    return any(name == r or name.partition(":")[0] == r for r in REQUIRED)


def _load(name: str):
    try:
        return get_backend(name)
    except BackendRefused as exc:
        pytest.fail(str(exc))
    except BackendError as exc:
        if _required(name):
            pytest.fail(f"{exc} (RELICGPU_REQUIRE_BACKENDS names it)")
        pytest.skip(str(exc))


@pytest.fixture(params=[_param(n) for n in BACKEND_NAMES])
def backend(request):
    return _load(request.param)


@pytest.fixture(params=[_param(n) for n in BACKEND_NAMES if n != "numpy"])
def device_backend(request):
    return _load(request.param)
