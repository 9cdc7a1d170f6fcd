#!/usr/bin/env bash
# Install everything from nothing (scripts/setup.sh) and run the demo: a synthetic
# broken vase, assembled, shown in the browser viewer.
set -euo pipefail
cd "$(dirname "$0")/.."
RELICGPU_SKIP_BROWSER=1 bash scripts/setup.sh
exec .venv/bin/relicgpu demo "$@"
