#!/usr/bin/env bash
# The GPU checks in one go, on a machine with an NVIDIA GPU (see README.md here):
#   bash benches/gpu/run.sh DEV_DIR OUT_DIR [gpu_checks.py options]
# DEV_DIR holds what build_cuda.sh --bundle prepares: moma.xz (the CUDA build), dav2/ (the official
# Depth-Anything-V2 python package), ref/ (input.png and two tiny reference models), scene/ (a moma set).
set -u
dev=${1:?DEV_DIR}
out=${2:?OUT_DIR}
shift 2
mkdir -p "$out"
nvidia-smi >"$out/nvidia-smi.txt" 2>&1
[ -f "$dev/moma.xz" ] && python3 -c 'import lzma,sys; open(sys.argv[2],"wb").write(lzma.open(sys.argv[1]).read())' "$dev/moma.xz" "$dev/moma"
chmod +x "$dev/moma"
set -o pipefail
PYTHONUNBUFFERED=1 python3 "$(dirname "$0")/gpu_checks.py" --moma "$dev/moma" --official "$dev/dav2" \
    --ref "$dev/ref" --scene "$dev/scene" --out "$out" "$@" 2>&1 | tee "$out/log.txt"
