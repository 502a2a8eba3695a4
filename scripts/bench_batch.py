"""Benchmark batch inversion: the sequential path against Dask clusters on one machine.

N synthetic targets (``octcl phantom skin`` seeds 0…N−1, rendered, saved as
``.npy`` as the challenge ships real scans) are inverted with the same
per-scan settings by each mode: the seed and a fixed schedule
(``--iterations`` stage-3 and ``--field-iterations`` stage-1 Adam steps,
:func:`octcl.host.pipeline.invert.invert`'s ``iterations``), so that every scan ends
on its schedule and not on the clock, whatever the load, and runs at the
mode's thread count per scan (all cores for ``sequential``, T otherwise):

- ``sequential``: one process inverting the scans one after the other with
  :func:`octcl.host.pipeline.invert.invert` (what ``octcl invert --targets`` did
  before it ran on Dask);
- ``local:WxT``: :func:`octcl.host.batch.invert_batch` on its embedded
  local cluster of W worker processes × T threads (cluster start included
  in the time);
- ``cluster:WxT``: a real cluster on this machine, ``dask scheduler`` and W
  ``dask worker --nthreads T`` processes started as subprocesses talking TCP
  on 127.0.0.1, reached with ``scheduler=ADDRESS`` (their start is not
  included), with the worker setting ``docs/batch.md`` recommends (the
  nanny's ``MALLOC_TRIM_THRESHOLD_`` unset, in a Dask configuration file);
- ``stock:WxT``: the same with Dask's defaults.

Per mode: scans per hour (scans / wall time of the whole batch), CPU use
(CPU seconds of the inversions, all threads, over wall time × cores), what
bounds the throughput (:func:`cpu_figures`: the scans' CPU seconds, the
scans an hour they would allow with every core busy throughout, and each
worker's seconds outside its scans), the peak resident memory of each
worker process (of the process, for sequential), and the global score
(mean of the 8 per-component medians).
Results go to ``--out``: ``bench_batch.json``, ``bench_batch.csv`` and
``bench_batch.png`` (scans per hour and CPU use per mode).

With ``--deadline`` each scan runs as ``octcl invert``'s default does (the
time budget decides, no fixed schedule), and with ``--plain`` the targets
are the renderings quantised plainly (floor(256·D)), with the unwritable
levels real scans have.

Examples (about 15 minutes, and 1 and 2 minutes, on two idle cores)::

    python scripts/bench_batch.py --scans 4 --iterations 20 --field-iterations 600 --out bench_batch
    python scripts/bench_batch.py --scans 20 --deadline --modes local:2x1 --out bench_batch_default
    python scripts/bench_batch.py --scans 20 --deadline --plain --modes local:2x1 --out bench_batch_plain
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from octcl._io import atomic_write
from octcl.host.batch import invert_batch
from octcl.host.batch.report import summarise
from octcl.host.threads import available_cores
from octcl.phantom import Phantom
from octcl.render import render

DASK = str(Path(sys.executable).with_name("dask"))


def make_targets(folder: Path, count: int, plain: bool = False) -> None:
    """``skin_N.npy``, the scanner's levels of ``Phantom.skin(N)``; ``plain``: its display quantised plainly,
    floor(256·D), with the unwritable levels a real scan has (``host/stage1/ceiling.py``)."""
    folder.mkdir(parents=True, exist_ok=True)
    for seed in range(count):
        path = folder / f"{'plain_' if plain else ''}skin_{seed}.npy"
        if not path.exists():
            rendering = render(Phantom.skin(seed))
            np.save(path, np.minimum(np.floor(256 * rendering.display), 255).astype(np.uint8) if plain
                    else rendering.levels)


def sequential_child(targets: Path, out: Path, budget: float, seed: int, schedule: dict) -> None:
    """The sequential path: :func:`invert` on each target in turn in this process; rows as JSON on stdout."""
    from octcl.host.pipeline.invert import invert

    rows = {}
    for path in sorted(targets.glob("*.npy")):
        cpu = time.process_time()
        result = invert(np.load(path), out / f"{path.stem}.txt", budget, seed, name=path.name, **schedule)
        rows[path.name] = {"scan": path.name, "status": "inverted", **result.components,
                           "seconds": result.seconds["total"], "peak_memory_mib": result.peak_memory_mib,
                           "cpu_s": time.process_time() - cpu, "worker": "sequential", "error": None}
    print(json.dumps(rows))


def run_sequential(targets: Path, out: Path, budget: float, seed: int, schedule: dict) -> dict:
    """:func:`sequential_child` in a process of its own, so that its peak memory is its own."""
    out.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    done = subprocess.run([sys.executable, __file__, "--sequential-child", str(targets), str(out), str(budget),
                           str(seed), json.dumps(schedule)], check=True, capture_output=True, text=True)
    return {"rows": json.loads(done.stdout.splitlines()[-1]), "wall_s": time.monotonic() - started}


#: The worker setting docs/batch.md recommends, as a Dask configuration file.
RECOMMENDED_CONFIG = "distributed:\n  nanny:\n    pre-spawn-environ:\n      MALLOC_TRIM_THRESHOLD_: null\n"


def start_stock_cluster(folder: Path, workers: int, threads: int, recommended: bool):
    """``dask scheduler`` and ``workers`` × ``dask worker --nthreads threads`` on 127.0.0.1.

    ``recommended``: with :data:`RECOMMENDED_CONFIG` (``DASK_CONFIG`` points at
    it), else Dask's defaults.
    """
    from distributed import Client

    environment = dict(os.environ)
    if recommended:
        (folder / "config").mkdir()
        (folder / "config" / "distributed.yaml").write_text(RECOMMENDED_CONFIG)
        environment["DASK_CONFIG"] = str(folder / "config")

    file = folder / "scheduler.json"
    # --dashboard-address: without it the scheduler's and workers' HTTP servers listen on every interface,
    # also with --no-dashboard.
    processes = [subprocess.Popen([DASK, "scheduler", "--host", "127.0.0.1", "--port", "0",
                                   "--dashboard-address", "127.0.0.1:0",
                                   "--scheduler-file", str(file)], stderr=subprocess.DEVNULL)]
    while not (file.exists() and file.read_text()):
        time.sleep(0.2)
    for index in range(workers):
        processes.append(subprocess.Popen(
            [DASK, "worker", "--scheduler-file", str(file), "--nthreads", str(threads), "--host", "127.0.0.1",
             "--dashboard-address", "127.0.0.1:0", "--local-directory", str(folder / f"w{index}")],
            stderr=subprocess.DEVNULL, env=environment))
    address = json.loads(file.read_text())["address"]
    with Client(address) as client:
        client.wait_for_workers(workers, timeout=180)
    return address, processes


def run_mode(mode: str, targets: Path, out: Path, budget: float, seed: int, schedule: dict, cores: int) -> dict:
    """One mode's batch: its rows (as ``summary["scans"]``) and wall time; ``schedule`` without ``threads``."""
    if mode == "sequential":
        return run_sequential(targets, out, budget, seed, {**schedule, "threads": cores})
    kind, shape = mode.split(":")
    workers, threads = map(int, shape.split("x"))
    processes, options = [], {"workers": workers, "threads_per_worker": threads}
    if kind in ("cluster", "stock"):
        address, processes = start_stock_cluster(Path(tempfile.mkdtemp(prefix="bench-cluster-")), workers, threads,
                                                 recommended=kind == "cluster")
        options = {"scheduler": address}
    try:
        started = time.monotonic()
        summary = invert_batch(targets, out, budget, seed, force=True, threads=threads, **schedule, **options)
        wall = time.monotonic() - started
    finally:
        for process in reversed(processes):
            process.terminate()
            process.wait()
    return {"rows": summary["scans"], "wall_s": wall}


