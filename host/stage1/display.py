"""Stage 1's display fit: Adam on the field's polar parameters against the target's display.

:func:`fit_field` finds F whose display D (``shared/physics.md`` §2 steps
9–10: 20·log10|A|, the brightest pixel at 0 dB, a 51 dB range) matches the
target B-scan's, A = H·F (:class:`~octcl.host.stage1.operator.FieldOperator`).
The target gives only |A| (to 8-bit precision), so this is phase retrieval;
the phases are what the decoders (:mod:`octcl.host.stage2`) turn into depths.
The loss and its gradient are :mod:`octcl.host.stage1.display_loss`; the
loop runs on a backend (:mod:`octcl.host.stage1.backend`).

References
----------
Kingma & Ba, "Adam: a method for stochastic optimization", ICLR 2015.
Loshchilov & Hutter, "SGDR: stochastic gradient descent with warm restarts",
ICLR 2017 (cosine annealing).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from ...config import DEFAULT_CONFIG, ScannerConfig
from ...render import Rendering
from .backend import Backend, NumpyBackend
from .display_loss import ENERGY_WEIGHT, DisplayGoal
from .levels import target_levels, target_magnitude

#: Adam's step size in (ln|F|, phase) units: 5 % in magnitude, 0.05 rad in phase.
LEARNING_RATE = 0.05
#: Share of the time budget that the learning rate's clock term ignores
#: (:func:`fit_field`): the first steps, FFT plans and the initialisation
#: would otherwise put the clock ahead of the step count on every fit, and
#: the learning rate, in its last bits, would follow the clock.
CLOCK_MARGIN = 0.1


@dataclass
class FieldFit:
    """Result of :func:`fit_field`.

    Attributes
    ----------
    field : ndarray of complex128, (Nz, Nx)
        F, scaled so that the brightest pixel of A(F) has |A| = 1.
    display : ndarray of float64, (Nz, Nx)
        D of A(F) (no shadowing), as :class:`octcl.render.Rendering` computes it.
    target_display : ndarray of float64, (Nz, Nx)
        D* (:func:`target_display`).
    losses : ndarray of float64
        The loss at each iteration.
    iterations : int
        Adam steps taken.
    seconds : float
        Wall time of the fit, initialisation included.
    threads : int
        FFT threads used (:attr:`FieldOperator.workers`).
    clock_steps : int
        Steps whose learning rate the clock set (the fit had fallen behind
        its time budget, :func:`fit_field`); 0: the fit took no decision
        from the clock.
    """

    field: np.ndarray
    display: np.ndarray
    target_display: np.ndarray
    losses: np.ndarray
    iterations: int
    seconds: float
    threads: int
    clock_steps: int


def fit_field(target, config: ScannerConfig = DEFAULT_CONFIG, iterations: int = 1500,
              time_budget_s: float | None = 40.0, energy_weight: float = ENERGY_WEIGHT,
              threads: int | None = None, dtype=np.float32,
              progress=None, initial: np.ndarray | None = None, backend: Backend | None = None) -> FieldFit:
    """Fit the complex field F of the linear scanner to a target B-scan (stage 1).

    Minimises, with Adam (Kingma & Ba 2015; step 0.05, cosine annealing),

        L(F) = mean|D − D*| + mean(D − D*)² + 0.5·mean|hp(D) − hp(D*)|
               + λ_E·mean|F|² / max|A|²,

    where A = A(F) (:class:`FieldOperator`), D = 1 + s·ln(|A|/max|A|) with
    s = 20/(51·ln 10) (the display without its clamp), D* the de-quantised
    target (:func:`target_display`) and hp(X) = X − box3(X) a high-pass.
    Where the target is at level 0, D is clamped at 0 (the inequality
    D ≤ 0: any magnitude below the floor is right); elsewhere it is clamped
    at −1 only, so a model pixel below the floor is still pulled up.

    The energy term is the field energy in units of the brightest rendered
    pixel, the unit the display itself uses; like the image terms it is
    scale-free, so it does not shrink F but penalises the field's shape:
    energy the scanner does not show (cancellation between neighbouring
    cells, components in the weak directions of the operator). At the end of
    a fit with λ_E = 0.1 (:data:`ENERGY_WEIGHT`, measured there) it is
    0.005–0.009 against about 0.001 for the image terms: a regulariser.

    F is parameterised by ρ = ln|F| and θ = arg F: the display is logarithmic
    over 51 dB and Adam's step is ≈ the step size in parameter units, so a
    step is a 5 % magnitude or 0.05 rad phase change at every brightness (in
    Re/Im the same step would swamp the cells 51 dB below the brightest).

    The start is the Tikhonov inverse (:meth:`FieldOperator.pseudo_inverse`)
    of the de-logged target magnitude (:func:`target_magnitude`) with zero
    phase: a non-negative image is mostly low-frequency, so the operator's
    pass band carries it and A(F₀) already has the target's speckle.
    Measured (MS-SSIM of the fitted display, 8-bit; about 20 ms of CPU a
    step in torch then, so 100 steps ≈ 2 s), for this start, the de-logged magnitude with
    random phases as F₀, and the inverse of the magnitude with random phases:

    ============  =========================  =========================
    steps         Uniform_A                  orange
    ============  =========================  =========================
    1             0.9885 / 0.8438 / 0.8951   0.9945 / 0.6959 / 0.7958
    100           0.9986 / 0.9944 / 0.9946   0.9965 / 0.9760 / 0.9752
    400           0.9997 / 0.9992 / 0.9990   0.9988 / 0.9967 / 0.9952
    ============  =========================  =========================

    so the random-phase starts are not offered.

    The learning rate follows lr₀·½(1 + cos(π·τ)) with
    τ = max(i/N, (t/T − m)/(1 − m)): i of N ``iterations`` taken, t of
    T = ``time_budget_s`` seconds used, m = :data:`CLOCK_MARGIN`. The
    schedule completes whichever ends first, and the clock takes over only
    where the fit falls behind the time it was given: a fit whose steps keep
    ahead of the clock's term (all of them on two idle cores: 1500 steps in
    11–12 s of a 45 s share) takes no decision from the clock. Then, or
    without a time budget, the fit depends on nothing but the target and
    the iterations: it is the same, bit for bit, at any thread count (each
    1-D FFT is one thread's, the sums NumPy's own; ``scripts/check_determinism.py``).

    The loss's gradient is derived by hand (:func:`~octcl.host.stage1.display_loss.display_loss`) and the
    step is :class:`octcl.host.optim.adam.Adam`: no torch, whose import and
    first optimiser (``python -c "import torch;
    torch.optim.Adam([torch.zeros(1, requires_grad=True)])"``) take 3.0 s on
    two cores of an AMD EPYC, ``import torch`` alone 1.2 s.

    Parameters
    ----------
    target : ndarray
        The target B-scan: uint8 levels or a float image from
        :func:`octcl._io.read_scan` (see :func:`target_levels`).
    config : ScannerConfig
        Scanner geometry; the target must have its shape (Nz, Nx).
    iterations : int
        Most Adam steps.
    time_budget_s : float or None
        Most wall time in seconds, initialisation included; the loop stops
        at the first step that ends past it. None: no time limit, all
        ``iterations`` run.
    energy_weight : float
        λ_E, the weight of the field-energy term.
    threads : int, optional
        FFT threads (:attr:`FieldOperator.workers`). By default 1 and all
        available cores are each timed on two steps and the faster is kept
        (see :func:`octcl.host.threads.thread_trials`); a fit of fewer than 5 steps, or on one
        core, uses 1.
    dtype : numpy.float32 or numpy.float64
        Precision of the fit (complex64 or complex128 FFTs). float32 took
        15.2 ms a step against 18.1 ms for float64 on Uniform A
        (``python scripts/bench_field_steps.py --threads 1``,
        two cores of an AMD EPYC).
    progress : callable, optional
        Called as ``progress(iteration, iterations, loss)`` after each step
        (on a device, for the steps since the last read, every few steps).
    initial : ndarray of complex, (Nz, Nx), optional
        The start; default the regularised inverse above.
    backend : NumpyBackend or OpenCLBackend, optional
        Where the steps run (:mod:`octcl.host.stage1.backend`); default
        ``NumpyBackend(config, threads)``. On an OpenCL backend the steps are
        kernels in its precision (``dtype`` is then the kernels'), and
        ``threads`` is not used.

    Returns
    -------
    FieldFit
    """
    start = time.perf_counter()
    if iterations < 1 or not (time_budget_s is None or time_budget_s > 0):
        raise ValueError(f"need iterations ≥ 1 and time_budget_s > 0, got {iterations}, {time_budget_s}")
    if dtype not in (np.float32, np.float64):
        raise ValueError(f"dtype must be numpy.float32 or numpy.float64, got {dtype}")
    levels = target_levels(target, config)
    backend = NumpyBackend(config, threads) if backend is None else backend
    operator = backend.operator
    goal = DisplayGoal.of(levels, energy_weight, backend.display_dtype(dtype))
    if initial is None:
        initial = operator.pseudo_inverse(target_magnitude(levels))
    initial = initial / np.abs(operator.apply(initial)).max()
    magnitude = np.abs(initial)
    floor = 1e-12 * magnitude.max()  # ln|F| of an exactly cancelled cell
    log_magnitude = np.log(np.maximum(magnitude, floor)).astype(goal.display.dtype)
    phase = np.angle(initial).astype(goal.display.dtype)
    schedule = CosineSchedule(iterations, time_budget_s, start)
    log_magnitude, phase, losses = backend.display_steps(goal, log_magnitude, phase, schedule, progress)

    field = np.exp(log_magnitude.astype(np.float64)) * np.exp(1j * phase.astype(np.float64))
    a_scans = operator.apply(field)
    field /= np.abs(a_scans).max()
    display = Rendering.from_a_scans(a_scans).display
    return FieldFit(field=field, display=display, target_display=goal.display.astype(np.float64),
                    losses=np.asarray(losses, dtype=np.float64), iterations=len(losses),
                    seconds=time.perf_counter() - start, threads=operator.workers, clock_steps=schedule.clock_steps)


class CosineSchedule:
    """The display fit's learning rate lr₀·½(1 + cos πτ), τ the larger of the steps' share and the clock's
    (:func:`fit_field`), and whether the fit may take another step."""

    def __init__(self, iterations: int, time_budget_s: float | None, start: float):
        self.iterations, self.time_budget_s, self.start = iterations, time_budget_s, start
        self.clock_steps = 0

    def time_fraction(self) -> float:
        return 0.0 if self.time_budget_s is None else (time.perf_counter() - self.start) / self.time_budget_s

    def go_on(self, taken: int) -> bool:
        return taken < self.iterations and self.time_fraction() < 1.0

    def rate(self, taken: int) -> float:
        clock = (self.time_fraction() - CLOCK_MARGIN) / (1.0 - CLOCK_MARGIN)
        self.clock_steps += clock > taken / self.iterations
        fraction = min(1.0, max(taken / self.iterations, clock))
        return LEARNING_RATE * 0.5 * (1.0 + math.cos(math.pi * fraction))

