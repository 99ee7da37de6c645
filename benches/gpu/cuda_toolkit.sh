#!/usr/bin/env bash
# NVIDIA's CUDA 13.0 compiler, headers and runtime from their PyPI wheels, unpacked under WORK_DIR
# (no GPU, no system CUDA toolkit needed); prints the CUDA root (bin/nvcc, include/, lib/).
# Every wheel is pinned to 13.0: a newer nvvm makes ptxas fail ("Unsupported .version").
#   CUDA_HOME="$(bash benches/gpu/cuda_toolkit.sh WORK_DIR)"
set -euo pipefail
work=${1:?WORK_DIR}
cuda=$work/x/nvidia/cu13
if [ ! -x "$cuda/bin/nvcc" ] || [ ! -x "$cuda/nvvm/bin/cicc" ]; then
    mkdir -p "$work/whl"
    python3 -m pip download -q --no-deps -d "$work/whl" nvidia-cuda-nvcc==13.0.88 \
        nvidia-cuda-runtime==13.0.96 nvidia-cuda-crt==13.0.88 nvidia-cuda-cccl==13.0.85 \
        nvidia-nvvm==13.0.88 >&2
    for w in "$work"/whl/*.whl; do python3 -m zipfile -e "$w" "$work/x"; done
    chmod +x "$cuda"/bin/* "$cuda"/nvvm/bin/*
fi
"$cuda/bin/nvcc" --version >&2
cd "$cuda" && pwd
