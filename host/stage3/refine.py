"""Stage 3: refine every scatterer's depth and energy by Adam on the scorer-aligned loss.

The unknowns are, per scatterer j, the depth z_j (µm) and u_j = ln E_j (E in
%); x_j and y_j stay where stage 2 put them. One iteration is

1. render: ``ScannerKernels.set_phantom`` (host sort into depth order and
   lateral bins) → ``forward(for_adjoint=True)`` (complex A-scans) →
   :meth:`octcl.render.Rendering.from_a_scans` (display D, 8-bit levels);
2. the loss and ∂loss/∂D (:class:`octcl.host.stage3.loss.DisplayLoss`);
3. back to the scatterers: :func:`octcl.render.display_vjp` (∂loss/∂A) →
   ``ScannerKernels.adjoint`` (∂loss/∂u_j, ∂loss/∂z_j);
4. an Adam step (Kingma & Ba, "Adam: a method for stochastic optimization",
   ICLR 2015) on (z, u), then the constraints 0 ≤ z ≤ Nz·Δz and
   ln E_floor ≤ u ≤ ln 100.

A phase of :data:`~octcl.host.stage3.schedule.HINGE` terms takes L-BFGS
iterations instead, on the levels' hinge (:mod:`octcl.host.stage3.hinge`,
:class:`_HingeRun`): each counts as a step, and is scored and timed as one.

Adam divides each parameter's step by the root mean square of its own
gradient, so a learning rate is a step length in the parameter's own unit:
``lr_z_um`` in µm and ``lr_u`` in nepers of energy (a step of 0.01 in u
changes E by 1 %). The carrier phase turns by 2·k0 ≈ 9.67 rad per µm of
depth (a full turn every 0.65 µm), so useful depth steps are thousandths of
a µm. Measured from stages 1–2 of orange.png (exact score 0.97746; 40 or
150 iterations, full loss):

- lr_z_um 0.02 / 0.01 / 0.005 / 0.002 / 0.001 (lr_u 0.05 for 20
  iterations, then 0.02): 0.99437 (40) / 0.99655 (40) / 0.99889 / 0.99936 /
  0.99922 (150); lr_z_um = 0 (energies only): 0.99913 (150) — most of the
  gain is in the energies, the depths add the rest;
- lr_u 0.1 then 0.03: 0.99877; a constant lr_u 0.02 with lr_z_um 0.005:
  0.99887 at 40 iterations, then falling;
- past ~160 iterations at those rates the score falls although the loss
  keeps falling (0.99927 → 0.99881 at 300); from the best phantom, 60 more
  iterations at (lr_z_um, lr_u) = (0.002, 0.02) / (0.001, 0.01) /
  (0.0005, 0.005) / (0, 0.01) gave 0.99912 / 0.99937 / 0.99943 / 0.99931
  (from 0.99920), hence the default's lower rates after 160 iterations.

Adaptive stopping (:attr:`RefineSchedule.min_gain`, ``patience``). The
exact score of the iterates is noisy: along the main run at lr_z_um 0.002
it moves by ±1e−4 to ±4e−4 between checkpoints 20 iterations apart, and the
best so far keeps rising by such jumps long after the loss has flattened.
Measured on the development set with the whole 400-iteration schedule and
with a stall rule on the main run (``python scripts/bench_invert.py --seeds
0 --skin 3 --schedules fixed-length stall-rule``, one run per scan; tables
in ``docs/benchmarks.md``, "Adaptive stopping"):

- orange.png: the main run's best came at iteration 120–140 and the next
  140–160 iterations never beat it; the restarts from that best phantom
  gained 2.6e−5 to 2.9e−4 each;
- Uniform A: a plateau from iteration 40 to 260 (0.99849–0.99863), then
  0.99887 at 280, the main run's last checkpoint; neither restart gained;
- Uniform B: new bests up to iteration 260 in jumps of up to 4e−4 after
  plateaus of 40–60 iterations; neither restart gained.

The stall rule (``patience`` 2 checkpoints without a gain of 1e−5, then the
restarts) cannot tell Uniform A's or B's plateaus from orange's: it took
0.54 of the time (median) with a global score as high, but ended Uniform
A 2.3e−4 and Uniform B 1.3e−4 below the whole schedule, and one run per
scan cannot tell whether that is its cost or the noise. So the main run
keeps its length by default (``patience=None``). What the data do support:
a restart that does not beat its parent was followed by one that did not
either (or gained < 6e−6), while restarts that gained were followed by
gains. Hence the default ``min_gain`` = 1e−5: the first restart that gains
less ends the refinement. On those runs it saves the last restart (13–14 %
of the run) on five of the seven scans, at most 5.4e−6 of score. Where the
main run stops early (``patience``, or a schedule whose restarts are
shorter than the iterations the main run left), the last restart is
repeated while each gains, so a scene that still gains keeps its
iterations.

A phase may end before its length (:attr:`Phase.patience`): the tissue
regime's pixel phases, whose exact score on orange.png peaked at step 40
and then fell while the hinge after them climbs at once
(host/pipeline/invert.py, ``TISSUE_PIXEL_PATIENCE``).

Falls (:attr:`RefineSchedule.max_falls`). One default run of Uniform A in
eight fell 2.1e−3 below the others: its first 20 steps took the exact score
from 0.99605 down to 0.99592 (the RSC map broke), and the main run went on
from there. A main run that scores below its start, or 1e−3 below its best,
now goes back to its best phantom at half the learning rates. From the
same stage-2 phantoms (``python scripts/bench_refine.py --scans
Scan_Exp1_Uniform_A Scan_Exp1_Uniform_B Scan_Exp2_Layers_A orange skin_0
--variants default no-fall-guard long-steps long-steps-no-fall-guard
--iterations 100 --score-every 20``, docs/benchmarks.md):

- the default fell only on skin_0 (step 20: −8e−5 under its start, a dip
  that the next checkpoint recovers either way) and ended within 8e−7 of
  the unguarded run; on the other four scans it never fell, bit for bit
  the same run;
- with every main-run step 4× longer (a scene the default's steps are too
  long for), the unguarded runs ended 2.9e−4 to 3.0e−3 below the default;
  the guarded ones fell after step 20, 40 or 80 and ended 2.1e−4 to
  5.4e−4 above the unguarded (within 2.6e−4 of the default, but orange).

At checkpoints every 10 steps the first checkpoint falls in the default
too (Uniform A and Layers A dip below their start at step 10 and are far
above it at 20), so the guard is meant for the default's spacing of 20.

The loss only stands in for the score, so progress is judged by the exact
score (:class:`octcl.host.stage3.loss.ExactScore`, the mean of the eight official
components of the rendered 8-bit scan). It is evaluated at checkpoints, and
the refinement returns the best phantom it has scored. Restarts (fresh Adam
moments at a lower learning rate, from the best phantom so far) keep the
best of the parent and their own checkpoints, as in the published schedule.

Everything stops at a deadline (``time.monotonic()``), checked before every
iteration and every exact evaluation against their measured durations. Without
one (a fixed schedule, :meth:`RefineSchedule.truncated`), or before it, no
decision depends on the clock: the result depends only on the inputs, the
schedule and the device, at any thread count (``docs/reproducibility.md``).

Cost on two CPU cores (PoCL), 280k scatterers, idle machine: 0.76 s an
iteration — set_phantom 0.12 s, forward 0.09 s, loss 0.40 s (two threads),
adjoint 0.09 s, Adam 0.007 s — and 0.7 s per exact evaluation; under a load
of 4–7 other processes about twice that. The 400 iterations of the default
schedule take some 310 s idle: 0.99900 → 0.99964 on Scan_Exp2_Layers_A and
0.99245 → 0.99950 on orange.png, most of the gain within 150 s.
"""

