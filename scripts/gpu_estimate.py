#!/usr/bin/env python
"""On paper: render and gradient time of the work-group kernels on GPUs, from counted work.

An estimate, not a measurement. For each benchmark scene it counts what one
forward render and one adjoint do in the work-group variant
(``kernels/scanner.cl``), from the scanner's own layout:

- pairs: (A-scan, candidate) pairs visited, P·(list entries), each one
  beam weight (1 exp), shadow energy and a double-word product step
  (≈ 30 flops), and a step of the work-group scan;
- taps: W spreading taps per pair inside the contribution window, each
  a sqrt and an exp (2 special-function ops) and ≈ 12 flops to spread
  (forward) or gather two grids (adjoint, counted twice);
- FFTs: 5·G·log2 G flops per complex G-point FFT, one per A-scan forward
  (G = 2·Nz), three in the adjoint;
- bytes: each list's Entry records come from memory once per pass (the P
  work-groups of a bin read the same list, a few MB at most, from L2);
  forward writes one complex slot per pair and reads it back to gather,
  the adjoint reads it, writes the pair's gradient and the reduction reads
  that again.

Time per pass = max(bytes / memory bandwidth, flops / FP32 rate,
special ops / special-function rate, latency): a roofline over the whole
GPU (512 work-groups of 128 work-items against 132 SMs, 104 CUs or 28 SMs, all
resident at the compiler-reported occupancy), with a latency floor: the
longest list's ⌈L/128⌉ chunks one after another, at an assumed
CHUNK_CYCLES each (not measured: no GPU was at hand). What a run on a GPU
would confirm or refute: that latency figure (the scans' barriers and the
waits on global loads), the load imbalance between short and long lists,
kernel launch latency (~5–10 µs each, 3–4 kernels a call),
and the host: the layout (depth order on a CPU device, bins, uploads:
measured on this machine, printed below) and PCIe transfers (z, E in;
A-scans and gradients out).

Stage 1's field solve (the default's display fit and projections,
:data:`~octcl.host.stage1.start.DISPLAY_ITERATIONS` and
:data:`~octcl.host.stage1.solve.START_PROJECTIONS` steps, then ``hinge:H``)
is counted from its kernels' passes over the (Nz, Nx) field
(:func:`field_solve_work`): per display-fit step, projection step and
hinge iteration the bytes each kernel reads and writes once (the stencils'
neighbours from cache), the FFT flops (5·n·log2 n per complex n-point
transform: two 256-point depth transforms per A-scan for H, and for H⁺ two
more and two 1024-point lateral ones per depth frequency) and the kernel
launches, at an assumed LAUNCH_S each; the hinge fit adds one read of a
few scalars per line-search trial and, every 10 iterations, the field
downloaded for the host's level check. Each step is the larger of its
memory and flop times plus its launches. The host's own part of stage 1
(the start, each step's share at aim, the result: a few float64 FFTs of
the field per step on the CPU) is measured here and printed beside it.

Peak rates are the vendors' datasheet figures (boost clock):

- NVIDIA H100 SXM5 80 GB: 3.35 TB/s HBM3, 66.9 TFLOP/s FP32 (non-tensor),
  132 SMs × 16 special-function results per clock × 1.98 GHz;
- AMD Instinct MI250, one of its two GCDs (OpenCL shows each as a device):
  1.64 TB/s HBM2e, 22.6 TFLOP/s FP32 vector, 104 CUs × 16 transcendental
  results per clock (quarter rate) × 1.7 GHz;
- NVIDIA GeForce RTX 3060 12 GB (GA106, the SynthOCT 2026 organisers'
  machine): 360 GB/s GDDR6, 12.7 TFLOP/s FP32, 28 SMs × 16
  special-function results per clock × 1.777 GHz, PCIe 4.0 x16.

    python scripts/gpu_estimate.py
"""

from __future__ import annotations

import math
import time

import numpy as np

from octcl.device.scanner import KernelSettings, ScannerKernels, contribution_ranges
from octcl.phantom import Phantom
from octcl.host.stage1.solve import START_PROJECTIONS
from octcl.host.stage1.start import DISPLAY_ITERATIONS

