"""Check that a fixed-schedule inversion repeats byte for byte, and show what thread counts and seeds change.

End to end, in fresh processes, as a user runs it::

    octcl invert TARGET -o OUT --regime R --seed S --iterations N --field-iterations M --threads T

``--repeats`` times for each thread count T of ``--threads``, and once with
seed S + 1 at the first thread count; then the files' SHA-256, their scores,
and how many rows differ from the first run.

With ``--stages``, each stage first, in this process, at each thread count:
stage 1's field (``fit_field`` without a time budget, then in the linear
regime ``retrieve_field`` from it); stage 2's phantom for seed S twice and
for S + 1 (``decode_field``; the linear regime's ``decode_exact`` takes no
seed), and the scanner's 8-bit rendering of each; the
OpenCL forward and adjoint twice on one phantom; the loss's gradient and the
exact score of one rendering. For each it prints whether the bits repeat and,
where they do not, the largest difference.

Exit status 1 if two runs with the same settings but for the thread count
gave different files (or a stage gave different bits for the same inputs at
any thread count), else 0: no bit depends on torch's thread count. See
``docs/reproducibility.md`` for what the differences mean.

Example::

    python scripts/check_determinism.py data/official/Scan_Exp2_Layers_A.png --threads 1 2 --stages
"""

from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def run_cli(target: Path, output: Path, regime: str, seed: int, iterations: int, field_iterations: int,
            threads: int, time_budget: float) -> dict:
    """``octcl invert`` in a fresh process; its ``--json`` result, the file's digest and the wall time."""
    start = time.monotonic()
    completed = subprocess.run(
        [sys.executable, "-m", "octcl.cli", "invert", str(target), "-o", str(output), "--regime", regime,
         "--seed", str(seed),
         "--iterations", str(iterations), "--field-iterations", str(field_iterations), "--threads", str(threads),
         "--time-budget", str(time_budget), "--quiet", "--json"],
        capture_output=True, text=True)
    if completed.returncode != 0:
        raise SystemExit(f"octcl invert failed ({completed.returncode}): {completed.stderr.strip()}")
    result = json.loads(completed.stdout)
    result["sha256"] = hashlib.sha256(output.read_bytes()).hexdigest()
    result["wall_s"] = time.monotonic() - start
    return result


def rows_differing(first: Path, other: Path) -> str:
    """How many rows of two phantom files differ, and in which columns."""
    a, b = np.loadtxt(first), np.loadtxt(other)
    if a.shape != b.shape:
        return f"{len(a):,} against {len(b):,} rows"
    differ = (a != b).any(axis=1)
    columns = ", ".join(f"{name} {np.mean(a[:, i] != b[:, i]):.1%}" for i, name in enumerate("xyzE"))
    return f"{differ.mean():.1%} of {len(a):,} rows ({columns})"


def compare(label: str, first: np.ndarray, other: np.ndarray, same_inputs: bool) -> bool:
    """Print whether two arrays are bit-identical, else their largest difference relative to the first's range."""
    identical = np.array_equal(first, other)
    if identical:
        detail = "identical bits"
    else:
        scale = np.abs(first).max() or 1.0
        detail = f"differ: max |Δ| = {np.abs(first - other).max() / scale:.1e} of max |value|"
    print(f"  {label:<58} {detail}")
    return identical or not same_inputs


