#!/usr/bin/env python
"""The scanner kernels on each OpenCL implementation here, in one run on one machine.

For every implementation found (PoCL, Intel's CPU runtime, Oclgrind, any
GPU driver) × kernel variant (work-item, work-group) × precision (float32,
float64) it reports:

- builds: the probe program (octcl.device.runtime.probe) and the scanner kernels;
- identical: % of 8-bit pixels equal to the float64 NumPy reference's, and
  the largest colour-index error;
- render_s: layout + forward render, and gradient_s: forward for the
  adjoint + adjoint, each the median of ``--repeats`` rounds; the rounds
  visit every configuration in turn (A B C … A B C …), so that all see the
  same machine load.

Real devices render the official Layers phantom (300,000 scatterers, the
full 512 A-scan scanner); Oclgrind, a simulator that interprets every
work-item, renders a small scene (8 A-scans, 48 µm, 300 scatterers) and is
not timed against the others. The CPU order octcl prefers
(octcl.device.runtime.CPU_ORDER) follows the render times measured here.

    python scripts/bench_implementations.py --out docs/bench --repeats 7
"""

from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

import numpy as np

from octcl import _reference as ref
from octcl.device.runtime import implementation, list_devices, probe
from octcl.device.scanner import VARIANTS, KernelSettings, ScannerKernels
from octcl.config import DEFAULT_CONFIG, ScannerConfig
from octcl.phantom import Phantom
from octcl.render import Rendering, display_vjp, render

#: The simulator's scene: small enough to interpret every work-item in about a second.
SMALL = ScannerConfig(a_scans=8, xmax_um=48.0)


def small_scene() -> Phantom:
    rng = np.random.default_rng(0)
    count = 300
    return Phantom(rng.uniform(-24, 24, count), rng.uniform(-3, 3, count), rng.uniform(0, 1536, count),
                   rng.uniform(0.1, 5.0, count))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="docs/bench", help="folder for implementations.csv")
    parser.add_argument("--repeats", type=int, default=5, help="timed rounds per configuration")
    args = parser.parse_args()

    scenes = {"layers_A": (DEFAULT_CONFIG, Phantom.baseline("layers", 42)), "small": (SMALL, small_scene())}
    references = {name: render(phantom, config, backend="numpy") for name, (config, phantom) in scenes.items()}
    rows, runs = [], []
    for key, device in list_devices():
        name = implementation(device)
        scene = "small" if name == "oclgrind" else "layers_A"
        config, phantom = scenes[scene]
        for variant in VARIANTS:
            for double in (False, True):
                row = {"implementation": name, "device": f"{key} {device.name.strip()}",
                       "version": device.driver_version.strip(), "variant": variant,
                       "precision": "float64" if double else "float32", "scene": scene,
                       "builds": probe(device).builds, "identical_pct": None, "max_index_error": None,
                       "render_s": None, "gradient_s": None}
                rows.append(row)
                if not row["builds"]:
                    continue
                try:
                    kernels = ScannerKernels(config, KernelSettings(variant=variant, double=double), device=device)
                except Exception as exc:  # a compiler that rejects the scanner: reported, not fatal
                    row["builds"] = False
                    print(f"{row['device']} {variant} {row['precision']}: {exc}", flush=True)
                    continue
                runs.append((row, kernels, phantom))

    def render_once(kernels, phantom):
        kernels.set_phantom(phantom.x_um, phantom.y_um, phantom.z_um, np.log(phantom.energy_pct))
        return Rendering.from_a_scans(kernels.forward())

    def gradient_once(kernels, phantom, rendering):
        kernels.set_phantom(phantom.x_um, phantom.y_um, phantom.z_um, np.log(phantom.energy_pct))
        forward = Rendering.from_a_scans(kernels.forward(for_adjoint=True))
        return kernels.adjoint(display_vjp(forward, forward.display - rendering.display))

    times = {id(row): ([], []) for row, _, _ in runs}
    for round_index in range(args.repeats + 1):  # round 0 warms caches up and is not counted
        for row, kernels, phantom in runs:
            start = time.perf_counter()
            rendering = render_once(kernels, phantom)
            render_s = time.perf_counter() - start
            start = time.perf_counter()
            gradient_once(kernels, phantom, references[row["scene"]])
            gradient_s = time.perf_counter() - start
            if round_index == 0:
                reference = references[row["scene"]]
                index_error = np.abs(ref.colour_index(rendering.display).astype(int)
                                     - ref.colour_index(reference.display))
                row["identical_pct"] = 100 * float(np.mean(rendering.levels == reference.levels))
                row["max_index_error"] = int(index_error.max())
            else:
                times[id(row)][0].append(render_s)
                times[id(row)][1].append(gradient_s)
    for row, _, _ in runs:
        row["render_s"], row["gradient_s"] = (float(np.median(t)) for t in times[id(row)])

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "implementations.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    print("| implementation | version | variant | precision | scene | builds | identical pixels | "
          "max index error | render (s) | gradient (s) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for row in rows:
        cells = [row["implementation"], row["version"], row["variant"], row["precision"], row["scene"],
                 "yes" if row["builds"] else "no",
                 "–" if row["identical_pct"] is None else f"{row['identical_pct']:.3f} %",
                 "–" if row["max_index_error"] is None else str(row["max_index_error"]),
                 "–" if row["render_s"] is None else f"{row['render_s']:.3f}",
                 "–" if row["gradient_s"] is None else f"{row['gradient_s']:.3f}"]
        print("| " + " | ".join(cells) + " |")
    print(f"wrote {out / 'implementations.csv'}")


if __name__ == "__main__":
    main()
