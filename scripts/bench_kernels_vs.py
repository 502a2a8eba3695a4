#!/usr/bin/env python
"""The scanner kernels of this checkout against those of an earlier revision, in one run.

Both versions run in their own Python process (the earlier one from a
``git archive`` of ``--baseline``), each with its kernels compiled once; the
driver then asks them in turn, A B A B …, for one layout (until the device
has finished the work it queued), one forward render and one gradient (forward for the adjoint, then the adjoint) of the same
phantom, so that both see the same machine load. It prints each version's
median times and the median of the pair-by-pair ratios (this checkout over
the baseline: below 1 is faster).

    python scripts/bench_kernels_vs.py --baseline fee6d69 --scene layers_A --rounds 7
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

# Runs inside each version's process: compile, then time one round per line on stdin.
WORKER = r"""
import json, sys, time
import numpy as np
from octcl.device.scanner import KernelSettings, ScannerKernels
from octcl.phantom import Phantom
from octcl.render import Rendering, display_vjp
scene, device, variant = sys.argv[1], sys.argv[2] or None, sys.argv[3]
phantom = Phantom.skin(1) if scene == "skin_1" else Phantom.baseline(scene.split("_")[0], 42)
options = {} if variant == "-" else {"variant": variant}
kernels = ScannerKernels(settings=KernelSettings(**options), device=device)
log_energy = np.log(phantom.energy_pct)
args = (phantom.x_um, phantom.y_um, phantom.z_um, log_energy)
kernels.set_phantom(*args)
weight = np.ones((256, 512))
print("ready", flush=True)
for _ in sys.stdin:
    times = {}
    start = time.perf_counter(); kernels.set_phantom(*args); kernels.queue.finish()
    times["layout_s"] = time.perf_counter() - start
    start = time.perf_counter(); kernels.forward(); times["forward_s"] = time.perf_counter() - start
    start = time.perf_counter()
    rendering = Rendering.from_a_scans(kernels.forward(for_adjoint=True))
    kernels.adjoint(display_vjp(rendering, weight))
    times["gradient_s"] = time.perf_counter() - start
    print(json.dumps(times), flush=True)
"""


def export(revision: str, folder: Path) -> Path:
    """The package of ``revision`` as an importable tree: octcl/ with its kernels inside."""
    archive = folder / "tree.tar"
    with open(archive, "wb") as handle:
        subprocess.run(["git", "-C", str(REPO), "archive", revision, "octcl", "kernels"], stdout=handle, check=True)
    with tarfile.open(archive) as tar:
        tar.extractall(folder, filter="data")
    shutil.move(str(folder / "kernels"), str(folder / "octcl" / "kernels"))
    (folder / "octcl" / "kernels" / "__init__.py").touch()
    return folder


def start(path: Path | None, scene: str, device: str | None, variant: str) -> subprocess.Popen:
    env_path = [] if path is None else [str(path)]
    code = "import sys; sys.path[:0] = %r\n" % env_path + WORKER
    process = subprocess.Popen([sys.executable, "-c", code, scene, device or "", variant],
                               stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=path or REPO)
    if process.stdout.readline().strip() != "ready":
        raise RuntimeError(f"the worker for {path or 'this checkout'} did not start")
    return process


def one_round(process: subprocess.Popen) -> dict:
    process.stdin.write("go\n")
    process.stdin.flush()
    return json.loads(process.stdout.readline())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--baseline", required=True, help="git revision to compare against")
    parser.add_argument("--scene", default="layers_A", choices=("uniform_A", "layers_A", "skin_1"))
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--device", help="OpenCL device (see `octcl devices`)")
    parser.add_argument("--variant", default="-",
                        help="this checkout's kernel variant (default: its automatic choice)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        baseline = start(export(args.baseline, Path(folder)), args.scene, args.device, "-")
        current = start(None, args.scene, args.device, args.variant)
        rows = {"baseline": [], "current": []}
        for _ in range(args.rounds):
            rows["baseline"].append(one_round(baseline))
            rows["current"].append(one_round(current))
        for process in (baseline, current):
            process.stdin.close()
            process.wait()
    print(f"scene {args.scene}, {args.rounds} rounds, baseline {args.baseline}, medians:")
    for key in rows["current"][0]:
        old = np.array([row[key] for row in rows["baseline"]])
        new = np.array([row[key] for row in rows["current"]])
        print(f"  {key:11s} baseline {np.median(old):.3f}  current {np.median(new):.3f}  "
              f"current/baseline {np.median(new / old):.2f} (pairs {np.min(new / old):.2f}–{np.max(new / old):.2f})")


if __name__ == "__main__":
    main()
