"""Invert a target B-scan into a digital phantom: stages 1–3 under a time budget.

1. :func:`octcl.host.field.fit_field` — a complex reflectivity field on the
   pixel grid whose linear (shadowing-free) rendering matches the target.
2. :func:`octcl.host.decode.decode_field` — point scatterers (x, y, z, E)
   that reproduce that field.
3. :func:`octcl.host.refine.refine` — Adam on every scatterer's depth and
   log-energy through the OpenCL scanner and its adjoint, judged by the
   exact score.

The output file is only ever replaced by a complete, validated phantom
(:meth:`octcl.phantom.Phantom.save` writes a temporary file and renames it),
first right after stage 2, then whenever the exact score improves (at most
every ``CHECKPOINT_INTERVAL_S`` seconds) and at the end; a process killed at
any moment leaves the last checkpoint, or no file before the first.

Two modes. In deadline mode (the default) the stages share out the time
budget, so how far each gets depends on the machine's speed and load; the
result records the iteration counts reached, and whether the clock decided
anything (:attr:`InvertResult.reproducible`): a run it did not is repeated
byte for byte by the same call and by its fixed schedule. A fixed schedule
(``iterations``) runs by iteration counts alone, takes no decision from the
clock, and writes the same file, byte for byte, every time, at any torch
thread count (``docs/reproducibility.md``); there the budget is only a
ceiling that fails the run loudly.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import resource
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path


from octcl._io import atomic_write, check_output_path
from octcl.config import DEFAULT_CONFIG, ScannerConfig
from octcl.phantom import CONTRACT_Y_LIMIT_UM, TARGET_ROWS, Phantom

from .refine import RefineProgress, RefineSchedule, TimeBudgetExceeded, _Clock, check_target_score, refine
from .target import check_target, read_target, target_scan

#: Least time between two checkpoint writes during refinement, in seconds.
#: Formatting and writing 295,000 rows takes 1.5–3.5 s of CPU (measured
#: idle and under load), in a background thread but on the same two cores.
CHECKPOINT_INTERVAL_S = 20.0
#: Share of the time budget stage 1 may use, and its cap in seconds. Stage 1
#: usually ends first at its 1500 iterations (11–12 s on two idle cores);
#: its length matters little for the end result: on orange.png a 5 s stage 1
#: ended at 0.99944 after 281 s, the full 11 s one at 0.99950 after 318 s.
FIELD_BUDGET_FRACTION = 0.08
FIELD_BUDGET_CAP_S = 45.0
#: Stage 1's Adam steps (its learning rate anneals over them).
FIELD_ITERATIONS = 1500
#: torch's thread count in a fixed-schedule run unless given. The thread
#: count changes no bit of the result (docs/reproducibility.md), only the
#: speed; one thread is never slowed by other processes holding the cores
#: (see host/refine.py, _ThreadChooser).
FIXED_THREADS = 1
#: Seconds kept back from stage 3 for the last checkpoint writes and the
#: report: a write may be under way when stage 3 ends and the best phantom
#: still pending (each 1.5–3.5 s for 295,000 rows).
FINAL_RESERVE_S = 7.0


@dataclass
class InvertResult:
    """Outcome of :func:`invert`.

    Attributes
    ----------
    target : str
        The target's name: its path, or the ``name`` given with an array.
    output : str
        The phantom file written.
    score : float
        Mean of the eight exact components of the written phantom's rendering.
    components : dict
        Those eight components.
    initial_score : float
        The exact score after stages 1–2.
    scatterers : int
        Rows in the output.
    iterations : int
        Adam steps of stage 3.
    seconds : dict
        Wall time of each stage and ``total``.
    checkpoints : int
        Times the output was written.
    peak_memory_mib : float
        Peak resident memory of the process (ru_maxrss).
    stopped_by_deadline : bool
        Stage 3 was cut short by the time budget.
    stop_reason : str
        What ended stage 3 (:attr:`octcl.host.refine.RefineResult.stop_reason`):
        ``schedule``, ``converged``, ``target score`` or ``deadline``.
    falls : list of int
        Stage-3 steps after which the main run fell and went back to the best
        phantom at lower learning rates
        (:attr:`octcl.host.refine.RefineSchedule.max_falls`).
    seed : int
    field_iterations : int
        Adam steps of stage 1.
    fixed_schedule : bool
        The run followed a fixed schedule (``iterations`` given): no
        decision was taken from the clock.
    threads : int or None
        torch's CPU thread count, held for the whole run; None where it was
        chosen by timing (a deadline run without ``threads``).
    reproduce : str
        ``octcl invert`` options that run this schedule again with no
        decision from the clock: ``--seed``, ``--iterations``,
        ``--field-iterations``, ``--threads``.
    reproducible : bool
        No decision of this run came from the clock, so ``reproduce`` gives
        the same file again, byte for byte (same version and device, see
        ``docs/reproducibility.md``): always for a fixed schedule; for a
        deadline run, unless stage 1 fell behind its time share (its
        learning rate then followed the clock) or the deadline ended stage 3.
        The thread count, timed or given, changes no bit (measured at 1 and
        2 threads).
    """

    target: str
    output: str
    score: float
    components: dict
    initial_score: float
    scatterers: int
    iterations: int
    seconds: dict
    checkpoints: int
    peak_memory_mib: float
    stopped_by_deadline: bool
    stop_reason: str
    falls: list
    seed: int
    field_iterations: int
    fixed_schedule: bool
    threads: int | None
    reproduce: str
    reproducible: bool

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class InvertProgress:
    """Where an inversion stands: what :func:`invert` tells its ``progress`` callback.

    The run ends at whichever comes first: the end of stage 3's schedule or
    stage 3's deadline (the budget less :data:`FINAL_RESERVE_S`).
    ``seconds_left`` is the earlier of the two estimates (the schedule's from
    stage 3's measured seconds per iteration, once there is one), so it never
    exceeds the time left in the budget; ``fraction`` is
    elapsed / (elapsed + seconds_left). The last state (stage ``done``) has
    fraction 1 and no time left.

    Attributes
    ----------
    stage : str
        ``field`` (stage 1), ``decode`` (stage 2), ``setup`` (kernels and
        scorer), ``refine`` or ``restart N`` (stage 3), ``done``.
    iteration, iterations : int
        Steps taken and planned in the stage (stage 3: Adam steps, restarts
        included, against the whole schedule).
    fraction : float
        Share of the run done, in [0, 1].
    seconds_left : float
        Estimated seconds until the run ends.
    elapsed_s : float
        Seconds since the run started.
    score : float or None
        The last exact score measured (None before stage 3's first).
    score_elapsed_s : float or None
        ``elapsed_s`` when it was measured.
    """

    stage: str
    iteration: int
    iterations: int
    fraction: float
    seconds_left: float
    elapsed_s: float
    score: float | None = None
    score_elapsed_s: float | None = None


class _ProgressReporter:
    """Turns the stages' callbacks into :class:`InvertProgress` states.

    ``end`` is the ``time.monotonic()`` by which the budget ends the run.
    """

    def __init__(self, callback, started: float, end: float):
        self.callback, self.started, self.end = callback, started, end
        self.score = self.score_time = None
        self._refine_start = None  # (monotonic time, iterations) of stage 3's first report

    def __call__(self, stage: str, iteration: int, iterations: int, seconds_left: float | None = None,
                 done: bool = False) -> None:
        if self.callback is None:
            return
        now = time.monotonic()
        budget_left = max(self.end - now, 0.0)
        seconds_left = 0.0 if done else budget_left if seconds_left is None else min(seconds_left, budget_left)
        elapsed = now - self.started
        self.callback(InvertProgress(
            stage=stage, iteration=iteration, iterations=iterations,
            fraction=1.0 if done else elapsed / (elapsed + seconds_left) if elapsed + seconds_left > 0 else 0.0,
            seconds_left=seconds_left, elapsed_s=elapsed, score=self.score,
            score_elapsed_s=None if self.score_time is None else self.score_time - self.started))

    def refine(self, status: RefineProgress) -> None:
        """Stage 3's report; the schedule's time left from its seconds per iteration so far."""
        self.score, self.score_time = status.score, status.score_time
        now = time.monotonic()
        if self._refine_start is None:
            self._refine_start = (now, status.iterations)
        start_time, start_iterations = self._refine_start
        schedule_left = None
        if status.iterations > start_iterations:
            per_iteration = (now - start_time) / (status.iterations - start_iterations)
            schedule_left = (status.total - status.iterations) * per_iteration
        self(status.stage, status.iterations, status.total, schedule_left)


def peak_memory_mib() -> float:
    """Peak resident set size of this process in MiB (ru_maxrss: KiB on Linux, bytes on macOS)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 2**20 if sys.platform == "darwin" else peak / 1024


class _CheckpointWriter:
    """Writes phantoms to the output in a background thread: validated, atomic, rate-limited.

    Formatting and writing 295,000 rows takes 1.5–3.5 s of Python on this
    machine; in the background it overlaps with the kernels and the loss,
    which release the interpreter lock, instead of stopping the refinement.
    Only the newest offered phantom is kept, and one is written at most every
    ``interval_s`` seconds; :meth:`close` writes what is still pending.
    """

    def __init__(self, path: Path, config: ScannerConfig, interval_s: float):
        self.path, self.config, self.interval_s = path, config, interval_s
        self.writes, self.seconds = 0, 0.0
        self._pending, self._closed, self._error = None, False, None
        self._last_write = -math.inf
        self._condition = threading.Condition()
        self._thread = threading.Thread(target=self._run, name="checkpoint-writer", daemon=True)
        self._thread.start()

    def offer(self, phantom: Phantom) -> None:
        """Queue ``phantom`` for writing, replacing any phantom not yet written."""
        with self._condition:
            self._pending = phantom
            self._condition.notify()

    def _run(self) -> None:
        while True:
            with self._condition:
                while True:
                    if self._pending is None:
                        if self._closed:
                            return
                        self._condition.wait()
                        continue
                    wait_s = self._last_write + self.interval_s - time.monotonic()
                    if wait_s <= 0 or self._closed:
                        break
                    self._condition.wait(wait_s)
                phantom, self._pending = self._pending, None
            start = time.monotonic()
            try:
                phantom.validate(self.config, y_limit_um=CONTRACT_Y_LIMIT_UM, source=str(self.path))
                phantom.save(self.path)
            except BaseException as exc:  # re-raised by close() in the caller's thread
                with self._condition:
                    self._error, self._closed, self._pending = exc, True, None
                return
            self._last_write = time.monotonic()
            self.seconds += self._last_write - start
            self.writes += 1

    def close(self) -> None:
        """Write the pending phantom now, stop the thread, and raise its error if it had one."""
        with self._condition:
            self._closed = True
            self._condition.notify()
        self._thread.join()
        if self._error is not None:
            raise self._error


def _decode(fit, config: ScannerConfig, seed: int) -> Phantom:
    """Stage 2, with the contract's row target."""
    from .decode import decode_field

    return decode_field(fit.field, config, max_scatterers=TARGET_ROWS, seed=seed)


def invert(target, output_path, time_budget_s: float = 600.0, seed: int = 0, report_path=None,
           progress=None, config: ScannerConfig = DEFAULT_CONFIG,
           schedule: RefineSchedule = RefineSchedule(), iterations: int | None = None,
           field_iterations: int = FIELD_ITERATIONS, threads: int | None = None,
           name: str | None = None, target_score: float | None = None) -> InvertResult:
    """Invert a target B-scan into a phantom file.

    Parameters
    ----------
    target : str, Path or ndarray of uint8
        The target: an 8-bit (Nz × Nx) grey, RGB or RGBA PNG, read once
        (:func:`octcl.host.target.read_target`), or an array in either form
        of :mod:`octcl.host.target`: (Nz, Nx) levels of a grey B-scan as the
        scanner saves it, or (Nz, Nx, C) PNG pixels. ``read_target(path)``
        gives the array that inverts exactly as ``path`` does.
    output_path : str or Path
        The phantom text file (``x y z E`` rows, ≤ 295,000 of them, all
        within the task contract: |x| ≤ Xmax/2, |y| ≤ 3 µm, 0 ≤ z ≤ Nz·Δz,
        0 ≤ E ≤ 100).
    time_budget_s : float
        Wall-clock budget in seconds for the whole inversion, reading the
        target and compiling the kernels included. Without ``iterations``
        (deadline mode) stage 1 gets min(8 % of it, 45 s), stage 2 runs
        once and stage 3 gets the rest, so how far each stage gets depends
        on the machine's speed and load. With ``iterations`` it is only a
        ceiling: :class:`TimeBudgetExceeded` if the fixed schedule has not
        ended when stage 3 would have to stop.
    seed : int
        Seed of stage 2's random choices (the scatterers' elevations).
    report_path : str or Path, optional
        JSON report: score trace against wall time per stage, final
        components, settings, seed, timings and peak memory.
    progress : callable, optional
        ``progress(InvertProgress)`` at each step of every stage and once at
        the end (stage ``done``).
    config : ScannerConfig
    schedule : RefineSchedule
        Stage 3's schedule (cut short by the budget in deadline mode).
    iterations : int, optional
        Fixed-schedule mode: stage 1 runs ``field_iterations`` steps and
        stage 3 the first ``iterations`` Adam steps of ``schedule``
        (:meth:`RefineSchedule.truncated`), whatever the clock says, at
        ``threads`` torch threads (default :data:`FIXED_THREADS`). With the
        same target, seed, iterations, field_iterations, threads, octcl
        version and device the output file is the same, byte for byte
        (``docs/reproducibility.md``). A deadline run's result says how to
        run its schedule this way (:attr:`InvertResult.reproduce`).
    field_iterations : int
        Stage 1's Adam steps (in deadline mode: at most, within its time share).
    threads : int, optional
        torch's CPU thread count for the whole run. In deadline mode it is
        otherwise chosen by timing steps, which follows the machine's load.
    name : str, optional
        The target's name in messages and the result; default: the path, or
        ``"target"`` for an array.
    target_score : float, optional
        End stage 3 as soon as an exact evaluation reaches this score.

    Returns
    -------
    InvertResult

    Raises
    ------
    ImageFormatError
        The target is not a usable B-scan (:func:`octcl.host.target.check_target`).
    OutputError
        ``output_path`` or ``report_path`` cannot be written (:func:`octcl._io.check_output_path`),
        checked before the work starts.
    ValueError
        A budget that is not a positive number, iterations beyond the
        schedule, a thread or stage-1 iteration count below 1, a target
        score outside (0, 1].
    TimeBudgetExceeded
        A fixed schedule did not end within the budget; the output then
        holds the best phantom scored so far (or nothing, if the budget ran
        out before stage 2), not the schedule's result.
    """
    from octcl._scanner_op import ScannerKernels

    from .field import fit_field
    from .loss import ExactScore

    started = time.monotonic()
    if not (isinstance(time_budget_s, (int, float)) and time_budget_s > 0 and math.isfinite(time_budget_s)):
        raise ValueError(f"time_budget_s must be a positive number of seconds, got {time_budget_s!r}")
    for label, count in (("threads", threads), ("field_iterations", field_iterations)):
        if count is not None and not (isinstance(count, int) and count >= 1):
            raise ValueError(f"{label} must be a whole number ≥ 1, got {count!r}")
    check_target_score(target_score)  # before the work starts, as the other arguments
    fixed = iterations is not None
    if fixed:
        schedule = schedule.truncated(iterations)
        threads = FIXED_THREADS if threads is None else threads
    deadline = started + time_budget_s
    # A bad output path fails now, not after the budget is spent.
    output_path = check_output_path(output_path)
    if report_path is not None:
        check_output_path(report_path)
    if isinstance(target, (str, os.PathLike)):
        name = str(target) if name is None else name
        target = read_target(target, config)
    else:
        name = "target" if name is None else name
        target = check_target(target, config, name)
    seconds, trace = {}, []

    def elapsed():
        return time.monotonic() - started

    tell = _ProgressReporter(progress, started, deadline - FINAL_RESERVE_S)
    field_budget = None if fixed else min(FIELD_BUDGET_FRACTION * time_budget_s, FIELD_BUDGET_CAP_S)
    # In a fixed schedule the budget is only a safety ceiling, checked at
    # every step; in deadline mode the stages fit themselves inside it.
    ceiling = _Clock(None, deadline - FINAL_RESERVE_S if fixed else None)
    writer = None

    def field_step(iteration, steps, loss):
        ceiling.check_ceiling(f"in stage 1 after {iteration} of {steps} iterations")
        tell("field", iteration, steps)

    try:
        tell("field", 0, 0)
        fit = fit_field(target_scan(target), config, iterations=field_iterations, time_budget_s=field_budget,
                        threads=threads, progress=field_step)
        seconds["field"] = fit.seconds
        trace.append({"time_s": elapsed(), "stage": "field", "iteration": fit.iterations,
                      "loss": float(fit.losses[-1]) if fit.losses.size else None, "score": None})

        tell("decode", 0, 1)
        start = time.monotonic()
        phantom = _decode(fit, config, seed)
        seconds["decode"] = time.monotonic() - start
        writer = _CheckpointWriter(output_path, config, CHECKPOINT_INTERVAL_S)
        writer.offer(phantom)

        tell("setup", 0, 1)
        start = time.monotonic()
        kernels = ScannerKernels(config)
        exact_score = ExactScore(target)
        seconds["setup"] = time.monotonic() - start
        ceiling.check_ceiling("before stage 3")
        offset = elapsed()
        result = refine(phantom, target, schedule, deadline=None if fixed else deadline - FINAL_RESERVE_S,
                        kernels=kernels, config=config, progress=tell.refine, exact_score=exact_score,
                        on_improvement=lambda improved, components: writer.offer(improved),
                        ceiling=ceiling.ceiling if fixed else None, threads=threads,
                        target_score=target_score)
    except TimeBudgetExceeded as exc:
        if writer is not None:
            writer.close()
        holds = f"{output_path} holds the best phantom scored so far, not the schedule's result" \
            if writer is not None and writer.writes else f"nothing was written to {output_path}"
        raise TimeBudgetExceeded(
            f"{name}: a fixed schedule ({field_iterations} + {schedule.total_iterations} iterations) did not fit "
            f"the time budget of {time_budget_s:g} s ({exc}); give a larger budget. {holds}") from None
    finally:
        if writer is not None:
            writer.close()  # writes the best phantom if the interval held it back
    seconds["refine"] = elapsed() - offset
    seconds["checkpoint_writes"] = writer.seconds
    trace += [{**entry, "time_s": entry["time_s"] + offset} for entry in result.trace]
    seconds["total"] = elapsed()
    tell("done", result.iterations, schedule.total_iterations, done=True)

    outcome = InvertResult(
        target=name, output=str(output_path), score=result.components["mean"],
        components=result.components, initial_score=result.initial_components["mean"],
        scatterers=len(result.phantom), iterations=result.iterations, seconds=seconds,
        checkpoints=writer.writes, peak_memory_mib=peak_memory_mib(),
        stopped_by_deadline=result.stopped_by_deadline, stop_reason=result.stop_reason,
        falls=result.falls, seed=seed, field_iterations=fit.iterations,
        fixed_schedule=fixed, threads=threads,
        reproduce=f"--seed {seed} --iterations {result.iterations} --field-iterations {fit.iterations} "
                  f"--threads {FIXED_THREADS if threads is None else threads}",
        reproducible=fit.clock_steps == 0 and not result.stopped_by_deadline)
    if report_path is not None:
        contents = {
            **outcome.as_dict(),
            "initial_components": result.initial_components,
            "settings": {"time_budget_s": time_budget_s, "field_budget_s": field_budget,
                         "field_iterations_planned": field_iterations, "field_threads": fit.threads,
                         "field_clock_steps": fit.clock_steps,
                         "refine_threads": result.torch_threads,
                         "schedule": dataclasses.asdict(schedule), "config": dataclasses.asdict(config),
                         "checkpoint_interval_s": CHECKPOINT_INTERVAL_S, "target_score": target_score},
            "refine_timings_s": result.timings_s,
            "refine_cpu_s": result.cpu_s,
            "trace": trace,
        }
        with atomic_write(report_path, "w") as handle:
            json.dump(contents, handle, indent=1, default=float)
    return outcome


__all__ = ["CHECKPOINT_INTERVAL_S", "FIELD_ITERATIONS", "FIXED_THREADS", "InvertProgress", "InvertResult",
           "TimeBudgetExceeded", "invert", "peak_memory_mib", "read_target"]
