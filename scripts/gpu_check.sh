#!/usr/bin/env bash
# One prepared command for a lent GPU machine (docs/gpu_check.md).
#
# The lent machine has Python 3.12 with numpy, scipy, torch, pytest, hypothesis, matplotlib, psutil, tqdm,
# pillow and scikit-image, but no internet and no pyopencl. So, here (with the network and .venv):
#
#     scripts/gpu_check.sh prepare [DIR]       # DIR defaults to .gpucheck (ignored by git)
#
# builds octcl's wheel from the working tree, downloads the wheels of pyopencl and its dependencies (pytools,
# platformdirs, siphash24; typing-extensions, installed there only where it is missing) for CPython 3.12 on
# x86-64 Linux, at the versions in .venv, and copies the LPIPS weights (~/.cache/octcl/lpips_alex_v0.1.npz) and
# the real scan ../shared/data/real/orange.png (when it exists; it is not in the repository) into DIR. dask and
# distributed are not carried: only `octcl invert --targets` (batch) imports them.
#
# There, in the copied working tree, with DIR carried (it is ignored by git, so it travels only when named):
#
#     scripts/gpu_check.sh run OUTDIR [DIR]
#
# installs the wheels into a scratch folder (pip --no-index --target, PYTHONPATH), lists the OpenCL devices
# (octcl devices), times the default `python -m octcl.cli invert TARGET -o OUT.txt --json --quiet` on each
# official scan (data/official/Scan_*.png other than the maps) and on orange (also with --time-budget 3), then
# runs the kernel tests with the time left, and writes at most 8 files into OUTDIR: gpu_check.md (the table),
# timings.jsonl (per run: process wall time and invert's JSON), devices.txt, env.txt, invert.log,
# kernel_tests.txt, kernel_tests.xml. The whole run keeps within GPU_CHECK_DEADLINE seconds (default 420).
#
# The device call (the run tool; command under 2000 characters, carry the prepared folder):
#
#     run(command='bash scripts/gpu_check.sh run "$OUT"', carry=[".gpucheck"], timeout_s=480)
#
# Settings (environment):
#   GPU_CHECK_PYTHON_VERSION  prepare: the Python the wheels are for (default 3.12)
#   GPU_CHECK_VENV_PYTHON     prepare: the interpreter whose package versions are carried (default .venv/bin/python)
#   GPU_CHECK_PYTHON          run: the interpreter (default python3)
#   GPU_CHECK_SITE            run: where the wheels are installed (default ${TMPDIR:-/tmp}/octcl-gpucheck/site)
#   GPU_CHECK_DEADLINE        run: seconds for the whole run (default 420)
#   GPU_CHECK_INVERT_TIMEOUT  run: seconds one invert may take (default 120)
#   GPU_CHECK_SCANS           run: only these scans, comma-separated names (e.g. Scan_Exp2_Layers_A,orange)
#   GPU_CHECK_TESTS           run: the kernel-test files, space-separated (default: the 7 kernel-test files)
#   GPU_CHECK_PYTEST_ARGS     run: more pytest arguments, e.g. "-k pocl" (word-split)
set -euo pipefail

