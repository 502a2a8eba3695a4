"""Where the tissue decode's start falls short: its assumed light against the light its phantom makes.

For a skin phantom (``octcl phantom skin --seed N``, rendered by the
scanner): stage 1's field (:func:`octcl.host.stage1.start.linear_start`),
its least-norm twin (:func:`octcl.host.stage1.start.least_norm_twin`, the
field the tissue regime decodes; stage 1's own with ``--stage1-field``) and
the spread of its lines' energies, then
:func:`octcl.host.stage2.tissue.decode_tissue`. Prints

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
   residual over the largest column value per iteration, on the
   least-norm twin: the field stage 1 finds carries lateral detail its
   rendering does not show, which the residual's way back across lines
   cannot reach.

4. with ``--coupled-sweep``, lights and line field chosen together from
   the bottom, cell row by cell row, on the least-norm twin: given the
   light below a row (every A-scan), the row's line field is the one whose
   rendering under the light above it is the target's column
   (:func:`lateral_solver`, λ = 1e−5), and the light above is the light
   below over one less the row's loss Σ_{i'} G_{i−i'}·ρ·|L_{i'}|² (ρ a
   cell's rows' energy over |L|², from its pair; each cell's energy capped
   at E = 100 % and a row's loss at 0.3, three passes per row); the light
   at the bottom per A-scan is then corrected until the light at the top
   is 1, as :func:`~octcl.host.stage2.tissue.decode_tissue` does per line
   (four passes), and ρ is taken again from the exact decode of the line
   field (two rounds), at ``FACTOR`` times the median of the lines' own
   c² (:func:`~octcl.host.stage2.tissue.tissue_scale` at 0.5, the decode's
   scale when it was measured). Prints the phantom's figures against the truth's and
   the lines whose light at the top stays above 1: there the light the
   sweep assumed is more than reaches, and the rendering is off.

5. with ``--quantiles``, the decode at each quantile of the lines' own c²
   (:data:`~octcl.host.stage2.tissue.SCALE_QUANTILE`): its shadow at the
   bottom of the visible tissue and each band's energy density against the
   truth's, the share of pixels at their level and the lines short of light;
   with ``--target PNG``, the same on a real(-like) target, without a
   truth's figures; with ``--refine SECONDS``, also stage 3
   (:data:`~octcl.host.pipeline.invert.TISSUE_SCHEDULE`, two threads) from
   each decode for that long, and the same figures with its exact score.

6. with ``--stripes``, the decode against the one before each line's
   shadow had a budget (octcl 0.8.3: each cell's pair nearest the local
   mean of |F|² unscaled, the scale from the pairs' energies): per decode,
   the lines short of light, their light at the top T(top) (5, 50, 95 %),
   the share of pixels at their level, and the stripes: each line's mean
   error of the rendering's display over rows 0–32 in dB (5, 50, 95 %) and
   its correlation with −20·log10 T(top). Both with this tree's light at
   the bottom (one value for every line since octcl 0.8.7).

7. with ``--neighbour-light RATIO ...``, the pairs' decode (its bright cells
   not split, as octcl 0.8.6's) with its lines'
   light integrated from the bottom layer by layer as the scanner loses it:
   line i loses Σ_d G_d·a²_{i−d} at a layer, a² = I/T² under the light of
   each row's own line, not under line i's as
   :func:`~octcl.host.stage2.tissue.rows_at_tissue_scale` takes it (two
   passes a layer from its root, each line's loss over its own light from
   Σ_d G_d·I_{i−d}·T_i²/T_{i−d}², the ratios clipped to [1/RATIO, RATIO];
   0: unclipped); each line's light at the bottom corrected as the decode
   did in 0.8.6. Prints per RATIO the figures of item 5 (shadow, bands
   against the truth's, median E, pixels at their level), the lines short
   of light, T(top) and the light the phantom makes against the light the
   decode assumed at rows 40, 80, 120 and 160 (item 1), and first those of
   that decode itself and of it with each row's amplitude c·w·v from the
   least-squares gain of the lines its beam reaches,
   v = Σ_d B_d²·T_{i'+d} / Σ_d B_d²·T²_{i'+d} (|d| ≤ 2, the scanner's
   window), instead of c·w/T of its own line.

8. with ``--bottom-light``, the decode with its pairs alone (octcl 0.8.6)
   and with its brightest cells split
   (:func:`~octcl.host.stage2.tissue.split_cells`), each with each line's
   own light at the bottom, corrected until its light at the top is 1
   (0.8.6), and with one light for every line, corrected until the median
   line's is (0.8.7): item 7's figures for each; with ``--target PNG``, the
   same on a real(-like) target.

Example::

    python scripts/check_tissue_decode.py --skin 5 --scales 0.0001 0.1 0.3
    python scripts/check_tissue_decode.py --skin 6 --stripes
    python scripts/check_tissue_decode.py --skin 5 --column-solve --regularisation 1e-3 1e-5
    python scripts/check_tissue_decode.py --skin 5 --coupled-sweep 1 0.3 0.1
    python scripts/check_tissue_decode.py --skin 5 --quantiles 0.5 0.75 0.9 0.95 1 --refine 45
    python scripts/check_tissue_decode.py --skin 5 --quantiles 0.95 --refine 45 --stage1-field
    python scripts/check_tissue_decode.py --target ../shared/data/real/orange.png --quantiles 0.95 1 --refine 45
    python scripts/check_tissue_decode.py --skin 6 --neighbour-light 0 1.2 1.5 2
    python scripts/check_tissue_decode.py --skin 6 --bottom-light
    python scripts/check_tissue_decode.py --target ../shared/data/real/orange.png --bottom-light
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import scipy.linalg
from scipy.ndimage import convolve1d

from octcl import _reference as ref
from octcl.config import DEFAULT_CONFIG
from octcl.host.stage1.start import least_norm_twin, linear_start
from octcl.host.stage2 import tissue
from octcl.host.stage1.backend import make_backend
from octcl.host.stage1.ceiling import aimed_levels
from octcl.host.stage1.operator import lateral_taps
from octcl.host.stage2.exact import decoded_weights, phantom_of_rows, rendered_cells
from octcl.host.pipeline.invert import TISSUE_SCHEDULE
from octcl.host.pipeline.target import read_target
from octcl.host.stage1.levels import display_of_level, target_levels
from octcl.host.stage3.loss import ExactScore
from octcl.host.stage3.refine import refine
from octcl.phantom import Phantom
from octcl.render import render
from octcl.tissue import shadow_db, tissue_figures, transmission_map


def light_spread_db(made: np.ndarray, light: np.ndarray, row: int) -> np.ndarray:
    """The light a phantom makes (:func:`~octcl.tissue.transmission_map`) over the light its decode assumed
    (``light``, (L, Nx), the first layer of each cell row taken) at pixel row ``row``, in dB: 5th, 50th and 95th
    percentiles over the lines with both positive (empty where none has)."""
    assumed = light[::light.shape[0] // made.shape[0]]
    both = (made[row] > 0) & (assumed[row] > 0)
    if not both.any():
        return np.array([])
    return np.quantile(20 * np.log10(made[row, both] / assumed[row, both]), [0.05, 0.5, 0.95])


def light_mismatch_db(decoded: tissue.TissueDecode, rows: list[int]) -> None:
    made = transmission_map(decoded.phantom, DEFAULT_CONFIG)
    for row in rows:
        quantiles = np.round(light_spread_db(made, decoded.transmission, row), 2)
        print(f"row {row}: made/assumed light, dB (5, 50, 95 %): {quantiles}")


def top_down_rows(weights: np.ndarray, scale_sq: float) -> np.ndarray:
    """The decode's rows (D, Nz, Nx) at c² = ``scale_sq``, each divided by its line's light from the top."""
    config, taps = DEFAULT_CONFIG, ref.shadow_taps(DEFAULT_CONFIG)
    order = tissue.layer_order(config, tissue.TISSUE_OFFSETS)
    layers = weights.reshape(-1, config.a_scans)[order]
    light, amplitudes = np.ones(config.a_scans), np.zeros_like(layers)
    for index, layer in enumerate(layers):
        amplitude_sq = np.minimum(scale_sq * layer**2 / np.maximum(light, 1e-300) ** 2, tissue.MAX_AMPLITUDE_SQ)
        amplitudes[index] = np.sqrt(amplitude_sq)
        light = light * np.maximum(1.0 - convolve1d(amplitude_sq, taps, mode="constant"), 0.0)
    rows = np.empty_like(amplitudes)
    rows[order] = amplitudes
    return rows.reshape(weights.shape) * (weights > 0)


def lateral_solver(regularisation: float):
    """x ↦ argmin ‖B·x − r‖² + λ‖x‖² across lines, per row: B the truncated convolution with the beam's lateral
    taps (:func:`~octcl.host.stage1.operator.lateral_taps`)."""
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


def line_energies(field: np.ndarray) -> np.ndarray:
    """Σ|F|² of each A-scan line."""
    return (np.abs(field) ** 2).sum(axis=0)


def least_norm_field(field: np.ndarray, levels: np.ndarray) -> np.ndarray:
    """The field's least-norm twin on the target's levels, as the tissue regime decodes it
    (:func:`~octcl.host.stage1.start.least_norm_twin`)."""
    return least_norm_twin(field, aimed_levels(levels), make_backend("opencl", DEFAULT_CONFIG)).field


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


#: Item 4's caps: a row's loss of light, a cell's energy (a² ≤ 1), passes per row, bottom passes, ρ rounds.
SWEEP_MAX_LOSS, SWEEP_ROW_PASSES, SWEEP_BOTTOM_PASSES, SWEEP_ROUNDS = 0.3, 3, 4, 2


def sweep_rows(column_target: np.ndarray, energy_ratio: np.ndarray, bottom: np.ndarray, solve):
    """One sweep from the bottom (item 4): the light above each cell row (Nz + 1, Nx) and the line field (Nz, Nx)."""
    taps = ref.shadow_taps(DEFAULT_CONFIG)
    rows = column_target.shape[0]
    light, line = np.empty((rows + 1, column_target.shape[1])), np.empty(column_target.shape, complex)
    light[rows] = np.sqrt(bottom)
    for row in range(rows - 1, -1, -1):
        first = solve(column_target[row][None])[0]
        # The light above as if it were the same on every line (decode_tissue's root), then the lines' own.
        least = tissue.light_above(light[row + 1], convolve1d(energy_ratio[row] * np.abs(first) ** 2, taps,
                                                              mode="constant"))
        above = least
        for _ in range(SWEEP_ROW_PASSES):
            line[row] = solve((column_target[row] / above)[None])[0]
            energy = np.minimum(energy_ratio[row] * np.abs(line[row]) ** 2, 1.0)
            loss = np.minimum(convolve1d(energy, taps, mode="constant"), SWEEP_MAX_LOSS)
            above = np.maximum(np.maximum(light[row + 1], 1e-300) / (1 - loss), least)
        light[row] = above
    return light, line


def energy_ratio(rows: np.ndarray, line_field: np.ndarray) -> np.ndarray:
    """ρ per cell: its rows' Σ w² over |L|² (1 where L = 0)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(np.abs(line_field) > 0, (rows**2).sum(0) / np.abs(line_field) ** 2, 1.0)


