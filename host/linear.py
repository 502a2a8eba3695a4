"""The linear regime: stages 1–2 in seconds, a phantom that renders as its field does, cell for cell.

Scale and shadowing. The display divides by the B-scan's own maximum
(``shared/physics.md`` §2 step 10), so multiplying every amplitude a_j by one
factor c changes a rendering only through shadowing, whose terms (B_ij·a_j)²
scale with c². In A-scan i a scatterer is dimmed by its transmission
T_ij = Π_m (1 − (B_im·a_m)²) ≥ 1 − s_i, s_i = Σ_m (B_im·a_m)², so the
shadowing changes A[n, i] by at most s_i·Σ_j |c_ij|, the sum of the
magnitudes of the contributions to that pixel. :func:`decode_exact` scales
the phantom so that max_i s_i = :data:`SHADOW_BOUND` = 1e−12: even where the
contributions cancel a thousandfold (Σ|c| = 10³·|A|), a pixel's magnitude
moves by 1e−9 of itself, 4e−8 dB, about 1e−7 of a display level; float64
rounding in the scanner's own sums is of the same order. The energies are
then about 1e−11 % for the brightest rows (measured on the development set), within the task's 0 ≤ E ≤ 100, and
the phantom file's 8 significant digits keep their relative precision at any
scale. ``tests/test_linear.py`` renders decoded phantoms with the float64
reference scanner, shadowing included, and compares the levels with those
of the field.

Stage 1, :func:`linear_start`: candidate schedules of named steps
(:mod:`octcl.host.field_solve`): a display fit (the physical regime's stage
1, shortened), :func:`retrieve_field`'s projections, :func:`fit_levels`'
hinge fit and the aim step; the best kept; once one renders every pixel at
its aimed level, the others are left out. The aimed levels are the
target's own where the scanner can write them, one level up or down where
it cannot: by error diffusion (:mod:`octcl.host.ceiling`), then moved
where the exact score gains (:mod:`octcl.host.aim`).

Projections, :func:`retrieve_field`. In this regime the scanner is the linear
operator A = H·F of :class:`octcl.host.field.FieldOperator` (a lateral
Gaussian and the windowed depth DFT, diagonal in the 2-D Fourier domain).
The target's 8-bit level L_p of pixel p says only that |A_p|/max|A| lies in
an interval [l_p, u_p] (the display interval of the level, de-logged; level 0:
[0, u_p]). Every F with |(HF)_p| in its interval for all p renders the
target exactly, so stage 1 looks for a point of the intersection of
𝓜 = {A : l ≤ |A| ≤ u} and the range of H. Alternating projections
(Gerchberg & Saxton 1972; Fienup 1982) do this: project A = HF onto 𝓜
(keep each pixel's phase, clip its magnitude into the interval), go back to
F by the Tikhonov-regularised inverse of H (:meth:`FieldOperator.pseudo_inverse`),
repeat. With Nesterov's momentum on F (Nesterov 1983; as in the accelerated
projection methods of phase retrieval, e.g. Xu et al., "Accelerated
Wirtinger flow", 2018) the iteration is

    Y_k = F_k + β·(F_k − F_{k−1}),
    F_{k+1} = Y_k + α·H⁺(P_𝓜(H·Y_k) − H·Y_k).

H⁺ inverts the circulant extension of H (the columns zero-padded), not
the cropped operator itself, and the problem is not convex: with momentum
0.9 a full step (α = 1) diverged on the four synthetic scans of the
development set tried (Uniform A's field grew to ~1e93; the real scan
converged), while α = :data:`STEP` = 0.8 converged on all seven
(``tests/test_linear.py`` keeps Uniform A bounded). The intervals are shrunk by :data:`INTERVAL_MARGIN` (a
tenth of their width in dB, at each end) so that the iterate lands inside
a level rather than on its edge. The start is the regularised inverse of
the de-logged target with zero phase, as in stage 1 of the physical regime,
unless given (:func:`linear_start` gives a display fit's field).

From the regularised inverse (``python scripts/bench_linear.py --skin 3``,
docs/benchmarks.md; the 8-component score of the field's own 8-bit
rendering) the score changes by up to 9.7e−4 between 100 and 300
iterations (:data:`RETRIEVAL_ITERATIONS`) and by at most 1.6e−5 after; from
a display fit (:func:`linear_start`) by at most 2e−6 between 100
(:data:`START_PROJECTIONS`) and 600. A projection costs about 8 ms on two cores.

Stage 2, :func:`decode_exact`. A scatterer at depth z = z_n + o (z_n the
cell depth of :func:`octcl.host.field.cell_depths_um`) adds
a·e^{−2i·k_q·z} to the spectrum: on the grid that is the cell value
a·e^{−2i·k0·z} times the depth-kernel shift e^{−2i·(k_q − k0)·o}, a factor
per wavenumber. With a fixed set of offsets o_d the rendering of the
phantom is therefore exactly linear in the rows' amplitudes and diagonal
in the depth DFT per offset:

    Â[q, ·] = w_q·Σ_d e^{−2i(k_q − k0)·o_d}·DFT_n(M_d)[q, ·],

M_d[n, i] the cell values of the rows at offset o_d. The four offsets
o_d = (−3, −1, 1, 3)·λ/16 give carrier phases 3π/4, π/4, −π/4, −3π/4:
any complex value is a non-negative combination of two neighbouring ones,
so each cell becomes two rows, not four. Their
depth-kernel shifts are at most 2δk·3λ/16 of a DFT bin's phase per bin,
which :func:`decode_exact` undoes by iterating F' ← F' + (F − F_eff(F'))
(each step shrinks the error by the largest |2(k_q − k0)·o_d| ≈ 0.13; 12
steps take it below float64 rounding). In the first row z_0 = 0, so the
negative offsets there move by λ/2 (same phase, another shift: the
formula holds with per-row offsets). The result is 2 rows per non-zero
cell, 262,144 for a full 256×512 grid, at elevation y = 0 and on the
A-scan lines x_i, below the contract's 295,000 rows.

References
----------
Gerchberg & Saxton, "A practical algorithm for the determination of phase
from image and diffraction plane pictures", Optik 35, 1972.
Fienup, "Phase retrieval algorithms: a comparison", Appl. Opt. 21(15), 1982.
Nesterov, "A method of solving a convex programming problem with
convergence rate O(1/k²)", Soviet Math. Dokl. 27, 1983.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass

import numpy as np
import scipy.fft

from .. import _reference as ref
from .._io import GREY_LUT
from ..config import DEFAULT_CONFIG, ScannerConfig
from ..phantom import SIGNIFICANT_DIGITS, Phantom, _round_significant
from ..render import Rendering
from .field import FieldOperator, cell_depths_um, target_levels, target_magnitude
from . import lbfgs
from .field_solve import FieldSchedule, FieldSolve, default_schedules

#: Largest Σ_j (B_ij·a_j)² of any A-scan in a decoded phantom (module docstring).
SHADOW_BOUND = 1e-12
#: Projection steps of :func:`retrieve_field`.
RETRIEVAL_ITERATIONS = 300
#: α, the length of the projection step (module docstring: ≤ 1, and < 1 with momentum).
STEP = 0.8
#: β, Nesterov's momentum.
MOMENTUM = 0.9
#: Share of each level's interval (in dB) given up at each end.
INTERVAL_MARGIN = 0.1
#: Updates of the placed field in :func:`decode_exact`.
DECODE_CORRECTIONS = 12
#: Display-fit lengths of :func:`linear_start`'s candidates, as multiples of its
#: first display fit's steps. A third at 2× won on one scan of seven by 8e−6 and cost
#: about 5 s (:func:`linear_start`).
START_LENGTHS = (1.0, 0.5)
#: Projection steps after each display fit in :func:`linear_start`.
START_PROJECTIONS = 100
#: Stage 3's floor of E (%) for a decoded phantom (the physical regime's is 1e−20 %):
#: at :data:`SHADOW_BOUND` the brightest rows are near 1e−11 % and the
#: faintest 1e−26 %, 150 dB below. 1e−36 % is an amplitude of 1e−19,
#: a normal float32 number, and 80 dB below the faintest decoded row.
ENERGY_FLOOR_PCT = 1e-36
#: Carrier offsets of the rows of a cell, in units of λ (module docstring).
OFFSETS_IN_WAVELENGTHS = np.array([-3.0, -1.0, 1.0, 3.0]) / 16.0


def level_magnitude_bounds(levels: np.ndarray, margin: float = INTERVAL_MARGIN) -> tuple[np.ndarray, np.ndarray]:
    """The interval [l, u] of |A|/max|A| that renders each 8-bit level.

    The scanner writes level GREY_LUT[c] for colour index c = min(⌊256·D⌋, 255),
    D = 1 + 20·log10(|A|/max|A|)/51 (clamped at 0). A level L therefore comes
    from D in the union of [c/256, (c + 1)/256) over the indices c with
    GREY_LUT[c] = L, i.e. |A|/max|A| in [10^{51(D_lo − 1)/20}, 10^{51(D_hi − 1)/20});
    the 24 levels the colour map skips (a target quantised plainly has them)
    take the plain quantiser's interval [L/256, (L + 1)/256). Level 0 holds
    everything at or below the floor: l = 0.

    Parameters
    ----------
    levels : ndarray of uint8
    margin : float
        Share of each interval's width in D (so in dB) removed at each end,
        in [0, 0.5).

    Returns
    -------
    lower, upper : ndarray of float64, the shape of ``levels``
    """
    if not 0 <= margin < 0.5:
        raise ValueError(f"margin must be in [0, 0.5), got {margin}")
    index = np.arange(256)
    low, high = np.full(256, np.inf), np.full(256, -np.inf)
    np.minimum.at(low, GREY_LUT, index / 256.0)
    np.maximum.at(high, GREY_LUT, (index + 1) / 256.0)
    skipped = ~np.isfinite(low)
    low[skipped], high[skipped] = index[skipped] / 256.0, (index[skipped] + 1) / 256.0
    width = high - low
    low, high = low + margin * width, high - margin * width

    def magnitude(display):
        return 10.0 ** (ref.DISPLAY_RANGE_DB * (display - 1.0) / 20.0)

    lower, upper = magnitude(low)[levels], magnitude(high)[levels]
    lower[levels == 0] = 0.0
    return lower, upper


@dataclass
class LinearFit:
    """Result of :func:`retrieve_field`.

    Attributes
    ----------
    field : ndarray of complex128, (Nz, Nx)
        F on the cell grid, scaled so that the brightest pixel of A(F) has |A| = 1.
    display : ndarray of float64, (Nz, Nx)
        D of A(F), as :class:`octcl.render.Rendering` computes it.
    identical : float
        Share of pixels whose 8-bit level is the target's.
    iterations : int
        Projection steps taken.
    seconds : float
        Wall time, the start included.
    clock_steps : int
        1 if the time budget ended the iterations early, else 0 (the fit
        then took a decision from the clock).
    """

    field: np.ndarray
    display: np.ndarray
    identical: float
    iterations: int
    seconds: float
    clock_steps: int


def retrieve_field(target, config: ScannerConfig = DEFAULT_CONFIG, iterations: int = RETRIEVAL_ITERATIONS,
                   time_budget_s: float | None = None, progress=None,
                   initial: np.ndarray | None = None, aim: np.ndarray | None = None,
                   workers: int = 1) -> LinearFit:
    """A field F whose linear rendering has the target's levels: accelerated projections (module docstring).

    Parameters
    ----------
    target : ndarray
        uint8 levels (Nz, Nx), or a float image in [0, 1]
        (:func:`octcl.host.field.target_levels`).
    config : ScannerConfig
    iterations : int
        Projection steps (≥ 1).
    time_budget_s : float, optional
        Stop after the first step that ends past this many seconds.
    progress : callable, optional
        ``progress(iteration, iterations)`` after each step.
    initial : ndarray of complex, (Nz, Nx), optional
        The start; default the regularised inverse of the de-logged target
        with zero phase.
    aim : ndarray of uint8, (Nz, Nx), optional
        The levels whose intervals the projections aim at (and that
        ``identical`` counts); default the target's own.
        :func:`octcl.host.ceiling.aimed_levels` gives ones the scanner writes.
    workers : int
        FFT threads (:attr:`octcl.host.field.FieldOperator.workers`; the same bits at any count).

    Returns
    -------
    LinearFit
    """
    start = time.perf_counter()
    operator = FieldOperator(config, workers)
    aimed, field, lower, upper = retrieval_start(target, iterations, initial, aim, operator)
    previous = field
    taken = clock_steps = 0
    while taken < iterations:
        if time_budget_s is not None and taken and time.perf_counter() - start > time_budget_s:
            clock_steps = 1
            break
        ahead = field + MOMENTUM * (field - previous)
        a_scans = operator.apply(ahead)
        previous, field = field, ahead + STEP * operator.pseudo_inverse(_project(a_scans, lower, upper) - a_scans)
        taken += 1
        if progress is not None:
            progress(taken, iterations)
    return _normalised_fit(operator, field, aimed, taken, time.perf_counter() - start, clock_steps)


def _check_iterations(iterations) -> None:
    if not (isinstance(iterations, int) and iterations >= 1):
        raise ValueError(f"iterations must be a whole number ≥ 1, got {iterations!r}")


def retrieval_start(target, iterations, initial, aim, operator: FieldOperator):
    """What :func:`retrieve_field` (and its device twin) start from, its arguments checked: the aimed levels,
    the start scaled so that max|A(F)| = 1, and the aimed intervals [l, u] (:func:`level_magnitude_bounds`)."""
    _check_iterations(iterations)
    levels = target_levels(target, operator.config)
    aimed = levels if aim is None else target_levels(aim, operator.config)
    if initial is None:
        initial = regularised_start(levels, operator)
    field = np.asarray(initial, dtype=np.complex128) / np.abs(operator.apply(initial)).max()
    return (aimed, field, *level_magnitude_bounds(aimed))


def regularised_start(levels: np.ndarray, operator: FieldOperator) -> np.ndarray:
    """The start of the projections without a given one: the regularised inverse
    (:meth:`~octcl.host.field.FieldOperator.pseudo_inverse`) of the de-logged target, zero phase."""
    return operator.pseudo_inverse(target_magnitude(levels).astype(np.complex128))


def _project(a_scans: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """P_𝓜: each pixel's magnitude clipped into [lower, upper], its phase kept (phase 0 at exactly 0)."""
    magnitude = np.abs(a_scans)
    clipped = np.clip(magnitude, lower, upper)
    return np.where(magnitude > 0, a_scans * (clipped / np.where(magnitude > 0, magnitude, 1.0)), clipped)


