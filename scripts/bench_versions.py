"""``octcl invert`` as a user runs it, from two or more source trees, on the same targets, in turn.

Each run is a whole process (``octcl invert TARGET -o OUT --report R
--quiet`` plus the options given) whose octcl is the tree's own (a ``git
worktree`` of a release, or this repository; :data:`BOOTSTRAP`): its wall
time from launch to exit is the user's. The trees take turns target by
target and repeat by repeat, so that they meet the same machine load. The
phantom each one wrote is then rendered and scored with this tree's scanner
and scorer (the score the file would get), whatever its own summary said.

Prints, and writes to ``--out``/``versions.csv`` and ``versions.md``, per
target and tree: the median wall time over the repeats, the longest, the
time the phantom was in place (the report's ``seconds.written``), and the
score; then per tree the median wall time over the targets, the longest,
and the global score (the mean of the 8 per-component medians), where
the time went, each part's median over the runs (:func:`run_parts`, from
the report and the wall time), and the median CPU time of a run (user and
system, all threads; on POSIX). A run's CPU seconds over the machine's
cores is the least wall time any split of that work between them could
take: the floor that the cores, not the order of the work, set.

Example (0.7.0 against the working tree, default options, real-like targets)::

    git worktree add /tmp/octcl-0.7.0 f5ecd5f
    python scripts/bench_invert.py --skin 0 --plain 6 --scans orange --seeds 0 --out OUT  # writes OUT/targets
    python scripts/bench_versions.py --trees /tmp/octcl-0.7.0 . --targets ../shared/data/real/orange.png \\
        OUT/targets/plain_skin_*.png --out OUT/versions
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from octcl.host.threads import available_cores
from octcl.host.pipeline.target import read_target
from octcl.host.stage3.loss import ExactScore
from octcl.phantom import CONTRACT_Y_LIMIT_UM, Phantom
from octcl.render import render
from octcl.scorer import global_score


#: The child's start: ``octcl`` from the tree, and each package that the tree's setup.cfg maps to another
#: folder (``package_dir``: ``octcl.host = host``, ``octcl.kernels = kernels``) from that folder, so that no
#: installed octcl is consulted; then the command.
BOOTSTRAP = """
import configparser, importlib.util, os, sys
tree = sys.argv.pop(1)
sys.path.insert(0, tree)
import octcl
setup = configparser.ConfigParser()
setup.read(os.path.join(tree, "setup.cfg"))
mapped = {}
for line in setup.get("options", "package_dir", fallback="").splitlines():
    name, _, folder = (part.strip() for part in line.partition("="))
    if "." in name and folder.replace("/", ".") != name:
        mapped[name] = os.path.join(tree, folder)
for name in sorted(mapped, key=lambda name: name.count(".")):
    parent, _, leaf = name.rpartition(".")
    if parent in mapped and os.path.join(mapped[parent], leaf) == mapped[name]:
        continue  # found through its parent's folder
    init = os.path.join(mapped[name], "__init__.py")
    spec = importlib.util.spec_from_file_location(name, init, submodule_search_locations=[mapped[name]])
    module = sys.modules[name] = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    setattr(sys.modules[parent], leaf, module)
from octcl.cli import command
sys.argv[0] = "octcl"
sys.exit(command())
"""


def run_tree(tree: Path, target: Path, output: Path, report: Path, options: list[str]) -> tuple[float, float]:
    """(wall seconds, CPU seconds) of one ``octcl invert`` process from ``tree``; the CPU seconds (user and
    system, all its threads) are NaN where the platform does not give a child's (``os.wait4``, POSIX only)."""
    command = [sys.executable, "-c", BOOTSTRAP, str(tree.resolve()), "invert", str(target.resolve()),
               "-o", str(output.resolve()), "--report", str(report.resolve()), "--quiet", *options]
    start = time.monotonic()
    process = subprocess.Popen(command)
    if hasattr(os, "wait4"):
        _, status, usage = os.wait4(process.pid, 0)
        process.returncode = os.waitstatus_to_exitcode(status)
        cpu_s = usage.ru_utime + usage.ru_stime
    else:
        process.wait()
        cpu_s = float("nan")
    wall_s = time.monotonic() - start
    if process.returncode:
        raise subprocess.CalledProcessError(process.returncode, command)
    return wall_s, cpu_s


#: Stage 1's steps whose seconds :func:`run_parts` reads from the report, summed over its candidates.
FIELD_STEPS = ("display", "project", "hinge", "aim")
#: :func:`run_parts`'s parts, in a run's order.
PARTS = ("before stage 1", *FIELD_STEPS, "decode", "to the write", "after the write")


