#!/usr/bin/env bash
# Installs the ONNX Runtime shared library for moma-depth's `onnx` feature (the `ort` crate loads it
# at run time: `load-dynamic`) from the `onnxruntime` PyPI wheel, which carries
# `onnxruntime/capi/libonnxruntime.so.<version>` (needs only glibc >= 2.28 and libstdc++).
#
# Usage:
#   export ORT_DYLIB_PATH="$(.ci/install-onnxruntime.sh)"            # library only (no deps, ~28 MB)
#   export ORT_DYLIB_PATH="$(.ci/install-onnxruntime.sh --python)"   # + a venv with onnxruntime and numpy
#                                                                     #   (for the Python side-by-side benchmark)
# The last line of stdout is the absolute path of libonnxruntime.so; everything else goes to stderr.
# Idempotent: a second run reuses the installation.
#
# Environment:
#   ORT_VERSION      wheel version (default 1.32.0; >= 1.17 is required by ort's `api-17` feature)
#   ORT_INSTALL_DIR  where to install (default <repo>/target-ort, git-ignored)
#   PYTHON           Python interpreter used for pip (default python3)
set -euo pipefail

ORT_VERSION="${ORT_VERSION:-1.32.0}"
REPO_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
ORT_INSTALL_DIR="${ORT_INSTALL_DIR:-$REPO_ROOT/target-ort}"
PYTHON="${PYTHON:-python3}"
WITH_PYTHON=0

for arg in "$@"; do
    case "$arg" in
        --python) WITH_PYTHON=1 ;;
        -h | --help)
            sed -n '2,16p' "${BASH_SOURCE[0]}" | sed 's/^# \{0,1\}//'
            exit 0
            ;;
        *)
            echo "install-onnxruntime.sh: unknown argument '$arg' (try --help)" >&2
            exit 2
            ;;
    esac
done

mkdir -p "$ORT_INSTALL_DIR"

if [[ "$WITH_PYTHON" == 1 ]]; then
    VENV="$ORT_INSTALL_DIR/venv"
    if [[ ! -x "$VENV/bin/python" ]]; then
        echo "creating venv $VENV" >&2
        "$PYTHON" -m venv "$VENV" >&2
    fi
    "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check \
        "onnxruntime==$ORT_VERSION" numpy >&2
    CAPI="$("$VENV/bin/python" -c 'import onnxruntime, os; print(os.path.join(os.path.dirname(onnxruntime.__file__), "capi"))')"
else
    TARGET="$ORT_INSTALL_DIR/onnxruntime-$ORT_VERSION"
    CAPI="$TARGET/onnxruntime/capi"
    if ! compgen -G "$CAPI/libonnxruntime.so.*" >/dev/null; then
        echo "installing onnxruntime==$ORT_VERSION (library only) into $TARGET" >&2
        "$PYTHON" -m pip install --quiet --disable-pip-version-check --no-deps \
            --target "$TARGET" "onnxruntime==$ORT_VERSION" >&2
    fi
fi

LIB="$(compgen -G "$CAPI/libonnxruntime.so.*" | head -n 1 || true)"
if [[ -z "$LIB" || ! -f "$LIB" ]]; then
    echo "install-onnxruntime.sh: libonnxruntime.so.* not found under $CAPI" >&2
    exit 1
fi
# A plain `libonnxruntime.so` link next to it, for loaders that look for the unversioned name.
ln -sf "$(basename "$LIB")" "$CAPI/libonnxruntime.so"
echo "ONNX Runtime $ORT_VERSION: $LIB" >&2
echo "$LIB"
