#!/usr/bin/env bash
# Set up .venv (scripts/setup.sh) and run the whole test suite on the CPU OpenCL device.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
exec .venv/bin/python -m pytest "$@"
