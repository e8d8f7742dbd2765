#!/usr/bin/env bash
# GPU checks in one go, for a machine with an NVIDIA GPU (H100 in the reference runs):
#   1. `sparseocc check-backend`: sparse convolutions (forward and gradients), the image encoder and a
#      SparseOcc++ forward pass on CUDA against the NdArray CPU reference;
#   2. one traced SparseOcc++ pass at the full SemanticKITTI setting (384x1280, ResNet-50, FP32,
#      batch 1; `SPARSEOCC_TRACE=1` prints every stage and U-Net level as it finishes, so a slow
#      first pass — kernel compilation, autotuning — shows where it is), counting the kernel
#      launches per frame by kernel (`SPARSEOCC_COUNT_LAUNCHES=1`, in trace_pp.json);
#   3. `sparseocc bench` of SparseOcc++ at that setting with the per-stage profile, then the three
#      models side by side (ALL=0 skips it), then the same SparseOcc++ bench with the
#      sparse convolutions on the gather + matrix-product path (`SPARSEOCC_CUBE_CONV=gather-gemm`, the
#      peer of the default `#[cube]` kernels), the same with the DCA sampling as burn tensor ops
#      (`SPARSEOCC_CUBE_DCA=tensor-ops`, the peer of its `#[cube]` kernel; DCA=0 skips it), the same
#      with the kernel maps built on the host (`SPARSEOCC_CUBE_MAPS=host`, the peer of the
#      device-built tables; MAPS=0 skips it), the same with burn's direct image convolutions
#      (`SPARSEOCC_CUBE_CONV2D=direct`, the peer of im2col + matmul; CONV2D=0 skips it), then
#      (SCAN=1) the memory scan;
#   4. (TRAIN=0 skips) SparseOcc++ training steps at that setting (batch 1, the paper's frames per
#      GPU) on a synthetic SemanticKITTI-layout sequence: the median step time as shipped (the DCA sampling's `#[cube]` training op, the
#      image convolutions' im2col op), with the DCA sampling as tensor ops in training
#      (`SPARSEOCC_CUBE_DCA=cube-infer`, the peer; DCA=0 skips it) and with burn's image
#      convolutions (`SPARSEOCC_CUBE_CONV2D=direct`; CONV2D=0 skips it), in train_steps.txt, the
#      per-step logs beside it.
# Kernel caches: cubecl's compiled-kernel and autotune caches (`SPARSEOCC_KERNEL_CACHE`) and the CUDA
# driver's (`CUDA_CACHE_PATH`) live in OUT/kernel_cache/<first 16 hex of the binary's sha256>, so they
# come back with the output; CACHE_FROM=<an earlier OUT> copies that folder in first (same binary:
# same key), so that a later run starts with its kernels compiled.
# Every step has its own time limit (seconds, overridable) so that one slow step still leaves the
# others' results, and the whole script a budget (BUDGET seconds, default 560, under a device call's
# 600): a step gets at most what is left of it, and a step with under 20 s left is skipped. The
# steps run in the order of what they are needed for: the check, the trace, the SparseOcc++ speed
# and the three models (the acceptance), then the peers and training.
#
# Before the session, `SPARSEOCC_BIN=<the same binary> scripts/cuda_source_check.sh` compiles the
# project's own CUDA kernels for sm_90a on the CPU machine (NVRTC from PyPI), so that no device
# time goes to a kernel CUDA cannot compile.
#
# Usage: scripts/gpu_check.sh [OUT_DIR]
# With SPARSEOCC_BIN set, uses that binary (built elsewhere with `--features cuda`, e.g. on a CPU-only
# machine: CUDARC_CUDA_VERSION=13000 cargo build --release -p sparseocc --features cuda); otherwise
# builds one here with cargo.
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-gpu_check_out}
FRAMES=${FRAMES:-20}
CFG=${CFG:-configs/semantickitti_sparseocc_pp.toml}
T_CHECK=${T_CHECK:-90}
T_TRACE=${T_TRACE:-180}
T_BENCH=${T_BENCH:-150}
T_ALL=${T_ALL:-150}
T_SCAN=${T_SCAN:-120}
T_TRAIN=${T_TRAIN:-180}
TRAIN_STEPS=${TRAIN_STEPS:-8}
BUDGET=${BUDGET:-560}
mkdir -p "$OUT"
BIN=${SPARSEOCC_BIN:-}
if [ -z "$BIN" ]; then
  CUDARC_CUDA_VERSION=${CUDARC_CUDA_VERSION:-13000} cargo build --release -p sparseocc --features cuda || exit 1
  BIN=${CARGO_TARGET_DIR:-target}/release/sparseocc
fi
step() { # name, limit, command...
  local name=$1 limit=$2 left=$((BUDGET - SECONDS))
  shift 2
  if [ "$left" -lt 20 ]; then
    echo "== $name: skipped, ${left} s of the ${BUDGET} s budget left" | tee -a "$OUT/skipped.txt"
    return 0
  fi
  [ "$left" -lt "$limit" ] && limit=$left
  echo "== $name (limit ${limit} s)"
  local t0=$SECONDS
  timeout "$limit" "$@" >"$OUT/$name.log" 2>&1
  local rc=$?
  tail -n 25 "$OUT/$name.log"
  echo "== $name: rc $rc, $((SECONDS - t0)) s"
}
KEY=$(sha256sum "$BIN" | cut -c1-16)
CACHE="$OUT/kernel_cache/$KEY"
if [ -n "${CACHE_FROM:-}" ] && [ -d "$CACHE_FROM/kernel_cache/$KEY" ]; then
  mkdir -p "$OUT/kernel_cache"
  cp -r "$CACHE_FROM/kernel_cache/$KEY" "$OUT/kernel_cache/"
  echo "kernel caches from $CACHE_FROM/kernel_cache/$KEY"
