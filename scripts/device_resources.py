#!/usr/bin/env python
"""What an installed OpenCL driver makes of octcl's kernels: resources per kernel.

For each build octcl uses on the device (the scanner in float32 and, where
the device has cl_khr_fp64, float64; the depth order on CPU devices) it
prints, per kernel, what the driver reports through
``clGetKernelWorkGroupInfo``: the largest work-group it can launch, the
preferred work-group multiple (the warp/wavefront width), private memory per
work-item (spills and private arrays) and local memory per work-group. On
NVIDIA drivers the build also runs with ``-cl-nv-verbose``, whose log holds
ptxas's register count per kernel; the log is printed as it comes.

``scripts/kernel_resources.py`` compiles the same builds offline for GPU
targets without a GPU; this script reads the real driver.

    python scripts/device_resources.py --device gpu
    python scripts/device_resources.py --device gpu --json resources.json
"""

from __future__ import annotations

import argparse
import json

from octcl.device.programs import build_options, kernel_source
from octcl.device.runtime import context_for, pyopencl_module, describe, select_device
from octcl.device.scanner import WORK_GROUP_SIZE, KernelSettings, program_defines
from octcl.config import DEFAULT_CONFIG


def kernel_report(program, device) -> list[dict]:
    cl = pyopencl_module()
    info = cl.kernel_work_group_info
    rows = []
    for kernel in program.all_kernels():
        rows.append({
            "kernel": kernel.function_name,
            "max_work_group_size": kernel.get_work_group_info(info.WORK_GROUP_SIZE, device),
            "preferred_multiple": kernel.get_work_group_info(info.PREFERRED_WORK_GROUP_SIZE_MULTIPLE, device),
            "private_bytes": kernel.get_work_group_info(info.PRIVATE_MEM_SIZE, device),
            "local_bytes": kernel.get_work_group_info(info.LOCAL_MEM_SIZE, device),
        })
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default=None, help="OpenCL device choice (see `octcl devices`)")
    parser.add_argument("--json", help="write the per-kernel table here")
    args = parser.parse_args()
    cl = pyopencl_module()
    device = select_device(args.device)
    context, _ = context_for(device)
    nvidia = "nvidia" in device.vendor.lower()
    work_group_size = min(WORK_GROUP_SIZE, 1 << (device.max_work_group_size.bit_length() - 1))
    builds = [("scanner", program_defines(DEFAULT_CONFIG, KernelSettings(), work_group_size), False)]
    if device.double_fp_config:
        builds.append(("scanner", program_defines(DEFAULT_CONFIG, KernelSettings(double=True), work_group_size),
                       True))
    if device.type & cl.device_type.CPU:
        builds.append(("depth_order", (), False))
    print(f"device: {describe(device)}; driver {device.driver_version}; {device.max_compute_units} compute units, "
          f"{device.local_mem_size // 1024} KiB local memory, work-groups up to {device.max_work_group_size}")
    report = {"device": describe(device), "driver": device.driver_version, "builds": []}
    for name, defines, double in builds:
        options = build_options(defines, double) + (["-cl-nv-verbose"] if nvidia else [])
        program = cl.Program(context, kernel_source(name)).build(options=options)
        rows = kernel_report(program, device)
        label = f"{name} ({'float64' if double else 'float32'}, WG_SIZE={work_group_size})"
        print(f"\n{label}")
        print(f"{'kernel':28s} {'max WG':>7s} {'multiple':>8s} {'private B':>10s} {'local B':>8s}")
        for row in rows:
            print(f"{row['kernel']:28s} {row['max_work_group_size']:7d} {row['preferred_multiple']:8d} "
                  f"{row['private_bytes']:10d} {row['local_bytes']:8d}")
        log = program.get_build_info(device, cl.program_build_info.LOG).strip()
        if log:
            print(f"build log:\n{log}")
        report["builds"].append({"build": label, "kernels": rows, "log": log})
    if args.json:
        with open(args.json, "w", encoding="utf-8") as handle:
            json.dump(report, handle, indent=1)


if __name__ == "__main__":
    main()
