#!/bin/bash
# Issue 26 item 4: candle latency (median of 3 runs, f32/bf16/int8 alternating in one process)
# and peak RSS (one process per precision, --runs 1) of ViT-S and ViT-B (RANDOM weights) at the
# four input sizes of a 640×480 frame (518, 434, 350, 266 px short side, multiples of 14).
#   cargo build --release -p moma-depth --example bench_candle
#   python benches/latency/random_vitb.py ../shared/reference/dav2/vits-rel.safetensors /tmp/vitb.safetensors
#   bash benches/latency/table.sh ../shared/reference/dav2/vits-rel.safetensors /tmp/vitb.safetensors
set -euo pipefail
B=target/release/examples/bench_candle
VITS=$1
VITB=$2
for model in vits vitb; do
  W=$VITS; [ $model = vitb ] && W=$VITB
  for hw in "518 686" "434 574" "350 462" "266 350"; do
    echo "=== $model ${hw/ /x} timing"
    $B --weights "$W" --model $model --height ${hw% *} --width ${hw#* } --runs 3 --dtype f32,bf16,int8 2>&1 | grep -E "median"
    for d in f32 bf16 int8; do
      echo "=== $model ${hw/ /x} rss $d"
      $B --weights "$W" --model $model --height ${hw% *} --width ${hw#* } --runs 1 --dtype $d 2>&1 | grep -i "peak RSS"
    done
  done
done
