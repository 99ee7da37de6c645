#!/usr/bin/env bash
# `moma align` batch throughput (docs/benchmarks.md): 300 frames of 640×480 (SIMULATED
# predictions of gqcnn-primesense, each of its 15 frames 20 times), side by side in one run with
# the file I/O alone (read the prediction, write depth.png and depth.npy; the io_only example).
# usage: bash benches/align/throughput.sh [SHARED_DIR] [WORK_DIR]
set -euo pipefail
shared=${1:-../shared}
work=${2:-$(mktemp -d)}
cargo build --release -q -p moma-cli -p moma-io --example io_only
cargo build --release -q -p moma-cli
moma=target/release/moma
set_dir="$shared/data/gqcnn-primesense"
rm -rf "$work/sim" "$work/pred" && mkdir -p "$work/pred"
"$moma" simulate --set "$set_dir" -o "$work/sim" >/dev/null 2>&1
sim="$work/sim"
for f in "$sim"/*.npy; do
  for k in $(seq 0 19); do cp "$f" "$work/pred/$(basename "$f" .npy)_$k.npy"; done
done
cp "$sim/predictions.json" "$work/pred/"
first=$(ls "$sim"/*.npy | head -1)
"$moma" calibrate --pred "$first" --gt "$set_dir/frames/$(basename "$first" .npy)/depth.png" \
  --camera "$set_dir/camera.json" -o "$work/calib.json" >/dev/null 2>&1
n=$(ls "$work"/pred/*.npy | wc -l)
# a run that fails stops the script (its time would read as a fast run)
time_of() { local t0 t1; t0=$(date +%s.%N); "$@" >/dev/null 2>&1 || { echo "failed: $*" >&2; exit 1; }; t1=$(date +%s.%N); echo "$t1 - $t0" | bc -l; }
for round in 1 2 3; do
  rm -rf "$work"/o*
  io=$(time_of target/release/examples/io_only "$work/oio" inverse-depth "$work"/pred/*.npy)
  # the copies are not listed in the copied index: their kind is stated
  plain=$(time_of "$moma" align --calib "$work/calib.json" --pred-kind relative-disparity --pred "$work"/pred/*.npy -o "$work/oplain")
  full=$(time_of "$moma" align --calib "$work/calib.json" --pred-kind relative-disparity --pred "$work"/pred/*.npy -o "$work/ofull" --colormap turbo --ply)
  printf 'round %d: %d frames, %s threads | io only %.1f fps | align %.1f fps (%.2f × io) | align --colormap --ply %.1f fps\n' \
    "$round" "$n" "${RAYON_NUM_THREADS:-all}" "$(echo "$n / $io" | bc -l)" "$(echo "$n / $plain" | bc -l)" \
    "$(echo "$io / $plain" | bc -l)" "$(echo "$n / $full" | bc -l)"
done
