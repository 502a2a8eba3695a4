"""OpenCL runtime: device choice, program builds, clear errors.

The device is chosen by the ``device`` argument, else the ``OCTCL_DEVICE``
environment variable, else the first GPU found, else the first CPU device.
A choice is one of

- ``"gpu"`` / ``"cpu"``: the first device of that type;
- ``"P:D"``: platform index P, device index D (as ``octcl devices`` lists);
- any other text: the first device whose platform or device name contains it
  (case-insensitive), e.g. ``"pocl"`` or ``"nvidia"``.

Programs are built once per (context, source, options); PyOpenCL keeps the
compiled binaries in its on-disk cache, so later runs skip the compiler.
"""

from __future__ import annotations

import functools
import os
from importlib import resources

DEVICE_ENV = "OCTCL_DEVICE"

_NO_PLATFORM_HELP = (
    "no OpenCL platform found. octcl needs an OpenCL driver: on any CPU, "
    "`pip install pocl-binary-distribution` (installed with octcl) provides PoCL; "
    "for GPUs install the vendor's OpenCL driver (NVIDIA, AMD ROCm, Intel)."
)


class OpenCLUnavailableError(RuntimeError):
    """No usable OpenCL platform or device; the message says how to get one."""


def _cl():
    try:
        import pyopencl
    except ImportError as exc:  # pragma: no cover - pyopencl is a dependency
        raise OpenCLUnavailableError(f"pyopencl cannot be imported ({exc})") from None
    return pyopencl


def list_devices() -> list[tuple[str, object]]:
    """All OpenCL devices as ("P:D", device) pairs."""
    cl = _cl()
    try:
        platforms = cl.get_platforms()
    except cl.Error:
        platforms = []
    devices = []
    for p_index, platform in enumerate(platforms):
        try:
            platform_devices = platform.get_devices()
        except cl.Error:
            continue
        for d_index, device in enumerate(platform_devices):
            devices.append((f"{p_index}:{d_index}", device))
    return devices


def describe(device) -> str:
    """One line naming a device, its platform and its memory."""
    cl = _cl()
    kind = cl.device_type.to_string(device.type).lower()
    return (f"{device.name.strip()} ({kind}, {device.platform.name.strip()}, "
            f"{device.global_mem_size / 2**30:.1f} GiB, "
            f"fp64 {'yes' if device.double_fp_config else 'no'})")


def select_device(choice: str | None = None):
    """Return the OpenCL device for ``choice`` (see the module docstring)."""
    cl = _cl()
    devices = list_devices()
    if not devices:
        raise OpenCLUnavailableError(_NO_PLATFORM_HELP)
    choice = choice if choice is not None else os.environ.get(DEVICE_ENV) or None
    if choice is None:
        for wanted in (cl.device_type.GPU, cl.device_type.CPU):
            for _, device in devices:
                if device.type & wanted:
                    return device
        return devices[0][1]
    text = choice.strip().lower()
    for key, device in devices:
        if text == key:
            return device
        if text == "gpu" and device.type & cl.device_type.GPU:
            return device
        if text == "cpu" and device.type & cl.device_type.CPU:
            return device
        if text not in ("gpu", "cpu") and (
                text in device.name.lower() or text in device.platform.name.lower()):
            return device
    listing = "; ".join(f"{key} {describe(d)}" for key, d in devices)
    raise OpenCLUnavailableError(f"no OpenCL device matches {choice!r}. Devices: {listing}")


@functools.lru_cache(maxsize=None)
def context_for(device):
    """A context and in-order queue on ``device`` (one per device per process)."""
    cl = _cl()
    context = cl.Context([device])
    return context, cl.CommandQueue(context)


def kernel_source(name: str) -> str:
    """The text of ``kernels/<name>.cl``."""
    return resources.files("octcl.kernels").joinpath(f"{name}.cl").read_text(encoding="utf-8")


def build_options(defines: tuple[tuple[str, object], ...], double: bool) -> list[str]:
    """The OpenCL compiler options of a build: ``-DKEY=VALUE`` per define, ``-DOCTCL_DOUBLE=1`` for float64.

    Shared by :func:`build` and ``scripts/kernel_resources.py``, so that the
    kernels compiled offline for GPU targets are the ones octcl runs.
    """
    options = [f"-D{key}={value}" for key, value in defines]
    if double:
        options.append("-DOCTCL_DOUBLE=1")
    return options


@functools.lru_cache(maxsize=None)
def build(context, name: str, defines: tuple[tuple[str, object], ...], double: bool):
    """Build ``kernels/<name>.cl`` with ``-D`` defines; checks fp64 when asked for."""
    cl = _cl()
    device = context.devices[0]
    if double and not device.double_fp_config:
        raise OpenCLUnavailableError(
            f"{describe(device)} has no double precision (cl_khr_fp64); "
            "use float32 (the default) or another device")
    try:
        return cl.Program(context, kernel_source(name)).build(options=build_options(defines, double))
    except cl.RuntimeError as exc:
        raise OpenCLUnavailableError(
            f"kernels/{name}.cl failed to build on {describe(device)}:\n{exc}") from None
