"""Stage 1 of the linear regime as data: named steps, schedules of them, and the solve that runs one.

As in PyNX's operators (Favre-Nicolin et al., "PyNX: high-performance
computing toolkit for coherent X-ray imaging based on operators",
J. Appl. Cryst. 53, 2020), the algorithm is a value a user composes, not
code: ``display(150) + project(50) + hinge(200)`` is the default, and
``FieldSchedule.parse("display:150,project:50,hinge:200")`` the same from
``octcl invert --field-schedule``. One :class:`FieldSolve` carries a run's
state (the field, the aimed levels, the backend its steps run on) and its history; one
step (:data:`STEPS`) is a function apart from the loop that runs them.

Steps, each from the field the previous one left (the first from the
regularised inverse of the de-logged target with zero phase):

- ``display``: :func:`octcl.host.stage1.display.fit_field`, Adam on the display
  loss: puts the dark pixels near their levels and keeps the field's norm
  near its rendering's.
- ``project``: :func:`octcl.host.stage1.projections.retrieve_field`, accelerated
  projections onto the aimed levels' intervals: most pixels onto their level.
- ``hinge``: :func:`octcl.host.stage1.hinge.fit_levels`, L-BFGS on the squared
  distance to the intervals, the brightest pixel pinned: the last pixels.
- ``aim``: :class:`octcl.host.stage1.aim.AimSearch`, rounds that move unwritable
  pixels of the aim to their other side where the exact score gains; from a
  field at its aim, which then follows the aim kept
  (:meth:`FieldSolve.reach`).

Each step is written once and runs its loop on the solve's backend
(:attr:`FieldSolve.backend`, :mod:`octcl.host.stage1.backend`): NumPy on the
host (the reference, ``--backend numpy``) or OpenCL kernels on a device;
the field passes between steps on the host, once per step.

Rules the loop keeps: the result is the best field any step left
(:attr:`FieldSolve.best_field`; a step that leaves fewer pixels at their
aimed level than it does not replace it, its record says ``kept: False``),
each step goes on from the field the last one left, and while every pixel
is at its aimed level the field steps are skipped. Under a time budget each
step gets its ``share`` of the time left when it starts (the last all of
it): display 1/2, project :data:`PROJECTION_SHARE` of the rest, hinge the
rest.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np

from ...render import Rendering
from .aim import AimSearch
from .backend import Backend
from .display import fit_field
from .hinge import LEVEL_FIT_ITERATIONS, fit_levels
from .projections import regularised_start, retrieve_field

#: Under a time budget, the projections' share of what the display fit before them leaves (the hinge fit
#: gets the rest). With ``--time-budget 3`` (Uniform B, skin_0, orange in one process) 1/3, 1/2 and 0.7
#: gave 0.96263/0.99999/0.99990, 0.98773/1.00000/0.99990 and 0.99437/0.99997/0.99990; with 5 s all
#: were within 7e−6 of each other (docs/benchmarks.md).
PROJECTION_SHARE = 0.5
#: Each step's share of the time left when it starts, unless the step says otherwise (module docstring).
DEFAULT_SHARES = {"display": 0.5, "project": PROJECTION_SHARE, "hinge": 1.0, "aim": 0.7}
#: Rounds of the default schedules' aim step (:func:`default_schedules`).
DEFAULT_AIM_ROUNDS = 4
#: Projections, then hinge iterations at most, for the field to follow the aim step's moves (a few tens of
#: pixels, two levels each; the fit stops once every pixel is at its new level). On orange.png, 16, 32 and
#: 64 moved pixels took the hinge fit alone 80–90 iterations (0.6–0.8 s on two cores); after 20
#: projections (0.1 s), 10 (0.1 s); after 5, 50–60 (``scripts/bench_aim.py``).
AIM_PROJECTIONS = 20
AIM_HINGE_ITERATIONS = 100
#: Seconds the aim step keeps for the field to follow its aim (:meth:`FieldSolve.reach`, 0.2 s above).
AIM_REACH_S = 0.5

#: Display-fit lengths of :func:`~octcl.host.stage1.start.linear_start`'s candidates, as multiples of its
#: first display fit's steps. A third at 2× won on one scan of seven by 8e−6 and cost
#: about 5 s (:func:`~octcl.host.stage1.start.linear_start`).
START_LENGTHS = (1.0, 0.5)
#: Projection steps after each display fit in :func:`~octcl.host.stage1.start.linear_start`. Once every pixel is
#: at its aimed level the score no longer depends on how the field got there, so the count is chosen by the time
#: stage 1 takes to get there. On 43 real-like targets (orange.png, it mirrored and through a gamma of 0.9, plainly
#: quantised skin renderings, seeds 0–39; ``python scripts/bench_field_schedules.py``, two Zen 4 cores)
#: ``display:150,project:50,hinge:200`` took 57.2 s in all (median 1.20 s, longest 2.24 s) against 65.0 s
#: (1.43 s, 2.35 s) with 100 projections, every pixel at its aim on all 43 either way; shorter display fits or
#: 70 projections after 120 display steps took 52–53 s but left 1–2 targets off their aim, which sends a run to
#: its second candidate. The projections' second 50 steps raised their share at the aim on 25 targets and lowered
#: it on 18, and saved the hinge fit 7 of its 47 iterations on average (median 30 either way): 0.4 s of
#: projections for 0.07 s of hinge (docs/benchmarks.md, "Stage 1's projections").
START_PROJECTIONS = 50


@dataclass(frozen=True)
class FieldStep:
    """``iterations`` of one named step (:data:`STEPS`); ``share`` of the time left when it starts.

    ``a + b`` is the schedule that runs a, then b.
    """

    name: str
    iterations: int
    share: float | None = None

    def __post_init__(self):
        if self.name not in STEPS:
            raise ValueError(f"unknown stage-1 step {self.name!r}; the steps are {', '.join(STEPS)}")
        if not (isinstance(self.iterations, int) and self.iterations >= 1):
            raise ValueError(f"step {self.name}: iterations must be a whole number ≥ 1, got {self.iterations!r}")
        if self.share is not None and not 0 < self.share <= 1:
            raise ValueError(f"step {self.name}: share must be in (0, 1], got {self.share!r}")

    @property
    def time_share(self) -> float:
        return DEFAULT_SHARES[self.name] if self.share is None else self.share

    def __add__(self, other) -> "FieldSchedule":
        return FieldSchedule((self,)) + other

    def __str__(self) -> str:
        return f"{self.name}:{self.iterations}"


@dataclass(frozen=True)
class FieldSchedule:
    """Steps run in order by :meth:`FieldSolve.run`."""

    steps: tuple

    def __post_init__(self):
        if not self.steps or not all(isinstance(step, FieldStep) for step in self.steps):
            raise ValueError("a stage-1 schedule is one or more steps")

    def __add__(self, other) -> "FieldSchedule":
        more = (other,) if isinstance(other, FieldStep) else other.steps
        return FieldSchedule(self.steps + tuple(more))

    @property
    def iterations(self) -> int:
        return sum(step.iterations for step in self.steps)

    @property
    def display_iterations(self) -> int:
        """Steps of the display fits (the ``--field-iterations`` of a default schedule)."""
        return sum(step.iterations for step in self.steps if step.name == "display")

    def __str__(self) -> str:
        return ",".join(str(step) for step in self.steps)

    @classmethod
    def parse(cls, text: str) -> "FieldSchedule":
        """``"display:150,project:100,hinge:200"``: NAME:ITERATIONS, comma-separated, in order."""
        steps = []
        for part in str(text).split(","):
            name, _, count = part.strip().partition(":")
            if not count.strip().isdigit():
                raise ValueError(f"stage-1 schedule {text!r}: {part.strip()!r} is not NAME:ITERATIONS "
                                 f"(e.g. display:150,project:100,hinge:200)")
            steps.append(FieldStep(name.strip(), int(count)))
        return cls(tuple(steps))


def display(iterations: int, share: float | None = None) -> FieldStep:
    """A display fit of ``iterations`` Adam steps (module docstring)."""
    return FieldStep("display", iterations, share)


def project(iterations: int, share: float | None = None) -> FieldStep:
    """``iterations`` accelerated projections onto the aimed intervals (module docstring)."""
    return FieldStep("project", iterations, share)


def aim(rounds: int, share: float | None = None) -> FieldStep:
    """Up to ``rounds`` rounds choosing the sides of the unwritable levels for the score (module docstring)."""
    return FieldStep("aim", rounds, share)


def hinge(iterations: int, share: float | None = None) -> FieldStep:
    """At most ``iterations`` L-BFGS iterations of the hinge fit (module docstring)."""
    return FieldStep("hinge", iterations, share)


@dataclass
class StepRecord:
    """What one step did: :attr:`FieldSolve.history`."""

    name: str
    iterations: int    # taken
    identical: float   # share of pixels at their aimed level after it
    seconds: float
    clock_steps: int   # 1 where the time budget cut it short
    kept: bool         # False: fewer pixels at their aim than the best field, which stays the result


@dataclass
class FieldSolve:
    """One stage-1 run: the target's levels, the levels aimed at, the field so far and the history.

    Parameters
    ----------
    levels : ndarray of uint8, (Nz, Nx)
        The target's levels.
    aim : ndarray of uint8, (Nz, Nx)
        The levels to render (:func:`octcl.host.stage1.ceiling.aimed_levels`).
    backend : NumpyBackend or OpenCLBackend
        Where the field steps run (:mod:`octcl.host.stage1.backend`): its
        ``config`` is the scanner's; a NumPy backend's FFT threads are timed
        by the first display fit unless it was given them.
    score : callable, optional
        ``score(levels) -> float``, the exact score against the target: the
        ``aim`` step's judge (:class:`octcl.host.stage1.aim.AimSearch`).
    aim_search : AimSearch, optional
        The ``aim`` step's search; by default a new
        :class:`~octcl.host.stage1.aim.AimSearch` of ``levels`` and ``score``.

    Attributes
    ----------
    field, identical
        The field the last step left, and its share of pixels at their aimed level.
    best_field, best_identical
        The field with the highest share so far (since the aim last moved): the solve's result.
    history : list of StepRecord
    """

    levels: np.ndarray
    aim: np.ndarray
    backend: Backend
    score: object = None
    field: np.ndarray | None = None
    identical: float = 0.0
    best_field: np.ndarray | None = None
    best_identical: float = 0.0
    history: list = dataclasses.field(default_factory=list)
    aim_search: object = None

    @property
    def config(self):
        """The scanner's configuration (the backend's)."""
        return self.backend.config

    def start_field(self) -> np.ndarray:
        """The field before any step: the regularised inverse of the de-logged target, zero phase."""
        return regularised_start(self.levels, self.backend.operator)

    def fit_levels(self, field: np.ndarray, aim: np.ndarray, iterations: int, budget_s: float | None = None):
        """The hinge fit of ``field`` onto ``aim`` (:func:`octcl.host.stage1.hinge.fit_levels`) on this solve's
        backend."""
        return fit_levels(field, aim, self.config, iterations=iterations, time_budget_s=budget_s,
                          backend=self.backend)

    def reach(self, levels: np.ndarray, field: np.ndarray) -> np.ndarray | None:
        """A field that renders ``levels`` exactly, from ``field`` (which renders levels a few pixels apart), or
        None where it does not get there: :data:`AIM_PROJECTIONS` projections onto the new levels' intervals,
        then at most :data:`AIM_HINGE_ITERATIONS` iterations of the hinge fit (it stops once every pixel is
        at its level)."""
        projected = retrieve_field(self.levels, self.config, iterations=AIM_PROJECTIONS, initial=field, aim=levels,
                                   backend=self.backend)
        fit = self.fit_levels(projected.field, levels, AIM_HINGE_ITERATIONS)
        return fit.field if fit.identical == 1.0 else None

    def share_at_aim(self, field_now: np.ndarray) -> float:
        """Share of pixels the field renders at their aimed level."""
        return float(np.mean(Rendering.from_a_scans(self.backend.operator.apply(field_now)).levels == self.aim))

    def run(self, schedule: FieldSchedule, time_budget_s: float | None = None, progress=None) -> "FieldSolve":
        """Run ``schedule``'s steps in order (module docstring); returns ``self``.

        ``progress(iteration, iterations)`` over the schedule's iterations.
        """
        start = time.perf_counter()
        done = 0
        for index, step in enumerate(schedule.steps):
            if step.name != "aim" and self.identical == 1.0:
                done += step.iterations
                continue  # every pixel at its aimed level: no field step can gain
            last = index == len(schedule.steps) - 1
            budget = None if time_budget_s is None else \
                max(0.0, (1.0 if last else step.time_share) * (time_budget_s - (time.perf_counter() - start)))

            def step_progress(taken, planned, offset=done):
                if progress is not None:
                    progress(offset + min(taken, planned), schedule.iterations)

            began = time.perf_counter()
            self.field, taken, clock_steps = STEPS[step.name](self, step.iterations, budget, step_progress)
            self.identical = self.share_at_aim(self.field)
            # The best field is kept apart: a step that leaves fewer pixels at their level than it does not
            # replace it, though the next step goes on from where this one ended (projections cut short by
            # the clock pass through fewer pixels on their way to more). The aim step changes what counts.
            kept = self.best_field is None or self.identical >= self.best_identical or step.name == "aim"
            if kept:
                self.best_field, self.best_identical = self.field, self.identical
            self.history.append(StepRecord(step.name, taken, self.identical, time.perf_counter() - began,
                                           clock_steps, kept))
            done += step.iterations
        return self

    @property
    def clock_steps(self) -> int:
        return sum(record.clock_steps for record in self.history)


def _display_step(solve: FieldSolve, iterations: int, budget_s, progress):
    fit = fit_field(solve.levels, solve.config, iterations=iterations, time_budget_s=budget_s,
                    initial=solve.field, backend=solve.backend,
                    progress=lambda taken, planned, loss: progress(taken, planned))
    return fit.field, fit.iterations, min(fit.clock_steps, 1)


def _project_step(solve: FieldSolve, iterations: int, budget_s, progress):
    fit = retrieve_field(solve.levels, solve.config, iterations=iterations, time_budget_s=budget_s,
                         initial=solve.field, aim=solve.aim, progress=progress, backend=solve.backend)
    return fit.field, fit.iterations, fit.clock_steps


def _hinge_step(solve: FieldSolve, iterations: int, budget_s, progress):
    start = solve.start_field() if solve.field is None else solve.field
    fit = solve.fit_levels(start, solve.aim, iterations, budget_s)
    progress(fit.iterations, iterations)
    return fit.field, fit.iterations, fit.clock_steps


def _aim_step(solve: FieldSolve, rounds: int, budget_s, progress):
    """Up to ``rounds`` rounds of :class:`octcl.host.stage1.aim.AimSearch` on ``solve.aim``, then the field
    follows the last aim kept (:meth:`FieldSolve.reach`; an earlier one where it cannot).

    Nothing to do (and no torch) for a target without unwritable levels.
    Under a budget a round starts only while it, at the rounds' measured
    pace (:meth:`~octcl.host.stage1.aim.AimSearch.rounds`), and the field's reach
    (:data:`AIM_REACH_S`) end within it. The rounds judge levels only, but
    they run here, after the field steps, not beside them on a thread: on
    two cores that made the default run 1–2 s slower (docs/benchmarks.md,
    "The aim's rounds beside the field steps: measured, not kept").
    """
    if solve.score is None:
        raise ValueError("the aim step needs the exact score (FieldSolve's score)")
    if solve.aim_search is None:
        solve.aim_search = AimSearch(solve.levels, solve.score)
    if solve.aim_search.done or solve.best_identical < 1.0:  # nothing to move, or no field at its aim
        return solve.field, 0, 0
    deadline = None if budget_s is None else time.perf_counter() + budget_s - AIM_REACH_S
    done = solve.aim_search.rounds(solve.aim, rounds, deadline, progress)
    solve.field = solve.best_field
    for aimed in reversed(done.kept[1:]):
        field = solve.reach(aimed, solve.field)
        if field is not None:
            solve.aim, solve.field = aimed, field
            break
    return solve.field, done.taken, done.clock_steps


#: The steps by name: ``function(solve, iterations, budget_s, progress) -> (field, iterations taken, clock steps)``.
STEPS = {"display": _display_step, "project": _project_step, "hinge": _hinge_step, "aim": _aim_step}


def default_schedules(display_iterations: int, aim_rounds: int = DEFAULT_AIM_ROUNDS) -> tuple:
    """The linear regime's stage-1 candidates, tried in order (:func:`octcl.host.stage1.start.linear_start`):
    ``display(N) + project(START_PROJECTIONS) + hinge(200) + aim(aim_rounds)``, then the same with
    N/2 display steps (:data:`START_LENGTHS`). The aim step does nothing on a target without unwritable
    levels; with ``aim_rounds`` 0 there is none, and the aim is the error-diffused one."""
    schedules = []
    for length in START_LENGTHS:
        schedule = display(max(1, round(length * display_iterations))) + project(START_PROJECTIONS) \
            + hinge(LEVEL_FIT_ITERATIONS)
        schedules.append(schedule + aim(aim_rounds) if aim_rounds else schedule)
    return tuple(schedules)


__all__ = ["AIM_HINGE_ITERATIONS", "AIM_PROJECTIONS", "AIM_REACH_S", "DEFAULT_SHARES", "PROJECTION_SHARE", "FieldSchedule", "FieldSolve", "FieldStep",
           "STEPS", "StepRecord", "aim", "default_schedules", "display", "hinge", "project"]