def coupled_sweep(field: np.ndarray, truth_figures: dict, levels: np.ndarray, scale_factor: float = 1.0) -> None:
    """Item 4 of the module docstring, printed per round, at ``scale_factor`` times the median of the lines' own c²."""
    config, solve, shadow = DEFAULT_CONFIG, lateral_solver(1e-5), tissue.local_mean_energy(field)
    weights = decoded_weights(field, config, offsets=tissue.TISSUE_OFFSETS, shadow=shadow)
    # The factor multiplies the median of the lines' own c², the decode's scale when item 4 was measured
    # (docs/benchmarks.md), not SCALE_QUANTILE's.
    scale_sq = scale_factor * tissue.tissue_scale((weights**2).sum(axis=0), ref.shadow_taps(config), 0.5)
    ratio = energy_ratio(weights, field)
    target = np.sqrt(scale_sq) * convolve1d(field, lateral_taps(), axis=1, mode="constant")
    bottom = np.zeros(config.a_scans)
    for round_ in range(SWEEP_ROUNDS):
        for _ in range(SWEEP_BOTTOM_PASSES):
            light, line = sweep_rows(target, ratio, bottom, solve)
            bottom = np.maximum(bottom + (1 - light[0] ** 2), 0.0)
        light, line = sweep_rows(target, ratio, bottom, solve)
        rows = decoded_weights(line, config, offsets=tissue.TISSUE_OFFSETS,
                               shadow=shadow * scale_sq / np.maximum(light[:-1], 1e-6) ** 2)
        ratio = energy_ratio(rows, line)
        phantom = phantom_of_rows(np.minimum(rows, 1.0), config, tissue.TISSUE_OFFSETS)
        print(f"round {round_ + 1}: lines with light above 1 at the top {int(np.sum(light[0] > 1 + 1e-3))} (largest "
              f"{light[0].max():.3g}), {figures_line(phantom, truth_figures, levels)}", flush=True)


