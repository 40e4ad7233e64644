#!/usr/bin/env bash
# What a lent GPU machine needs for scripts/gpu_check.sh, made on the CPU machine as one archive the
# device tool can carry (the working tree and carried paths together: 64 MiB), and unpacked there.
#   make  wheels of the packages the device image lacks (nerfstudio, tyro, pycolmap, ...; the image has
#         torch, numpy, scipy, opencv, pytest), edygs_ns's entry points, and gsplat 1.4.0 with its CUDA
#         kernels compiled ahead for the device's Python, torch and GPU arch (the slow part: about
#         30-50 min on 2 cores; reused while Python, torch and arch stay the same), installed into one
#         folder and packed as OUT/site.tar.xz with OUT/bundle.json saying what it was made for.
#   use   on the device machine: unpack into /tmp/edygs_site (or $EDYGS_SITE); prints the export to eval.
# Usage:
#   bash scripts/gpu_bundle.sh make [--python 3.12] [--torch 2.11.0] [--arch 9.0] [--out .gpu]
#   eval "$(bash scripts/gpu_bundle.sh use [--out .gpu])"
# The defaults are the nvidia-h200 image's Python 3.12 and torch 2.11.0+cu130 (H200: sm_90).
set -euo pipefail
cd "$(dirname "$0")/.."
repo="$(pwd)"
mode="${1:-}"; shift || true
pyv=3.12; torchv=2.11.0; arch=9.0; out=.gpu
while [ $# -gt 0 ]; do
  case "$1" in
    --python) pyv="$2"; shift 2;; --torch) torchv="$2"; shift 2;;
    --arch) arch="$2"; shift 2;; --out) out="$2"; shift 2;;
    *) echo "gpu_bundle: unknown option $1 (see the header of scripts/gpu_bundle.sh)" >&2; exit 2;;
  esac
done

if [ "$mode" = use ]; then
  site="${EDYGS_SITE:-/tmp/edygs_site}"
  [ -f "$out/site.tar.xz" ] || { echo "gpu_bundle: $out/site.tar.xz: no bundle (run 'gpu_bundle.sh make' on the CPU machine and carry $out)" >&2; exit 1; }
  rm -rf "$site" && mkdir -p "$site" && tar -xJf "$out/site.tar.xz" -C "$site"
  have="$(python3 -c 'import sys, torch; print("%d.%d" % sys.version_info[:2], torch.__version__.split("+")[0])' 2>/dev/null || echo "no torch")"
  want="$(python3 -c 'import json, sys; b = json.load(open(sys.argv[1])); print(b["python"], b["torch"])' "$out/bundle.json")"
  [ "$have" = "$want" ] || echo "gpu_bundle: warning: bundle made for python/torch $want, this machine has $have; gsplat's kernels will not load" >&2
  echo "export PYTHONPATH=$repo:$site${PYTHONPATH:+:$PYTHONPATH}"
  exit 0
fi
[ "$mode" = make ] || { echo "usage: gpu_bundle.sh make|use [options] (see the header)" >&2; exit 2; }

work="${TMPDIR:-/tmp}/edygs_gpu_bundle"
mkdir -p "$work/wheels" "$out"
host=.venv/bin/python
[ -x "$host" ] || { echo "gpu_bundle: .venv missing: run 'bash scripts/setup_env.sh test' first" >&2; exit 1; }
# 1. a Python of the device's version with its torch, to compile gsplat against
if [ ! -x "$work/py/bin/python" ]; then
  base="$(command -v "python$pyv" 2>/dev/null || true)"
  if [ -z "$base" ] || ! "$base" --version >/dev/null 2>&1; then
    ver="$(pyenv versions --bare 2>/dev/null | grep "^$pyv" | tail -1 || true)"
    [ -n "$ver" ] || { echo "gpu_bundle: no Python $pyv here (install one, e.g. pyenv install $pyv)" >&2; exit 1; }
    base="$(pyenv root)/versions/$ver/bin/python"
  fi
  "$base" -m venv "$work/py"
fi
py="$work/py/bin/python"
if ! "$py" -c "import torch, sys; sys.exit(torch.__version__.split('+')[0] != '$torchv')" 2>/dev/null; then
  echo "[gpu_bundle] installing torch $torchv for Python $pyv (build only)"
  "$py" -m pip install -q "torch==$torchv" numpy ninja "setuptools<82" wheel
