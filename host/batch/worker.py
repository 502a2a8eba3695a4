"""One scan of a batch, as a Dask worker runs it: target bytes in, phantom and report bytes out.

Nothing here touches the client's files: the target arrives as the file's
bytes, is decoded and checked here (:func:`octcl.host.pipeline.target.decode_target`,
which reads the bytes as :func:`octcl.host.pipeline.target.read_target` reads the
file, so a scan inverts the same in a batch as on its own), inverted into the worker's own
scratch folder, and the phantom, its report and two pictures go back to the
client, which writes them. So workers need octcl and nothing else: no shared
file system.
"""

from __future__ import annotations

import json
import os
import platform
import tempfile
import time
from pathlib import Path

from octcl._io import ImageFormatError
from octcl.config import DEFAULT_CONFIG


def _scratch_folder() -> str | None:
    """The Dask worker's local directory (cleaned by Dask, also after a crash), else the system's."""
    try:
        from distributed import get_worker

        return get_worker().local_directory
    except ValueError:  # not inside a Dask task
        return None


def invert_scan(name: str, data: bytes, time_budget_s: float, seed: int, options: dict) -> dict:
    """Invert the target file ``data`` (PNG or ``.npy`` bytes) called ``name``.

    Parameters
    ----------
    name : str
        The target's name in messages and in the report.
    data : bytes
        The target file's contents.
    time_budget_s, seed, options
        :func:`octcl.host.pipeline.invert.invert`'s budget, seed and other keyword
        options, passed on unchanged.

    Returns
    -------
    dict
        ``name``; for a target that is not a usable B-scan only ``error``,
        its one-line reason (no retry can change that; likewise a fixed
        schedule that does not fit in the time budget); else ``phantom``
        (the file's bytes), ``report`` (invert's report, ``target`` set to
        ``name``), ``panel`` and ``plot`` (PNG bytes,
        :func:`octcl.host.batch.report.comparison_panel` and
        :func:`~octcl.host.batch.report.score_plot`), in the tissue regime
        ``tissue`` (PNG bytes, :func:`~octcl.host.batch.report.tissue_panel` of the
        written phantom's attenuation), ``cpu_s`` (this
        process's CPU seconds, all threads, while inverting), ``wall_s``,
        ``worker`` (host name and process id).

    Notes
    -----
    torch runs with as many threads as the process may use
    (:func:`octcl.host.threads.available_cores`: a Dask worker's thread
    count, set by :class:`octcl.host.batch.runner.OneScanPerWorker`). Other
    failures raise, so that Dask retries the scan.
    """
    from octcl.phantom import CONTRACT_Y_LIMIT_UM, Phantom
    from octcl.tissue import attenuation_map, transmission_map
    from octcl.torch_import import import_torch

    from ..threads import available_cores
    from ..pipeline.invert import TimeBudgetExceeded, invert
    from ..pipeline.target import decode_target

    from .report import comparison_panel, score_plot, tissue_panel, wants_score_plot

    torch = import_torch()
    started, cpu_started = time.monotonic(), time.process_time()
    config = options.get("config", DEFAULT_CONFIG)
    try:
        target = decode_target(data, config, name)
    except ImageFormatError as exc:
        return {"name": name, "error": str(exc)}
    torch.set_num_threads(available_cores())
    with tempfile.TemporaryDirectory(prefix="octcl-scan-", dir=_scratch_folder()) as scratch:
        phantom_path, report_path = Path(scratch) / "phantom.txt", Path(scratch) / "report.json"
        try:
            result = invert(target, phantom_path, time_budget_s, seed, report_path, name=name, **options)
        except TimeBudgetExceeded as exc:
            return {"name": name, "error": str(exc)}
        cpu_s = time.process_time() - cpu_started
        phantom = phantom_path.read_bytes()
        report = json.loads(report_path.read_text(encoding="utf-8"))
        attenuation = result.attenuation_per_mm
        if options.get("regime") == "tissue" and attenuation is None:  # the budget left no time for it in invert
            written = Phantom.load(phantom_path, config, y_limit_um=CONTRACT_Y_LIMIT_UM)
            attenuation = attenuation_map(transmission_map(written, config), config)
    report["target"] = name
    score = "left out (time budget)" if result.score is None else f"{result.score:.5f}"
    title = f"{name}: score {score} after {result.seconds['total']:.0f} s"
    # The written phantom's rendering and attenuation map are invert's own (InvertResult.levels,
    # .attenuation_per_mm): rendering the file again took a render, and the map a transmission map (about 1 s).
    pictures = {"panel": comparison_panel(target, result.levels, title)}
    if wants_score_plot(report["trace"]):
        pictures["plot"] = score_plot({name: report["trace"]}, name)
    if attenuation is not None:
        pictures["tissue"] = tissue_panel(target, attenuation, f"{name}: attenuation")
    return {"name": name, "phantom": phantom, "report": report, **pictures,
            "cpu_s": cpu_s, "wall_s": time.monotonic() - started, "worker": f"{platform.node()}:{os.getpid()}"}


__all__ = ["invert_scan"]
