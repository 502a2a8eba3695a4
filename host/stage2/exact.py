"""Stage 2 of the linear regime: the exact decode, a phantom that renders as its field does, cell for cell.

A scatterer at depth z = z_n + o (z_n the
cell depth of :func:`octcl.host.stage1.operator.cell_depths_um`) adds
a·e^{−2i·k_q·z} to the spectrum: on the grid that is the cell value
a·e^{−2i·k0·z} times the depth-kernel shift e^{−2i·(k_q − k0)·o}, a factor
per wavenumber. With a fixed set of offsets o_d the rendering of the
phantom is therefore exactly linear in the rows' amplitudes and diagonal
in the depth DFT per offset:

    Â[q, ·] = w_q·Σ_d e^{−2i(k_q − k0)·o_d}·DFT_n(M_d)[q, ·],

M_d[n, i] the cell values of the rows at offset o_d. The four offsets
o_d = (−3, −1, 1, 3)·λ/16 give carrier phases 3π/4, π/4, −π/4, −3π/4:
any complex value is a non-negative combination of two neighbouring ones,
so each cell becomes two rows, not four. Their
depth-kernel shifts are at most 2δk·3λ/16 of a DFT bin's phase per bin,
which :func:`decode_exact` undoes by iterating F' ← F' + (F − F_eff(F'))
(each step shrinks the error by the largest |2(k_q − k0)·o_d| ≈ 0.13; 12
steps take it below float64 rounding). The iteration stops once
max|F − F_eff| ≤ :data:`DECODE_TOLERANCE`·max|F|: at a pixel at the
display's floor (51 dB below the brightest) that residual moves the
display by 2e−3 dB, a tenth of the margin the field's fit keeps inside each
level's interval (:data:`octcl.host.stage1.levels.INTERVAL_MARGIN`), and
on orange.png, two plainly quantised skin renderings and a skin phantom's
scan each update shrank the residual 15–22 times, and the updates stop
after 4, not 12 (the decode 0.38–0.46 s against 0.95–1.03 s on two cores),
with every pixel rendered at the level 12 give (``scripts/bench_decode.py``). In the first row z_0 = 0, so the
negative offsets there move by λ/2 (same phase, another shift: the
formula holds with per-row offsets). The result is 2 rows per non-zero
cell, 262,144 for a full 256×512 grid, at elevation y = 0 and on the
A-scan lines x_i, below the contract's 295,000 rows.

Scale and shadowing. The display divides by the B-scan's own maximum
(``shared/physics.md`` §2 step 10), so multiplying every amplitude a_j by one
factor c changes a rendering only through shadowing, whose terms (B_ij·a_j)²
scale with c². In A-scan i a scatterer is dimmed by its transmission
T_ij = Π_m (1 − (B_im·a_m)²) ≥ 1 − s_i, s_i = Σ_m (B_im·a_m)², so the
shadowing changes A[n, i] by at most s_i·Σ_j |c_ij|, the sum of the
magnitudes of the contributions to that pixel. :func:`decode_exact` scales
the phantom so that max_i s_i = :data:`SHADOW_BOUND` = 1e−12: even where the
contributions cancel a thousandfold (Σ|c| = 10³·|A|), a pixel's magnitude
moves by 1e−9 of itself, 4e−8 dB, about 1e−7 of a display level; float64
rounding in the scanner's own sums is of the same order. The energies are
then about 1e−11 % for the brightest rows (measured on the development set), within the task's 0 ≤ E ≤ 100, and
the phantom file's 8 significant digits keep their relative precision at any
scale. ``tests/stage2/test_exact.py`` renders decoded phantoms with the float64
reference scanner, shadowing included, and compares the levels with those
of the field.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import scipy.fft

from ... import _reference as ref
from ...config import DEFAULT_CONFIG, ScannerConfig
from ...phantom import SIGNIFICANT_DIGITS, Phantom, round_significant
from ..stage1.operator import cell_depths_um

#: Largest Σ_j (B_ij·a_j)² of any A-scan in a decoded phantom (module docstring).
SHADOW_BOUND = 1e-12
#: Updates of the placed field in :func:`decode_exact`, at most.
DECODE_CORRECTIONS = 12
#: Residual max|F − F_eff| of the rows' rendering, relative to max|F|, at which the updates stop (module
#: docstring): 20·log10(1 + 6.5e−7/10^(−51/20)) = 2e−3 dB at the display's floor.
DECODE_TOLERANCE = 6.5e-7
#: Stage 3's floor of E (%) for a decoded phantom (the physical regime's is 1e−20 %):
#: at :data:`SHADOW_BOUND` the brightest rows are near 1e−11 % and the
#: faintest 1e−26 %, 150 dB below. 1e−36 % is an amplitude of 1e−19,
#: a normal float32 number, and 80 dB below the faintest decoded row.
ENERGY_FLOOR_PCT = 1e-36
#: Least angle between a value and either carrier of the pair :func:`shadow_pairs` gives it: the corrections of
#: :func:`decoded_weights` then move it within its pair (a pair 90° wide centred on it always has 45°).
PAIR_MARGIN_RAD = 0.2
#: Bound of the shadow a line's cells carry on to the next row in :func:`diffused_shadow_pairs`, in units of the
#: next row's own target: a line past a bright stretch does not go dark to pay it back at once.
SHADOW_CARRY_LIMIT = 3.0
#: Carrier offsets of the rows of a cell, in units of λ (module docstring).
OFFSETS_IN_WAVELENGTHS = np.array([-3.0, -1.0, 1.0, 3.0]) / 16.0


def row_depths_um(config: ScannerConfig = DEFAULT_CONFIG, offsets: np.ndarray = OFFSETS_IN_WAVELENGTHS) -> np.ndarray:
    """Depths (µm) of the four rows of each cell row n, as the phantom file holds them: (4, Nz).

    z_n + (−3, −1, 1, 3)·λ/16, z_n the cell depth; in row 0 (z_0 = 0) the
    negative offsets move by λ/2, keeping their carrier phase, so that
    z ≥ 0. Each depth is rounded to :data:`octcl.phantom.SIGNIFICANT_DIGITS`
    as the file writes it, and the decode is exact for these depths: an
    unrounded depth moves by up to 5e−5 µm in the file (z ≥ 1000 µm), a
    carrier phase of 4.8e−4 rad, enough to move a dark pixel whose
    contributions cancel a thousandfold by a level (0.03 % of Uniform A's
    pixels were).
    """
    shifts = np.repeat((np.asarray(offsets) * config.wavelength_um)[:, None], config.depth_pixels, axis=1)
    shifts[:, 0] = np.where(shifts[:, 0] < 0, shifts[:, 0] + config.wavelength_um / 2, shifts[:, 0])
    return round_significant(cell_depths_um(config)[None, :] + shifts, SIGNIFICANT_DIGITS)


def row_offsets_um(config: ScannerConfig = DEFAULT_CONFIG, offsets: np.ndarray = OFFSETS_IN_WAVELENGTHS) -> np.ndarray:
    """Depth offsets o_{d,n} (µm) of the rows of a cell in row n from its cell depth: (D, Nz)
    (:func:`row_depths_um` less z_n)."""
    return row_depths_um(config, offsets) - cell_depths_um(config)[None, :]


def row_carriers(config: ScannerConfig, offsets: np.ndarray = OFFSETS_IN_WAVELENGTHS) -> np.ndarray:
    """e^{−2i·k0·o_{d,n}}, the carrier phase of each row's offset: (4, Nz, 1), broadcasting over columns.

    Near (3π/4, π/4, −π/4, −3π/4) for the offsets (−3, −1, 1, 3)·λ/16; the
    file's rounding of the depths moves them by up to 5e−4 rad.
    """
    return np.exp(-2j * config.k0_rad_per_um * row_offsets_um(config, offsets))[:, :, None]


def split_on_carriers(values: np.ndarray, carriers: np.ndarray) -> np.ndarray:
    """Non-negative weights p_d, two per value, with Σ_d p_d·carriers[d] = value.

    ``carriers`` are unit phasors about 90° apart: (D,), the same for every
    value, or (D, ...) broadcasting against ``values`` (:func:`row_carriers`:
    per row), in the same order around the circle for every value. A value
    goes to the two whose angles enclose it. Returns (D,) + values.shape.
    """
    carriers = np.asarray(carriers)
    if carriers.ndim == 1:
        carriers = carriers.reshape(carriers.shape + (1,) * np.ndim(values))
    angles = np.angle(carriers)  # (D, ...) broadcasting against values, never expanded to their size
    order = np.argsort(angles.reshape(carriers.shape[0], -1)[:, 0])
    value_angles = np.angle(values)
    weights = np.zeros((carriers.shape[0],) + np.shape(values))
    turn = 2 * np.pi
    claimed = np.zeros(np.shape(values), bool)
    for position, first in enumerate(order):
        second = order[(position + 1) % order.size]
        sector = (angles[second] - angles[first]) % turn
        within = (value_angles - angles[first]) % turn
        # A value on a carrier's angle can round to just outside both sectors beside it (−1 − 1j against a
        # carrier at −3π/4 + 4e−16: 2π below one, the whole sector above the other): each sector takes what
        # lies within SECTOR_EDGE_RAD of its edges, the first to take a value keeps it, and the weight on
        # the far side, −1e−14 of the value at most, is clipped to 0 below.
        inside = ~claimed & ((within < sector + SECTOR_EDGE_RAD) | (within > turn - SECTOR_EDGE_RAD))
        claimed |= inside
        c1, c2 = carriers[first], carriers[second]
        # value = p·c1 + q·c2 with real p, q: Im(conj(c1)·c2) is the determinant. Computed for every value
        # and kept where it lies in this sector: cheaper than gathering the sector's values.
        determinant = (np.conj(c1) * c2).imag
        weights[first] = np.where(inside, (np.conj(values) * c2).imag / determinant, weights[first])
        weights[second] = np.where(inside, (np.conj(c1) * values).imag / determinant, weights[second])
    return np.maximum(weights, 0.0)  # rounding can leave −1e−17 on a sector's edge


#: Angle (rad) within which a value on the edge of :func:`split_on_carriers`' sectors is taken by either.
SECTOR_EDGE_RAD = 1e-14
#: Terms of the series in :func:`rendered_cells` for the rounded offsets' depth-kernel shifts.
_SHIFT_TERMS = 3


def rendered_cells(weights: np.ndarray, config: ScannerConfig = DEFAULT_CONFIG,
                   offsets: np.ndarray = OFFSETS_IN_WAVELENGTHS, workers: int = 1) -> np.ndarray:
    """The grid field that renders like rows of amplitude ``weights`` at :func:`row_depths_um`.

    F_eff = IDFT_q(Σ_d Σ_n e^{−2i(k_q − k0)·o_{d,n}}·M_d[n]·e^{−2πiqn/Nz}),
    M_d[n, ·] = weights_d·e^{−2i·k0·(z_n + o_{d,n})} (module docstring). The
    offsets of rows n ≥ 1 are ō_d + δ_{d,n}, ō_d the unrounded offset and
    |δ| ≤ 5e−5 µm the file's rounding: e^{−2i(k_q − k0)·δ} is its series,
    Σ_m (−2i(k_q − k0)·δ)^m/m!, whose terms after the third are below 1e−14
    (|2(k_q − k0)·δ| < 1e−4), so each m is one depth DFT. Row 0's own
    offsets enter as one extra term each.

    The D·:data:`_SHIFT_TERMS` depth DFTs are one call of SciPy's FFT over
    ``workers`` threads: each column's transform is computed alone, so the
    result is the same to the bit at any count (``tests/stage2/test_exact.py``).
    """
    phase, rounding, powers, nominal_shift, first_shift = _rendered_cells_factors(config, _offsets_key(offsets))
    count = weights.shape[0]
    terms = np.empty((count, _SHIFT_TERMS) + weights.shape[1:], dtype=np.complex128)
    first_rows = []
    for d in range(count):
        cells = weights[d] * phase[d]
        first_rows.append(cells[0].copy())
        cells[0] = 0.0
        terms[d, 0] = cells
        for m in range(1, _SHIFT_TERMS):
            terms[d, m] = terms[d, m - 1] * rounding[d] / m
    transforms = scipy.fft.fft(terms, axis=2, workers=workers)
    spectrum = np.zeros(weights.shape[1:], dtype=np.complex128)
    for d in range(count):
        series = np.zeros_like(spectrum)
        for m in range(_SHIFT_TERMS):
            series += powers[m] * transforms[d, m]
        spectrum += nominal_shift[d] * series
        spectrum += first_shift[d] * first_rows[d][None, :]
    return scipy.fft.ifft(spectrum, axis=0, workers=workers)


def _offsets_key(offsets: np.ndarray) -> tuple:
    """``offsets`` as a hashable key for :func:`_rendered_cells_factors`."""
    return tuple(float(offset) for offset in np.asarray(offsets).ravel())


@functools.lru_cache(maxsize=4)
def _rendered_cells_factors(config: ScannerConfig, offsets: tuple) -> tuple:
    """The per-row and per-wavenumber factors of :func:`rendered_cells`, the same for every call with these
    ``config`` and ``offsets``: each row's carrier e^{−2i·k0·(z_n + o_{d,n})} (D, Nz, 1), its rounding δ_{d,n}
    (D, Nz, 1), (−2i(k_q − k0))^m (M, Nz, 1), e^{−2i(k_q − k0)·ō_d} and e^{−2i(k_q − k0)·o_{d,0}} (D, Nz, 1)."""
    k = ref.wavenumbers(config)
    k0 = config.k0_rad_per_um
    depth_um = cell_depths_um(config)[None, :]
    nominal = np.asarray(offsets) * config.wavelength_um
    row_offsets = row_offsets_um(config, np.asarray(offsets))  # (D, Nz)
    shift = -2j * (k - k0)  # (Nz,): the depth-kernel shift's rate per µm at each wavenumber
    phase = np.exp(-2j * k0 * (depth_um + row_offsets))[:, :, None]
    rounding = (row_offsets - nominal[:, None])[:, :, None]
    powers = np.stack([shift ** m for m in range(_SHIFT_TERMS)])[:, :, None]
    nominal_shift = np.exp(shift[None, :] * nominal[:, None])[:, :, None]
    first_shift = np.exp(shift[None, :] * row_offsets[:, :1])[:, :, None]
    for factor in (phase, rounding, powers, nominal_shift, first_shift):
        factor.flags.writeable = False  # shared by every call
    return phase, rounding, powers, nominal_shift, first_shift


def _cell_weights(field: np.ndarray, config: ScannerConfig, offsets: np.ndarray = OFFSETS_IN_WAVELENGTHS,
                  pairs: np.ndarray | None = None) -> np.ndarray:
    """Each cell value, its cell's own carrier e^{−2i·k0·z_n} taken out, on two row carriers: the two enclosing it
    (:func:`split_on_carriers`), or the cell's ``pairs`` (:func:`split_on_pairs`)."""
    values = _carrier_free(field, config)
    if pairs is None:
        return split_on_carriers(values, row_carriers(config, offsets))
    return split_on_pairs(values, row_carriers(config, offsets), pairs)