fi
torch_full="$("$py" -c 'import torch; print(torch.__version__)')"
# 2. gsplat with compiled kernels (setup.py's gsplat.csrc); the sdist lacks glm, the wheel has it
built="$work/gsplat-1.4.0-py$pyv-torch$torch_full-sm$arch"  # the wheel, under its own name
if ! ls "$built"/gsplat-1.4.0-*.whl >/dev/null 2>&1; then
  rm -rf "$work/gsplat" && mkdir -p "$work/gsplat"
  "$py" -m pip download -q --no-deps --no-binary=:all: -d "$work/gsplat" gsplat==1.4.0
  "$py" -m pip download -q --no-deps --only-binary=:all: -d "$work/gsplat" gsplat==1.4.0
  tar -xzf "$work"/gsplat/gsplat-1.4.0.tar.gz -C "$work/gsplat"
  (cd "$work/gsplat" && unzip -q gsplat-1.4.0-py3-none-any.whl 'gsplat/cuda/csrc/third_party/*' -d wheel)
  cp -r "$work/gsplat/wheel/gsplat/cuda/csrc/third_party" "$work/gsplat/gsplat-1.4.0/gsplat/cuda/csrc/"
  cuda_home="$($host -m edygs_ns.cuda_setup --cuda-home)"
  echo "[gpu_bundle] compiling gsplat's kernels for sm_$arch against torch $torch_full (CUDA_HOME=$cuda_home; about 30-50 min on 2 cores)"
  (cd "$work/gsplat/gsplat-1.4.0" && CUDA_HOME="$cuda_home" TORCH_CUDA_ARCH_LIST="$arch" MAX_JOBS="${MAX_JOBS:-2}" \
     PATH="$work/py/bin:$PATH" "$py" -m pip wheel -q . --no-build-isolation --no-deps -w "$work/gsplat/dist")
  rm -rf "$built.part" && mkdir -p "$built.part" && cp "$work"/gsplat/dist/gsplat-1.4.0-*.whl "$built.part/" && mv "$built.part" "$built"
fi
# 3. wheels of what the device image lacks, at the versions this venv runs (fpsample: the newest
#    with a wheel for that Python; nerfstudio only imports it)
pkgs="appdirs defusedxml dill docstring_parser mediapy msgspec multiprocess nerfacc nerfstudio pathos ppft pycolmap
pyquaternion pytorch-msssim rawpy splines tensorly traitlets typeguard tyro viser websockets PySocks ipython"
plat=(--python-version "$pyv" --implementation cp --only-binary=:all: --no-deps)
for p in manylinux_2_17_x86_64 manylinux2014_x86_64 manylinux_2_24_x86_64 manylinux_2_27_x86_64 manylinux_2_28_x86_64 \
         manylinux_2_31_x86_64 manylinux_2_34_x86_64 manylinux_2_35_x86_64 manylinux1_x86_64 manylinux_2_5_x86_64; do
  plat+=(--platform "$p")
done
rm -rf "$work/wheels" && mkdir -p "$work/wheels"
pins="$($host -c 'import importlib.metadata as m, sys; print(" ".join(f"{n}=={m.version(n)}" for n in sys.argv[1:]))' $pkgs)"
"$host" -m pip download -q "${plat[@]}" -d "$work/wheels" $pins fpsample
# 4. one folder: the wheels, gsplat, edygs_ns's dist-info (entry points; the code is the working tree)
rm -rf "$work/site" "$work/edygs" && mkdir -p "$work/site"
"$py" -m pip install -q --no-deps --no-compile --target "$work/site" "$work"/wheels/*.whl "$built"/gsplat-1.4.0-*.whl
"$host" -m pip wheel -q --no-deps --no-build-isolation -w "$work/edygs" .
(cd "$work/site" && unzip -q -o "$work"/edygs/edygs_ns-*.whl 'edygs_ns-*.dist-info/*')
"$py" -c "import json, sys; json.dump({'python': '$pyv', 'torch': '${torch_full%%+*}', 'torch_full': '$torch_full', 'arch': '$arch',
  'wheels': sorted(__import__('os').listdir('$work/wheels')) + sorted(__import__('os').listdir('$built'))}, open('$out/bundle.json', 'w'), indent=1)"
echo "[gpu_bundle] packing $out/site.tar.xz"
tar -C "$work/site" -cf - . | xz -9 -T0 > "$out/site.tar.xz.part" && mv "$out/site.tar.xz.part" "$out/site.tar.xz"
echo "[gpu_bundle] done: $(du -h "$out/site.tar.xz" | cut -f1) in $out/site.tar.xz (carry '$out'; on the device: eval \"\$(bash scripts/gpu_bundle.sh use)\")"
