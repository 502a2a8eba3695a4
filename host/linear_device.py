"""Stage 1's ``project`` and ``hinge`` steps with the field on an OpenCL device.

:func:`retrieve_field_device` and :func:`fit_levels_device` are
:func:`octcl.host.linear.retrieve_field` and
:func:`octcl.host.linear.fit_levels` (the same iterations, constants and
stopping rules; their docstrings give the maths) with H, Hᴴ and H⁺ from
:class:`~octcl.host.field_kernels.FieldKernels`, the intervals from
:class:`~octcl.host.level_kernels.LevelKernels` and L-BFGS from
:mod:`octcl.host.lbfgs_device`. What runs once per step runs on the host
in float64 with the kernels' twin (:attr:`FieldKernels.twin`, at the
kernels' padding): the start's scale, the anchored bounds, the regularised
start, and the result's normalisation and share at the aimed levels
(:func:`octcl.host.linear._normalised_fit`), so a
:class:`~octcl.host.linear.LinearFit` from here means what one from the
host path means.

Reads from the device inside the loops:

- projections: none. Each step is enqueued whole (H, the interval
  difference, H⁺, the update: 7 kernels); the host waits for the step
  :data:`PROJECTIONS_IN_FLIGHT` behind the last enqueued before it reads the
  clock, so a budget is overrun by at most that many steps, and the
  device always has the next step queued;
- hinge fit: one read of L-BFGS's scalars per line-search trial
  (:func:`octcl.host.lbfgs_device.minimise`), and the field every
  :data:`~octcl.host.linear.LEVEL_CHECK_EVERY` iterations, whose levels are
  compared with the aim on the host with the twin,
  ``Rendering.from_a_scans(twin.apply(field)).levels``, as the result's
  ``identical`` is counted.
"""

from __future__ import annotations

import collections
import time

import numpy as np

from ..render import Rendering
from .field_kernels import FieldKernels
from .lbfgs_device import minimise
from .level_kernels import LevelKernels
from .linear import (INTERVAL_MARGIN, LEVEL_FIT_ITERATIONS, LEVEL_FIT_MEMORY, RETRIEVAL_ITERATIONS,
                     LevelStop, LinearFit, _normalised_fit, hinge_start, retrieval_start)

#: Projection steps enqueued past the one the host waits for before reading the clock.
PROJECTIONS_IN_FLIGHT = 2
#: :func:`retrieve_field_device` calls ``progress`` every this many steps, and after the last.
PROGRESS_EVERY = 10


def retrieve_field_device(kernels: FieldKernels, target, iterations: int = RETRIEVAL_ITERATIONS,
                          time_budget_s: float | None = None, progress=None, initial: np.ndarray | None = None,
                          aim: np.ndarray | None = None) -> LinearFit:
    """:func:`octcl.host.linear.retrieve_field` on ``kernels``' device (module docstring).

    Y_k = F_k + β·(F_k − F_{k−1}), F_{k+1} = Y_k + α·H⁺(P_𝓜(H·Y_k) − H·Y_k),
    α = :data:`~octcl.host.linear.STEP`, β = :data:`~octcl.host.linear.MOMENTUM`,
    H⁺ at the kernels' padding (a power of two ≥ Nx + 2R, 1024 columns for
    Nx = 512, where the host pads to 525: only the circulant extension H⁺
    inverts differs).

    Parameters
    ----------
    kernels : FieldKernels
    target, iterations, initial, aim
        As :func:`~octcl.host.linear.retrieve_field`; the default start is the
        regularised inverse at the kernels' padding.
    time_budget_s : float, optional
        Stop enqueueing once the clock, read after the step
        :data:`PROJECTIONS_IN_FLIGHT` before the last has ended, is past
        this many seconds.
    progress : callable, optional
        ``progress(iteration, iterations)`` every :data:`PROGRESS_EVERY`
        steps enqueued and after the last.

    Returns
    -------
    LinearFit
    """
    start = time.perf_counter()
    twin = kernels.twin
    aimed, initial, lower, upper = retrieval_start(target, iterations, initial, aim, twin)
    ops = LevelKernels(kernels)
    lower, upper = ops.bounds_to_device(lower, upper)
    field = kernels.to_device(initial)
    ahead, scratch = field.copy(), kernels.empty()  # Y_0 = F_0: no momentum at the first step
    pending = collections.deque()
    taken = clock_steps = 0
    while taken < iterations:
        if time_budget_s is not None and taken and time.perf_counter() - start > time_budget_s:
            clock_steps = 1
            break
        kernels.apply(ahead, out=scratch)
        ops.interval_difference(scratch, lower, upper, out=scratch)
        kernels.pseudo_inverse(scratch, out=scratch)
        pending.append(ops.momentum_step(field, ahead, scratch))
        taken += 1
        if len(pending) > PROJECTIONS_IN_FLIGHT:
            pending.popleft().wait()
        if progress is not None and taken % PROGRESS_EVERY == 0:
            progress(taken, iterations)
    if progress is not None and taken % PROGRESS_EVERY:
        progress(taken, iterations)
    found = kernels.to_host(field)
    return _normalised_fit(twin, found, aimed, taken, time.perf_counter() - start, clock_steps)


