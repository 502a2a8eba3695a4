"""Thin host-side op around ``kernels/field_operator.cl``: stage 1's field operator on an OpenCL device.

:class:`FieldKernels` applies H (= Hᴴ, the operator is self-adjoint) and
the regularised inverse H⁺ of :class:`octcl.host.stage1.operator.FieldOperator`, its
float64 NumPy twin, to fields kept on the device. A field lives there A-scan
by A-scan, (Nx, Nz) in C order, so that each column is contiguous:
:meth:`FieldKernels.to_device` and :meth:`FieldKernels.to_host` convert
from and to the host's (Nz, Nx).

The kernels' radix-4/radix-2 FFTs pad the columns to a power of two
(:func:`~octcl.host.stage1.operator.padded_column_count`: 1024 for
Nx = 512), and so does the twin by default: the NumPy backend and the
kernels invert the same circulant extension, and
``tests/stage1/test_operator_device.py`` compares each kernel with the
twin as the NumPy backend runs it, on every OpenCL implementation present
(PoCL, Intel's CPU runtime, Oclgrind).

The transforms are the project's own kernels rather than a library's.
pyvkfft (VkFFT's OpenCL backend) publishes no wheel (``pip download pyvkfft
--only-binary :all:`` finds none; its sdist needs a C++ compiler and the
OpenCL headers), which would break ``pip install octcl`` on Windows and
macOS, and clFFT is unmaintained. Built here, VkFFT was no faster:
``scripts/bench_fft_library.py`` timed the depth convolution at 0.41 ms
with VkFFT against 0.37 ms with these kernels, and H⁺ at 1.70 against
1.64 ms, on Intel's CPU runtime (on PoCL 0.72 against 0.73 ms, and 5.2
against 2.2 ms), on two cores of an AMD EPYC (docs/benchmarks.md, 0.7.0).
``scripts/bench_field_steps.py`` measures them against the host path's
``scipy.fft``.
"""

from __future__ import annotations

import numpy as np

from ... import _reference as ref
from ...device.programs import build
from ...device.runtime import context_for, select_device
from ...config import DEFAULT_CONFIG, ScannerConfig
from .operator import REGULARISATION, FieldOperator, lateral_taps, padded_column_count

#: Work-items of each FFT work-group (one radix-4 butterfly each per stage of the 256-point depth transforms).
WORK_GROUP_SIZE = 64


def program_defines(config: ScannerConfig, reach: int, work_group_size: int = WORK_GROUP_SIZE) -> tuple:
    """Compile-time constants of ``kernels/field_operator.cl`` (its header)."""
    nz = config.depth_pixels
    padded = padded_column_count(config, reach)
    return (("NZ", nz), ("LOG2_NZ", nz.bit_length() - 1), ("NX", config.a_scans), ("REACH", reach),
            ("PADDED", padded), ("LOG2_PADDED", padded.bit_length() - 1), ("TWIDDLE_N", max(nz, padded)),
            ("WG_SIZE", work_group_size))


