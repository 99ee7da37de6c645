#!/bin/bash
# Issue 26 item 4: candle latency (median of 3 runs, f32/bf16/int8 alternating in one process)
# and peak RSS (one process per precision, --runs 1) of ViT-S and ViT-B (RANDOM weights) at the
# four input sizes of a 640×480 frame (518, 434, 350, 266 px short side, multiples of 14).
# With OFFICIAL_DIR and PYTHON, the official code runs in the same loop, right after candle at
# each size: PyTorch f32/int8 and ONNX Runtime f32/int8 alternating in one process
# (benches/latency/official.py; exports cached in $ONNX_DIR, default /tmp/moma-latency-onnx),
# and its peak RSS one process per backend.
#   cargo build --release -p moma-depth --example bench_candle
#   python benches/latency/random_vitb.py ../shared/reference/dav2/vits-rel.safetensors /tmp/vitb.safetensors
#   bash benches/latency/table.sh ../shared/reference/dav2/vits-rel.safetensors /tmp/vitb.safetensors \
#       [OFFICIAL_DIR PYTHON]
# OFFICIAL_DIR: a checkout of github.com/DepthAnything/Depth-Anything-V2; PYTHON: one with torch,
# torchvision, safetensors, onnx, onnxruntime.
set -euo pipefail
B=target/release/examples/bench_candle
VITS=$1
VITB=$2
OFFICIAL=${3:-}
PY=${4:-python3}
ONNX_DIR=${ONNX_DIR:-/tmp/moma-latency-onnx}
official() {
  "$PY" benches/latency/official.py --official "$OFFICIAL" --weights "$1" --model "$2" \
    --height "$3" --width "$4" --onnx-dir "$ONNX_DIR" --threads 2 "${@:5}" 2>&1
}
for model in vits vitb; do
  W=$VITS; [ $model = vitb ] && W=$VITB
  for hw in "518 686" "434 574" "350 462" "266 350"; do
    h=${hw% *}; w=${hw#* }
    echo "=== $model ${h}x$w timing"
    $B --weights "$W" --model $model --height $h --width $w --runs 3 --dtype f32,bf16,int8 2>&1 | grep -E "median"
    if [ -n "$OFFICIAL" ]; then
      official "$W" $model $h $w --runs 3 | grep -E "median|onnxruntime"
    fi
    for d in f32 bf16 int8; do
      echo "=== $model ${h}x$w rss $d"
      $B --weights "$W" --model $model --height $h --width $w --runs 1 --dtype $d 2>&1 | grep -i "peak RSS"
    done
    if [ -n "$OFFICIAL" ]; then
      for b in torch-f32 torch-int8 ort-f32 ort-int8; do
        echo "=== $model ${h}x$w rss $b"
        official "$W" $model $h $w --runs 1 --backends $b | grep -i "peak RSS"
      done
    fi
  done
done
