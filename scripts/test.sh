#!/usr/bin/env bash
# Set up the environment (if needed) and run the test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_env.sh test
# small torch ops on 2 cores slow down ~25x when OpenMP threads spin-wait under load
export OMP_WAIT_POLICY="${OMP_WAIT_POLICY:-PASSIVE}"
exec .venv/bin/python -m pytest -q tests "$@"
