"""Stage 1's backends: the loops of its steps, in NumPy on the host or as OpenCL kernels on a device.

A step (:func:`~octcl.host.stage1.display.fit_field`,
:func:`~octcl.host.stage1.projections.retrieve_field`,
:func:`~octcl.host.stage1.hinge.fit_levels`) is written once: it checks its
arguments, makes its start and normalises its result on the host in float64
with :attr:`Backend.operator`, and asks its backend for the loop between:

================  ===================================  ======================================
method            :class:`NumpyBackend` (reference)     :class:`OpenCLBackend`
================  ===================================  ======================================
display_steps     :func:`~.display_loss.display_loss`,  :class:`~.display_device.DisplayFitKernels`
                  :class:`~octcl.host.optim.adam.Adam`
project_steps     :class:`~.operator.FieldOperator`,    :class:`~.operator_device.FieldKernels`,
                  :func:`~.levels.interval_projection`  :class:`~.levels_device.LevelKernels`
hinge_steps       :func:`octcl.host.optim.lbfgs.        :func:`octcl.host.optim.lbfgs_device.
                  minimise`                             minimise`
================  ===================================  ======================================

Both backends' :attr:`~Backend.operator` is a :class:`~.operator.FieldOperator`
at the same padding, so a field means the same on either, and each kernel
test compares the device with this configuration.

Reads from the device inside the loops (:class:`OpenCLBackend`):

- display fit: none per step; the losses every
  :data:`~.display_device.LOSS_READ_EVERY` steps, for ``progress``;
- projections: none. Each step is enqueued whole (H, the interval
  difference, H⁺, the update: 7 kernels);
- in both, the host waits for the step :data:`STEPS_IN_FLIGHT` behind the
  last enqueued before it reads the clock, so a budget is overrun by at
  most that many steps. The display fit once read the clock only as it
  enqueued, and its queue drained at the loss reads: under
  ``--time-budget 3`` on two first-generation EPYC cores, a display fit
  given 0.25–0.29 s ran its first 25 steps, 0.51 s;
- hinge fit: one read of L-BFGS's scalars per line-search trial
  (:func:`octcl.host.optim.lbfgs_device.minimise`), and, when the step's
  stop rule asks for its levels, the field's float32 A-scans
  (:meth:`OpenCLBackend.may_render`) and only where they render the aim the
  field itself (:meth:`Backend.levels_of`, the exact check).

A new device op goes beside its NumPy twin in this folder
(``<name>.py`` and ``<name>_device.py``), and its loop into both classes
here.
"""

from __future__ import annotations

import collections
import time

import numpy as np

from ...config import DEFAULT_CONFIG, ScannerConfig
from ...render import Rendering
from ..optim import lbfgs, lbfgs_device
from ..optim.adam import Adam
from ..threads import thread_trials
from .display_device import LOSS_READ_EVERY, DisplayFitKernels
from .display_loss import DisplayGoal, display_loss
from .levels import interval_projection
from .levels_device import LevelKernels
from .operator import FieldOperator
from .operator_device import FieldKernels

#: The backends by name, the reference last (``octcl invert --backend``).
BACKENDS = ("opencl", "numpy")
#: Display-fit and projection steps enqueued past the one the host waits for before reading the clock.
STEPS_IN_FLIGHT = 2
#: The device's projections call ``progress`` every this many steps, and after the last.
PROGRESS_EVERY = 10


def report_losses(losses: np.ndarray, reported: int, planned: int, progress) -> int:
    """``progress(step, planned, loss)`` for each step after the first ``reported``; returns the steps reported."""
    for index in range(reported, len(losses)) if progress is not None else ():
        progress(index + 1, planned, float(losses[index]))
    return len(losses)


def out_of_time(deadline: float | None) -> bool:
    """Whether ``time.perf_counter()`` is past ``deadline`` (None: never)."""
    return deadline is not None and time.perf_counter() > deadline


