"""The tissue regime against the truth its targets were made from: energies, shadow, band densities, rendering.

For each target, ``octcl invert --regime tissue`` (host/pipeline/invert.py) in
this process under ``--time-budget``, then the written phantom's figures as
tissue (:func:`octcl.tissue.tissue_figures`) against the target's levels and,
for a skin phantom (``octcl phantom skin --seed N``, rendered by the scanner),
against the truth's: each band with signal's energy density over the truth's,
the shadow at the bottom of the visible tissue (dB, the truth's beside it),
the share of pixels at the target's level and the exact score, beside the
stage-2 start's (``initial_score``: the decode alone, before stage 3).

Seeds used while building the decode: skin 5 and the two-layer truth of
``tests/stage2/test_tissue_decode.py``; report others.

Example::

    python scripts/bench_tissue.py --skin 0 1 2 3 4 --real ../shared/data/real/orange.png --time-budget 60 --out OUT
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from octcl._io import write_grey_png
from octcl.config import DEFAULT_CONFIG
from octcl.host.pipeline.invert import invert
from octcl.host.pipeline.target import read_target, target_scan
from octcl.host.stage1.levels import target_levels
from octcl.phantom import Phantom
from octcl.render import render
from octcl.tissue import tissue_figures


def figures_against(phantom: Phantom, levels: np.ndarray, truth: dict | None) -> dict:
    """The phantom's figures, its rendering's share at the target's levels, and ratios to the truth's."""
    figures = tissue_figures(phantom, levels)
    row = {"median_energy_pct": figures["energy_pct"]["p50"], "p95_energy_pct": figures["energy_pct"]["p95"],
           "shadow_db": figures["shadow_db"], "exact_share": float(np.mean(render(phantom).levels == levels))}
    if truth is not None:
        row["truth_shadow_db"] = truth["shadow_db"]
        row["band_ratios"] = [mine / theirs for mine, theirs, signal in
                              zip(figures["band_densities_pct"], truth["band_densities_pct"], truth["bands_with_signal"])
                              if signal and theirs > 0]
    return row


def bench(name: str, target_path: Path, truth: Phantom | None, budget: float, out: Path) -> dict:
    levels = target_levels(target_scan(read_target(target_path)), DEFAULT_CONFIG)
    truth_figures = None if truth is None else tissue_figures(truth, levels)
    start = time.monotonic()
    result = invert(target_path, out / f"{name}.txt", time_budget_s=budget, regime="tissue",
                    report_path=out / f"{name}.report.json")
    wall = time.monotonic() - start
    row = {"target": name, "wall_s": wall, "score": result.score, "initial_score": result.initial_score,
           "iterations": result.iterations,
           **figures_against(Phantom.load(out / f"{name}.txt"), levels, truth_figures)}
    if truth_figures is not None:
        row["truth_median_energy_pct"] = truth_figures["energy_pct"]["p50"]
    print(json.dumps(row), flush=True)
    return row


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--skin", type=int, nargs="*", default=[0, 1, 2, 3, 4], help="skin phantom seeds")
    parser.add_argument("--real", type=Path, nargs="*", default=[], help="real(-like) targets, no truth")
    parser.add_argument("--time-budget", type=float, default=60.0)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for seed in args.skin:
        truth = Phantom.skin(seed)
        target = args.out / f"skin_{seed}.png"
        write_grey_png(target, render(truth).levels)
        rows.append(bench(f"skin_{seed}", target, truth, args.time_budget, args.out))
    for path in args.real:
        rows.append(bench(path.stem, path, None, args.time_budget, args.out))
    (args.out / "bench_tissue.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
