"""Stage 2 at tissue scale: the exact decode's rows, each amplitude divided by the light the rows above leave it.

The exact decode (:mod:`octcl.host.stage2.exact`) gives rows of amplitude w
(two per cell, on the A-scan lines, y = 0) that render the field without
shadowing, at any overall scale c. With shadowing (``shared/physics.md`` §2
step 4) a row of amplitude a under transmission T shows T·a and leaves
T·(1 − a²) below it; with the beam's lateral weights, the transmission of
A-scan i after a layer ℓ of rows (amplitudes a_ℓ on the lines i') is

    T_i ← T_i·Π_{i'} (1 − G_{i−i'}·a²_{ℓ,i'}),   G_d = e^{−2(d·Δx)²/w0²},

and the phantom renders as the field does where every row shows c·w:
a = c·w/T, T the transmission of the row's own line when the light reaches
its layer (the layers, in depth order, are the cell rows' sixteen depth
offsets, :data:`TISSUE_ROW_OFFSETS`: 4096 of them).

Integrating T from the top, T ← T·(1 − c²w²/T²), is unstable: an error in T
grows like e^{2μz} through a homogeneous layer. From the bottom it shrinks.
The beam is wider than the line spacing (G_1 = 0.49), so T varies slowly
across lines, and each line's loss at a layer is taken as S/T², S the
layer's shown intensities I = c²w² weighted by G across the lines (as if T
were the same on the lines the beam reaches: solving with each line's own T
instead fed back, a dim line's bright rows shadowing their neighbours ever
more, and diverged on a skin phantom). Given the light T_b below a layer,
the light above it solves T_b = T_a·(1 − S/T_a²), whose root
T_a = (T_b + sqrt(T_b² + 4S))/2 is ≥ sqrt(S), so a² = I/T_a² ≤ I/S ≤ 1
(E ≤ 100 %). To first order T² drops by 2·S at each layer, so
T²(z) = T²(bottom) + 2·Σ_{z' ≥ z} S: with no light left at the bottom,
a² = I/(2·Σ_{z'≥z} S), the depth-resolved attenuation estimator (Vermeer et
al., Biomed. Opt. Express 5, 322, 2014), whose energies blow up at the
bottom of the data. The light left at the bottom is the one free
parameter, and T(top) = 1 then fixes the scale c.

The light below the data. Beyond the deepest rows with signal the light
goes on decaying: the tail of Σ I is estimated per line from the decay of
the deepest rows with signal, R(n)·r/(1 − r), r the fitted per-row ratio
(the correction of Liu et al., "Optimized depth-resolved estimation to
measure optical attenuation coefficients from optical coherence tomography
and its application in cancer detection", Biomed. Opt. Express 10, 2019).

The scale and each line's budget. Each line asks for its own scale
c_i² = 1/(2·(ΣI_i + tail_i)), ΣI_i read from the local mean of |F|² (σ
:data:`SHADOW_SMOOTHING`, the speckle-free intensity a cell's pair aims its
shadow at); the phantom has one, a high quantile of the lines' own
(:data:`SCALE_QUANTILE`). Measured on skin phantoms, the scale that gives the
truth's shadow and band densities is near the largest of them, not the
median. The lines' c_i² are not one value, as the truth's would be: the
field's energy per line follows its speckle and the detail its rendering
does not show, not the tissue's n·E (the tissue regime decodes the field of
least norm with the same rendering,
:func:`octcl.host.stage1.start.least_norm_twin`, whose lines' Σ|F|² spread
0.63–1.52 times the median line's on skin 5 where stage 1's field's spread
0.57–1.98, 5–95 %). So what a line shadows is not what its field shows:
each line's cells aim at the local mean scaled to the line's budget, the
light the scale leaves it, 1/(2c²) − tail (:func:`shadow_budget`), and the
pairs are chosen down each line with the shadow missed carried on
(:func:`octcl.host.stage2.exact.diffused_shadow_pairs`: a cell's pair
shadows 0.59–3.4 times what it shows; on the random field of
``tests/stage2/test_tissue_decode.py`` the median line's sum misses the
local mean's by 3.5 %, by 12 % with each cell's nearest pair).
What a line's rows show is still c·w/T. Against shadows that followed each
line's own field (each cell's pair nearest the local mean unscaled, octcl
0.8.3), whole ``--regime tissue --time-budget 30`` runs on two slow cores
went from 0.99526–0.99833 to 0.99921–0.99960 on skins 6–10 (seeds not used
to build it), and from 0.99266–0.99881 to 0.99919–0.99946 on four
real-like scans (docs/benchmarks.md, "Each line's shadow on its budget").

Bright cells split. A pair of rows shows at most 1/0.59 of what it shadows
(its two carriers 45° apart, p = q), while tissue shows a bright speckle
with many scatterers of one mean energy: a line whose brightest cells alone
shadow more than its budget runs out of light (on skin 6, 504 lines of 512
at octcl 0.8.6). The rows the contract leaves beyond two a cell (295,000
against 262,144) split the brightest cells (:func:`split_cells`): half of
each of the pair's weights stays, half goes to a replica half a wavelength
nearer the cell's depth (the same carrier phase, 2·k0·λ/2 = 2π; the exact
decode's corrections take up the depth kernel's shift), so the four rows
show as the pair did and shadow half as much.

The light at the bottom: one value for every line. With each line's own
(corrected until its T(top) is 1), the lines whose split brought them onto
their budget left light below the data and their neighbours none: T at
depth then differed between neighbouring lines by several dB, where each
row's own-line compensation errs most (the light the phantom makes against
the light the decode assumed, row 120 of skin 6: −3.6 to +4.0 dB, 5–95 %).
The light below the tissue is laterally smooth in tissue (the beam shadows
its neighbours, G): one value, corrected until the median line's T(top) is
1, gave −1.0 to +1.1 dB there, 59 % of pixels at their level against 46 %
(and 49 % for the pairs alone), and the truth's shadow (28.2 dB, truth 28.4)
(docs/benchmarks.md, "Bright cells split, one light at the bottom").
The lines' T(top) then scatter about 1 (0.97–1.05 on skin 6): a line above
1 renders dimmer than the field asks, one below brighter, by its T(top);
those above are counted (:attr:`TissueDecode.short_lines`), and stage 3
takes them back. On orange.png (0.94–1.07) the brightest pixel's line
renders brighter, which shifts the whole display: the decode puts 3 % of
pixels at their level against 37 % with each line's own light, and stage 3
takes that back too (whole ``--regime tissue --time-budget 30`` runs on
twelve targets, orange.png's family among them: global 0.99967 → 0.99976,
higher on ten, lower on orange.png through a gamma by 1.2e−4).

Lateral variation of T between neighbouring lines is not compensated (each
row takes its own line's T; the neighbouring A-scans it reaches see theirs),
nor are rows that share a depth across lines (the scanner's tie order
decides which of them shadows which): stage 3 refines what is left.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import convolve1d, gaussian_filter

from ... import _reference as ref
from ...config import DEFAULT_CONFIG, ScannerConfig
from ...phantom import TARGET_ROWS, Phantom
from .exact import (DECODE_CORRECTIONS, DECODE_TOLERANCE, decoded_weights, phantom_of_rows, replicated_offsets,
                    row_depths_um)

#: Carrier offsets of the rows of a cell, in units of λ: eight, 45° apart in carrier phase, so that a cell's
#: pair can shadow from 0.59 to 3.4 times what it shows (:func:`octcl.host.stage2.exact.shadow_pairs`).
TISSUE_OFFSETS = np.arange(-7, 8, 2) / 32.0
#: The rows' offsets: TISSUE_OFFSETS and their replicas half a wavelength nearer 0 (split cells, :func:`split_cells`).
TISSUE_ROW_OFFSETS = replicated_offsets(TISSUE_OFFSETS)
#: σ in rows and lines of the local mean of |F|² that each cell's pair aims its shadow at (a speckle-free n·E).
#: Wider (4 × 48) changed a skin phantom's decode by little: stripes across lines of 12–14 dB either way
#: (docs/benchmarks.md, "Phantoms as tissue").
SHADOW_SMOOTHING = (2.0, 4.0)
#: Largest a² a row may take (E = 100·a² %): the rules' E ≤ 100 %.
MAX_AMPLITUDE_SQ = 1.0
#: The phantom's c² is this quantile of the lines' own (module docstring). Decoded from stage 1's field of skin 5
#: (the seed the choice was made on), the quantiles 0.5, 0.75, 0.9, 0.95 and 1 gave shadows of 18.2, 29.2, 30.2,
#: 30.5 and 30.6 dB at the bottom of the visible tissue (the truth's 29.8), the deepest band's n·E 0.45, 0.74,
#: 0.89, 0.95 and 1.0 of the truth's, and 43–50 % of pixels at their level; 45 s of stage 3 (the tissue
#: schedule) took them to 0.99911, 0.99931, 0.99944, 0.99956 and 0.99966, 79–89 % of pixels at their level:
#: more shadow, closer bands and a better score up to the largest line's own c². That one is a single line's
#: (the dimmest with signal), so the choice is a quantile that a few lines cannot move, 0.95
#: (``scripts/check_tissue_decode.py --skin 5 --quantiles 0.5 0.75 0.9 0.95 1 --refine 45 --stage1-field``,
#: docs/benchmarks.md: stage 1's own field, decoded before the tissue regime took its least-norm twin).
#: Rechecked on the twin: the largest line's own scored higher on skins 5–7 and plain_skin_0 (by up to 1.6e−4
#: after 45 s) and lower on orange.png; a line dim from top to bottom would set it for all, so 0.95 stays
#: (``scripts/check_tissue_decode.py --skin 6 --quantiles 0.95 0.99 1 --refine 45``, ``--target PNG``).
#: Those lines' own c² were read from the pairs' energies; since each line's shadow follows its budget
#: (:func:`shadow_budget`) they are read from the local mean of |F|², and 0.95 was not chosen again.
SCALE_QUANTILE = 0.95
#: Passes correcting the light at the bottom (one value for every line) until the median line's light at the top is 1.
BOTTOM_PASSES = 8
#: Rows with signal: the shadow-weighted row intensity above this share of the brightest row's (the display's
#: floor is 51 dB below its maximum pixel: 10^−5.1 in intensity).
SIGNAL_SHARE = 10 ** (-51 / 10)
#: Deepest rows with signal whose decay gives a line's tail (:func:`tail_sums`).
TAIL_ROWS = 24
#: Largest per-row decay ratio of a tail: a line that does not decay still has a finite tail (≤ 99 rows' worth).
MAX_TAIL_RATIO = 0.99


@dataclass
class TissueDecode:
    """What :func:`decode_tissue` made, and what it chose.

    Attributes
    ----------
    phantom : Phantom
        The rows at tissue scale.
    scale : float
        c: every row shows c·w (w the exact decode's amplitude at the field's scale).
    transmission : ndarray, (L, Nx)
        T of each line when the light reaches each layer, layers in depth order (L = 16·Nz: the rows of
        :data:`TISSUE_ROW_OFFSETS`).
    bottom_light : ndarray, (Nx,)
        T² below the last layer, per line (one value for every line, module docstring).
    short_lines : int
        Lines whose light at the top stayed above 1: their rows render dimmer than the field asks, by their
        T(top) (more signal than the light left them can make at this scale).
    capped_rows : int
        Rows whose a² reached :data:`MAX_AMPLITUDE_SQ`.
    """

    phantom: Phantom
    scale: float
    transmission: np.ndarray
    bottom_light: np.ndarray
    short_lines: int
    capped_rows: int

    def summary(self) -> dict:
        """The choices as plain numbers (an inversion's report): the scale, the lines short of light, the rows
        at E = 100 %, the light left at the bottom (median T², and in dB)."""
        bottom = float(np.median(self.bottom_light))
        return {"scale": self.scale, "short_lines": self.short_lines, "capped_rows": self.capped_rows,
                "bottom_light_median": bottom,
                "bottom_light_db": None if bottom <= 0 else float(-10 * np.log10(bottom))}


def layer_order(config: ScannerConfig = DEFAULT_CONFIG, offsets: np.ndarray = TISSUE_ROW_OFFSETS) -> np.ndarray:
    """The (offset, row) pairs of :func:`row_depths_um` in depth order, as flat indices into its (D, Nz)."""
    return np.argsort(row_depths_um(config, offsets).ravel(), kind="stable")


def light_above(below: np.ndarray, shadow_sq: np.ndarray) -> np.ndarray:
    """T above a layer from T below it, per line: the root of T_b = T_a·(1 − S/T_a²), S the layer's
    shadow-weighted shown intensity on the line (module docstring); T_a ≥ sqrt(S)."""
    return (below + np.sqrt(below**2 + 4 * shadow_sq)) / 2


def transmission_from_bottom(shadow_sq: np.ndarray, bottom_light: np.ndarray) -> np.ndarray:
    """T of each line at each layer, (L, Nx), integrated from the bottom: ``shadow_sq`` (L, Nx) each layer's
    shadow-weighted shown intensity per line (depth order), ``bottom_light`` T² below the last."""
    transmission = np.empty_like(shadow_sq)
    below = np.sqrt(bottom_light)
    for layer in range(shadow_sq.shape[0] - 1, -1, -1):
        below = transmission[layer] = light_above(below, shadow_sq[layer])
    return transmission


def tail_sums(rows_sq: np.ndarray) -> np.ndarray:
    """Per line, Σ I beyond the data: R(n_last)·r/(1 − r) from the decay of its deepest :data:`TAIL_ROWS` rows with
    signal (module docstring); ``rows_sq`` (Nz, Nx) is each cell row's shadow-weighted Σ w². 0 without signal.

    The decay is the least-squares line log R ≈ s·n + b through those rows, all lines at once from its sums
    (s = (m·Σny − Σn·Σy)/(m·Σn² − (Σn)²), b = (Σy − s·Σn)/m over the m rows, y = log R): a loop of
    ``np.polyfit`` over 512 lines took 0.09 s, twice a tissue decode.
    """
    signal = rows_sq > SIGNAL_SHARE * rows_sq.max()
    # The deepest TAIL_ROWS rows with signal of each line: those with at most that many signal rows from them down.
    from_bottom = np.cumsum(signal[::-1], axis=0)[::-1]
    fitted = signal & (from_bottom <= TAIL_ROWS)
    count = fitted.sum(axis=0)
    lines = count >= 2
    rows = np.arange(rows_sq.shape[0], dtype=float)[:, None]
    log_rows = np.log(np.where(fitted, rows_sq, 1.0))  # 0 off the fitted rows
    sum_n, sum_nn = (fitted * rows).sum(axis=0), (fitted * rows**2).sum(axis=0)
    sum_y, sum_ny = log_rows.sum(axis=0), (log_rows * rows).sum(axis=0)
    m = np.maximum(count, 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        slope = np.where(lines, (m * sum_ny - sum_n * sum_y) / (m * sum_nn - sum_n**2), 0.0)
    intercept = (sum_y - slope * sum_n) / m
    last = np.where(lines, rows_sq.shape[0] - 1 - np.argmax(signal[::-1], axis=0), 0)
    ratio = np.minimum(np.exp(slope), MAX_TAIL_RATIO)
    return np.where(lines, np.exp(slope * last + intercept) * ratio / (1 - ratio), 0.0)


def tissue_scale(intensity: np.ndarray, taps: np.ndarray, quantile: float = SCALE_QUANTILE) -> float:
    """c²: the ``quantile`` of the lines' own 1/(2·(ΣI + tail)) over the lines with signal, ΣI each line's
    shadow-weighted Σ of ``intensity`` (Nz, Nx: what the cells shadow at the field's scale), ``taps`` the shadow's
    lateral weights G."""
    if not 0 <= quantile <= 1:
        raise ValueError(f"the scale's quantile must be in [0, 1], got {quantile!r}")
    rows_sq = convolve1d(intensity, taps, axis=1, mode="constant")
    per_line = rows_sq.sum(axis=0) + tail_sums(rows_sq)
    lit = per_line > 0
    return float(np.quantile(1.0 / (2.0 * per_line[lit]), quantile))


def shadow_budget(local_mean: np.ndarray, taps: np.ndarray, scale_sq: float) -> np.ndarray:
    """What each cell is to shadow at the field's scale (Nz, Nx): ``local_mean`` (:func:`local_mean_energy`) on each
    line scaled so that the line spends the light the scale c² gives it, its shadow-weighted sum
    1/(2c²) − tail (module docstring: T(top) = 1 with the tail's light left at the bottom)."""
    rows_sq = convolve1d(local_mean, taps, axis=1, mode="constant")
    per_line = rows_sq.sum(axis=0)
    budget = np.maximum(1.0 / (2.0 * scale_sq) - tail_sums(rows_sq), 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        factor = np.where(per_line > 0, budget / per_line, 0.0)
    # A line whose tail takes all its light still shows its rows: they aim at the least shadow their pairs carry.
    return np.maximum(local_mean * factor, np.finfo(float).tiny)


def split_cells(field: np.ndarray, max_rows: int = TARGET_ROWS) -> np.ndarray:
    """The cells whose rows are split onto replicas (Nz, Nx, bool; module docstring): the brightest |F|², as many as
    the rows beyond two per non-zero cell leave under ``max_rows`` (two more rows a split cell)."""
    energy = np.abs(field) ** 2
    cells = int(np.count_nonzero(energy))
    split = np.zeros(field.shape, dtype=bool)
    spare = min(max(0, (max_rows - 2 * cells) // 2), cells)
    if spare:
        split.flat[np.argsort(energy, axis=None, kind="stable")[-spare:]] = True
    return split


def local_mean_energy(field: np.ndarray) -> np.ndarray:
    """The local mean of |F|² (σ :data:`SHADOW_SMOOTHING` rows × lines) that each cell's pair aims its shadow at."""
    return gaussian_filter(np.abs(field) ** 2, SHADOW_SMOOTHING, mode="nearest")


def decode_tissue(field: np.ndarray, config: ScannerConfig = DEFAULT_CONFIG, scale_sq: float | None = None,
                  corrections: int = DECODE_CORRECTIONS, scale_quantile: float = SCALE_QUANTILE,
                  workers: int = 1, tolerance: float = DECODE_TOLERANCE) -> TissueDecode:
    """The exact decode's rows at tissue scale (module docstring).

    Parameters
    ----------
    field : ndarray of complex, (Nz, Nx)
        F on the cell grid; any overall scale.
    config : ScannerConfig
    scale_sq : float, optional
        c², the light the rows show relative to the field's scale (default: from the data, :func:`tissue_scale`).
    corrections : int
        The exact decode's corrections, at most.
    scale_quantile : float
        The quantile of the lines' own c² that :func:`tissue_scale` takes, where ``scale_sq`` is not given.
    workers : int
        Threads of the exact decode's depth DFTs; the result is the same at any count.
    tolerance : float
        The exact decode's residual at which its corrections stop (:func:`~octcl.host.stage2.exact.decoded_weights`;
        0: all of them).
    """
    taps, local_mean = ref.shadow_taps(config), local_mean_energy(field)
    scale_sq = tissue_scale(local_mean, taps, scale_quantile) if scale_sq is None else float(scale_sq)
    if not scale_sq > 0:
        raise ValueError(f"the scale c² must be positive, got {scale_sq!r}")
    weights = decoded_weights(field, config, corrections, TISSUE_OFFSETS, diffuse=True, workers=workers,
                              shadow=shadow_budget(local_mean, taps, scale_sq), tolerance=tolerance,
                              split=split_cells(field))
    return rows_at_tissue_scale(weights, scale_sq, config)


def rows_at_tissue_scale(weights: np.ndarray, scale_sq: float, config: ScannerConfig = DEFAULT_CONFIG,
                         offsets: np.ndarray = TISSUE_ROW_OFFSETS) -> TissueDecode:
    """The exact decode's rows ``weights`` (D, Nz, Nx, at the field's scale, at ``offsets``) shown at the scale
    c² = ``scale_sq``, each divided by the light its line has left at its layer, integrated from the bottom from
    one light for every line, corrected until the light at the top of the median line with rows is 1 (module
    docstring)."""
    taps = ref.shadow_taps(config)
    order = layer_order(config, offsets)
    layers = weights.reshape(-1, config.a_scans)[order]  # (L, Nx), depth order
    shown_sq = scale_sq * layers**2
    shadow_sq = convolve1d(shown_sq, taps, axis=1, mode="constant")
    # The light at the bottom, one value: first order 1 − 2c²ΣI of the median line with rows, then corrected until
    # that line's light at the top is 1 (T² at the top moves about one for one with T² at the bottom). A line
    # without rows has the light at the bottom at its top: it does not vote.
    lit = shown_sq.any(axis=0)
    if not lit.any():
        lit = np.ones_like(lit)

    def one_light(per_line: np.ndarray) -> np.ndarray:
        return np.full(config.a_scans, max(float(np.median(per_line[lit])), 0.0))

    bottom = one_light(1.0 - 2.0 * shadow_sq.sum(axis=0))
    for _ in range(BOTTOM_PASSES):
        transmission = transmission_from_bottom(shadow_sq, bottom)
        bottom = one_light(bottom + (1.0 - transmission[0] ** 2))
    transmission = transmission_from_bottom(shadow_sq, bottom)
    with np.errstate(divide="ignore", invalid="ignore"):
        amplitude_sq = np.where(transmission > 0, np.minimum(shown_sq / transmission**2, MAX_AMPLITUDE_SQ), 0.0)
    capped = int(np.count_nonzero((amplitude_sq >= MAX_AMPLITUDE_SQ) & (layers > 0)))
    rows = np.empty_like(layers)
    rows[order] = np.sqrt(amplitude_sq)
    phantom = phantom_of_rows(rows.reshape(weights.shape) * (weights > 0), config, offsets)
    return TissueDecode(phantom, float(np.sqrt(scale_sq)), transmission, bottom,
                        int(np.count_nonzero(transmission[0] > 1.0 + 1e-6)), capped)


__all__ = ["MAX_AMPLITUDE_SQ", "SCALE_QUANTILE", "TISSUE_OFFSETS", "TISSUE_ROW_OFFSETS", "TissueDecode",
           "decode_tissue", "layer_order", "light_above", "local_mean_energy", "rows_at_tissue_scale", "shadow_budget",
           "split_cells", "tail_sums", "tissue_scale", "transmission_from_bottom"]
