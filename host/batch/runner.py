"""Run a batch of inversions as tasks on dask.distributed.

The engine is Dask's: scheduling, transport, retries and the dashboard are
``dask.distributed``'s, nothing here re-implements them.

- Cluster. By default an embedded :class:`distributed.LocalCluster` of
  worker *processes*, scheduler, workers and dashboard all listening on
  127.0.0.1 only (a Dask scheduler runs whatever code it is sent, so it must
  not be reachable from the network). With ``scheduler=ADDRESS`` the batch
  goes to an existing cluster (``dask scheduler`` / ``dask worker``,
  dask-jobqueue), over TLS when ``security`` (or Dask's configuration) says
  so: ``docs/batch.md``.
- One scan at a time per worker. Each worker offers one unit of the
  resource :data:`SCAN_RESOURCE` and each scan needs it, so a worker with T
  threads runs one scan with T torch and PoCL threads
  (:class:`OneScanPerWorker`) rather than T scans fighting over the
  process-wide thread settings.
- Targets travel as file bytes and results come back to this process,
  which writes every output atomically (phantom, pictures, then the report
  that marks the scan done, :mod:`octcl.host.batch.targets`): no shared
  file system, and an interrupted run leaves only whole files.
- Faults. A scan whose worker dies (SIGKILL, out of memory) is rescheduled
  by Dask on another worker, up to ``retries`` deaths (the embedded
  scheduler's ``allowed-failures``; a remote scheduler uses its own, 3 by
  default); a scan that raises is retried ``retries`` times (Dask's
  ``retries=``); a target that is not a B-scan fails at once with its
  reason. None of these stops the other scans.
- At most twice as many scans as there are workers are submitted at a time,
  so a dataset of thousands of targets is read as it is inverted and the
  scheduler holds a few megabytes, not the dataset.

Defaults chosen by measurement (``scripts/bench_batch.py``, docs/benchmarks.md):
on 2 cores, 2 workers × 1 thread invert more scans per hour than 1 worker
× 2 threads, so a local cluster gets one single-threaded worker per core.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

from distributed.diagnostics.plugin import WorkerPlugin

from octcl._io import ImageFormatError, atomic_write, read_image_bytes
from octcl.scorer import COMPONENTS

from .report import PICTURES, write_reports
from .targets import Scan, completed_report, find_scans, settings_record, sha256

#: Threads per worker of the embedded cluster (and so torch threads per scan).
DEFAULT_THREADS_PER_WORKER = 1
#: Worker deaths and exceptions a scan survives before it is recorded as failed.
DEFAULT_RETRIES = 2
#: The Dask worker resource a scan occupies: each worker has one.
SCAN_RESOURCE = "octcl-scan"
#: Scans submitted ahead per worker.
SCANS_AHEAD_PER_WORKER = 2


class OneScanPerWorker(WorkerPlugin):
    """Make a stock Dask worker run one scan at a time with all of its threads.

    On each worker (those there now and those that join later): one unit of
    :data:`SCAN_RESOURCE`, and ``OMP_NUM_THREADS`` (torch, and octcl's
    thread choice, :func:`octcl.host.threads.available_cores`) and
    ``POCL_MAX_PTHREAD_COUNT`` (the PoCL CPU device, unless already set) set
    to the worker's thread count. Dask's nanny sets ``OMP_NUM_THREADS=1``
    in every worker whatever its thread count, so ``dask worker
    --nthreads 2`` would otherwise run torch on one thread.
    """

    name = "octcl-one-scan-per-worker"

    async def setup(self, worker) -> None:
        threads = str(worker.state.nthreads)
        os.environ["OMP_NUM_THREADS"] = threads
        os.environ.setdefault("POCL_MAX_PTHREAD_COUNT", threads)
        await worker.set_resources(**{SCAN_RESOURCE: 1})


@dataclass(frozen=True)
class BatchProgress:
    """Where a batch stands: what :func:`invert_batch` tells its ``progress`` callback.

    Attributes
    ----------
    total : int
        Scans in the batch.
    inverted, resumed, failed : int
        Scans inverted by this run, found done from an earlier one, failed.
    running : int
        Scans being inverted now (at most one per worker).
    seconds_left : float or None
        Estimated seconds to the end: the remaining scans at this run's rate
        so far, or before the first ends, at one time budget per round of
        workers.
    cluster : str or None
        The cluster and its dashboard link (None until connected).
    """

    total: int
    inverted: int
    resumed: int
    failed: int
    running: int
    seconds_left: float | None
    cluster: str | None

    @property
    def finished(self) -> int:
        return self.inverted + self.resumed + self.failed


def _octcl_version() -> str:
    from octcl import __version__

    return __version__


def _worker_environment() -> tuple[str, str | None]:
    """On a worker: its octcl version and ``MALLOC_TRIM_THRESHOLD_``."""
    return _octcl_version(), os.environ.get("MALLOC_TRIM_THRESHOLD_")


def check_cluster_options(scheduler: str | None, workers: int | None, threads_per_worker: int | None) -> None:
    """Raise ValueError for cluster options :func:`connect` cannot follow."""
    for label, value in (("workers", workers), ("threads_per_worker", threads_per_worker)):
        if value is not None and not (isinstance(value, int) and value >= 1):
            raise ValueError(f"{label} must be a whole number ≥ 1, got {value!r}")
    if scheduler is not None and (workers is not None or threads_per_worker is not None):
        raise ValueError("workers and threads per worker are the cluster's own with a scheduler address; "
                         "give them to dask worker (--nworkers, --nthreads)")


@contextlib.contextmanager
def connect(scheduler: str | None = None, workers: int | None = None, threads_per_worker: int | None = None,
            security=None, retries: int = DEFAULT_RETRIES):
    """A Dask client ready for scans, and a one-line description of its cluster with the dashboard link.

    Without ``scheduler``: an embedded local cluster of ``workers`` worker
    processes (default: one per available core / ``threads_per_worker``)
    with ``threads_per_worker`` threads (default
    :data:`DEFAULT_THREADS_PER_WORKER`), on 127.0.0.1 only, closed on exit.
    With it: a client of that scheduler (``tcp://HOST:8786``,
    ``tls://...``), with ``security`` (a :class:`distributed.Security`; by
    default Dask's configuration). Both get :class:`OneScanPerWorker`.

    Raises
    ------
    ValueError
        ``workers`` or ``threads_per_worker`` below 1, or given with
        ``scheduler``; workers running another octcl version than this one.
    ConnectionError
        No scheduler at ``scheduler`` (within Dask's connect timeout).
    """
    import dask
    from distributed import Client, LocalCluster

    from ..threads import available_cores

    check_cluster_options(scheduler, workers, threads_per_worker)
    cluster = None
    if scheduler is None:
        threads = threads_per_worker or DEFAULT_THREADS_PER_WORKER
        workers = workers or max(1, available_cores() // threads)
        with dask.config.set({"distributed.scheduler.allowed-failures": retries,
                              "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}):
            cluster = LocalCluster(n_workers=workers, threads_per_worker=threads, processes=True,
                                   host="127.0.0.1", dashboard_address="127.0.0.1:0",
                                   silence_logs=logging.ERROR)
        client = Client(cluster)
        description = (f"local cluster: {workers} worker process{'es' if workers > 1 else ''} x {threads} "
                       f"thread{'s' if threads > 1 else ''} at {cluster.scheduler_address}, "
                       f"dashboard {cluster.dashboard_link}")
    else:
        try:
            client = Client(scheduler, security=security)
        except OSError as exc:
            raise ConnectionError(f"{scheduler}: no Dask scheduler answers ({exc})") from None
    try:
        client.register_plugin(OneScanPerWorker())
        if scheduler is not None:
            nthreads = client.nthreads()
            description = (f"cluster at {scheduler}: {len(nthreads)} workers, {sum(nthreads.values())} threads, "
                           f"dashboard {client.dashboard_link}")
            workers_seen = client.run(_worker_environment)
            other = {address: version for address, (version, _) in workers_seen.items() if version != _octcl_version()}
            if other:
                raise ValueError(f"workers run another octcl version than this client ({_octcl_version()}): "
                                 + ", ".join(f"{address} {version}" for address, version in other.items()))
            trimmed = sum(trim is not None for _, trim in workers_seen.values())
            if trimmed:
                description += (f"; {trimmed} workers have MALLOC_TRIM_THRESHOLD_ set (Dask's nanny default), "
                                "which makes scans about twice as slow: see docs/batch.md")
        yield client, description
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def _row(name: str, status: str, report: dict) -> dict:
    """A summary row from a scan's report."""
    record = report.get("batch", {})
    components = report["components"] or {}  # None: a time budget left no time to score it
    return {"scan": name, "status": status, **{c: components.get(c) for c in (*COMPONENTS, "mean")},
            "seconds": report["seconds"]["total"], "peak_memory_mib": report["peak_memory_mib"],
            "cpu_s": record.get("cpu_s"), "worker": record.get("worker"), "error": None}


def _failed(name: str, reason: str) -> dict:
    return {"scan": name, "status": "failed", "error": " ".join(reason.split()) or "failed"}


def _reason(exc: BaseException) -> str:
    """One line for a scan's exception."""
    from distributed.scheduler import KilledWorker

    if isinstance(exc, KilledWorker):
        return f"its worker died while inverting it, too often (KilledWorker: {exc})"
    return f"{type(exc).__name__}: {exc}"


def _store(scan: Scan, result: dict, target_sha256: str, settings: dict) -> dict:
    """Write a worker's result for ``scan`` (each file atomically, the report last); return the report."""
    with atomic_write(scan.output("phantom")) as handle:
        handle.write(result["phantom"])
    scan.write_pictures({kind: result[kind] for kind in PICTURES if kind in result})
    report = {**result["report"], "output": scan.output("phantom").name,
              "batch": {**settings, "target": scan.name, "target_sha256": target_sha256,
                        "phantom_sha256": sha256(result["phantom"]), "cpu_s": result["cpu_s"],
                        "wall_s": result["wall_s"], "worker": result["worker"]}}
    with atomic_write(scan.output("report"), "w") as handle:
        json.dump(report, handle, indent=1, default=float)
    return report


def invert_batch(targets_dir, out_dir, time_budget_s: float = 600.0, seed: int = 0, *,
                 workers: int | None = None, threads_per_worker: int | None = None, scheduler: str | None = None,
                 security=None, force: bool = False, retries: int = DEFAULT_RETRIES, progress=None,
                 **invert_options) -> dict:
    """Invert every target under ``targets_dir`` into ``out_dir`` on a Dask cluster.

    Parameters
    ----------
    targets_dir, out_dir : str or Path
        Targets (``*.png``, ``*.npy``, recursively,
        :func:`octcl.host.batch.targets.find_scans`) and the output folder,
        which mirrors their tree: per scan ``NAME.txt``, ``NAME.report.json``,
        ``NAME.panel.png``, ``NAME.score.png`` (where the scan was scored
        more than once: :func:`octcl.host.batch.report.wants_score_plot`); for the batch
        ``summary.csv``, ``summary.json``, ``report.html``
        (:mod:`octcl.host.batch.report`).
    time_budget_s, seed, **invert_options
        Passed to :func:`octcl.host.pipeline.invert.invert` for every scan.
    workers, threads_per_worker, scheduler, security, retries
        The cluster (:func:`connect`) and how often a scan is retried.
    force : bool
        Invert scans that are already done (by default they are skipped,
        :func:`octcl.host.batch.targets.completed_report`).
    progress : callable, optional
        ``progress(BatchProgress)`` when the cluster is up and whenever a
        scan ends (once, if every scan is already done).

    Returns
    -------
    dict
        The summary (:func:`octcl.host.batch.report.summarise`), also in
        ``out_dir/summary.json``.

    Notes
    -----
    On KeyboardInterrupt the scans still running are cancelled, the
    summary and report are written with them ``pending``, and the
    interrupt goes on; every finished scan's files are whole. No cluster is
    started when every scan is already done.
    """
    started = time.monotonic()
    check_cluster_options(scheduler, workers, threads_per_worker)
    out_dir = Path(out_dir)
    scans = find_scans(targets_dir, out_dir)
    settings = settings_record(time_budget_s, seed, invert_options)
    rows, todo = {}, []
    for scan in scans:
        try:
            report = None if force else completed_report(scan, sha256(read_image_bytes(scan.target, "target")),
                                                         settings)
        except ImageFormatError as exc:  # unreadable, or larger than any target octcl reads
            rows[scan.name] = _failed(scan.name, str(exc))
            continue
        if report is None:
            rows[scan.name] = {"scan": scan.name, "status": "pending", "error": None}
            todo.append(scan)
        else:
            rows[scan.name] = _row(scan.name, "resumed", report)
    state = {"cluster": None, "running": 0, "run_started": None, "ended": 0, "slots": 1}

    def tell() -> None:
        if progress is None:
            return
        counts = {status: sum(row["status"] == status for row in rows.values())
                  for status in ("inverted", "resumed", "failed")}
        left = sum(row["status"] == "pending" for row in rows.values())
        if state["run_started"] is None:
            seconds_left = None
        elif state["ended"]:
            seconds_left = left * (time.monotonic() - state["run_started"]) / state["ended"]
        else:
            seconds_left = math.ceil(left / state["slots"]) * time_budget_s
        progress(BatchProgress(total=len(rows), running=state["running"], seconds_left=seconds_left,
                               cluster=state["cluster"], **counts))

    try:
        if todo:
            with connect(scheduler, workers, threads_per_worker, security, retries) as (client, description):
                state["cluster"], state["run_started"] = description, time.monotonic()
                _run(client, todo, rows, settings, time_budget_s, seed, invert_options, retries, state, tell)
        else:
            tell()
    finally:
        by_name = {scan.name: scan for scan in scans}
        summary = write_reports(out_dir, rows, settings, state["cluster"], time.monotonic() - started,
                                lambda name: by_name[name].read_pictures())
    return summary


def _run(client, todo: list[Scan], rows: dict, settings: dict, time_budget_s: float, seed: int,
         invert_options: dict, retries: int, state: dict, tell) -> None:
    """Submit ``todo`` a few scans ahead, store each result as it comes; cancel what is left on interrupt."""
    from distributed import as_completed

    from .worker import invert_scan

    queue, in_flight = iter(todo), {}
    completed = as_completed()

    def submit_next() -> bool:
        for scan in queue:
            try:
                data = read_image_bytes(scan.target, "target")
            except ImageFormatError as exc:
                rows[scan.name] = _failed(scan.name, str(exc))
                continue
            future = client.submit(invert_scan, scan.name, data, time_budget_s, seed, invert_options,
                                   key=f"invert-{uuid.uuid4().hex}", resources={SCAN_RESOURCE: 1},
                                   retries=retries)
            in_flight[future] = (scan, sha256(data))
            completed.add(future)
            return True
        return False

    def fill() -> None:
        state["slots"] = max(len(client.nthreads()), 1)
        while len(in_flight) < SCANS_AHEAD_PER_WORKER * state["slots"] and submit_next():
            pass
        state["running"] = min(len(in_flight), state["slots"])

    try:
        fill()
        tell()
        for future in completed:
            scan, target_sha256 = in_flight.pop(future)
            if future.status == "finished":
                result = future.result()
                rows[scan.name] = _failed(scan.name, result["error"]) if "error" in result else \
                    _row(scan.name, "inverted", _store(scan, result, target_sha256, settings))
            elif future.status == "cancelled":
                rows[scan.name] = _failed(scan.name, "cancelled by the cluster")
            else:
                rows[scan.name] = _failed(scan.name, _reason(future.exception()))
            future.release()
            state["ended"] += 1
            fill()
            tell()
    except BaseException:
        client.cancel(list(in_flight))
        raise
