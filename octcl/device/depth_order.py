"""The Virtual Scanner's depth order: NumPy's classic ``np.argsort``.

The official scanner sorts scatterers by depth with ``np.argsort(z)`` (default
``kind='quicksort'``) before the depth-cumulative shadowing, and the order it
gives tied depths decides which tied scatterer shadows which. NumPy 1.24
and earlier run the portable C introsort ``aquicksort_`` there, which is not
stable; NumPy ≥ 1.25 on AVX-512 (and later AVX2) machines dispatches to
x86-simd-sort, which orders ties differently, so the installed
``np.argsort`` cannot stand in for it. This module computes the classic
permutation exactly (docs/scanner.md, "Residual").

Two implementations of the same algorithm sort the same integer keys
(:func:`sort_keys`): ``kernels/depth_order.cl`` on an OpenCL device, a single
work-item, and :func:`introsort_argsort_python`, pure Python, which keeps the
float64 reference free of OpenCL. :func:`depth_order` skips both when no two
keys are equal, since every correct sort then gives the same permutation.

References
----------
D. R. Musser, "Introspective sorting and selection algorithms", Software:
Practice and Experience 27 (1997) 983–993. NumPy's numpy/_core/src/npysort/
quicksort.cpp (``aquicksort_``) and heapsort.cpp (``aheapsort_``).
"""

from __future__ import annotations

import functools

import numpy as np

#: NumPy's SMALL_QUICKSORT: ranges with pr − pl > 15 are partitioned, ranges
#: of at most 16 entries are finished by insertion sort.
SMALL_PARTITION = 15

_LOW_63_BITS = np.int64(0x7FFF_FFFF_FFFF_FFFF)


def program_defines() -> tuple[tuple[str, object], ...]:
    """Compile-time constants of ``kernels/depth_order.cl`` (its header): the Python twin's SMALL_PARTITION."""
    return (("SMALL_PARTITION", SMALL_PARTITION),)


def sort_keys(values) -> np.ndarray:
    """int64 keys ordered exactly as NumPy orders the float64 ``values``.

    For the IEEE bits b of a double, b ^ ((b >> 63) & (2⁶³ − 1)) is strictly
    increasing in the value as a signed integer: non-negative doubles keep
    their bits, negative ones have their magnitude bits reversed and stay
    below zero. Before the map −0.0 becomes +0.0 (they compare equal) and
    every NaN becomes the one positive quiet NaN, so NaNs sort after +inf and
    tie with each other, as in NumPy's float ``less``.
    """
    z = np.asarray(values, dtype=np.float64).ravel() + 0.0  # −0.0 + 0.0 = +0.0
    z = np.where(np.isnan(z), np.nan, z)
    bits = z.view(np.int64)
    return bits ^ ((bits >> 63) & _LOW_63_BITS)


def introsort_depth_limit(count: int) -> int:
    """2·floor(log2 n): partitions allowed before a range is heapsorted (0 for n ≤ 1)."""
    return 2 * (max(count, 1).bit_length() - 1)


def _sift_down(key: list, order: list, base: int, slot: int, n: int) -> None:
    """Move the entry at 1-based slot ``slot`` down the max-heap of ``n`` slots at ``order[base:]``."""
    moving = order[base + slot - 1]
    child = slot << 1
    while child <= n:
        if child < n and key[order[base + child - 1]] < key[order[base + child]]:
            child += 1
        if not key[moving] < key[order[base + child - 1]]:
            break
        order[base + slot - 1] = order[base + child - 1]
        slot, child = child, child + child
    order[base + slot - 1] = moving


def _heapsort_range(key: list, order: list, first: int, n: int) -> None:
    """Heapsort ``order[first:first + n]`` by ``key`` (NumPy's ``aheapsort_``)."""
    for slot in range(n >> 1, 0, -1):
        _sift_down(key, order, first, slot, n)
    while n > 1:
        order[first], order[first + n - 1] = order[first + n - 1], order[first]
        n -= 1
        _sift_down(key, order, first, 1, n)


def introsort_argsort_python(keys) -> np.ndarray:
    """NumPy's classic argsort of ``keys``, in pure Python.

    The same algorithm as ``kernels/depth_order.cl`` (see there): median-of-3
    quicksort, insertion sort for ranges of at most 16 entries, heapsort once
    2·floor(log2 n) partitions have been spent, the larger part of every
    partition pushed on a stack. Like NumPy it permutes an index list and
    reads keys through it. 1–2 s for 300,000 keys.

    Parameters
    ----------
    keys : array_like, shape (n,)
        Integer keys from :func:`sort_keys` (or any values Python compares
        the way NumPy does: finite floats give the same result).

    Returns
    -------
    ndarray of int64, shape (n,)
    """
    key = np.asarray(keys).tolist()
    order = list(range(len(key)))
    pending = []  # (first, last, depth budget) of ranges still to sort
    pl, pr, depth = 0, len(key) - 1, introsort_depth_limit(len(key))
    while True:
        if depth < 0:
            _heapsort_range(key, order, pl, pr - pl + 1)
        else:
            while pr - pl > SMALL_PARTITION:
                pm = pl + ((pr - pl) >> 1)
                if key[order[pm]] < key[order[pl]]:
                    order[pm], order[pl] = order[pl], order[pm]
                if key[order[pr]] < key[order[pm]]:
                    order[pr], order[pm] = order[pm], order[pr]
                if key[order[pm]] < key[order[pl]]:
                    order[pm], order[pl] = order[pl], order[pm]
                pivot = key[order[pm]]
                pi, pj = pl, pr - 1
                order[pm], order[pj] = order[pj], order[pm]
                while True:  # key[pl] ≤ pivot and key[pr − 1] = pivot stop both scans
                    pi += 1
                    while key[order[pi]] < pivot:
                        pi += 1
                    pj -= 1
                    while pivot < key[order[pj]]:
                        pj -= 1
                    if pi >= pj:
                        break
                    order[pi], order[pj] = order[pj], order[pi]
                order[pi], order[pr - 1] = order[pr - 1], order[pi]
                depth -= 1
                if pi - pl < pr - pi:
                    pending.append((pi + 1, pr, depth))
                    pr = pi - 1
                else:
                    pending.append((pl, pi - 1, depth))
                    pl = pi + 1
            for pi in range(pl + 1, pr + 1):
                moving = order[pi]
                moving_key = key[moving]
                pj = pi
                while pj > pl and moving_key < key[order[pj - 1]]:
                    order[pj] = order[pj - 1]
                    pj -= 1
                order[pj] = moving
        if not pending:
            break
        pl, pr, depth = pending.pop()
    return np.array(order, dtype=np.int64)


