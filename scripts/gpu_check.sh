#!/usr/bin/env bash
# Issue 19's GPU check in one command: doctor, CUDA parity tests, a short ns-train edygs crossing
# the static->dynamic switch, an opacity reset and pruning, ns-render camera-path, edygs-eval,
# and the 400x400 x 60-frame benchmark (EDyGS + blurry baseline). Writes OUT/gpu_check.{json,md}.
# Usage: bash scripts/gpu_check.sh [--out DIR] [--device cuda|cpu] [more options: --help]
#   --device cpu is the dry mode (tiny sizes, few iterations; tests/test_gpu_check.py runs it).
# Environment: PYTHON (default .venv/bin/python, else python3). gsplat's kernels: build them
# ahead with `edygs-doctor --build-gsplat` (the check's doctor stage says whether they are there).
set -euo pipefail
cd "$(dirname "$0")/.."
py="${PYTHON:-}"
if [ -z "$py" ]; then if [ -x .venv/bin/python ]; then py=.venv/bin/python; else py=python3; fi; fi
export PYTHONUNBUFFERED=1
export OMP_WAIT_POLICY="${OMP_WAIT_POLICY:-PASSIVE}"
case " $* " in *" --device cpu "*|*" --device=cpu "*) export OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}";; esac
exec "$py" benchmarks/gpu_check.py "$@"
