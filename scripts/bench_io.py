#!/usr/bin/env python
"""Phantom I/O and rendering overhead: load, save, ``octcl.render()`` and ``octcl render``.

Measures, on 300,000-row phantoms (the official ``layers`` baseline, seed 42,
and ``Phantom.skin(0)``, whose values are not rounded):

- ``Phantom.load`` of files written with 6–9 significant digits (the fast
  reader), of plain decimals (``np.loadtxt``), and the line-by-line reader
  that words the errors, for the ratio;
- ``Phantom.save`` at 6–9 significant digits: time, file size, and what the
  rounding does to the depths: max |z − z_file|, the carrier phase
  2·k0·|z − z_file| (k0 = 2π/λ), the 8-bit pixels of the rendering that
  change, and the SynthOCT score of the file's rendering against the
  unrounded phantom's (``--no-score`` skips it: it needs torch);
- the peak memory of loading the largest file accepted
  (``max_scatterers·MAX_ROW_BYTES`` bytes), by the fast and the exact reader;
- ``octcl.render()`` in-process: the first call (builds the scanner) and
  then in a loop, with where a loop call's time goes (cProfile, cumulative);
- ``octcl render PHANTOM -o SCAN`` as a whole command (a new process each
  time), and the Python start-up and imports it cannot avoid.

With ``--old REF`` (a git commit, e.g. the one before the fast reader) the
same load, save, render loop and whole command run with that commit's code
in the same run, alternating with today's: its ``octcl/phantom.py`` and
``octcl/render.py`` imported by path (their relative imports resolve to
today's other modules), and its whole tree (``git archive``) for the
command. With ``--inverted PHANTOM TARGET`` an inverted phantom is rendered
rounded to 6–9 significant digits and scored against its target.

Times are medians of ``--repeats`` runs: wall clock, and CPU time of this
process (all its threads) or of the child, which the other jobs on a shared
machine inflate less. The load average is printed with them.

    python scripts/bench_io.py --old fee6d69
    python scripts/bench_io.py --no-score --inverted OUT/orange.txt ../shared/data/real/orange.png
"""

from __future__ import annotations

import argparse
import cProfile
import importlib.util
import io
import json
import os
import platform
import pstats
import resource
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

from octcl import Phantom, render
from octcl._io import write_grey_png
from octcl.config import DEFAULT_CONFIG
from octcl.phantom import MAX_ROW_BYTES, PhantomError, _parse_rows_exact, round_significant
from octcl.render import _scanner_kernels

DIGITS = (6, 7, 8, 9)
ROOT = Path(__file__).resolve().parents[1]


def timed(function, repeats: int) -> tuple[float, float, object]:
    """Median wall and CPU seconds of ``repeats`` calls, and the last result."""
    walls, cpus = [], []
    for _ in range(repeats):
        wall, cpu = time.perf_counter(), time.process_time()
        result = function()
        walls.append(time.perf_counter() - wall)
        cpus.append(time.process_time() - cpu)
    return statistics.median(walls), statistics.median(cpus), result


def run_command(command: list[str], environment=None) -> tuple[float, float]:
    """Wall and child CPU seconds of one run of ``command``, in the temporary folder.

    Not in the repository: ``python -m`` puts the working directory first on
    the path, where today's ``octcl/`` would hide the old tree's.
    """
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    wall = time.perf_counter()
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=environment,
                   cwd=tempfile.gettempdir())
    wall = time.perf_counter() - wall
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime


def timed_commands(commands: list[tuple[list[str], dict | None]], repeats: int) -> list[tuple[float, float]]:
    """Median wall and child CPU seconds of each command, run in turn (A B A B …) ``repeats`` times."""
    runs = [[run_command(*command) for command in commands] for _ in range(repeats)]
    return [(statistics.median(r[i][0] for r in runs), statistics.median(r[i][1] for r in runs))
            for i in range(len(commands))]


def table(header: list[str], rows: list[list]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(cell) for cell in row) + " |" for row in rows]
    return "\n".join(lines)


def seconds(wall_cpu) -> str:
    return f"{wall_cpu[0]:.3f} / {wall_cpu[1]:.3f}"


# --------------------------------------------------------------- old code
def old_tree(ref: str, folder: Path) -> Path:
    """``ref``'s octcl, host and kernels (``git archive``), laid out as setup.cfg installs them."""
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", ref, "octcl", "host", "kernels"],
                             check=True, capture_output=True).stdout
    with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
        tar.extractall(folder, filter="data")
    (folder / "octcl" / "host").symlink_to("../host")
    (folder / "octcl" / "kernels").symlink_to("../kernels")
    return folder


