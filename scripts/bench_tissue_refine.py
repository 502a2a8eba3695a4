"""Stage 3 in the tissue regime: schedules compared from the same tissue-scale start, under the same clock.

For each skin seed the scanner's rendering of ``octcl phantom skin --seed N``
is the target, and so is each ``--real`` file; ``octcl invert --regime tissue --iterations 0`` (stages 1–2
only) gives the start once; then each schedule (:data:`SCHEDULES`) runs
stage 3 from that start for ``--seconds``, one after the other in one
process with the same threads, its pixel phase comparing with the aimed
levels (:func:`octcl.host.stage1.ceiling.aimed_levels`, as the tissue regime's),
and the result's exact score and shares of pixels at the target's level and
at the aimed one are printed, one JSON row per run:

- ``full``: the physical regime's schedule (``RefineSchedule()``: every loss
  term from the first step), the tissue regime's before it had its own;
- ``pixel``: the pixel term alone at the rates of ``--pixel-rates``
  (lr_z_um, lr_u), as long as the clock lets it;
- ``tissue``: :data:`octcl.host.pipeline.invert.TISSUE_SCHEDULE`, the
  tissue regime's default, its first pixel phase ``--pixel-steps`` long
  when given (one run for each length);
- with ``--phases SPEC ...``, instead of named schedules, the tissue
  regime's schedule with its main phases replaced by each SPEC in turn:
  phases ``TERMS:ITERATIONS:LR_Z_UM:LR_U``, a hinge phase's with ``:GAMMA``
  after them where its γ is not 0 (:attr:`octcl.host.stage3.schedule.Phase.relative_exponent`),
  joined by commas (its restarts kept).

torch is imported before the first schedule's clock starts, so that no
schedule pays for it.

Example::

    python scripts/bench_tissue_refine.py --skin 5 --seconds 40 --out OUT
    python scripts/bench_tissue_refine.py --skin 5 --schedules tissue --pixel-steps 500 --seconds 120 --out OUT
    python scripts/bench_tissue_refine.py --skin 6 --real ../shared/data/real/orange.png --schedules tissue \
        --pixel-steps 250 100 60 --seconds 20 --out OUT
    python scripts/bench_tissue_refine.py --skin 6 --real ../shared/data/real/orange.png --seconds 21 --out OUT \
        --phases pixel:120:0.001:0.02,hinge:300:0:0 pixel:100:0.001:0.02,pixel:40:0.00025:0.005,hinge:300:0:0

Three more named schedules (``tissue-no-lpips``, ``tissue-lpips-every``,
``tissue-level``) varied the full loss that ended the tissue schedule until
octcl 0.8.7; they are in this script up to 0.8.8.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from octcl._io import write_grey_png
from octcl.config import DEFAULT_CONFIG
from octcl.host.pipeline.invert import TISSUE_SCHEDULE, invert
from octcl.host.pipeline.target import read_target, target_scan
from octcl.host.stage1.ceiling import aimed_levels
from octcl.host.stage1.levels import target_levels
from octcl.host.stage3.refine import Phase, RefineSchedule, refine
from octcl.phantom import Phantom
from octcl.render import render
from octcl.torch_import import import_torch

#: Schedules by name (module docstring); ``pixel`` takes its rates from the command line.
SCHEDULES = ("full", "pixel", "tissue")


def schedule_named(name: str, pixel_rates: tuple[float, float], steps: int | None) -> RefineSchedule:
    """The schedule called ``name`` (module docstring); ``steps`` the first pixel phase's length (``tissue``)."""
    if name == "full":
        return RefineSchedule()
    if name == "pixel":
        return RefineSchedule(phases=(Phase(100_000, *pixel_rates, terms="pixel"),), restarts=())
    if steps is None:
        return TISSUE_SCHEDULE
    first, *rest = TISSUE_SCHEDULE.phases
    return dataclasses.replace(TISSUE_SCHEDULE, phases=(dataclasses.replace(first, iterations=steps), *rest))


