#!/usr/bin/env bash
# GPU checks in one go, for a machine with an NVIDIA GPU (H100 in the reference runs):
#   1. `sparseocc check-backend`: sparse convolutions (forward and gradients), the image encoder and a
#      SparseOcc++ forward pass on CUDA against the NdArray CPU reference;
#   2. `sparseocc bench`: SparseOcc++ at the full SemanticKITTI setting (384x1280, ResNet-50, FP32,
#      batch 1) with the per-stage profile, then the three models side by side, then the memory scan.
#
# Usage: scripts/gpu_check.sh [OUT_DIR]
# With SPARSEOCC_BIN set, uses that binary (built elsewhere with `--features cuda`, e.g. on a CPU-only
# machine: CUDARC_CUDA_VERSION=13000 cargo build --release -p sparseocc --features cuda); otherwise
# builds one here with cargo.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-gpu_check_out}
FRAMES=${FRAMES:-20}
mkdir -p "$OUT"
BIN=${SPARSEOCC_BIN:-}
if [ -z "$BIN" ]; then
  CUDARC_CUDA_VERSION=${CUDARC_CUDA_VERSION:-13000} cargo build --release -p sparseocc --features cuda
  BIN=${CARGO_TARGET_DIR:-target}/release/sparseocc
fi
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv | tee "$OUT/gpu.txt"
echo "== check-backend"
"$BIN" check-backend --json "$OUT/check_backend.json" 2>&1 | tee "$OUT/check_backend.log"
echo "== SparseOcc++, SemanticKITTI setting"
"$BIN" bench --config configs/semantickitti_sparseocc_pp.toml --models sparseocc++ \
  --frames "$FRAMES" --warmup 3 --json "$OUT/bench_pp.json" 2>&1 | tee "$OUT/bench_pp.log"
echo "== three models, same input"
"$BIN" bench --config configs/semantickitti_sparseocc_pp.toml --models sparseocc++,sparseocc,dense \
  --frames 5 --warmup 2 --json "$OUT/bench_all.json" 2>&1 | tee "$OUT/bench_all.log"
if [ "${SCAN:-1}" = 1 ]; then
  echo "== memory scan"
  "$BIN" bench --config configs/semantickitti_sparseocc_pp.toml --models sparseocc++,sparseocc,dense \
    --frames 1 --warmup 1 --scan "$OUT/memory_scan" 2>&1 | tail -3 | tee "$OUT/scan.log"
fi
echo "results in $OUT"
