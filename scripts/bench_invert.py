"""Benchmark ``octcl.host.invert`` on a development set of B-scans.

The set: the official scans in the repository's ``data/official`` (Uniform A
and B, Layers A), the real scan ``../shared/data/real/orange.png`` beside the
repository and, with ``--skin N``, N skin-like synthetic targets rendered from
:meth:`octcl.phantom.Phantom.skin`. The real scan may not be redistributed, so
the repository does not carry it (``data/README.md``); without it the set goes
on without ``orange``, and says so. Each scan is inverted in its own
process (so the peak memory is that scan's) with the given time budget.
The written phantom is then rendered again with the OpenCL scanner and
scored exactly against the target, which is the score the file would get.

Writes, in ``--out``:

- ``NAME.txt``, ``NAME.report.json`` (invert's report), ``NAME_render.png``;
- ``NAME_panel.png``: target (top) and rendering (bottom), each as scan,
  OAC, SC and RSC maps;
- ``bench.csv`` and ``bench.json``: per scan the 8 components, their mean,
  seconds, peak memory; then the medians and the global score (mean of the
  8 medians);
- ``score_vs_time.png``: exact score against wall time, from the traces.

Example::

    python scripts/bench_invert.py --time-budget 600 --scans Scan_Exp2_Layers_A orange
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from octcl._io import atomic_write, read_png_rgb, write_grey_png
from octcl.host.loss import ExactScore, scan_of_levels
from octcl.maps import map_levels
from octcl.phantom import CONTRACT_Y_LIMIT_UM, Phantom
from octcl.render import render
from octcl.scorer import COMPONENTS

REPOSITORY = Path(__file__).resolve().parents[1]
OFFICIAL_DIR = REPOSITORY / "data" / "official"
OFFICIAL = ("Scan_Exp1_Uniform_A", "Scan_Exp1_Uniform_B", "Scan_Exp2_Layers_A")
ORANGE = REPOSITORY.parent / "shared" / "data" / "real" / "orange.png"
ORANGE_MISSING = f"orange: {ORANGE} not found (a real scan the repository may not carry; see data/README.md)"


def development_set(out: Path, skin: int) -> dict[str, Path]:
    """{name: target PNG}; skin targets are rendered into ``out/targets``; orange only if present."""
    targets = {name: OFFICIAL_DIR / f"{name}.png" for name in OFFICIAL}
    if ORANGE.is_file():
        targets["orange"] = ORANGE
    for seed in range(skin):
        path = out / "targets" / f"skin_{seed}.png"
        if not path.exists():
            write_grey_png(path, render(Phantom.skin(seed)).levels)
        targets[f"skin_{seed}"] = path
    return targets


def run_invert(target: Path, output: Path, report: Path, budget: float, seed: int) -> None:
    """invert() in a child process, so that ru_maxrss is this scan's peak."""
    code = ("import sys; from octcl.host.invert import invert; "
            "invert(sys.argv[1], sys.argv[2], time_budget_s=float(sys.argv[4]), seed=int(sys.argv[5]), "
            "report_path=sys.argv[3])")
    subprocess.run([sys.executable, "-c", code, str(target), str(output), str(report), str(budget), str(seed)],
                   check=True)


def panel(path: Path, target_levels: np.ndarray, render_levels: np.ndarray, title: str) -> None:
    """Target and rendering, each as Struct, OAC, SC and RSC, in a 2×4 grid (Pillow)."""
    from PIL import Image, ImageDraw

    rows = []
    for levels in (target_levels, render_levels):
        maps = map_levels(scan_of_levels(levels))
        rows.append([levels, maps["OAC"], maps["SC"], maps["RSC"]])
    height, width = target_levels.shape
    label = 16
    image = Image.new("L", (4 * width, 2 * (height + label) + label), 255)
    draw = ImageDraw.Draw(image)
    draw.text((4, 2), title, fill=0)
    for r, (row_name, row) in enumerate(zip(("target", "rendering"), rows)):
        top = label + r * (height + label)
        for c, (map_name, levels) in enumerate(zip(("scan", "OAC", "SC", "RSC"), row)):
            draw.text((c * width + 4, top + 2), f"{row_name} {map_name}", fill=0)
            image.paste(Image.fromarray(levels), (c * width, top + label))
    with atomic_write(path) as handle:
        image.save(handle, format="PNG")


