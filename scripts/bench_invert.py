"""Benchmark ``octcl.host.pipeline.invert`` on a development set of B-scans, over several seeds.

The set: the official scans in the repository's ``data/official`` (Uniform A
and B, Layers A), the real scan ``../shared/data/real/orange.png`` beside the
repository and, with ``--skin N``, N skin-like synthetic targets rendered from
:meth:`octcl.phantom.Phantom.skin`. The real scan may not be redistributed, so
the repository does not carry it (``data/README.md``); without it the set goes
on without ``orange``, and says so. Each scan is inverted once per seed
(``--seeds``, three by default), each run in its own process (so the peak
memory is that run's), with the given time budget or, with
``--iterations``, a fixed schedule (no decision from the clock, so the
scores do not depend on the machine's load; ``docs/reproducibility.md``).
The written phantom is then rendered again with the OpenCL scanner and
scored exactly against the target, which is the score the file would get.

Two versions of the inversion differ significantly on a scan when their
mean scores over n seeds each differ by more than
t_{0.975, 2n−2}·s·sqrt(2/n), s the seeds' standard deviation (Student's
two-sample t-test at 5 %, equal spreads); ``min_significant_difference``
is that bound, per scan and for the global score.

Writes, in ``--out``:

- ``NAME_sSEED.txt``, ``NAME_sSEED.report.json`` (invert's report),
  ``NAME_sSEED_render.png``;
- ``NAME_panel.png``: target (top) and rendering of the first seed (bottom),
  each as scan, OAC, SC and RSC maps;
- ``bench.csv``: per run the 8 components, their mean, seconds, peak memory
  and the machine's 5-minute load average at its end;
- ``spread.csv``: per scan, and for the global score (the mean of the 8
  per-component medians over the scans, one per seed), the seeds' mean,
  standard deviation, minimum, maximum and ``min_significant_difference``;
- ``bench.json``: all of it;
- ``score_vs_time.png``: per scan, the best exact score against wall time
  of each run, from the traces;
- ``exact_share_vs_time.png``: per scan, the share of pixels off their
  aimed level after each stage-1 step against stage 1's seconds;
- ``comparison.md``: per run the score, seconds, iterations and what ended
  stage 3; with several ``--schedules``, each one's score difference and
  time ratio to the first, its global score and median seconds; the
  seconds each run took to reach 0.9947, 0.998, 0.999, 0.9995, 0.9998, its final score
  − 1e−4 and the score of the target's error-diffused image (the
  ceiling, host/stage1/ceiling.py, beside the shares of pixels exact, writable and avoidably off); and stage 3's time per iteration, part by part, in wall and CPU
  seconds (``--summarise`` writes it again from the files).

``--schedules fixed-length default`` runs, on each scan and seed, the
schedule before adaptive stopping and then the default one, so that both
meet the same machine load.

Examples::

    python scripts/bench_invert.py --time-budget 600 --scans Scan_Exp2_Layers_A orange --seeds 0 1 2
    python scripts/bench_invert.py --seeds 0 --skin 3 --schedules fixed-length default --out OUT
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from octcl._io import atomic_write, write_grey_png
from octcl.host.batch.report import comparison_panel
from octcl.host.stage3.loss import ExactScore
from octcl.host.stage3.refine import RefineSchedule
from octcl.host.stage1.levels import target_levels
from octcl.host.pipeline.target import read_target, target_scan
from octcl.phantom import CONTRACT_Y_LIMIT_UM, Phantom
from octcl.render import render
from octcl.scorer import COMPONENTS, global_score

REPOSITORY = Path(__file__).resolve().parents[1]
OFFICIAL_DIR = REPOSITORY / "data" / "official"
OFFICIAL = ("Scan_Exp1_Uniform_A", "Scan_Exp1_Uniform_B", "Scan_Exp2_Layers_A")
ORANGE = REPOSITORY.parent / "shared" / "data" / "real" / "orange.png"
ORANGE_MISSING = f"orange: {ORANGE} not found (a real scan the repository may not carry; see data/README.md)"


def development_set(out: Path, skin: int, plain: int = 0) -> dict[str, Path]:
    """{name: target PNG}; skin targets are rendered into ``out/targets``; orange only if present.

    ``plain_skin_N`` (``plain`` of them) are renderings of ``Phantom.skin(N)`` quantised plainly,
    floor(256·D) with no colour map: targets with unwritable levels, as real scans have, whose phantom is
    known (host/stage1/ceiling.py).
    """
    targets = {name: OFFICIAL_DIR / f"{name}.png" for name in OFFICIAL}
    if ORANGE.is_file():
        targets["orange"] = ORANGE
    for seed in range(skin):
        path = out / "targets" / f"skin_{seed}.png"
        if not path.exists():
            write_grey_png(path, render(Phantom.skin(seed)).levels)
        targets[f"skin_{seed}"] = path
    for seed in range(plain):
        path = out / "targets" / f"plain_skin_{seed}.png"
        if not path.exists():
            display = render(Phantom.skin(seed)).display
            write_grey_png(path, np.minimum(np.floor(256 * display), 255).astype(np.uint8))
        targets[f"plain_skin_{seed}"] = path
    return targets


#: ``--schedules``: what runs, as :func:`octcl.host.pipeline.invert.invert` keyword
#: arguments (beside the time budget, seed and iterations, which they may
#: override). ``default`` is invert's default (the linear regime);
#: ``physical`` the published pipeline (``--regime physical``);
#: ``budget-10`` (``-5``, ``-3``) the default with a 10 s (5 s, 3 s) time budget; ``field-300`` and
#: ``field-75`` the linear regime's first display fit of 300 or 75 steps (150 by default); ``no-aim`` the default's
#: first stage-1 candidate without its aim step (host/stage1/solve.py); ``fixed-length`` the
#: default's phases and restarts, each run to its whole length (the schedule
#: before adaptive stopping); ``stall-rule`` adds the main run's stall rule
#: with a patience of 2 checkpoints (host/stage3/refine.py); ``no-fall-guard`` never
#: goes back to the best phantom when the main run falls (``max_falls`` 0); ``numpy`` the default with stage 1
#: on the host (``--backend numpy``), the reference the device path is measured against.
#: Variants of the loss are compared by ``bench_refine.py``.
SCHEDULES = {"default": "", "physical": "regime='physical'", "budget-10": "time_budget_s=10.0",
             "budget-5": "time_budget_s=5.0", "budget-3": "time_budget_s=3.0",
             "field-300": "field_iterations=300", "field-75": "field_iterations=75",
             "no-aim": "field_schedule='display:150,project:100,hinge:200'",
             "fixed-length": "schedule=RefineSchedule().fixed_length()",
             "stall-rule": "schedule=RefineSchedule(patience=2)", "no-fall-guard": "schedule=RefineSchedule(max_falls=0)",
             "numpy": "backend='numpy'"}


def run_invert(target: Path, output: Path, report: Path, budget: float, seed: int, iterations: int | None,
               schedule: str = "default") -> None:
    """invert() in a child process, so that ru_maxrss is this run's peak; its budget runs from the child's start
    and it ends as ``octcl invert`` does (:func:`octcl.cli.exit_now`)."""
    code = ("import sys; from octcl.host.pipeline.invert import invert; from octcl.host.stage3.refine import RefineSchedule; "
            "from octcl.cli import exit_now, process_started; "
            "options = dict(time_budget_s=float(sys.argv[4])); "
            f"options.update(dict({SCHEDULES[schedule]})); "
            "invert(sys.argv[1], sys.argv[2], seed=int(sys.argv[5]), report_path=sys.argv[3], "
            "iterations=None if sys.argv[6] == 'None' else int(sys.argv[6]), started=process_started(), **options); "
            "exit_now(0)")
    subprocess.run([sys.executable, "-c", code, str(target), str(output), str(report), str(budget), str(seed),
                    str(iterations)], check=True)


def spread(scores: list[float]) -> dict:
    """Mean, sample standard deviation, range and the least significant difference of n seeds' scores."""
    from scipy.stats import t

    n = len(scores)
    std = float(np.std(scores, ddof=1)) if n > 1 else float("nan")
    bound = float(t.ppf(0.975, 2 * n - 2) * std * np.sqrt(2 / n)) if n > 1 else float("nan")
    return {"n": n, "mean": float(np.mean(scores)), "std": std, "min": float(min(scores)),
            "max": float(max(scores)), "min_significant_difference": bound}