def figures_line(phantom: Phantom, its: dict | None, levels: np.ndarray) -> str:
    """Shadow, bands over the truth's, median E and the share of pixels at their level, as one line; ``its`` the
    truth's :func:`~octcl.tissue.tissue_figures` (None for a target without one: no bands)."""
    mine = tissue_figures(phantom, levels)
    exact = f"pixels at their level {np.mean(render(phantom).levels == levels):.3f}"
    if its is None:
        return f"shadow {mine['shadow_db']:.1f} dB, median E {mine['energy_pct']['p50']:.3g} %, {exact}"
    bands = [round(ours / theirs, 2) for theirs, ours, signal in zip(
        its["band_densities_pct"], mine["band_densities_pct"], its["bands_with_signal"]) if signal]
    return (f"shadow {mine['shadow_db']:.1f} dB (truth {its['shadow_db']:.1f}), bands / truth's {bands}, median E "
            f"{mine['energy_pct']['p50']:.3g} % (truth {its['energy_pct']['p50']:.3g}), {exact}")


def quantile_choice(field: np.ndarray, truth_figures: dict | None, levels: np.ndarray, quantiles: list[float],
                    refine_s: float | None) -> None:
    """Item 5 of the module docstring."""
    for quantile in quantiles:
        decoded = tissue.decode_tissue(field, DEFAULT_CONFIG, scale_quantile=quantile)
        print(f"quantile {quantile:g}: decode {figures_line(decoded.phantom, truth_figures, levels)}, lines short "
              f"of light {decoded.short_lines}", flush=True)
        if refine_s is not None:
            result = refine(decoded.phantom, levels, TISSUE_SCHEDULE, deadline=time.monotonic() + refine_s, threads=2)
            print(f"quantile {quantile:g}: stage 3 for {refine_s:g} s ({result.iterations} steps): score "
                  f"{result.components['mean']:.5f}, {figures_line(result.phantom, truth_figures, levels)}",
                  flush=True)