from __future__ import annotations

import math
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from octcl.config import DEFAULT_CONFIG, ScannerConfig
from octcl.phantom import SIGNIFICANT_DIGITS, Phantom, round_significant
from octcl.render import Rendering, display_vjp

from ..optim.adam import Adam
from ..threads import available_cores
from ..optim import lbfgs
from ..pipeline.target import target_scan
from ..stage1.levels import target_levels
from .hinge import HINGE_MAX_HALVINGS, HINGE_MEMORY, HingeUnknowns, LevelHinge
from .schedule import FALL_LR_FACTOR, HINGE, MAX_ENERGY_PCT, SINGLE_TERM_PHASES, STOP_RULES, Phase, RefineSchedule

if TYPE_CHECKING:
    from .loss import DisplayLoss, ExactScore



@dataclass
class Checkpoint:
    """A scored phantom: the depths and log-energies with their exact score and the levels it scored."""

    z_um: np.ndarray
    log_energy: np.ndarray
    components: dict | None  # None: the input, its score left out (:meth:`_Run.score_input`)
    stage: str
    iteration: int
    levels: np.ndarray

    @property
    def score(self) -> float:
        return -math.inf if self.components is None else self.components["mean"]


@dataclass(frozen=True)
class RefineProgress:
    """What :func:`refine` tells its ``progress`` callback.

    Attributes
    ----------
    stage : str
        ``refine`` (the main run) or ``restart N``.
    iterations, total : int
        Adam steps taken so far (restarts included) and in the schedule.
    score : float
        The last exact score measured.
    score_time : float
        ``time.monotonic()`` when it was measured.
    best_score : float
        The best exact score so far (the phantom a checkpoint holds).
    """

    stage: str
    iterations: int
    total: int
    score: float
    score_time: float
    best_score: float


@dataclass
class RefineResult:
    """What :func:`refine` returns.

    Attributes
    ----------
    phantom : Phantom
        The best phantom scored (the input's x and y, refined z and E).
    components : dict or None
        Its eight exact components and their ``mean``; None where the
        deadline left no time to score the input and nothing else ran
        (:meth:`_Run.score_input`).
    initial_components : dict or None
        Those of the input phantom (None as above).
    iterations : int
        Adam steps taken, restarts included.
    trace : list of dict
        Per iteration: ``time_s`` (since the start of :func:`refine`),
        ``stage``, ``iteration``, ``loss`` and ``score`` (None where not
        evaluated).
    timings_s : dict
        Total seconds in each part of the iteration (``set_phantom``,
        ``forward``, ``loss``, ``adjoint``, ``adam``, ``exact_score``).
    cpu_s : dict
        The process's CPU seconds (all its threads: OpenCL's, torch's, the
        checkpoint writer's) during each of those parts; cpu_s / timings_s
        is the number of cores busy in a part.
    stopped_by_deadline : bool
        The deadline cut the schedule short.
    stop_reason : str
        What ended the refinement: ``schedule`` (its phases and restarts, or
        ``max_iterations``, ran out), ``converged`` (a restart gained less
        than :attr:`RefineSchedule.min_gain`), ``target score``,
        ``ceiling`` (the input renders the aimed levels: :func:`refine`'s
        ``aim``) or ``deadline``.
    torch_threads : int
        CPU threads the loss ran with at the end (:class:`_ThreadChooser`).
    falls : list of int
        The Adam steps (restarts included, as ``iterations`` counts them)
        after which the main run fell and went back to the best phantom
        (:attr:`RefineSchedule.max_falls`).
    levels : ndarray of uint8
        The 8-bit levels of the best phantom's rendering, the ones its
        ``components`` score.
    """

    phantom: Phantom
    components: dict
    initial_components: dict
    iterations: int
    trace: list
    timings_s: dict
    cpu_s: dict
    stopped_by_deadline: bool
    stop_reason: str
    torch_threads: int
    falls: list
    levels: np.ndarray


def check_target_score(target_score) -> None:
    """Raise ValueError unless ``target_score`` is None or a score in (0, 1]."""
    if target_score is not None and not (isinstance(target_score, (int, float)) and 0 < target_score <= 1):
        raise ValueError(f"target_score must be a score in (0, 1], got {target_score!r}")


def saved_precision(values: np.ndarray) -> np.ndarray:
    """``values`` as the phantom file holds them: rounded to ``SIGNIFICANT_DIGITS`` as :meth:`Phantom.save` writes them."""
    return round_significant(values, SIGNIFICANT_DIGITS)