def run_parts(report: dict, wall_s: float) -> dict[str, float]:
    """Seconds of one run's parts: before stage 1 (the interpreter, the imports, the target, the device's
    programs), stage 1's steps (:data:`FIELD_STEPS`), the decode, from the decode to the phantom in place (the
    write and stage 3), and from there to the process's exit (the scores, the summary)."""
    seconds = report["seconds"]
    field_end = next(entry["time_s"] for entry in report["trace"] if entry["stage"] == "field")  # after the decode
    steps = [step for candidate in report["settings"]["field_candidates"] or () for step in candidate["steps"]]
    return {"before stage 1": field_end - seconds["field"] - seconds["decode"],
            **{name: sum(step["seconds"] for step in steps if step["name"] == name) for name in FIELD_STEPS},
            "decode": seconds["decode"], "to the write": seconds["written"] - field_end,
            "after the write": wall_s - seconds["written"]}


def table_lines(rows: list[dict], names: list[str]) -> list[str]:
    """versions.md: per target and tree, then per tree the medians, the global score and the parts."""
    lines = ["| target | " + " | ".join(f"{name} wall s (max) / written s / score" for name in names) + " |",
             "|---|" + "---|" * len(names)]
    for target in dict.fromkeys(row["target"] for row in rows):
        cells = []
        for name in names:
            runs = [row for row in rows if row["target"] == target and row["tree"] == name]
            cells.append(f"{np.median([r['wall_s'] for r in runs]):.2f} ({max(r['wall_s'] for r in runs):.2f}) / "
                         f"{np.median([r['written_s'] for r in runs]):.2f} / {runs[0]['mean']:.7f}")
        lines.append(f"| {target} | " + " | ".join(cells) + " |")
    for name in names:
        runs = [row for row in rows if row["tree"] == name]
        by_target = {}
        for row in runs:
            by_target.setdefault(row["target"], []).append(row["wall_s"])
        medians = [float(np.median(walls)) for walls in by_target.values()]
        firsts = [row for row in runs if row["repeat"] == 0]
        parts = ", ".join(f"{part} {np.median([row[part] for row in runs]):.2f}" for part in PARTS)
        cpu_s, cores = np.median([row["cpu_s"] for row in runs]), available_cores()
        lines.append(f"\n{name}: median wall {np.median(medians):.2f} s over {len(medians)} targets, longest "
                     f"{max(medians):.2f} s; global score {global_score(firsts)[1]:.7f} "
                     f"(over the targets' first runs); parts, median s over the runs: {parts}; "
                     f"median CPU {cpu_s:.2f} s a run, {cpu_s / cores:.2f} s over {cores} cores")
    return lines


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trees", nargs="+", type=Path, required=True, help="source trees, the first the baseline")
    parser.add_argument("--targets", nargs="+", type=Path, required=True, help="target B-scans")
    parser.add_argument("--repeats", type=int, default=1, help="runs per target and tree (default 1)")
    parser.add_argument("--options", default="", help="more invert options, one string (e.g. '--time-budget 3')")
    parser.add_argument("--out", type=Path, required=True, help="folder for the phantoms, reports and tables")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    names = [f"{index}:{tree.resolve().name}" for index, tree in enumerate(args.trees)]
    rows = []
    for target in args.targets:
        exact = ExactScore(read_target(target))
        for repeat in range(args.repeats):
            for name, tree in zip(names, args.trees):
                stem = f"{target.stem}_{name.replace(':', '_')}_r{repeat}"
                output, report_path = args.out / f"{stem}.txt", args.out / f"{stem}.report.json"
                wall, cpu_s = run_tree(tree, target, output, report_path, args.options.split())
                report = json.loads(report_path.read_text())
                components = exact(render(Phantom.load(output, y_limit_um=CONTRACT_Y_LIMIT_UM)).levels)
                rows.append({"target": target.stem, "tree": name, "repeat": repeat, "wall_s": wall, "cpu_s": cpu_s,
                             "written_s": report["seconds"]["written"], **run_parts(report, wall), **components})
                print(f"{target.stem} {name} r{repeat}: {wall:.2f} s (CPU {cpu_s:.2f} s), written {report['seconds']['written']:.2f} s, "
                      f"score {components['mean']:.7f}", flush=True)
    with open(args.out / "versions.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    lines = table_lines(rows, names)
    (args.out / "versions.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
