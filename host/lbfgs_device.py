"""L-BFGS with its vectors on an OpenCL device: :mod:`octcl.host.lbfgs`'s algorithm, ``kernels/lbfgs.cl``'s operations.

The same method as :func:`octcl.host.lbfgs.minimise` (Nocedal 1980; Nocedal
& Wright, "Numerical optimization", 2nd ed., 2006, algorithms 7.4 and 3.1):
the two-loop recursion with H_k⁰ = ⟨s, y⟩/⟨y, y⟩ of the newest pair, a
backtracking line search on the Armijo condition (c₁ = :data:`ARMIJO`,
halving, at most :data:`MAX_HALVINGS` trials), pairs with ⟨s, y⟩ ≤ 0 not
stored, and a direction that does not descend replaced by −g with the
memory cleared; the first step along −g has length min(1, 1/‖g‖).

    d = −H_k·g,  x_{k+1} = x_k + t·d,
    t the first of t₀, t₀/2, … with f(x + t·d) ≤ f(x) + c₁·t·⟨g, d⟩.

:class:`VectorKernels` is the op: dot products go into a small device
array of scalars (``scalars``), and the recursion's updates read their
coefficients from it, so the recursion enqueues its 2m + 1 dot products
(⟨g, d⟩ the last; 2m − 1 of them computed in the pass of the update before
them) and 2m + 1 updates without waiting for any of them. The host reads that array
once before the first iteration (f and ‖g‖² at the start) and once per
line-search trial: f at the trial point, ⟨g, d⟩ of the direction, and, for
the pair the trial would make, ⟨s, y⟩, ⟨y, y⟩ and the trial gradient's
‖g‖², enqueued together with the trial so that an accepted trial needs no
second read. Dot products are sums in a fixed order (``kernels/lbfgs.cl``),
so a run repeats to the bit on one device.
"""

from __future__ import annotations

import math

import numpy as np

from .._runtime import build
from .lbfgs import ARMIJO, MAX_HALVINGS

#: Work-items of each reduction work-group (a power of two; fewer where the device allows fewer).
REDUCTION_WORK_GROUP = 64
#: Reduction work-groups per compute unit, at least :data:`MIN_REDUCTION_GROUPS`.
REDUCTION_GROUPS_PER_UNIT = 4
MIN_REDUCTION_GROUPS = 16

# Slots of the minimiser's scalars: a zero, the loss at the last point evaluated, ‖g‖² of its gradient,
# ⟨q, g⟩ of the recursion's result, ⟨y_i, q⟩ of the second loop, then per ring slot of a pair
# ⟨s, y⟩, ⟨y, y⟩ and ⟨s, q⟩ of the first loop.
_ZERO, _LOSS, _GRADIENT_SQUARED, _SLOPE, _Y_Q, _PAIRS = range(6)


def reduction_work_group(device) -> int:
    """The reductions' work-group size on ``device``: :data:`REDUCTION_WORK_GROUP`, or the largest power of
    two the device allows below it."""
    return 1 << (min(REDUCTION_WORK_GROUP, device.max_work_group_size).bit_length() - 1)


def program_defines(work_group_size: int = REDUCTION_WORK_GROUP) -> tuple:
    """Compile-time constants of ``kernels/lbfgs.cl`` and ``kernels/level_fit.cl`` (their headers)."""
    return (("WG_SIZE", work_group_size),)


def _curvature(slot: int) -> int:
    return _PAIRS + 3 * slot


def _y_squared(slot: int) -> int:
    return _PAIRS + 3 * slot + 1


def _s_q(slot: int) -> int:
    return _PAIRS + 3 * slot + 2


