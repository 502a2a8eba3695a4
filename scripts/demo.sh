#!/usr/bin/env bash
# Set up .venv, then show octcl end to end in out/demo/:
#  1. reproduce the official Layers scan: render the regenerated baseline phantom,
#     make its maps, score it against the official scan in data/official/;
#  2. invert a bundled example: render a skin-like phantom, invert that B-scan
#     into a new phantom with the batch command (time budget $DEMO_BUDGET s,
#     default 120), render and score it, and point at its comparison panel.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh >/dev/null
octcl=.venv/bin/octcl
out=out/demo
mkdir -p "$out"

echo "== 1. Official Layers scan reproduced by octcl"
$octcl phantom baseline --kind layers --seed 42 -o "$out/layers.txt"
$octcl render "$out/layers.txt" -o "$out/layers.png"
$octcl maps "$out/layers.png"
$octcl score data/official/Scan_Exp2_Layers_A.png "$out/layers.png"

echo "== 2. Inverting a skin-like B-scan (budget ${DEMO_BUDGET:-120} s)"
$octcl phantom skin --seed 7 -o "$out/skin.txt"
mkdir -p "$out/targets"
$octcl render "$out/skin.txt" -o "$out/targets/skin.png"
$octcl invert --targets "$out/targets" --out "$out/inverted" --time-budget "${DEMO_BUDGET:-120}" --force >/dev/null
$octcl render "$out/inverted/skin.txt" -o "$out/skin_inverted.png"
$octcl score "$out/targets/skin.png" "$out/skin_inverted.png"
echo "Outputs in $out/"
echo "Target and rendering side by side (scan, OAC, SC, RSC): $out/inverted/skin.panel.png"
echo "Report of the batch: $out/inverted/report.html"
