"""Backend registry: `numpy`, `warp-cpu`, `warp-cuda[:N]`, `opencl[:PLATFORM]`, and `auto`.

A backend is a `base.Backend`: the kernel functions of `relicgpu.backends.numpy` (the
float64 specification) face_normals, edge_angles, contour_features, flag_matrix,
lcs_lengths, nearest_neighbors, nearest_index (a target prepared once for many
queries), cross_covariance, the mosaic's led and block_entropy, and ppf_votes (the
coarse stage's point-pair votes), plus a `name`.
`auto` (and the RELICGPU_BACKEND environment variable) chooses one; see `resolve`.

No backend is trusted on sight: `get_backend` runs `selfcheck.run` on it once per
process and refuses it (`BackendRefused`, one warning line on stderr) when any kernel
family disagrees with the NumPy reference; `auto` then picks among the others.
"""
from __future__ import annotations

import functools
import os
import sys
import threading
import time

import numpy as np

from . import numpy as numpy_backend
from . import selfcheck
from .base import Backend
from .opencl import OpenCLBackend, platform_names
from .warp import WarpBackend, _quiet_warp


class BackendError(RuntimeError):
    """A backend that was asked for cannot be used here (named, with the reason)."""


class BackendRefused(BackendError):
    """A backend that loads but gives wrong answers: it failed its self-check."""


def _load(name: str) -> Backend:
    base, _, arg = name.partition(":")
    if base == "numpy":
        return numpy_backend
    if base == "warp-cpu":
        return WarpBackend("cpu")
    if base == "warp-cuda":
        return WarpBackend(f"cuda:{arg or 0}")
    if base == "opencl":
        return OpenCLBackend(arg or None)
    raise BackendError(f"unknown backend {name!r}; choose from numpy, warp-cpu, warp-cuda[:N], opencl[:PLATFORM], auto")


_loaded: dict[str, object] = {}  # name -> backend, or the BackendError it raised
_checks: dict[str, dict[str, str | None]] = {}  # name -> self-check result per family
_loading = threading.RLock()


def _load_checked(name: str):
    try:
        backend = _load(name)
    except BackendError:
        raise
    except Exception as exc:  # missing package, no device, driver error
        raise BackendError(f"backend {name!r} is not available: {exc}") from exc
    if backend is numpy_backend:
        return backend
    t0 = time.perf_counter()
    result = selfcheck.run(backend)
    result_s = time.perf_counter() - t0
    _checks[name] = result
    wrong = {family: why for family, why in result.items() if why}
    if wrong:
        family, why = next(iter(wrong.items()))
        message = (f"backend {name!r} refused: its {', '.join(wrong)} kernel{'s' if len(wrong) > 1 else ''} "
                   f"disagree{'' if len(wrong) > 1 else 's'} with the NumPy reference ({family}: {why})")
        print(f"relicgpu: warning: {message}", file=sys.stderr)
        raise BackendRefused(message)
    backend.selfcheck_s = result_s
    return backend


def get_backend(name: str) -> Backend:
    """The backend called `name` (not `auto`), created and self-checked once per process.

    Raises BackendError when it cannot load here, BackendRefused (a BackendError) when
    it loads but any kernel family disagrees with the NumPy reference."""
    with _loading:
        if name not in _loaded:
            try:
                _loaded[name] = _load_checked(name)
            except BackendError as exc:
                if name.partition(":")[0] not in ("numpy", "warp-cpu", "warp-cuda", "opencl"):
                    raise  # an unknown name is not remembered
                _loaded[name] = exc
        got = _loaded[name]
    if isinstance(got, BackendError):
        raise got
    return got


def selfcheck_results() -> dict[str, dict[str, str | None]]:
    """The self-check of every backend checked so far in this process: {name: {family: None or why}}."""
    return dict(_checks)


def available_backends() -> list[str]:
    """Names of the backends that load, pass their self-check and run here, numpy first."""
    names = candidate_backends()
    return [name for name in names if _usable(name)]


def candidate_backends() -> list[str]:
    """Every backend name worth trying here (loaded or not), numpy first."""
    names = ["numpy", "warp-cpu"]
    try:
        import warp as wp
        _quiet_warp(wp)
        wp.init()
        names += [f"warp-cuda:{d.ordinal}" for d in wp.get_cuda_devices()]
    except Exception:
        pass
    try:
        # through the backend module: it must repair PoCL before devices are listed
        names += [f"opencl:{name}" for name in platform_names()]
    except Exception:
        pass
    return names


def _usable(name: str) -> bool:
    try:
        get_backend(name)
        return True
    except BackendError:
        return False


def _probe_time(backend, repeats: int = 3, give_up_after: float = float("inf")) -> float:
    """Median time of the pipeline's hot path in small: ICP rounds, nearest neighbours of 40k
    points into a 1,500-point surface, half of them near it (a converging fit) and half
    scattered around it (the screen's starts, up to 180 degrees off), within the screen's reach
    (`NearestIndex.query(within=)`, a tenth of the size as `Params.screen_reject`). Nearest
    neighbours are most of a pair's time on every backend; a grid search is fast near the surface
    and slow far from it, a k-d tree the other way round, so both kinds are asked. Returns inf as
    soon as one run takes longer than `give_up_after` seconds."""
    reach = 0.2  # a tenth of the unit sphere's size
    rng = np.random.default_rng(0)
    target = rng.normal(size=(1500, 3))
    target /= np.linalg.norm(target, axis=1, keepdims=True)
    near = target[rng.integers(0, len(target), 20000)] + 0.02 * rng.normal(size=(20000, 3))
    far = target[rng.integers(0, len(target), 20000)] + rng.normal(size=(20000, 3))
    index = backend.nearest_index(target)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(4):
            index.query(near, within=reach)
            index.query(far, within=reach)
        times.append(time.perf_counter() - t0)
        if times[-1] > give_up_after:
            return float("inf")
    return float(np.median(times))


def probe_times() -> dict[str, float]:
    """Measured probe time (seconds, warm, compile excluded) of every available backend;
    inf for one that took more than five times the best."""
    names = available_backends()
    times: dict[str, float] = {}
    for name in [n for n in names if n != "numpy"] + ["numpy"]:
        backend = get_backend(name)
        best = min(times.values(), default=float("inf"))
        if name != "numpy":
            _probe_time(backend, repeats=1)  # compile and warm up
        times[name] = _probe_time(backend, give_up_after=5 * best)
    return {name: times[name] for name in names}


def auto_choice(times: dict[str, float]) -> str:
    """`auto`'s pick from measured probe times: the fastest of numpy and the GPU backends. The
    CPU kernels (warp-cpu, PoCL) are used where asked for by name: on a CPU an assembly forks a
    numpy worker per core (`heap.engines`), where they run in one process with the host code on
    one core, and within the search's reach the k-d tree keeps up with their grid search."""
    eligible = [name for name in times
                if name == "numpy" or getattr(get_backend(name), "kind", "cpu") in ("cuda", "gpu")]
    return min(eligible, key=lambda name: times[name])


@functools.lru_cache(maxsize=None)
def fastest_backend() -> str:
    """`auto`: `auto_choice` of the available backends' measured probes (warm, compile excluded)."""
    return auto_choice(probe_times())


def resolve(name: str | Backend | None = "auto") -> Backend:
    """The backend object for `name`; `auto`/None honours RELICGPU_BACKEND, else measures."""
    if name is None or name == "auto":
        name = os.environ.get("RELICGPU_BACKEND") or "auto"
    if not isinstance(name, str):
        return name  # already a backend object
    if name == "auto":
        name = fastest_backend()
    return get_backend(name)