class VectorKernels:
    """``kernels/lbfgs.cl`` on one queue: operations on device arrays as vectors of reals.

    A device array of the kernels' real dtype or of the complex one of the
    same precision is a vector of ``reals(array)`` reals (a complex array's
    (Re, Im) pairs). Every method enqueues and returns at once.

    Parameters
    ----------
    context, queue
        As :func:`octcl._runtime.context_for` gives them; the queue in order.
    double : bool
        float64 kernels (cl_khr_fp64); default float32.

    Attributes
    ----------
    real : numpy dtype of the vectors' elements and of the scalars.
    work_group_size, groups : the reductions' work-group size and number of groups.
    partials : device array of ``groups`` reals, the group sums of the last reduction.
    """

    def __init__(self, context, queue, double: bool = False):
        import pyopencl as cl
        import pyopencl.array as cl_array

        self._cl, self._array = cl, cl_array
        self.context, self.queue = context, queue
        device = queue.device
        self.real = np.float64 if double else np.float32
        self.work_group_size = reduction_work_group(device)
        self.groups = max(MIN_REDUCTION_GROUPS, REDUCTION_GROUPS_PER_UNIT * device.max_compute_units)
        program = build(context, "lbfgs", program_defines(self.work_group_size), double)
        self._dot_partial = cl.Kernel(program, "dot_partial")
        self._finish_sum = cl.Kernel(program, "finish_sum")
        self._axpy = cl.Kernel(program, "axpy")
        self._axpy_ratio = cl.Kernel(program, "axpy_ratio")
        self._axpy_ratio_dot = cl.Kernel(program, "axpy_ratio_dot")
        self._scale_ratio = cl.Kernel(program, "scale_ratio")
        self._pair_difference = cl.Kernel(program, "pair_difference")
        self.partials = cl_array.empty(queue, self.groups, self.real)

    def reals(self, vector) -> int:
        """The number of reals of a device array: its size, twice that for a complex one."""
        return vector.nbytes // np.dtype(self.real).itemsize

    def scalars(self, count: int):
        """A device array of ``count`` reals, zero."""
        return self._array.zeros(self.queue, count, self.real)

    def dot(self, x, y, scalars, slot: int):
        """scalars[slot] = ⟨x, y⟩."""
        self._dot_partial(self.queue, (self.groups * self.work_group_size,), (self.work_group_size,), x.data, y.data,
                          np.int32(self.reals(x)), self.partials.data)
        return self.finish_sum(self.partials, scalars, slot)

    def finish_sum(self, partials, scalars, slot: int):
        """scalars[slot] = Σ partials (one work-group, a fixed order); returns its event."""
        return self._finish_sum(self.queue, (self.work_group_size,), (self.work_group_size,), partials.data,
                                np.int32(partials.size), scalars.data, np.int32(slot))

    def axpy(self, x, c: float, d, out):
        """out = x + c·d, c a number from the host."""
        return self._axpy(self.queue, (self.reals(x),), None, x.data, self.real(c), d.data, out.data)

    def axpy_ratio(self, x, y, scalars, plus: int, minus: int, divisor: int):
        """y += ((scalars[plus] − scalars[minus])/scalars[divisor])·x."""
        return self._axpy_ratio(self.queue, (self.reals(x),), None, x.data, y.data, scalars.data, np.int32(plus),
                                np.int32(minus), np.int32(divisor))

    def axpy_ratio_dot(self, x, y, scalars, plus: int, minus: int, divisor: int, z, slot: int):
        """y += ((scalars[plus] − scalars[minus])/scalars[divisor])·x, then scalars[slot] = ⟨y, z⟩ (z not y)."""
        self._axpy_ratio_dot(self.queue, (self.groups * self.work_group_size,), (self.work_group_size,), x.data,
                             y.data, scalars.data, np.int32(plus), np.int32(minus), np.int32(divisor), z.data,
                             np.int32(self.reals(y)), self.partials.data)
        return self.finish_sum(self.partials, scalars, slot)

    def scale_ratio(self, x, scalars, numerator: int, denominator: int):
        """x *= scalars[numerator]/scalars[denominator]."""
        return self._scale_ratio(self.queue, (self.reals(x),), None, x.data, scalars.data, np.int32(numerator),
                                 np.int32(denominator))

    def pair_difference(self, x_next, x, g_next, g, s, y):
        """s = x_next − x, y = g_next − g."""
        return self._pair_difference(self.queue, (self.reals(x),), None, x_next.data, x.data, g_next.data, g.data,
                                     s.data, y.data)

    def copy(self, source, out):
        """out = source."""
        return self._cl.enqueue_copy(self.queue, out.data, source.data, byte_count=source.nbytes)


