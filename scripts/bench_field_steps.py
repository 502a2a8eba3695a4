"""Benchmark the host path's stage-1 steps, one at a time, in one process: the costs a device loop must beat.

On one target (default the official Uniform A), after the default's display
fit and projections (:data:`~octcl.host.stage1.start.DISPLAY_ITERATIONS` and
:data:`~octcl.host.stage1.solve.START_PROJECTIONS` steps):

- a display-fit step (:func:`octcl.host.stage1.display_loss.display_loss` and an Adam
  step), float32 and float64, over 50 steps of :func:`fit_field`;
- a projection step (:func:`octcl.host.stage1.projections.retrieve_field`), over 50;
- the hinge fit (:func:`octcl.host.stage1.hinge.fit_levels`) from the projected
  field to every pixel at its level, with octcl's L-BFGS
  (:mod:`octcl.host.optim.lbfgs`) at 5, 10 and 20 stored pairs, and with SciPy's
  L-BFGS-B at 10 and 20 on the same loss: iterations, seconds, share at the
  aimed level;
- the same three steps as OpenCL kernels (:mod:`octcl.host.stage1.display_device`,
  :mod:`octcl.host.stage1.backend`) on ``--device`` (default octcl's choice),
  float32, each with the host step's time over its own (a ratio of 3 or
  more: the kernels' step takes at most a third of the host's), and the
  operator H and its regularised inverse H⁺ alone, and the device's hinge fit
  with every level check exact (:class:`Unscreened`) against the default's
  screened checks (:meth:`~octcl.host.stage1.backend.OpenCLBackend.may_render`);
- MS-SSIM of one 256×512 pair: :func:`octcl._msssim.msssim_exact` (the
  window as two 1-D passes) against the 2-D window of ``scipy.signal.convolve2d``.

Every timing is the median of ``--repeats`` runs, at ``--threads`` FFT
threads. Prints a Markdown table. Example::

    python scripts/bench_field_steps.py --threads 1
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from octcl._io import read_scan
from octcl.host.stage1.ceiling import aimed_levels
from octcl.host.stage1.display import fit_field
from octcl.host.stage1.levels import target_levels
from octcl.host.stage1.operator import FieldOperator
from octcl.host.stage1.backend import NumpyBackend, OpenCLBackend
from octcl.host.stage1.solve import START_PROJECTIONS, FieldSolve, display, project
from octcl.host.stage1.start import DISPLAY_ITERATIONS
from octcl.host.stage1 import hinge, levels as stage1_levels, projections as linear
from octcl.render import Rendering

REPOSITORY = Path(__file__).resolve().parents[1]


class Unscreened(OpenCLBackend):
    """The OpenCL backend with every hinge level check exact: the float64 levels on the host each time, as
    before :meth:`~octcl.host.stage1.backend.OpenCLBackend.may_render` screened them."""

    def may_render(self, field, aim) -> bool:
        return True


def median_seconds(function, repeats: int) -> tuple[float, object]:
    times, result = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        result = function()
        times.append(time.perf_counter() - start)
    return float(np.median(times)), result


def scipy_hinge(field, aim, memory: int, iterations: int, workers: int):
    """fit_levels' loss minimised by SciPy's L-BFGS-B (no bounds), stopping as fit_levels does."""
    import scipy.optimize

    operator = FieldOperator(workers=workers)
    magnitude = np.abs(operator.apply(field))
    field = field / magnitude.max()
    lower, upper = stage1_levels.anchored_bounds(aim, magnitude / magnitude.max(), stage1_levels.INTERVAL_MARGIN)
    size, shape = field.size, field.shape

    def as_field(vector):
        return vector[:size].reshape(shape) + 1j * vector[size:].reshape(shape)

    def loss_and_gradient(vector):
        a_scans = operator.apply(as_field(vector))
        residual = a_scans - stage1_levels.interval_projection(a_scans, lower, upper)
        gradient = operator.adjoint(residual)
        return 0.5 * float(np.vdot(residual, residual).real), np.concatenate([gradient.real.ravel(),
                                                                             gradient.imag.ravel()])

    taken = [0]

    def stop_when_done(intermediate_result):  # the name asks SciPy for an OptimizeResult
        taken[0] += 1
        if taken[0] % hinge.LEVEL_CHECK_EVERY == 0 and \
                np.array_equal(Rendering.from_a_scans(operator.apply(as_field(intermediate_result.x))).levels, aim):
            raise StopIteration

    found = scipy.optimize.minimize(loss_and_gradient, np.concatenate([field.real.ravel(), field.imag.ravel()]),
                                    jac=True, method="L-BFGS-B", callback=stop_when_done,
                                    options={"maxiter": iterations, "maxcor": memory, "ftol": 0.0, "gtol": 0.0})
    levels = Rendering.from_a_scans(operator.apply(as_field(found.x))).levels
    return taken[0], float(np.mean(levels == aim))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--target", type=Path, default=REPOSITORY / "data" / "official" / "Scan_Exp1_Uniform_A.png")
    parser.add_argument("--threads", type=int, default=1, help="FFT threads (default 1)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--device", help="OpenCL device of the kernel rows (default: octcl's choice)")
    args = parser.parse_args(argv)
    levels = target_levels(read_scan(args.target))
    aim = aimed_levels(levels)
    rows = []

    host_display = {}
    for dtype in (np.float32, np.float64):
        seconds, _ = median_seconds(lambda: fit_field(levels, iterations=50, time_budget_s=None,
                                                      threads=args.threads, dtype=dtype), args.repeats)
        rows.append((f"display-fit step, {np.dtype(dtype).name}", f"{1e3 * seconds / 50:.1f} ms", ""))
        host_display[np.dtype(dtype).name] = seconds
    seconds, _ = median_seconds(lambda: linear.retrieve_field(levels, iterations=50, aim=aim,
                                                              workers=args.threads), args.repeats)
    rows.append(("projection step, complex128", f"{1e3 * seconds / 50:.1f} ms", ""))
    host_projection = seconds

    from octcl.device.runtime import describe
    from octcl.host.stage1.operator_device import FieldKernels

    kernels = FieldKernels(device=args.device)
    device = OpenCLBackend(kernels=kernels)
    fit_field(levels, iterations=2, time_budget_s=None, backend=device)  # builds and first launches, not timed
    seconds, _ = median_seconds(lambda: fit_field(levels, iterations=50, time_budget_s=None, backend=device), args.repeats)
    rows.append(("display-fit step, OpenCL float32", f"{1e3 * seconds / 50:.1f} ms",
                 f"host float32 / kernels: {host_display['float32'] / seconds:.1f}×"))
    device_field = kernels.to_device(linear.regularised_start(levels, FieldOperator()))
    for name, operation in (("H", kernels.apply), ("H⁺", kernels.pseudo_inverse)):
        def twenty_calls(operation=operation):
            for _ in range(20):
                operation(device_field, kernels.empty())
            kernels.queue.finish()

        seconds, _ = median_seconds(twenty_calls, args.repeats)
        rows.append((f"{name} of a field, OpenCL float32", f"{1e3 * seconds / 20:.2f} ms", ""))
    seconds, _ = median_seconds(lambda: linear.retrieve_field(levels, iterations=50, aim=aim, backend=device), args.repeats)
    rows.append(("projection step, OpenCL float32", f"{1e3 * seconds / 50:.1f} ms",
                 f"host complex128 / kernels: {host_projection / seconds:.1f}×"))

    start = FieldSolve(levels, aim, NumpyBackend(threads=args.threads)).run(
        display(DISPLAY_ITERATIONS) + project(START_PROJECTIONS))
    seconds, fit = median_seconds(lambda: hinge.fit_levels(start.field, aim, iterations=200, backend=device), args.repeats)
    rows.append(("hinge fit, OpenCL float32 L-BFGS, 10 pairs", f"{seconds:.2f} s",
                 f"{fit.iterations} iterations, {100 * fit.identical:.3f} % at aim"))
    exact_s, exact = median_seconds(lambda: hinge.fit_levels(start.field, aim, iterations=200,
                                                             backend=Unscreened(kernels=kernels)), args.repeats)
    rows.append(("the same, every level check exact", f"{exact_s:.2f} s",
                 f"{exact.iterations} iterations; screened / exact: {seconds / exact_s:.2f}"))
    for memory in (5, 10, 20):
        hinge.LEVEL_FIT_MEMORY = memory
        seconds, fit = median_seconds(lambda: hinge.fit_levels(start.field, aim, iterations=200,
                                                                workers=args.threads), args.repeats)
        rows.append((f"hinge fit, octcl L-BFGS, {memory} pairs", f"{seconds:.2f} s",
                     f"{fit.iterations} iterations, {100 * fit.identical:.3f} % at aim"))
    for memory in (10, 20):
        seconds, (iterations, identical) = median_seconds(
            lambda: scipy_hinge(start.field, aim, memory, 200, args.threads), args.repeats)
        rows.append((f"hinge fit, SciPy L-BFGS-B, {memory} pairs", f"{seconds:.2f} s",
                     f"{iterations} iterations, {100 * identical:.3f} % at aim"))

    from scipy.signal import convolve2d

    from octcl import _msssim

    rng = np.random.default_rng(0)
    first = rng.integers(0, 256, (256, 512)).astype(np.uint8)
    second = np.clip(first + rng.normal(0, 8, first.shape), 0, 255).astype(np.uint8)
    separable, value = median_seconds(lambda: _msssim.msssim_exact(first, second), args.repeats)
    window = _msssim._gaussian_window()
    image = first.astype(np.float64)
    one_1d, _ = median_seconds(lambda: _msssim._ssim_and_cs(image, image, window), args.repeats)
    two_d, _ = median_seconds(lambda: convolve2d(image, np.rot90(window, 2), mode="valid"), args.repeats)
    rows.append(("MS-SSIM of a 256×512 pair (5 scales)", f"{1e3 * separable:.1f} ms", f"value {value:.12f}"))
    rows.append(("finest scale: its SSIM terms (5 local means as 1-D passes) / 5 local means by the 2-D window",
                 f"{1e3 * one_1d:.1f} ms / {5e3 * two_d:.1f} ms", ""))

    print(f"target {args.target.name}, {args.threads} FFT thread(s), median of {args.repeats}; "
          f"kernels on {describe(kernels.device)}\n")
    print("| step | time | outcome |\n|---|---|---|")
    for row in rows:
        print("| " + " | ".join(row) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
