#!/usr/bin/env bash
# Create (or reuse) .venv with edygs_ns installed editable, plus the system packages it needs.
# Usage: bash scripts/setup_env.sh [test]
set -euo pipefail
cd "$(dirname "$0")/.."
if [ "$(id -u)" = 0 ]; then SUDO=""; else SUDO="sudo"; fi
apt_install() {  # apt_install PACKAGE...: Debian packages, quietly
  $SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "$@" >/dev/null
}
if ! command -v ffmpeg >/dev/null 2>&1; then
  echo "[setup] installing ffmpeg (ns-render needs it)"
  apt_install ffmpeg
fi
if [ "${1:-}" = "test" ] && ! command -v chromium >/dev/null 2>&1; then
  echo "[setup] installing chromium (the viewer test drives ns-viewer in a headless browser)"
  apt_install chromium || echo "[setup] chromium could not be installed: the browser test will be skipped"
fi
if [ ! -x .venv/bin/python ]; then
  echo "[setup] creating .venv"
  python3 -m venv .venv
fi
extra=""
if [ "${1:-}" = "test" ]; then extra="[test]"; fi
stamp=".venv/.edygs-installed${extra}"
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  echo "[setup] installing edygs_ns${extra} and its dependencies (first time: several minutes)"
  start=$(date +%s)
  .venv/bin/python -m pip install -q --upgrade pip >/dev/null
  .venv/bin/python -m pip install -q -e ".${extra}"
  echo "[setup] install took $(( $(date +%s) - start )) s"
  touch "$stamp"
fi
# CUDA: torch derives CUDA_HOME from the folder above nvcc, wrong where nvcc is a link or wrapper
# (/usr/local/bin/nvcc -> /usr/local); gsplat's build then misses cuda_runtime.h. edygs sets
# CUDA_HOME itself before gsplat builds; the venv's activate script exports it for other tools.
.venv/bin/python -m edygs_ns.cuda_setup || true
cuda_home="$(.venv/bin/python -m edygs_ns.cuda_setup --cuda-home 2>/dev/null || true)"
if [ -n "$cuda_home" ] && ! grep -q "edygs: CUDA_HOME" .venv/bin/activate; then
  printf '\nexport CUDA_HOME="${CUDA_HOME:-%s}"  # edygs: CUDA_HOME (scripts/setup_env.sh)\n' "$cuda_home" >> .venv/bin/activate
fi