def stripes(field: np.ndarray, levels: np.ndarray) -> None:
    """Item 6 of the module docstring."""
    config, taps = DEFAULT_CONFIG, ref.shadow_taps(DEFAULT_CONFIG)
    weights = decoded_weights(field, config, offsets=tissue.TISSUE_OFFSETS, shadow=tissue.local_mean_energy(field))
    nearest = tissue.rows_at_tissue_scale(weights, tissue.tissue_scale((weights**2).sum(axis=0), taps), config,
                                          tissue.TISSUE_OFFSETS)
    target = display_of_level()[levels]
    for name, decoded in (("nearest pairs (0.8.3)", nearest), ("budget", tissue.decode_tissue(field, config))):
        rendering = render(decoded.phantom)
        shown = (levels > 0) & (rendering.display > 0)
        error_db = np.where(shown, ref.DISPLAY_RANGE_DB * (rendering.display - target), np.nan)[:32]
        counted = shown[:32].any(axis=0)
        per_line = np.nanmean(error_db[:, counted], axis=0)
        top_db = -20 * np.log10(decoded.transmission[0, counted])
        print(f"{name}: lines short of light {decoded.short_lines}, T(top) (5, 50, 95 %) "
              f"{np.round(np.quantile(decoded.transmission[0], [0.05, 0.5, 0.95]), 3)}, pixels at their level "
              f"{np.mean(rendering.levels == levels):.3f}, each line's error over rows 0–32 (5, 50, 95 %) "
              f"{np.round(np.quantile(per_line, [0.05, 0.5, 0.95]), 2)} dB, correlation with −20·log10 T(top) "
              f"{np.corrcoef(per_line, top_db)[0, 1]:.2f}")


