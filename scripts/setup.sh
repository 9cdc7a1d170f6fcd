#!/usr/bin/env bash
# Set up a fresh machine for relicgpu: a virtual environment with every extra, the
# viewer's three.js from npm, and Debian's chromium for the browser test.
# Idempotent: steps already done are skipped.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
.venv/bin/python -m pip install -q --upgrade pip
# torch is pinned to 2.13.0 in the `train` extra: the CPU build on this machine's disk.
.venv/bin/python -m pip install -q -e ".[dev]"
if command -v npm >/dev/null 2>&1 && [ -f viewer/package.json ]; then
  (cd viewer && npm ci --no-audit --no-fund --silent)
fi
if [ "${RELICGPU_SKIP_BROWSER:-0}" != 1 ] && ! command -v chromium >/dev/null 2>&1; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null) \
      || echo "setup: could not install chromium; the browser test will be skipped" >&2
  else
    echo "setup: chromium missing (install Debian's chromium for the browser test)" >&2
  fi
fi
