"""The exact score along a hinge phase, from the tissue regime's pixel phases' end, every few iterations.

For each target, ``octcl invert --regime tissue --iterations 0`` (stages 1–2)
gives the start once (kept in ``--out``, as ``scripts/bench_tissue_refine.py`` keeps it); the tissue schedule's pixel phases
(:data:`octcl.host.pipeline.invert.TISSUE_SCHEDULE`, its phases before the
hinge) run from it once; then a hinge phase of ``--iterations`` runs from
their end for each ``--anchor-weights`` value
(:attr:`~octcl.host.stage3.schedule.RefineSchedule.hinge_anchor_weight`) and each
``--relative-exponents`` γ (:attr:`~octcl.host.stage3.schedule.Phase.relative_exponent`),
scored every ``--score-every`` iterations. One JSON row per run: the target,
the weight, γ and the (iteration, exact score) pairs.

Example::

    python scripts/bench_hinge_trace.py --targets OUT/targets/plain_skin_2.png ../shared/data/real/orange.png \\
        --iterations 60 --anchor-weights 1 1000 --out OUT
    python scripts/bench_hinge_trace.py --targets OUT/targets/skin_6.png --iterations 300 --score-every 20 \
        --relative-exponents 0 0.5 --out OUT
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import sys
from pathlib import Path

from octcl.host.pipeline.invert import TISSUE_SCHEDULE
from octcl.host.stage3.refine import Phase, RefineSchedule, refine
from octcl.host.stage3.schedule import HINGE

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_tissue_refine import tissue_start  # noqa: E402


def trace(target: Path, iterations: int, weights: list[float], exponents: list[float], score_every: int,
          out: Path) -> None:
    """The JSON rows of one target (module docstring)."""
    levels, aim, start = tissue_start(target, target.stem, out)
    pixel_phases = tuple(phase for phase in TISSUE_SCHEDULE.phases if phase.terms != HINGE)
    pixel = dataclasses.replace(TISSUE_SCHEDULE, phases=pixel_phases, restarts=(), score_every=10**6)
    warm = refine(start, levels, pixel, threads=2, aim=aim).phantom
    for weight, exponent in itertools.product(weights, exponents):
        hinge = RefineSchedule(phases=(Phase(iterations, 0.0, 0.0, terms=HINGE, relative_exponent=exponent),),
                               restarts=(), score_every=score_every, hinge_anchor_weight=weight)
        result = refine(warm, levels, hinge, threads=2, aim=aim)
        print(json.dumps({"target": target.stem, "anchor_weight": weight, "relative_exponent": exponent,
                          "scores": [(entry["iteration"], entry["score"]) for entry in result.trace
                                     if entry["score"] is not None]}), flush=True)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--targets", nargs="+", type=Path, required=True)
    parser.add_argument("--iterations", type=int, default=60, help="the hinge phase's iterations (default 60)")
    parser.add_argument("--anchor-weights", nargs="+", type=float, default=[1.0],
                        help="the anchor pixel's weight, one run each (default 1)")
    parser.add_argument("--relative-exponents", nargs="+", type=float, default=[0.0],
                        help="the hinge's γ in [0, 1], one run each with each weight (default 0)")
    parser.add_argument("--score-every", type=int, default=2, help="iterations between scores (default 2)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    for target in args.targets:
        trace(target, args.iterations, args.anchor_weights, args.relative_exponents, args.score_every, args.out)


if __name__ == "__main__":
    main()
