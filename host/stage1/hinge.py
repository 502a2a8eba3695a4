"""Stage 1's ``hinge`` step: L-BFGS moves a field until every pixel renders at its aimed level.

:func:`fit_levels` minimises ½·Σ_p dist(|A_p|, [l_p, u_p])² over F, A = H·F,
with one pixel pinned at |A| = 1 (:func:`~octcl.host.stage1.levels.anchored_bounds`);
:class:`LevelStop` ends it once every pixel is at its level, or past its
budget. The loop runs on a backend (:mod:`octcl.host.stage1.backend`).

References
----------
Nocedal, "Updating quasi-Newton matrices with limited storage", Math.
Comp. 35, 1980.
"""

from __future__ import annotations

import time

import numpy as np

from ...config import DEFAULT_CONFIG, ScannerConfig
from .backend import Backend, NumpyBackend
from .levels import INTERVAL_MARGIN, anchored_bounds, target_levels
from .operator import FieldOperator
from .projections import LinearFit, check_iterations, normalised_fit

#: L-BFGS iterations of :func:`fit_levels`.
LEVEL_FIT_ITERATIONS = 200
#: Pairs L-BFGS keeps (:func:`octcl.host.optim.lbfgs.minimise`'s ``memory``; SciPy's default). From the same
#: projected field of Uniform A, 5, 10 and 20 pairs all put every pixel at its level in 20 iterations,
#: taking 0.31, 0.52 and 0.66 s (``python scripts/bench_field_steps.py --threads 1``, two cores of an AMD
#: EPYC); 5 is not yet measured on the development set.
LEVEL_FIT_MEMORY = 10
#: :func:`fit_levels` compares the rendering's levels with the aimed ones every this many iterations.
LEVEL_CHECK_EVERY = 10


def fit_levels(field: np.ndarray, aim: np.ndarray, config: ScannerConfig = DEFAULT_CONFIG,
               iterations: int = LEVEL_FIT_ITERATIONS, margin: float = INTERVAL_MARGIN,
               time_budget_s: float | None = None, workers: int = 1,
               backend: Backend | None = None) -> LinearFit:
    """Move a field until every pixel of its rendering lies in its aimed level's interval: L-BFGS on a hinge.

    Minimises ½·Σ_p dist(|A_p|, [l_p, u_p])² over F, A = H·F
    (:class:`~octcl.host.stage1.operator.FieldOperator`), with the bounds of
    :func:`anchored_bounds` (one pixel pinned at |A| = 1, so that the
    display's normalisation holds exactly at zero loss). With r_p = A_p −
    P_p(A_p), P_p the projection of A_p onto its annulus (the phase kept),
    the gradient with respect to (Re F, Im F) is (Re, Im) of Hᴴ·r: two FFT
    pairs an evaluation. L-BFGS (Nocedal 1980; :mod:`octcl.host.optim.lbfgs`) reaches
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
        (:func:`octcl.host.stage1.ceiling.aimed_levels`).
    config : ScannerConfig
    iterations : int
        L-BFGS iterations at most (≥ 1); it stops sooner once every pixel
        renders at its aimed level (checked every :data:`LEVEL_CHECK_EVERY`).
    margin : float
        :func:`level_magnitude_bounds`' margin.
    time_budget_s : float, optional
        Stop after the first iteration that ends past this many seconds.
    workers : int
        FFT threads of the default backend (:attr:`~octcl.host.stage1.operator.FieldOperator.workers`;
        the same bits at any count).
    backend : NumpyBackend or OpenCLBackend, optional
        Where the iterations run (:mod:`octcl.host.stage1.backend`); default
        ``NumpyBackend(config, workers)``. On a device the level check reads
        the field and compares its levels on the host with the float64 twin.

    Returns
    -------
    LinearFit
        ``identical`` counts pixels at their aimed level.
    """
    start = time.perf_counter()
    backend = NumpyBackend(config, workers) if backend is None else backend
    aim, field, lower, upper = hinge_start(field, aim, iterations, margin, backend.operator)
    stop = LevelStop(aim, backend.levels_of, start, time_budget_s, backend.may_render)
    found = backend.hinge_steps(field, lower, upper, iterations, LEVEL_FIT_MEMORY, stop)
    return normalised_fit(backend.operator, found, aim, stop.taken, time.perf_counter() - start, stop.clock_steps)


def hinge_start(field, aim, iterations, margin: float, operator: FieldOperator):
    """What :func:`fit_levels` (and its device twin) start from, its arguments checked: the aimed levels, the
    field scaled so that max|A(F)| = 1, and the anchored intervals [l, u] (:func:`anchored_bounds`)."""
    check_iterations(iterations)
    aim = target_levels(aim, operator.config)
    field = np.asarray(field, dtype=np.complex128)
    magnitude = np.abs(operator.apply(field))
    scale = magnitude.max()
    return (aim, field / scale, *anchored_bounds(aim, magnitude / scale, margin))


class LevelStop:
    """The hinge fit's L-BFGS callback: counts the iterations, and ends the fit past its time budget or once
    every pixel renders at its aimed level, checked every :data:`LEVEL_CHECK_EVERY` iterations.

    ``levels_of(field)`` gives a field's 8-bit rendering (on the host, or from a device's field): the check.
    ``may_render(field, aim)``, where given, screens it: where a cheaper rendering of the field differs from
    the aim (a device's float32 one, :meth:`octcl.host.stage1.backend.OpenCLBackend.may_render`) it is False,
    and the exact check is left out. ``clock_steps`` is 1 where the budget ended the fit.
    """

    def __init__(self, aim: np.ndarray, levels_of, start: float, time_budget_s: float | None, may_render=None):
        self.aim, self.levels_of, self.start, self.time_budget_s = aim, levels_of, start, time_budget_s
        self.may_render = may_render
        self.taken = self.clock_steps = 0

    def __call__(self, field_now) -> None:
        self.taken += 1
        if self.time_budget_s is not None and time.perf_counter() - self.start > self.time_budget_s:
            self.clock_steps = 1
            raise StopIteration
        if self.taken % LEVEL_CHECK_EVERY or (self.may_render is not None
                                              and not self.may_render(field_now, self.aim)):
            return
        if np.array_equal(self.levels_of(field_now), self.aim):
            raise StopIteration

