"""Render the three official phantoms with the float64 reference scanner and
compare the 8-bit pixels with the official SynthOCT scans.

Usage::

    python scripts/check_reference.py [--data DIR] [--depth-order {numpy-introsort,stable}]

DIR is the folder holding ``official/``; it defaults to the repository's
``data/`` (see ``data/README.md``). Prints, per scan, the share of identical
pixels, the histogram of level differences (ours − official) and the
rendering time.

The reference orders depths as the scanner's NumPy classic ``np.argsort``
(``numpy-introsort``, :mod:`octcl.device.depth_order`); ``--depth-order stable``
replaces that step by a stable sort, ties in file order, to show what the
order of tied depths is worth (docs/scanner.md, "Residual"). The reference
module itself is not changed.
"""

from __future__ import annotations

import argparse
import functools
import sys
import time
from pathlib import Path

import numpy as np

from octcl import _reference
from octcl._io import read_png_rgb
from octcl.config import DEFAULT_CONFIG
from octcl.phantom import Phantom

SCANS = [
    ("uniform", 42, "Scan_Exp1_Uniform_A.png"),
    ("uniform", 101, "Scan_Exp1_Uniform_B.png"),
    ("layers", 42, "Scan_Exp2_Layers_A.png"),
]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path,
                        default=Path(__file__).resolve().parents[1] / "data")
    parser.add_argument("--depth-order", choices=("numpy-introsort", "stable"), default="numpy-introsort")
    args = parser.parse_args(argv)
    official_dir = args.data / "official"
    if not official_dir.is_dir():
        print(f"error: {official_dir} is not a folder", file=sys.stderr)
        return 2
    if args.depth_order == "stable":
        _reference.depth_order = functools.partial(np.argsort, kind="stable")
    print(f"depth order: {args.depth_order}")
    worst = 100.0
    for kind, seed, name in SCANS:
        official = read_png_rgb(official_dir / name, shape=DEFAULT_CONFIG.shape)[:, :, 0]
        start = time.perf_counter()
        levels = _reference.render_reference(Phantom.baseline(kind, seed)).levels
        seconds = time.perf_counter() - start
        diff = levels.astype(int) - official.astype(int)
        identical = 100.0 * np.mean(diff == 0)
        worst = min(worst, identical)
        values, counts = np.unique(diff, return_counts=True)
        histogram = "  ".join(f"{v:+d}: {c}" for v, c in zip(values.tolist(), counts.tolist()))
        print(f"{name:26s} Phantom.baseline({kind!r}, {seed:3d})  {identical:8.4f} % identical  "
              f"max |diff| {np.abs(diff).max()}  [{histogram}]  {seconds:5.1f} s", flush=True)
    return 0 if worst >= 99.9 else 1


if __name__ == "__main__":
    sys.exit(main())
