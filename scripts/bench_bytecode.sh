#!/usr/bin/env bash
# What byte-code on disk saves a run where PYTHONDONTWRITEBYTECODE is set (as in many container images): the
# default `octcl invert` of a target (default orange.png beside the repository, ../shared/data/real),
# REPEATS times (default 3) with every __pycache__ of .venv and of octcl's sources removed, then REPEATS times
# after scripts/setup.sh has compiled them again. Prints each run's wall time.
set -euo pipefail
cd "$(dirname "$0")/.."
target=${1:-../shared/data/real/orange.png}
repeats=${REPEATS:-3}
out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT
runs() {
    for _ in $(seq "$repeats"); do
        PYTHONDONTWRITEBYTECODE=1 /usr/bin/time -f "$1: %e s" .venv/bin/octcl invert "$target" -o "$out/phantom.txt" --quiet
    done
}
scripts/setup.sh >/dev/null
find .venv octcl host kernels -name __pycache__ -type d -prune -exec rm -rf {} +
rm -f .venv/octcl-compiled-from
runs "no byte-code on disk"
/usr/bin/time -f "scripts/setup.sh, compiling: %e s" scripts/setup.sh >/dev/null
runs "byte-code written by scripts/setup.sh"