def old_module(tree: Path, name: str):
    """``tree``'s ``octcl/<name>.py`` as the module ``octcl._old_<name>`` (relative imports: today's octcl)."""
    spec = importlib.util.spec_from_file_location(f"octcl._old_{name}", tree / "octcl" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


# ---------------------------------------------------------- measurements
def precision(folder: Path, repeats: int, score: bool) -> None:
    """skin_0 written with 6–9 digits: file size, times, depth and phase error, pixels and score."""
    skin = Phantom.skin(0)
    k0 = DEFAULT_CONFIG.k0_rad_per_um
    unrounded_levels = render(skin).levels
    if score:
        from octcl.scorer import score as score_scans

        write_grey_png(folder / "skin.png", unrounded_levels)
    rows = []
    for digits in DIGITS:
        path = folder / f"skin_{digits}.txt"
        save = timed(lambda: skin.save(path, significant_digits=digits), repeats)
        load = timed(lambda: Phantom.load(path), repeats)
        depth_error = np.abs(load[2].z_um - skin.z_um)
        levels = render(load[2]).levels
        changed = levels != unrounded_levels
        row = [digits, f"{path.stat().st_size / 1e6:.1f}", seconds(save), seconds(load),
               f"{depth_error.max():.1e}", f"{2 * k0 * depth_error.max():.1e}",
               f"{2 * k0 * np.sqrt(np.mean(depth_error**2)):.1e}", f"{100 * changed.mean():.3f}",
               int(np.abs(levels.astype(int) - unrounded_levels).max())]
        if score:
            write_grey_png(folder / f"skin_{digits}.png", levels)
            row.append(f"{score_scans(folder / 'skin.png', folder / f'skin_{digits}.png')['mean']:.6f}")
        rows.append(row)
    header = ["digits", "file MB", "save s (wall / CPU)", "load s (wall / CPU)", "max abs dz um",
              "max phase rad", "RMS phase rad", "pixels changed %", "max level change"]
    print("\nskin_0 (295,000 rows, unrounded) written with d significant digits and read back:\n")
    print(table(header + (["score vs unrounded"] if score else []), rows))


def load_and_save(folder: Path, repeats: int, old) -> None:
    """The layers baseline: save and load by format, today's against ``old``'s phantom module."""
    layers = Phantom.baseline("layers", 42)
    rows = []
    for digits in (5, 6, 8):  # the official baseline's, the published method's, octcl's
        path = folder / f"layers_{digits}.txt"
        save = timed(lambda: layers.save(path, significant_digits=digits), repeats)
        load = timed(lambda: Phantom.load(path), repeats)
        rows.append([f"'%.{digits - 1}e' (octcl, {digits} digits)", seconds(save), seconds(load)])
    plain = folder / "layers_plain.txt"
    np.savetxt(plain, layers.as_array(), fmt="%.6f")
    rows.append(["'%.6f' (np.loadtxt)", "", seconds(timed(lambda: Phantom.load(plain), repeats))])
    data = (folder / "layers_6.txt").read_bytes()
    exact = timed(lambda: _parse_rows_exact(plain, data, DEFAULT_CONFIG, False, 10.0), max(1, repeats // 3))
    spec = ".5e"
    python = timed(lambda: "\n".join(" ".join(format(v, spec) for v in row) for row in layers.as_array().tolist()),
                   max(1, repeats // 3))
    rows.append(["line by line (the error path) / Python format() per value", seconds(python), seconds(exact)])
    if old is not None:
        path = folder / "layers_old.txt"
        old_phantom = old.Phantom(*layers.as_array().T)
        old_save = timed(lambda: old_phantom.save(path), max(1, repeats // 3))
        old_load = timed(lambda: old.Phantom.load(path), max(1, repeats // 3))
        assert path.read_bytes() == (folder / "layers_6.txt").read_bytes()
        rows.append(["'%.5e', the old code", seconds(old_save), seconds(old_load)])
    print("\nlayers baseline (300,000 rows), save and load:\n")
    print(table(["format", "save s (wall / CPU)", "load s (wall / CPU)"], rows))


def largest_file_memory(folder: Path) -> None:
    """Peak traced memory of loading a file of exactly the size limit, by each reader."""
    limit = DEFAULT_CONFIG.max_scatterers * MAX_ROW_BYTES
    row = b"1.00000e+00 2.00000e+00 3.00000e+00 4.00000e+00"
    padded = row + b" " * (MAX_ROW_BYTES - len(row) - 1) + b"\n"
    path = folder / "largest.txt"
    path.write_bytes(padded * DEFAULT_CONFIG.max_scatterers)
    assert path.stat().st_size == limit
    results = []
    for name, text in (("fast reader", None), ("line-by-line reader", b"-1")):
        if text is not None:  # a bad last value sends the file to the line-by-line reader
            path.write_bytes(padded * (DEFAULT_CONFIG.max_scatterers - 1) + padded.replace(b"4.00000e+00", text))
        tracemalloc.start()
        try:
            Phantom.load(path)
        except PhantomError:
            pass
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        results.append([name, f"{limit / 1e6:.1f}", f"{peak / 1e6:.0f}", f"{peak / limit:.1f}"])
    print("\nlargest file accepted (300,000 rows of 256 bytes), peak memory of Phantom.load (tracemalloc):\n")
    print(table(["reader", "file MB", "peak MB", "peak / file size"], results))


def render_in_process(repeats: int, old_render) -> None:
    phantom = Phantom.baseline("layers", 42)
    _scanner_kernels.cache_clear()
    first = timed(lambda: render(phantom), 1)
    rows = [["first (builds the scanner)", f"{first[0]:.3f}", f"{first[1]:.3f}"]]
    if old_render is None:
        loop = timed(lambda: render(phantom), repeats)
        rows.append([f"later (median of {repeats})", f"{loop[0]:.3f}", f"{loop[1]:.3f}"])
    else:  # in turn, so that both see the same load
        new_runs, old_runs = [], []
        for _ in range(repeats):
            new_runs.append(timed(lambda: render(phantom), 1)[:2])
            old_runs.append(timed(lambda: old_render.render(phantom), 1)[:2])
        for name, runs in ((f"later (median of {repeats})", new_runs),
                           ("the old code, every call (a new scanner each time)", old_runs)):
            rows.append([name] + [f"{statistics.median(run[i] for run in runs):.3f}" for i in (0, 1)])
        ratio = statistics.median(old[0] / new[0] for old, new in zip(old_runs, new_runs))
        rows.append(["old / later, wall, median of the pairs", f"{ratio:.2f}", ""])
    print("\noctcl.render() of the layers baseline, in one process:\n")
    print(table(["call", "wall s", "CPU s"], rows))
    profile = cProfile.Profile()
    profile.enable()
    for _ in range(repeats):
        render(phantom)
    profile.disable()
    stats = pstats.Stats(profile).stats
    parts = {}
    for (filename, _, function), (_, _, _, cumulative, _) in stats.items():
        module = Path(filename).stem
        if module in ("render", "scanner", "depth_order", "__init__") and function in (
                "render", "set_phantom", "_depth_order", "_contribution_ranges", "forward", "from_a_scans",
                "enqueue_copy"):
            key = f"{module}.{function}" if module != "__init__" else f"pyopencl.{function}"
            parts[key] = parts.get(key, 0.0) + cumulative / repeats
    print("\nwhere a later call's time goes (cProfile, cumulative s per call; enqueue_copy waits for kernels):\n")
    print(table(["function", "s"], [[name, f"{seconds:.3f}"] for name, seconds in
                                     sorted(parts.items(), key=lambda item: -item[1])]))


#: The steps of ``octcl render PHANTOM -o SCAN`` (``octcl.cli._cmd_render``), timed one by one in a new process.
COMMAND_STEPS = """
import json, sys, time
marks = [time.perf_counter()]
import numpy as np
import octcl.cli
marks.append(time.perf_counter())
from octcl.device.runtime import context_for, select_device
device = select_device()
context_for(device)
marks.append(time.perf_counter())
from octcl.device.scanner import KernelSettings
from octcl.config import DEFAULT_CONFIG
from octcl.render import Rendering, _scanner_kernels
kernels, _ = _scanner_kernels(DEFAULT_CONFIG, KernelSettings(), device)
marks.append(time.perf_counter())
phantom = octcl.cli.Phantom.load(sys.argv[1])
phantom.validate()
marks.append(time.perf_counter())
with np.errstate(divide="ignore"):
    kernels.set_phantom(phantom.x_um, phantom.y_um, phantom.z_um, np.log(phantom.energy_pct))
marks.append(time.perf_counter())
a_scans = kernels.forward()
marks.append(time.perf_counter())
from octcl._io import write_grey_png
write_grey_png(sys.argv[2], Rendering.from_a_scans(a_scans).levels)
marks.append(time.perf_counter())
print(json.dumps(list(np.diff(marks))))
"""
STEP_NAMES = ("import NumPy and octcl.cli", "import PyOpenCL, find the device, make its context",
              "build the scanner (programs from the binary cache, tables)", "Phantom.load and validate",
              "layout (set_phantom: depth order, builds its program the first time; bins; uploads)",
              "forward kernel and copy back", "display, 8-bit levels, PNG")


def whole_command(folder: Path, repeats: int, tree: Path | None) -> None:
    phantom = folder / "layers.txt"
    Phantom.baseline("layers", 42).save(phantom)
    render_args = ["render", str(phantom), "-o", str(folder / "scan.png")]
    commands = [("python -c pass", [sys.executable, "-c", "pass"], None),
                ("python -c 'import numpy, pyopencl'", [sys.executable, "-c", "import numpy, pyopencl"], None),
                ("octcl render layers.txt -o scan.png", [sys.executable, "-m", "octcl.cli"] + render_args, None)]
    if tree is not None:  # the old tree comes first on the path, before the installed octcl
        environment = dict(os.environ, PYTHONPATH=os.pathsep.join(
            filter(None, [str(tree), os.environ.get("PYTHONPATH")])))
        commands.append(("the same, the old code", [sys.executable, "-m", "octcl.cli"] + render_args, environment))
    results = timed_commands([(argv, environment) for _, argv, environment in commands], repeats)
    rows = [[name, f"{wall:.3f}", f"{cpu:.3f}"] for (name, _, _), (wall, cpu) in zip(commands, results)]
    probe = ("import sys; from octcl.cli import main; "
             f"main(['render', {str(phantom)!r}, '-o', {str(folder / 'probe.png')!r}]); "
             "sys.exit('torch' in sys.modules)")
    torch_free = subprocess.run([sys.executable, "-c", probe], stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL).returncode == 0
    print(f"\nwhole command, a new process each time, in turn (median of {repeats}; the CLI imports torch: "
          f"{'no' if torch_free else 'yes'}):\n")
    print(table(["command", "wall s", "CPU s (child)"], rows))
    steps = []
    for _ in range(repeats):
        output = subprocess.run([sys.executable, "-c", COMMAND_STEPS, str(phantom), str(folder / "steps.png")],
                                check=True, capture_output=True, text=True, cwd=tempfile.gettempdir()).stdout
        steps.append(json.loads(output))
    print(f"\nits steps, one by one in a new process (wall s, median of {repeats}):\n")
    print(table(["step", "wall s"], [[name, f"{statistics.median(run[i] for run in steps):.3f}"]
                                     for i, name in enumerate(STEP_NAMES)]))


def inverted(folder: Path, phantom_path: Path, target: Path) -> None:
    """An inverted phantom rounded to 6–9 digits (as saving and loading it would), scored against its target."""
    from octcl.scorer import score as score_scans

    phantom = Phantom.load(phantom_path)
    rows = []
    for digits in DIGITS + (None,):
        rounded = phantom if digits is None else Phantom(*round_significant(phantom.as_array(), digits).T)
        scan = folder / f"inverted_{digits}.png"
        write_grey_png(scan, render(rounded).levels)
        rows.append([digits or "as read", f"{score_scans(target, scan)['mean']:.6f}"])
    print(f"\n{phantom_path.name} rounded to d significant digits, scored against {target.name}:\n")
    print(table(["digits", "score"], rows))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--no-score", action="store_true", help="skip the score column (no torch)")
    parser.add_argument("--old", metavar="REF", help="also time this git commit's code, in turn with today's")
    parser.add_argument("--inverted", nargs=2, type=Path, metavar=("PHANTOM", "TARGET"),
                        help="only score an inverted phantom rounded to 6-9 digits against its target")
    args = parser.parse_args()
    from octcl.device.runtime import describe, select_device

    print(f"machine: {platform.machine()}, {os.cpu_count()} CPUs, {platform.python_implementation()} "
          f"{platform.python_version()}, NumPy {np.__version__}; OpenCL device: {describe(select_device())}")
    print(f"load average at the start: {os.getloadavg()[0]:.1f}")
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        if args.inverted:
            inverted(folder, *args.inverted)
        else:
            tree = old_tree(args.old, folder / "old") if args.old else None
            precision(folder, args.repeats, not args.no_score)
            load_and_save(folder, args.repeats, tree and old_module(tree, "phantom"))
            largest_file_memory(folder)
            render_in_process(args.repeats, tree and old_module(tree, "render"))
            whole_command(folder, args.repeats, tree)
    print(f"\nload average at the end: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