GPUS = {
    "NVIDIA H100 SXM5": {"bandwidth": 3.35e12, "flops": 66.9e12, "special": 132 * 16 * 1.98e9, "pcie": 25e9,
                         "clock": 1.98e9},
    "AMD MI250 (one GCD)": {"bandwidth": 1.64e12, "flops": 22.6e12, "special": 104 * 16 * 1.7e9, "pcie": 25e9,
                            "clock": 1.7e9},
    "NVIDIA RTX 3060 12 GB": {"bandwidth": 360e9, "flops": 12.7e12, "special": 28 * 16 * 1.777e9, "pcie": 25e9,
                              "clock": 1.777e9},
}
SCENES = {"layers_A": lambda: Phantom.baseline("layers", 42), "skin_1": lambda: Phantom.skin(1)}
FLOPS_PER_PAIR = 30
SPECIAL_PER_PAIR = 1
FLOPS_PER_TAP = 12
SPECIAL_PER_TAP = 2
#: Assumed cycles per chunk of WG_SIZE list entries: the forward pass's
#: product scan (7 steps, each a local-memory round trip and a barrier, twice
#: for the double word), a global load that the group must wait for, and the
#: taps; the adjoint adds the affine suffix scan and the second grid.
CHUNK_CYCLES = {"forward": 2000, "adjoint": 3000}
#: Assumed seconds per kernel launch on a GPU's in-order queue, and per blocking read of a few bytes.
LAUNCH_S = 5e-6
READ_S = 20e-6
#: Hinge iterations of the estimate: what the default's hinge step took on the development set (30-70).
HINGE_ITERATIONS = 50


def field_solve_work(nz: int = 256, nx: int = 512, padded: int = 1024, pairs: int = 10) -> dict:
    """Bytes, flops and launches of stage 1's steps on the device (module docstring), float32."""
    field, image = 8 * nz * nx, 4 * nz * nx          # a complex field, a real image
    depth_fft = 5 * nz * math.log2(nz) * nx          # one depth transform of every A-scan
    lateral_fft = 5 * padded * math.log2(padded) * nz
    apply = {"bytes": 4 * field, "flops": 2 * depth_fft + 10 * nz * nx, "launches": 2}
    display = {"bytes": 2 * apply["bytes"] + 2 * field + (2 * field + 2 * image) + 4 * image + 5 * image
               + (2 * field + image) + (3 * field + 6 * image + 4 * image),
               "flops": 2 * apply["flops"] + 200 * nz * nx, "launches": 2 * apply["launches"] + 8}
    project = {"bytes": apply["bytes"] + 3 * field + 4 * field + image * padded // nx + 6 * field,
               "flops": apply["flops"] + 2 * depth_fft + 2 * lateral_fft + 40 * nz * nx,
               "launches": apply["launches"] + 5}
    evaluation = {"bytes": 2 * apply["bytes"] + 3 * field, "flops": 2 * apply["flops"], "launches": 7}
    # The compact L-BFGS (host/optim/lbfgs_device.py): pair_dots reads the trial's and the last point and gradient and
    # the 2m stored vectors and writes the new pair; direction reads the gradient, the point and the 2m vectors
    # and writes the direction and the trial point; a finish_sums and one write of the 2m + 1 coefficients.
    compact = {"bytes": (2 * pairs + 6 + 2 * pairs + 4) * field, "flops": 2 * 4 * 2 * pairs * nz * nx,
               "launches": 4}
    hinge = {key: evaluation[key] + compact[key] for key in evaluation}
    hinge["reads"] = 1 + field / 25e9 / READ_S / 10    # a read per trial; a tenth of a download each iteration
    return {"display": display, "project": project, "hinge": hinge}


def field_solve_seconds(work: dict, gpu: dict) -> float:
    """One step: the larger of its memory and FP32 times, plus its launches and reads."""
    return (max(work["bytes"] / gpu["bandwidth"], work["flops"] / gpu["flops"]) + work["launches"] * LAUNCH_S
            + work.get("reads", 0) * READ_S)


def host_share_of_stage_1_s() -> tuple[float, float]:
    """Seconds of the host's work between stage 1's device steps on this machine: the float64 share at aim
    after a step and the hinge fit's last level check (one FieldOperator.apply and the rendering's levels),
    and the levels of the device's A-scans that screen every other level check
    (:meth:`octcl.host.stage1.backend.OpenCLBackend.may_render`, its read from the device apart)."""
    from octcl.host.stage1.operator import FieldOperator
    from octcl.render import Rendering

    operator = FieldOperator()
    field = np.random.default_rng(0).normal(size=operator.config.shape) * (1 + 0j)
    start = time.perf_counter()
    for _ in range(5):
        Rendering.from_a_scans(operator.apply(field))
    exact_s = (time.perf_counter() - start) / 5
    a_scans = operator.apply(field)
    start = time.perf_counter()
    for _ in range(5):
        Rendering.from_a_scans(a_scans)
    return exact_s, (time.perf_counter() - start) / 5