def score_vs_time(path: Path, reports: dict) -> None:
    """Exact score against wall time per scan (matplotlib if importable, else Pillow)."""
    series = {}
    for name, report in reports.items():
        points = [(e["time_s"], e["score"]) for e in report["trace"] if e.get("score") is not None]
        best, xs, ys = -np.inf, [], []
        for t, s in points:  # the best so far: what the checkpoint holds
            best = max(best, s)
            xs.append(t)
            ys.append(best)
        series[name] = (xs, ys)
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        from octcl._plot import line_chart

        line_chart(path, series, "best exact score against time", "seconds", "score")
        return
    figure, axes = plt.subplots(figsize=(9, 5.6))
    for name, (xs, ys) in series.items():
        axes.plot(xs, ys, label=name)
    axes.set(xlabel="seconds", ylabel="score", title="best exact score against time")
    axes.legend()
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=100)
    with atomic_write(path) as handle:
        handle.write(buffer.getvalue())


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--time-budget", type=float, default=600.0, help="seconds per scan (default 600)")
    parser.add_argument("--out", type=Path, default=Path("bench_invert"), help="output folder")
    parser.add_argument("--scans", nargs="*", help="names to run (default: all of the set)")
    parser.add_argument("--skin", type=int, default=2, help="synthetic skin targets to add (default 2)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    targets = development_set(args.out, args.skin)
    names = args.scans or list(targets)
    if "orange" not in targets:
        if not args.scans:
            print(f"{ORANGE_MISSING}: the set goes on without it", file=sys.stderr)
        elif "orange" in args.scans:
            parser.error(ORANGE_MISSING)
    unknown = sorted(set(names) - set(targets))
    if unknown:
        parser.error(f"unknown scans {unknown}; known: {sorted(targets)}")
    rows, reports = {}, {}
    for name in names:
        target = targets[name]
        output, report_path = args.out / f"{name}.txt", args.out / f"{name}.report.json"
        start = time.monotonic()
        run_invert(target, output, report_path, args.time_budget, args.seed)
        wall = time.monotonic() - start
        report = reports[name] = json.loads(report_path.read_text())
        levels = render(Phantom.load(output, y_limit_um=CONTRACT_Y_LIMIT_UM)).levels
        write_grey_png(args.out / f"{name}_render.png", levels)
        components = ExactScore(target)(levels)
        panel(args.out / f"{name}_panel.png", read_png_rgb(target)[..., 0], levels,
              f"{name}: score {components['mean']:.5f} after {report['seconds']['total']:.0f} s")
        rows[name] = {**{c: components[c] for c in COMPONENTS}, "mean": components["mean"],
                      "initial_score": report["initial_score"], "iterations": report["iterations"],
                      "seconds": report["seconds"]["total"], "wall_s": wall,
                      "peak_memory_mib": report["peak_memory_mib"]}
        print(f"{name}: {components['mean']:.5f} (stages 1-2: {report['initial_score']:.5f}), "
              f"{report['iterations']} iterations, {report['seconds']['total']:.0f} s, "
              f"{report['peak_memory_mib']:.0f} MiB", flush=True)

    medians = {c: float(np.median([row[c] for row in rows.values()])) for c in COMPONENTS}
    summary = {"time_budget_s": args.time_budget, "seed": args.seed, "scans": rows, "medians": medians,
               "score": float(np.mean(list(medians.values()))),
               "median_seconds": float(np.median([row["seconds"] for row in rows.values()]))}
    with atomic_write(args.out / "bench.json", "w") as handle:
        json.dump(summary, handle, indent=1)
    columns = [*COMPONENTS, "mean", "initial_score", "iterations", "seconds", "wall_s", "peak_memory_mib"]
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(["scan", *columns])
    for name, row in rows.items():
        writer.writerow([name, *(row[c] for c in columns)])
    writer.writerow(["median", *(medians[c] for c in COMPONENTS), summary["score"], "", "", summary["median_seconds"]])
    with atomic_write(args.out / "bench.csv", "w") as handle:
        handle.write(buffer.getvalue())
    score_vs_time(args.out / "score_vs_time.png", reports)
    print(f"global score {summary['score']:.5f} over {len(rows)} scans; median {summary['median_seconds']:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
