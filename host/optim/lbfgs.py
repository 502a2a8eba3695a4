"""L-BFGS (Nocedal, "Updating quasi-Newton matrices with limited storage", Math. Comp. 35, 1980) on one array.

The hinge fit (:func:`octcl.host.stage1.hinge.fit_levels`) minimises over the
262,144 real numbers of a 256×512 complex field. SciPy's L-BFGS-B (whose
bounds machinery, unused here, runs over every variable) took 1.08 s for
the 20 iterations that put every pixel of Uniform A at its level, this
module 0.52 s for the same 20 with the same 10 pairs (``python scripts/bench_field_steps.py --threads 1`` on two cores of an AMD EPYC). The
unbounded method is the two-loop recursion below, a few dot products and
updates of the array per stored pair (Nocedal & Wright, "Numerical
optimization", 2nd ed., Springer 2006, algorithm 7.4), with a backtracking
line search on the Armijo condition (their algorithm 3.1); written on
NumPy arrays, it is also what a device loop runs as kernels.

    d = −H_k·g,  H_k from the last m pairs (s_i, y_i) = (x_{i+1} − x_i, g_{i+1} − g_i),
    x_{k+1} = x_k + t·d,  t the first of 1, ½, ¼, … with f(x + t·d) ≤ f(x) + c₁·t·⟨g, d⟩.

A pair with ⟨s, y⟩ ≤ 0 (the loss is not convex) is not stored, and a
direction that does not descend is replaced by −g with the memory cleared.
"""

from __future__ import annotations

import numpy as np

#: c₁ of the Armijo condition.
ARMIJO = 1e-4
#: Steps an iteration tries at most before it gives up (the default of :func:`minimise`'s ``max_halvings``).
MAX_HALVINGS = 30


def minimise(loss_and_gradient, start: np.ndarray, iterations: int, memory: int = 20, callback=None,
             max_halvings: int = MAX_HALVINGS):
    """Minimise ``loss_and_gradient(x) -> (float, gradient like x)`` from ``start`` by L-BFGS.

    Parameters
    ----------
    loss_and_gradient : callable
    start : ndarray of float64 or complex128
        A complex array is treated as the real vector (Re, Im): its
        gradient must be ∂f/∂Re + i·∂f/∂Im.
    iterations : int
        Iterations at most.
    memory : int
        Pairs kept (m).
    callback : callable, optional
        ``callback(x)`` after each iteration; raising StopIteration ends the
        minimisation there.
    max_halvings : int
        Steps an iteration tries at most (1, ½, … 2^(1 − max_halvings)); where
        none decreases the loss enough, the minimisation ends there.

    Returns
    -------
    x : ndarray, like ``start``
    taken : int
        Iterations completed.
    """
    x = np.array(start, copy=True)
    complex_valued = np.iscomplexobj(x)

    def real(array):  # the real vector a complex array stands for, without copying
        return array.view(np.float64).ravel() if complex_valued else array.ravel()

    loss, gradient = loss_and_gradient(x)
    pairs, taken = [], 0
    while taken < iterations:
        g = real(gradient)
        direction = -_two_loop(g, pairs)
        slope = float(direction @ g)
        if not slope < 0:  # not a descent direction: steepest descent, the memory forgotten
            pairs.clear()
            direction, slope = -g, -float(g @ g)
            if slope == 0:
                break  # a stationary point
        step = 1.0 if pairs else min(1.0, 1.0 / np.sqrt(-slope))
        for _ in range(max_halvings):
            trial = x + (step * direction).view(x.dtype).reshape(x.shape) if complex_valued \
                else x + step * direction.reshape(x.shape)
            trial_loss, trial_gradient = loss_and_gradient(trial)
            if trial_loss <= loss + ARMIJO * step * slope:
                break
            step *= 0.5
        else:
            break  # no step decreases the loss
        s, y = real(trial) - real(x), real(trial_gradient) - g
        curvature = float(s @ y)
        if curvature > 0:
            pairs.append((s, y, 1.0 / curvature))
            del pairs[:-memory]
        x, loss, gradient = trial, trial_loss, trial_gradient
        taken += 1
        if callback is not None:
            try:
                callback(x)
            except StopIteration:
                break
    return x, taken


def _two_loop(gradient: np.ndarray, pairs: list) -> np.ndarray:
    """H_k·g by the two-loop recursion, H_k⁰ = ⟨s, y⟩/⟨y, y⟩ of the newest pair (identity without pairs)."""
    q = gradient.copy()
    alphas = []
    for s, y, rho in reversed(pairs):
        alpha = rho * float(s @ q)
        q -= alpha * y
        alphas.append(alpha)
    if pairs:
        s, y, _ = pairs[-1]
        q *= float(s @ y) / float(y @ y)
    for (s, y, rho), alpha in zip(pairs, reversed(alphas)):
        beta = rho * float(y @ q)
        q += (alpha - beta) * s
    return q


__all__ = ["ARMIJO", "MAX_HALVINGS", "minimise"]
