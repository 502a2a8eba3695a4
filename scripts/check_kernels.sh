#!/usr/bin/env bash
# Compile every OpenCL kernel for AMD (gfx906, gfx90a) and NVIDIA (sm_80) GPUs
# and print the compilers' resource reports; exit non-zero on any compile
# error (scripts/kernel_resources.py). Installs clang-14 and libclc-14 from the
# distribution's packages when they are missing and this runs as root.
# ptxas (CUDA) is used when found; without it the NVIDIA numbers come from the PTX.
set -euo pipefail
cd "$(dirname "$0")/.."
if ! command -v clang-14 >/dev/null || [ ! -e /usr/lib/clc/amdgcn--amdhsa.bc ]; then
    if [ "$(id -u)" -ne 0 ] || ! command -v apt-get >/dev/null; then
        echo "check_kernels: clang-14 and libclc-14 are missing; install them (apt-get install clang-14 libclc-14)" >&2
        exit 2
    fi
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq clang-14 libclc-14 >/dev/null
fi
PYTHON=${PYTHON:-.venv/bin/python}
[ -x "$PYTHON" ] || scripts/setup.sh
exec "$PYTHON" scripts/kernel_resources.py "$@"