def check_stages(target_path: Path, regime: str, seed: int, field_iterations: int, thread_counts: list[int]) -> bool:
    """The stages one by one (module docstring); False if the same inputs gave different bits."""
    import torch

    from octcl.device.scanner import ScannerKernels
    from octcl.host.stage2.capped import decode_field
    from octcl.host.stage1.display import fit_field
    from octcl.host.stage1.projections import retrieve_field
    from octcl.host.stage2.exact import decode_exact
    from octcl.host.stage3.loss import DisplayLoss, ExactScore
    from octcl.host.pipeline.target import read_target, target_scan
    from octcl.phantom import TARGET_ROWS
    from octcl.render import Rendering, render

    target = read_target(target_path)
    scan = target_scan(target)
    ok = True
    print(f"stage 1: fit_field, {field_iterations} iterations, no time budget")
    fields = {threads: fit_field(scan, iterations=field_iterations, time_budget_s=None, threads=threads).field
              for threads in thread_counts}
    first = thread_counts[0]
    again = fit_field(scan, iterations=field_iterations, time_budget_s=None, threads=first).field
    ok &= compare(f"{first} thread(s), twice", fields[first], again, True)
    for threads in thread_counts[1:]:
        ok &= compare(f"{first} against {threads} threads", fields[first], fields[threads], True)

    if regime == "linear":
        print("stage 1: retrieve_field from each of those fields")
        fields = {threads: retrieve_field(scan, initial=field).field for threads, field in fields.items()}
        ok &= compare(f"{first} thread(s), twice", fields[first], retrieve_field(scan, initial=again).field, True)
        for threads in thread_counts[1:]:
            ok &= compare(f"{first} against {threads} threads", fields[first], fields[threads], True)
        print(f"stage 2: decode_exact of the {first}-thread field (no seed: S + 1 is S)")
        phantoms = [decode_exact(fields[first]) for _ in range(3)]
    else:
        print(f"stage 2: decode_field of the {first}-thread field")
        phantoms = [decode_field(fields[first], max_scatterers=TARGET_ROWS, seed=s) for s in (seed, seed, seed + 1)]
    for column in ("x_um", "y_um", "z_um", "energy_pct"):
        ok &= compare(f"seed {seed} twice: {column}", getattr(phantoms[0], column), getattr(phantoms[1], column), True)
        compare(f"seed {seed} against {seed + 1}: {column}", getattr(phantoms[0], column),
                getattr(phantoms[2], column), False)
    levels = [render(phantom).levels for phantom in (phantoms[0], phantoms[2])]
    print(f"  {'rendering, seed ' + str(seed) + ' against ' + str(seed + 1):<58} "
          f"{np.mean(levels[0] == levels[1]):.4%} of pixels identical")

    print("stage 3: OpenCL scanner, loss and exact score on the seed's phantom")
    kernels = ScannerKernels()
    phantom = phantoms[0]
    with np.errstate(divide="ignore"):
        log_energy = np.log(phantom.energy_pct)
    outputs = []
    for _ in range(2):
        kernels.set_phantom(phantom.x_um, phantom.y_um, phantom.z_um, log_energy)
        a_scans = kernels.forward(for_adjoint=True)
        outputs.append((a_scans, *kernels.adjoint(np.conj(a_scans))))
    for name, one, two in zip(("forward A-scans", "adjoint ∂/∂u", "adjoint ∂/∂z"), *outputs):
        ok &= compare(f"{name}, twice", one, two, True)
    rendering = Rendering.from_a_scans(outputs[0][0])
    loss, exact_score = DisplayLoss(scan), ExactScore(target)
    previous = torch.get_num_threads()
    gradients, scores = {}, {}
    try:
        for threads in [first, *thread_counts]:
            torch.set_num_threads(threads)
            gradient = loss(rendering.display).grad_display
            score = np.array([exact_score(rendering.levels)["mean"]])
            if threads in gradients:
                ok &= compare(f"loss gradient, {threads} thread(s), twice", gradients[threads], gradient, True)
                ok &= compare(f"exact score, {threads} thread(s), twice", scores[threads], score, True)
            gradients[threads], scores[threads] = gradient, score
    finally:
        torch.set_num_threads(previous)
    for threads in thread_counts[1:]:
        ok &= compare(f"loss gradient, {first} against {threads} threads", gradients[first], gradients[threads],
                      True)
        ok &= compare(f"exact score, {first} against {threads} threads", scores[first], scores[threads], True)
    return ok


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("target", type=Path, help="target B-scan PNG")
    parser.add_argument("--seed", type=int, default=5)
    parser.add_argument("--iterations", type=int, default=20, help="stage-3 iterations (default 20)")
    parser.add_argument("--regime", choices=("linear", "physical"), default="linear")
    parser.add_argument("--field-iterations", type=int, help="stage-1 Adam steps (default: the regime's)")
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="thread counts (default 1 2)")
    parser.add_argument("--repeats", type=int, default=2, help="runs per thread count (default 2)")
    parser.add_argument("--time-budget", type=float, default=3600.0, help="ceiling per run (default 3600 s)")
    parser.add_argument("--stages", action="store_true", help="check each stage in this process first")
    args = parser.parse_args(argv)

    if args.field_iterations is None:
        from octcl.host.pipeline.invert import FIELD_ITERATIONS

        args.field_iterations = FIELD_ITERATIONS[args.regime]
    ok = check_stages(args.target, args.regime, args.seed, args.field_iterations, args.threads) \
        if args.stages else True

    print(f"end to end: octcl invert {args.target.name} --regime {args.regime} --seed S --iterations {args.iterations} "
          f"--field-iterations {args.field_iterations} --threads T, fresh processes")
    runs = [(threads, args.seed) for threads in args.threads for _ in range(args.repeats)]
    runs.append((args.threads[0], args.seed + 1))
    with tempfile.TemporaryDirectory() as folder:
        files, results = [], []
        for index, (threads, seed) in enumerate(runs):
            files.append(Path(folder) / f"run{index}.txt")
            results.append(run_cli(args.target, files[-1], args.regime, seed, args.iterations, args.field_iterations,
                                   threads, args.time_budget))
            result = results[-1]
            print(f"  T {threads}  seed {seed}  sha256 {result['sha256'][:16]}  score {result['score']:.9f}  "
                  f"{result['scatterers']:,} rows  {result['wall_s']:.0f} s", flush=True)
        first = results[0]
        for index, ((threads, seed), result) in enumerate(zip(runs, results)):
            if index == 0:
                continue
            same_settings = seed == runs[0][1] or args.regime == "linear"  # no bit from threads; linear: nor seed
            verdict = "identical file" if result["sha256"] == first["sha256"] else \
                f"differs: {rows_differing(files[0], files[index])}, score Δ {result['score'] - first['score']:+.1e}"
            print(f"  T {threads} seed {seed} against T {runs[0][0]} seed {runs[0][1]}: {verdict}")
            ok &= result["sha256"] == first["sha256"] or not same_settings
            repeat_of = next(i for i, run in enumerate(runs) if run == (threads, seed))
            ok &= result["sha256"] == results[repeat_of]["sha256"]
    print("repeatable" if ok else "NOT repeatable: the same settings (thread counts aside) gave different bits")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