#: Item 7's passes a layer.
NEIGHBOUR_PASSES = 2


def neighbour_light(shown_sq: np.ndarray, bottom: np.ndarray, ratio: float) -> np.ndarray:
    """Item 7: each line's light above each layer (L, Nx), from the bottom, under its neighbours' light."""
    taps = ref.shadow_taps(DEFAULT_CONFIG)
    reach = taps.size // 2
    # window[i, k]: line i − d of the zero-padded lines, d = reach − k, so that taps[k] = G_d.
    window = np.arange(shown_sq.shape[1])[:, None] + np.arange(2 * reach + 1)[::-1]
    light, below = np.empty_like(shown_sq), np.sqrt(bottom)
    rooted = convolve1d(shown_sq, taps, axis=1, mode="constant")
    for layer in range(shown_sq.shape[0] - 1, -1, -1):
        above, shown = tissue.light_above(below, rooted[layer]), shown_sq[layer]
        neighbours = np.pad(shown, reach)[window]
        for _ in range(NEIGHBOUR_PASSES if shown.any() else 0):
            with np.errstate(divide="ignore", invalid="ignore"):
                # Σ_d G_d·I_{i−d}·T_i²/T_{i−d}²: what line i loses, over its own light squared (zero padded).
                lateral = np.nan_to_num(above[:, None] ** 2 / np.pad(above, reach)[window] ** 2, nan=1.0,
                                        posinf=1e300)
            if ratio:
                lateral = np.clip(lateral, 1 / ratio, ratio)
            above = tissue.light_above(below, (taps * neighbours * lateral).sum(axis=1))
        light[layer] = below = above
    return light


def least_squares_gain(light: np.ndarray) -> np.ndarray:
    """Item 7: v per row, the least-squares gain over the lines its beam reaches (|d| ≤ 2)."""
    beam_sq = lateral_taps(DEFAULT_CONFIG) ** 2  # B_d² over the scanner's window
    with np.errstate(divide="ignore", invalid="ignore"):
        return convolve1d(light, beam_sq, axis=1, mode="constant") / convolve1d(light**2, beam_sq, axis=1,
                                                                                  mode="constant")


def neighbour_rows(weights: np.ndarray, scale_sq: float, ratio: float | None, gain: bool,
                   offsets: np.ndarray = tissue.TISSUE_OFFSETS, common: bool = False):
    """Items 7 and 8: the phantom of ``weights`` (at ``offsets``) and the light it assumed, (L, Nx) in depth order;
    ``ratio`` None: each line's light as the decode takes it; the light at the bottom each line's own, corrected
    until its light at the top is 1, or with ``common`` one value, until the median line's is."""
    config, taps = DEFAULT_CONFIG, ref.shadow_taps(DEFAULT_CONFIG)
    order = tissue.layer_order(config, offsets)
    shown_sq = scale_sq * weights.reshape(-1, config.a_scans)[order] ** 2
    shadow_sq = convolve1d(shown_sq, taps, axis=1, mode="constant")

    def light_of(bottom):
        if ratio is None:
            return tissue.transmission_from_bottom(shadow_sq, bottom)
        return neighbour_light(shown_sq, bottom, ratio)

    lit = shown_sq.any(axis=0)

    def corrected(bottom):  # one value: the median line's of those with rows, as the decode takes it
        bottom = np.maximum(bottom, 0.0)
        return np.full_like(bottom, np.median(bottom[lit])) if common else bottom

    bottom = corrected(1.0 - 2.0 * shadow_sq.sum(axis=0))
    for _ in range(tissue.BOTTOM_PASSES):
        bottom = corrected(bottom + (1.0 - light_of(bottom)[0] ** 2))
    light = light_of(bottom)
    with np.errstate(divide="ignore", invalid="ignore"):
        gain_sq = least_squares_gain(light) ** 2 if gain else 1 / light**2
        amplitude_sq = np.where(shown_sq > 0, np.minimum(np.nan_to_num(shown_sq * gain_sq, nan=1.0, posinf=1.0),
                                                         tissue.MAX_AMPLITUDE_SQ), 0.0)
    rows = np.empty_like(shown_sq)
    rows[order] = np.sqrt(amplitude_sq)
    return phantom_of_rows(rows.reshape(weights.shape) * (weights > 0), config, offsets), light


