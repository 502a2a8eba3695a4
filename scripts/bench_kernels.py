#!/usr/bin/env python
"""Error against run time of the OpenCL scanner kernels.

Sweeps the accuracy knobs (spreading width W, shadowing reach R², early stop
τ, float32/float64) on the official 300k phantoms and a stiff set, and
measures against the float64 NumPy reference:

- identical 8-bit pixels (%) and the largest colour-index error,
- MS-SSIM of the 8-bit images (the official implementation),
- gradient relative error ‖g − g*‖/‖g*‖ of ∂L/∂z and ∂L/∂u for the smooth
  loss L = ½·Σ(D − D_ref)²·w, against float64 kernels at W = 12, R² = 20
  (those are checked against finite differences of the reference in
  tests/device/test_scanner.py),
- render time (layout + forward, and each alone) and gradient time
  (forward + adjoint), the median of ``--repeats`` runs, and the reference's
  render time in the same run;
- with ``--memory``, instead: peak resident memory of a fresh process that
  lays out, renders and takes one gradient at the default settings.

Writes ``--out``/kernels.csv and kernels.png (error against time).

    python scripts/bench_kernels.py --out docs/bench
    python scripts/bench_kernels.py --memory
"""

from __future__ import annotations

import argparse
import dataclasses
import csv
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from octcl import _reference as ref
from octcl.device.scanner import KernelSettings, ScannerKernels
from octcl.phantom import Phantom
from octcl.render import Rendering, display_vjp, render

# The scorer and plotting (torch, Pillow) are imported in main(): the memory
# probe imports this module and must measure the scanner, not them.


def _dense_window(count: int = 300_000) -> Phantom:
    """Every scatterer inside one A-scan's contribution window."""
    rng = np.random.default_rng(0)
    return Phantom(rng.uniform(-5, 5, count), rng.uniform(-3, 3, count),
                   rng.uniform(0, 1536, count), np.full(count, 1e-3))


SCENES = {
    "uniform_A": lambda: Phantom.baseline("uniform", 42),
    "layers_A": lambda: Phantom.baseline("layers", 42),
    "skin_1": lambda: Phantom.skin(1),
    "dense_window": _dense_window,
}


def scene_names(quick: bool) -> tuple[str, ...]:
    return ("layers_A", "skin_1") if quick else tuple(SCENES)


def sweep(quick: bool) -> list[KernelSettings]:
    settings = [KernelSettings(spread_width=w) for w in ((4, 8) if quick else (4, 6, 8, 10))]
    settings += [KernelSettings(shadow_radius_sq=r2) for r2 in ((4.0, 9.0) if quick else (3.0, 4.0, 6.0, 9.0))]
    settings += [KernelSettings(min_transmission=t) for t in ((1e-3,) if quick else (1e-4, 1e-2))]
    settings += [KernelSettings(double=True)]
    return settings


def timed(function, repeats: int):
    times, result = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        result = function()
        times.append(time.perf_counter() - start)
    return float(np.median(times)), result


def gradient(kernels: ScannerKernels, target: np.ndarray, weight: np.ndarray):
    rendering = Rendering.from_a_scans(kernels.forward(for_adjoint=True))
    return kernels.adjoint(display_vjp(rendering, weight * (rendering.display - target)))


def measure_memory(scene: str) -> tuple[float, float]:
    """Peak RSS (MiB) of a fresh process before and after layout + render + one gradient.

    The first figure is the process with the phantom built and NumPy/PyOpenCL
    loaded; the difference is what the scanner itself takes. The peak is the
    kernel's VmHWM of the new process image (``getrusage`` would report the
    parent's size, inherited through fork).
    """
    code = (
        "import re, sys, numpy as np\n"
        "def peak():\n"
        "    return float(re.search(r'VmHWM:\\s+(\\d+)', open('/proc/self/status').read()).group(1)) / 1024\n"
        f"sys.path.insert(0, {str(Path(__file__).parent)!r})\n"
        "from bench_kernels import SCENES\n"
        "from octcl.device.scanner import ScannerKernels\n"
        "from octcl.render import Rendering, display_vjp\n"
        f"p = SCENES[{scene!r}]()\n"
        "k = ScannerKernels()\n"
        "before = peak()\n"
        "k.set_phantom(p.x_um, p.y_um, p.z_um, np.log(p.energy_pct))\n"
        "r = Rendering.from_a_scans(k.forward(for_adjoint=True))\n"
        "k.adjoint(display_vjp(r, np.ones_like(r.display)))\n"
        "print(before, peak())\n")
    output = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    before, after = map(float, output.stdout.split()[-2:])
    return before, after


