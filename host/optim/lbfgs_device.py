"""L-BFGS with its vectors on an OpenCL device: :mod:`octcl.host.optim.lbfgs`'s algorithm, ``kernels/lbfgs.cl``'s operations.

The same method as :func:`octcl.host.optim.lbfgs.minimise` (Nocedal 1980; Nocedal
& Wright, "Numerical optimization", 2nd ed., 2006, algorithms 7.4 and 3.1):
H_k the L-BFGS matrix of the last m pairs with H_k⁰ = γ·I, γ = ⟨s, y⟩/⟨y, y⟩
of the newest pair, a backtracking line search on the Armijo condition
(c₁ = :data:`ARMIJO`, halving, at most :data:`MAX_HALVINGS` trials), pairs
with ⟨s, y⟩ ≤ 0 not stored, and a direction that does not descend replaced
by −g with the memory cleared; the first step along −g has length
min(1, 1/‖g‖).

    d = −H_k·g,  x_{k+1} = x_k + t·d,
    t the first of t₀, t₀/2, … with f(x + t·d) ≤ f(x) + c₁·t·⟨g, d⟩.

H_k·g is computed by the compact representation of the matrix that the
host's two-loop recursion applies (Byrd, Nocedal & Schnabel,
"Representations of quasi-Newton matrices and their use in limited memory
methods", Math. Prog. 63, 1994, theorem 2.2 and §4; Nocedal & Wright §7.2):
with S and Y the n×m matrices of the stored pairs, oldest first, R the
upper triangle of SᵀY (R_ij = ⟨s_i, y_j⟩, i ≤ j) and D its diagonal,

    H_k = γ·I + [S  γ·Y]·[R⁻ᵀ(D + γ·YᵀY)R⁻¹  −R⁻ᵀ; −R⁻¹  0]·[Sᵀ; γ·Yᵀ],

so that with u = Sᵀg, v = Yᵀg and w = R⁻¹u

    H_k·g = γ·g + S·a + Y·b,   a = R⁻ᵀ((D + γ·YᵀY)·w − γ·v),   b = −γ·w,
    ⟨g, d⟩ = −(γ·‖g‖² + ⟨a, u⟩ + ⟨b, v⟩).

Per iteration this is two passes over the stored vectors instead of the
recursion's 4m: the pass that makes a trial's pair (``pair_dots``: s and y
into the ring, and every dot product below, from one read of each vector)
and the pass that forms the direction and the first trial point
(``direction``); the m×m algebra (two triangular solves) runs on the host in
float64. SᵀY's upper triangle and YᵀY are kept per ring slot and grow by a
column when a pair is stored: ⟨s_i, y_new⟩ and ⟨y_i, y_new⟩ for the stored
i, and the pair's own ⟨s, y⟩ and ⟨y, y⟩, all from the pass that made the pair.

:class:`VectorKernels` is the op: dot products go into a small device
array of scalars (``scalars``). The host reads that array once before the
first iteration (f and ‖g‖² at the start) and once per line-search trial:
f at the trial point, ‖g‖² of its gradient, u and v of its gradient and the
new column of SᵀY and YᵀY of the pair it makes, all enqueued with the trial,
so that an accepted trial needs no second read and the next direction's
⟨g, d⟩ is known before it is enqueued. The host writes the direction's
2m + 1 coefficients once per iteration. Dot products are sums in a fixed
order (``kernels/lbfgs.cl``), so a run repeats to the bit on one device.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg import solve_triangular

from ...device.programs import REDUCTION_WORK_GROUP, build, reduction_work_group
from .lbfgs import ARMIJO, MAX_HALVINGS

#: Reduction work-groups per compute unit, at least :data:`MIN_REDUCTION_GROUPS`.
REDUCTION_GROUPS_PER_UNIT = 4
MIN_REDUCTION_GROUPS = 16
#: Work-groups of :meth:`VectorKernels.pair_dots` at least (more than the reductions' where a device has few
#: compute units: Intel's CPU runtime on two cores streams the 2m + 4 vectors in 1.3 ms with 64 groups, 2.2 ms
#: with 16, m = 10, float32, 262,144 reals).
MIN_PAIR_GROUPS = 64
#: Pairs kept at most: the kernels select the ring's slots (one more than the pairs) by the bits of a
#: 64-bit mask, bits 0 to 62.
MAX_MEMORY = 62

#: :meth:`VectorKernels.pair_dots`' sums before the stored slots' four each: ⟨g', g'⟩, ⟨s, y⟩, ⟨y, y⟩,
#: ⟨s, g'⟩, ⟨y, g'⟩ of the new pair (s, y) and the trial gradient g'.
PAIR_SUMS = 5
_GRADIENT_SQUARED, _CURVATURE, _Y_SQUARED, _S_G, _Y_G = range(PAIR_SUMS)
# Slots of the minimiser's scalars: the loss at the last point evaluated, then pair_dots' sums.
_LOSS, _PAIR = 0, 1


def program_defines(work_group_size: int = REDUCTION_WORK_GROUP) -> tuple:
    """Compile-time constants of ``kernels/lbfgs.cl`` (its header): the reductions' work-group size and
    :data:`PAIR_SUMS`."""
    return (("REDUCTION_GROUP_SIZE", work_group_size), ("PAIR_SUMS", PAIR_SUMS))


def pair_sum(slot: int, which: int) -> int:
    """The index among :meth:`VectorKernels.pair_dots`' sums of ring slot ``slot``'s ⟨s_j, g'⟩ (``which`` 0),
    ⟨y_j, g'⟩ (1), ⟨s_j, y⟩ (2) or ⟨y_j, y⟩ (3)."""
    return PAIR_SUMS + 4 * slot + which


