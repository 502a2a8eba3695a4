#!/usr/bin/env bash
# Set up .venv (scripts/setup.sh) and run the whole test suite on the CPU OpenCL device.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
# --durations: the slowest tests in every log, to keep the CI run under 15 minutes.
exec .venv/bin/python -m pytest --durations=15 "$@"