def _normalised_fit(operator: FieldOperator, field: np.ndarray, aimed: np.ndarray, iterations: int,
                    seconds: float, clock_steps: int) -> LinearFit:
    """The :class:`LinearFit` of ``field`` scaled so that max|A(F)| = 1, ``identical`` counted against ``aimed``."""
    a_scans = operator.apply(field)
    scale = np.abs(a_scans).max()
    rendering = Rendering.from_a_scans(a_scans / scale)
    return LinearFit(field=field / scale, display=rendering.display,
                     identical=float(np.mean(rendering.levels == aimed)), iterations=iterations, seconds=seconds,
                     clock_steps=clock_steps)


# -------------------------------------------------------------- intervals
#: L-BFGS iterations of :func:`fit_levels`.
LEVEL_FIT_ITERATIONS = 200
#: Pairs L-BFGS keeps (:func:`octcl.host.lbfgs.minimise`'s ``memory``; SciPy's default). From the same
#: projected field of Uniform A, 5, 10 and 20 pairs all put every pixel at its level in 20 iterations,
#: taking 0.31, 0.52 and 0.66 s (``python scripts/bench_field_steps.py --threads 1``, two cores of an AMD
#: EPYC); 5 is not yet measured on the development set.
LEVEL_FIT_MEMORY = 10
#: :func:`fit_levels` compares the rendering's levels with the aimed ones every this many iterations.
LEVEL_CHECK_EVERY = 10