def _knob_label(row: dict) -> str:
    """The knob that differs from the defaults (W 8, R² 20, τ 0, float32)."""
    if row["precision"] == "float64":
        return "f64"
    if row["spread_width"] != 8:
        return f"W={row['spread_width']}"
    if row["shadow_radius_sq"] != 20:
        return f"R2={row['shadow_radius_sq']:g}"
    if row["min_transmission"]:
        return f"tau={row['min_transmission']:g}"
    return "default"


def main() -> None:
    from octcl._msssim import msssim_exact
    from octcl._plot import line_chart

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="docs/bench", help="folder for kernels.csv, kernels.png")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help="two scenes, fewer settings")
    parser.add_argument("--device", help="OpenCL device (see `octcl devices`)")
    parser.add_argument("--variant", default="auto", choices=("auto", "work-item", "work-group"),
                        help="kernel variant (kernels/scanner.cl); auto follows the device type")
    parser.add_argument("--memory", action="store_true",
                        help="only the peak-memory probe: a fresh process per scene")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.memory:
        for name in scene_names(args.quick):
            before, after = measure_memory(name)
            print(f"{name}: peak RSS {after:.0f} MiB after render + gradient at default settings "
                  f"({before:.0f} MiB before)", flush=True)
        return
    rows = []
    for name in scene_names(args.quick):
        phantom = SCENES[name]()
        log_energy = np.log(phantom.energy_pct)
        start = time.perf_counter()
        reference = render(phantom, backend="numpy")
        reference_s = time.perf_counter() - start
        rng = np.random.default_rng(1)
        target, weight = reference.display, rng.uniform(0, 1, reference.display.shape)
        best = ScannerKernels(settings=KernelSettings(spread_width=12, double=True, variant=args.variant),
                              device=args.device)
        best.set_phantom(phantom.x_um, phantom.y_um, phantom.z_um, log_energy)
        target = np.clip(target + 0.05 * rng.standard_normal(target.shape), 0, 1)
        grad_u_star, grad_z_star = gradient(best, target, weight)
        print(f"{name}: reference {reference_s:.1f} s", flush=True)
        for settings in sweep(args.quick):
            settings = dataclasses.replace(settings, variant=args.variant)
            kernels = ScannerKernels(settings=settings, device=args.device)

            def render_once():
                kernels.set_phantom(phantom.x_um, phantom.y_um, phantom.z_um, log_energy)
                return Rendering.from_a_scans(kernels.forward())

            render_s, rendering = timed(render_once, args.repeats)
            layout_s, _ = timed(lambda: kernels.set_phantom(phantom.x_um, phantom.y_um, phantom.z_um, log_energy),
                                args.repeats)
            forward_s, _ = timed(kernels.forward, args.repeats)
            gradient_s, (grad_u, grad_z) = timed(lambda: gradient(kernels, target, weight), args.repeats)
            index_error = np.abs(ref.colour_index(rendering.display).astype(int) - ref.colour_index(reference.display))
            row = {
                "scene": name, "spread_width": settings.spread_width,
                "shadow_radius_sq": settings.shadow_radius_sq, "min_transmission": settings.min_transmission,
                "precision": "float64" if settings.double else "float32", "variant": kernels.variant,
                "identical_pct": 100 * float(np.mean(rendering.levels == reference.levels)),
                "max_index_error": int(index_error.max()),
                "msssim": msssim_exact(reference.levels, rendering.levels),
                "grad_z_rel_error": float(np.linalg.norm(grad_z - grad_z_star) / np.linalg.norm(grad_z_star)),
                "grad_u_rel_error": float(np.linalg.norm(grad_u - grad_u_star) / np.linalg.norm(grad_u_star)),
                "render_s": render_s, "layout_s": layout_s, "forward_s": forward_s,
                "gradient_s": gradient_s, "reference_s": reference_s,
                "speedup_vs_reference": reference_s / render_s, "gradient_over_render": gradient_s / render_s,
            }
            rows.append(row)
            print(json.dumps({k: (round(v, 6) if isinstance(v, float) else v) for k, v in row.items()}), flush=True)
    with open(out / "kernels.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    # Error against time: one point per knob setting, labelled; differing
    # pixels are floored at one pixel in the whole image so that exact
    # settings still show on the log axis.
    floor_pct = 100 / (256 * 512)
    series, labels = {}, {}
    for row in rows:
        x, y = series.setdefault(row["scene"], ([], []))
        x.append(row["render_s"])
        y.append(max(100 - row["identical_pct"], floor_pct))
        labels.setdefault(row["scene"], []).append(_knob_label(row))
    line_chart(out / "kernels.png", series,
               "OpenCL scanner: error against render time, one point per knob setting",
               "render time (layout + forward), s", "% of 8-bit pixels differing from the float64 reference",
               log_y=True, connect=False, point_labels=labels)
    print(f"wrote {out / 'kernels.csv'} and {out / 'kernels.png'}")


if __name__ == "__main__":
    main()
