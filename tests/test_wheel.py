"""The built wheel works away from the source tree: it carries kernels/ (as
relicgpu.kernels) and the viewer page with its three.js, and `relicgpu demo`
from a fresh venv serves a working page.

Offline and without downloading dependencies: the wheel is built with
--no-build-isolation from a copy of the package's sources (so nothing is
written into the checkout), installed with --no-deps into a venv made here, and
that venv sees the dev venv's third-party packages through a .pth line (a plain
path: the dev venv's own .pth files, among them the editable relicgpu's finder,
are not run).
"""
from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import sysconfig
import threading
import urllib.request
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
THREE = ROOT / "viewer" / "node_modules" / "three"

pytest.importorskip("flask")
pytest.importorskip("waitress")
if not (THREE / "build" / "three.module.js").is_file():
    pytest.skip("three.js is not in viewer/node_modules (scripts/setup.sh installs it); building the "
                "wheel would run npm ci, which needs the network", allow_module_level=True)


def _run(cmd, **kw) -> subprocess.CompletedProcess:
    r = subprocess.run([str(c) for c in cmd], capture_output=True, text=True, timeout=300, **kw)
    assert r.returncode == 0, f"{cmd}\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    return r


def _get(url: str) -> tuple[int, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=30) as resp:
            return resp.status, resp.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read()


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> Path:
    """A fresh venv with the wheel built from this checkout installed; returns its python."""
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"
    src.mkdir()
    for name in ("pyproject.toml", "setup.py", "MANIFEST.in", "README.md"):
        shutil.copy2(ROOT / name, src / name)
    skip = shutil.ignore_patterns("__pycache__", "*.pyc", "node_modules")
    for name in ("relicgpu", "kernels", "viewer"):
        shutil.copytree(ROOT / name, src / name, ignore=skip)
    assert not (src / "relicgpu" / "kernels").exists(), "relicgpu/kernels must not exist: kernels/ is mapped"
    (src / "viewer" / "node_modules").mkdir()
    (src / "viewer" / "node_modules" / "three").symlink_to(THREE)

    _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index",
          "-q", "-w", tmp / "dist", src])
    wheels = list((tmp / "dist").glob("relicgpu-*.whl"))
    assert len(wheels) == 1, wheels

    venv = tmp / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", venv])
    py = venv / "bin" / "python"
    _run([sys.executable, "-m", "pip", "--python", py, "install", "--no-deps", "--no-index", "-q", wheels[0]])
    purelib = _run([py, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"]).stdout.strip()
    dev = {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]}
    (Path(purelib) / "relicgpu_test_dev_site.pth").write_text("".join(p + "\n" for p in sorted(dev)))
    return py


def _env() -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "RELICGPU_VIEWER_DIR")}
    env["PYTHONNOUSERSITE"] = "1"
    return env


def test_installed_wheel_carries_kernels_and_page(installed, tmp_path):
    venv = installed.parents[1]
    probe = """
import importlib.resources, json, relicgpu, relicgpu.kernels.warp.normals as wn
from relicgpu.viewer.app import viewer_dir
cl = importlib.resources.files("relicgpu.kernels.opencl")
print(json.dumps({"relicgpu": relicgpu.__file__, "warp": wn.__file__, "page": str(viewer_dir()),
                  "cl": sorted(p.name for p in cl.iterdir() if p.name.endswith(".cl"))}))
"""
    out = json.loads(_run([installed, "-c", probe], cwd=tmp_path, env=_env()).stdout)
    for key in ("relicgpu", "warp", "page"):
        assert Path(out[key]).resolve().is_relative_to(venv.resolve()), (key, out[key])
    assert out["cl"] == sorted(p.name for p in (ROOT / "kernels" / "opencl").glob("*.cl"))
    page = Path(out["page"])
    assert (page / "index.html").is_file() and (page / "node_modules" / "three" / "LICENSE").is_file()


def test_demo_from_the_installed_wheel_serves_the_page(installed, tmp_path):
    run_dir = tmp_path / "elsewhere"
    run_dir.mkdir()
    cmd = [installed.parent / "relicgpu", "demo", "--no-browser", "--workspace", "ws",
           "--shape", "slab", "--pieces", "3", "--port", "0"]
    proc = subprocess.Popen([str(c) for c in cmd], cwd=run_dir, env=_env(), text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    watchdog = threading.Timer(240, proc.kill)
    watchdog.start()
    lines, url = [], None
    try:
        for line in proc.stdout:
            lines.append(line)
            m = re.match(r"open (http://\S+)/#case=(\S+)", line)
            if m:
                url, case = m.group(1), m.group(2)
                break
        assert url is not None, "the demo never printed its address:\n" + "".join(lines[-40:])

        status, body = _get(url + "/")
        assert status == 200, (status, body[:300])
        page = body.decode()
        imports = json.loads(page.split('<script type="importmap">')[1].split("</script>")[0])["imports"]
        targets = [u + "controls/OrbitControls.js" if u.endswith("/") else u for u in imports.values()]
        targets += ["/vendor/three/build/three.core.js", "/static/main.js", "/static/scene.js",
                    "/static/api.js", "/static/style.css"]
        for t in targets:
            status, body = _get(url + t)
            assert status == 200 and body, (t, status)
        status, body = _get(f"{url}/api/cases/{case}/fragments")
        assert status == 200, (status, body[:300])
        frags = json.loads(body)
        assert frags["assembled"] and len(frags["fragments"]) == 3, frags
    finally:
        watchdog.cancel()
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        proc.stdout.close()
    assert (run_dir / "ws" / case / "assembly" / "assembly.json").is_file()
