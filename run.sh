#!/usr/bin/env bash
# Set up whatever is missing, then run the pipeline (default profile). Extra args go to `pipeline run`.
set -euo pipefail
cd "$(dirname "$0")"
bash scripts/setup.sh
exec .venv/bin/python -m pipeline run "$@"