def cpu_figures(rows: dict, wall_s: float, cores: int) -> dict:
    """What bounds a batch's throughput, from its rows (``summary["scans"]``: each scan's ``seconds``, ``cpu_s``
    and ``worker``):

    - ``cpu_s_per_scan``: the scans' mean CPU seconds (all threads);
    - ``cpu_bound_scans_per_hour``: cores·3600/that, the most any schedule of this work could reach on these
      cores, every core busy from the start to the end;
    - ``outside_scans_s``: per worker, the batch's wall time less the seconds of its own scans (the cluster's
      start, the first import in the worker, the last scans' tail, the close), their mean over the workers;
    - ``cpu_use_pct``: the scans' CPU seconds over wall time × cores.
    """
    cpu = [row["cpu_s"] for row in rows.values()]
    inside = {}
    for row in rows.values():
        inside[row["worker"]] = inside.get(row["worker"], 0.0) + row["seconds"]
    return {"cpu_s_per_scan": sum(cpu) / len(cpu), "cpu_bound_scans_per_hour": cores * 3600 * len(cpu) / sum(cpu),
            "outside_scans_s": sum(wall_s - seconds for seconds in inside.values()) / len(inside),
            "cpu_use_pct": 100 * sum(cpu) / (wall_s * cores)}


def measure(mode: str, result: dict, cores: int) -> dict:
    rows = result["rows"]
    summary = summarise(rows, {}, None, result["wall_s"])
    peaks = {}
    for row in rows.values():
        peaks[row["worker"]] = max(peaks.get(row["worker"], 0.0), row["peak_memory_mib"])
    return {"mode": mode, "scans": len(rows), "wall_s": result["wall_s"],
            "scans_per_hour": 3600 * len(rows) / result["wall_s"], **cpu_figures(rows, result["wall_s"], cores),
            "peak_memory_mib_per_worker": max(peaks.values()), "median_seconds_per_scan": summary["median_seconds"],
            "score": summary["score"], "medians": summary["medians"],
            "scan_scores": {name: row["mean"] for name, row in rows.items()}}