def fit_levels_device(kernels: FieldKernels, field: np.ndarray, aim: np.ndarray,
                      iterations: int = LEVEL_FIT_ITERATIONS, margin: float = INTERVAL_MARGIN,
                      time_budget_s: float | None = None) -> LinearFit:
    """:func:`octcl.host.linear.fit_levels` on ``kernels``' device (module docstring).

    L-BFGS (:func:`octcl.host.lbfgs_device.minimise`, memory
    :data:`~octcl.host.linear.LEVEL_FIT_MEMORY`) on
    f(F) = ½·Σ_p dist(|A_p|, [l_p, u_p])², A = H·F, the bounds of
    :func:`~octcl.host.linear._anchored_bounds` (one pixel pinned at |A| = 1),
    gradient Hᴴ·r, r = A − P_𝓜(A): per evaluation H, the residual with its
    sum, Hᴴ.

    Parameters
    ----------
    kernels : FieldKernels
    field : ndarray of complex, (Nz, Nx)
        The start (a retrieved field), on the host.
    aim, iterations, margin
        As :func:`~octcl.host.linear.fit_levels`: it stops sooner once every
        pixel renders at its aimed level, checked every
        :data:`~octcl.host.linear.LEVEL_CHECK_EVERY` iterations on the host
        with the twin.
    time_budget_s : float, optional
        Stop after the first iteration that ends past this many seconds.

    Returns
    -------
    LinearFit
        ``identical`` counts pixels at their aimed level.
    """
    start = time.perf_counter()
    twin = kernels.twin
    aim, field, lower, upper = hinge_start(field, aim, iterations, margin, twin)
    ops = LevelKernels(kernels)
    lower, upper = ops.bounds_to_device(lower, upper)
    a_scans = kernels.empty()

    def loss_and_gradient(field_now, gradient, scalars, slot):
        kernels.apply(field_now, out=a_scans)
        ops.hinge_residual(a_scans, lower, upper, a_scans, scalars, slot)
        kernels.adjoint(a_scans, out=gradient)

    stop = LevelStop(aim, lambda field_now: Rendering.from_a_scans(twin.apply(kernels.to_host(field_now))).levels,
                     start, time_budget_s)
    found, _ = minimise(ops.vectors, loss_and_gradient, kernels.to_device(field), iterations,
                        memory=LEVEL_FIT_MEMORY, callback=stop)
    return _normalised_fit(twin, kernels.to_host(found), aim, stop.taken, time.perf_counter() - start,
                           stop.clock_steps)


__all__ = ["PROGRESS_EVERY", "PROJECTIONS_IN_FLIGHT", "fit_levels_device", "retrieve_field_device"]
