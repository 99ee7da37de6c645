#!/usr/bin/env bash
# Builds `moma` with `--features cuda` on a machine WITHOUT a GPU or a CUDA toolkit (a build machine),
# for a GPU machine with the CUDA 13 libraries (driver >= 580): the compiler, headers and runtime come
# from NVIDIA's PyPI wheels; cuBLAS, cuBLASLt, cuRAND, NVRTC and the driver API are linked against
# stub libraries generated from cudarc's own bindings (the real ones are loaded by soname at run time).
# On a machine with the CUDA toolkit installed none of this is needed:
#   CUDA_COMPUTE_CAP=90 cargo build --release -p moma-cli --features cuda
#
#   bash benches/gpu/build_cuda.sh [WORK_DIR] [--bundle DEV_DIR OFFICIAL_DIR SHARED_DIR]
# WORK_DIR (default /tmp/moma-cuda) receives the toolkit, the stubs and the cargo target folder.
# --bundle also gathers what benches/gpu/run.sh needs into DEV_DIR (the stripped binary, xz-compressed, the official
# depth_anything_v2 package, input.png with two tiny reference models, and a `moma demo` scene).
# Compute capability: CUDA_COMPUTE_CAP (default 90: H100/H200).
set -euo pipefail
work=${1:-/tmp/moma-cuda}
mkdir -p "$work/stubs"
cuda=$(bash "$(dirname "$0")/cuda_toolkit.sh" "$work")
cargo fetch -q
cudarc=$(cargo metadata --format-version 1 --features moma-depth/cuda | python3 -c 'import json,sys; print(next(p["manifest_path"] for p in json.load(sys.stdin)["packages"] if p["name"]=="cudarc"))')
src=$(dirname "$cudarc")/src
stub() { # name soname binding-files...: every function cudarc declares, as an empty symbol
    local name=$1 soname=$2
    shift 2
    grep -h -o 'pub unsafe fn [A-Za-z0-9_]*' "$@" | awk '{print "void "$4"(void){}"}' | sort -u >"$work/stubs/$name.c"
    gcc -shared -fPIC -o "$work/stubs/lib$name.so" -Wl,-soname,"$soname" "$work/stubs/$name.c"
}
stub cuda libcuda.so.1 "$src"/driver/sys/*.rs
stub nvrtc libnvrtc.so.13 "$src"/nvrtc/sys/*.rs
stub curand libcurand.so.10 "$src"/curand/sys/*.rs
stub cublas libcublas.so.13 "$src"/cublas/sys/*.rs
stub cublasLt libcublasLt.so.13 "$src"/cublaslt/sys/*.rs
ln -sf "$cuda/lib/libcudart.so.13" "$work/stubs/libcudart.so"
export PATH=$cuda/bin:$PATH CUDA_HOME=$cuda CUDA_COMPUTE_CAP=${CUDA_COMPUTE_CAP:-90}
export CARGO_TARGET_DIR=$work/target RUSTFLAGS="-L $work/stubs"
echo "building with nvcc 13.0 from PyPI (about 8 min on 2 cores, half of it candle's CUDA kernels)" >&2
cargo build --release -p moma-cli --features cuda
bin=$work/target/release/moma
if [ "${2:-}" = "--bundle" ]; then
    dev=${3:?DEV_DIR} official=${4:?OFFICIAL_DIR} shared=${5:?SHARED_DIR}
    rm -rf "$dev" && mkdir -p "$dev/ref" "$dev/dav2"
    strip -o "$work/moma.stripped" "$bin" && xz -T0 -6 -c "$work/moma.stripped" >"$dev/moma.xz"  # 61 MB -> 8.5 MB
    cp -r "$official/depth_anything_v2" "$dev/dav2/"
    for f in input.png tiny-rel.safetensors tiny-rel.output_full.npy tiny-metric-392.safetensors \
        tiny-metric-392.output_full.npy; do cp "$shared/reference/dav2/$f" "$dev/ref/"; done
    # the scene comes from the CPU build: the CUDA binary needs the driver library to start
    env -u CARGO_TARGET_DIR -u RUSTFLAGS cargo run -q --release -p moma-cli -- demo -o "$work/demo" --no-exports >/dev/null
    cp -r "$work/demo/scene" "$dev/scene"
    du -sh "$dev"
fi
echo "$bin"
