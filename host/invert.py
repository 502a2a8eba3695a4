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
"""

from __future__ import annotations

import dataclasses
import json
import math
import resource
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from octcl._io import ImageFormatError, atomic_write, check_scan_levels, read_png_rgb, read_scan
from octcl.config import DEFAULT_CONFIG, ScannerConfig
from octcl.phantom import CONTRACT_Y_LIMIT_UM, TARGET_ROWS, Phantom

from .refine import RefineProgress, RefineSchedule, refine

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
#: Seconds kept back from stage 3 for the last checkpoint writes and the
#: report: a write may be under way when stage 3 ends and the best phantom
#: still pending (each 1.5–3.5 s for 295,000 rows).
FINAL_RESERVE_S = 7.0


@dataclass
class InvertResult:
    """Outcome of :func:`invert`.

    Attributes
    ----------
    target, output : str
        The target PNG and the phantom file written.
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
    seed : int
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
    seed: int

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


def read_target(target, config: ScannerConfig = DEFAULT_CONFIG, source: str | None = None) -> np.ndarray:
    """Read and check a target B-scan; returns it as :func:`octcl._io.read_scan` does.

    ``target`` is a PNG file, or the scan's 8-bit grey levels as a 2-D
    ``uint8`` array, taken as the opaque grey PNG of them that the scanner
    writes (pixel values level / 255; scored as :class:`octcl.host.loss.
    ExactScore` scores such a PNG).
    ``source`` names the target in messages (default: the path, or
    ``target array``).

    Raises
    ------
    ImageFormatError
        Not a PNG, not 8-bit, not (Nz, Nx) (:func:`octcl._io.read_png_rgb`,
        :func:`octcl._io.check_scan_levels`), or one uniform level. The
        scanner's display puts its brightest pixel at level 255 and spans
        51 dB below it, so an all-black or uniform grey image is not one of
        its B-scans, and an all-white one would need every pixel equally
        bright: no phantom renders such an image, and its OAC and speckle
        maps are undefined (0/0), so it is refused rather than inverted into
        noise.
    """
    if isinstance(target, np.ndarray):
        source = source or "target array"
        pixels = check_scan_levels(target, config.shape, source)
    else:
        source = source or str(target)
        pixels = read_png_rgb(target, config.shape)
    low, high = int(pixels.min()), int(pixels.max())
    if low == high:
        colour = {0: "black", 255: "white"}.get(low, f"grey level {low}")
        raise ImageFormatError(
            f"{source}: every pixel is {colour}; a B-scan has structure (its brightest pixel is "
            "level 255 and its speckle spans the 51 dB display range), so there is nothing to invert")
    if isinstance(target, np.ndarray):
        from .loss import scan_of_levels

        return scan_of_levels(pixels)
    return read_scan(target, config.shape)


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


def invert(target_path, output_path, time_budget_s: float = 600.0, seed: int = 0, report_path=None,
           progress=None, config: ScannerConfig = DEFAULT_CONFIG,
           schedule: RefineSchedule = RefineSchedule()) -> InvertResult:
    """Invert a target B-scan PNG into a phantom file.

    Parameters
    ----------
    target_path : str, Path or ndarray
        The target: an 8-bit (Nz × Nx) grey, RGB or RGBA PNG, or its grey
        levels as an (Nz, Nx) ``uint8`` array (:func:`read_target`).
    output_path : str or Path
        The phantom text file (``x y z E`` rows, ≤ 295,000 of them, all
        within the task contract: |x| ≤ Xmax/2, |y| ≤ 3 µm, 0 ≤ z ≤ Nz·Δz,
        0 ≤ E ≤ 100).
    time_budget_s : float
        Wall-clock budget in seconds for the whole inversion, reading the
        target and compiling the kernels included. Stage 1 gets
        min(8 % of it, 45 s); stage 2 runs once; stage 3 gets the rest.
    seed : int
        Seed of stage 2's random choices; with the same seed and machine
        load the result repeats (the deadline decides how many iterations run).
    report_path : str or Path, optional
        JSON report: score trace against wall time per stage, final
        components, settings, seed, timings and peak memory.
    progress : callable, optional
        ``progress(InvertProgress)`` at each step of every stage and once at
        the end (stage ``done``).
    config : ScannerConfig
    schedule : RefineSchedule
        Stage 3's schedule (cut short by the budget).

    Returns
    -------
    InvertResult

    Raises
    ------
    ImageFormatError
        The target is not a usable B-scan (:func:`read_target`).
    ValueError
        A budget that is not a positive number.
    """
    from octcl._scanner_op import ScannerKernels

    from .field import fit_field
    from .loss import ExactScore

    started = time.monotonic()
    if not (isinstance(time_budget_s, (int, float)) and time_budget_s > 0 and math.isfinite(time_budget_s)):
        raise ValueError(f"time_budget_s must be a positive number of seconds, got {time_budget_s!r}")
    deadline = started + time_budget_s
    if not isinstance(target_path, np.ndarray):
        target_path = Path(target_path)
    output_path = Path(output_path)
    target = read_target(target_path, config)
    seconds, trace = {}, []

    def elapsed():
        return time.monotonic() - started

    tell = _ProgressReporter(progress, started, deadline - FINAL_RESERVE_S)
    field_budget = min(FIELD_BUDGET_FRACTION * time_budget_s, FIELD_BUDGET_CAP_S)
    tell("field", 0, 0)
    fit = fit_field(target, config, time_budget_s=field_budget,
                    progress=lambda i, n, loss: tell("field", i, n))
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
    exact_score = ExactScore(target_path)
    seconds["setup"] = time.monotonic() - start
    offset = elapsed()
    try:
        result = refine(phantom, target_path, schedule, deadline=deadline - FINAL_RESERVE_S,
                        kernels=kernels, config=config, progress=tell.refine, exact_score=exact_score,
                        on_improvement=lambda improved, components: writer.offer(improved))
    finally:
        writer.close()  # writes the best phantom if the interval held it back
    seconds["refine"] = elapsed() - offset
    seconds["checkpoint_writes"] = writer.seconds
    trace += [{**entry, "time_s": entry["time_s"] + offset} for entry in result.trace]
    seconds["total"] = elapsed()
    tell("done", result.iterations, schedule.total_iterations, done=True)

    outcome = InvertResult(
        target="array" if isinstance(target_path, np.ndarray) else str(target_path), output=str(output_path),
        score=result.components["mean"],
        components=result.components, initial_score=result.initial_components["mean"],
        scatterers=len(result.phantom), iterations=result.iterations, seconds=seconds,
        checkpoints=writer.writes, peak_memory_mib=peak_memory_mib(),
        stopped_by_deadline=result.stopped_by_deadline, seed=seed)
    if report_path is not None:
        contents = {
            **outcome.as_dict(),
            "initial_components": result.initial_components,
            "settings": {"time_budget_s": time_budget_s, "field_budget_s": field_budget,
                         "field_iterations": fit.iterations, "field_threads": fit.threads,
                         "schedule": dataclasses.asdict(schedule), "config": dataclasses.asdict(config),
                         "checkpoint_interval_s": CHECKPOINT_INTERVAL_S},
            "refine_timings_s": result.timings_s,
            "trace": trace,
        }
        with atomic_write(report_path, "w") as handle:
            json.dump(contents, handle, indent=1, default=float)
    return outcome


__all__ = ["CHECKPOINT_INTERVAL_S", "InvertProgress", "InvertResult", "invert", "peak_memory_mib", "read_target"]