def time_to_scores(trace: list[dict], final: float, others: dict | None = None) -> dict:
    """Seconds from the run's start until its best exact score first reached each of :data:`SCORE_LEVELS`.

    ``final`` is the run's final score; its level is final − 1e−4. ``others``
    adds {label: score} (the target's ceiling score). None where
    never reached; a ceiling score a budget left out (None) is not a level.
    """
    levels = {**{f"{level:g}": level for level in SCORE_LEVELS}, "final-1e-4": final - 1e-4, **(others or {})}
    scored = [(entry["time_s"], entry["score"]) for entry in trace if entry.get("score") is not None]
    return {label: None if level is None else next((t for t, score in scored if score >= level), None)
            for label, level in levels.items()}


#: Scores whose time to reach :func:`time_to_scores` reports: the published
#: global score and two above it.
SCORE_LEVELS = (0.9947, 0.998, 0.999, 0.9995, 0.9998)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--time-budget", type=float, default=600.0,
                        help="seconds per run (default 600; with --iterations only a ceiling)")
    parser.add_argument("--iterations", type=int, help="fixed schedule: stage-3 Adam steps (invert's iterations)")
    parser.add_argument("--out", type=Path, default=Path("bench_invert"), help="output folder")
    parser.add_argument("--scans", nargs="*", help="names to run (default: all of the set)")
    parser.add_argument("--skin", type=int, default=2, help="synthetic skin targets to add (default 2)")
    parser.add_argument("--plain", type=int, default=0,
                        help="plainly quantised skin renderings to add, targets with unwritable levels (default 0)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="seeds per scan (default 0 1 2)")
    parser.add_argument("--schedules", nargs="+", choices=sorted(SCHEDULES), default=["default"],
                        help="stage-3 schedules to compare, run one after the other on each scan and seed "
                             "(default: default)")
    parser.add_argument("--summarise", action="store_true",
                        help="run nothing: write comparison.md and score_vs_time.png again from --out's bench.json")
    args = parser.parse_args(argv)
    if args.summarise:
        print(write_summary(args.out))
        return 0

    targets = development_set(args.out, args.skin, args.plain)
    names = args.scans or list(targets)
    if "orange" not in targets:
        if not args.scans:
            print(f"{ORANGE_MISSING}: the set goes on without it", file=sys.stderr)
        elif "orange" in args.scans:
            parser.error(ORANGE_MISSING)
    unknown = sorted(set(names) - set(targets))
    if unknown:
        parser.error(f"unknown scans {unknown}; known: {sorted(targets)}")
    several = len(args.schedules) > 1
    rows = {}
    for name in names:
        target_array = read_target(targets[name])
        exact_score = ExactScore(target_array)
        for seed in args.seeds:
            for schedule in args.schedules:
                run = f"{name}_{schedule}_s{seed}" if several else f"{name}_s{seed}"
                panel = seed == args.seeds[0] and schedule == args.schedules[0]
                rows[run] = bench_run(args, name, targets[name], target_array, exact_score, run, seed, schedule, panel)
    write_results(args, rows, names)
    print(write_summary(args.out))
    return 0


def bench_run(args, name: str, target: Path, target_array: np.ndarray, exact_score, run: str, seed: int,
              schedule: str, panel: bool) -> dict:
    """One ``octcl invert`` of ``target`` in a fresh process, its rendering scored; its row of bench.csv (and, if
    ``panel``, the scan's comparison panel)."""
    output, report_path = args.out / f"{run}.txt", args.out / f"{run}.report.json"
    start = time.monotonic()
    run_invert(target, output, report_path, args.time_budget, seed, args.iterations, schedule)
    wall = time.monotonic() - start
    report = json.loads(report_path.read_text())
    levels = render(Phantom.load(output, y_limit_um=CONTRACT_Y_LIMIT_UM)).levels
    write_grey_png(args.out / f"{run}_render.png", levels)
    components = exact_score(levels)
    if panel:
        with atomic_write(args.out / f"{name}_panel.png") as handle:
            handle.write(comparison_panel(target_array, levels,
                                          f"{name}, seed {seed}: score {components['mean']:.5f} after "
                                          f"{report['seconds']['total']:.0f} s"))
    ceiling = report["ceiling"]
    reached = time_to_scores(report["trace"], components["mean"],
                             {"diffused": ceiling["diffused_score"]})
    row = {"scan": name, "schedule": schedule, "seed": seed,
           **{c: components[c] for c in COMPONENTS},
           "mean": components["mean"], "initial_score": report["initial_score"],
           "iterations": report["iterations"], "field_iterations": report["field_iterations"],
           "stop_reason": report.get("stop_reason"),
           "falls": " ".join(map(str, report.get("falls", []))),
           "reproducible": report.get("reproducible"),
           "exact_share": float(np.mean(levels == target_levels(target_scan(target_array)))),
           "writable_share": ceiling["writable_share"], "avoidable_share": report["avoidable_share"],
           "diffused_score": ceiling["diffused_score"],
           "seconds": report["seconds"]["total"], "wall_s": wall,
           "written_s": report["seconds"]["written"],
           **{f"seconds_to_{label}": value for label, value in reached.items()},
           "peak_memory_mib": report["peak_memory_mib"], "load_average": os.getloadavg()[1]}
    initial = "left out" if report["initial_score"] is None else f"{report['initial_score']:.6f}"
    print(f"{run}: {components['mean']:.6f} (stages 1-2: {initial}), "
          f"{report['iterations']} iterations ({report.get('stop_reason')}), "
          f"falls after steps [{row['falls']}], "
          f"{report['seconds']['total']:.0f} s, {report['peak_memory_mib']:.0f} MiB", flush=True)
    return row


def write_results(args, rows: dict, names: list[str]) -> None:
    """bench.json, bench.csv and spread.csv of the runs' ``rows``; each scan's spread over the seeds printed."""
    def global_of(schedule, seed):  # mean of the 8 per-component medians over the scans, for one seed
        return global_score(row for row in rows.values() if row["seed"] == seed and row["schedule"] == schedule)[1]

    spreads = {}
    for schedule in args.schedules:
        of = [row for row in rows.values() if row["schedule"] == schedule]
        for name in names:
            spreads[schedule, name] = spread([row["mean"] for row in of if row["scan"] == name])
        spreads[schedule, "global"] = spread([global_of(schedule, seed) for seed in args.seeds])
        spreads[schedule, "median_seconds"] = spread([float(np.median([row["seconds"] for row in of
                                                                       if row["seed"] == seed]))
                                                      for seed in args.seeds])
    summary = {"time_budget_s": args.time_budget, "iterations": args.iterations, "seeds": args.seeds,
               "schedules": args.schedules, "runs": rows,
               "spread": {f"{schedule}/{name}": values for (schedule, name), values in spreads.items()}}
    with atomic_write(args.out / "bench.json", "w") as handle:
        json.dump(summary, handle, indent=1)
    columns = ["scan", "schedule", "seed", *COMPONENTS, "mean", "initial_score", "iterations", "field_iterations",
               "stop_reason", "falls", "reproducible", "exact_share", "writable_share", "avoidable_share",
               "diffused_score", "seconds", "wall_s", "written_s", *[key for key in next(iter(rows.values())) if
                                                     key.startswith("seconds_to_")],
               "peak_memory_mib", "load_average"]
    write_csv(args.out / "bench.csv", columns, rows.values())
    write_csv(args.out / "spread.csv",
              ["schedule", "scan", "n", "mean", "std", "min", "max", "min_significant_difference"],
              [{"schedule": schedule, "scan": name, **values} for (schedule, name), values in spreads.items()])
    for (schedule, name), values in spreads.items():
        print(f"{schedule} {name}: {values['mean']:.6f} ± {values['std']:.1e} (min {values['min']:.6f}, "
              f"max {values['max']:.6f}, n {values['n']}); significant difference > "
              f"{values['min_significant_difference']:.1e}")


def write_summary(out: Path) -> str:
    """``comparison.md`` and ``score_vs_time.png`` from ``out/bench.json`` and the runs' reports; returns the text.

    The text: per run its score, seconds, iterations and what stopped it; with
    several schedules, each one's difference to the first (score, and time as
    a ratio), the global score and the median seconds; seconds to reach each
    score level; and where an iteration's time goes (wall and CPU seconds per
    stage-3 iteration, and the cores busy, CPU / wall, from the reports'
    ``refine_timings_s`` and ``refine_cpu_s``).
    """
    bench = json.loads((out / "bench.json").read_text())
    rows, schedules = bench["runs"], bench.get("schedules", ["default"])
    reports = {run: json.loads((out / f"{run}.report.json").read_text()) for run in rows}
    first = schedules[0]
    lines = ["| scan | seed | " + " | ".join(f"{s} score | {s} s | {s} iterations (stop)" for s in schedules)
             + "".join(f" | {s} − {first} score | {s} / {first} s" for s in schedules[1:]) + " |",
             "|---|---|" + "---|---|---|" * len(schedules) + "---|---|" * (len(schedules) - 1)]
    pairs = {}
    for row in rows.values():
        pairs.setdefault((row["scan"], row["seed"]), {})[row["schedule"] if "schedule" in row else first] = row
    for (scan, seed), by in pairs.items():
        cells = [f"{by[s]['mean']:.6f} | {by[s]['seconds']:.0f} | {by[s]['iterations']} ({by[s].get('stop_reason')})"
                 if s in by else " | | " for s in schedules]
        deltas = [f"{by[s]['mean'] - by[first]['mean']:+.1e} | {by[s]['seconds'] / by[first]['seconds']:.2f}"
                  if s in by and first in by else " | " for s in schedules[1:]]
        lines.append(f"| {scan} | {seed} | " + " | ".join(cells + deltas) + " |")
    for schedule in schedules:
        of = [row for row in rows.values() if row.get("schedule", first) == schedule]
        for seed in sorted({row["seed"] for row in of}):
            runs = [row for row in of if row["seed"] == seed]
            lines.append(f"\n{schedule}, seed {seed}: global score {global_score(runs)[1]:.6f}, median "
                         f"{float(np.median([row['seconds'] for row in runs])):.1f} s inside invert, "
                         f"{float(np.median([row['wall_s'] for row in runs])):.1f} s of process wall time "
                         f"(max {max(row['wall_s'] for row in runs):.1f} s); phantom written "
                         f"{max(row['written_s'] for row in runs):.2f} s after the process started at most; "
                         f"total {sum(row['seconds'] for row in runs):.0f} s over {len(runs)} scans")
    labels = [key[len("seconds_to_"):] for key in next(iter(rows.values())) if key.startswith("seconds_to_")]
    lines += ["", "Seconds from the start of the run until the best exact score reached:", "",
              "| run | " + " | ".join(labels) + " |", "|---|" + "---|" * len(labels)]
    for run, row in rows.items():
        cells = ["–" if row[f"seconds_to_{label}"] is None else f"{row[f'seconds_to_{label}']:.0f}"
                 for label in labels]
        lines.append(f"| {run} | " + " | ".join(cells) + " |")
    whole = [run for run, row in rows.items() if row.get("schedule") == "fixed-length"]
    if whole:
        min_gain = RefineSchedule().min_gain
        lines += ["", f"The default's restart rule (stop after a restart that gains < {min_gain:g}) replayed on "
                  "the fixed-length runs, whose steps it shares up to where it stops:", "",
                  "| run | fixed-length score | s | rule's score | s | difference | time ratio |",
                  "|---|---|---|---|---|---|---|"]
        for run in whole:
            score, seconds = replay_restart_rule(reports[run]["trace"], reports[run]["seconds"]["total"], min_gain)
            row = rows[run]
            lines.append(f"| {run} | {reports[run]['score']:.6f} | {row['seconds']:.0f} | {score:.6f} | "
                         f"{seconds:.0f} | {score - reports[run]['score']:+.1e} | {seconds / row['seconds']:.2f} |")
    for schedule in schedules:
        runs = [run for run, row in rows.items() if row.get("schedule", first) == schedule]
        iterations = sum(reports[run]["iterations"] for run in runs)
        if not iterations or "refine_cpu_s" not in reports[runs[0]]:
            continue
        lines += ["", f"Stage 3 per iteration, {schedule} ({iterations} iterations over {len(runs)} runs):", "",
                  "| part | wall s | CPU s | cores busy |", "|---|---|---|---|"]
        parts = reports[runs[0]]["refine_timings_s"]
        for part in parts:
            wall = sum(reports[run]["refine_timings_s"][part] for run in runs) / iterations
            cpu = sum(reports[run]["refine_cpu_s"][part] for run in runs) / iterations
            lines.append(f"| {part} | {wall:.3f} | {cpu:.3f} | {cpu / wall if wall else 0:.2f} |")
        refine_s = sum(reports[run]["seconds"]["refine"] for run in runs) / iterations
        lines.append(f"| whole iteration (stage 3's wall time / iterations) | {refine_s:.3f} | | |")
    text = "\n".join(lines) + "\n"
    with atomic_write(out / "comparison.md", "w") as handle:
        handle.write(text)
    with atomic_write(out / "score_vs_time.png") as handle:
        handle.write(comparison_plot(rows, reports, schedules))
    with atomic_write(out / "exact_share_vs_time.png") as handle:
        handle.write(exact_share_plot(rows, reports, schedules))
    return text


def restart_stages(trace: list[dict]) -> list[tuple[float, float, float]]:
    """Per restart of a report's ``trace``, in order: (the best exact score before it, the best after it, the
    time of its last entry in seconds)."""
    best, stages = -np.inf, []
    for entry in trace:
        stage = entry["stage"]
        if stage.startswith("restart") and (not stages or stages[-1]["stage"] != stage):
            stages.append({"stage": stage, "before": best})
        if entry.get("score") is not None:
            best = max(best, entry["score"])
        if stages and stages[-1]["stage"] == stage:
            stages[-1].update(after=best, end_s=entry["time_s"])
    return [(float(stage["before"]), float(stage["after"]), float(stage["end_s"])) for stage in stages]


def replay_restart_rule(trace: list[dict], total_s: float, min_gain: float,
                        patience: int = 1) -> tuple[float, float]:
    """(best score, seconds) where a run would have stopped after the first ``patience`` restarts in a row that
    together gained < ``min_gain`` (:attr:`~octcl.host.stage3.schedule.RefineSchedule.restart_patience`).

    ``trace`` is a whole-schedule run's (invert's report): the rule takes the
    same steps up to the end of the last of those restarts, so its score there
    is the run's best so far and its time the trace's time there plus what the
    run spent after its last trace entry (the final writes). Without such
    restarts: the run's own best score and time.
    """
    stages = restart_stages(trace)
    for index, (_, best, end) in enumerate(stages):
        if index + 1 >= patience and best - stages[index + 1 - patience][0] < min_gain:
            return best, end + total_s - trace[-1]["time_s"]
    return float(max((entry["score"] for entry in trace if entry.get("score") is not None), default=-np.inf)), \
        float(total_s)


def comparison_plot(rows: dict, reports: dict, schedules: list[str]) -> bytes:
    """PNG: one panel per scan, the best exact score against seconds of each of its runs."""
    from octcl.host.batch.report import best_so_far

    panels = {}
    for run, row in rows.items():
        label = f"{row.get('schedule', schedules[0])}, seed {row['seed']}"
        panels.setdefault(row["scan"], []).append((*best_so_far(reports[run]["trace"]), label))
    return panels_png(panels, "best exact score", columns=4, panel_size=(3.6, 2.8), markersize=3)


def exact_share_plot(rows: dict, reports: dict, schedules: list[str]) -> bytes:
    """PNG: per scan, the share of pixels off their aimed level after each stage-1 step, against the seconds
    of stage 1 (the report's ``field_candidates``: each step's record), one line per run; the aim step's
    points are where the aim itself moved."""
    panels = {}
    for run, row in rows.items():
        seconds, off = [0.0], [1.0]
        for candidate in reports[run]["settings"].get("field_candidates") or []:
            for step in candidate.get("steps", []):
                seconds.append(seconds[-1] + step["seconds"])
                off.append(max(1.0 - step["identical"], 1e-7) if step["kept"] else off[-1])
        panels.setdefault(row["scan"], []).append((seconds, off, f"{row.get('schedule', schedules[0])}, "
                                                                 f"seed {row['seed']}"))
    return panels_png(panels, "share off its aimed level (1e-7: none)", columns=4, panel_size=(3.6, 2.8),
                      markersize=4, log_y=True)


def panels_png(panels: dict[str, list[tuple]], y_label: str, columns: int, panel_size: tuple[float, float],
               markersize: float, log_y: bool = False) -> bytes:
    """PNG of a grid of panels, ``columns`` wide: per title, lines of (seconds, values, label)."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    columns = min(len(panels), columns)
    rows = -(-len(panels) // columns)
    figure = Figure(figsize=(panel_size[0] * columns, panel_size[1] * rows), dpi=100, layout="constrained")
    axes = figure.subplots(rows, columns, squeeze=False).ravel()
    for panel, (title, lines) in zip(axes, panels.items()):
        for seconds, values, label in lines:
            panel.plot(seconds, values, marker=".", markersize=markersize, label=label)
        panel.set(title=title, xlabel="seconds", ylabel=y_label, yscale="log" if log_y else "linear")
        panel.grid(alpha=0.3)
        panel.legend(fontsize=7)
    for panel in axes[len(panels):]:
        panel.set_visible(False)
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png")
    return buffer.getvalue()


def write_csv(path: Path, columns: list[str], rows) -> None:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(columns)
    for row in rows:
        writer.writerow([row.get(c, "") for c in columns])
    with atomic_write(path, "w") as handle:
        handle.write(buffer.getvalue())


if __name__ == "__main__":
    sys.exit(main())
