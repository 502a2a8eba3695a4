"""Benchmark the linear regime's stages 1–2 (``octcl.host.stage1.projections``) on the development set.

For each scan and each count of display-fit Adam steps (``--adam``, 0 = the
projections start from the regularised inverse of the de-logged target),
the projections run for each of ``--projections`` steps, and the field's own
8-bit rendering is scored exactly against the target (the 8 components'
mean), with its share of pixels at the target's level and its seconds. For
the default (300 Adam steps, 300 projections) the field is also decoded
(:func:`octcl.host.stage2.exact.decode_exact`), written and read back as the
phantom file, rendered by the OpenCL scanner and by the float64 reference
(shadowing included), and scored: the phantom's score against the field's.

Writes ``linear.csv`` and ``linear.md`` in ``--out``. Example::

    python scripts/bench_linear.py --skin 3 --out OUT
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_invert import ORANGE_MISSING, development_set, write_csv  # noqa: E402

from octcl.host.stage1.display import fit_field
from octcl.host.stage1.operator import FieldOperator
from octcl.host.stage1.projections import RETRIEVAL_ITERATIONS, retrieve_field
from octcl.host.stage2.exact import decode_exact
from octcl.host.stage3.loss import ExactScore
from octcl.host.pipeline.target import read_target
from octcl.phantom import CONTRACT_Y_LIMIT_UM, Phantom  # noqa: E402
from octcl.render import Rendering, render  # noqa: E402


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("bench_linear"))
    parser.add_argument("--scans", nargs="*", help="names to run (default: all of the set)")
    parser.add_argument("--skin", type=int, default=3, help="synthetic skin targets to add (default 3)")
    parser.add_argument("--adam", type=int, nargs="+", default=[0, 150, 300, 600, 1500])
    parser.add_argument("--projections", type=int, nargs="+", default=[100, 300, 600])
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    targets = development_set(args.out, args.skin)
    if "orange" not in targets:
        print(f"{ORANGE_MISSING}: the set goes on without it", file=sys.stderr)
    operator = FieldOperator()
    rows = []
    for name in args.scans or list(targets):
        target = read_target(targets[name])
        exact = ExactScore(target)
        for adam in args.adam:
            start = time.perf_counter()
            initial = None if adam == 0 else fit_field(target, iterations=adam, time_budget_s=None, threads=1).field
            adam_s = time.perf_counter() - start
            for projections in args.projections:
                fit = retrieve_field(target, iterations=projections, initial=initial)
                levels = Rendering.from_a_scans(operator.apply(fit.field)).levels
                row = {"scan": name, "adam": adam, "projections": projections,
                       "score": exact(levels)["mean"], "identical": fit.identical,
                       "seconds": adam_s + fit.seconds,
                       "norm_ratio": float(np.linalg.norm(fit.field) / np.linalg.norm(operator.apply(fit.field)))}
                if adam == 300 and projections == RETRIEVAL_ITERATIONS:
                    start = time.perf_counter()
                    path = args.out / f"{name}_linear.txt"
                    decode_exact(fit.field).save(path)
                    row["decode_write_s"] = time.perf_counter() - start
                    phantom = Phantom.load(path, y_limit_um=CONTRACT_Y_LIMIT_UM)
                    for backend in ("opencl", "numpy"):
                        rendered = render(phantom, backend=backend).levels
                        row[f"phantom_score_{backend}"] = exact(rendered)["mean"]
                        row[f"phantom_same_as_field_{backend}"] = float(np.mean(rendered == levels))
                rows.append(row)
                print(", ".join(f"{key} {value:.6g}" if isinstance(value, float) else f"{key} {value}"
                                for key, value in row.items()), flush=True)
    columns = ["scan", "adam", "projections", "score", "identical", "seconds", "norm_ratio", "decode_write_s",
               "phantom_score_opencl", "phantom_same_as_field_opencl", "phantom_score_numpy",
               "phantom_same_as_field_numpy"]
    write_csv(args.out / "linear.csv", columns, rows)
    lines = ["| scan | " + " | ".join(f"Adam {a} + {p} proj." for a in args.adam for p in args.projections) + " |",
             "|---|" + "---|" * (len(args.adam) * len(args.projections))]
    for name in dict.fromkeys(row["scan"] for row in rows):
        cells = {(row["adam"], row["projections"]): row for row in rows if row["scan"] == name}
        lines.append(f"| {name} | " + " | ".join(
            f"{cells[a, p]['score']:.5f} ({cells[a, p]['seconds']:.1f} s)" if (a, p) in cells else ""
            for a in args.adam for p in args.projections) + " |")
    (args.out / "linear.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
