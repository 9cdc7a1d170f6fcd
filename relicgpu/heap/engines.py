"""Where the per-fragment and per-pair work of an assembly runs.

An engine maps a module-level function over a list of jobs and hands each
result back to the caller as soon as it is ready (the caller caches it on disk,
so an interrupted run loses nothing finished). A job is a payload plus the keys
of the shared objects it needs; the function is called as
`fn(payload, *[objects[k] for k in needs])` and returns a picklable result.

* `local`: on this machine: a thread pool when the backend releases the GIL (its
  `releases_gil` attribute); forked worker processes, one thread each, where the backend keeps
  no device or thread state a fork would break (its `forks` attribute: numpy) and the system
  forks (Linux); else one job after the other in this process.
* `ray`: each job is a Ray task. `address` joins a running cluster, otherwise a
  local Ray starts with `workers` CPUs (or the machine's). Shared objects go
  into the object store once; a task takes one GPU where the cluster has GPUs and the
  backend runs on one (or `gpus_per_task`, a fraction, so that several tasks share a GPU);
  a task lost with its worker or node is retried by Ray (`max_retries`).
  Scheduling, retries and data movement are all Ray's.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import multiprocessing
import os
import signal
import sys
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor, as_completed
from dataclasses import dataclass
from typing import Any, Callable

ENGINES = ("local", "ray")
MAX_RETRIES = 3  # Ray retries of a task whose worker died


@dataclass(frozen=True)
class Job:
    payload: Any
    needs: tuple = ()  # keys into the shared objects


def make_engine(name: str, workers: int | None = None, address: str | None = None, backend=None,
                gpus_per_task: float | None = None):
    """The engine called `name` ("local" or "ray")."""
    if name == "local":
        return LocalEngine(workers, threads=bool(getattr(backend, "releases_gil", False)),
                           processes=bool(getattr(backend, "forks", False)))
    if name == "ray":
        return RayEngine(workers, address, gpus_per_task, needs_gpu=backend is None or on_gpu(backend))
    raise ValueError(f"unknown engine {name!r}; choose from {', '.join(ENGINES)}")


def on_gpu(backend) -> bool:
    """Whether a backend runs its kernels on a GPU (warp-cuda, an OpenCL GPU)."""
    return getattr(backend, "kind", "cpu") in ("cuda", "gpu")


def task_gpus(cluster_gpus: int, requested: float | None, needs_gpu: bool) -> float:
    """GPUs a task asks Ray for: none where the cluster has none or the backend runs on the CPU
    (a numpy run on a GPU host asking one GPU per task had run one task at a time), else the
    request, by default one."""
    if not cluster_gpus or not needs_gpu:
        return 0.0
    return 1.0 if requested is None else float(requested)


class LocalEngine:
    name = "local"

    def __init__(self, workers: int | None = None, threads: bool = False, processes: bool = False):
        self.workers = max(1, int(workers or os.cpu_count() or 1))
        self.threads = threads and self.workers > 1
        # (Linux only: macOS forks, but its BLAS does not survive a fork)
        self.processes = processes and not self.threads and self.workers > 1 and sys.platform.startswith("linux")

    def map(self, fn: Callable, jobs: list[Job], objects: dict, on_result: Callable[[Job, Any], None]) -> None:
        if self.processes and len(jobs) > 1:
            return self._map_forked(fn, jobs, objects, on_result)
        if not self.threads:
            for job in jobs:
                on_result(job, fn(job.payload, *[objects[k] for k in job.needs]))
            return
        with ThreadPoolExecutor(self.workers) as pool:
            futures = {pool.submit(fn, job.payload, *[objects[k] for k in job.needs]): job for job in jobs}
            _collect(futures, on_result)

    def _map_forked(self, fn, jobs, objects, on_result) -> None:
        global _FORKED
        _FORKED = (fn, jobs, objects)  # the workers inherit these: nothing is pickled but the results
        try:
            with ProcessPoolExecutor(min(self.workers, len(jobs)), mp_context=multiprocessing.get_context("fork"),
                                     initializer=_forked_start, initargs=(os.getpid(),)) as pool:
                _collect({pool.submit(_forked_job, k): job for k, job in enumerate(jobs)}, on_result)
        finally:
            _FORKED = None

    def close(self) -> None:
        pass

    @property
    def parallelism(self) -> int:
        return self.workers if self.threads or self.processes else 1


_FORKED: tuple | None = None  # (fn, jobs, objects) of the forked map under way


def _forked_start(parent: int) -> None:
    """A forked worker: one thread of its own (`backends.numpy.query_threads`); the parent's
    host thread pool did not survive the fork. It ends with its parent: the workers of a killed
    `relicgpu assemble` waited on their job queue for good, each holding the prepared fragments."""
    from ..backends import _prep

    os.environ["OMP_NUM_THREADS"] = "1"
    _prep._POOL = None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG (Linux: the only system that forks here)
    except (OSError, AttributeError):
        return
    if os.getppid() != parent:  # the parent died before the signal was asked for
        os._exit(1)


def _forked_job(k: int):
    fn, jobs, objects = _FORKED
    return fn(jobs[k].payload, *[objects[n] for n in jobs[k].needs])


def _collect(futures: dict, on_result: Callable[[Job, Any], None]) -> None:
    """Hand each result back as it comes; on an error cancel what has not started, then raise."""
    try:
        for fut in as_completed(futures):
            on_result(futures[fut], fut.result())
    except BaseException:
        for fut in futures:
            fut.cancel()
        raise


class RayEngine:
    name = "ray"

    def __init__(self, workers: int | None = None, address: str | None = None, gpus_per_task: float | None = None,
                 needs_gpu: bool = True):
        try:
            import ray
        except ImportError as exc:  # ray is an optional dependency
            raise RuntimeError(f"the ray engine needs the 'ray' package ({exc}): pip install 'relicgpu[distributed]'") from None
        if gpus_per_task is not None and not 0.0 <= float(gpus_per_task):
            raise ValueError(f"gpus_per_task must not be negative, got {gpus_per_task}")
        self._ray = ray
        self._started = False
        if not ray.is_initialized():
            if address:
                ray.init(address=address, log_to_driver=False, configure_logging=False)
            else:
                ray.init(num_cpus=int(workers or os.cpu_count() or 1), include_dashboard=False,
                         log_to_driver=False, configure_logging=False)
            self._started = True
        resources = ray.cluster_resources()
        self.gpus = int(resources.get("GPU", 0))
        self.cpus = int(resources.get("CPU", 1))
        # One GPU per task where the cluster has GPUs; a fraction lets several tasks share one
        # (the pair work is mostly host code around short kernels).
        self.gpus_per_task = task_gpus(self.gpus, gpus_per_task, needs_gpu)
        if self.gpus_per_task > 1 and self.gpus_per_task != int(self.gpus_per_task) or self.gpus_per_task > self.gpus:
            self.close()  # a task asking for more than a node can give would wait forever
            raise ValueError(f"gpus_per_task must be a fraction or a whole number up to {self.gpus}, got {gpus_per_task}")

    @property
    def parallelism(self) -> int:
        if self.gpus_per_task > 0:
            return max(1, min(self.cpus, int(self.gpus / self.gpus_per_task)))
        return max(1, self.cpus)

    def map(self, fn: Callable, jobs: list[Job], objects: dict, on_result: Callable[[Job, Any], None]) -> None:
        ray = self._ray
        if not jobs:
            return
        needed = sorted({k for job in jobs for k in job.needs}, key=repr)
        refs = {k: ray.put(objects[k]) for k in needed}
        task = ray.remote(fn).options(num_cpus=1, num_gpus=self.gpus_per_task, max_retries=MAX_RETRIES,
                                      retry_exceptions=False)
        pending = {task.remote(job.payload, *[refs[k] for k in job.needs]): job for job in jobs}
        try:
            while pending:
                done, _ = ray.wait(list(pending), num_returns=1)
                for ref in done:
                    job = pending.pop(ref)
                    on_result(job, ray.get(ref))
        except BaseException:
            for ref in pending:
                ray.cancel(ref, force=True)
            raise
        finally:
            del refs

    def close(self) -> None:
        if self._started and self._ray.is_initialized():
            self._ray.shutdown()
            self._started = False
