"""The self-check before trust: it passes every working backend, catches a wrong answer in
each kernel family, and keeps a refused backend out of use (issue 14)."""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

import relicgpu.backends as backends
from relicgpu.backends import BackendError, BackendRefused, selfcheck
from relicgpu.backends import numpy as ref


def test_every_backend_passes_its_self_check(backend):
    assert selfcheck.run(backend) == {family: None for family in selfcheck.FAMILIES}


class _Faulty:
    """The NumPy reference with one family's answer slightly wrong."""

    name = "numpy-faulty"  # the mosaic functions take it for the reference
    real = np.float64

    def __init__(self, family: str):
        self.family = family

    def __getattr__(self, attr):
        return getattr(ref, attr)

    def face_normals(self, v, f):
        n, a = ref.face_normals(v, f)
        if self.family == "normals":
            n = n.copy()
            n[len(n) // 2] = n[len(n) // 2][[1, 0, 2]]
        return n, a

    def contour_features(self, pts, k, stride):
        out = ref.contour_features(pts, k, stride)
        return out * (1 + 1e-6) if self.family == "curvature" else out

    def flag_matrix(self, a, b, eps):
        out = ref.flag_matrix(a, b, eps)
        if self.family == "flags":
            out = out.copy()
            out[-1, -1] ^= True
        return out

    def lcs_lengths(self, *args):
        out = ref.lcs_lengths(*args)
        if self.family == "lcs":  # the PoCL fault: only pairs past one 64-column word go wrong
            long = np.diff(args[1])[np.asarray(args[4])[:, 0]] > 64
            out = np.where(long, out - 1, out).astype(np.int32)
        return out

    def nearest_neighbors(self, s, t):
        return self.nearest_index(t).query(s)

    def nearest_index(self, t):
        index = ref.nearest_index(t)
        if self.family != "nearest":
            return index
        target = np.asarray(t)

        class Second:
            def query(self, s, within=None):  # the second-nearest point for one source point, its true distance
                idx, d = index.query(s)
                idx, d = idx.copy(), d.copy()
                dists = np.linalg.norm(target - np.asarray(s)[-2], axis=1)
                idx[-2] = np.argsort(dists)[-1]
                d[-2] = dists[idx[-2]]
                return idx, d
        return Second()

    def cross_covariance(self, s, t, w=None):
        cs, ct, h, wsum = ref.cross_covariance(s, t, w)
        return (cs, ct, h + 1e-6 * np.abs(h).max(), wsum) if self.family == "covariance" else (cs, ct, h, wsum)

    def ppf_votes(self, *args):
        if self.family != "ppf":
            return ref.ppf_votes(*args)
        rows = ref.ppf_vote_rows(*args)  # ties to the last largest cell instead of the first
        last = rows.shape[1] - 1 - rows[:, ::-1].argmax(axis=1)
        return last, rows.max(axis=1).astype(np.float64)


@pytest.mark.parametrize("family", [f for f in selfcheck.FAMILIES if f != "mosaic"])
def test_self_check_catches_a_fault_in_each_family(family):
    result = selfcheck.run(_Faulty(family))
    assert result[family] is not None
    assert all(why is None for f, why in result.items() if f not in (family, "mosaic"))


def test_self_check_counts_a_crash_as_a_disagreement():
    class Crashing(_Faulty):
        def lcs_lengths(self, *args):
            raise RuntimeError("clBuildProgram failed")
    assert "clBuildProgram failed" in selfcheck.check_family(Crashing("none"), "lcs")


def test_refused_backend_is_never_used(monkeypatch, capsys):
    """A backend whose LCS is wrong: one warning line naming it and the family, `auto`
    picks another, and asking for it by name is a clear error."""
    monkeypatch.setattr(backends, "_loaded", {})
    monkeypatch.setattr(backends, "_checks", {})
    real_load = backends._load
    monkeypatch.setattr(backends, "_load", lambda name: _Faulty("lcs") if name == "warp-cpu" else real_load(name))
    monkeypatch.setattr(backends, "candidate_backends", lambda: ["numpy", "warp-cpu"])
    monkeypatch.delenv("RELICGPU_BACKEND", raising=False)
    backends.fastest_backend.cache_clear()
    try:
        with pytest.raises(BackendRefused, match="'warp-cpu' refused: its lcs kernel disagrees"):
            backends.get_backend("warp-cpu")
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "warp-cpu" in err[0] and "lcs" in err[0]
        assert backends.available_backends() == ["numpy"]
        assert backends.resolve("auto") is ref
        with pytest.raises(BackendError, match="refused"):
            backends.resolve("warp-cpu")
        assert capsys.readouterr().err == ""  # one warning per process, not per request
    finally:
        backends.fastest_backend.cache_clear()


class _SlowFarAway:
    """The NumPy reference as a grid search would be: instant LCS, nearest neighbours cheap
    for points near the target and dear for points far from it."""

    name = "numpy-grid"
    real = np.float64

    def __getattr__(self, attr):
        return getattr(ref, attr)

    def lcs_lengths(self, *args):
        from relicgpu.heap.screen import lcs_lengths_bitparallel

        return lcs_lengths_bitparallel(*args)

    def nearest_index(self, target):
        index = ref.nearest_index(target)
        outer = np.linalg.norm(np.asarray(target), axis=1).max()

        class Index:
            def query(self, source, within=None):
                far = int((np.linalg.norm(np.asarray(source), axis=1) > 1.5 * outer).sum())
                time.sleep(1e-5 * far)  # a far query sweeps most of the grid
                return index.query(source)
        return Index()


def test_auto_times_what_the_pipeline_does(monkeypatch):
    """`auto` picks by the pipeline's hot path, nearest neighbours near the surface and far
    from it: a backend slow on far queries loses to the reference, however fast its LCS."""
    monkeypatch.setattr(backends, "_loaded", {})
    monkeypatch.setattr(backends, "_checks", {})
    real_load = backends._load
    monkeypatch.setattr(backends, "_load", lambda name: _SlowFarAway() if name == "warp-cpu" else real_load(name))
    monkeypatch.setattr(backends, "candidate_backends", lambda: ["numpy", "warp-cpu"])
    monkeypatch.delenv("RELICGPU_BACKEND", raising=False)
    backends.fastest_backend.cache_clear()
    try:
        times = backends.probe_times()
        assert times["numpy"] < times["warp-cpu"], times
        assert backends.resolve("auto") is ref
    finally:
        backends.fastest_backend.cache_clear()


def test_cli_match_with_a_refused_backend_stops_clearly(tmp_path):
    """`--backend NAME` for a refused backend: exit 2 and one line saying why (the LCS
    kernel built 16 lanes wide for a CPU target where PoCL's compiler gets that wrong)."""
    code = textwrap.dedent("""
        import sys
        import relicgpu.backends as b
        from relicgpu.backends.opencl import OpenCLBackend
        from relicgpu.backends.selfcheck import check_family
        if check_family(OpenCLBackend("Portable", lcs_masks=16), "lcs") is None:
            sys.exit(77)  # this PoCL compiles the 16-wide masks right: no fault to refuse
        real = b._load
        b._load = lambda name: OpenCLBackend("Portable", lcs_masks=16) if name.startswith("opencl") else real(name)
        from relicgpu.cli import main
        sys.exit(main(["match", sys.argv[1], sys.argv[2], "-o", sys.argv[3], "--backend", "opencl:Portable"]))
    """)
    pytest.importorskip("pyopencl")
    _needs_avx2()
    import trimesh
    frags = [tmp_path / "a.stl", tmp_path / "b.stl"]
    for i, path in enumerate(frags):
        trimesh.creation.box(extents=[1, 2, 3 + i]).export(path)
    env = dict(os.environ, RELICGPU_POCL_CPU="haswell", POCL_CACHE_DIR=str(tmp_path / "pocl"))
    run = subprocess.run([sys.executable, "-c", code, str(frags[0]), str(frags[1]), str(tmp_path / "out")],
                         env=env, capture_output=True, text=True, timeout=600)
    if run.returncode == 77:
        pytest.skip("this PoCL compiles 16-wide masks right for haswell: no fault to refuse")
    assert run.returncode == 2, run.stderr
    assert "refused" in run.stderr and "lcs" in run.stderr


def _needs_avx2():
    flags = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").exists() else ""
    if " avx2" not in flags or " fma" not in flags:
        pytest.skip("this CPU cannot run code compiled for haswell")


def test_pocl_16_wide_masks_are_refused_where_wrong_and_8_wide_chosen(tmp_path):
    """The fault of issue 14, reproduced on any AVX2 machine: PoCL made to compile for
    haswell (no AVX-512) folds 16-wide compares wrongly; the self-check refuses that build
    and the backend settles on a width that agrees."""
    pytest.importorskip("pyopencl")
    _needs_avx2()
    code = textwrap.dedent("""
        import json
        from relicgpu.backends import selfcheck
        from relicgpu.backends.opencl import OpenCLBackend
        from relicgpu.backends.pocl import repair_pocl_cpu_name
        forced = OpenCLBackend("Portable", lcs_masks=16)
        chosen = OpenCLBackend("Portable")
        print(json.dumps({"cpu": repair_pocl_cpu_name(), "device": forced.device.version,
                          "forced": selfcheck.check_family(forced, "lcs"),
                          "chosen": chosen.default_options("lcs.cl"), "refused": chosen.lcs_masks_refused,
                          "chosen_check": selfcheck.run(chosen)}))
    """)
    env = dict(os.environ, RELICGPU_POCL_CPU="haswell", POCL_CACHE_DIR=str(tmp_path / "pocl"))
    run = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    import json
    out = json.loads(run.stdout.strip().splitlines()[-1])
    if out["cpu"] is None:
        pytest.skip("this PoCL is not the wheel's (a system one): its CPU target cannot be set here")
    assert out["cpu"] == "haswell" and "haswell" in out["device"]
    if out["forced"] is None:
        pytest.skip("this PoCL compiles 16-wide masks right for haswell: no fault to refuse")
    assert "values wrong" in out["forced"]
    assert "16" in out["refused"] and "-DRELIC_VECTOR_MASKS=16" not in out["chosen"]
    assert all(why is None for why in out["chosen_check"].values())


def test_auto_takes_numpy_or_a_gpu_backend_and_leaves_the_cpu_kernels_to_be_named(monkeypatch):
    """On a CPU an assembly forks a numpy worker per core: a CPU kernel that probes faster is
    still not `auto`'s pick; a GPU backend that probes faster is."""
    from types import SimpleNamespace

    kinds = {"numpy": "cpu", "warp-cpu": "cpu", "opencl:PoCL": "cpu", "warp-cuda:0": "cuda", "opencl:GPU": "gpu"}
    monkeypatch.setattr(backends, "get_backend", lambda name: SimpleNamespace(kind=kinds[name]))
    assert backends.auto_choice({"numpy": 0.03, "warp-cpu": 0.01, "opencl:PoCL": 0.02}) == "numpy"
    assert backends.auto_choice({"numpy": 0.03, "warp-cpu": 0.01, "warp-cuda:0": 0.02}) == "warp-cuda:0"
    assert backends.auto_choice({"numpy": 0.03, "opencl:GPU": 0.005, "warp-cuda:0": 0.004}) == "warp-cuda:0"
    assert backends.auto_choice({"numpy": 0.01, "opencl:GPU": 0.05}) == "numpy"