def slot_mask(slots) -> np.uint64:
    """The kernels' mask of ring slots: bit j for slot j."""
    return np.uint64(sum(1 << slot for slot in slots))


class VectorKernels:
    """``kernels/lbfgs.cl`` on one queue: operations on device arrays as vectors of reals.

    A device array of the kernels' real dtype or of the complex one of the
    same precision is a vector of ``reals(array)`` reals (a complex array's
    (Re, Im) pairs). A ring (:meth:`ring`) holds ``slots`` such vectors, slot
    j the reals from j·n. Every method enqueues and returns at once.

    Parameters
    ----------
    context, queue
        As :func:`octcl.device.runtime.context_for` gives them; the queue in order.
    double : bool
        float64 kernels (cl_khr_fp64); default float32.

    Attributes
    ----------
    real : numpy dtype of the vectors' elements and of the scalars.
    work_group_size, groups : the reductions' work-group size and number of groups.
    partials : device array of ``groups`` reals, the group sums of the last reduction.
    pair_items : work-items of :meth:`pair_dots`.
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
        self._pair_dots = cl.Kernel(program, "pair_dots")
        self._finish_sums = cl.Kernel(program, "finish_sums")
        self._direction = cl.Kernel(program, "direction")
        self.partials = cl_array.empty(queue, self.groups, self.real)
        self.pair_items = max(MIN_PAIR_GROUPS, self.groups) * self.work_group_size

    def reals(self, vector) -> int:
        """The number of reals of a device array: its size, twice that for a complex one."""
        return vector.nbytes // np.dtype(self.real).itemsize

    def scalars(self, count: int):
        """A device array of ``count`` reals, zero."""
        return self._array.zeros(self.queue, count, self.real)

    def ring(self, slots: int, like):
        """A ring of ``slots`` vectors of ``reals(like)`` reals, uninitialised."""
        return self._array.empty(self.queue, slots * self.reals(like), self.real)

    def pair_partials(self, slots: int):
        """The work-items' sums :meth:`pair_dots` writes for rings of ``slots`` slots."""
        return self._array.empty(self.queue, (PAIR_SUMS + 4 * slots) * self.pair_items, self.real)

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

    def pair_dots(self, x_next, x, g_next, g, s, y, fresh: int, stored: list, partials, scalars, base: int):
        """s_fresh = x_next − x and y_fresh = g_next − g in slot ``fresh`` of the rings ``s`` and ``y``, and into
        scalars[base + k] the sums k of ``kernels/lbfgs.cl``'s pair_dots: k < :data:`PAIR_SUMS` those of the
        new pair, k = :func:`pair_sum` (j, ·) those of each slot j of ``stored`` (``fresh`` not among them);
        ``partials`` from :meth:`pair_partials`. Returns the last event."""
        items = self.pair_items
        count = (partials.size // items - PAIR_SUMS) // 4
        mask = slot_mask(stored)
        self._pair_dots(self.queue, (items,), (self.work_group_size,), x_next.data, x.data, g_next.data, g.data,
                        s.data, y.data, np.int32(self.reals(x)), np.int32(fresh), mask, partials.data)
        return self._finish_sums(self.queue, ((PAIR_SUMS + 4 * count) * self.work_group_size,),
                                 (self.work_group_size,), partials.data, np.int32(items), mask, scalars.data,
                                 np.int32(base))

    def direction(self, g, s, y, stored: list, coefficients, x, step: float, out, trial):
        """out = c[0]·g + Σ_{j in stored} (c[1 + 2j]·s_j + c[2 + 2j]·y_j), c the device array ``coefficients``
        and s_j, y_j slot j of the rings ``s`` and ``y``, and trial = x + step·out."""
        return self._direction(self.queue, (self.reals(x),), None, g.data, s.data, y.data, np.int32(self.reals(x)),
                               slot_mask(stored), coefficients.data, x.data, self.real(step), out.data, trial.data)


def minimise(vectors: VectorKernels, loss_and_gradient, start, iterations: int, memory: int = 20, callback=None):
    """Minimise a loss over a device vector by L-BFGS (module docstring), as :func:`octcl.host.optim.lbfgs.minimise`.

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
        Pairs kept (m), 1 to :data:`MAX_MEMORY`.
    callback : callable, optional
        ``callback(x)`` after each iteration, x on the device; raising
        StopIteration ends the minimisation there.

    Returns
    -------
    x : pyopencl.array.Array, like ``start``
    taken : int
        Iterations completed.
    """
    if not 1 <= memory <= MAX_MEMORY:
        raise ValueError(f"memory must be 1 to {MAX_MEMORY} pairs, got {memory!r}")
    like = vectors._array.empty_like
    x, trial, gradient, trial_gradient, search = start.copy(), like(start), like(start), like(start), like(start)
    slots = memory + 1  # one for each stored pair and one for the pair the next step makes
    s_ring, y_ring = vectors.ring(slots, start), vectors.ring(slots, start)
    partials = vectors.pair_partials(slots)
    scalars = vectors.scalars(_PAIR + PAIR_SUMS + 4 * slots)
    coefficients = vectors.scalars(1 + 2 * slots)
    loss_and_gradient(x, gradient, scalars, _LOSS)
    vectors.dot(gradient, gradient, scalars, _PAIR + _GRADIENT_SQUARED)
    values = scalars.get()
    loss, gradient_squared = float(values[_LOSS]), float(values[_PAIR + _GRADIENT_SQUARED])
    # ⟨s_i, y_j⟩ (i stored before or with j) and ⟨y_i, y_j⟩ by ring slot; ⟨s_j, g⟩, ⟨y_j, g⟩ of the current g.
    s_y, y_y = np.zeros((slots, slots)), np.zeros((slots, slots))
    s_g, y_g = np.zeros(slots), np.zeros(slots)
    pairs, taken = [], 0  # ring slots of the stored pairs, oldest first
    while taken < iterations:
        if pairs:
            weights, curvature = _compact_coefficients(pairs, s_y, y_y, s_g, y_g, gradient_squared)
            slope = -curvature
            if not slope < 0:  # not a descent direction: steepest descent, the memory forgotten
                pairs.clear()
        if pairs:  # search = H_k·g, the trial x − search
            step = 1.0
            coefficients.set(weights.astype(vectors.real), async_=True)  # its event kept by the array, no wait
            vectors.direction(gradient, s_ring, y_ring, pairs, coefficients, x, -step, search, trial)
            along = search
        else:
            if gradient_squared == 0:
                break  # a stationary point
            along, step, slope = gradient, min(1.0, 1.0 / math.sqrt(gradient_squared)), -gradient_squared
            vectors.axpy(x, -step, along, trial)
        free = next(slot for slot in range(slots) if slot not in pairs)
        failures = 0
        while True:
            loss_and_gradient(trial, trial_gradient, scalars, _LOSS)
            vectors.pair_dots(trial, x, trial_gradient, gradient, s_ring, y_ring, free, pairs, partials, scalars,
                              _PAIR)
            values = scalars.get().astype(np.float64)
            if values[_LOSS] <= loss + ARMIJO * step * slope:
                break
            failures += 1
            if failures == MAX_HALVINGS:
                return x, taken  # no step decreases the loss
            step *= 0.5
            vectors.axpy(x, -step, along, trial)
        sums = values[_PAIR:]
        for slot in pairs:
            s_g[slot], y_g[slot] = sums[pair_sum(slot, 0)], sums[pair_sum(slot, 1)]
        s_g[free], y_g[free] = sums[_S_G], sums[_Y_G]
        if sums[_CURVATURE] > 0:
            for slot in pairs:
                s_y[slot, free] = sums[pair_sum(slot, 2)]
                y_y[slot, free] = y_y[free, slot] = sums[pair_sum(slot, 3)]
            s_y[free, free], y_y[free, free] = sums[_CURVATURE], sums[_Y_SQUARED]
            pairs.append(free)
            del pairs[:-memory]
        x, trial = trial, x
        gradient, trial_gradient = trial_gradient, gradient
        loss, gradient_squared = float(values[_LOSS]), float(sums[_GRADIENT_SQUARED])
        taken += 1
        if callback is not None:
            try:
                callback(x)
            except StopIteration:
                break
    return x, taken


def _compact_coefficients(pairs: list, s_y: np.ndarray, y_y: np.ndarray, s_g: np.ndarray, y_g: np.ndarray,
                          gradient_squared: float) -> tuple[np.ndarray, float]:
    """H_k·g's coefficients by the compact representation (module docstring), in float64, and ⟨g, H_k·g⟩.

    ``pairs`` the stored pairs' ring slots, oldest first; ``s_y``, ``y_y``
    ⟨s_i, y_j⟩ and ⟨y_i, y_j⟩ by slot (``s_y`` read above its diagonal in the
    pairs' order only); ``s_g``, ``y_g`` u and v by slot. Returns c with
    c[0] = γ, c[1 + 2j] = a_j and c[2 + 2j] = b_j for slot j (zero for the
    others), so that H_k·g = c[0]·g + Σ_j (c[1 + 2j]·s_j + c[2 + 2j]·y_j).
    """
    order = np.asarray(pairs)
    block = np.ix_(order, order)
    curvatures = s_y[block]
    newest = pairs[-1]
    gamma = s_y[newest, newest] / y_y[newest, newest]
    u, v = s_g[order], y_g[order]
    upper = np.triu(curvatures)
    w = solve_triangular(upper, u)
    a = solve_triangular(upper, np.diag(curvatures) * w + gamma * (y_y[block] @ w) - gamma * v, trans="T")
    b = -gamma * w
    weights = np.zeros(1 + 2 * len(s_g))
    weights[0], weights[1 + 2 * order], weights[2 + 2 * order] = gamma, a, b
    return weights, gamma * gradient_squared + float(a @ u) + float(b @ v)


__all__ = ["MAX_MEMORY", "MIN_PAIR_GROUPS", "MIN_REDUCTION_GROUPS", "PAIR_SUMS", "REDUCTION_GROUPS_PER_UNIT",
           "VectorKernels", "minimise", "pair_sum", "program_defines",
           "slot_mask"]
