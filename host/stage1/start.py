"""Stage 1 of the linear regime: candidate schedules of named steps, the best field kept.

:func:`linear_start` runs candidate schedules of named steps
(:mod:`octcl.host.stage1.solve`): a display fit (the physical regime's stage
1, shortened), :func:`~octcl.host.stage1.projections.retrieve_field`'s projections,
:func:`~octcl.host.stage1.hinge.fit_levels`' hinge fit and the aim step; the best kept; once one renders every pixel at
its aimed level, the others are left out. The aimed levels are the
target's own where the scanner can write them, one level up or down where
it cannot: by error diffusion (:mod:`octcl.host.stage1.ceiling`), then moved
where the exact score gains (:mod:`octcl.host.stage1.aim`).

:func:`least_norm_twin` gives, for the tissue regime's decode, the field of
least norm among those that render what a field renders. The field the
steps find is one of many with its rendering: the operator A (the beam's
lateral weights and the depth kernel) passes little of the finest lateral
detail, and the display fit puts energy there that the rendering does not
show. The tissue decode reads each A-scan line's energy as the light its
tissue takes (:mod:`octcl.host.stage2.tissue`), so that unseen energy is
shadow the target does not ask for.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np

from ...config import DEFAULT_CONFIG, ScannerConfig
from ...render import Rendering
from .backend import Backend, NumpyBackend
from .hinge import fit_levels
from .levels import target_levels
from .projections import LinearFit
from .solve import FieldSchedule, FieldSolve, default_schedules

#: Display-fit steps of the first candidate by default, ``octcl invert``'s in the linear regime; the
#: second candidate, run only where the first does not render every aimed level, has half as many. With the
#: hinge fit (:func:`octcl.host.stage1.hinge.fit_levels`) after the projections, 300, 150 and 75 steps all
#: put every pixel of the nine development scans at its aimed level with the same scores (0.5.0,
#: docs/benchmarks.md); with 0.6.0's faster hinge fit and the aim step, 75 steps took 5.1 s of median wall
#: time against 150's 6.1 s, scored 9.5e−7 less on orange and took 1–2 s more on the two plain skins
#: (docs/benchmarks.md, 0.6.0).
DISPLAY_ITERATIONS = 150
#: Hinge iterations of :func:`least_norm_twin` at most (it stops once every pixel is at its level). On skin 5,
#: 20, 50 and 200 left 63 %, 70 % and 99.1 % of pixels at their level (0.2, 0.55 and 1.9 s on two cores); its
#: per-line energy spread 0.63–1.52 times the median line's (5–95 %) after 200, where the field it came from
#: spread 0.57–1.98 (``scripts/check_tissue_decode.py``, docs/benchmarks.md, "The decode's field").
TWIN_ITERATIONS = 200


@dataclass
class LinearStart:
    """Result of :func:`linear_start`.

    Attributes
    ----------
    field : ndarray of complex128, (Nz, Nx)
        The best candidate's field, scaled so that max|A(F)| = 1.
    schedule : FieldSchedule
        The best candidate's stage-1 schedule.
    aim : ndarray of uint8, (Nz, Nx)
        The levels its field was made to render (its ``aim`` steps' choice).
    candidates : list of dict
        Per candidate tried: ``schedule`` (its text), ``score`` (the exact
        score of the field's own 8-bit rendering, where there were several
        candidates to choose from; else None), ``identical`` (share of
        pixels at the aimed level), ``seconds`` and ``steps`` (what each
        step did, :class:`octcl.host.stage1.solve.StepRecord`).
    seconds : float
    clock_steps : int
        Decisions the clock took: a step cut by the budget, or a planned
        candidate left out because it would not fit.
    threads : int
        CPU threads of the FFTs (timed by the first display fit unless given).
    """

    field: np.ndarray
    schedule: FieldSchedule
    aim: np.ndarray
    candidates: list
    seconds: float
    clock_steps: int
    threads: int


def linear_start(target, score, config: ScannerConfig = DEFAULT_CONFIG, schedules: tuple | None = None,
                 time_budget_s: float | None = None, threads: int | None = None, progress=None,
                 aim: np.ndarray | None = None, backend: Backend | None = None) -> LinearStart:
    """Stage 1 of the linear regime: candidate schedules of named steps, the best field by score.

    Each candidate is a :class:`~octcl.host.stage1.solve.FieldSchedule` run
    by a :class:`~octcl.host.stage1.solve.FieldSolve`; by default
    :func:`~octcl.host.stage1.solve.default_schedules` of
    :data:`DISPLAY_ITERATIONS` display steps (``octcl invert``'s):
    ``display:150,project:50,hinge:200,aim:4``, then the same with 75. Once a
    candidate renders every pixel at its aimed level the others are left
    out; of several, the one whose field renders with the highest
    ``score`` is kept. The display fit puts the dark pixels near their
    levels (its loss is on the logarithmic display) and keeps the field
    close to its rendering in norm (‖F‖/‖A(F)‖ 1.1–2.3 against 3.6–6.6 from
    the regularised inverse); the projections then put most pixels exactly
    at their level, and the hinge fit the rest. Which display length ends
    best varies from scan to scan (the problem is not convex). Measured on
    the development set without the hinge fit (``python
    scripts/bench_linear.py --skin 3``, docs/benchmarks.md, the field's own
    score): of 150, 300 and 600 display steps, 300 was best on 4 of the 7
    scans, 150 on 2 (by 2.3e−4 on Uniform B and 7e−5 on skin_2) and 600 on
    orange (by 8e−6), hence :data:`START_LENGTHS`; 600 projections alone,
    from the regularised inverse, scored 0.99913–0.99987, 2.5e−5 to 7.4e−4
    below the best of the three on every scan. 100 projections after a
    display fit ended within 2e−6 of 600.

    Parameters
    ----------
    target : ndarray
        uint8 levels (Nz, Nx) or a float image (:func:`octcl.host.stage1.levels.target_levels`).
    score : callable
        ``score(levels) -> float``: the exact score of 8-bit levels against the
        target (the mean of :class:`octcl.host.stage3.loss.ExactScore`'s components).
    config : ScannerConfig
    schedules : tuple of FieldSchedule, optional
        The candidates, tried in order; default ``default_schedules(DISPLAY_ITERATIONS)``.
    time_budget_s : float, optional
        The first candidate gets all of it (its steps their shares); a
        later one runs only if its iterations, at the first candidate's
        measured pace, end within it.
    threads : int, optional
        FFT threads of the default backend (:func:`octcl.host.stage1.display.fit_field`; by default timed
        there).
    progress : callable, optional
        ``progress(step, steps)`` over all candidates' iterations.
    aim : ndarray of uint8, optional
        The levels the steps aim at; default the target's own. The
        candidates are still judged by ``score`` against the target.
    backend : NumpyBackend or OpenCLBackend, optional
        Where the steps run (:mod:`octcl.host.stage1.backend`), shared by the candidates; default
        ``NumpyBackend(config, threads)``.

    Returns
    -------
    LinearStart
    """
    start = time.perf_counter()
    schedules = default_schedules(DISPLAY_ITERATIONS) if schedules is None else tuple(schedules)
    backend = NumpyBackend(config, threads) if backend is None else backend
    if not schedules or not all(isinstance(schedule, FieldSchedule) for schedule in schedules):
        raise ValueError("schedules must be one or more FieldSchedule")
    levels = target_levels(target, config)
    aim = levels if aim is None else target_levels(aim, config)
    total = sum(schedule.iterations for schedule in schedules)
    candidates, solves, done, clock_steps, pace = [], [], 0, 0, None

    def elapsed():
        return time.perf_counter() - start

    for schedule in schedules:
        if solves and solves[0].best_identical == 1.0:
            break  # every pixel at its aimed level: another candidate would render the same levels
        if solves and time_budget_s is not None and elapsed() + pace * schedule.iterations > time_budget_s:
            clock_steps += 1
            continue
        began = time.perf_counter()
        solve = FieldSolve(levels, aim, backend, score=score)
        solve.run(schedule, time_budget_s=None if solves or time_budget_s is None else time_budget_s - elapsed(),
                  progress=lambda step, steps, offset=done: progress and progress(offset + step, total))
        clock_steps += solve.clock_steps
        done += schedule.iterations
        candidates.append({"schedule": str(schedule), "score": None, "identical": solve.best_identical,
                           "seconds": time.perf_counter() - began,
                           "steps": [dataclasses.asdict(record) for record in solve.history]})
        solves.append(solve)
        if pace is None:
            pace = candidates[0]["seconds"] / max(1, sum(record.iterations for record in solve.history))
    # Scored only where there is a choice to make: an exact score costs 0.3–1 s, and stage 3 scores the
    # start anyway.
    if len(candidates) > 1:
        for candidate, solve in zip(candidates, solves):
            candidate["score"] = float(score(Rendering.from_a_scans(backend.operator.apply(solve.best_field)).levels))
    chosen = max(range(len(candidates)), key=lambda index: candidates[index]["score"] or 0.0)
    return LinearStart(field=solves[chosen].best_field, schedule=schedules[chosen], aim=solves[chosen].aim,
                       candidates=candidates, seconds=elapsed(), clock_steps=clock_steps,
                       threads=backend.threads or 1)


def least_norm_twin(field: np.ndarray, aim: np.ndarray, backend: Backend, iterations: int = TWIN_ITERATIONS,
                    time_budget_s: float | None = None) -> LinearFit:
    """The field of least norm that renders as ``field`` does, fitted back onto ``aim`` (module docstring).

    F' = A⁺(A(F)), A⁺ the Tikhonov-regularised pseudo-inverse
    (:meth:`~octcl.host.stage1.operator.FieldOperator.pseudo_inverse`), the
    F' minimising ‖A(F') − A(F)‖² + λ·‖F'‖²: F without what A does not pass,
    and with a little of what it passes weakly, so that its rendering moves
    off some levels; the hinge fit (:func:`~octcl.host.stage1.hinge.fit_levels`,
    at most ``iterations``, within ``time_budget_s``) takes it back onto ``aim``.
    """
    operator = backend.operator
    return fit_levels(operator.pseudo_inverse(operator.apply(field)), aim, backend.config, iterations=iterations,
                      time_budget_s=time_budget_s, backend=backend)