class NumpyBackend:
    """Stage 1's loops in NumPy and SciPy's FFTs on the host: the reference (``--backend numpy``).

    Parameters
    ----------
    config : ScannerConfig
    threads : int, optional
        FFT threads. None: the first display fit times 1 and all available
        cores (:func:`octcl.host.threads.thread_trials`) and keeps the faster.
    """

    name = "numpy"

    def __init__(self, config: ScannerConfig = DEFAULT_CONFIG, threads: int | None = None):
        self.config = config
        self.operator = FieldOperator(config, workers=threads or 1)
        self.threads = threads

    def display_dtype(self, requested):
        """The display fit's precision: the one asked for."""
        return requested

    def levels_of(self, field: np.ndarray) -> np.ndarray:
        """The 8-bit levels a field of this backend renders at (no shadowing)."""
        return Rendering.from_a_scans(self.operator.apply(field)).levels

    def may_render(self, field: np.ndarray, aim: np.ndarray) -> bool:
        """True: on the host :meth:`levels_of` is the check itself, with nothing cheaper to screen it."""
        return True

    def display_steps(self, goal: DisplayGoal, log_magnitude, phase, schedule, progress):
        """Adam on (ρ, θ) against :func:`display_loss` while ``schedule.go_on``; returns ρ, θ and the losses."""
        operator = self.operator
        adam = Adam((log_magnitude.shape, phase.shape), dtype=log_magnitude.dtype)
        losses = []
        trials = thread_trials(self.threads, schedule.iterations)
        trial_seconds = {}
        while schedule.go_on(len(losses)):
            trial = len(losses)
            if trial < len(trials):
                operator.workers = trials[trial]
            elif trial == len(trials) and trial_seconds:
                operator.workers = min(trial_seconds, key=trial_seconds.get)
            step_start = time.perf_counter()
            lr = schedule.rate(len(losses))
            field = np.exp(log_magnitude) * (np.cos(phase) + 1j * np.sin(phase))
            loss, gradient = display_loss(field, operator, goal)
            # ∂L/∂ln|F| = Re(conj(G)·F), ∂L/∂arg F = Re(conj(G)·iF) = −Im(conj(G)·F).
            along = np.conj(gradient) * field
            adam.step((log_magnitude, phase), (along.real, -along.imag), (lr, lr))
            losses.append(loss)
            if 0 < trial < len(trials):
                trial_seconds[trials[trial]] = trial_seconds.get(trials[trial], 0.0) + time.perf_counter() - step_start
            if progress is not None:
                progress(len(losses), schedule.iterations, loss)
        self.threads = operator.workers
        return log_magnitude, phase, losses

    def project_steps(self, field: np.ndarray, lower, upper, iterations: int, step: float, momentum: float,
                      deadline: float | None, progress):
        """Nesterov-accelerated projections onto [l, u] (:mod:`~octcl.host.stage1.projections`); returns
        the field, the steps taken and 1 where the deadline ended them (else 0)."""
        operator, previous, taken = self.operator, field, 0
        while taken < iterations:
            if taken and out_of_time(deadline):
                return field, taken, 1
            ahead = field + momentum * (field - previous)
            a_scans = operator.apply(ahead)
            correction = operator.pseudo_inverse(interval_projection(a_scans, lower, upper) - a_scans)
            previous, field = field, ahead + step * correction
            taken += 1
            if progress is not None:
                progress(taken, iterations)
        return field, taken, 0

    def hinge_steps(self, field: np.ndarray, lower, upper, iterations: int, memory: int, stop) -> np.ndarray:
        """L-BFGS on ½·Σ dist(|A_p|, [l_p, u_p])² (:mod:`~octcl.host.stage1.hinge`) with ``stop`` as its
        callback; returns the field."""
        operator = self.operator

        def loss_and_gradient(field_now):  # the gradient as ∂/∂Re F + i·∂/∂Im F: Hᴴ·r
            a_scans = operator.apply(field_now)
            residual = a_scans - interval_projection(a_scans, lower, upper)
            return 0.5 * float(np.vdot(residual, residual).real), operator.adjoint(residual)

        found, _ = lbfgs.minimise(loss_and_gradient, field, iterations, memory=memory, callback=stop)
        return found