def _anchored_bounds(aim: np.ndarray, magnitude: np.ndarray, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`level_magnitude_bounds` of ``aim`` with one pixel pinned at |A| = 1: of the pixels at the highest
    aimed level, the brightest in ``magnitude``. Every upper bound is ≤ 1, so a field inside these bounds
    has max|A| = 1 exactly and renders each pixel at the level its bounds say: the display's division by
    its own maximum is then part of the constraints."""
    lower, upper = level_magnitude_bounds(aim, margin)
    anchor = np.unravel_index(np.argmax(np.where(aim == aim.max(), magnitude, -1.0)), aim.shape)
    lower[anchor] = upper[anchor] = 1.0
    return lower, upper


def fit_levels(field: np.ndarray, aim: np.ndarray, config: ScannerConfig = DEFAULT_CONFIG,
               iterations: int = LEVEL_FIT_ITERATIONS, margin: float = INTERVAL_MARGIN,
               time_budget_s: float | None = None, workers: int = 1) -> LinearFit:
    """Move a field until every pixel of its rendering lies in its aimed level's interval: L-BFGS on a hinge.

    Minimises ½·Σ_p dist(|A_p|, [l_p, u_p])² over F, A = H·F
    (:class:`~octcl.host.field.FieldOperator`), with the bounds of
    :func:`_anchored_bounds` (one pixel pinned at |A| = 1, so that the
    display's normalisation holds exactly at zero loss). With r_p = A_p −
    P_p(A_p), P_p the projection of A_p onto its annulus (the phase kept),
    the gradient with respect to (Re F, Im F) is (Re, Im) of Hᴴ·r: two FFT
    pairs an evaluation. L-BFGS (Nocedal 1980; :mod:`octcl.host.lbfgs`) reaches
    where the projections of :func:`retrieve_field` stall: they fix each
    pixel's magnitude in turn through a regularised inverse, which leaves
    dark pixels one level bright where their neighbours' sidelobes land
    (Uniform A: 93.2 % of pixels on their level after the projections,
    99.998 % after 100 iterations here; ``scripts/bench_linear.py``).

    Parameters
    ----------
    field : ndarray of complex, (Nz, Nx)
        The start (a retrieved field).
    aim : ndarray of uint8, (Nz, Nx)
        The levels aimed at, each one the scanner writes
        (:func:`octcl.host.ceiling.aimed_levels`).
    config : ScannerConfig
    iterations : int
        L-BFGS iterations at most (≥ 1); it stops sooner once every pixel
        renders at its aimed level (checked every :data:`LEVEL_CHECK_EVERY`).
    margin : float
        :func:`level_magnitude_bounds`' margin.
    time_budget_s : float, optional
        Stop after the first iteration that ends past this many seconds.
    workers : int
        FFT threads (:attr:`octcl.host.field.FieldOperator.workers`; the same bits at any count).

    Returns
    -------
    LinearFit
        ``identical`` counts pixels at their aimed level.
    """
    start = time.perf_counter()
    operator = FieldOperator(config, workers)
    aim, field, lower, upper = hinge_start(field, aim, iterations, margin, operator)

    def loss_and_gradient(field_now):  # the gradient as ∂/∂Re F + i·∂/∂Im F: Hᴴ·r
        a_scans = operator.apply(field_now)
        residual = a_scans - _project(a_scans, lower, upper)
        return 0.5 * float(np.vdot(residual, residual).real), operator.adjoint(residual)

    stop = LevelStop(aim, lambda field_now: Rendering.from_a_scans(operator.apply(field_now)).levels, start,
                     time_budget_s)
    found, _ = lbfgs.minimise(loss_and_gradient, field, iterations, memory=LEVEL_FIT_MEMORY, callback=stop)
    return _normalised_fit(operator, found, aim, stop.taken, time.perf_counter() - start, stop.clock_steps)


def hinge_start(field, aim, iterations, margin: float, operator: FieldOperator):
    """What :func:`fit_levels` (and its device twin) start from, its arguments checked: the aimed levels, the
    field scaled so that max|A(F)| = 1, and the anchored intervals [l, u] (:func:`_anchored_bounds`)."""
    _check_iterations(iterations)
    aim = target_levels(aim, operator.config)
    field = np.asarray(field, dtype=np.complex128)
    magnitude = np.abs(operator.apply(field))
    scale = magnitude.max()
    return (aim, field / scale, *_anchored_bounds(aim, magnitude / scale, margin))


class LevelStop:
    """The hinge fit's L-BFGS callback: counts the iterations, and ends the fit past its time budget or once
    every pixel renders at its aimed level, checked every :data:`LEVEL_CHECK_EVERY` iterations.

    ``levels_of(field)`` gives a field's 8-bit rendering (on the host, or from a device's field).
    ``clock_steps`` is 1 where the budget ended the fit.
    """

    def __init__(self, aim: np.ndarray, levels_of, start: float, time_budget_s: float | None):
        self.aim, self.levels_of, self.start, self.time_budget_s = aim, levels_of, start, time_budget_s
        self.taken = self.clock_steps = 0

    def __call__(self, field_now) -> None:
        self.taken += 1
        if self.time_budget_s is not None and time.perf_counter() - self.start > self.time_budget_s:
            self.clock_steps = 1
            raise StopIteration
        if self.taken % LEVEL_CHECK_EVERY == 0 and np.array_equal(self.levels_of(field_now), self.aim):
            raise StopIteration


# ------------------------------------------------------------------- start
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
        step did, :class:`octcl.host.field_solve.StepRecord`).
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
                 aim: np.ndarray | None = None, kernels=None) -> LinearStart:
    """Stage 1 of the linear regime: candidate schedules of named steps, the best field by score.

    Each candidate is a :class:`~octcl.host.field_solve.FieldSchedule` run
    by a :class:`~octcl.host.field_solve.FieldSolve`; by default
    :func:`~octcl.host.field_solve.default_schedules` of 300 display steps:
    ``display:300,project:100,hinge:200``, then the same with 150. Once a
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
        uint8 levels (Nz, Nx) or a float image (:func:`octcl.host.field.target_levels`).
    score : callable
        ``score(levels) -> float``: the exact score of 8-bit levels against the
        target (the mean of :class:`octcl.host.loss.ExactScore`'s components).
    config : ScannerConfig
    schedules : tuple of FieldSchedule, optional
        The candidates, tried in order; default ``default_schedules(300)``.
    time_budget_s : float, optional
        The first candidate gets all of it (its steps their shares); a
        later one runs only if its iterations, at the first candidate's
        measured pace, end within it.
    threads : int, optional
        FFT threads (:func:`octcl.host.field.fit_field`; by default timed there).
    progress : callable, optional
        ``progress(step, steps)`` over all candidates' iterations.
    aim : ndarray of uint8, optional
        The levels the steps aim at; default the target's own. The
        candidates are still judged by ``score`` against the target.
    kernels : FieldKernels, optional
        The steps' OpenCL backend (:class:`~octcl.host.field_solve.FieldSolve`); None: NumPy.

    Returns
    -------
    LinearStart
    """
    start = time.perf_counter()
    schedules = default_schedules(300) if schedules is None else tuple(schedules)
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
        solve = FieldSolve(levels, aim, config, threads if not solves else solves[0].threads, score=score,
                           kernels=kernels)
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
        operator = FieldOperator(config)
        for candidate, solve in zip(candidates, solves):
            candidate["score"] = float(score(Rendering.from_a_scans(operator.apply(solve.best_field)).levels))
    chosen = max(range(len(candidates)), key=lambda index: candidates[index]["score"] or 0.0)
    return LinearStart(field=solves[chosen].best_field, schedule=schedules[chosen], aim=solves[chosen].aim,
                       candidates=candidates, seconds=elapsed(), clock_steps=clock_steps,
                       threads=solves[0].threads or 1)


# ------------------------------------------------------------------ decode
def row_depths_um(config: ScannerConfig = DEFAULT_CONFIG) -> np.ndarray:
    """Depths (µm) of the four rows of each cell row n, as the phantom file holds them: (4, Nz).

    z_n + (−3, −1, 1, 3)·λ/16, z_n the cell depth; in row 0 (z_0 = 0) the
    negative offsets move by λ/2, keeping their carrier phase, so that
    z ≥ 0. Each depth is rounded to :data:`octcl.phantom.SIGNIFICANT_DIGITS`
    as the file writes it, and the decode is exact for these depths: an
    unrounded depth moves by up to 5e−5 µm in the file (z ≥ 1000 µm), a
    carrier phase of 4.8e−4 rad, enough to move a dark pixel whose
    contributions cancel a thousandfold by a level (0.03 % of Uniform A's
    pixels were).
    """
    offsets = np.repeat((OFFSETS_IN_WAVELENGTHS * config.wavelength_um)[:, None], config.depth_pixels, axis=1)
    offsets[:, 0] = np.where(offsets[:, 0] < 0, offsets[:, 0] + config.wavelength_um / 2, offsets[:, 0])
    return _round_significant(cell_depths_um(config)[None, :] + offsets, SIGNIFICANT_DIGITS)


def row_offsets_um(config: ScannerConfig = DEFAULT_CONFIG) -> np.ndarray:
    """Depth offsets o_{d,n} (µm) of the four rows of a cell in row n from its cell depth: (4, Nz)
    (:func:`row_depths_um` less z_n)."""
    return row_depths_um(config) - cell_depths_um(config)[None, :]


def _carriers(config: ScannerConfig) -> np.ndarray:
    """e^{−2i·k0·o_{d,n}}, the carrier phase of each row's offset: (4, Nz, 1), broadcasting over columns.

    Near (3π/4, π/4, −π/4, −3π/4) for the offsets (−3, −1, 1, 3)·λ/16; the
    file's rounding of the depths moves them by up to 5e−4 rad.
    """
    return np.exp(-2j * (2 * np.pi / config.wavelength_um) * row_offsets_um(config))[:, :, None]


def split_on_carriers(values: np.ndarray, carriers: np.ndarray) -> np.ndarray:
    """Non-negative weights p_d, two per value, with Σ_d p_d·carriers[d] = value.

    ``carriers`` are unit phasors about 90° apart: (D,), the same for every
    value, or (D, ...) broadcasting against ``values`` (:func:`_carriers`:
    per row), in the same order around the circle for every value. A value
    goes to the two whose angles enclose it. Returns (D,) + values.shape.
    """
    carriers = np.asarray(carriers)
    if carriers.ndim == 1:
        carriers = carriers.reshape(carriers.shape + (1,) * np.ndim(values))
    angles = np.angle(carriers)  # (D, ...) broadcasting against values, never expanded to their size
    order = np.argsort(angles.reshape(carriers.shape[0], -1)[:, 0])
    value_angles = np.angle(values)
    weights = np.zeros((carriers.shape[0],) + np.shape(values))
    turn = 2 * np.pi
    for position, first in enumerate(order):
        second = order[(position + 1) % order.size]
        sector = (angles[second] - angles[first]) % turn
        inside = (value_angles - angles[first]) % turn < sector
        c1, c2 = carriers[first], carriers[second]
        # value = p·c1 + q·c2 with real p, q: Im(conj(c1)·c2) is the determinant. Computed for every value
        # and kept where it lies in this sector: cheaper than gathering the sector's values.
        determinant = (np.conj(c1) * c2).imag
        weights[first] = np.where(inside, (np.conj(values) * c2).imag / determinant, weights[first])
        weights[second] = np.where(inside, (np.conj(c1) * values).imag / determinant, weights[second])
    return np.maximum(weights, 0.0)  # rounding can leave −1e−17 on a sector's edge


#: Terms of the series in :func:`rendered_cells` for the rounded offsets' depth-kernel shifts.
_SHIFT_TERMS = 3


def rendered_cells(weights: np.ndarray, config: ScannerConfig = DEFAULT_CONFIG) -> np.ndarray:
    """The grid field that renders like rows of amplitude ``weights`` at :func:`row_depths_um`.

    F_eff = IDFT_q(Σ_d Σ_n e^{−2i(k_q − k0)·o_{d,n}}·M_d[n]·e^{−2πiqn/Nz}),
    M_d[n, ·] = weights_d·e^{−2i·k0·(z_n + o_{d,n})} (module docstring). The
    offsets of rows n ≥ 1 are ō_d + δ_{d,n}, ō_d the unrounded offset and
    |δ| ≤ 5e−5 µm the file's rounding: e^{−2i(k_q − k0)·δ} is its series,
    Σ_m (−2i(k_q − k0)·δ)^m/m!, whose terms after the third are below 1e−14
    (|2(k_q − k0)·δ| < 1e−4), so each m is one depth DFT. Row 0's own
    offsets enter as one extra term each.
    """
    k = ref.wavenumbers(config)
    k0 = 2 * np.pi / config.wavelength_um
    depth_um = cell_depths_um(config)[:, None]
    offsets = row_offsets_um(config)
    nominal = OFFSETS_IN_WAVELENGTHS * config.wavelength_um
    spectrum = np.zeros(weights.shape[1:], dtype=np.complex128)
    for d in range(weights.shape[0]):
        cells = weights[d] * np.exp(-2j * k0 * (depth_um + offsets[d][:, None]))
        first_row = cells[0].copy()
        cells[0] = 0.0
        rounding = (offsets[d] - nominal[d])[:, None]
        term, series = cells, np.zeros_like(spectrum)
        for m in range(_SHIFT_TERMS):
            if m:
                term = term * rounding / m
            series += (-2j * (k - k0))[:, None] ** m * scipy.fft.fft(term, axis=0)
        spectrum += np.exp(-2j * (k - k0) * nominal[d])[:, None] * series
        spectrum += np.exp(-2j * (k - k0) * offsets[d, 0])[:, None] * first_row[None, :]
    return scipy.fft.ifft(spectrum, axis=0)


def _cell_weights(field: np.ndarray, config: ScannerConfig) -> np.ndarray:
    """:func:`split_on_carriers` of each cell value with its cell's own carrier e^{−2i·k0·z_n} taken out."""
    k0 = 2 * np.pi / config.wavelength_um
    return split_on_carriers(field * np.exp(2j * k0 * cell_depths_um(config))[:, None], _carriers(config))


def decode_exact(field: np.ndarray, config: ScannerConfig = DEFAULT_CONFIG,
                 shadow_bound: float = SHADOW_BOUND, corrections: int = DECODE_CORRECTIONS) -> Phantom:
    """Two rows per non-zero cell that render, without shadowing, exactly as the field (module docstring).

    Parameters
    ----------
    field : ndarray of complex, (Nz, Nx)
        F on the cell grid; any overall scale.
    config : ScannerConfig
    shadow_bound : float
        max_i Σ_j (B_ij·a_j)² of the result, in (0, 0.5]: the absolute scale.
    corrections : int
        Updates of the placed field for the rows' depth-kernel shifts.

    Returns
    -------
    Phantom
        Rows ordered by cell (row-major) and offset, x on the A-scan lines,
        y = 0, 0 ≤ z ≤ Nz·Δz, E = 100·a².

    Raises
    ------
    ValueError
        A field of the wrong shape, non-finite or all zero; a bound outside (0, 0.5].
    """
    field = np.asarray(field, dtype=np.complex128)
    if field.shape != config.shape:
        raise ValueError(f"field is {field.shape}, the scanner's grid is {config.shape}")
    if not np.isfinite(field).all():
        raise ValueError("field has non-finite values")
    if not np.any(field):
        raise ValueError("the field is zero everywhere: there is nothing to decode")
    if not 0 < shadow_bound <= 0.5:
        raise ValueError(f"shadow_bound must be in (0, 0.5], got {shadow_bound}")
    placed = field
    for _ in range(corrections):
        placed = placed + (field - rendered_cells(_cell_weights(placed, config), config))
    weights = _cell_weights(placed, config)
    # Scale: Σ_j (B_ij·a_j)² over an A-scan is a lateral convolution of the
    # columns' Σ a² with e^{−2d²/w0²} (y = 0), over the offsets the float64
    # scanner resolves (octcl._reference.SHADOW_EXACT_RADIUS_SQ).
    w0, pitch = config.beam_radius_um, config.lateral_pitch_um
    reach = math.ceil(math.sqrt(ref.SHADOW_EXACT_RADIUS_SQ) * w0 / pitch)
    offsets_um = np.arange(-reach, reach + 1) * pitch
    per_ascan = np.convolve((weights**2).sum(axis=(0, 1)), np.exp(-2 * offsets_um**2 / w0**2), mode="same")
    scale = math.sqrt(shadow_bound / per_ascan.max())
    row, column, offset = np.nonzero(np.moveaxis(weights, 0, -1) > 0)
    amplitude = scale * np.moveaxis(weights, 0, -1)[row, column, offset]
    z_um = row_depths_um(config)[offset, row]
    x_um = ref.ascan_positions_um(config)[column]
    return Phantom(x_um, np.zeros_like(x_um), z_um, 100.0 * amplitude**2)


__all__ = ["DECODE_CORRECTIONS", "ENERGY_FLOOR_PCT", "INTERVAL_MARGIN", "LinearFit", "LinearStart",
           "LEVEL_FIT_ITERATIONS", "START_LENGTHS", "START_PROJECTIONS", "linear_start", "MOMENTUM", "RETRIEVAL_ITERATIONS",
           "SHADOW_BOUND", "STEP", "LevelStop", "decode_exact", "hinge_start", "retrieval_start", "level_magnitude_bounds", "rendered_cells",
           "retrieve_field", "row_depths_um", "row_offsets_um", "split_on_carriers", "fit_levels"]
