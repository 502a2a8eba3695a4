#!/usr/bin/env bash
# Set up .venv (scripts/setup.sh) and run the whole test suite on the CPU OpenCL device, in two runs; the
# arguments go to both.
#  1. Every test but those marked ``clock`` in two pytest-xdist workers, one per CI core: much of a test is
#     single-threaded (imports, subprocesses, NumPy). Each worker's OpenBLAS on one thread: beside the other
#     worker, OpenBLAS's threads waiting for work held the cores from the OpenCL runtimes' threads (the kernel,
#     reference and decode tests, tests/device/test_scanner.py tests/test_render.py tests/stage2
#     tests/stage1/test_operator.py, took 294 s in two workers, 77 s with OPENBLAS_NUM_THREADS=1, on two
#     first-generation Zen cores).
#  2. The ``clock`` tests (what a run does against its clock: a budget's share, a score left out when no time
#     is left) in one process after it. Beside a second worker a machine is half as fast to them: with every
#     test in two workers, a 10 s run left no time to score in one of three full CI runs (docs/benchmarks.md).
# --durations: the slowest tests in every log, to keep the CI run under 15 minutes.
set -uo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh || exit $?
OPENBLAS_NUM_THREADS=1 .venv/bin/python -m pytest -n 2 -m "not clock" --durations=15 "$@"
rest=$?
[ "$rest" -eq 2 ] && exit 2  # interrupted (Ctrl-C): no second run
.venv/bin/python -m pytest -m clock --durations=5 "$@"
clock=$?
# pytest's status 5 is "no test collected": an error only where neither run collected one.
if [ "$rest" -eq 5 ] && [ "$clock" -eq 5 ]; then exit 5; fi
for status in "$rest" "$clock"; do
    if [ "$status" -ne 0 ] && [ "$status" -ne 5 ]; then exit "$status"; fi
done
exit 0
