#!/usr/bin/env bash
# Create .venv with octcl and everything it needs (CPU-only torch, PoCL from PyPI and,
# on x86-64 Linux, Intel's OpenCL CPU runtime: the extra "intel"), fetch the LPIPS
# weights once, and list the OpenCL devices, which build and the one octcl uses.
# Idempotent: a second run only checks.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
VENV=${OCTCL_VENV:-.venv}

if [ ! -x "$VENV/bin/python" ]; then
    "$PYTHON" -m venv "$VENV"
fi
# Every install below takes --no-compile, and the installed packages are compiled once after it, in parallel
# (compile_venv below): pip compiles every module one after the other (the torch wheel: 40.0 s instead of 16.6 s
# on two first-generation Zen cores).
pip() { "$VENV/bin/python" -m pip --disable-pip-version-check -q "$@"; }

# pip 23.2 (Python 3.11's own) downloads the newest SciPy wheels of other platforms, discards them and takes
# older ones; pip 26.3 takes the newest (scripts/check_platforms.py: two platforms in 13 s instead of 25 s).
if ! "$VENV/bin/python" -c "import sys, pip; sys.exit(int(pip.__version__.split('.')[0]) < 25)"; then
    pip install --no-compile --upgrade pip
fi

if ! "$VENV/bin/python" -c "import sys; from importlib.metadata import version
sys.exit(version('torch').split('+')[0] != '2.13.0')" 2>/dev/null; then
    # torch 2.13.0, CPU build only: a wheel from the folder $PIP_FIND_LINKS names if it holds
    # one (for machines without access to PyTorch's index), else PyTorch's CPU index.
    wheel=
    if [ -n "${PIP_FIND_LINKS:-}" ]; then
        wheel=$(ls "$PIP_FIND_LINKS"/torch-2.13.0+cpu-*.whl 2>/dev/null | head -n 1 || true)
    fi
    rm -f "$VENV/octcl-compiled-from"
    if [ -n "$wheel" ]; then
        pip install --no-compile "$wheel"
    else
        pip install --no-compile torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu
    fi
fi
# octcl (editable) and its requirements, again only where setup.cfg or octcl/__init__.py (the version) has
# changed since the last install into this venv: a second run of this script took 10.0 s with the install and
# torch's import, 0.9 s with these checks, on two slow cores.
if ! cat setup.cfg octcl/__init__.py | cmp -s - "$VENV/octcl-installed-from"; then
    pip install --no-compile -e ".[test,intel]"
    cat setup.cfg octcl/__init__.py > "$VENV/octcl-installed-from"
fi
# Byte-code, written once here: where PYTHONDONTWRITEBYTECODE is set (as in many container images) Python would
# otherwise compile every module it imports at every start and write none. On two Zen 4 cores a default
# `octcl invert` of orange.png took 6.9-7.4 s that way and 4.8-5.5 s with the byte-code written, and this
# script took 21 s compiling the venv (scripts/bench_bytecode.sh). octcl's own sources (an editable install) are compiled at
# every run of this script: compileall skips those up to date.
compile_venv() {
    env -u PYTHONDONTWRITEBYTECODE "$VENV/bin/python" -m compileall -q -j 0 "$@" >/dev/null 2>&1 || true
}
installed=$(cat "$VENV/octcl-installed-from")
if [ "$installed" != "$(cat "$VENV/octcl-compiled-from" 2>/dev/null)" ]; then
    compile_venv "$("$VENV/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')"
    printf '%s' "$installed" > "$VENV/octcl-compiled-from"
fi
compile_venv octcl host kernels
"$VENV/bin/octcl" weights check >/dev/null 2>&1 || "$VENV/bin/octcl" weights fetch
"$VENV/bin/octcl" devices