def light_line(name: str, phantom: Phantom, light: np.ndarray, levels: np.ndarray, its: dict | None) -> str:
    """Items 7 and 8's figures of a phantom whose decode assumed ``light`` (L, Nx), as one line."""
    made = transmission_map(phantom, DEFAULT_CONFIG)
    rows = [f"row {row} " + (" ".join(f"{value:.2f}" for value in light_spread_db(made, light, row)) or "–")
            for row in (40, 80, 120, 160)]
    top = np.quantile(light[0], [0.05, 0.5, 0.95])
    return (f"{name}: {figures_line(phantom, its, levels)}, lines short of light {int(np.sum(light[0] > 1 + 1e-6))}, "
            f"T(top) (5, 50, 95 %) {' '.join(f'{value:.3g}' for value in top)}; made/assumed light, dB (5, 50, 95 %): "
            + "; ".join(rows))


def decode_weights(field: np.ndarray, split: bool) -> tuple[np.ndarray, float]:
    """The tissue decode's rows at the field's scale (split or pairs alone) and its scale c²."""
    taps, local_mean = ref.shadow_taps(DEFAULT_CONFIG), tissue.local_mean_energy(field)
    scale_sq = tissue.tissue_scale(local_mean, taps)
    weights = decoded_weights(field, DEFAULT_CONFIG, offsets=tissue.TISSUE_OFFSETS, diffuse=True,
                              shadow=tissue.shadow_budget(local_mean, taps, scale_sq),
                              split=tissue.split_cells(field) if split else None)
    return weights, scale_sq


def neighbour_light_check(field: np.ndarray, levels: np.ndarray, ratios: list[float], its: dict | None) -> None:
    """Item 7 of the module docstring."""
    weights, scale_sq = decode_weights(field, split=False)
    runs = [("the pairs' decode, each line's own light at the bottom (0.8.6)", None, False),
            ("least-squares gain", None, True)]
    runs += [(f"neighbours' light, ratios {f'within ×{r:g}' if r else 'unclipped'}", r, False) for r in ratios]
    for name, ratio, gain in runs:
        print(light_line(name, *neighbour_rows(weights, scale_sq, ratio, gain), levels, its), flush=True)