@functools.lru_cache(maxsize=None)
def _introsort_kernel(context):
    """The built ``introsort_argsort`` kernel of ``kernels/depth_order.cl`` for ``context``."""
    import pyopencl as cl

    from .programs import build

    return cl.Kernel(build(context, "depth_order", program_defines(), False), "introsort_argsort")


def introsort_argsort_opencl(keys, device=None) -> np.ndarray:
    """NumPy's classic argsort of int64 ``keys`` by ``kernels/depth_order.cl``.

    One work-item on ``device``, a CPU device (a pyopencl device, or a
    choice for :func:`octcl.device.runtime.select_device`; default: the first CPU
    device). Returns int64 indices, shape (n,).

    Raises
    ------
    ValueError
        ``device`` is not a CPU: a single work-item would stall a GPU.
    """
    import pyopencl as cl

    from .runtime import context_for, select_device

    keys = np.ascontiguousarray(keys, dtype=np.int64)
    count = keys.size
    if count >= 2**31:
        raise ValueError(f"the OpenCL depth order takes fewer than 2**31 keys, got {count}")
    if count == 0:
        return np.zeros(0, dtype=np.int64)
    if device is None or isinstance(device, str):
        device = select_device(device or "cpu")
    if not device.type & cl.device_type.CPU:
        # One work-item on a GPU is one slow thread holding up the device:
        # octcl.device.scanner.sort_device_for sends the sort to a CPU device.
        raise ValueError(f"the depth order is a single work-item kernel and runs on CPU devices only, "
                         f"not on {device.name.strip()}")
    context, queue = context_for(device)
    mf = cl.mem_flags
    key_buffer = cl.Buffer(context, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=keys)
    order_buffer = cl.Buffer(context, mf.WRITE_ONLY, count * 4)
    params = np.array((count, introsort_depth_limit(count)),
                      dtype=[("count", "i4"), ("depth_limit", "i4")])
    _introsort_kernel(context)(queue, (1,), (1,), params, key_buffer, order_buffer)
    order = np.empty(count, dtype=np.int32)
    cl.enqueue_copy(queue, order, order_buffer)
    return order.astype(np.int64)


def _has_ties(sorted_keys: np.ndarray) -> bool:
    """True if two neighbours of the sorted keys are equal."""
    return bool(np.any(sorted_keys[1:] == sorted_keys[:-1]))


def depth_order(z_um, *, backend: str = "auto", device=None, guess=None) -> np.ndarray:
    """Indices sorting depths as NumPy's classic ``np.argsort(z_um)`` does.

    Two short-cuts come first, both exact: if no two depths are equal every
    correct sort gives the same permutation, so the stable NumPy sort is
    returned; and an array of at most 16 depths is insertion-sorted by the
    classic algorithm, which is stable. Otherwise the introsort runs on
    ``backend``.

    Parameters
    ----------
    z_um : array_like, shape (n,)
        Depths (any float64 values; NaNs sort last, as in NumPy).
    backend : {"auto", "opencl", "python"}
        "opencl": ``kernels/depth_order.cl`` on ``device`` (tens of ms for
        300,000 depths on a CPU device); "python": the pure-Python
        transcription (seconds, no OpenCL); "auto": OpenCL when a device is
        available, else Python.
    device : optional
        OpenCL device or device choice, see :func:`introsort_argsort_opencl`.
    guess : ndarray of int, shape (n,), optional
        A permutation of 0 … n − 1 close to the answer (the previous order
        while depths move a little between refinement steps). The tie check
        sorts from it, which is faster on nearly sorted data; the result does
        not depend on it.

    Returns
    -------
    ndarray of int64, shape (n,)
    """
    if backend not in ("auto", "opencl", "python"):
        raise ValueError(f"backend must be 'auto', 'opencl' or 'python', got {backend!r}")
    keys = sort_keys(z_um)
    if guess is None:
        ascending = np.argsort(keys, kind="stable")
    else:
        guess = np.asarray(guess, dtype=np.int64)
        if guess.shape != keys.shape:
            raise ValueError(f"guess has shape {guess.shape}, the depths {keys.shape}")
        ascending = guess[np.argsort(keys[guess], kind="stable")]
    if not _has_ties(keys[ascending]):
        return ascending
    if keys.size <= SMALL_PARTITION + 1:
        return np.argsort(keys, kind="stable")
    if backend == "python":
        return introsort_argsort_python(keys)
    if backend == "auto":
        from .runtime import OpenCLUnavailableError

        try:
            return introsort_argsort_opencl(keys, device)
        except (ImportError, OpenCLUnavailableError):
            return introsort_argsort_python(keys)
    return introsort_argsort_opencl(keys, device)

