"""Where the aim step's time goes (host/stage1/aim.py), part by part, on targets with unwritable levels.

For each target: stage 1 up to its aim (display, projections, hinge fit on
the OpenCL device), then, timed one by one in this process, torch's
import, the exact score's and the loss's construction, exact scores, the
loss's gradient (the proposal), and the rounds of
:class:`octcl.host.stage1.aim.AimSearch` with each one's gain and whether
it was kept; last, the field's reach of the aim the rounds kept, by the
hinge fit alone and by :meth:`octcl.host.stage1.solve.FieldSolve.reach`
(projections, then the hinge fit). Prints a table per target.

With ``--singles N``, the first N pixels of the first round's proposal are
then moved one at a time from the error-diffused aim: each one's predicted
change of the loss (g_p·ΔD_p), its exact change of the score and of each of
the eight components: what the gradient's ranking gets right and which
map's term it misses.

Example::

    python scripts/bench_aim.py ../shared/data/real/orange.png OUT/targets/plain_skin_0.png --rounds 4 --singles 4
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from octcl.config import DEFAULT_CONFIG
from octcl.host.pipeline.target import read_target
from octcl.host.stage1.aim import AimSearch
from octcl.host.stage1.backend import make_backend
from octcl.host.stage1.ceiling import WRITABLE, aimed_levels
from octcl.host.stage1.levels import display_of_level, target_levels
from octcl.host.stage1.solve import AIM_HINGE_ITERATIONS, FieldSolve, default_schedules
from octcl.host.stage1.start import DISPLAY_ITERATIONS


def timed(function, *args):
    start = time.perf_counter()
    value = function(*args)
    return value, time.perf_counter() - start


def single_moves(search: AimSearch, exact, aim: np.ndarray, count: int) -> None:
    """Print the first ``count`` pixels of ``search``'s proposal from ``aim`` moved one at a time: the predicted
    change of the loss and the exact change of the score and of each component."""
    base = exact(aim)
    proposed, picks = search.proposal(aim)
    predicted = search.predicted_change(aim)
    print(f"  single moves (first {min(count, picks.size)} of the first round's {picks.size}):")
    for pick in picks[:count]:
        moved = aim.copy()
        moved.flat[pick] = proposed.flat[pick]
        components = exact(moved)
        row, column = divmod(int(pick), aim.shape[1])
        changes = " ".join(f"{name.replace('one_minus_', '1-')} {components[name] - base[name]:+.1e}"
                           for name in components if name != "mean")
        print(f"    ({row},{column}) level {aim.flat[pick]}->{proposed.flat[pick]}: predicted {predicted[pick]:+.2e}, "
              f"score {components['mean'] - base['mean']:+.2e}; {changes}")


def bench(path: Path, rounds: int, first: bool, singles: int = 0) -> None:
    target = read_target(path)
    levels = target_levels(target, DEFAULT_CONFIG)
    aim = aimed_levels(levels)
    solve = FieldSolve(levels, aim, make_backend("opencl", DEFAULT_CONFIG))
    _, seconds = timed(solve.run, default_schedules(DISPLAY_ITERATIONS, aim_rounds=0)[0])
    print(f"\n{path.name}: unwritable pixels {np.mean(~WRITABLE[levels]):.3%}, stage 1 to its aim {seconds:.2f} s, "
          f"at its aim {solve.best_identical:.4%}")
    rows = []
    if first:
        rows.append(("import torch", timed(__import__, "torch")[1], ""))
    from octcl.host.stage1.aim import SCORE_WEIGHTS
    from octcl.host.stage3.loss import DisplayLoss, ExactScore, scan_of_levels

    exact, seconds = timed(ExactScore, target)
    rows.append(("ExactScore(target)", seconds, "maps, LPIPS network, target features"))
    for _ in range(2):
        base, seconds = timed(exact, aim)
        rows.append(("exact score", seconds, f"{base['mean']:.7f}"))
    loss, seconds = timed(DisplayLoss, scan_of_levels(levels), SCORE_WEIGHTS)
    rows.append(("DisplayLoss(target)", seconds, ""))
    for _ in range(2):
        rows.append(("gradient (proposal)", timed(loss, display_of_level()[aim])[1], ""))
    search = AimSearch(levels, lambda image: exact(image)["mean"])
    current, current_score = aim, base["mean"]
    for round_ in range(rounds):
        if search.done:
            break
        (kept, score), seconds = timed(search.step, current, current_score)
        moved = kept is not current
        rows.append((f"round {round_ + 1}", seconds,
                     f"{'kept' if moved else 'rejected'}, score {score - current_score:+.2e}"))
        current, current_score = kept, score
    if current is not aim:
        fit, seconds = timed(solve.fit_levels, solve.best_field, current, AIM_HINGE_ITERATIONS)
        rows.append(("reach: hinge fit alone", seconds, f"{fit.iterations} iterations, at the aim {fit.identical:.4%}"))
        field, seconds = timed(solve.reach, current, solve.best_field)
        rows.append(("reach: projections + hinge fit", seconds, "reached" if field is not None else "not reached"))
    rows.append(("score: aim kept against error-diffused", 0.0, f"{current_score - base['mean']:+.2e}"))
    for name, seconds, note in rows:
        print(f"  {name:<40} {seconds:7.3f} s  {note}")
    if singles:
        single_moves(AimSearch(levels, lambda image: exact(image)["mean"]), exact, aim, singles)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("targets", nargs="+", type=Path, help="target B-scans (PNG or .npy of levels)")
    parser.add_argument("--rounds", type=int, default=4, help="aim rounds at most (default 4, invert's)")
    parser.add_argument("--singles", type=int, default=0,
                        help="then move the first round's first N pixels one at a time (default 0: none)")
    args = parser.parse_args(argv)
    for index, path in enumerate(args.targets):
        bench(path, args.rounds, first=index == 0, singles=args.singles)


if __name__ == "__main__":
    main()
