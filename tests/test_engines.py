"""Engines: local (sequential / threads / forked processes, one assembly alike) and Ray (same
assembly as local; a worker killed mid-run is retried and nothing is lost). One local Ray session
is shared by the module."""
import os
import signal
import sys
import threading
import time
from pathlib import Path

import pytest

from relicgpu import synth
from relicgpu.heap.assembly import assemble
from relicgpu.heap.engines import Job, LocalEngine, make_engine
from relicgpu.io.load import load_directory


def _square(payload, *shared):
    return payload * payload + sum(shared)


def _square_where(payload, *shared):
    return _square(payload, *shared), os.getpid()


def _fail_on_three(payload, *shared):
    if payload == 3:
        raise ValueError("job 3 failed")
    return payload


forks = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the local engine forks on Linux only")


def test_local_engine_hands_back_every_result_sequential_and_threaded():
    jobs = [Job(i, (i % 2,)) for i in range(7)]
    objects = {0: 10, 1: 100}
    for engine in (LocalEngine(1), LocalEngine(3, threads=True)):
        got = {}
        engine.map(_square, jobs, objects, lambda job, r: got.__setitem__(job.payload, r))
        assert got == {i: i * i + objects[i % 2] for i in range(7)}


@forks
def test_local_engine_forks_workers_that_see_the_shared_objects():
    jobs = [Job(i, (i % 2,)) for i in range(7)]
    objects = {0: 10, 1: 100}
    engine = LocalEngine(3, processes=True)
    assert engine.processes and engine.parallelism == 3
    got = {}
    engine.map(_square_where, jobs, objects, lambda job, r: got.__setitem__(job.payload, r))
    assert {i: r for i, (r, _) in got.items()} == {i: i * i + objects[i % 2] for i in range(7)}
    assert os.getpid() not in {pid for _, pid in got.values()}
    # one thread each: a process per core, not a kd-tree's threads per process too
    assert not LocalEngine(1, processes=True).processes
    assert make_engine("local", 2, backend=sys.modules["relicgpu.backends.numpy"]).processes


@forks
def test_a_forked_job_that_fails_stops_the_map_with_its_error():
    with pytest.raises(ValueError, match="job 3 failed"):
        LocalEngine(2, processes=True).map(_fail_on_three, [Job(i) for i in range(6)], {}, lambda job, r: None)


def test_unknown_engine_is_refused():
    with pytest.raises(ValueError, match="unknown engine"):
        make_engine("dask")


@pytest.fixture(scope="module")
def ray_session():
    ray = pytest.importorskip("ray")
    started = not ray.is_initialized()
    if started:
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False)
    # this test file is not importable on the workers: ship its functions by value
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    yield ray
    if started:
        ray.shutdown()


@pytest.fixture(scope="module")
def synth_fragments(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth")
    synth.write(synth.generate(shape="slab", pieces=4, seed=3, faces=1000, progress=False), out)
    return load_directory(out / "fragments")


@pytest.fixture(scope="module")
def local_doc(synth_fragments):
    return _comparable(assemble(synth_fragments, backend="numpy", progress=False).to_dict())


@forks
def test_forked_assembly_equals_one_job_after_the_other(synth_fragments):
    one, forked = (_comparable(assemble(synth_fragments, backend="numpy", workers=w, progress=False).to_dict())
                   for w in (1, 2))
    assert one == forked


def _comparable(doc):
    return {k: v for k, v in doc.items() if k not in ("timings", "engine")}


def test_ray_engine_map(ray_session):
    engine = make_engine("ray")
    assert engine.cpus == 2
    got = {}
    engine.map(_square, [Job(i, (0,)) for i in range(5)], {0: 1}, lambda job, r: got.__setitem__(job.payload, r))
    engine.close()  # does not shut down a session it did not start
    assert ray_session.is_initialized()
    assert got == {i: i * i + 1 for i in range(5)}


def test_ray_assembly_equals_local(ray_session, synth_fragments, local_doc):
    result = assemble(synth_fragments, backend="numpy", engine="ray", progress=False)
    assert result.engine == "ray"
    assert _comparable(result.to_dict()) == local_doc


def _parent(pid: int) -> int:
    return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])


def _ray_task_pids(name: str) -> list[int]:
    """Workers of this process's own Ray (worker -> raylet -> this driver) whose title is
    ray::<name>, i.e. running that task. Other people's Ray runs on the machine are left alone."""
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            cmd = (entry / "cmdline").read_bytes().split(b"\0")[0].decode(errors="replace")
            if cmd.startswith(f"ray::{name}") and _parent(_parent(int(entry.name))) == os.getpid():
                pids.append(int(entry.name))
        except (OSError, ValueError, IndexError):
            continue
    return pids


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="finds Ray workers through /proc")
def test_ray_worker_killed_mid_run_is_retried_and_nothing_is_lost(ray_session, synth_fragments, local_doc):
    killed = []
    stop = threading.Event()

    def killer():
        while not stop.is_set():
            pids = _ray_task_pids("_match_job")
            if pids:
                os.kill(pids[0], signal.SIGKILL)
                killed.append(pids[0])
                return
            time.sleep(0.005)

    watcher = threading.Thread(target=killer, daemon=True)
    watcher.start()
    try:
        result = assemble(synth_fragments, backend="numpy", engine="ray", progress=False)
    finally:
        stop.set()
        watcher.join(5)
    assert killed, "no Ray worker was seen running a match task"
    assert _comparable(result.to_dict()) == local_doc


def test_ray_tasks_ask_for_a_gpu_only_for_a_gpu_backend():
    from relicgpu.backends import get_backend
    from relicgpu.heap.engines import on_gpu, task_gpus

    assert not on_gpu(get_backend("numpy"))
    assert task_gpus(1, None, needs_gpu=False) == 0.0  # numpy on a GPU host: all CPUs work at once
    assert task_gpus(1, 0.25, needs_gpu=False) == 0.0
    assert task_gpus(1, None, needs_gpu=True) == 1.0
    assert task_gpus(2, 0.0625, needs_gpu=True) == 0.0625
    assert task_gpus(0, 1.0, needs_gpu=True) == 0.0  # no GPU in the cluster