def phases_schedule(spec: str) -> RefineSchedule:
    """The tissue regime's schedule with its main phases from ``spec``: ``TERMS:ITERATIONS:LR_Z_UM:LR_U[:GAMMA]``
    joined by commas."""
    phases = []
    for part in spec.split(","):
        terms, iterations, lr_z_um, lr_u, *exponent = part.split(":")
        if len(exponent) > 1:
            raise ValueError(f"phase {part!r}: TERMS:ITERATIONS:LR_Z_UM:LR_U[:GAMMA], got {len(exponent) + 4} fields")
        phases.append(Phase(int(iterations), float(lr_z_um), float(lr_u), terms=terms,
                            relative_exponent=float(exponent[0]) if exponent else 0.0))
    return dataclasses.replace(TISSUE_SCHEDULE, phases=tuple(phases))


def tissue_start(target: Path, name: str, out: Path) -> tuple[np.ndarray, np.ndarray, Phantom]:
    """The target's levels, the tissue regime's aimed levels, and its phantom after stages 1–2
    (``octcl invert --regime tissue --iterations 0``), written to ``out`` once per target and folder."""
    levels = target_levels(target_scan(read_target(target)), DEFAULT_CONFIG)
    aim = aimed_levels(levels)  # the tissue regime's, as octcl invert passes it to stage 3
    start_path = out / f"{name}_start.txt"
    if not start_path.exists():
        invert(target, start_path, regime="tissue", iterations=0, threads=2)
    return levels, aim, Phantom.load(start_path)


def bench(name: str, target: Path, runs: list[tuple[dict, RefineSchedule]], seconds: float, out: Path) -> None:
    """Stage 3 from the target's tissue-regime start for ``seconds`` per run: ``runs`` (label, schedule) pairs, each
    label a dict of what names the run in its JSON row."""
    levels, aim, start = tissue_start(target, name, out)
    import_torch()  # before any schedule's clock
    for label, schedule in runs:
        began = time.perf_counter()
        result = refine(start, levels, schedule, deadline=time.monotonic() + seconds, threads=2, aim=aim)
        rendered = render(result.phantom).levels
        exact_share, aim_share = float(np.mean(rendered == levels)), float(np.mean(rendered == aim))
        print(json.dumps({"target": name, **label, "seconds": round(time.perf_counter() - began, 1),
                          "steps": result.iterations, "start_score": result.initial_components["mean"],
                          "score": result.components["mean"], "exact_share": exact_share,
                          "aim_share": aim_share}), flush=True)


def named_runs(names: list[str], pixel_rates, pixel_steps: list) -> list[tuple[dict, RefineSchedule]]:
    """(label, schedule) of each named schedule, ``tissue`` once for each of ``pixel_steps``."""
    runs = []
    for schedule in names:
        for steps in pixel_steps if schedule == "tissue" else [None]:
            runs.append(({"schedule": schedule, "pixel_rates": pixel_rates, "steps_of_phase": steps},
                         schedule_named(schedule, pixel_rates, steps)))
    return runs


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--skin", nargs="*", type=int, default=[5], help="skin phantom seeds (default 5)")
    parser.add_argument("--real", nargs="*", type=Path, default=[], help="real(-like) targets")
    parser.add_argument("--schedules", nargs="+", choices=SCHEDULES, default=list(SCHEDULES))
    parser.add_argument("--seconds", type=float, default=40.0, help="stage 3's clock per schedule (default 40)")
    parser.add_argument("--pixel-rates", nargs=2, type=float, default=(0.001, 0.02), metavar=("LR_Z_UM", "LR_U"),
                        help="the pixel schedule's learning rates (default 0.001 0.02)")
    parser.add_argument("--pixel-steps", nargs="+", type=int, default=[None],
                        help="the tissue schedule's first pixel phase's steps, one run each (default its own)")
    parser.add_argument("--phases", nargs="+", metavar="SPEC",
                        help="instead of --schedules: the tissue schedule's main phases, TERMS:ITERATIONS:LR_Z_UM:LR_U "
                             "joined by commas, one run each")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    targets = []
    for seed in args.skin:
        targets.append((f"skin_{seed}", args.out / f"skin_{seed}.png"))
        write_grey_png(targets[-1][1], render(Phantom.skin(seed)).levels)
    targets += [(path.stem, path) for path in args.real]
    if args.phases:
        runs = [({"phases": spec}, phases_schedule(spec)) for spec in args.phases]
    else:
        runs = named_runs(args.schedules, tuple(args.pixel_rates), args.pixel_steps)
    for name, target in targets:
        bench(name, target, runs, args.seconds, args.out)


if __name__ == "__main__":
    main()