def count(phantom: Phantom, kernels: ScannerKernels) -> dict:
    config = kernels.config
    log_energy = np.log(phantom.energy_pct)
    kernels.set_phantom(phantom.x_um, phantom.y_um, phantom.z_um, log_energy)
    # The layout as refinement sees it: x, y unchanged, depths moved a little.
    moved_z_um = phantom.z_um + np.random.default_rng(0).normal(0, 0.05, phantom.z_um.size)
    start = time.perf_counter()
    kernels.set_phantom(phantom.x_um, phantom.y_um, moved_z_um, log_energy)
    layout_s = time.perf_counter() - start
    start = time.perf_counter()
    kernels._depth_order(phantom.z_um)
    depth_order_s = time.perf_counter() - start
    kernels.set_phantom(phantom.x_um, phantom.y_um, phantom.z_um, log_energy)
    list_lengths = np.diff(kernels._lateral.list_start)
    pairs = kernels.ascans_per_bin * kernels.entries
    window = contribution_ranges(phantom.x_um, phantom.y_um, config)
    contributing = int(np.sum(np.maximum(window[:, 1] - window[:, 0] + 1, 0)))
    taps = contributing * kernels.settings.spread_width
    grid, nx = kernels.grid, config.a_scans
    fft = 5 * grid * math.log2(grid)
    complex_bytes, entry_bytes = 8, kernels.entry_bytes
    forward = {"flops": pairs * FLOPS_PER_PAIR + taps * FLOPS_PER_TAP + nx * fft,
               "special": pairs * SPECIAL_PER_PAIR + taps * SPECIAL_PER_TAP,
               "bytes": kernels.entries * entry_bytes + pairs * complex_bytes * 2 + nx * config.depth_pixels * complex_bytes}
    adjoint = {"flops": pairs * FLOPS_PER_PAIR + 2 * taps * FLOPS_PER_TAP + 3 * nx * fft,
               "special": pairs * SPECIAL_PER_PAIR + taps * SPECIAL_PER_TAP,
               "bytes": kernels.entries * entry_bytes + pairs * complex_bytes * 3 + 3 * phantom.x_um.size * 8}
    transfer_bytes = {"forward": 3 * 4 * phantom.x_um.size + nx * config.depth_pixels * complex_bytes,
                      "adjoint": nx * config.depth_pixels * complex_bytes + phantom.x_um.size * complex_bytes}
    return {"pairs": pairs, "taps": taps, "layout_s": layout_s, "depth_order_s": depth_order_s,
            "chunks": int(math.ceil(list_lengths.max() / kernels.work_group_size)), "forward": forward, "adjoint": adjoint,
            "transfer_bytes": transfer_bytes, "entries": kernels.entries}


def roofline(work: dict, gpu: dict, chunks: int, chunk_cycles: int) -> tuple[float, str]:
    times = {"memory": work["bytes"] / gpu["bandwidth"], "FP32": work["flops"] / gpu["flops"],
             "special functions": work["special"] / gpu["special"],
             "latency": chunks * chunk_cycles / gpu["clock"]}
    bound = max(times, key=times.get)
    return times[bound], bound


def main() -> None:
    kernels = ScannerKernels(settings=KernelSettings(variant="work-group"))
    for name, make in SCENES.items():
        counted = count(make(), kernels)
        print(f"{name}: {counted['entries']:,} list entries, {counted['pairs']:,} pairs, {counted['taps']:,} taps, "
              f"{counted['chunks']} chunks in the longest list; host layout per refinement step on this machine "
              f"{1000 * counted['layout_s']:.0f} ms, of which the depth order (on the CPU device, from the last "
              f"order) {1000 * counted['depth_order_s']:.0f} ms")
        for gpu_name, gpu in GPUS.items():
            cells = []
            for stage in ("forward", "adjoint"):
                seconds, bound = roofline(counted[stage], gpu, counted["chunks"], CHUNK_CYCLES[stage])
                transfer = counted["transfer_bytes"][stage] / gpu["pcie"]
                cells.append(f"{stage} {1000 * seconds:.2f} ms ({bound}-bound) + PCIe {1000 * transfer:.2f} ms")
            print(f"  {gpu_name}: " + "; ".join(cells))
    work = field_solve_work()
    exact_s, screen_s = host_share_of_stage_1_s()
    checks = HINGE_ITERATIONS // 10
    print(f"stage 1, display:{DISPLAY_ITERATIONS},project:{START_PROJECTIONS},hinge:{HINGE_ITERATIONS} on the "
          f"device (float32); on this machine the host's share at aim after each of the 4 steps and the hinge's "
          f"last level check take {1000 * exact_s:.1f} ms each, its {checks - 1} screened checks before "
          f"{1000 * screen_s:.1f} ms each")
    for gpu_name, gpu in GPUS.items():
        steps = {name: field_solve_seconds(counted_work, gpu) for name, counted_work in work.items()}
        total = (DISPLAY_ITERATIONS * steps["display"] + START_PROJECTIONS * steps["project"]
                 + HINGE_ITERATIONS * steps["hinge"])
        host = 5 * exact_s + (checks - 1) * screen_s
        print(f"  {gpu_name}: display step {1e3 * steps['display']:.3f} ms, projection step "
              f"{1e3 * steps['project']:.3f} ms, hinge iteration {1e3 * steps['hinge']:.3f} ms; "
              f"stage 1 {1e3 * total:.0f} ms on the device + {1e3 * host:.0f} ms on the host")


if __name__ == "__main__":
    main()