def bottom_light_check(field: np.ndarray, levels: np.ndarray, its: dict | None) -> None:
    """Item 8 of the module docstring."""
    for split in (False, True):
        weights, scale_sq = decode_weights(field, split)
        offsets = tissue.TISSUE_ROW_OFFSETS if split else tissue.TISSUE_OFFSETS
        for common in (False, True):
            name = (f"{'bright cells split' if split else 'pairs alone'}, "
                    f"{'one light' if common else 'each line its own light'} at the bottom")
            print(light_line(name, *neighbour_rows(weights, scale_sq, None, False, offsets, common), levels, its),
                  flush=True)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--skin", type=int, default=5, help="skin phantom seed (default 5)")
    parser.add_argument("--target", type=Path, help="with --quantiles: a real(-like) target instead of a skin "
                                                    "phantom (figures without a truth)")
    parser.add_argument("--rows", nargs="+", type=int, default=[50, 80, 110, 150, 200])
    parser.add_argument("--scales", nargs="+", type=float, default=[0.0001, 0.1, 0.3, 1.0])
    parser.add_argument("--column-solve", action="store_true", help="item 3 of the description, instead of 1–2")
    parser.add_argument("--regularisation", nargs="+", type=float, default=[1e-3, 1e-5])
    parser.add_argument("--coupled-sweep", nargs="*", type=float, metavar="FACTOR",
                        help="item 4 of the description, instead of 1–2, at each FACTOR times the median of the "
                             "lines' own c² (default 1)")
    parser.add_argument("--quantiles", nargs="+", type=float, help="item 5 of the description, instead of 1–2")
    parser.add_argument("--stripes", action="store_true", help="item 6 of the description, instead of 1–2")
    parser.add_argument("--bottom-light", action="store_true", help="item 8 of the description, instead of 1–2")
    parser.add_argument("--neighbour-light", nargs="+", type=float, metavar="RATIO",
                        help="item 7 of the description, instead of 1–2 (0: unclipped)")
    parser.add_argument("--refine", type=float, metavar="SECONDS", help="with --quantiles: stage 3 from each decode")
    parser.add_argument("--stage1-field", action="store_true",
                        help="items 1, 2 and 5 decode stage 1's own field, not its least-norm twin (the tissue "
                             "regime's)")
    args = parser.parse_args(argv)
    if args.target and not (args.quantiles or args.bottom_light):
        parser.error("--target goes with --quantiles or --bottom-light (items 1–4 are the skin phantoms')")
    truth = None if args.target else Phantom.skin(args.skin)
    levels = target_levels(read_target(args.target), DEFAULT_CONFIG) if args.target else render(truth).levels
    name = args.target.name if args.target else f"skin {args.skin}"
    exact = ExactScore(levels)
    field = linear_start(levels, lambda image: exact(image)["mean"], aim=aimed_levels(levels)).field
    twin = least_norm_field(field, levels)
    decoded_field = field if args.stage1_field else twin
    spread = np.quantile(line_energies(decoded_field) / np.median(line_energies(decoded_field)), [0.05, 0.95])
    print(f"{name}: decoding {'stage 1' if args.stage1_field else 'the least-norm twin of stage 1'}'s "
          f"field, its lines' Σ|F|² {spread[0]:.2f}–{spread[1]:.2f} times the median line's (5–95 %)", flush=True)
    truth_figures = None if truth is None else tissue_figures(truth, levels)
    if args.quantiles:
        quantile_choice(decoded_field, truth_figures, levels, args.quantiles, args.refine)
        return
    if args.stripes:
        stripes(decoded_field, levels)
        return
    if args.neighbour_light:
        neighbour_light_check(decoded_field, levels, args.neighbour_light, truth_figures)
        return
    if args.bottom_light:
        bottom_light_check(decoded_field, levels, truth_figures)
        return
    if args.coupled_sweep is not None:
        for factor in args.coupled_sweep or [1.0]:
            print(f"c² × {factor:g}")
            coupled_sweep(twin, truth_figures, levels, factor)
        return
    if args.column_solve:
        lines = np.arange(DEFAULT_CONFIG.a_scans)
        noise = np.random.default_rng(0).standard_normal(lines.size)
        for name, profile in (("one value", np.full(lines.size, 0.5)), ("smooth", 0.5 + 0.3 * np.sin(lines / 40)),
                              ("noisy per line", 0.5 * (1 + 0.1 * noise))):
            for regularisation in args.regularisation:
                residuals = column_solve(twin, np.broadcast_to(profile, field.shape), regularisation)
                print(f"lights {name}, λ {regularisation:g}: residual per iteration "
                      + " ".join(f"{value:.1e}" for value in residuals))
        return
    decoded = tissue.decode_tissue(decoded_field, DEFAULT_CONFIG)
    print(f"skin {args.skin}: decode c² {decoded.scale**2:.4g}, lines short of light {decoded.short_lines}, pixels at "
          f"their level {np.mean(render(decoded.phantom).levels == levels):.3f}")
    light_mismatch_db(decoded, args.rows)
    shadow = tissue.shadow_budget(tissue.local_mean_energy(decoded_field), ref.shadow_taps(DEFAULT_CONFIG),
                                  decoded.scale**2)  # the decode's own pairs
    weights = decoded_weights(decoded_field, DEFAULT_CONFIG, offsets=tissue.TISSUE_OFFSETS, shadow=shadow,
                              diffuse=True)
    for factor in args.scales:
        phantom = phantom_of_rows(top_down_rows(weights, factor * decoded.scale**2), DEFAULT_CONFIG,
                                  tissue.TISSUE_OFFSETS)
        rendered = render(phantom).levels
        print(f"from the top, c² × {factor:g}: pixels at their level {np.mean(rendered == levels):.3f}, shadow "
              f"{shadow_db(transmission_map(phantom, DEFAULT_CONFIG), levels):.1f} dB")


if __name__ == "__main__":
    main()
