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
   light, not its own line's;
3. with ``--column-solve``, the compensation per A-scan that item 2 lacks,
   for lights given and fixed: lights of one value (0.5), of a smooth
   lateral profile (0.5 + 0.3·sin(i/40)) and with independent noise per
   line (0.5·(1 + 0.1·N(0, 1))), each the same at every depth. Each
   iteration decodes the line field L exactly
   (:func:`~octcl.host.stage2.exact.decoded_weights`), renders its rows with
   every row dimmed by the light of each A-scan it reaches (the scanner's
   model for fixed lights: T_i·Σ_{i'} B_{i−i'}·w_{i'}, then the depth
   kernel), and adds to L the column-space residual divided by the light
   and taken back across lines by Tikhonov-regularised least squares with
   the scanner's lateral weights B (5 taps; the banded normal equations
   (BᵀB + λ)·x = Bᵀ·r, λ = ``--regularisation``). Prints the largest
   residual over the largest column value per iteration. The field is
   first replaced by its least-norm twin (:meth:`FieldOperator.pseudo_inverse`
   of its own rendering, then the hinge fit back onto the target's levels):
   the field stage 1 finds carries lateral detail its rendering does not
   show, which the residual's way back across lines cannot reach.

Example::

    python scripts/check_tissue_decode.py --skin 5 --scales 0.0001 0.1 0.3
    python scripts/check_tissue_decode.py --skin 5 --column-solve --regularisation 1e-3 1e-5
"""

from __future__ import annotations

import argparse

import numpy as np
import scipy.linalg
from scipy.ndimage import convolve1d

from octcl import _reference as ref
from octcl.config import DEFAULT_CONFIG
from octcl.host.stage1.start import linear_start
from octcl.host.stage2 import tissue
from octcl.host.stage1.backend import make_backend
from octcl.host.stage1.ceiling import aimed_levels
from octcl.host.stage1.operator import FieldOperator
from octcl.host.stage1.solve import FieldSolve
from octcl.host.stage2.exact import decoded_weights, phantom_of_rows, rendered_cells
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


def lateral_taps() -> np.ndarray:
    """B_d = e^{−(d·Δx)²/w0²} over the lines a scatterer on the A-scan lines reaches (the contribution window)."""
    config = DEFAULT_CONFIG
    reach = int(np.sqrt(ref.CONTRIBUTION_RADIUS_SQ) * config.beam_radius_um / config.lateral_pitch_um)
    offsets_um = np.arange(-reach, reach + 1) * config.lateral_pitch_um
    return ref.beam_weight(offsets_um, np.zeros_like(offsets_um), config.beam_radius_um)


def lateral_solver(regularisation: float):
    """x ↦ argmin ‖B·x − r‖² + λ‖x‖² across lines (B the truncated convolution with :func:`lateral_taps`), per row."""
    taps, lines = lateral_taps(), DEFAULT_CONFIG.a_scans
    reach = taps.size // 2
    matrix = sum(np.diag(np.full(lines - abs(k), taps[k + reach]), k) for k in range(-reach, reach + 1))
    normal = matrix.T @ matrix + regularisation * np.eye(lines)
    bands = 2 * reach
    banded = np.zeros((2 * bands + 1, lines))
    for k in range(-bands, bands + 1):
        banded[bands - k, max(k, 0):lines + min(k, 0)] = np.diagonal(normal, k)

    def solve(residual: np.ndarray) -> np.ndarray:
        right = matrix.T @ residual.T
        both = scipy.linalg.solve_banded((bands, bands), banded, np.concatenate([right.real, right.imag], axis=1))
        return (both[:, :residual.shape[0]] + 1j * both[:, residual.shape[0]:]).T

    return solve


def least_norm_field(field: np.ndarray, levels: np.ndarray) -> np.ndarray:
    """The field's least-norm twin, fitted back onto the target's levels (module docstring, item 3)."""
    operator = FieldOperator(DEFAULT_CONFIG)
    solve = FieldSolve(levels, aimed_levels(levels), make_backend("opencl", DEFAULT_CONFIG))
    return solve.fit_levels(operator.pseudo_inverse(operator.apply(field), 1e-3), levels, 200).field


def column_solve(field: np.ndarray, lights: np.ndarray, regularisation: float, iterations: int = 10) -> list[float]:
    """Item 3 of the module docstring for ``lights`` (Nz, Nx): the relative residual after each iteration."""
    taps, shadow = lateral_taps(), tissue.local_mean_energy(field)
    target = convolve1d(field, taps, axis=1, mode="constant")
    solve, line, residuals = lateral_solver(regularisation), field / lights, []
    for _ in range(iterations):
        weights = decoded_weights(line, DEFAULT_CONFIG, offsets=tissue.TISSUE_OFFSETS, shadow=shadow)
        shown = rendered_cells(lights * convolve1d(weights, taps, axis=2, mode="constant"), DEFAULT_CONFIG,
                               tissue.TISSUE_OFFSETS)
        residual = target - shown
        residuals.append(float(np.abs(residual).max() / np.abs(target).max()))
        line = line + solve(residual / lights)
    return residuals


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--skin", type=int, default=5, help="skin phantom seed (default 5)")
    parser.add_argument("--rows", nargs="+", type=int, default=[50, 80, 110, 150, 200])
    parser.add_argument("--scales", nargs="+", type=float, default=[0.0001, 0.1, 0.3, 1.0])
    parser.add_argument("--column-solve", action="store_true", help="item 3 of the description, instead of 1–2")
    parser.add_argument("--regularisation", nargs="+", type=float, default=[1e-3, 1e-5])
    args = parser.parse_args(argv)
    levels = render(Phantom.skin(args.skin)).levels
    exact = ExactScore(levels)
    field = linear_start(levels, lambda image: exact(image)["mean"]).field
    if args.column_solve:
        twin = least_norm_field(field, levels)
        lines = np.arange(DEFAULT_CONFIG.a_scans)
        noise = np.random.default_rng(0).standard_normal(lines.size)
        for name, profile in (("one value", np.full(lines.size, 0.5)), ("smooth", 0.5 + 0.3 * np.sin(lines / 40)),
                              ("noisy per line", 0.5 * (1 + 0.1 * noise))):
            for regularisation in args.regularisation:
                residuals = column_solve(twin, np.broadcast_to(profile, field.shape), regularisation)
                print(f"lights {name}, λ {regularisation:g}: residual per iteration "
                      + " ".join(f"{value:.1e}" for value in residuals))
        return
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