def minimise(vectors: VectorKernels, loss_and_gradient, start, iterations: int, memory: int = 20, callback=None):
    """Minimise a loss over a device vector by L-BFGS (module docstring), as :func:`octcl.host.lbfgs.minimise`.

    Parameters
    ----------
    vectors : VectorKernels
    loss_and_gradient : callable
        ``loss_and_gradient(x, gradient, scalars, slot)`` enqueues f(x) into
        the device array ``scalars[slot]`` and ∇f(x) into ``gradient`` (a
        device array like ``x``; for a complex one ∂f/∂Re + i·∂f/∂Im), and
        reads nothing.
    start : pyopencl.array.Array
        The start, real or complex; left as it is.
    iterations : int
        Iterations at most.
    memory : int
        Pairs kept (m).
    callback : callable, optional
        ``callback(x)`` after each iteration, x on the device; raising
        StopIteration ends the minimisation there.

    Returns
    -------
    x : pyopencl.array.Array, like ``start``
    taken : int
        Iterations completed.
    """
    like = vectors._array.empty_like
    x, trial, gradient, trial_gradient, direction = start.copy(), like(start), like(start), like(start), like(start)
    # Ring slots of the pairs (s, y): one for each stored pair and one for the pair the next step makes.
    s_slots, y_slots = [like(start) for _ in range(memory + 1)], [like(start) for _ in range(memory + 1)]
    scalars = vectors.scalars(_PAIRS + 3 * (memory + 1))
    loss_and_gradient(x, gradient, scalars, _LOSS)
    vectors.dot(gradient, gradient, scalars, _GRADIENT_SQUARED)
    values = scalars.get()
    loss, gradient_squared = float(values[_LOSS]), float(values[_GRADIENT_SQUARED])
    pairs, taken = [], 0  # ring slots of the stored pairs, oldest first
    while taken < iterations:
        if pairs:
            _two_loop(vectors, gradient, direction, pairs, s_slots, y_slots, scalars)
            search, step, slope = direction, 1.0, None  # d = −q; ⟨g, d⟩ read with the first trial
        else:
            if gradient_squared == 0:
                break  # a stationary point
            search, step, slope = gradient, min(1.0, 1.0 / math.sqrt(gradient_squared)), -gradient_squared
        free = next(slot for slot in range(memory + 1) if slot not in pairs)
        failures = 0
        while True:
            vectors.axpy(x, -step, search, trial)
            loss_and_gradient(trial, trial_gradient, scalars, _LOSS)
            vectors.pair_difference(trial, x, trial_gradient, gradient, s_slots[free], y_slots[free])
            vectors.dot(s_slots[free], y_slots[free], scalars, _curvature(free))
            vectors.dot(y_slots[free], y_slots[free], scalars, _y_squared(free))
            vectors.dot(trial_gradient, trial_gradient, scalars, _GRADIENT_SQUARED)
            values = scalars.get()
            if slope is None:
                slope = -float(values[_SLOPE])
                if not slope < 0:  # not a descent direction: steepest descent, the memory forgotten
                    pairs.clear()
                    search, slope = gradient, -gradient_squared
                    if slope == 0:
                        return x, taken
                    step = min(1.0, 1.0 / math.sqrt(gradient_squared))
                    continue
            if values[_LOSS] <= loss + ARMIJO * step * slope:
                break
            failures += 1
            if failures == MAX_HALVINGS:
                return x, taken  # no step decreases the loss
            step *= 0.5
        if values[_curvature(free)] > 0:
            pairs.append(free)
            del pairs[:-memory]
        x, trial = trial, x
        gradient, trial_gradient = trial_gradient, gradient
        loss, gradient_squared = float(values[_LOSS]), float(values[_GRADIENT_SQUARED])
        taken += 1
        if callback is not None:
            try:
                callback(x)
            except StopIteration:
                break
    return x, taken


def _two_loop(vectors: VectorKernels, gradient, out, pairs: list, s_slots: list, y_slots: list, scalars):
    """out = H_k·g by the two-loop recursion over the stored pairs' ring slots (oldest first), enqueued, and
    scalars[_SLOPE] = ⟨out, g⟩.

    First loop, newest pair first: α_i = ⟨s_i, q⟩/⟨s_i, y_i⟩ (its numerator
    kept in the pair's slot), q −= α_i·y_i; then q *= ⟨s, y⟩/⟨y, y⟩ of the
    newest pair; second loop, oldest first: q += (α_i − ⟨y_i, q⟩/⟨s_i, y_i⟩)·s_i.
    Each update but the first loop's last computes the next dot product in
    the same pass (:meth:`VectorKernels.axpy_ratio_dot`).
    """
    vectors.copy(gradient, out)
    newest_first = pairs[::-1]
    vectors.dot(s_slots[newest_first[0]], out, scalars, _s_q(newest_first[0]))
    for slot, older in zip(newest_first[:-1], newest_first[1:]):
        vectors.axpy_ratio_dot(y_slots[slot], out, scalars, _ZERO, _s_q(slot), _curvature(slot), s_slots[older],
                               _s_q(older))
    oldest = pairs[0]
    vectors.axpy_ratio(y_slots[oldest], out, scalars, _ZERO, _s_q(oldest), _curvature(oldest))
    vectors.scale_ratio(out, scalars, _curvature(pairs[-1]), _y_squared(pairs[-1]))
    vectors.dot(y_slots[oldest], out, scalars, _Y_Q)
    for slot, newer in zip(pairs, pairs[1:]):
        vectors.axpy_ratio_dot(s_slots[slot], out, scalars, _s_q(slot), _Y_Q, _curvature(slot), y_slots[newer], _Y_Q)
    newest = pairs[-1]
    vectors.axpy_ratio_dot(s_slots[newest], out, scalars, _s_q(newest), _Y_Q, _curvature(newest), gradient, _SLOPE)


__all__ = ["MIN_REDUCTION_GROUPS", "REDUCTION_GROUPS_PER_UNIT", "REDUCTION_WORK_GROUP", "VectorKernels", "minimise",
           "program_defines", "reduction_work_group"]
