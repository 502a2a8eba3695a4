"""Compare stage-3 variants from the same starting phantom: exact score against seconds.

``bench_invert.py`` compares whole inversions, whose stages 1–2 and clock
decisions differ from run to run. To ask what a change to stage 3 buys per
second (a cheaper loss, LPIPS less often), this runs stages 1–2 once per
scan (fixed schedule, ``--threads``) and then each variant's stage 3 from
that same phantom, one after the other in one process, at the same thread
count, with the same compiled kernels and the same exact scorer. Each
variant runs the default schedule's first ``--iterations`` steps without
adaptive stopping, with an exact evaluation every ``--score-every`` steps
(each costs the same in every variant). ``--from-iterations M`` starts the
variants instead from the best phantom of the default's first M steps, and
runs the steps after them (lower learning rates past step 160): what a
variant does late in the run.

Variants (:data:`VARIANTS`): ``default``; ``lpips-every-K``, the LPIPS
terms' gradient computed on every K-th step and reused between
(:attr:`octcl.host.stage3.refine.RefineSchedule.lpips_every`); ``no-lpips``, the
loss without its LPIPS terms; ``oac-lpips-only``, the loss without the
Struct, SC and RSC LPIPS terms (OAC's has 8× their weight);
``no-fall-guard``, the main run never goes back to its best phantom when it
falls (:attr:`octcl.host.stage3.refine.RefineSchedule.max_falls` 0);
``long-steps`` and ``long-steps-no-fall-guard``, the main run's learning
rates ``LONG_STEPS`` times the default's, with and without that guard (a
scene the default's steps are too long for).

Writes, in ``--out``: ``SCAN_stage2.txt`` (and ``SCAN_after_M.txt``), reused
when present; ``refine.json`` (every variant's trace and timings);
``refine_comparison.md`` (per scan and variant: seconds per step and the
loss's share of them, final
best score and its difference to ``default``, the best score by the time
the fastest variant ended, the seconds to reach ``default``'s final
best − 1e−4, and the steps after which the main run fell);
``refine_score_vs_time.png`` (per scan, each variant's iterate scores
against seconds). ``--summarise`` writes the last two again
from ``refine.json``.

Example::

    python scripts/bench_refine.py --scans orange Scan_Exp1_Uniform_A --iterations 60 --out OUT
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path


from bench_invert import development_set, panels_png
from octcl._io import atomic_write
from octcl.host.pipeline.invert import invert
from octcl.host.stage3.loss import ExactScore
from octcl.host.stage3.refine import RefineSchedule, refine
from octcl.host.pipeline.target import read_target
from octcl.phantom import Phantom

#: The main run's learning rates in the ``long-steps`` variants, times the default's.
LONG_STEPS = 4.0
#: Variant name → the change it makes to a schedule.
VARIANTS = {
    "default": lambda schedule: schedule,
    **{f"lpips-every-{k}": (lambda schedule, k=k: dataclasses.replace(schedule, lpips_every=k)) for k in (2, 3)},
    "no-lpips": lambda schedule: dataclasses.replace(
        schedule, phases=tuple(dataclasses.replace(p, terms="no_lpips") for p in schedule.phases),
        restarts=tuple(dataclasses.replace(p, terms="no_lpips") for p in schedule.restarts)),
    "oac-lpips-only": lambda schedule: dataclasses.replace(
        schedule, loss_weights=dataclasses.replace(schedule.loss_weights, struct_lpips=0.0, sc_lpips=0.0,
                                                   rsc_lpips=0.0)),
    "no-fall-guard": lambda schedule: dataclasses.replace(schedule, max_falls=0),
    "long-steps": lambda schedule: longer_steps(schedule, LONG_STEPS),
    "long-steps-no-fall-guard": lambda schedule: dataclasses.replace(longer_steps(schedule, LONG_STEPS), max_falls=0),
}


def longer_steps(schedule: RefineSchedule, factor: float) -> RefineSchedule:
    """``schedule`` with its main run's learning rates times ``factor``: a scene its steps are too long for."""
    return dataclasses.replace(schedule, phases=tuple(
        dataclasses.replace(p, lr_z_um=factor * p.lr_z_um, lr_u=factor * p.lr_u) for p in schedule.phases))


def after_steps(schedule: RefineSchedule, steps: int) -> RefineSchedule:
    """``schedule`` with the first ``steps`` steps of its main run removed (its phases from there on)."""
    phases, left = [], steps
    for phase in schedule.phases:
        skipped = min(left, phase.iterations)
        left -= skipped
        if phase.iterations > skipped:
            phases.append(dataclasses.replace(phase, iterations=phase.iterations - skipped))
    if left:
        raise ValueError(f"the main run has only {steps - left} steps, not {steps}")
    return dataclasses.replace(schedule, phases=tuple(phases))


def seconds_to(trace: list[dict], level: float) -> float | None:
    """Seconds from the start until an exact evaluation first reached ``level`` (None: never)."""
    return next((entry["time_s"] for entry in trace if entry["score"] is not None and entry["score"] >= level), None)


def best_by(trace: list[dict], seconds: float) -> float:
    """The best exact score of the evaluations made within ``seconds``."""
    return max(entry["score"] for entry in trace if entry["score"] is not None and entry["time_s"] <= seconds)