class OpenCLBackend:
    """Stage 1's loops as OpenCL kernels on one device (module docstring); the default.

    Parameters
    ----------
    config : ScannerConfig
    device : pyopencl.Device or str, optional
        As :func:`octcl.device.runtime.select_device` takes it.
    double : bool
        float64 kernels; default float32.
    kernels : FieldKernels, optional
        An operator already built (its config and device are used).
    """

    name = "opencl"

    def __init__(self, config: ScannerConfig = DEFAULT_CONFIG, device=None, double: bool = False,
                 kernels: FieldKernels | None = None):
        self.kernels = FieldKernels(config, device, double) if kernels is None else kernels
        self.config = self.kernels.config
        self.operator = self.kernels.twin
        self.threads = 1
        self._levels = None
        self._screen = None  # may_render's A-scans, a device field made at its first call

    @property
    def level_kernels(self) -> LevelKernels:
        """The interval kernels, built at their first use."""
        if self._levels is None:
            self._levels = LevelKernels(self.kernels)
        return self._levels

    def display_dtype(self, requested):
        """The display fit's precision: the kernels'."""
        return self.kernels.real

    def levels_of(self, field) -> np.ndarray:
        """The 8-bit levels a device field renders at, by the float64 twin on the host (reads the field)."""
        return Rendering.from_a_scans(self.operator.apply(self.kernels.to_host(field))).levels

    def may_render(self, field, aim: np.ndarray) -> bool:
        """Whether a device field may render ``aim``: its A-scans by the kernels (float32), quantised on the host.

        A screen for :meth:`levels_of`, whose float64 operator on the host is
        most of the cost of a hinge fit's level check: on two Zen 4 cores
        that check took 18.7 ms against about 10 ms a hinge iteration, and
        this one 3–4 ms (docs/benchmarks.md, "The hinge's level check
        screened on the device"). False where a pixel's level differs from
        ``aim``; a pixel within float32's rounding of its level's edge can
        make it False where the exact check would pass, and the fit then
        goes on to its next check.
        """
        if self._screen is None:
            self._screen = self.kernels.empty()
        a_scans = self.kernels.to_host(self.kernels.apply(field, out=self._screen))
        return bool(np.array_equal(Rendering.from_a_scans(a_scans).levels, aim))

    def display_steps(self, goal: DisplayGoal, log_magnitude, phase, schedule, progress):
        """The display fit's steps enqueued while ``schedule.go_on``, the clock read after the step
        :data:`STEPS_IN_FLIGHT` before the last has ended, the losses read every :data:`LOSS_READ_EVERY` steps;
        returns ρ, θ and the losses."""
        fit = DisplayFitKernels(self.kernels, goal, log_magnitude, phase, schedule.iterations)
        reported, pending = 0, collections.deque()
        while schedule.go_on(fit.steps):
            pending.append(fit.step(schedule.rate(fit.steps)))
            if len(pending) > STEPS_IN_FLIGHT:
                pending.popleft().wait()
            if fit.steps % LOSS_READ_EVERY == 0:
                reported = report_losses(fit.losses(), reported, schedule.iterations, progress)  # waits for the queue
        losses = fit.losses()
        report_losses(losses, reported, schedule.iterations, progress)
        log_magnitude, phase = fit.parameters()
        return log_magnitude, phase, losses

    def project_steps(self, field: np.ndarray, lower, upper, iterations: int, step: float, momentum: float,
                      deadline: float | None, progress):
        """:meth:`NumpyBackend.project_steps` on the device, H⁺ at the shared padding; the clock read after
        the step :data:`STEPS_IN_FLIGHT` before the last has ended."""
        kernels, ops = self.kernels, self.level_kernels
        lower, upper = ops.bounds_to_device(lower, upper)
        field = kernels.to_device(field)
        ahead, scratch = field.copy(), kernels.empty()  # Y_0 = F_0: no momentum at the first step
        pending = collections.deque()
        taken = clock_steps = 0
        while taken < iterations:
            if taken and out_of_time(deadline):
                clock_steps = 1
                break
            kernels.apply(ahead, out=scratch)
            ops.interval_difference(scratch, lower, upper, out=scratch)
            kernels.pseudo_inverse(scratch, out=scratch)
            pending.append(ops.momentum_step(field, ahead, scratch, step, momentum))
            taken += 1
            if len(pending) > STEPS_IN_FLIGHT:
                pending.popleft().wait()
            if progress is not None and taken % PROGRESS_EVERY == 0:
                progress(taken, iterations)
        if progress is not None and taken % PROGRESS_EVERY:
            progress(taken, iterations)
        return kernels.to_host(field), taken, clock_steps

    def hinge_steps(self, field: np.ndarray, lower, upper, iterations: int, memory: int, stop) -> np.ndarray:
        """:meth:`NumpyBackend.hinge_steps` on the device: per evaluation H, the residual with its sum, Hᴴ."""
        kernels, ops = self.kernels, self.level_kernels
        lower, upper = ops.bounds_to_device(lower, upper)
        a_scans = kernels.empty()

        def loss_and_gradient(field_now, gradient, scalars, slot):
            kernels.apply(field_now, out=a_scans)
            ops.hinge_residual(a_scans, lower, upper, a_scans, scalars, slot)
            kernels.adjoint(a_scans, out=gradient)

        found, _ = lbfgs_device.minimise(ops.vectors, loss_and_gradient, kernels.to_device(field), iterations,
                                         memory=memory, callback=stop)
        return kernels.to_host(found)


#: What a stage-1 step asks for its loops: either backend.
Backend = NumpyBackend | OpenCLBackend


def make_backend(name: str, config: ScannerConfig = DEFAULT_CONFIG, threads: int | None = None,
                 device=None) -> Backend:
    """The backend called ``name`` (:data:`BACKENDS`): OpenCL on ``device`` (default octcl's choice,
    :func:`octcl.device.runtime.select_device`) or NumPy with ``threads`` FFT threads."""
    if name == "opencl":
        return OpenCLBackend(config, device)
    if name == "numpy":
        return NumpyBackend(config, threads)
    raise ValueError(f"backend must be one of {', '.join(BACKENDS)}, got {name!r}")


__all__ = ["BACKENDS", "Backend", "NumpyBackend", "OpenCLBackend", "PROGRESS_EVERY", "STEPS_IN_FLIGHT",
           "make_backend"]
