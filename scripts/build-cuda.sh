#!/usr/bin/env bash
# Builds osrt with the `cuda` feature on a machine with no system CUDA toolkit and no GPU.
#
#   scripts/build-cuda.sh                     # cargo build --release --features cuda
#   scripts/build-cuda.sh test --features cuda --no-run   # any other cargo command
#   source scripts/build-cuda.sh --env        # only set the environment (CUDA_HOME, PATH, …)
#
# What it does (docs/gpu.md explains why each piece is needed):
# 1. installs NVIDIA's CUDA 13.0 compiler, headers and libraries from PyPI into
#    $OSRT_CUDA_DIR (default: cuda-toolkit in cargo's target directory): 13.0.x to match
#    a 13.0 driver, whose loader may refuse PTX from a newer nvcc;
# 2. assembles a CUDA root there: bin/include/nvvm of the wheels, and lib64 with the
#    unversioned `libX.so` links the linker's `-lX` wants;
# 3. writes a link-time stub of the driver library (`libcuda.so`, soname `libcuda.so.1`)
#    defining every `cu*` entry point cudarc declares; it is never shipped: at run time
#    the machine's own driver library is loaded;
# 4. runs cargo with CUDA_HOME pointing there and CUDA_COMPUTE_CAP=90 (H100/H200).
#
# At run time the binary needs libcuda.so.1 (the driver), libcublas.so.13,
# libcublasLt.so.13, libcurand.so.10, libcudart.so.13, libnvrtc.so.13: on the GPU machine
# point LD_LIBRARY_PATH at the nvidia/*/lib folders of a CUDA 13 PyTorch install, or at
# $OSRT_CUDA_DIR/lib64 after copying it there.
set -euo pipefail
ROOT_DIR="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
CUDA_DIR="${OSRT_CUDA_DIR:-${CARGO_TARGET_DIR:-$ROOT_DIR/target}/cuda-toolkit}"
COMPUTE_CAP="${CUDA_COMPUTE_CAP:-90}"
PYTHON="${PYTHON:-python3}"
WHEELS=(
    nvidia-cuda-nvcc==13.0.88 nvidia-cuda-crt==13.0.88 nvidia-nvvm==13.0.88
    nvidia-cuda-runtime==13.0.96 nvidia-cuda-cccl==13.0.85 nvidia-cuda-nvrtc==13.0.88
    nvidia-cublas==13.0.2.14 nvidia-curand==10.4.5.25
)

install_toolkit() {
    local stamp="$CUDA_DIR/.installed"
    if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "${WHEELS[*]}" ]; then
        return
    fi
    echo "build-cuda: installing the CUDA 13.0 toolkit wheels into $CUDA_DIR" >&2
    rm -rf "$CUDA_DIR"
    mkdir -p "$CUDA_DIR"
    "$PYTHON" -m pip install --quiet --disable-pip-version-check --no-deps \
        --only-binary=:all: --target "$CUDA_DIR/site" "${WHEELS[@]}"
    local cu="$CUDA_DIR/site/nvidia/cu13"
    for d in bin include nvvm; do
        [ -d "$cu/$d" ] || { echo "build-cuda: $cu/$d missing after install" >&2; exit 1; }
        ln -s "$cu/$d" "$CUDA_DIR/$d"
    done
    mkdir -p "$CUDA_DIR/lib64/stubs"
    # Every shared library of every wheel, under its versioned name and unversioned.
    local lib base
    for lib in "$CUDA_DIR"/site/nvidia/*/lib/lib*.so*; do
        base="$(basename "$lib")"
        ln -sf "$lib" "$CUDA_DIR/lib64/$base"
        ln -sf "$lib" "$CUDA_DIR/lib64/${base%%.so*}.so"
    done
    write_driver_stub
    echo "${WHEELS[*]}" >"$stamp"
}

# The driver API's entry points as cudarc's bindings name them, each defined as an empty
# function: enough for the linker to resolve `-lcuda`, never called.
write_driver_stub() {
    local sys
    sys="$(cargo metadata --format-version 1 --manifest-path "$ROOT_DIR/Cargo.toml" \
        --features cuda 2>/dev/null | "$PYTHON" -c '
import json, sys
m = json.load(sys.stdin)
p = [p for p in m["packages"] if p["name"] == "cudarc"]
print(p[0]["manifest_path"].rsplit("/", 1)[0] + "/src/driver/sys/mod.rs" if p else "")')"
    if [ -z "$sys" ] || [ ! -f "$sys" ]; then
        echo "build-cuda: cudarc's driver bindings not found (cargo fetch first)" >&2
        exit 1
    fi
    grep -oE '^\s+fn cu[A-Z][A-Za-z0-9_]*' "$sys" | awk '{print "void " $2 "(void) {}"}' \
        | sort -u >"$CUDA_DIR/lib64/stubs/cuda_stub.c"
    cc -shared -fPIC -Wl,-soname,libcuda.so.1 -o "$CUDA_DIR/lib64/stubs/libcuda.so" \
        "$CUDA_DIR/lib64/stubs/cuda_stub.c"
}

set_env() {
    export CUDA_HOME="$CUDA_DIR" CUDA_PATH="$CUDA_DIR" CUDA_ROOT="$CUDA_DIR"
    export PATH="$CUDA_DIR/bin:$PATH"
    export CUDA_COMPUTE_CAP="$COMPUTE_CAP"
    # Smaller embedded kernels: the binary is carried to GPU machines with a size limit.
    export NVCC_APPEND_FLAGS="${NVCC_APPEND_FLAGS:---compress-mode=size}"
    export LIBRARY_PATH="$CUDA_DIR/lib64:$CUDA_DIR/lib64/stubs${LIBRARY_PATH:+:$LIBRARY_PATH}"
}

(cd "$ROOT_DIR" && cargo fetch --quiet)
install_toolkit
set_env
if [ "${1:-}" = "--env" ]; then
    return 0 2>/dev/null || exit 0
fi
cd "$ROOT_DIR"
if [ "$#" -eq 0 ]; then
    set -- build --release --features cuda
fi
exec cargo "$@"
