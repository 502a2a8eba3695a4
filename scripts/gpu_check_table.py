"""The timing and table steps of ``scripts/gpu_check.sh run`` (docs/gpu_check.md); the standard library only.

``time OUT --scans DIR --extra DIR``: runs the default ``python -m octcl.cli invert TARGET -o PHANTOM.txt --json
--quiet`` on each official scan (``DIR/Scan_*.png`` but the ``_OAC``, ``_SC`` and ``_RSC`` maps) and on each
PNG of ``--extra`` (the real scan orange, also with ``--time-budget 3``, and in the tissue regime with
``--time-budget`` :data:`TISSUE_BUDGET_S` and a report, whose stage-3 timings per part are kept: what a step of
stage 3 costs on the machine), one process each, and appends one JSON line a run to ``OUT/timings.jsonl``: the
process's wall time as this parent saw it, its exit status and invert's JSON document. Standard error of failed
runs goes to ``OUT/invert.log``.

``table OUT``: writes ``OUT/gpu_check.md`` from ``env.txt``, ``devices.txt``, ``timings.jsonl``,
``kernel_tests.xml`` and ``kernel_tests.txt`` there.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time
import xml.etree.ElementTree as ElementTree
from pathlib import Path

MAPS = ("_OAC", "_SC", "_RSC")
STAGES = ("field", "decode", "setup", "refine", "written", "total")
IMPLEMENTATIONS = ("nvidia", "amd", "intel-gpu", "pocl", "intel", "oclgrind")
#: The tissue regime's run on each extra scan: long enough for its pixel phase and some full-loss steps.
TISSUE_BUDGET_S = 30
#: Stage 3's parts as the report's ``refine_timings_s`` names them.
REFINE_PARTS = ("set_phantom", "forward", "loss", "adjoint", "adam", "exact_score")


def runs(scans: Path, extra: Path | None, only: set[str]) -> list[tuple[str, Path, list[str]]]:
    """(label, target, extra options) of each run, official scans first."""
    targets = sorted(p for p in scans.glob("Scan_*.png") if not p.stem.endswith(MAPS))
    if not targets:
        raise SystemExit(f"gpu_check_table: no Scan_*.png scans in {scans}")
    found = [(p.stem, p, []) for p in targets]
    for p in sorted(extra.glob("*.png")) if extra and extra.is_dir() else []:
        found += [(p.stem, p, []), (f"{p.stem} --time-budget 3", p, ["--time-budget", "3"]),
                  (f"{p.stem} --regime tissue", p, ["--regime", "tissue", "--time-budget", str(TISSUE_BUDGET_S)])]
    if only:
        unknown = only - {label.split()[0] for label, _, _ in found}
        if unknown:
            raise SystemExit(f"gpu_check_table: GPU_CHECK_SCANS names {', '.join(sorted(unknown))}, which are not "
                             f"among {', '.join(dict.fromkeys(label.split()[0] for label, _, _ in found))}")
        found = [run for run in found if run[0].split()[0] in only]
    return found


def time_runs(args) -> int:
    out = Path(args.out)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    only = {name.strip() for name in args.only.split(",") if name.strip()}
    end = time.monotonic() + args.seconds
    failures = 0
    with open(out / "timings.jsonl", "a") as jsonl, open(out / "invert.log", "a") as log:
        for order, (label, target, options) in enumerate(runs(Path(args.scans), Path(args.extra) if args.extra else None, only)):
            phantom = work / f"{label.replace(' ', '_')}.txt"
            report = phantom.with_suffix(".report.json")
            command = [sys.executable, "-m", "octcl.cli", "invert", str(target), "-o", str(phantom), *options,
                       *(["--report", str(report)] if "--regime" in options else []), "--json", "--quiet"]
            record = {"run": label, "order": order, "target": target.name, "options": options,
                      "command": " ".join(["python", *command[1:]])}
            timeout = min(args.timeout, end - time.monotonic())
            if timeout < 5:
                record.update(rc=None, error=f"not run: the timing step's {args.seconds:.0f} s were spent")
                jsonl.write(json.dumps(record) + "\n")
                jsonl.flush()
                print(f"gpu_check: {label}: not run (no time left)", flush=True)
                continue
            started = time.monotonic()
            try:
                done = subprocess.run(command, capture_output=True, text=True, timeout=timeout)
                wall, rc, stdout, stderr = time.monotonic() - started, done.returncode, done.stdout, done.stderr
            except subprocess.TimeoutExpired as exc:
                wall, rc = time.monotonic() - started, "timeout"
                stdout = exc.stdout.decode() if isinstance(exc.stdout, bytes) else exc.stdout or ""
                stderr = (exc.stderr.decode() if isinstance(exc.stderr, bytes) else exc.stderr or "") + \
                    f"\n(killed after {timeout:.0f} s)"
            record.update(rc=rc, wall_s=round(wall, 3))
            try:
                record["result"] = json.loads(stdout) if rc == 0 else None
            except json.JSONDecodeError:
                record["result"] = None
                record["stdout"] = stdout[-2000:]
            if rc != 0 or record["result"] is None:
                failures += 1
                lines = [line for line in stderr.splitlines() if line.strip()]
                record["error"] = lines[-1] if lines else f"exit status {rc}, no message"
                log.write(f"===== {label} (exit {rc}, {wall:.1f} s): {record['command']}\n{stderr[-20000:]}\n")
                log.flush()
            if report.exists():  # stage 3's seconds per part, and its steps
                contents = json.loads(report.read_text())
                record["refine"] = {"timings_s": contents.get("refine_timings_s"),
                                    "iterations": contents.get("iterations")}
            jsonl.write(json.dumps(record) + "\n")
            jsonl.flush()
            result = record["result"] or {}
            print(f"gpu_check: {label}: exit {rc}, {wall:.1f} s, score {result.get('score')}, "
                  f"seconds {result.get('seconds')}" + (f", error: {record['error']}" if "error" in record else ""),
                  flush=True)
    return 1 if failures else 0


def _number(value, digits: int) -> str:
    return f"{value:.{digits}f}" if isinstance(value, (int, float)) and not isinstance(value, bool) else "–"


def _read(path: Path) -> str:
    try:
        return path.read_text(errors="replace")
    except OSError:
        return ""


def _kernel_tests(out: Path) -> list[str]:
    lines = ["## Kernel tests", ""]
    text = _read(out / "kernel_tests.txt")
    xml = out / "kernel_tests.xml"
    if xml.is_file():
        try:
            root = ElementTree.parse(xml).getroot()
        except ElementTree.ParseError as exc:
            root = None
            lines.append(f"kernel_tests.xml does not parse: {exc}")
        if root is not None:
            cases = list(root.iter("testcase"))
            tallies: dict[str, dict[str, int]] = {}
            failed = []
            for case in cases:
                outcome = ("failed" if case.find("failure") is not None or case.find("error") is not None
                           else "skipped" if case.find("skipped") is not None else "passed")
                name = case.get("name", "")
                found = [impl for impl in IMPLEMENTATIONS if re.search(rf"[\[-]{re.escape(impl)}[\]-]", name)]
                key = found[0] if found else "(no implementation in the id)"
                tallies.setdefault(key, {}).setdefault(outcome, 0)
                tallies[key][outcome] += 1
                if outcome == "failed":
                    failed.append(f"{case.get('classname', '')}::{name}")
            suite = root if root.tag == "testsuite" else root.find("testsuite")
            if suite is not None:
                lines.append(f"{suite.get('tests')} tests, {suite.get('failures')} failures, {suite.get('errors')} "
                             f"errors, {suite.get('skipped')} skipped, {float(suite.get('time', 0)):.1f} s.")
                lines.append("")
            lines += ["| implementation | passed | failed | skipped |", "|---|---|---|---|"]
            for key, tally in sorted(tallies.items()):
                lines.append(f"| {key} | {tally.get('passed', 0)} | {tally.get('failed', 0)} | {tally.get('skipped', 0)} |")
            if failed:
                lines += ["", "Failed:", ""] + [f"- `{name}`" for name in failed[:30]]
                if len(failed) > 30:
                    lines.append(f"- ... and {len(failed) - 30} more (kernel_tests.xml)")
    else:
        lines.append("No kernel_tests.xml (not run, or stopped before pytest wrote it).")
    tail = [line for line in text.splitlines() if line.strip()][-6:]
    if tail:
        lines += ["", "```", *tail, "```"]
    return lines


def table(args) -> int:
    out = Path(args.out)
    records = [json.loads(line) for line in _read(out / "timings.jsonl").splitlines() if line.strip()]
    env = _read(out / "env.txt")
    gpu = next((line for line in env.splitlines()[env.splitlines().index("# GPU") + 1:]
                if line.strip()), "?") if "# GPU" in env.splitlines() else "?"
    versions = [line for line in env.splitlines()
                if re.match(r"(python|octcl|pyopencl|numpy|torch|torch\.cuda|cpus) ", line)]
    lines = ["# octcl GPU check", "",
             f"GPU: {gpu}. Whole run {args.elapsed:.0f} s.", "",
             "```", *versions, "```", "",
             "## OpenCL devices (`octcl devices`)", "", "```", *_read(out / "devices.txt").rstrip().splitlines(),
             "```", "",
             "## Default `octcl invert` per scan", "",
             "One process per run, in this order (the first pays the cold start: imports, kernel builds). "
             "wall: the process as the parent saw it; the stage columns are the JSON's `seconds`; "
             "`written`: seconds from the process's start until the phantom was written; `threads`: CPU threads, "
             "`timed` where invert chose them by timing.", "",
             "| run | exit | score | wall s | " + " | ".join(f"{s} s" for s in STAGES)
             + " | stop | iterations | threads | peak MiB |",
             "|---|---|---|---|" + "---|" * len(STAGES) + "---|---|---|---|"]
    for record in records:
        result = record.get("result") or {}
        seconds = result.get("seconds") or {}
        lines.append(" | ".join([
            f"| {record['run']}", str(record.get("rc")), _number(result.get("score"), 6),
            _number(record.get("wall_s"), 2), *(_number(seconds.get(s), 2) for s in STAGES),
            str(result.get("stop_reason", "–")), str(result.get("iterations", "–")),
            "timed" if result and result.get("threads") is None else str(result.get("threads", "–")),
            _number(result.get("peak_memory_mib"), 0)]) + " |")
    refined = [record for record in records if (record.get("refine") or {}).get("timings_s")
               and record["refine"].get("iterations")]
    if refined:
        lines += ["", "## Stage 3's step", "",
                  "Milliseconds per stage-3 step by part (the report's `refine_timings_s` over its iterations; "
                  "`exact_score` is spent at checkpoints only, spread over the steps here).", "",
                  "| run | steps | " + " | ".join(f"{part} ms" for part in REFINE_PARTS) + " | all ms |",
                  "|---|---|" + "---|" * (len(REFINE_PARTS) + 1)]
        for record in refined:
            timings, steps = record["refine"]["timings_s"], record["refine"]["iterations"]
            lines.append(f"| {record['run']} | {steps} | " + " | ".join(
                _number(1000 * timings.get(part, 0.0) / steps, 1) for part in REFINE_PARTS)
                + f" | {_number(1000 * sum(timings.values()) / steps, 1)} |")
    errors = [f"- {record['run']}: {record['error']}" for record in records if record.get("error")]
    if errors:
        lines += ["", "Errors (invert.log has their standard error):", "", *errors]
    other = sorted({key for record in records for key in ((record.get("result") or {}).get("seconds") or {})}
                   - set(STAGES))
    if other:
        lines += ["", f"Other `seconds` keys in timings.jsonl: {', '.join(other)}."]
    lines += ["", *_kernel_tests(out), ""]
    (out / "gpu_check.md").write_text("\n".join(lines))
    print("\n".join(lines))
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="step", required=True)
    p = sub.add_parser("time", help="time the default invert on each scan")
    p.add_argument("out")
    p.add_argument("--scans", required=True, help="folder of the official scans")
    p.add_argument("--extra", default="", help="folder of more PNG scans (orange.png)")
    p.add_argument("--only", default="", help="comma-separated scan names (default: all)")
    p.add_argument("--seconds", type=float, default=240.0, help="seconds for all the runs together")
    p.add_argument("--timeout", type=float, default=120.0, help="seconds one run may take")
    p.add_argument("--work", default=os.path.join(os.environ.get("TMPDIR", "/tmp"), "octcl-gpucheck", "phantoms"),
                   help="folder for the phantoms written")
    p = sub.add_parser("table", help="write OUT/gpu_check.md")
    p.add_argument("out")
    p.add_argument("--elapsed", type=float, default=float("nan"), help="seconds of the whole run")
    args = parser.parse_args(argv)
    return time_runs(args) if args.step == "time" else table(args)


if __name__ == "__main__":
    sys.exit(main())
