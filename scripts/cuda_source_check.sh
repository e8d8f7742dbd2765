#!/usr/bin/env bash
# Before a GPU session, on any x86-64 Linux machine (no GPU, no CUDA install): compiles every
# configuration of this project's own CUDA kernels for an H100 (sm_90a) as the GPU run would, with
# `sparseocc check-cuda-source --require-nvrtc`: the CUDA C++ that cubecl-cuda generates, then
# NVRTC's PTX and sm_90a binary of it. NVRTC and the CUDA headers come from NVIDIA's PyPI wheels
# (CUDA 13.0, as the binary is built for), downloaded once into a cache folder outside the
# repository (about 96 MB; SPARSEOCC_NVRTC_CACHE, default ~/.cache/sparseocc/nvrtc-13.0).
#
# Usage: scripts/cuda_source_check.sh [OUT_DIR]
# With SPARSEOCC_BIN set, checks that binary (built with `--features cuda`, e.g. the one to be
# carried to the GPU machine); otherwise builds one with cargo. OUT_DIR (default
# cuda_source_out) gets the .cu and .ptx files and cuda_source.json.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-cuda_source_out}
CACHE=${SPARSEOCC_NVRTC_CACHE:-${XDG_CACHE_HOME:-$HOME/.cache}/sparseocc/nvrtc-13.0}
CUDA_DIR="$CACHE/nvidia/cu13"
# NVRTC, the runtime headers, the headers those include (crt/) and CCCL (cuda/barrier, ...).
WHEELS=(nvidia-cuda-nvrtc==13.0.88 nvidia-cuda-runtime==13.0.96 nvidia-cuda-crt==13.0.88
  nvidia-cuda-cccl==13.0.85)

if [ ! -f "$CUDA_DIR/include/cuda_runtime.h" ] || [ ! -e "$CUDA_DIR/lib/libnvrtc.so.13" ]; then
  command -v python3 >/dev/null || { echo "error: python3 (with pip) is needed to fetch NVRTC" >&2; exit 1; }
  PIP=(python3 -m pip)
  if ! python3 -m pip --version >/dev/null 2>&1; then
    python3 -m venv "$CACHE/venv"
    PIP=("$CACHE/venv/bin/python" -m pip)
  fi
  mkdir -p "$CACHE/wheels"
  "${PIP[@]}" download --quiet --disable-pip-version-check --no-deps --only-binary=:all: \
    --dest "$CACHE/wheels" "${WHEELS[@]}"
  for w in "$CACHE"/wheels/*.whl; do
    python3 -m zipfile -e "$w" "$CACHE"
  done
fi
[ -f "$CUDA_DIR/include/cuda_runtime.h" ] || { echo "error: no CUDA headers in $CUDA_DIR/include" >&2; exit 1; }

BIN=${SPARSEOCC_BIN:-}
if [ -z "$BIN" ]; then
  CUDARC_CUDA_VERSION=${CUDARC_CUDA_VERSION:-13000} cargo build --release -p sparseocc --features cuda
  BIN=${CARGO_TARGET_DIR:-target}/release/sparseocc
fi
mkdir -p "$OUT"
CUDA_PATH="$CUDA_DIR" LD_LIBRARY_PATH="$CUDA_DIR/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}" \
  "$BIN" check-cuda-source --require-nvrtc --out "$OUT" --json "$OUT/cuda_source.json"
