"""H⁺'s column padding on the NumPy backend: a projection step at the first fast FFT length against the device's.

The NumPy twin pads H⁺ to the device's power of two (:func:`octcl.host.stage1.operator.padded_column_count`,
1024 columns for Nx = 512) so that both backends invert the same circulant extension; before 0.8.0 it padded
to :func:`scipy.fft.next_fast_len` (525). This times 50 projection steps on one thread at each, alternating,
in one process, and prints the share of pixels at their level each leaves (docs/benchmarks.md, 0.8.0)::

    python scripts/bench_padding.py [--target SCAN.png] [--repeats 2]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import scipy.fft

from octcl._io import read_scan
from octcl.host.stage1.backend import NumpyBackend
from octcl.host.stage1.levels import target_levels
from octcl.host.stage1.operator import FieldOperator, lateral_taps, padded_column_count
from octcl.host.stage1.projections import retrieve_field

REPOSITORY = Path(__file__).resolve().parents[1]
STEPS = 50


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--target", type=Path, default=REPOSITORY / "data" / "official" / "Scan_Exp1_Uniform_A.png")
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args(argv)
    levels = target_levels(read_scan(args.target))
    config = FieldOperator().config
    reach = lateral_taps(config).size // 2
    paddings = (scipy.fft.next_fast_len(config.a_scans + 2 * reach), padded_column_count(config, reach))
    for _ in range(args.repeats):
        for padding in paddings:
            backend = NumpyBackend(config, threads=1)
            backend.operator = FieldOperator(config, workers=1, padded_columns=padding)
            start = time.perf_counter()
            fit = retrieve_field(levels, iterations=STEPS, backend=backend)
            print(f"P = {padding}: {1e3 * (time.perf_counter() - start) / STEPS:.1f} ms a projection step, "
                  f"{100 * fit.identical:.2f} % of pixels at their level")


if __name__ == "__main__":
    main()
