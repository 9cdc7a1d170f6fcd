#!/usr/bin/env bash
# Install everything from nothing (scripts/setup.sh) and run the whole test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
# the CPU backends are installed by setup.sh on every machine: their tests must run, not skip
export RELICGPU_REQUIRE_BACKENDS="${RELICGPU_REQUIRE_BACKENDS-warp-cpu,opencl}"
exec .venv/bin/python -m pytest -q -p no:cacheprovider "$@"
