"""What importing torch costs on this machine, known before it is paid.

A time budget is the process's (``octcl invert --time-budget``), and torch
comes into a run only where it is needed: the exact score, the aim step's
loss, stage 3's loss. Whether a step fits is decided before it starts, so
the import's cost must be known before the import. It differs by more than
the rest of a short run:

- torch 2.13.0's CPU build imports in 1.0–1.2 s on two cores of an AMD EPYC
  (``scripts/bench_aim.py``);
- torch 2.11.0+cu130 took 2.9–5.3 s on an NVIDIA H200 machine (16 Xeon
  cores; docs/benchmarks.md, "On an NVIDIA H200 (0.8.0)"): a
  ``--time-budget 6`` run there, done at 3.2 s, would have started its score
  on the CPU figure and ended at about 7 s.

So :func:`import_torch` times the import where it happens and keeps the last
:data:`KEPT_TIMES` figures in octcl's cache (:class:`octcl.measured.MeasuredTimes`),
per Python interpreter and torch version; :func:`torch_import_s` answers 0
once torch is imported, the median of the figures kept where there are some
(an import from a cold page cache takes longer than the next ones: 1.6–1.7 s
against 1.1 s here; the callers' margins cover the difference), else
:data:`CPU_BUILD_IMPORT_S` for a CPU build and :data:`OTHER_BUILD_IMPORT_S`
for a CUDA or ROCm one. Which build is installed is read from the
distribution's metadata, which does not import torch: a version ending
``+cpu`` is a CPU build, ``+cu…`` or ``+rocm…`` not, and one without a local
part (PyPI's own wheels) is a CUDA build where it requires NVIDIA's
``nvidia-*`` packages (Linux) and a CPU build where it does not.

A run that will need torch can start its import at its beginning, on a
thread (:func:`import_torch_in_background`), while stage 1 works on the
device. The two still share the interpreter, which the import holds for
much of its time (on an H200 machine octcl's start-up took 0.7 s longer
beside it, and orange.png's default run went from 7.37 s to 6.86 s), and
on two CPU cores they share the cores too (the OpenCL CPU runtime uses
both; the median default run there went from 6.22 s to 5.56 s:
docs/benchmarks.md, "Work beside stage 1"). An import beside a run takes
longer: its times are kept apart (:data:`BACKGROUND`), and
:func:`torch_import_s` is what is left of such an import's expected time
(at least :data:`BACKGROUND_LEFT_MIN_S` while it runs).
"""

from __future__ import annotations

import sys
import threading
import time
from importlib import metadata

from .measured import MeasuredTimes

#: Seconds ``import torch`` is taken to cost for a CPU build nothing was measured for (1.0–1.2 s measured).
CPU_BUILD_IMPORT_S = 1.2
#: The same for a CUDA or ROCm build (2.9–5.3 s measured for 2.11.0+cu130), with a margin.
OTHER_BUILD_IMPORT_S = 6.0
#: The cache file of measured import times.
CACHE_FILE = "torch_import.json"
#: Measured import times kept per interpreter and torch version.
KEPT_TIMES = 5
#: The cache key's suffix for imports made on a thread beside a run (module docstring).
BACKGROUND = "background"
#: Factor on the foreground figure for a background import nothing was measured for (module docstring).
BACKGROUND_FACTOR = 1.5
#: Seconds a running background import is taken to need at least, whatever its expected time says.
BACKGROUND_LEFT_MIN_S = 0.1

#: The measured import times, per interpreter and torch version (and :data:`BACKGROUND`).
MEASURED = MeasuredTimes(CACHE_FILE, KEPT_TIMES)

_background: dict = {}  # "thread" and "started" (time.perf_counter()) of this process's background import


def _torch_version() -> str | None:
    try:
        return metadata.version("torch")
    except metadata.PackageNotFoundError:
        return None


def _key(version: str, mode: str = "") -> str:
    return f"{sys.executable} torch {version}" + (f" {mode}" if mode else "")


def _importing() -> bool:
    """Whether this process's background import is still running."""
    thread = _background.get("thread")
    return thread is not None and thread.is_alive()


def torch_import_s() -> float:
    """Seconds ``import torch`` would take now: 0 once imported, what is left of a background import's expected
    time while one runs, else the figure measured here before, else the build's default (module docstring)."""
    if _importing():
        expected = _expected_s(BACKGROUND)
        return max(expected - (time.perf_counter() - _background["started"]), BACKGROUND_LEFT_MIN_S)
    if "torch" in sys.modules:
        return 0.0
    return _expected_s()


def _expected_s(mode: str = "") -> float:
    """The median of the import times kept for ``mode`` (foreground ``""`` or :data:`BACKGROUND`), else the
    default: the build's for the foreground, :data:`BACKGROUND_FACTOR` times the foreground's for the background."""
    version = _torch_version()
    if version is None:
        return CPU_BUILD_IMPORT_S  # the import will fail and say why; nothing to wait for
    measured = MEASURED.median(_key(version, mode))
    if measured is not None:
        return measured
    if mode:
        return BACKGROUND_FACTOR * _expected_s()
    return CPU_BUILD_IMPORT_S if _cpu_build(version) else OTHER_BUILD_IMPORT_S


def _cpu_build(version: str) -> bool:
    local = version.partition("+")[2]
    if local:
        return local == "cpu"
    try:
        requirements = metadata.requires("torch") or []
    except metadata.PackageNotFoundError:
        requirements = []
    return not any(requirement.lower().startswith("nvidia-") for requirement in requirements)


def record_import_s(seconds: float, mode: str = "") -> None:
    """Keep ``seconds`` as an import time of this interpreter's torch, in the foreground (``mode`` ``""``) or
    the background (:data:`BACKGROUND`); the last :data:`KEPT_TIMES` of each stay, and a cache that cannot be
    written is left as it is."""
    version = _torch_version()
    if version is not None:
        MEASURED.record(_key(version, mode), seconds)


def import_torch():
    """``import torch``, timed where it is the first in this process and the time kept for
    :func:`torch_import_s` (:func:`record_import_s`); returns the module. Where a background import
    (:func:`import_torch_in_background`) has begun, it waits for that one."""
    thread = _background.get("thread")
    if thread is not None:
        thread.join()
    if "torch" in sys.modules:
        return sys.modules["torch"]
    return _timed_import()


def _timed_import(mode: str = ""):
    start = time.perf_counter()
    import torch

    record_import_s(time.perf_counter() - start, mode)
    return torch


def import_torch_in_background() -> None:
    """Begin ``import torch`` on a daemon thread, once a process and only where torch is not imported yet
    (module docstring); :func:`import_torch` then waits for it. A failed import is left for the foreground's
    :func:`import_torch` to raise again."""
    if "thread" in _background or "torch" in sys.modules:
        return

    def run():
        try:
            _timed_import(BACKGROUND)
        except Exception:  # noqa: BLE001 - the foreground's import raises it with its own traceback
            pass

    _background["started"] = time.perf_counter()
    _background["thread"] = thread = threading.Thread(target=run, name="octcl-import-torch", daemon=True)
    thread.start()


__all__ = ["BACKGROUND", "BACKGROUND_FACTOR", "BACKGROUND_LEFT_MIN_S", "CACHE_FILE", "CPU_BUILD_IMPORT_S", "KEPT_TIMES",
           "OTHER_BUILD_IMPORT_S", "import_torch", "import_torch_in_background", "record_import_s", "torch_import_s"]