class TimeBudgetExceeded(RuntimeError):
    """A run with a fixed schedule reached its time ceiling before the schedule's end."""


class RefineClock:
    """Deadline bookkeeping: does an operation of measured duration still fit?

    Without a deadline everything fits, and no decision depends on the clock;
    a ``ceiling`` is then only a safety limit: :meth:`check_ceiling` raises
    past it.
    """

    def __init__(self, deadline: float | None, ceiling: float | None = None):
        self.deadline = math.inf if deadline is None else deadline
        self.ceiling = math.inf if ceiling is None else ceiling
        self.durations: dict[str, float] = {}

    def check_ceiling(self, where: str) -> None:
        if time.monotonic() > self.ceiling:
            raise TimeBudgetExceeded(f"the time budget ran out {where}")

    def seconds_left(self) -> float:
        return self.deadline - time.monotonic()

    def fits(self, *operations: str) -> bool:
        """True if the operations' measured durations end before the deadline."""
        return sum(self.durations.get(name, 0.0) for name in operations) <= self.seconds_left()

    def record(self, name: str, seconds: float, longest: bool = False) -> None:
        """Keep ``seconds`` as the duration of ``name``: the last measured, or with ``longest`` the longest so far
        (an operation whose cost varies from call to call)."""
        self.durations[name] = max(seconds, self.durations.get(name, 0.0)) if longest else seconds


def _set_torch_threads(count: int) -> None:
    """torch's thread count, where torch is in use: a refinement that ends at its first score of a phantom
    rendering its target exactly never imports it (:func:`refine`, the caller's ``exact_score``)."""
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(count)


class _FixedThreads:
    """torch's thread count held at ``threads`` for the whole refinement (reproducible runs)."""

    def __init__(self, threads: int):
        self.threads = threads

    def before_call(self) -> None:
        _set_torch_threads(self.threads)

    def after_call(self, kind, seconds: float) -> None:
        pass


class _ThreadChooser:
    """torch's thread count for the loss: one or all cores, chosen by timing real calls.

    On an idle machine all cores are faster, but when other processes hold
    the cores every OpenMP barrier waits for a descheduled thread (measured
    here under load: the full loss took 0.57 s with one thread and 5.7–7.7 s
    with two, and a run that had picked two threads while the machine was
    idle spent 8 s a call once it was not). So: calls 2–5 alternate between
    one thread and all cores (the first warms up) and the faster is kept;
    with all cores kept, a call slower than ``SLOWDOWN`` times the last
    one-thread call of the same loss falls back to one thread, and all cores
    are tried again ``RETRY_CALLS`` calls later.
    """

    SLOWDOWN = 1.5
    RETRY_CALLS = 40

    def __init__(self, cores: int):
        self.cores = cores
        self.threads = cores if cores > 1 else 1
        self._plan = [self.threads, 1, cores, 1, cores] if cores > 1 else []
        self._seconds: dict[tuple, float] = {}  # (loss kind, threads) → last call
        self._calls, self._retry_at = 0, None
        self._trial = False

    def before_call(self) -> None:
        self._trial = bool(self._plan) or self._retry_at == self._calls
        current = self._plan[0] if self._plan else (self.cores if self._trial else self.threads)
        _set_torch_threads(current)
        self._current = current

    def after_call(self, kind, seconds: float) -> None:
        first = self._calls == 0
        self._calls += 1
        if self._plan:
            self._plan.pop(0)
        if not first:
            self._seconds[kind, self._current] = seconds
        one_thread = self._seconds.get((kind, 1), math.inf)
        if self._trial and not self._plan:  # end of a timing round: keep the faster
            self.threads = self.cores if self._seconds.get((kind, self.cores), math.inf) < one_thread else 1
        elif self._current == self.cores and seconds > self.SLOWDOWN * one_thread:
            self.threads = 1
        if self.threads == 1 and self.cores > 1 and (self._retry_at is None or self._retry_at < self._calls):
            self._retry_at = self._calls + self.RETRY_CALLS


