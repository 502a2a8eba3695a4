"""octcl's OpenCL programs: one place that assembles, configures and builds every kernel file.

A program is ``kernels/prelude.cl`` followed by ``kernels/<name>.cl``
(:func:`kernel_source`): the prelude defines what every file shares (the
``real``/``complex_t`` types of a float32 or float64 build, ``cmul``, the
fixed-order work-group sum), so no kernel file repeats it. The prelude is
prepended rather than included: an ``#include`` needs an include path that
every compiler, pyopencl's binary cache (keyed by the source text) and the
offline GPU compilers of ``scripts/kernel_resources.py`` resolve alike,
where a prepended text is the same source everywhere. A ``#line 1``
directive after the prelude keeps a compiler's line numbers those of the
kernel file.

Constants that host and kernels must agree on are passed as ``-D``
defines from the host's own values (:func:`build_options`): a kernel file
names them and defines none of them itself. Each op's ``program_defines``
gives its file's defines; :data:`REDUCTION_WORK_GROUP` and
:func:`reduction_work_group` are the reductions' work-group size every
op shares (the define ``REDUCTION_GROUP_SIZE`` of the files that call the
prelude's ``group_sum``).

Programs are built once per (context, name, defines, precision)
(:func:`build`, memoised); pyopencl keeps the compiled binaries in its
on-disk cache, so later runs skip the compiler. Builds are serialised
across a process's threads (:data:`_BUILDING`): a run builds stage 3's
scanner on a thread while stage 1 builds its own programs
(:func:`octcl.device.scanner.scanner_in_background`), and Intel's CPU
runtime ended such a process with exit status 1, and no message, when two
compiles ran at once (its compiler's option parser is the process's).
"""

from __future__ import annotations

import threading
from importlib import resources
from pathlib import Path

from . import runtime
from .runtime import OpenCLUnavailableError, describe, has_fp64, pyopencl_module

#: The file every program starts with (module docstring).
PRELUDE = "prelude"
#: Work-items of the reductions' work-groups (a power of two; fewer where the device allows fewer).
REDUCTION_WORK_GROUP = 64

_BUILDING = threading.Lock()  # held while a program is built or looked up (module docstring)
_BUILT: dict = {}  # (context, name, defines, double) → program


def reduction_work_group(device) -> int:
    """The reductions' work-group size on ``device``: :data:`REDUCTION_WORK_GROUP`, or the largest power of
    two the device allows below it."""
    return 1 << (min(REDUCTION_WORK_GROUP, device.max_work_group_size).bit_length() - 1)


def kernel_file(name: str, directory: Path | None = None) -> str:
    """The text of ``kernels/<name>.cl`` alone, or of ``<directory>/<name>.cl``."""
    folder = resources.files("octcl.kernels") if directory is None else directory
    return folder.joinpath(f"{name}.cl").read_text(encoding="utf-8")


def kernel_source(name: str, directory: Path | None = None) -> str:
    """The source octcl builds for ``kernels/<name>.cl``: the prelude, then the file from its line 1.

    ``directory`` takes both files from another folder, as ``scripts/kernel_resources.py``
    does for its ``--kernel-dir``.
    """
    return f"{kernel_file(PRELUDE, directory)}\n#line 1\n{kernel_file(name, directory)}"


def build_options(defines: tuple[tuple[str, object], ...], double: bool) -> list[str]:
    """The OpenCL compiler options of a build: ``-DKEY=VALUE`` per define, ``-DOCTCL_DOUBLE=1`` for float64.

    Shared by :func:`build` and ``scripts/kernel_resources.py``, so that the
    kernels compiled offline for GPU targets are the ones octcl runs.
    """
    options = [f"-D{key}={value}" for key, value in defines]
    if double:
        options.append("-DOCTCL_DOUBLE=1")
    return options


def build(context, name: str, defines: tuple[tuple[str, object], ...], double: bool):
    """Build ``kernels/<name>.cl`` (after the prelude) with ``-D`` defines, once per process and one build at a
    time (module docstring); checks fp64 when asked for."""
    key = (context, name, defines, double)
    with _BUILDING:
        if key not in _BUILT:
            _BUILT[key] = _compiled(context, name, defines, double)
        return _BUILT[key]


def _compiled(context, name: str, defines: tuple[tuple[str, object], ...], double: bool):
    cl = pyopencl_module()
    device = context.devices[0]
    if double and not has_fp64(device):
        raise OpenCLUnavailableError(
            f"{describe(device)} has no double precision (cl_khr_fp64); "
            "use float32 (the default) or another device")
    try:
        # Through the module, so that a test's stand-in for runtime.quiet_build serves the probe and octcl's builds alike.
        return runtime.quiet_build(context, kernel_source(name), build_options(defines, double), device)
    except cl.RuntimeError as exc:
        raise OpenCLUnavailableError(
            f"kernels/{name}.cl failed to build on {describe(device)}:\n{exc}") from None


__all__ = ["PRELUDE", "REDUCTION_WORK_GROUP", "build", "build_options", "kernel_file", "kernel_source",
           "reduction_work_group"]
