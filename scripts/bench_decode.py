"""Stage 2's exact decode: every update of the placed field against the updates its tolerance leaves.

For each target, stage 1's field (the default schedule, as ``octcl invert``
runs it) is computed once and kept in OUT; then
:func:`octcl.host.stage2.exact.decode_exact` decodes it with ``tolerance`` 0
(every one of its :data:`~octcl.host.stage2.exact.DECODE_CORRECTIONS`
updates) and with the default :data:`~octcl.host.stage2.exact.DECODE_TOLERANCE`,
each timed on the machine's cores. Both phantoms are rendered by the float64
reference scanner, and one JSON row per target gives the rows' residual
max|F − F_eff|/max|F| after each count of updates and the count the
tolerance stops at, each decode's seconds, the pixels whose levels differ
between the two renderings, and each rendering's share of pixels at the
aimed levels.

Example::

    python scripts/bench_decode.py --targets ../shared/data/real/orange.png OUT/targets/plain_skin_0.png --out OUT
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from octcl.config import DEFAULT_CONFIG
from octcl.host.pipeline.target import read_target, target_scan
from octcl.host.stage1.ceiling import aimed_levels
from octcl.host.stage1.levels import target_levels
from octcl.host.stage1.start import linear_start
from octcl.host.stage2 import exact
from octcl.host.stage3.loss import ExactScore
from octcl.render import render


def stage1_field(target: Path, out: Path) -> np.ndarray:
    """Stage 1's field of ``target`` (default schedule), computed once and kept in ``out``."""
    kept = out / f"{target.stem}.field.npy"
    if kept.exists():
        return np.load(kept)
    scan = target_scan(read_target(target))
    score = ExactScore(read_target(target))
    aim = aimed_levels(target_levels(scan, DEFAULT_CONFIG))
    field = linear_start(scan, lambda levels: score(levels)["mean"], DEFAULT_CONFIG, aim=aim).field
    np.save(kept, field)
    return field


def residuals(field: np.ndarray) -> list[float]:
    """max|F − F_eff|/max|F| of the rows after 0, 1, … :data:`~octcl.host.stage2.exact.DECODE_CORRECTIONS` updates
    of the placed field (each decode run with every update up to that count)."""
    scale = np.abs(field).max()
    return [float(np.abs(field - exact.rendered_cells(exact.decoded_weights(field, DEFAULT_CONFIG, updates,
                                                                           tolerance=0.0))).max() / scale)
            for updates in range(exact.DECODE_CORRECTIONS + 1)]


def timed_decode(field: np.ndarray, tolerance: float) -> tuple:
    """The decode at ``tolerance`` on the machine's cores: its phantom and seconds."""
    began = time.perf_counter()
    phantom = exact.decode_exact(field, DEFAULT_CONFIG, tolerance=tolerance, workers=os.cpu_count())
    return phantom, time.perf_counter() - began


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--targets", nargs="+", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True, help="folder for stage 1's fields")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    for target in args.targets:
        field = stage1_field(target, args.out)
        aim = aimed_levels(target_levels(target_scan(read_target(target)), DEFAULT_CONFIG))
        residual = residuals(field)
        row, levels = {"target": target.name, "residual_after_updates": [float(f"{r:.2e}") for r in residual],
                       "updates_to_tolerance": next((count for count, r in enumerate(residual)
                                                     if r <= exact.DECODE_TOLERANCE), None)}, {}
        for name, tolerance in (("every_update", 0.0), ("tolerance", exact.DECODE_TOLERANCE)):
            phantom, seconds = timed_decode(field, tolerance)
            levels[name] = render(phantom).levels
            row[name] = {"seconds": round(seconds, 3), "at_aim": float(np.mean(levels[name] == aim))}
        row["pixels_differing"] = int(np.count_nonzero(levels["every_update"] != levels["tolerance"]))
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