fi
mkdir -p "$CACHE/driver"
export SPARSEOCC_KERNEL_CACHE="$CACHE" CUDA_CACHE_PATH="$CACHE/driver" CUDA_CACHE_MAXSIZE=4294967296
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv | tee "$OUT/gpu.txt"
step check_backend "$T_CHECK" "$BIN" check-backend --json "$OUT/check_backend.json"
if [ "${TRACE:-1}" = 1 ]; then
  step trace_pp "$T_TRACE" env SPARSEOCC_TRACE=1 SPARSEOCC_COUNT_LAUNCHES=1 "$BIN" bench \
    --config "$CFG" --models sparseocc++ --frames 1 --warmup 2 --json "$OUT/trace_pp.json"
fi
step bench_pp "$T_BENCH" "$BIN" bench --config "$CFG" --models sparseocc++ \
  --frames "$FRAMES" --warmup 3 --json "$OUT/bench_pp.json"
if [ "${ALL:-1}" = 1 ]; then
  step bench_all "$T_ALL" "$BIN" bench --config "$CFG" --models sparseocc++,sparseocc,dense \
    --frames 3 --warmup 2 --json "$OUT/bench_all.json"
fi
if [ "${GG:-1}" = 1 ]; then
  step bench_pp_gather_gemm "$T_BENCH" env SPARSEOCC_CUBE_CONV=gather-gemm "$BIN" bench \
    --config "$CFG" --models sparseocc++ --frames "$FRAMES" --warmup 3 --json "$OUT/bench_pp_gg.json"
fi
if [ "${DCA:-1}" = 1 ]; then
  step bench_pp_dca_tensor_ops "$T_BENCH" env SPARSEOCC_CUBE_DCA=tensor-ops "$BIN" bench \
    --config "$CFG" --models sparseocc++ --frames "$FRAMES" --warmup 3 --json "$OUT/bench_pp_dca_ops.json"
fi
if [ "${MAPS:-1}" = 1 ]; then
  step bench_pp_host_maps "$T_BENCH" env SPARSEOCC_CUBE_MAPS=host "$BIN" bench \
    --config "$CFG" --models sparseocc++ --frames "$FRAMES" --warmup 3 --json "$OUT/bench_pp_host_maps.json"
fi
if [ "${CONV2D:-1}" = 1 ]; then
  step bench_pp_direct_conv2d "$T_BENCH" env SPARSEOCC_CUBE_CONV2D=direct "$BIN" bench \
    --config "$CFG" --models sparseocc++ --frames "$FRAMES" --warmup 3 --json "$OUT/bench_pp_direct_conv2d.json"
fi
if [ "${TRAIN:-1}" = 1 ]; then
  # Training steps at the setting on a synthetic SemanticKITTI-layout sequence (the config's image
  # size, grid and model; forward with labels, the losses, backward, clipping, AdamW), every step
  # logged; the median of the steps after the first two (kernel compilation) is printed. The run
  # folders stay outside OUT (a checkpoint is 100+ MB); their logs are copied into it.
  # Batch 1: the paper trains with one frame per GPU (8 GPUs, batch 8).
  SYN=${TMPDIR:-/tmp}/sparseocc_gpu_check_synth
  TRAIN_CFG="$OUT/train_config.toml"
  sed 's/^batch_size *=.*/batch_size = 1/' "$CFG" >"$TRAIN_CFG"
  rm -rf "$SYN"
  step synth_kitti 120 "$BIN" synth --preset kitti --sequences 00:4 --out "$SYN"
  train_step() { # name, environment (VAR=value ...)
    local name=$1 run=${TMPDIR:-/tmp}/sparseocc_gpu_check_$1
    shift
    rm -rf "$run"
    step "$name" "$T_TRAIN" env "$@" "$BIN" train --config "$TRAIN_CFG" --data "$SYN" \
      --out "$run" --steps "$TRAIN_STEPS" --sequences 00 --val-sequences "" --log-every 1
    cp "$run/train_log.csv" "$OUT/${name}_log.csv" 2>/dev/null
    awk -F, 'NR > 1 && $1 > 2 { print $5 }' "$run/train_log.csv" 2>/dev/null | sort -g |
      awk -v n="$name" '{ v[NR] = $1 } END { if (NR) printf "%s: median step %.3f s over %d steps (steps 3+)\n", n, (NR % 2 ? v[(NR + 1) / 2] : (v[NR / 2] + v[NR / 2 + 1]) / 2), NR }' |
      tee -a "$OUT/train_steps.txt"
  }
  train_step train_pp
  [ "${DCA:-1}" = 1 ] && train_step train_pp_dca_tensor_ops SPARSEOCC_CUBE_DCA=cube-infer
  [ "${CONV2D:-1}" = 1 ] && train_step train_pp_direct_conv2d SPARSEOCC_CUBE_CONV2D=direct
fi
if [ "${SCAN:-0}" = 1 ]; then
  step memory_scan "$T_SCAN" "$BIN" bench --config "$CFG" --models sparseocc++,sparseocc,dense \
    --frames 1 --warmup 2 --scan "$OUT/memory_scan"
fi
echo "results in $OUT ($SECONDS s)"
