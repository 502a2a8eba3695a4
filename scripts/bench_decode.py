"""Stage 2's exact decode: every update of the placed field against the updates its tolerance leaves.

For each target, stage 1's field (the default schedule, as ``octcl invert``
runs it) is computed once and kept in OUT; then
:func:`octcl.host.stage2.exact.decode_exact` decodes it with ``tolerance`` 0
(every one of its :data:`~octcl.host.stage2.exact.DECODE_CORRECTIONS`
updates) and with the default :data:`~octcl.host.stage2.exact.DECODE_TOLERANCE`,
each timed on the machine's cores. Both phantoms are rendered by the float64
reference scanner, and one JSON row per target gives the rows' renders each
decode took, its seconds, the pixels whose levels differ between the two
renderings, and each rendering's share of pixels at the aimed levels.

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


def decode_counted(field: np.ndarray, tolerance: float) -> tuple:
    """The decode at ``tolerance`` on the machine's cores: its phantom, renders of the rows, seconds."""
    renders, rendered_cells = [], exact.rendered_cells

    def counted(*args):
        renders.append(1)
        return rendered_cells(*args)

    exact.rendered_cells = counted
    try:
        began = time.perf_counter()
        phantom = exact.decode_exact(field, DEFAULT_CONFIG, tolerance=tolerance, workers=os.cpu_count())
        return phantom, len(renders), time.perf_counter() - began
    finally:
        exact.rendered_cells = rendered_cells


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--targets", nargs="+", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True, help="folder for stage 1's fields")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    for target in args.targets:
        field = stage1_field(target, args.out)
        aim = aimed_levels(target_levels(target_scan(read_target(target)), DEFAULT_CONFIG))
        row, levels = {"target": target.name}, {}
        for name, tolerance in (("every_update", 0.0), ("tolerance", exact.DECODE_TOLERANCE)):
            phantom, renders, seconds = decode_counted(field, tolerance)
            levels[name] = render(phantom).levels
            row[name] = {"renders": renders, "seconds": round(seconds, 3),
                         "at_aim": float(np.mean(levels[name] == aim))}
        row["pixels_differing"] = int(np.count_nonzero(levels["every_update"] != levels["tolerance"]))
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
