"""CPU threads for the host's FFTs: how many cores this process may use, and which count to time."""

from __future__ import annotations

import os


def available_cores() -> int:
    """CPU cores this process may use: those it may run on, at most ``OMP_NUM_THREADS`` where set.

    ``OMP_NUM_THREADS`` is how a process is given a share of a machine's
    cores: batch schedulers set it per job, and octcl's batch mode sets it
    in each Dask worker to the worker's thread count
    (:mod:`octcl.host.batch.runner`), so that two workers on two cores use
    one core each instead of both timing and fighting over both.
    """
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cores = os.cpu_count() or 1
    share = os.environ.get("OMP_NUM_THREADS", "")
    return min(cores, int(share)) if share.isdigit() and int(share) >= 1 else cores


def thread_trials(threads: int | None, iterations: int) -> list[int]:
    """Thread counts for the first steps of a fit; after them the fastest is kept.

    Several threads beat one on an idle machine, but when other processes
    hold the cores every thread barrier waits for a descheduled thread:
    measured here, an element-wise op on a 256×512 image took 12 ms with 2
    OpenMP threads against 40 µs with 1. Timing real steps picks whichever
    holds now. The first step (FFT plans, allocations) is a warm-up and is
    not timed; then two steps with 1 thread and two with every core.
    """
    cores = available_cores()
    if threads is not None or cores == 1 or iterations < 5:
        return []
    return [1, 1, 1, cores, cores]