def summary_lines(results: dict) -> list[str]:
    """The markdown table of ``refine_comparison.md``, one row per scan and variant."""
    lines = ["| scan | variant | s / step | loss s / step | final best | − default | best by the fastest's end | "
             "s to default's best − 1e−4 | falls after step |", "|---|---|---|---|---|---|---|---|---|"]
    for scan, by_variant in results.items():
        default = by_variant["default"]["best"]
        fastest_end = min(run["trace"][-1]["time_s"] for run in by_variant.values())
        for variant, run in by_variant.items():
            reached = seconds_to(run["trace"], default - 1e-4)
            steps = max(run["iterations"], 1)
            lines.append(f"| {scan} | {variant} | {run['trace'][-1]['time_s'] / steps:.2f} | "
                         f"{run['timings_s']['loss'] / steps:.2f} | {run['best']:.6f} | {run['best'] - default:+.1e} | "
                         f"{best_by(run['trace'], fastest_end):.6f} | "
                         f"{'never' if reached is None else f'{reached:.0f}'} | "
                         f"{', '.join(map(str, run.get('falls', []))) or '–'} |")
    return lines


def plot(results: dict) -> bytes:
    """PNG: per scan, each variant's iterate scores against seconds."""
    panels = {scan: [(*zip(*[(e["time_s"], e["score"]) for e in run["trace"] if e["score"] is not None]), variant)
                     for variant, run in by_variant.items()] for scan, by_variant in results.items()}
    return panels_png(panels, "exact score", columns=3, panel_size=(4.2, 3.0), markersize=4)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scans", nargs="+", default=["Scan_Exp1_Uniform_A", "Scan_Exp2_Layers_A", "orange"],
                        help="development-set scans (bench_invert.py's names; skin_N renders Phantom.skin(N))")
    parser.add_argument("--variants", nargs="+", choices=list(VARIANTS), default=list(VARIANTS))
    parser.add_argument("--iterations", type=int, default=60, help="stage-3 steps of each variant (default 60)")
    parser.add_argument("--from-iterations", type=int, default=0, metavar="M",
                        help="start from the best phantom of the default's first M steps (default 0: stage 2)")
    parser.add_argument("--score-every", type=int, default=10, help="steps between exact evaluations (default 10)")
    parser.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    parser.add_argument("--seed", type=int, default=0, help="stage 2's seed (default 0)")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--summarise", action="store_true",
                        help="run nothing: write refine_comparison.md and the plot again from --out's refine.json")
    args = parser.parse_args(argv)
    if args.summarise:
        saved = json.loads((args.out / "refine.json").read_text())
        print(write_summary(args.out, saved["settings"], saved["results"]))
        return 0
    if "default" not in args.variants:
        parser.error("--variants must include default (the others are compared with it)")
    args.out.mkdir(parents=True, exist_ok=True)
    skin = max((int(name[5:]) + 1 for name in args.scans if name.startswith("skin_")), default=0)
    targets = development_set(args.out, skin)
    missing = [name for name in args.scans if name not in targets]
    if missing:
        parser.error(f"unknown or missing scans: {', '.join(missing)} (have {', '.join(targets)})")

    from octcl.device.scanner import ScannerKernels

    kernels = ScannerKernels()
    base = RefineSchedule(score_every=args.score_every).fixed_length()
    results = {}
    for name in args.scans:
        target = read_target(targets[name])
        exact_score = ExactScore(target)
        start_path = args.out / f"{name}_stage2.txt"
        if not start_path.exists():
            invert(target, start_path, time_budget_s=3600, seed=args.seed, iterations=0, threads=args.threads)
        start = Phantom.load(start_path)
        if args.from_iterations:
            later_path = args.out / f"{name}_after_{args.from_iterations}.txt"
            if not later_path.exists():
                refine(start, target, RefineSchedule().fixed_length().truncated(args.from_iterations),
                       kernels=kernels, exact_score=exact_score, threads=args.threads).phantom.save(later_path)
            start = Phantom.load(later_path)
        schedule = after_steps(base, args.from_iterations)
        results[name] = {}
        for variant in args.variants:
            result = refine(start, target, VARIANTS[variant](schedule).truncated(args.iterations), kernels=kernels,
                            exact_score=exact_score, threads=args.threads)
            results[name][variant] = {"best": result.components["mean"], "iterations": result.iterations,
                                      "falls": result.falls,
                                      "initial": result.initial_components["mean"], "trace": result.trace,
                                      "timings_s": result.timings_s, "cpu_s": result.cpu_s}
            print(f"{name} {variant}: {result.initial_components['mean']:.6f} → {result.components['mean']:.6f} "
                  f"in {result.trace[-1]['time_s']:.0f} s, falls after steps {result.falls}", flush=True)
    settings = {key: (str(value) if isinstance(value, Path) else value) for key, value in vars(args).items()
                if key not in ("out", "summarise")}
    with atomic_write(args.out / "refine.json", "w") as handle:
        json.dump({"settings": settings, "results": results}, handle, indent=1)
    print(write_summary(args.out, settings, results))
    return 0


def write_summary(out: Path, settings: dict, results: dict) -> str:
    """``refine_comparison.md`` and ``refine_score_vs_time.png`` in ``out``; returns the text."""
    text = "\n".join([f"Settings: {json.dumps(settings)}", "", *summary_lines(results)]) + "\n"
    with atomic_write(out / "refine_comparison.md", "w") as handle:
        handle.write(text)
    with atomic_write(out / "refine_score_vs_time.png", "wb") as handle:
        handle.write(plot(results))
    return text


if __name__ == "__main__":
    sys.exit(main())
