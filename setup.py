"""Build hook: what pyproject.toml cannot say.

- `kernels/` stays at the top of the repository and ships as `relicgpu.kernels`
  through a package-dir mapping (an editable install maps it the same way).
- A wheel carries the viewer's page: `viewer/`'s own files and the few three.js
  modules the page imports, copied from `viewer/node_modules/three` (installed by
  `npm ci` first when missing) into `relicgpu/viewer/page/`, where
  `relicgpu.viewer.page.viewer_dir` looks first. Editable installs copy nothing:
  they serve `viewer/` itself.
"""
from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

from setuptools import find_packages, setup
from setuptools.command.build_py import build_py

ROOT = Path(__file__).resolve().parent
PAGE = ROOT / "viewer"
PAGE_FILES = ("index.html", "*.js", "*.css")
# Relative and bare ('three', 'three/addons/...') module specifiers of ES-module sources.
IMPORT_RE = re.compile(r"""(?:^|[\s;}])(?:import|export)\b[^'"]*?\bfrom\s*['"]([^'"]+)['"]|"""
                       r"""(?:^|[\s;}])import\s*['"]([^'"]+)['"]""", re.M)


def _imports(path: Path) -> list[str]:
    return [a or b for a, b in IMPORT_RE.findall(path.read_text(encoding="utf-8"))]


def three_files(page: Path) -> list[str]:
    """Paths inside node_modules/three that the page needs: the import map's two roots
    followed through every module's imports (three.module.js -> three.core.js, addons)."""
    three = page / "node_modules" / "three"
    todo = ["build/three.module.js"]
    for js in sorted(page.glob("*.js")):
        todo += ["examples/jsm/" + s[len("three/addons/"):] for s in _imports(js) if s.startswith("three/addons/")]
    seen: set[str] = set()
    while todo:
        rel = todo.pop()
        if rel in seen:
            continue
        if not (three / rel).is_file():
            raise SystemExit(f"building the viewer: {three / rel} is missing (the page imports it)")
        seen.add(rel)
        for spec in _imports(three / rel):
            if spec.startswith("."):
                target = (Path(rel).parent / spec).as_posix()
                parts: list[str] = []
                for p in target.split("/"):
                    if p == "..":
                        parts.pop()
                    elif p != ".":
                        parts.append(p)
                todo.append("/".join(parts))
            elif spec.startswith("three/addons/"):
                todo.append("examples/jsm/" + spec[len("three/addons/"):])
            elif spec == "three":
                todo.append("build/three.module.js")
    return sorted(seen) + ["LICENSE", "package.json"]


def ensure_three(page: Path) -> None:
    """Install three.js with npm (from viewer/package-lock.json) when it is not there."""
    if (page / "node_modules" / "three" / "build" / "three.module.js").is_file():
        return
    npm = shutil.which("npm")
    if npm is None:
        raise SystemExit("building the viewer: three.js is not in viewer/node_modules and npm is not "
                         "installed; install Node.js/npm or run `npm ci` in viewer/ first")
    subprocess.run([npm, "ci", "--no-audit", "--no-fund"], cwd=page, check=True)


class BuildPyWithPage(build_py):
    """build_py, then the viewer page (with its three.js) into relicgpu/viewer/page/."""

    def run(self):
        super().run()
        if getattr(self, "editable_mode", False):
            return
        ensure_three(PAGE)
        dest = Path(self.build_lib) / "relicgpu" / "viewer" / "page"
        if dest.exists():
            shutil.rmtree(dest)
        dest.mkdir(parents=True)
        for pattern in PAGE_FILES:
            for f in PAGE.glob(pattern):
                shutil.copy2(f, dest / f.name)
        three = PAGE / "node_modules" / "three"
        version = json.loads((three / "package.json").read_text(encoding="utf-8")).get("version")
        for rel in three_files(PAGE):
            (dest / "node_modules" / "three" / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(three / rel, dest / "node_modules" / "three" / rel)
        print(f"viewer page with three.js {version} -> {dest}")


setup(
    packages=find_packages(include=["relicgpu*"]) + [
        "relicgpu.data", "relicgpu.kernels", "relicgpu.kernels.warp", "relicgpu.kernels.opencl"],
    package_dir={"relicgpu.kernels": "kernels"},
    cmdclass={"build_py": BuildPyWithPage},
)