class _Refiner:
    """Rendering, loss, gradients and exact scores of one phantom's (z, u)."""

    def __init__(self, x_um, y_um, kernels, scan, exact_score, schedule, config, clock, threads, pixel_scan=None):
        self.x_um, self.y_um = x_um, y_um
        self.kernels, self.exact_score, self.schedule = kernels, exact_score, schedule
        self.depth_um = config.depth_range_um
        self.scan, self._losses = scan, {}
        self.pixel_scan = scan if pixel_scan is None else pixel_scan
        self.clock = clock
        self.timings = dict.fromkeys(("set_phantom", "forward", "loss", "adjoint", "adam", "exact_score"), 0.0)
        self.cpu_seconds = dict.fromkeys(self.timings, 0.0)
        self.threads = _ThreadChooser(available_cores()) if threads is None else _FixedThreads(threads)

    def loss(self, terms: str) -> "DisplayLoss":
        """The loss with a phase's terms (:attr:`~octcl.host.stage3.schedule.Phase.terms`), built at its first use.

        Building one with LPIPS terms costs 0.4–0.9 s (the network and the
        target's maps and features; a loss builds only what its weighted terms
        compare), so a refinement that the deadline ends after its first exact
        evaluation (``octcl invert --time-budget 10``) builds none. The pixel or
        the level term alone (:data:`~octcl.host.stage3.schedule.SINGLE_TERM_PHASES`)
        compares with :attr:`pixel_scan`: the aimed levels where :func:`refine`
        has them (its docstring).
        """
        if terms not in self._losses:
            from .loss import DisplayLoss

            self._losses[terms] = DisplayLoss(self.pixel_scan if terms in SINGLE_TERM_PHASES else self.scan,
                                              self.schedule.loss_weights.for_terms(terms))
        return self._losses[terms]

    def _timed(self, name, function, *args, **kwargs):
        start, cpu_start = time.perf_counter(), time.process_time()
        result = function(*args, **kwargs)
        self.timings[name] += time.perf_counter() - start
        self.cpu_seconds[name] += time.process_time() - cpu_start
        return result

    def render(self, z_um, log_energy, for_adjoint: bool) -> Rendering:
        start = time.perf_counter()
        self._timed("set_phantom", self.kernels.set_phantom, self.x_um, self.y_um, z_um, log_energy)
        a_scans = self._timed("forward", self.kernels.forward, for_adjoint=for_adjoint)
        rendering = Rendering.from_a_scans(a_scans)
        self.clock.record("render", time.perf_counter() - start)
        return rendering

    def gradients(self, rendering: Rendering, terms: str, lpips_mode: str = "compute"):
        """(loss value, ∂loss/∂u, ∂loss/∂z) of the last :meth:`render` (with for_adjoint).

        ``terms`` chooses the loss (:meth:`loss`); ``lpips_mode`` is
        :class:`DisplayLoss`'s ``lpips`` argument (``compute`` for a loss
        without LPIPS terms).
        """
        self.threads.before_call()
        start = time.perf_counter()
        value = self._timed("loss", self.loss(terms), rendering.display, lpips_mode)
        self.threads.after_call((terms, lpips_mode), time.perf_counter() - start)
        grad_u, grad_z = self.adjoint(display_vjp(rendering, value.grad_display))
        return value, grad_u, grad_z

    def adjoint(self, a_scan_bar: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(∂loss/∂u, ∂loss/∂z) of the last :meth:`render` (with for_adjoint), given Ā = ∂loss/∂Re A + i·∂loss/∂Im A."""
        return self._timed("adjoint", self.kernels.adjoint, a_scan_bar)

    def score(self, rendering: Rendering) -> dict:
        start = time.perf_counter()
        components = self._timed("exact_score", self.exact_score, rendering.levels)
        # A memoised score (the pipeline's) answers an image it has seen at once; the clock plans the next
        # evaluation with what computing one took (its ``seconds``), not with the look-up.
        computed_s = getattr(self.exact_score, "seconds", 0.0)
        self.clock.record("score", max(time.perf_counter() - start, computed_s))
        return components

    def step(self, adam: Adam, params, grads, lrs) -> None:
        """An Adam step on (z, u), projected back onto the constraints."""
        self._timed("adam", adam.step, params, grads, lrs)
        self.constrain(*params)

    def constrain(self, z_um, log_energy) -> None:
        """Project onto 0 ≤ z ≤ Nz·Δz and ln E_floor ≤ u ≤ ln 100, in place."""
        np.clip(z_um, 0.0, self.depth_um, out=z_um)
        np.clip(log_energy, self.schedule.min_log_energy, math.log(MAX_ENERGY_PCT), out=log_energy)

    def round_as_saved(self, z_um, log_energy) -> None:
        """Put z and E on the grid of the phantom file (``SIGNIFICANT_DIGITS``, 8), in place.

        A scored iterate is exactly what a checkpoint writes, so its score is
        the file's. With the 6 digits written before, the file's last digit
        at z ≥ 1000 µm was 0.01 µm, a carrier phase step of 0.097 rad, and
        rounding moved a refined phantom's score by up to 7e−5 when it was
        scored before rounding; with 8 it is 1e−4 µm, below the smallest
        depth step of the schedule.
        """
        z_um[:] = saved_precision(z_um)
        log_energy[:] = np.log(np.minimum(saved_precision(np.exp(log_energy)), MAX_ENERGY_PCT))
        self.constrain(z_um, log_energy)


def refine(phantom: Phantom, target: np.ndarray, schedule: RefineSchedule = RefineSchedule(),
           deadline: float | None = None, kernels=None, config: ScannerConfig = DEFAULT_CONFIG,
           progress=None, on_improvement=None, exact_score: "ExactScore | None" = None,
           ceiling: float | None = None, threads: int | None = None,
           target_score: float | None = None, aim: np.ndarray | None = None,
           score_by: float | None = None) -> RefineResult:
    """Refine depths and energies of ``phantom`` towards the target scan.

    Parameters
    ----------
    phantom : Phantom
        The starting phantom (stage 2); its x and y are kept. Energies of 0
        start at the energy floor e^{min_log_energy}.
    target : ndarray of uint8
        The target B-scan (256×512) in either form of :mod:`octcl.host.pipeline.target`.
    schedule : RefineSchedule
        Phases, restarts, checkpoints and Adam settings.
    deadline : float, optional
        ``time.monotonic()`` value by which :func:`refine` returns. An
        iteration or exact evaluation starts only if its last measured
        duration ends before it; the input phantom's own evaluation runs
        unless ``score_by`` leaves it out. Without one, the schedule runs to
        its end and no decision is taken from the clock.
    kernels : octcl.device.scanner.ScannerKernels, optional
        Reuse compiled kernels (built for ``config`` if not given).
    config : ScannerConfig
    progress : callable, optional
        ``progress(RefineProgress)`` after the input phantom's evaluation,
        after each iteration and after the final evaluation.
    on_improvement : callable, optional
        ``on_improvement(phantom, components)`` whenever the best exact score
        improves on the best so far (the input phantom's at first).
    exact_score : callable, optional
        ``exact_score(levels)`` → the components and their ``mean``:
        :class:`ExactScore` of the target (the default), or one that
        builds it at first use (:func:`octcl.host.pipeline.invert.invert`'s).
    ceiling : float, optional
        ``time.monotonic()`` value past which :class:`TimeBudgetExceeded` is
        raised (checked before every iteration): a safety limit for runs
        without a deadline.
    threads : int, optional
        torch's thread count for the whole refinement (loss and exact
        scores). By default it is chosen by timing (:class:`_ThreadChooser`);
        either way it changes the speed, not the result.
    target_score : float, optional
        Stop as soon as an exact evaluation reaches this score (in (0, 1]).
    aim : ndarray of uint8, optional
        The levels the start was made to render (stage 1's aim,
        :func:`octcl.host.stage1.ceiling.aimed_levels`): the phases of the
        pixel term alone (``terms`` ``pixel``) compare the rendering with
        these levels, not the target's: a level the scanner never writes
        cannot be reached, and a pixel term pulling towards it took orange.png
        further from its best after 60–80 steps (docs/benchmarks.md, "The pixel
        phase aims at the aimed levels"). If the input phantom
        renders every pixel at its aimed level, nothing is refined
        (``stop_reason`` ``ceiling``): every pixel the scanner can write is
        then at the target's level, and each unwritable one on the side
        chosen for it.
    score_by : float, optional
        ``time.monotonic()`` value by which the input phantom's exact score
        must end (default: ``deadline``): where ``exact_score`` tells its
        cost (``exact_score.cost_s(levels)``, the pipeline's does) and the
        score would end later, it is left out and nothing else runs
        (the result's ``components`` None). A caller whose deadline keeps
        time for a last write that will not come (a phantom at its aim)
        passes a later one.

    Returns
    -------
    RefineResult

    Notes
    -----
    Without ``threads`` the loss (torch) runs with one thread or with all
    cores, whichever is faster at the time (:class:`_ThreadChooser`); the
    caller's setting is restored on return. Unless the ``deadline`` ends
    it, the result depends only on the inputs, the schedule and the device
    (``docs/reproducibility.md``).

    Raises
    ------
    TimeBudgetExceeded
        Past ``ceiling``.
    ValueError
        ``target_score`` outside (0, 1].
    """
    started = time.monotonic()
    plan = _Plan.checked(target, schedule, deadline, kernels, config, progress, on_improvement, exact_score,
                         ceiling, threads, target_score, aim, deadline if score_by is None else score_by)
    run = _Run(plan, phantom, started)
    with _callers_torch_threads():
        run.score_input()
        if not run.stop_reason:
            run.main_run()
        run.restarts()
    return run.result()


@contextmanager
def _callers_torch_threads():
    """Give torch back the caller's thread count on leaving, where torch was in use before."""
    torch = sys.modules.get("torch")
    previous_threads = None if torch is None else torch.get_num_threads()
    try:
        yield
    finally:
        if previous_threads is not None:
            torch.set_num_threads(previous_threads)


@dataclass(frozen=True)
class _Plan:
    """What :func:`refine` was asked to run, checked and completed with its defaults."""

    schedule: RefineSchedule
    scan: np.ndarray               # the target in the loss's form (:func:`target_scan`)
    kernels: object                # octcl.device.scanner.ScannerKernels
    exact_score: object            # levels → the components and their ``mean``
    config: ScannerConfig
    deadline: float | None
    ceiling: float | None
    threads: int | None            # None: chosen by timing (:class:`_ThreadChooser`)
    target_score: float | None
    aim: np.ndarray | None
    levels: np.ndarray             # what a hinge phase fits: the aim where given, else the target's levels
    score_by: float | None         # the input's score ends by then, or is left out
    progress: object               # callable or None
    on_improvement: object         # callable or None

    @classmethod
    def checked(cls, target, schedule, deadline, kernels, config, progress, on_improvement, exact_score, ceiling,
                threads, target_score, aim, score_by) -> _Plan:
        """The arguments checked (:func:`refine`'s Raises) before the kernels and the scorer are built."""
        check_target_score(target_score)
        if kernels is None:
            from octcl.device.scanner import ScannerKernels

            kernels = ScannerKernels(config)
        if exact_score is None:
            from .loss import ExactScore

            exact_score = ExactScore(target)
        levels = target_levels(target if aim is None else aim, config)
        return cls(schedule, target_scan(target), kernels, exact_score, config, deadline, ceiling, threads,
                   target_score, aim, levels, score_by, progress, on_improvement)


class _Run:
    """One :func:`refine` run's state: its clock, iterate, best checkpoint, progress and trace, and its steps.

    The steps, in order: :meth:`score_input`, :meth:`main_run` (unless the
    input already ended the refinement), :meth:`restarts`, :meth:`result`.
    ``stop_reason`` is None until something other than the schedule's end
    stops the refinement.
    """

    def __init__(self, plan: _Plan, phantom: Phantom, started: float):
        self.plan, self.started = plan, started
        self.clock = RefineClock(plan.deadline, plan.ceiling)
        self.x_um, self.y_um = saved_precision(phantom.x_um), saved_precision(phantom.y_um)
        self.refiner = _Refiner(self.x_um, self.y_um, plan.kernels, plan.scan, plan.exact_score, plan.schedule,
                                plan.config, self.clock, plan.threads,
                                None if plan.aim is None else target_scan(plan.aim))
        self.z_um = np.array(phantom.z_um, dtype=np.float64)
        with np.errstate(divide="ignore"):  # E = 0 gives u = −∞, then the energy floor
            self.log_energy = np.log(phantom.energy_pct)
        self.refiner.constrain(self.z_um, self.log_energy)
        self.refiner.round_as_saved(self.z_um, self.log_energy)
        self.total = plan.schedule.total_iterations
        self.iterations = 0            # Adam steps so far, restarts included
        self.trace, self.falls = [], []  # falls: the steps after which the main run went back to the best
        self.stop_reason = None
        self.initial = self.best = None  # the input's components; the best Checkpoint
        self.last_score = None         # (score, time.monotonic()) of the last exact evaluation

    def as_phantom(self, z_um, log_energy) -> Phantom:
        # A copy: the iterate changes in place while a writer thread may hold
        # the phantom; exp(ln 100) can round to just above 100.
        return Phantom(self.x_um, self.y_um, z_um.copy(), np.minimum(np.exp(log_energy), MAX_ENERGY_PCT))

    def check_ceiling(self, stage: str) -> None:
        self.clock.check_ceiling(f"in stage 3 ({stage}) after {self.iterations} of {self.total} iterations")

    def report(self, stage: str) -> None:
        if self.plan.progress:
            self.plan.progress(RefineProgress(stage, self.iterations, self.total, *self.last_score,
                                              self.best.score))

    def log(self, stage: str, iteration: int, score: float | None = None, now: float | None = None) -> dict:
        """Append a trace entry (the loss is filled in once computed) and return it."""
        now = time.monotonic() if now is None else now
        entry = {"time_s": now - self.started, "stage": stage, "iteration": iteration, "loss": None, "score": score}
        self.trace.append(entry)
        return entry

    def consider(self, components: dict, stage: str, iteration: int, z_um, log_energy, levels) -> None:
        """Keep (z, u) and its rendering's ``levels`` if it beats the best, then :meth:`check_target`."""
        self.last_score = (components["mean"], time.monotonic())
        if components["mean"] > self.best.score:
            self.best = Checkpoint(z_um.copy(), log_energy.copy(), components, stage, iteration, levels)
            if self.plan.on_improvement:
                self.plan.on_improvement(self.as_phantom(z_um, log_energy), components)
        self.check_target()

    def check_target(self) -> None:
        """Stop everything once the best score has reached the target score."""
        if self.plan.target_score is not None and self.best.score >= self.plan.target_score:
            self.stop_reason = "target score"

    def score_input(self) -> None:
        """The input phantom's exact score: the first checkpoint.

        Where the score's ``cost_s(levels)`` (a scorer that can tell, such
        as the pipeline's) would end past ``score_by``, the score is left
        out and nothing else runs: stop_reason ``ceiling`` where the input
        renders the aimed levels, else ``deadline``. A time budget is the
        process's (``--time-budget``): the first score of a run imports
        torch and builds the LPIPS network, 1.4 s on two cores.
        """
        self.refiner.threads.before_call()  # exact scores, the first included, at the loss's thread count
        rendering = self.refiner.render(self.z_um, self.log_energy, for_adjoint=False)
        at_aim = self.plan.aim is not None and np.array_equal(rendering.levels, self.plan.aim)
        cost_s = getattr(self.plan.exact_score, "cost_s", None)
        if self.plan.score_by is not None and cost_s is not None and \
                time.monotonic() + cost_s(rendering.levels) > self.plan.score_by:
            self.best = Checkpoint(self.z_um.copy(), self.log_energy.copy(), None, "initial", 0, rendering.levels)
            self.stop_reason = "ceiling" if at_aim else "deadline"
            self.log("initial", 0)
            return
        self.initial = self.refiner.score(rendering)
        self.best = Checkpoint(self.z_um.copy(), self.log_energy.copy(), self.initial, "initial", 0, rendering.levels)
        if at_aim:
            self.stop_reason = "ceiling"
        self.last_score = (self.initial["mean"], time.monotonic())
        self.log("initial", 0, self.initial["mean"], now=self.last_score[1])
        self.report("refine")
        self.check_target()

    def main_run(self) -> None:
        """The schedule's phases from the input, guarded against falls; scored every ``score_every`` steps."""
        schedule = self.plan.schedule
        length = sum(phase.iterations for phase in schedule.phases)
        checkpoints = set(range(schedule.score_every, length, schedule.score_every))
        stalled = _Descent(self, "refine", schedule.phases, self.z_um, self.log_energy, checkpoints,
                           guarded=True).run()
        if stalled and not schedule.restarts:
            self.stop_reason = "converged"

    def restarts(self) -> None:
        """The restarts in order, each from the best phantom so far with fresh moments.

        With adaptive stopping the last is repeated while they gain, until
        the iterations the main run left are spent; the refinement ends once
        the last ``restart_patience`` restarts together gained less than
        ``min_gain`` over the best score before the first of them.
        """
        schedule, parents = self.plan.schedule, []
        while self._restart_due(len(parents)):
            restart = schedule.restarts[min(len(parents), len(schedule.restarts) - 1)]
            parents.append(self.best.score)
            _Descent(self, f"restart {len(parents)}", (restart,), self.best.z_um.copy(),
                     self.best.log_energy.copy(), {restart.iterations // 2}).run()
            if (schedule.min_gain is not None and not self.stop_reason and len(parents) >= schedule.restart_patience
                    and self.best.score - parents[-schedule.restart_patience] < schedule.min_gain):
                self.stop_reason = "converged"

    def _restart_due(self, done: int) -> bool:
        """Whether another restart runs after ``done`` of them."""
        schedule = self.plan.schedule
        return bool(schedule.restarts) and not self.stop_reason and self.iterations < self.total and (
            schedule.min_gain is not None or done < len(schedule.restarts))

    def result(self) -> RefineResult:
        best = self.best
        return RefineResult(phantom=self.as_phantom(best.z_um, best.log_energy), components=best.components,
                            initial_components=self.initial, iterations=self.iterations, trace=self.trace,
                            timings_s=dict(self.refiner.timings), cpu_s=dict(self.refiner.cpu_seconds),
                            stopped_by_deadline=self.stop_reason == "deadline",
                            stop_reason=self.stop_reason or "schedule", torch_threads=self.refiner.threads.threads,
                            falls=self.falls, levels=best.levels)


def _loss_adjoint_operation(lpips_mode: str) -> str:
    """The clock's name for a step's loss and adjoint: its duration depends on what LPIPS does."""
    return f"loss_adjoint {lpips_mode}"


class _Descent:
    """One Adam run from one iterate (the main run or a restart): its steps, checkpoints and moments.

    It scores the iterate after the step counts in ``checkpoints`` and at its
    end; a ``guarded`` run goes back to the best phantom when it falls
    (:attr:`RefineSchedule.max_falls`). ``z_um`` and ``log_energy`` change in place.
    """

    def __init__(self, refinement: _Run, stage: str, phases, z_um, log_energy, checkpoints, guarded=False):
        self.refinement, self.stage, self.schedule = refinement, stage, refinement.plan.schedule
        self.z_um, self.log_energy = z_um, log_energy
        self.checkpoints, self.guarded = checkpoints, guarded
        # The steps of these phases that the schedule's iteration count still allows.
        allowed = refinement.total - refinement.iterations
        self.steps = [phase for phase in phases for _ in range(phase.iterations)][:allowed]
        self.adam = self._fresh_adam()
        self.start_score, self.lr_scale = refinement.best.score, 1.0
        self.best_after = [refinement.best.score]  # the best score at the start and after each checkpoint
        self.lpips_kept_at = None  # the step whose LPIPS gradient the loss keeps (lpips_every > 1)
        self.stalled = False
        self.phase_ended = False  # the phase's patience ran out at the last checkpoint (Phase.patience)
        self.scored_after = None  # the step count whose iterate was scored last

    def _fresh_adam(self) -> Adam:
        shapes = (self.z_um.shape, self.log_energy.shape)
        return Adam(shapes, self.schedule.beta1, self.schedule.beta2, self.schedule.epsilon)

    def run(self) -> bool:
        """Take the steps; True when the run stalled (:attr:`RefineSchedule.patience`).

        A stalled run, or one that set the refinement's ``stop_reason`` at a
        checkpoint, returns there without scoring again; one the deadline
        stops scores its last iterate if that still fits. The iterate a hinge
        phase begins from is scored where its step is a checkpoint: the hinge
        scores after its own iterations, and on a skin its first ones score
        below the Adam phase before it (docs/benchmarks.md, "The iterate a
        hinge phase starts from is scored"); a rounded copy is scored, and the
        hinge starts from the iterate as it was.
        """
        step = 0
        while step < len(self.steps):
            phase = self.steps[step]
            self.refinement.check_ceiling(self.stage)
            if phase.terms == HINGE:
                if step in self.checkpoints:  # the iterate the hinge starts from: where the phase before it ended
                    self._score_end(step)
                step = _HingeRun(self, step, phase.relative_exponent).run(self._phase_end(step) - step)
                if self.refinement.stop_reason == "deadline":
                    self._score_end(step)
                    return False
                if self.refinement.stop_reason or self.stalled:
                    return self.stalled
                self.adam = self._fresh_adam()  # the moments are those of an iterate the hinge has moved from
                continue
            lpips_mode = self._lpips_mode(step, phase)
            if not self.refinement.clock.fits("render", _loss_adjoint_operation(lpips_mode), "adam", "render", "score"):
                self.refinement.stop_reason = "deadline"
                self._score_end(step)
                return False
            if not self._take_step(step, phase, lpips_mode):
                return self.stalled
            if self.phase_ended:  # scored here and stalled: the next phase from this iterate, without a step
                self.phase_ended = False
                step = self.scored_after = self._phase_end(step)
                continue
            step += 1
        self.refinement.check_ceiling(self.stage)
        self._score_end(len(self.steps))
        return False

    def _lpips_mode(self, step: int, phase: Phase) -> str:
        """What the loss does with its LPIPS terms at this step (:class:`DisplayLoss`'s ``lpips``)."""
        if not (phase.lpips and self.schedule.lpips_every > 1):
            self.lpips_kept_at = None  # the next LPIPS step computes and keeps afresh
            return "compute"
        if self.lpips_kept_at is None or step - self.lpips_kept_at >= self.schedule.lpips_every:
            self.lpips_kept_at = step
            return "keep"
        return "reuse"

    def _take_step(self, step: int, phase: Phase, lpips_mode: str) -> bool:
        """Render (and score, at a checkpoint) the iterate, then an Adam step; False where the run stops."""
        refiner = self.refinement.refiner
        # Timed under the mode the deadline check read, even where a fall changes it.
        operation = _loss_adjoint_operation(lpips_mode)
        scored = (step in self.checkpoints and step > 0 and step != self.scored_after
                  and self.refinement.clock.fits("score"))
        if scored:
            refiner.round_as_saved(self.z_um, self.log_energy)
        rendering = refiner.render(self.z_um, self.log_energy, for_adjoint=True)
        entry = self.refinement.log(self.stage, step)
        if scored:
            components = self._score(rendering, step, entry)
            if self.refinement.stop_reason or self.stalled:
                self.refinement.report(self.stage)
                return False
            fallen = self._has_fallen(components["mean"])
            if fallen:
                lpips_mode = self._go_back(step, lpips_mode)
            if self._gained_less(phase.patience):  # the next phase begins here (from the best, where this one fell)
                self.phase_ended = True
                self.refinement.report(self.stage)
                return True
            if fallen:
                rendering = refiner.render(self.z_um, self.log_energy, for_adjoint=True)
        self._adam_step(rendering, phase, lpips_mode, operation, entry)
        return True

    def _score(self, rendering: Rendering, step: int, entry: dict) -> dict:
        """A checkpoint's exact score, into the trace and the best; sets ``stalled``."""
        components = self.refinement.refiner.score(rendering)
        self.scored_after = step
        entry["score"] = components["mean"]
        self.refinement.consider(components, self.stage, step, self.z_um, self.log_energy, rendering.levels)
        self.best_after.append(self.refinement.best.score)
        self.stalled = self._gained_less(self.schedule.patience)
        return components

    def _gained_less(self, patience: int | None) -> bool:
        """Whether the best score gained less than ``min_gain`` over the last ``patience`` checkpoints (False
        without a patience, without adaptive stopping, or before that many checkpoints)."""
        min_gain = self.schedule.min_gain
        return bool(patience and min_gain is not None and len(self.best_after) > patience
                    and self.best_after[-1] - self.best_after[-1 - patience] < min_gain)

    def _phase_end(self, step: int) -> int:
        """The first step after ``step`` whose phase is not step ``step``'s (the run's length after its last)."""
        phase = self.steps[step]
        return next((end for end in range(step, len(self.steps)) if self.steps[end] is not phase), len(self.steps))

    def _has_fallen(self, score: float) -> bool:
        """A guarded run's checkpoint below its start or too far below the best (:attr:`RefineSchedule.max_falls`)."""
        floor = max(self.start_score, self.refinement.best.score - self.schedule.fall_tolerance)
        return self.guarded and len(self.refinement.falls) < self.schedule.max_falls and score < floor

    def _go_back(self, step: int, lpips_mode: str) -> str:
        """On from the best phantom with fresh moments and shorter steps; returns the step's LPIPS mode."""
        self.refinement.falls.append(self.refinement.iterations)
        self.z_um[:], self.log_energy[:] = self.refinement.best.z_um, self.refinement.best.log_energy
        self.adam = self._fresh_adam()
        self.lr_scale *= FALL_LR_FACTOR
        if lpips_mode == "reuse":  # the kept LPIPS gradient is the fallen iterate's
            self.lpips_kept_at = step
            return "keep"
        return lpips_mode

    def _adam_step(self, rendering: Rendering, phase: Phase, lpips_mode: str, operation: str, entry: dict) -> None:
        refiner, clock = self.refinement.refiner, self.refinement.clock
        start = time.perf_counter()
        value, grad_u, grad_z = refiner.gradients(rendering, phase.terms, lpips_mode)
        clock.record(operation, time.perf_counter() - start)
        entry["loss"] = value.loss
        start = time.perf_counter()
        refiner.step(self.adam, (self.z_um, self.log_energy), (grad_z, grad_u),
                     (self.lr_scale * phase.lr_z_um, self.lr_scale * phase.lr_u))
        clock.record("adam", time.perf_counter() - start)
        self.refinement.iterations += 1
        self.refinement.report(self.stage)

    def _score_end(self, step: int) -> None:
        """Score the iterate (not rendered yet) after ``step`` > 0 steps, at the run's end or where a hinge phase
        begins, if that still fits and nothing scored it there. What is scored is a copy on the file's grid
        (:meth:`_Refiner.round_as_saved`): the iterate itself goes on unrounded, so that a hinge phase starts
        where it would without this score."""
        if not (step and step != self.scored_after and self.refinement.clock.fits("render", "score")):
            return
        refiner = self.refinement.refiner
        z_um, log_energy = self.z_um.copy(), self.log_energy.copy()
        refiner.round_as_saved(z_um, log_energy)
        rendering = refiner.render(z_um, log_energy, for_adjoint=False)
        components = refiner.score(rendering)
        self.scored_after = step
        self.refinement.log(self.stage, step, components["mean"])
        self.refinement.consider(components, self.stage, step, z_um, log_energy, rendering.levels)
        self.refinement.report(self.stage)


class _HingeRun:
    """A hinge phase's L-BFGS iterations within a :class:`_Descent` (:mod:`octcl.host.stage3.hinge`).

    Each iteration counts as a step of the descent: it is scored at the
    descent's checkpoints, reported, and starts only while the longest
    iteration so far and a score still fit the deadline (one iteration is a
    render and an adjoint, more where its line search halves the step).
    """

    def __init__(self, descent: _Descent, step: int, relative_exponent: float):
        self.descent, self.step, self.relative_exponent = descent, step, relative_exponent
        self.refinement = descent.refinement
        self.unknowns = HingeUnknowns(self.refinement.plan.config)

    def run(self, length: int) -> int:
        """Up to ``length`` iterations; the descent's next step (the step reached where the deadline stopped
        them). The iterate ends in the descent's (z, u)."""
        refiner = self.refinement.refiner
        start = refiner.render(self.descent.z_um, self.descent.log_energy, for_adjoint=False)
        self.end, self.began = self.step + length, time.perf_counter()
        if not np.abs(start.a_scans).any():  # a dark rendering has no pixel to anchor the levels at: nothing to fit
            return self.end
        self.hinge = LevelHinge(self.refinement.plan.levels, start.a_scans,
                                anchor_weight=self.descent.schedule.hinge_anchor_weight,
                                relative_exponent=self.relative_exponent)
        if self._fits():
            x, _ = lbfgs.minimise(self._loss_and_gradient, self.unknowns.pack(self.descent.z_um,
                                  self.descent.log_energy), length, HINGE_MEMORY, self._after_iteration,
                                  max_halvings=HINGE_MAX_HALVINGS)
            self._set_iterate(x)
        return self.step if self.refinement.stop_reason == "deadline" else self.end

    def _loss_and_gradient(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        refiner = self.refinement.refiner
        z_um, log_energy = self.unknowns.unpack(x)
        refiner.constrain(z_um, log_energy)
        rendering = refiner.render(z_um, log_energy, for_adjoint=True)
        loss, a_bar = self.hinge(rendering.a_scans)
        grad_u, grad_z = refiner.adjoint(a_bar)
        return loss, self.unknowns.gradient(grad_u, grad_z)

    def _set_iterate(self, x: np.ndarray) -> None:
        z_um, log_energy = self.unknowns.unpack(x)
        self.refinement.refiner.constrain(z_um, log_energy)
        self.descent.z_um[:], self.descent.log_energy[:] = z_um, log_energy

    def _fits(self) -> bool:
        if self.refinement.clock.fits("render", "hinge", "render", "score"):
            return True
        self.refinement.stop_reason = "deadline"
        return False

    def _after_iteration(self, x: np.ndarray) -> None:
        """lbfgs's callback: count, time, score at a checkpoint and at the end; StopIteration where the descent
        stops here."""
        # An iteration is one evaluation or several (its line search): the deadline is kept on the longest, so
        # that the last iterate is still scored (on the last, 0.24 s after 0.17 s, a 30 s run of a mirrored
        # orange.png left 0.33 s for a 0.4 s score and kept its pixel phase's best, 4.4e−4 lower).
        self.refinement.clock.record("hinge", time.perf_counter() - self.began, longest=True)
        self.refinement.iterations += 1
        self.step += 1
        entry = self.refinement.log(self.descent.stage, self.step)
        last = self.step == self.end or not self._fits()
        if (self.step in self.descent.checkpoints or last) and self.refinement.clock.fits("render", "score"):
            self._set_iterate(x)
            refiner = self.refinement.refiner
            refiner.round_as_saved(self.descent.z_um, self.descent.log_energy)
            rendering = refiner.render(self.descent.z_um, self.descent.log_energy, for_adjoint=False)
            self.descent._score(rendering, self.step, entry)
        self.refinement.report(self.descent.stage)
        if last or self.refinement.stop_reason or self.descent.stalled:
            raise StopIteration
        self.refinement.check_ceiling(self.descent.stage)
        self.began = time.perf_counter()


__all__ = ["Checkpoint", "FALL_LR_FACTOR", "MAX_ENERGY_PCT", "Phase", "RefineProgress", "RefineResult", "RefineSchedule",
           "STOP_RULES", "TimeBudgetExceeded", "check_target_score", "refine", "saved_precision"]
