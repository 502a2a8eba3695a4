"""Where the tissue decode's start falls short: its assumed light against the light its phantom makes.

For a skin phantom (``octcl phantom skin --seed N``, rendered by the
scanner): stage 1's field (:func:`octcl.host.stage1.start.linear_start`),
then :func:`octcl.host.stage2.tissue.decode_tissue`. Prints

1. per depth row (``--rows``), the decode's own transmission of each line
   (the first layer of the cell row) against the transmission its phantom
   makes in the scanner (:func:`octcl.tissue.transmission_map`): the
   difference in dB, 5th, 50th and 95th percentiles over the lines with both
   positive;
2. the same rows decoded from the top instead, each row divided by its own
   line's exact light (T computed layer by layer from the rows above, as
   the scanner does, no per-line bottom light to choose), at the decode's
   scale c² times each of ``--scales``: the share of pixels the phantom
   renders at the target's level and its shadow at the bottom of the
   visible tissue. Where the light is exact per line, what is left off is
   the lateral coupling: a row reaches its neighbours' A-scans under their
   light, not its own line's.

Example::

    python scripts/check_tissue_decode.py --skin 5 --scales 0.0001 0.1 0.3
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.ndimage import convolve1d

from octcl import _reference as ref
from octcl.config import DEFAULT_CONFIG
from octcl.host.stage1.start import linear_start
from octcl.host.stage2 import tissue
from octcl.host.stage2.exact import decoded_weights, phantom_of_rows
from octcl.host.stage3.loss import ExactScore
from octcl.phantom import Phantom
from octcl.render import render
from octcl.tissue import shadow_db, transmission_map


def light_mismatch_db(decoded: tissue.TissueDecode, rows: list[int]) -> None:
    made = transmission_map(decoded.phantom, DEFAULT_CONFIG)
    assumed = decoded.transmission[::len(tissue.TISSUE_OFFSETS)]  # the first layer of each cell row
    for row in rows:
        both = (made[row] > 0) & (assumed[row] > 0)
        difference = 20 * np.log10(made[row, both] / assumed[row, both])
        print(f"row {row}: made/assumed light, dB (5, 50, 95 %): {np.round(np.quantile(difference, [0.05, 0.5, 0.95]), 2)}")


def top_down_rows(weights: np.ndarray, scale_sq: float) -> np.ndarray:
    """The decode's rows (D, Nz, Nx) at c² = ``scale_sq``, each divided by its line's light from the top."""
    config, taps = DEFAULT_CONFIG, ref.shadow_taps(DEFAULT_CONFIG)
    order = tissue.layer_order(config)
    layers = weights.reshape(-1, config.a_scans)[order]
    light, amplitudes = np.ones(config.a_scans), np.zeros_like(layers)
    for index, layer in enumerate(layers):
        amplitude_sq = np.minimum(scale_sq * layer**2 / np.maximum(light, 1e-300) ** 2, tissue.MAX_AMPLITUDE_SQ)
        amplitudes[index] = np.sqrt(amplitude_sq)
        light = light * np.maximum(1.0 - convolve1d(amplitude_sq, taps, mode="constant"), 0.0)
    rows = np.empty_like(amplitudes)
    rows[order] = amplitudes
    return rows.reshape(weights.shape) * (weights > 0)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--skin", type=int, default=5, help="skin phantom seed (default 5)")
    parser.add_argument("--rows", nargs="+", type=int, default=[50, 80, 110, 150, 200])
    parser.add_argument("--scales", nargs="+", type=float, default=[0.0001, 0.1, 0.3, 1.0])
    args = parser.parse_args(argv)
    levels = render(Phantom.skin(args.skin)).levels
    exact = ExactScore(levels)
    field = linear_start(levels, lambda image: exact(image)["mean"]).field
    decoded = tissue.decode_tissue(field, DEFAULT_CONFIG)
    print(f"skin {args.skin}: decode c² {decoded.scale**2:.4g}, lines short of light {decoded.short_lines}, pixels at "
          f"their level {np.mean(render(decoded.phantom).levels == levels):.3f}")
    light_mismatch_db(decoded, args.rows)
    weights = decoded_weights(field, DEFAULT_CONFIG, offsets=tissue.TISSUE_OFFSETS,
                                     shadow=tissue.local_mean_energy(field))
    for factor in args.scales:
        phantom = phantom_of_rows(top_down_rows(weights, factor * decoded.scale**2), DEFAULT_CONFIG,
                                  tissue.TISSUE_OFFSETS)
        rendered = render(phantom).levels
        print(f"from the top, c² × {factor:g}: pixels at their level {np.mean(rendered == levels):.3f}, shadow "
              f"{shadow_db(transmission_map(phantom, DEFAULT_CONFIG), levels):.1f} dB")


if __name__ == "__main__":
    main()
