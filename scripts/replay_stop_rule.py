"""Where stage 3's restart rules would have stopped, replayed on runs that ran every restart.

A run of ``octcl invert TARGET --stop-rule none --report R.json`` (every
restart once, no decision from the gains) holds in its trace the exact
score at each restart's checkpoints. A rule that ends the refinement once
the last P restarts together gained less than G
(:attr:`octcl.host.stage3.schedule.RefineSchedule.min_gain`, ``restart_patience``)
takes the same steps up to where it stops, so its score and time there are
the trace's (:func:`bench_invert.replay_restart_rule`, over
:func:`bench_invert.restart_stages`): one whole run per
target compares every rule without rerunning.

Prints markdown: per report, each restart's gain over the best before it
(in 1e−6), then per rule ``G/P`` the best score and the seconds it would
have ended at.

Example::

    octcl invert skin_6.png --regime tissue --stop-rule none -o OUT/skin_6.txt --report OUT/skin_6.json
    python scripts/replay_stop_rule.py OUT/*.json --rules 1e-5/1 5e-6/2
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_invert import replay_restart_rule, restart_stages  # noqa: E402  (a script beside this one)


def parse_rule(text: str) -> tuple[float, int]:
    """``G/P`` → (min_gain G, restart_patience P)."""
    try:
        gain, patience = text.split("/")
        rule = float(gain), int(patience)
    except ValueError:
        raise argparse.ArgumentTypeError(f"a rule is MIN_GAIN/PATIENCE (e.g. 5e-6/2), got {text!r}") from None
    if not (rule[0] >= 0 and rule[1] >= 1):
        raise argparse.ArgumentTypeError(f"need MIN_GAIN ≥ 0 and PATIENCE ≥ 1, got {text!r}")
    return rule


def table(reports: dict[str, dict], rules: list[tuple[float, int]]) -> str:
    header = ["report", "restart gains (1e−6)", "whole run: score / s"] + [f"{g:g}/{p}: score / s" for g, p in rules]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for name, report in reports.items():
        trace, total_s = report["trace"], report["seconds"]["total"]
        gains = " ".join(f"{1e6 * (after - before):.1f}" for before, after, _ in restart_stages(trace))
        cells = [name, gains, f"{report['score']:.7f} / {total_s:.0f}"]
        for gain, patience in rules:
            score, seconds = replay_restart_rule(trace, total_s, gain, patience)
            cells.append(f"{score:.7f} / {seconds:.0f}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("reports", nargs="+", type=Path, help="invert reports of --stop-rule none runs")
    parser.add_argument("--rules", nargs="+", type=parse_rule, default=[(1e-5, 1), (5e-6, 2)],
                        help="MIN_GAIN/PATIENCE pairs (default: 1e-5/1 5e-6/2)")
    args = parser.parse_args(argv)
    reports = {}
    for path in args.reports:
        report = json.loads(path.read_text())
        if report.get("score") is None or not report.get("trace"):
            parser.error(f"{path}: no score or no trace (a run whose score was left out cannot be replayed)")
        reports[path.stem] = report
    sys.stdout.write(table(reports, args.rules))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