die() { echo "gpu_check: $*" >&2; exit 2; }
absolute() { case $1 in /*) printf '%s\n' "$1" ;; *) printf '%s\n' "$PWD/$1" ;; esac; }
usage() {
    echo "usage: scripts/gpu_check.sh prepare [DIR]      (here: wheels, weights, orange into DIR, default .gpucheck)" >&2
    echo "       scripts/gpu_check.sh run OUTDIR [DIR]   (on the GPU machine: results into OUTDIR)" >&2
    exit 2
}

REPOSITORY=$(cd "$(dirname "$0")/.." && pwd)
PACKAGES="pyopencl pytools platformdirs siphash24"   # pyopencl and the dependencies the lent machine lacks
OPTIONAL="typing_extensions"                         # installed there only where it is missing
KERNEL_TESTS="tests/device/test_scanner.py tests/device/test_programs.py tests/device/test_depth_order.py
tests/device/test_runtime.py tests/stage1/test_operator_device.py tests/stage1/test_display_device.py
tests/stage1/test_levels_device.py"

# ------------------------------------------------------------------ prepare (here)
prepare() {
    local dir=$1 version=${GPU_CHECK_PYTHON_VERSION:-3.12}
    local venv_python=${GPU_CHECK_VENV_PYTHON:-$REPOSITORY/.venv/bin/python}
    local weights=${OCTCL_CACHE_DIR:-$HOME/.cache/octcl}/lpips_alex_v0.1.npz
    local orange=$REPOSITORY/../shared/data/real/orange.png
    [ -x "$venv_python" ] || die "$venv_python is missing: run scripts/setup.sh (or set GPU_CHECK_VENV_PYTHON)"
    [ -f "$weights" ] || die "$weights is missing: run 'octcl weights fetch' first"
    case $version in 3.[0-9]|3.[0-9][0-9]) ;; *) die "GPU_CHECK_PYTHON_VERSION=$version: expected e.g. 3.12" ;; esac
    local tag=cp${version/./}

    rm -rf "$dir/wheels" "$dir/optional" "$dir/cache" "$dir/scans" "$dir/manifest.txt"
    mkdir -p "$dir/wheels" "$dir/optional" "$dir/cache" "$dir/scans"

    # The versions .venv has (the ones the tests ran with here).
    local specs=() optional=() name v
    for name in $PACKAGES $OPTIONAL; do
        v=$("$venv_python" -c "import importlib.metadata as m, sys; print(m.version(sys.argv[1]))" "$name" 2>/dev/null) \
            || die "$name is not installed in $venv_python's environment (its version is the one carried)"
        case " $OPTIONAL " in *" $name "*) optional+=("$name==$v") ;; *) specs+=("$name==$v") ;; esac
    done
    local download=("$venv_python" -m pip download -q --disable-pip-version-check --no-deps --only-binary=:all:
                    --python-version "$version" --implementation cp --platform manylinux_2_28_x86_64
                    --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64)
    echo "gpu_check: downloading ${specs[*]} ${optional[*]} for CPython $version, x86-64 Linux"
    "${download[@]}" -d "$dir/wheels" "${specs[@]}" 2>&1 | grep -v "is ignored: it is neither a file nor a directory" >&2 || true
    "${download[@]}" -d "$dir/optional" "${optional[@]}" 2>&1 | grep -v "is ignored: it is neither a file nor a directory" >&2 || true
    for name in $PACKAGES; do
        compgen -G "$dir/wheels/${name}-*.whl" >/dev/null \
            || die "no wheel of $name for CPython $version x86-64 Linux in $dir/wheels (pip download failed, see above)"
    done
    compgen -G "$dir/optional/${OPTIONAL}-*.whl" >/dev/null || die "no wheel of $OPTIONAL in $dir/optional"

    # octcl's wheel, built from a copy of the working tree's files (tracked, and untracked but not ignored:
    # what the lent machine gets), so that no stale build/ folder of this checkout leaks into it.
    scratch=$(mktemp -d "${TMPDIR:-/tmp}/octcl-gpucheck-build.XXXXXX")
    trap 'rm -rf "$scratch"' EXIT
    (cd "$REPOSITORY" && git ls-files -z -c -o --exclude-standard) | "$venv_python" -c '
import shutil, sys
from pathlib import Path
source, target = Path(sys.argv[1]), Path(sys.argv[2])
for name in sys.stdin.buffer.read().decode().split("\0"):
    if name and (source / name).is_file():  # a tracked file deleted in the working tree is left out
        (target / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(source / name, target / name)
' "$REPOSITORY" "$scratch/src"
    "$venv_python" -m pip wheel -q --disable-pip-version-check --no-deps --no-build-isolation \
        -w "$dir/wheels" "$scratch/src" >&2 || die "building octcl's wheel failed (pip wheel, see above)"
    local wheel
    wheel=$(compgen -G "$dir/wheels/octcl-*.whl" | head -n 1) || die "no octcl wheel in $dir/wheels after pip wheel"
    "$venv_python" - "$wheel" "$REPOSITORY" <<'EOF' || die "octcl's wheel $wheel is incomplete (above)"
import sys, zipfile
from pathlib import Path
names = set(zipfile.ZipFile(sys.argv[1]).namelist())
repository = Path(sys.argv[2])
wanted = [f"octcl/kernels/{p.name}" for p in (repository / "kernels").glob("*.cl")]
wanted += [f"octcl/host/{p.relative_to(repository / 'host')}" for p in (repository / "host").rglob("*.py")]
wanted += ["octcl/kernels/prelude.cl", "octcl/host/stage1/__init__.py", "octcl/cli.py", "octcl/device/runtime.py"]
missing = sorted(set(wanted) - names)
if missing:
    sys.exit("gpu_check: the wheel lacks " + ", ".join(missing[:10]) + (" ..." if len(missing) > 10 else ""))
EOF

    cp "$weights" "$dir/cache/"
    if [ -f "$orange" ]; then
        cp "$orange" "$dir/scans/orange.png"
    else
        echo "gpu_check: $orange is not there: the check goes on without the real scan" >&2
    fi
    {
        echo "python=$version"
        echo "tag=$tag"
        echo "prepared=$(date -u +%Y-%m-%dT%H:%M:%SZ)"
        echo "commit=$(cd "$REPOSITORY" && git rev-parse HEAD 2>/dev/null || echo unknown)"
        echo "working_tree_changes=$(cd "$REPOSITORY" && git status --porcelain 2>/dev/null | wc -l)"
        echo "wheels=$(cd "$dir/wheels" && ls *.whl | tr '\n' ' ')"
        echo "optional=$(cd "$dir/optional" && ls *.whl | tr '\n' ' ')"
    } > "$dir/manifest.txt"
    echo "gpu_check: prepared $dir ($(du -sh "$dir" | cut -f1)): $(cd "$dir" && find . -type f | sort | tr '\n' ' ')"
    if [ "$dir" = "$REPOSITORY/.gpucheck" ]; then
        echo "gpu_check: on the lent machine: bash scripts/gpu_check.sh run \"\$OUT\"   (carry [\".gpucheck\"])"
    fi
}

# ------------------------------------------------------------------ run (on the lent machine)
run() {
    local out=$1 dir=$2
    local python=${GPU_CHECK_PYTHON:-python3}
    local deadline_s=${GPU_CHECK_DEADLINE:-420}
    local site=${GPU_CHECK_SITE:-${TMPDIR:-/tmp}/octcl-gpucheck/site}
    local started=$SECONDS
    [ -d "$dir" ] || die "$dir is missing: run 'scripts/gpu_check.sh prepare' here and carry the folder (carry [\".gpucheck\"])"
    [ -f "$dir/manifest.txt" ] || die "$dir/manifest.txt is missing: $dir is not a prepared folder (scripts/gpu_check.sh prepare)"
    compgen -G "$dir/wheels/octcl-*.whl" >/dev/null || die "$dir/wheels has no octcl wheel: prepare again"
    compgen -G "$dir/wheels/pyopencl-*.whl" >/dev/null || die "$dir/wheels has no pyopencl wheel: prepare again"
    [ -f "$dir/cache/lpips_alex_v0.1.npz" ] || die "$dir/cache/lpips_alex_v0.1.npz is missing: prepare again"
    command -v "$python" >/dev/null || die "$python not found (set GPU_CHECK_PYTHON)"
    command -v timeout >/dev/null || die "timeout (coreutils) not found: it caps the kernel tests"
    local have want
    have=$("$python" -c 'import sys; print("%d.%d" % sys.version_info[:2])')
    want=$(sed -n 's/^python=//p' "$dir/manifest.txt")
    [ "$have" = "$want" ] || die "$dir holds wheels for Python $want, but $python is $have: prepare with GPU_CHECK_PYTHON_VERSION=$have"
    mkdir -p "$out" || die "cannot create the output folder $out"
    local env_txt=$out/env.txt

    # Install: octcl, pyopencl, pytools, platformdirs, siphash24 (and typing-extensions where it is missing).
    local wheels=("$dir"/wheels/*.whl)
    if ! "$python" -c "import typing_extensions" 2>/dev/null; then wheels+=("$dir"/optional/*.whl); fi
    rm -rf "$site" && mkdir -p "$site"
    {
        echo "# gpu_check run $(date -u +%Y-%m-%dT%H:%M:%SZ) on $(hostname)"
        cat "$dir/manifest.txt"
        echo "# install"
        echo "$python -m pip install --no-index --no-deps --target $site ${wheels[*]##*/}"
    } > "$env_txt"
    "$python" -m pip install -q --disable-pip-version-check --no-index --no-deps --no-compile --no-cache-dir \
        --upgrade --target "$site" "${wheels[@]}" >> "$env_txt" 2>&1 \
        || { tail -n 20 "$env_txt" >&2; die "pip install of the wheels in $dir/wheels failed (above; $env_txt)"; }
    # Byte-code for the installed wheels, in parallel: with PYTHONDONTWRITEBYTECODE (below, so that the checkout's
    # tests leave no __pycache__) every process would compile octcl, pyopencl and dask at its start
    # (scripts/bench_bytecode.sh: 1.5-2.5 s a default run on two cores).
    env -u PYTHONDONTWRITEBYTECODE "$python" -m compileall -q -j 0 "$site" >/dev/null 2>&1 || true
    export PYTHONPATH=$site${PYTHONPATH:+:$PYTHONPATH}
    export PYTHONSAFEPATH=1          # the checkout's octcl/ must not shadow the installed package (no octcl.host there)
    export PYTHONDONTWRITEBYTECODE=1
    # A writable copy of the cache: octcl reads the LPIPS weights there and writes its ICD folder and probes.
    export OCTCL_CACHE_DIR=${site%/*}/cache
    rm -rf "$OCTCL_CACHE_DIR" && mkdir -p "$OCTCL_CACHE_DIR" && cp "$dir/cache/lpips_alex_v0.1.npz" "$OCTCL_CACHE_DIR/"
    {
        echo "# environment"
        echo "PYTHONPATH=$PYTHONPATH OCTCL_CACHE_DIR=$OCTCL_CACHE_DIR"
        "$python" - <<'EOF' 2>&1
import importlib, importlib.metadata as m, os, platform, sys
print("python", sys.version.split()[0], sys.executable, platform.platform())
for name in ("octcl", "pyopencl", "pytools", "platformdirs", "siphash24", "typing_extensions", "numpy", "scipy",
             "torch", "pytest", "hypothesis", "skimage", "PIL", "psutil"):
    try:
        module = importlib.import_module(name)
        print(f"{name} {getattr(module, '__version__', '?')} {os.path.dirname(module.__file__)}")
    except Exception as exc:
        print(f"{name} MISSING: {type(exc).__name__}: {exc}")
try:
    import torch
    print("torch.cuda", torch.cuda.is_available(), torch.cuda.get_device_name(0) if torch.cuda.is_available() else "")
except Exception as exc:
    print("torch.cuda ?", exc)
print("cpus", os.cpu_count())
EOF
        echo "# GPU"
        if command -v nvidia-smi >/dev/null; then
            nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.max.sm --format=csv,noheader 2>&1 || true
        else
            echo "no nvidia-smi"
        fi
        ls -l /usr/local/nvidia/lib64/libnvidia-opencl.so* /etc/OpenCL/vendors 2>&1 || true
    } >> "$env_txt"
    "$python" -c "import octcl.host.pipeline.invert, pyopencl" 2>>"$env_txt" \
        || { tail -n 5 "$env_txt" >&2; die "octcl or pyopencl does not import from $site ($env_txt)"; }
    echo "gpu_check: installed into $site ($((SECONDS - started)) s)"

    # 1. Devices (this also builds octcl's kernels once on each device).
    "$python" -m octcl.cli devices > "$out/devices.txt" 2>&1 || echo "(octcl devices exited $?)" >> "$out/devices.txt"
    cat "$out/devices.txt"

    # 2. Timings of the default invert: the most valuable part, so first.
    local scans_dir=$REPOSITORY/data/official extra=$dir/scans
    local timing_end=$((deadline_s - 150 - (SECONDS - started)))   # seconds: leave >= 150 s for the kernel tests
    (( timing_end > 30 )) || timing_end=30
    "$python" "$REPOSITORY/scripts/gpu_check_table.py" time "$out" --scans "$scans_dir" --extra "$extra" \
        --only "${GPU_CHECK_SCANS:-}" --seconds "$timing_end" --timeout "${GPU_CHECK_INVERT_TIMEOUT:-120}" \
        --work "${site%/*}/phantoms" || echo "gpu_check: some invert runs failed (invert.log)" >&2

    # 3. Kernel tests with the time left (SIGINT first: pytest then still writes its summary and the XML).
    local left=$((deadline_s - (SECONDS - started) - 20))
    local tests
    read -r -d '' -a tests <<< "${GPU_CHECK_TESTS:-$KERNEL_TESTS}" || true
    if (( left >= 30 )); then
        echo "gpu_check: kernel tests, at most $left s"
        # shellcheck disable=SC2086  # GPU_CHECK_PYTEST_ARGS is word-split on purpose
        (cd "$REPOSITORY" && timeout -s INT -k 15 "$left" "$python" -m pytest -q -rfEs -p no:cacheprovider \
            -o addopts="" --junitxml="$out/kernel_tests.xml" "${tests[@]}" ${GPU_CHECK_PYTEST_ARGS:-}) \
            > "$out/kernel_tests.txt" 2>&1 && rc=0 || rc=$?
        if ((rc == 124 || rc == 137)); then
            echo "(pytest exit status $rc: stopped at the $left s limit)" >> "$out/kernel_tests.txt"
        else
            echo "(pytest exit status $rc)" >> "$out/kernel_tests.txt"
        fi
        tail -n 3 "$out/kernel_tests.txt"
    else
        echo "not run: only $left s were left of GPU_CHECK_DEADLINE=$deadline_s" > "$out/kernel_tests.txt"
    fi

    # 4. The table.
    "$python" "$REPOSITORY/scripts/gpu_check_table.py" table "$out" \
        --elapsed "$((SECONDS - started))" || die "writing $out/gpu_check.md failed"
    echo "gpu_check: done in $((SECONDS - started)) s: $out/gpu_check.md"
}

case ${1:-} in
    prepare)
        [ $# -le 2 ] || usage
        dir=$(absolute "${2:-$REPOSITORY/.gpucheck}")
        prepare "$dir" ;;
    run)
        [ $# -ge 2 ] && [ $# -le 3 ] || usage
        out=$(absolute "$2")
        dir=$(absolute "${3:-$REPOSITORY/.gpucheck}")
        run "$out" "$dir" ;;
    *) usage ;;
esac
