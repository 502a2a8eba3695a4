"""Benchmark stage 1's field schedules alone: the time each takes to put every pixel at its aimed level.

For each target (PNG or ``.npy`` of uint8 levels) and each schedule
(``--schedules``, ``octcl invert --field-schedule`` texts without the aim
step), one :class:`octcl.host.stage1.solve.FieldSolve` runs on octcl's
OpenCL device from the target's error-diffused aim
(:func:`octcl.host.stage1.ceiling.aimed_levels`), all in one process, each
target's schedules one after the other, so that the machine's load falls
on all alike. A schedule that leaves a pixel off its aimed level sends
``octcl invert`` to its second candidate (a display fit half as long,
:func:`octcl.host.stage1.start.linear_start`), so a schedule is only as
good as its worst target.

Once every pixel is at its aimed level the scores no longer depend on the
schedule: the aim step judges levels, and the written phantom renders
them. So time is the measure here, and where a schedule misses the aim,
that it did.

Writes ``schedules.jsonl`` (a row per target and schedule: seconds, share
at the aim, each step's iterations, share and seconds) and prints a
Markdown table per schedule (sum, median and longest seconds over the
targets, targets off their aim). Example::

    python scripts/bench_field_schedules.py TARGETS/*.npy --out OUT \\
        --schedules display:150,project:100,hinge:200 display:150,project:50,hinge:200
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

from octcl._io import read_scan
from octcl.host.stage1.backend import make_backend
from octcl.host.stage1.ceiling import aimed_levels
from octcl.host.stage1.levels import target_levels
from octcl.host.stage1.solve import FieldSchedule, FieldSolve


def run(schedule: FieldSchedule, levels, aim, backend) -> dict:
    """One schedule from the start on one target: its seconds, its share at the aim and its steps."""
    began = time.perf_counter()
    solve = FieldSolve(levels, aim, backend).run(schedule)
    return {"schedule": str(schedule), "seconds": time.perf_counter() - began, "identical": solve.best_identical,
            "steps": [[record.name, record.iterations, record.identical, record.seconds]
                      for record in solve.history]}


def table(rows: list[dict]) -> str:
    """Per schedule, in the order first met: targets, sum, median and longest seconds, targets off their aim."""
    lines = ["| schedule | targets | sum s | median s | longest s | off the aim |", "|---|---|---|---|---|---|"]
    for schedule in dict.fromkeys(row["schedule"] for row in rows):
        seconds = [row["seconds"] for row in rows if row["schedule"] == schedule]
        off = sum(row["identical"] < 1.0 for row in rows if row["schedule"] == schedule)
        lines.append(f"| `{schedule}` | {len(seconds)} | {sum(seconds):.1f} | {statistics.median(seconds):.2f} | "
                     f"{max(seconds):.2f} | {off} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("targets", nargs="+", type=Path)
    parser.add_argument("--schedules", nargs="+", default=["display:150,project:100,hinge:200"],
                        help="stage-1 schedules without the aim step (default: octcl invert's)")
    parser.add_argument("--out", type=Path, default=Path("bench_field_schedules"))
    args = parser.parse_args(argv)
    schedules = [FieldSchedule.parse(text) for text in args.schedules]
    if any(step.name == "aim" for schedule in schedules for step in schedule.steps):
        parser.error("the schedules are timed without the aim step, whose rounds need torch and the exact score")
    backend = make_backend("opencl")
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    with open(args.out / "schedules.jsonl", "w", encoding="utf-8") as handle:
        for path in args.targets:
            levels = target_levels(read_scan(path))
            aim = aimed_levels(levels)
            for schedule in schedules:
                row = {"target": path.stem, **run(schedule, levels, aim, backend)}
                rows.append(row)
                handle.write(json.dumps(row) + "\n")
                print(f"{path.stem}: {row['schedule']} {row['seconds']:.2f} s, at the aim {row['identical']:.4%}",
                      flush=True)
    print(table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