def plot(path: Path, results: list[dict], title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    figure = Figure(figsize=(9, 3.6), dpi=100, layout="constrained")
    speed, cpu = figure.subplots(1, 2)
    modes = [r["mode"] for r in results]
    bars = speed.bar(modes, [r["scans_per_hour"] for r in results], color="tab:blue")
    speed.bar_label(bars, fmt="%.1f")
    speed.set(ylabel="scans per hour", title=title)
    bars = cpu.bar(modes, [r["cpu_use_pct"] for r in results], color="tab:orange")
    cpu.bar_label(bars, fmt="%.0f %%")
    cpu.set(ylabel="CPU use, % of all cores", ylim=(0, 100), title="CPU seconds of the inversions / (wall × cores)")
    for axes in (speed, cpu):
        axes.tick_params(axis="x", labelrotation=15)
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png")
    with atomic_write(path) as handle:
        handle.write(buffer.getvalue())


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--sequential-child"]:
        targets, out, budget, seed, schedule = argv[1:]
        sequential_child(Path(targets), Path(out), float(budget), int(seed), json.loads(schedule))
        return 0
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scans", type=int, default=4, help="synthetic targets (default 4)")
    parser.add_argument("--iterations", type=int, default=20, help="stage-3 Adam steps per scan (default 20)")
    parser.add_argument("--field-iterations", type=int, default=600,
                        help="stage-1 Adam steps per scan (default 600)")
    parser.add_argument("--time-budget", type=float, default=600.0, help="seconds per scan, a ceiling (default 600)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--modes", nargs="+",
                        default=["sequential", "local:1x2", "local:2x1", "cluster:2x1", "stock:2x1"],
                        help="sequential, local:WxT, cluster:WxT, stock:WxT (default: all five on two cores)")
    parser.add_argument("--out", type=Path, default=Path("bench_batch"))
    parser.add_argument("--deadline", action="store_true",
                        help="each scan as octcl invert's default runs it (deadline mode, the time budget): "
                             "no fixed schedule, --iterations and --field-iterations ignored")
    parser.add_argument("--plain", action="store_true",
                        help="targets quantised plainly, with unwritable levels as real scans have them")
    args = parser.parse_args(argv)

    targets = args.out / ("plain_targets" if args.plain else "targets")
    make_targets(targets, args.scans, args.plain)
    cores = available_cores()
    results = []
    for mode in args.modes:
        load = os.getloadavg()[0]
        schedule = {} if args.deadline else {"iterations": args.iterations, "field_iterations": args.field_iterations}
        result = measure(mode, run_mode(mode, targets, args.out / mode.replace(":", "_"), args.time_budget,
                                        args.seed, schedule, cores), cores)
        result["load_average_before"] = load
        results.append(result)
        print(f"{mode}: {result['scans_per_hour']:.1f} scans/h ({result['wall_s']:.0f} s), CPU "
              f"{result['cpu_use_pct']:.0f} %, peak {result['peak_memory_mib_per_worker']:.0f} MiB/worker, "
              f"score {result['score']:.6f} (load average before: {load:.1f}); "
              f"{result['cpu_s_per_scan']:.2f} CPU s a scan, at most {result['cpu_bound_scans_per_hour']:.0f} "
              f"scans/h on {cores} cores; {result['outside_scans_s']:.1f} s a worker outside its scans", flush=True)
    baseline = results[0]["score"]
    for result in results:
        result["score_difference"] = result["score"] - baseline
    meta = {"command": " ".join(["python", "scripts/bench_batch.py", *argv]), "cores": cores,
            "scans": args.scans, "iterations": None if args.deadline else args.iterations,
            "field_iterations": None if args.deadline else args.field_iterations, "plain": args.plain,
            "time_budget_s": args.time_budget, "seed": args.seed}
    with atomic_write(args.out / "bench_batch.json", "w") as handle:
        json.dump({**meta, "results": results}, handle, indent=1)
    columns = ["mode", "scans", "wall_s", "scans_per_hour", "cpu_use_pct", "cpu_s_per_scan", "cpu_bound_scans_per_hour",
               "outside_scans_s", "peak_memory_mib_per_worker",
               "median_seconds_per_scan", "score", "score_difference", "load_average_before"]
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(columns)
    for result in results:
        writer.writerow([result[c] for c in columns])
    with atomic_write(args.out / "bench_batch.csv", "w") as handle:
        handle.write(buffer.getvalue())
    what = "the default schedule" if args.deadline else f"{args.field_iterations} + {args.iterations} iterations"
    plot(args.out / "bench_batch.png", results,
         f"{args.scans} {'plain ' if args.plain else ''}scans, {what}, {cores} cores")
    return 0


if __name__ == "__main__":
    sys.exit(main())
