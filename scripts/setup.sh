#!/usr/bin/env bash
# Set up a fresh machine for relicgpu: a virtual environment with every extra, the
# viewer's three.js from npm, and (unless RELICGPU_SKIP_BROWSER=1) Debian's chromium
# for the browser test. Idempotent: steps already done are skipped.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
.venv/bin/python -m pip install -q --upgrade pip
# torch is pinned to 2.13.0 in the `train` extra: the CPU build on this machine's disk.
.venv/bin/python -m pip install -q -e ".[dev]"
if [ "${RELICGPU_SKIP_BROWSER:-0}" = 1 ]; then
  # the demo needs only three.js for the page
  if [ ! -f viewer/node_modules/three/build/three.module.js ]; then
    (cd viewer && npm ci --no-audit --no-fund --silent)
  fi
else
  bash scripts/install_browser.sh
fi
