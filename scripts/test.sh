#!/usr/bin/env bash
# Set up .venv (scripts/setup.sh) and run the whole test suite on the CPU OpenCL device.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
# --durations: the slowest tests in every log, to keep the CI run under 15 minutes. -n 2: two pytest-xdist
# workers, one per CI core: 838 s against 1082 s for the suite on two first-generation Zen cores, every test
# passing (much of a test is single-threaded: imports, subprocesses, NumPy); -n 0 after it runs one process.
exec .venv/bin/python -m pytest -n 2 --durations=15 "$@"
