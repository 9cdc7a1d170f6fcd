#!/usr/bin/env bash
# What the viewer and its browser test need beyond Python, on a fresh Debian machine:
# three.js in viewer/node_modules (from viewer/package-lock.json; npm from apt when missing)
# and Debian's chromium at /usr/bin/chromium (driven by Playwright with executable_path,
# so no `playwright install` download). Idempotent; apt-get needs root.
set -euo pipefail
cd "$(dirname "$0")/.."

need_apt=()
command -v npm >/dev/null 2>&1 || need_apt+=(nodejs npm)
[ -x /usr/bin/chromium ] || need_apt+=(chromium)
if [ ${#need_apt[@]} -gt 0 ]; then
  if [ "$(id -u)" != 0 ] || ! command -v apt-get >/dev/null 2>&1; then
    echo "install_browser: please install ${need_apt[*]} (needs root and apt-get)" >&2
    exit 1
  fi
  apt-get update -qq
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${need_apt[@]}" >/dev/null
fi

if [ ! -f viewer/node_modules/three/build/three.module.js ]; then
  (cd viewer && npm ci --no-audit --no-fund --silent)
fi
echo "install_browser: $(/usr/bin/chromium --version 2>/dev/null | head -1); three $(node -p 'require("./viewer/node_modules/three/package.json").version')"