class FieldKernels:
    """H, Hᴴ and H⁺ of stage 1 on one OpenCL device (module docstring).

    Parameters
    ----------
    config : ScannerConfig
        Nz must be a power of two.
    device : pyopencl.Device or str, optional
        As :func:`octcl.device.runtime.select_device` takes it.
    double : bool
        float64 kernels (cl_khr_fp64); default float32.
    regularisation : float
        λ of H⁺ relative to max|H|² (:data:`octcl.host.stage1.operator.REGULARISATION`).

    Attributes
    ----------
    twin : FieldOperator
        The float64 twin, at the kernels' padding.
    queue, context, device
    real, complex : numpy dtypes of the device arrays.
    """

    def __init__(self, config: ScannerConfig = DEFAULT_CONFIG, device=None, double: bool = False,
                 regularisation: float = REGULARISATION):
        import pyopencl as cl
        import pyopencl.array as cl_array

        nz = config.depth_pixels
        if nz & (nz - 1):
            raise ValueError(f"the OpenCL field operator needs a power-of-two depth_pixels, got {nz}")
        self._cl, self._array = cl, cl_array
        self.config = config
        self.device = select_device(device) if device is None or isinstance(device, str) else device
        self.context, self.queue = context_for(self.device)
        self.real = np.float64 if double else np.float32
        self.complex = np.complex128 if double else np.complex64
        reach = lateral_taps(config).size // 2
        self.twin = FieldOperator(config)  # at P = padded_column_count, as the kernels
        defines = program_defines(config, reach, min(WORK_GROUP_SIZE, self.device.max_work_group_size))
        self.work_group_size = dict(defines)["WG_SIZE"]
        program = build(self.context, "field_operator", defines, double)
        self._depth_convolve = cl.Kernel(program, "depth_convolve")
        self._lateral_convolve = cl.Kernel(program, "lateral_convolve")
        self._depth_fft = cl.Kernel(program, "depth_fft")
        self._lateral_filter = cl.Kernel(program, "lateral_filter")
        twiddle_n = dict(defines)["TWIDDLE_N"]
        window = ref.hann_window(nz) / nz
        # The inverse's filter, real (Ĥ is real: w real, g even), with 1/Nz and 1/P of both inverse DFTs in it.
        inverse = self.twin.inverse_transfer(regularisation).real / (nz * self.twin.padded_columns)
        self._window = self._upload(window, self.real)
        self._taps = self._upload(self.twin.taps, self.real)
        self._twiddle = self._upload(np.exp(-2j * np.pi * np.arange(twiddle_n) / twiddle_n), self.complex)
        self._filter = self._upload(inverse, self.real)
        self._scratch = self.empty()

    def _upload(self, values, dtype):
        return self._array.to_device(self.queue, np.ascontiguousarray(values, dtype=dtype))

    # ----------------------------------------------------------- arrays
    def empty(self):
        """A device field, (Nx, Nz), uninitialised."""
        return self._array.empty(self.queue, (self.config.a_scans, self.config.depth_pixels), self.complex)

    def to_device(self, field: np.ndarray):
        """The host's (Nz, Nx) field as a device field (Nx, Nz) of the kernels' precision."""
        return self.image_to_device(field, self.complex)

    def image_to_device(self, image: np.ndarray, dtype):
        """A host (Nz, Nx) image as a device array in the fields' layout, (Nx, Nz), of ``dtype``."""
        image = np.asarray(image)
        if image.shape != self.config.shape:
            raise ValueError(f"field is {image.shape}, the scanner's grid is {self.config.shape}")
        return self._upload(image.T, dtype)

    def to_host(self, field) -> np.ndarray:
        """A device field as the host's (Nz, Nx), complex128."""
        return field.get().T.astype(np.complex128)

    # -------------------------------------------------------- operators
    def apply(self, field, out=None):
        """A = H·F (= Hᴴ·F); returns ``out`` (a new device field when None). ``out`` may be ``field``."""
        out = self.empty() if out is None else out
        nx, nz = self.config.a_scans, self.config.depth_pixels
        self._depth_convolve(self.queue, (nx * self.work_group_size,), (self.work_group_size,), field.data,
                             self._scratch.data, self._window.data, self._twiddle.data)
        self._lateral_convolve(self.queue, (nx * nz,), None, self._scratch.data, out.data, self._taps.data)
        return out

    #: Hᴴ = H: both parts have real transfer functions (``kernels/field_operator.cl``).
    adjoint = apply

    def pseudo_inverse(self, a_scans, out=None):
        """F = H⁺·A, the Tikhonov-regularised inverse at the kernels' padding; ``out`` may be ``a_scans``."""
        out = self.empty() if out is None else out
        nx, nz, group = self.config.a_scans, self.config.depth_pixels, self.work_group_size
        self._depth_fft(self.queue, (nx * group,), (group,), a_scans.data, self._scratch.data, np.int32(-1),
                        self._twiddle.data)
        self._lateral_filter(self.queue, (nz * group,), (group,), self._scratch.data, self._filter.data,
                             self._twiddle.data)
        self._depth_fft(self.queue, (nx * group,), (group,), self._scratch.data, out.data, np.int32(1),
                        self._twiddle.data)
        return out


__all__ = ["FieldKernels", "WORK_GROUP_SIZE", "program_defines"]
