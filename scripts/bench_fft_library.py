"""octcl's FFT kernels against VkFFT (pyvkfft's OpenCL backend) for stage 1's operators, on one device.

Times, on a 256×512 complex64 field stored A-scan by A-scan (Nx, Nz):

- the depth convolution D (``kernels/field_operator.cl`` ``depth_convolve``:
  per A-scan a 256-point FFT, the window, the inverse, one kernel) against
  VkFFT's batched forward transform along depth, the window as a pyopencl
  elementwise product, and VkFFT's inverse;
- the regularised inverse H⁺ (:meth:`octcl.host.stage1.operator_device.FieldKernels.pseudo_inverse`:
  depth FFTs, per depth frequency a 1024-point lateral FFT, the filter and
  its inverse, the depth inverses) against the same with VkFFT: the field
  zero-padded to (1024, 256), VkFFT's 2-D forward transform, the filter,
  its 2-D inverse, the crop;

each the median of ``--repeats`` runs of ``--calls`` calls, the queue
drained; both results are compared with the float64 twin.

pyvkfft has no wheel on PyPI: build it first, for OpenCL only, with a C++
compiler and the OpenCL headers (Debian: ``apt-get install
ocl-icd-opencl-dev``)::

    VKFFT_BACKEND=opencl pip install --no-build-isolation pyvkfft
    python scripts/bench_fft_library.py --device intel
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def median_ms(run, queue, calls: int, repeats: int) -> float:
    run()
    queue.finish()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(calls):
            run()
        queue.finish()
        times.append((time.perf_counter() - start) / calls)
    return 1e3 * float(np.median(times))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", help="OpenCL device (default: octcl's choice)")
    parser.add_argument("--calls", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)
    try:
        from pyvkfft.opencl import VkFFTApp
    except ImportError:
        raise SystemExit("bench_fft_library: pyvkfft is not installed; see this script's docstring") from None
    import pyopencl.array as cl_array
    import pyopencl.elementwise as cl_elementwise

    from octcl import _reference as ref
    from octcl.device.runtime import describe
    from octcl.host.stage1.operator_device import FieldKernels

    kernels = FieldKernels(device=args.device)
    queue, config = kernels.queue, kernels.config
    nz, nx, padded = config.depth_pixels, config.a_scans, kernels.twin.padded_columns
    rng = np.random.default_rng(0)
    field = rng.normal(size=config.shape) + 1j * rng.normal(size=config.shape)
    device_field, out = kernels.to_device(field), kernels.empty()

    # D with VkFFT: batched 1-D transforms along depth (the last axis), the window between them.
    window = cl_array.to_device(queue, (ref.hann_window(nz) / nz).astype(np.float32))
    scale = cl_elementwise.ElementwiseKernel(kernels.context, "cfloat_t *x, const float *w",
                                             f"x[i] = cfloat_mulr(x[i], w[i % {nz}])", "scale_columns")
    depth_app = VkFFTApp((nx, nz), np.complex64, queue=queue, ndim=1, inplace=True, norm=0)
    work = device_field.copy()

    def vkfft_depth():
        depth_app.fft(work, work)
        scale(work, window)
        depth_app.ifft(work, work)

    ours_depth = median_ms(lambda: kernels._depth_convolve(
        queue, (nx * kernels.work_group_size,), (kernels.work_group_size,), device_field.data, out.data,
        kernels._window.data, kernels._twiddle.data), queue, args.calls, args.repeats)
    work = device_field.copy()
    theirs_depth = median_ms(vkfft_depth, queue, args.calls, args.repeats)
    check = device_field.copy()
    work = check
    vkfft_depth()
    expected = np.fft.ifft(ref.hann_window(nz)[:, None] * np.fft.fft(field, axis=0), axis=0)
    depth_error = np.abs(kernels.to_host(check) - expected).max() / np.abs(expected).max()
    kernels._depth_convolve(queue, (nx * kernels.work_group_size,), (kernels.work_group_size,), device_field.data,
                            out.data, kernels._window.data, kernels._twiddle.data)
    ours_depth_error = np.abs(kernels.to_host(out) - expected).max() / np.abs(expected).max()

    # H⁺ with VkFFT: the field zero-padded to (P, Nz), a 2-D transform, the filter, the inverse, the crop.
    filter_ = cl_array.to_device(queue, np.ascontiguousarray(
        kernels.twin.inverse_transfer().real.T / (nz * padded)).astype(np.float32))
    product = cl_elementwise.ElementwiseKernel(kernels.context, "cfloat_t *x, const float *f",
                                               "x[i] = cfloat_mulr(x[i], f[i])", "filter_spectrum")
    plane_app = VkFFTApp((padded, nz), np.complex64, queue=queue, ndim=2, inplace=True, norm=0)
    plane = cl_array.zeros(queue, (padded, nz), np.complex64)

    def vkfft_inverse():
        plane[:nx] = device_field
        plane[nx:] = 0
        plane_app.fft(plane, plane)
        product(plane, filter_)
        plane_app.ifft(plane, plane)

    ours_inverse = median_ms(lambda: kernels.pseudo_inverse(device_field, out), queue, args.calls, args.repeats)
    theirs_inverse = median_ms(vkfft_inverse, queue, args.calls, args.repeats)
    vkfft_inverse()
    expected = kernels.twin.pseudo_inverse(field)
    inverse_error = np.abs(plane[:nx].get().T - expected).max() / np.abs(expected).max()
    ours_error = np.abs(kernels.to_host(kernels.pseudo_inverse(device_field)) - expected).max() / np.abs(expected).max()

    print(f"device {describe(kernels.device)}; median of {args.repeats} × {args.calls} calls\n")
    print("| operator | octcl's kernels | VkFFT (pyvkfft) | VkFFT / octcl | max error vs float64: octcl / VkFFT |")
    print("|---|---|---|---|---|")
    print(f"| D, depth convolution | {ours_depth:.3f} ms | {theirs_depth:.3f} ms | {theirs_depth / ours_depth:.2f} | "
          f"{ours_depth_error:.1e} / {depth_error:.1e} |")
    print(f"| H⁺, regularised inverse (P = {padded}) | {ours_inverse:.3f} ms | {theirs_inverse:.3f} ms | "
          f"{theirs_inverse / ours_inverse:.2f} | {ours_error:.1e} / {inverse_error:.1e} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