def _carrier_free(field: np.ndarray, config: ScannerConfig) -> np.ndarray:
    """Each cell value with its cell's own carrier e^{−2i·k0·z_n} taken out (what the row carriers then carry)."""
    return field * np.exp(2j * config.k0_rad_per_um * cell_depths_um(config))[:, None]


def _pair_carriers(carriers: np.ndarray, pairs: np.ndarray, shape: tuple) -> tuple[np.ndarray, np.ndarray]:
    """The two carriers of each cell's pair, each of ``shape``: ``carriers`` (D, Nz, 1) at ``pairs`` (2,) + shape."""
    everywhere = np.broadcast_to(carriers, (carriers.shape[0],) + shape)
    return tuple(np.take_along_axis(everywhere, index[None], 0)[0] for index in pairs)


def split_on_pairs(values: np.ndarray, carriers: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """Weights p, q ≥ 0 with p·c_a + q·c_b = value on each cell's own pair (a, b) = ``pairs[:, cell]`` of the
    ``carriers`` (D, Nz, 1); a value just outside its pair's sector (by rounding) gets the nearer edge. (D, ...)."""
    c1, c2 = _pair_carriers(carriers, pairs, values.shape)
    determinant = (np.conj(c1) * c2).imag
    weights = np.zeros((carriers.shape[0],) + values.shape)
    np.put_along_axis(weights, pairs[0][None], np.maximum((np.conj(values) * c2).imag / determinant, 0.0)[None], 0)
    np.put_along_axis(weights, pairs[1][None], np.maximum((np.conj(c1) * values).imag / determinant, 0.0)[None], 0)
    return weights


def _carrier_order(carriers: np.ndarray) -> np.ndarray:
    """The carriers' indices in order around the circle (by the angle of their first row's value)."""
    return np.argsort(np.angle(carriers).reshape(carriers.shape[0], -1)[:, 0])


def _pair_candidates(values: np.ndarray, carriers: np.ndarray, steps: int):
    """Every pair of carriers (a, b) at most ``steps`` apart around the circle: yields (a, b, inside, energy), inside
    where a value lies strictly within the pair's sector (by :data:`PAIR_MARGIN_RAD`), energy its weights' p² + q²."""
    count, order = carriers.shape[0], _carrier_order(carriers)
    value_angles = np.angle(values)
    for step in range(1, steps + 1):
        for position, first in enumerate(order):
            second = order[(position + step) % count]
            c1, c2 = carriers[first], carriers[second]
            within = (value_angles - np.angle(c1)) % (2 * np.pi)
            inside = (within > PAIR_MARGIN_RAD) & (within < np.angle(c2 / c1) % (2 * np.pi) - PAIR_MARGIN_RAD)
            determinant = (np.conj(c1) * c2).imag
            p, q = (np.conj(values) * c2).imag / determinant, (np.conj(c1) * values).imag / determinant
            yield first, second, inside, p**2 + q**2


def _first_pair(values: np.ndarray, carriers: np.ndarray) -> np.ndarray:
    """The pair zero values keep (both weights 0): the first two carriers around the circle, (2,) + values.shape."""
    order = _carrier_order(carriers)
    pairs = np.zeros((2,) + values.shape, dtype=np.int64)
    pairs[0], pairs[1] = order[0], order[1]
    return pairs


def shadow_pairs(values: np.ndarray, carriers: np.ndarray, shadow: np.ndarray, steps: int = 3) -> np.ndarray:
    """For each value, the pair of carriers (a, b), at most ``steps`` apart around the circle and enclosing it,
    whose non-negative weights have p² + q² nearest ``shadow`` in ratio: (2,) + values.shape carrier indices.

    Carriers α apart carry a value with p² + q² = |value|² − 2pq·cos α: 45° apart from 0.59 to 1 times |value|²
    (0.59 in the middle of the pair, 0.69 at :data:`PAIR_MARGIN_RAD` from a carrier), 90° apart exactly 1, 135°
    apart from 1 to 3.4: the pair sets how much a cell shadows, the value what it shows. A value within the margin
    of a carrier has no 45° pair, and shadows at least what it shows."""
    best = np.full(values.shape, np.inf)
    pairs = _first_pair(values, carriers)
    for first, second, inside, energy in _pair_candidates(values, carriers, steps):
        with np.errstate(divide="ignore", invalid="ignore"):
            cost = np.abs(np.log(energy / shadow))
        better = inside & (cost < best)
        best = np.where(better, cost, best)
        pairs[0] = np.where(better, first, pairs[0])
        pairs[1] = np.where(better, second, pairs[1])
    return pairs


def diffused_shadow_pairs(values: np.ndarray, carriers: np.ndarray, shadow: np.ndarray, steps: int = 3,
                          split: np.ndarray | None = None) -> np.ndarray:
    """:func:`shadow_pairs` for a grid of values (Nz, Nx), the shadow they miss carried down each A-scan line.

    Row by row from the top, each cell takes the pair whose p² + q² is nearest its target t_n = s_n + r_n, s the
    ``shadow`` and r what the cells above on its line missed of theirs: r_{n+1} = t_n − (p² + q²)_n, bounded to
    ±:data:`SHADOW_CARRY_LIMIT`·s_n. A cell's pair reaches 0.59–3.4 times its |value|², so a bright cell shadows
    more than its share and a dark one less; carried on, the line's shadow summed down to any depth follows
    Σ s (error diffusion along depth), where :func:`shadow_pairs` leaves each cell's miss where it falls.
    A cell of ``split`` (Nz, Nx; :func:`split_weights`) shadows half its pair's p² + q²."""
    candidates = list(_pair_candidates(values, carriers, steps))
    firsts = np.array([first for first, _, _, _ in candidates])
    seconds = np.array([second for _, second, _, _ in candidates])
    inside = np.stack([candidate[2] for candidate in candidates])
    energy = np.where(inside, np.stack([candidate[3] for candidate in candidates]), np.nan)
    if split is not None:
        energy = np.where(split, energy / 2, energy)
    pairs = _first_pair(values, carriers)
    carry = np.zeros(values.shape[1:])
    lines = np.arange(values.shape[1])
    for row in range(values.shape[0]):
        target = shadow[row] + carry
        cost = np.where(inside[:, row], np.abs(energy[:, row] - target), np.inf)
        chosen = np.argmin(cost, axis=0)
        found = np.isfinite(cost[chosen, lines])  # a zero value has no pair inside: it keeps the first, at 0
        pairs[0, row] = np.where(found, firsts[chosen], pairs[0, row])
        pairs[1, row] = np.where(found, seconds[chosen], pairs[1, row])
        met = np.where(found, energy[chosen, row, lines], 0.0)
        limit = SHADOW_CARRY_LIMIT * shadow[row]
        carry = np.clip(target - met, -limit, limit)
    return pairs


def replicated_offsets(offsets: np.ndarray) -> np.ndarray:
    """The carrier ``offsets`` (in λ) and after them their replicas, each half a wavelength nearer 0: the same
    carrier phase (2·k0·λ/2 = 2π), another depth (:func:`split_weights`)."""
    offsets = np.asarray(offsets, dtype=float)
    return np.concatenate([offsets, offsets - np.copysign(0.5, offsets)])


def split_weights(weights: np.ndarray, split: np.ndarray) -> np.ndarray:
    """Rows (2D, Nz, Nx) at :func:`replicated_offsets` from the pairs' weights (D, Nz, Nx): a cell of ``split``
    keeps half of each weight and gives its replica the other half; they shadow (p² + q²)/2."""
    half = np.where(split, 0.5, 0.0)
    return np.concatenate([weights * (1.0 - half), weights * half])


def decoded_weights(field: np.ndarray, config: ScannerConfig = DEFAULT_CONFIG,
                    corrections: int = DECODE_CORRECTIONS, offsets: np.ndarray = OFFSETS_IN_WAVELENGTHS,
                    shadow: np.ndarray | None = None, diffuse: bool = False, workers: int = 1,
                    tolerance: float = DECODE_TOLERANCE, split: np.ndarray | None = None) -> np.ndarray:
    """The rows' amplitudes that render, without shadowing, exactly as the field: (D, Nz, Nx), at the field's scale.

    Offset d of cell (n, i) is the row at depth ``row_depths_um(config, offsets)[d, n]``
    on A-scan line i; two of a cell's D are non-zero (module docstring):
    the two carriers enclosing its value or, with ``shadow`` (Nz, Nx), the
    pair whose weights' p² + q² is nearest it (:func:`shadow_pairs`, chosen
    once from the field; with ``diffuse``, :func:`diffused_shadow_pairs`). ``workers``: threads of the depth
    DFTs (:func:`rendered_cells`; the same result at any count). Up to ``corrections`` updates of the placed
    field, fewer once max|F − F_eff| ≤ ``tolerance``·max|F| (module docstring; 0: every one). With ``split``
    (Nz, Nx, bool), those cells' weights go half onto replicas (:func:`split_weights`): the result is (2D, Nz, Nx)
    at :func:`replicated_offsets`, and a split cell's pair is chosen for what it shadows, half its p² + q².

    Raises
    ------
    ValueError
        A field of the wrong shape, non-finite or all zero.
    """
    field = np.asarray(field, dtype=np.complex128)
    if field.shape != config.shape:
        raise ValueError(f"field is {field.shape}, the scanner's grid is {config.shape}")
    if not np.isfinite(field).all():
        raise ValueError("field has non-finite values")
    if not np.any(field):
        raise ValueError("the field is zero everywhere: there is nothing to decode")
    pairs = None
    placed = field
    enough = tolerance * np.abs(field).max()
    rows = offsets if split is None else replicated_offsets(offsets)
    for _ in range(corrections + 1):
        if shadow is not None:  # chosen from the field; again for a value a correction moved out of its pair
            pairs = _kept_pairs(placed, config, offsets, shadow, pairs, diffuse, split)
        weights = _cell_weights(placed, config, offsets, pairs)
        if split is not None:
            weights = split_weights(weights, split)
        residual = field - rendered_cells(weights, config, rows, workers)
        if np.abs(residual).max() <= enough:
            break
        placed = placed + residual
    return weights


def _kept_pairs(placed, config, offsets, shadow, pairs, diffuse: bool = False, split=None):
    """``pairs``, with :func:`shadow_pairs` for the cells of ``placed`` whose value is not strictly inside its
    pair (every cell at first); chosen again only for the cells that left their pair: the choice is per cell,
    so these are the pairs a choice over every cell gives, for the cost of the few that moved. With ``diffuse``
    the first choice is :func:`diffused_shadow_pairs`; a cell that leaves its pair takes the nearest alone. A cell
    of ``split`` shadows half its pair's p² + q²: the diffused choice halves its candidates' energies (the shadow it
    carries on stays in one unit), the nearest-pair choice aims its p² + q² at twice its shadow."""
    values, carriers = _carrier_free(placed, config), row_carriers(config, offsets)
    if pairs is None and diffuse:
        return diffused_shadow_pairs(values, carriers, shadow, split=split)
    if split is not None:
        shadow = np.where(split, 2 * shadow, shadow)
    if pairs is None:
        return shadow_pairs(values, carriers, shadow)
    c1, c2 = _pair_carriers(carriers, pairs, values.shape)
    within = np.angle(values / c1) % (2 * np.pi)
    outside = ~((within > 0) & (within < np.angle(c2 / c1) % (2 * np.pi)))
    if not outside.any():
        return pairs
    everywhere = np.broadcast_to(carriers, (carriers.shape[0],) + values.shape)
    chosen = pairs.copy()
    chosen[:, outside] = shadow_pairs(values[outside], everywhere[:, outside], shadow[outside])
    return chosen


def phantom_of_rows(amplitude: np.ndarray, config: ScannerConfig = DEFAULT_CONFIG,
                    offsets: np.ndarray = OFFSETS_IN_WAVELENGTHS) -> Phantom:
    """The rows of non-zero ``amplitude`` (D, Nz, Nx) as a phantom: ordered by cell (row-major) and offset, x on
    the A-scan lines, y = 0, z = :func:`row_depths_um`, E = 100·a²."""
    row, column, offset = np.nonzero(np.moveaxis(amplitude, 0, -1) > 0)
    z_um = row_depths_um(config, offsets)[offset, row]
    x_um = ref.ascan_positions_um(config)[column]
    return Phantom(x_um, np.zeros_like(x_um), z_um, 100.0 * np.moveaxis(amplitude, 0, -1)[row, column, offset] ** 2)


def decode_exact(field: np.ndarray, config: ScannerConfig = DEFAULT_CONFIG,
                 shadow_bound: float = SHADOW_BOUND, corrections: int = DECODE_CORRECTIONS, workers: int = 1,
                 tolerance: float = DECODE_TOLERANCE) -> Phantom:
    """Two rows per non-zero cell that render, without shadowing, exactly as the field (module docstring).

    Parameters
    ----------
    field : ndarray of complex, (Nz, Nx)
        F on the cell grid; any overall scale.
    config : ScannerConfig
    shadow_bound : float
        max_i Σ_j (B_ij·a_j)² of the result, in (0, 0.5]: the absolute scale.
    corrections : int
        Updates of the placed field for the rows' depth-kernel shifts, at most.
    workers : int
        Threads of the depth DFTs; the result is the same at any count.
    tolerance : float
        The updates stop once the rows' rendering is within ``tolerance``·max|F| of the field (0: all of them).

    Returns
    -------
    Phantom
        Rows ordered by cell (row-major) and offset, x on the A-scan lines,
        y = 0, 0 ≤ z ≤ Nz·Δz, E = 100·a².

    Raises
    ------
    ValueError
        A field of the wrong shape, non-finite or all zero; a bound outside (0, 0.5].
    """
    if not 0 < shadow_bound <= 0.5:
        raise ValueError(f"shadow_bound must be in (0, 0.5], got {shadow_bound}")
    weights = decoded_weights(field, config, corrections, workers=workers, tolerance=tolerance)
    # Scale: Σ_j (B_ij·a_j)² over an A-scan is a lateral convolution of the
    # columns' Σ a² with e^{−2d²/w0²} (y = 0), over the offsets the float64
    # scanner resolves (octcl._reference.SHADOW_EXACT_RADIUS_SQ).
    per_ascan = np.convolve((weights**2).sum(axis=(0, 1)), ref.shadow_taps(config), mode="same")
    return phantom_of_rows(math.sqrt(shadow_bound / per_ascan.max()) * weights, config)

