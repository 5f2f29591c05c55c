#!/usr/bin/env bash
# Set up whatever is missing, then run the test suite. Extra args go to pytest.
# The suite runs in parallel processes (pytest-xdist), one per core up to 4 (TEST_WORKERS overrides;
# 0 runs it in this process), each test file whole in one process: the end-to-end file's tests share
# one toy store, built once and read in order. Pass -n 0 (or TEST_WORKERS=0) to debug with pdb.
set -euo pipefail
cd "$(dirname "$0")"
bash scripts/setup.sh
cores=$(nproc 2>/dev/null || echo 2)
workers=${TEST_WORKERS:-$(( cores < 4 ? cores : 4 ))}
exec .venv/bin/python -m pytest -n "$workers" --dist loadfile "$@"
