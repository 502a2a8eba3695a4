"""Stage 1's ``project`` step: a field whose linear rendering has the aimed levels, by accelerated projections.

In this regime the scanner is the linear
operator A = H·F of :class:`~octcl.host.stage1.operator.FieldOperator` (a lateral
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
(``tests/stage1/test_projections.py`` keeps Uniform A bounded). The intervals are shrunk by :data:`INTERVAL_MARGIN` (a
tenth of their width in dB, at each end) so that the iterate lands inside
a level rather than on its edge. The start is the regularised inverse of
the de-logged target with zero phase, as in stage 1 of the physical regime,
unless given (:func:`~octcl.host.stage1.start.linear_start` gives a display fit's field).

From the regularised inverse (``python scripts/bench_linear.py --skin 3``,
docs/benchmarks.md; the 8-component score of the field's own 8-bit
rendering) the score changes by up to 9.7e−4 between 100 and 300
iterations (:data:`RETRIEVAL_ITERATIONS`) and by at most 1.6e−5 after; from
a display fit (:func:`~octcl.host.stage1.start.linear_start`) by at most 2e−6 between 100 and 600.
Within the default's stage 1 a hinge fit follows them and puts every pixel at its
level; there :data:`~octcl.host.stage1.solve.START_PROJECTIONS` is chosen by the
time to get there. A projection costs about 8 ms on two cores.

References
----------
Gerchberg & Saxton, "A practical algorithm for the determination of phase
from image and diffraction plane pictures", Optik 35, 1972.
Fienup, "Phase retrieval algorithms: a comparison", Appl. Opt. 21(15), 1982.
Nesterov, "A method of solving a convex programming problem with
convergence rate O(1/k²)", Soviet Math. Dokl. 27, 1983.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ...config import DEFAULT_CONFIG, ScannerConfig
from ...render import Rendering
from .backend import Backend, NumpyBackend
from .levels import level_magnitude_bounds, target_levels, target_magnitude
from .operator import FieldOperator

#: Projection steps of :func:`retrieve_field`.
RETRIEVAL_ITERATIONS = 300
#: α, the length of the projection step (module docstring: ≤ 1, and < 1 with momentum).
STEP = 0.8
#: β, Nesterov's momentum.
MOMENTUM = 0.9


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
                   workers: int = 1, backend: Backend | None = None) -> LinearFit:
    """A field F whose linear rendering has the target's levels: accelerated projections (module docstring).

    Parameters
    ----------
    target : ndarray
        uint8 levels (Nz, Nx), or a float image in [0, 1]
        (:func:`octcl.host.stage1.levels.target_levels`).
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
        :func:`octcl.host.stage1.ceiling.aimed_levels` gives ones the scanner writes.
    workers : int
        FFT threads of the default backend (:attr:`~octcl.host.stage1.operator.FieldOperator.workers`;
        the same bits at any count).
    backend : NumpyBackend or OpenCLBackend, optional
        Where the steps run (:mod:`octcl.host.stage1.backend`); default ``NumpyBackend(config, workers)``.
        On a device, ``time_budget_s`` is checked after the step
        :data:`~octcl.host.stage1.backend.STEPS_IN_FLIGHT` before the last enqueued has ended, and
        ``progress`` is called every :data:`~octcl.host.stage1.backend.PROGRESS_EVERY` steps.

    Returns
    -------
    LinearFit
    """
    start = time.perf_counter()
    backend = NumpyBackend(config, workers) if backend is None else backend
    aimed, field, lower, upper = retrieval_start(target, iterations, initial, aim, backend.operator)
    deadline = None if time_budget_s is None else start + time_budget_s
    field, taken, clock_steps = backend.project_steps(field, lower, upper, iterations, STEP, MOMENTUM, deadline,
                                                      progress)
    return normalised_fit(backend.operator, field, aimed, taken, time.perf_counter() - start, clock_steps)


def check_iterations(iterations) -> None:
    if not (isinstance(iterations, int) and iterations >= 1):
        raise ValueError(f"iterations must be a whole number ≥ 1, got {iterations!r}")


def retrieval_start(target, iterations, initial, aim, operator: FieldOperator):
    """What :func:`retrieve_field` (and its device twin) start from, its arguments checked: the aimed levels,
    the start scaled so that max|A(F)| = 1, and the aimed intervals [l, u] (:func:`level_magnitude_bounds`)."""
    check_iterations(iterations)
    levels = target_levels(target, operator.config)
    aimed = levels if aim is None else target_levels(aim, operator.config)
    if initial is None:
        initial = regularised_start(levels, operator)
    field = np.asarray(initial, dtype=np.complex128) / np.abs(operator.apply(initial)).max()
    return (aimed, field, *level_magnitude_bounds(aimed))


def regularised_start(levels: np.ndarray, operator: FieldOperator) -> np.ndarray:
    """The start of the projections without a given one: the regularised inverse
    (:meth:`~octcl.host.stage1.operator.FieldOperator.pseudo_inverse`) of the de-logged target, zero phase."""
    return operator.pseudo_inverse(target_magnitude(levels).astype(np.complex128))


def normalised_fit(operator: FieldOperator, field: np.ndarray, aimed: np.ndarray, iterations: int,
                    seconds: float, clock_steps: int) -> LinearFit:
    """The :class:`LinearFit` of ``field`` scaled so that max|A(F)| = 1, ``identical`` counted against ``aimed``."""
    a_scans = operator.apply(field)
    scale = np.abs(a_scans).max()
    rendering = Rendering.from_a_scans(a_scans / scale)
    return LinearFit(field=field / scale, display=rendering.display,
                     identical=float(np.mean(rendering.levels == aimed)), iterations=iterations, seconds=seconds,
                     clock_steps=clock_steps)

