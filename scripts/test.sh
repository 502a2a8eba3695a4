#!/usr/bin/env bash
# Set up .venv (scripts/setup.sh) and run the whole test suite on the CPU OpenCL device.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
# --durations: the slowest tests in every log, to keep the CI run under 15 minutes. One process: two
# pytest-xdist workers took the suite from 1082 to 838-857 s on two first-generation Zen cores, but a test of
# a run against its clock (a 10 s budget left no time to score) failed in one of three runs, as on a machine
# half as fast (docs/benchmarks.md).
exec .venv/bin/python -m pytest --durations=15 "$@"
