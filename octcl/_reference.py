"""Float64 NumPy reference of the SynthOCT Virtual Scanner.

Each step of the scanner (``shared/physics.md`` §2) is one function here, in
the order the scanner applies them, written for clarity: this module is the
oracle that the OpenCL kernels are checked against, not the fast path.

Notation: A-scan i at lateral position x_i, scatterer j at (x_j, y_j, z_j)
with amplitude a_j; w0 the beam radius; Nz depth samples of Δz µm.

References
----------
Fercher, Drexler, Hitzenberger & Lasser, "Optical coherence tomography —
principles and applications", Rep. Prog. Phys. 66 (2003): the Fourier-domain
A-scan as the inverse DFT of the interference spectrum.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .device.depth_order import depth_order as classic_depth_order
from ._io import GREY_LUT
from .config import DEFAULT_CONFIG, ScannerConfig
from .phantom import Phantom

#: A scatterer adds to A-scan i only where (x_i − x_j)² + y_j² < 3·w0².
CONTRIBUTION_RADIUS_SQ = 3.0
#: Shadowing counts every shallower scatterer, but a factor 1 − (B·a)² with
#: (B·a)² ≤ 2⁻⁵⁴ rounds to exactly 1.0 in float64. Since a ≤ 1 and
#: B² = exp(−2d²/w0²), every scatterer with d² ≥ 20·w0² has
#: (B·a)² ≤ exp(−40) ≈ 4.2e−18 < 2⁻⁵⁴ ≈ 5.6e−17, so leaving those out changes
#: no bit of the product.
SHADOW_EXACT_RADIUS_SQ = 20.0
#: |A| is replaced by this where it is exactly zero, before taking the log.
MAGNITUDE_FLOOR = 1e-10
#: Display dynamic range in dB.
DISPLAY_RANGE_DB = 51.0


def amplitudes(energy_pct: np.ndarray) -> np.ndarray:
    """Step 1: field amplitude a_j = sqrt(E_j / 100)."""
    return np.sqrt(np.asarray(energy_pct, dtype=np.float64) / 100.0)


def ascan_positions_um(config: ScannerConfig = DEFAULT_CONFIG) -> np.ndarray:
    """Step 2: x_i = (i − Nx/2)·Δx for i = 0 … Nx−1, in µm."""
    return (np.arange(config.a_scans) - config.a_scans / 2) * config.lateral_pitch_um


def shadow_taps(config: ScannerConfig = DEFAULT_CONFIG) -> np.ndarray:
    """Step 4's B² = e^{−2(d·Δx)²/w0²} at y = 0 for the A-scan offsets d = −R … R this scanner resolves
    (:data:`SHADOW_EXACT_RADIUS_SQ`): the weight, in A-scan i's shadow, of a scatterer on the line d away."""
    w0, pitch = config.beam_radius_um, config.lateral_pitch_um
    reach = int(np.ceil(np.sqrt(SHADOW_EXACT_RADIUS_SQ) * w0 / pitch))
    offsets_um = np.arange(-reach, reach + 1) * pitch
    return np.exp(-2 * offsets_um**2 / w0**2)


def beam_weight(dx_um: np.ndarray, y_um: np.ndarray, beam_radius_um: float) -> np.ndarray:
    """Step 3: Gaussian beam weight B = exp(−(Δx² + y²)/w0²)."""
    return np.exp(-(dx_um**2 + y_um**2) / beam_radius_um**2)


def in_contribution_window(dx_um: np.ndarray, y_um: np.ndarray, beam_radius_um: float) -> np.ndarray:
    """Step 3: True where (x_i − x_j)² + y_j² < 3·w0² (the scatterer adds to A-scan i)."""
    return dx_um**2 + y_um**2 < CONTRIBUTION_RADIUS_SQ * beam_radius_um**2


def depth_order(z_um: np.ndarray) -> np.ndarray:
    """Step 4: indices sorting scatterers by depth, as the scanner's ``np.argsort`` does.

    That is NumPy's classic introsort, which is not stable: the order it gives
    equal depths decides which tied scatterer shadows which, and with it the
    reference reproduces both official Uniform scans pixel for pixel
    (docs/scanner.md). The pure-Python path keeps this module free of OpenCL.
    """
    return classic_depth_order(z_um, backend="python")


def shadow_transmission(beam_amplitude: np.ndarray) -> np.ndarray:
    """Step 4: T_r = Π_{m<r} (1 − min((B_m·a_m)², 1)) for scatterers in depth order.

    Parameters
    ----------
    beam_amplitude : ndarray, shape (M,)
        B·a of the scatterers of one A-scan, sorted by depth.

    Returns
    -------
    ndarray, shape (M,)
        The exclusive cumulative product: a scatterer is dimmed by every
        shallower one, not by itself. A mirror (B·a ≥ 1) makes every deeper
        transmission exactly 0.
    """
    loss = 1.0 - np.minimum(beam_amplitude**2, 1.0)
    transmission = np.empty_like(loss)
    if loss.size:
        transmission[0] = 1.0
        np.cumprod(loss[:-1], out=transmission[1:])
    return transmission


def wavenumber_grid(config: ScannerConfig = DEFAULT_CONFIG) -> tuple[float, float, np.ndarray]:
    """Step 5's grid: (k0, δk, s) with k_q = k0 + s_q·δk (:func:`wavenumbers`).

    H = Δz·(Nz − 1), δk = (π/H)·Nz/(Nz + 1) in rad/µm, k0 = 2π/λ, and the
    integer s_q = q for q ≤ Nz/2, q − Nz otherwise (q = 0 … Nz−1, FFT order).
    """
    nz = config.depth_pixels
    span_um = config.pixel_size_um * (nz - 1)
    dk = (np.pi / span_um) * nz / (nz + 1)
    k0 = config.k0_rad_per_um
    q = np.arange(nz)
    return k0, dk, np.where(q <= nz // 2, q, q - nz)


def wavenumbers(config: ScannerConfig = DEFAULT_CONFIG) -> np.ndarray:
    """Step 5: k_q = k0 + s_q·δk in rad/µm, q = 0 … Nz−1 in FFT order (:func:`wavenumber_grid`)."""
    k0, dk, s = wavenumber_grid(config)
    return k0 + s * dk


#: Wavenumbers per block of :func:`spectrum`'s factorisation: 16 blocks of 16 for Nz = 256.
SPECTRUM_BLOCK = 16


def spectrum(z_um: np.ndarray, weight: np.ndarray, config: ScannerConfig = DEFAULT_CONFIG) -> np.ndarray:
    """Step 6: S(k_q) = Σ_j w_j·exp(−2i·k_q·z_j), with w_j = T_j·a_j·B_j (n = 1), q in FFT order.

    The wavenumbers lie on the grid k0 + s·δk (:func:`wavenumber_grid`). With
    m = s − min(s) = B·α + β (B = :data:`SPECTRUM_BLOCK`), each term is the
    product of two exponentials computed directly,

        exp(−2i·k·z) = exp(−2i·(k0 + (min(s) + B·α)·δk)·z) · exp(−2i·β·δk·z),

    so the sum over scatterers is a matrix product,
    S[α, β] = Σ_j (w_j·P[α, j])·Q[β, j]: ⌈Nz/B⌉ + B complex exponentials per
    scatterer (32 for Nz = 256) instead of Nz. Each term is within a few ulp
    of the direct exponential, whose own argument (|2kz| up to about 1.5·10⁴
    rad at z = 1536 µm) carries a rounding error of about 2·10⁻¹² rad. The
    official phantoms' reference renders took 25 s each on two slow cores
    with Nz exponentials per scatterer, 5.1–5.2 s with these
    (docs/benchmarks.md, "CI on two slow cores").
    """
    k0, dk, s = wavenumber_grid(config)
    lowest = int(s.min())
    blocks = -(-(int(s.max()) - lowest + 1) // SPECTRUM_BLOCK)
    block_k = k0 + (lowest + SPECTRUM_BLOCK * np.arange(blocks)) * dk
    offset_k = np.arange(SPECTRUM_BLOCK) * dk
    grid = np.zeros((blocks, SPECTRUM_BLOCK), dtype=np.complex128)
    for start in range(0, z_um.size, 8192):  # bounded memory: (⌈Nz/B⌉ + B) × 8192 phases at a time
        z = z_um[start:start + 8192]
        outer = np.exp(-2j * np.outer(block_k, z)) * weight[start:start + 8192]
        grid += outer @ np.exp(-2j * np.outer(offset_k, z)).T
    return grid.ravel()[s - lowest]


def hann_window(nz: int) -> np.ndarray:
    """Step 7: symmetric Hann window w[n] = 0.5 − 0.5·cos(2πn/(Nz − 1)) in FFT order."""
    n = np.arange(nz)
    return np.fft.ifftshift(0.5 - 0.5 * np.cos(2 * np.pi * n / (nz - 1)))


def inverse_dft(windowed_spectrum: np.ndarray) -> np.ndarray:
    """Step 8: the complex A-scans A = IDFT_q(S·w), with 1/Nz normalisation (axis 0)."""
    return np.fft.ifft(windowed_spectrum, axis=0)


def ascan_magnitude(a_scans: np.ndarray) -> np.ndarray:
    """Step 8: |A|; exact zeros become 1e−10."""
    magnitude = np.abs(a_scans)
    magnitude[magnitude == 0] = MAGNITUDE_FLOOR
    return magnitude


def to_decibels(magnitude: np.ndarray) -> np.ndarray:
    """Step 9: dB = 20·log10 |A|."""
    return 20.0 * np.log10(magnitude)


def to_display(db: np.ndarray) -> np.ndarray:
    """Step 10: D = max(dB − max dB + 51, 0) / max(·), D ∈ [0, 1], max over the B-scan."""
    clipped = np.maximum(db - db.max() + DISPLAY_RANGE_DB, 0.0)
    return clipped / clipped.max()


def colour_index(display: np.ndarray) -> np.ndarray:
    """Step 11a: colour index min(floor(256·D), 255) of the display value."""
    return np.minimum(np.floor(256.0 * display), 255).astype(np.uint8)


def quantise(display: np.ndarray) -> np.ndarray:
    """Step 11: the 8-bit PNG level, GREY_LUT[min(floor(256·D), 255)].

    The scanner writes through matplotlib's grey colormap, whose byte table
    truncates 24 of the 256 indices one level down (:data:`octcl._io.GREY_LUT`);
    with it the reference matches the official scans on 99.9 % of pixels
    instead of 93 % (docs/scanner.md).
    """
    return GREY_LUT[colour_index(display)]


@dataclass
class ReferenceRender:
    """Every intermediate of a reference rendering, (Nz, Nx) arrays."""

    a_scans: np.ndarray
    magnitude: np.ndarray
    db: np.ndarray
    display: np.ndarray
    levels: np.ndarray


def render_spectra(phantom: Phantom, config: ScannerConfig = DEFAULT_CONFIG,
                   shadowing: bool = True) -> np.ndarray:
    """Steps 1–6: the complex spectra S_i(k_q), shape (Nz, Nx), q in FFT order.

    ``shadowing=False`` sets T = 1 (used to check the shadowing step alone).
    """
    w0 = config.beam_radius_um
    amplitude = amplitudes(phantom.energy_pct)
    rank = np.empty(len(phantom), dtype=np.int64)
    rank[depth_order(phantom.z_um)] = np.arange(len(phantom))
    # Sort laterally once; each A-scan then takes a slice of candidates.
    by_x = np.argsort(phantom.x_um, kind="stable")
    x_sorted = phantom.x_um[by_x]
    reach_um = np.sqrt(SHADOW_EXACT_RADIUS_SQ) * w0
    spectra = np.zeros((config.depth_pixels, config.a_scans), dtype=np.complex128)
    for i, x_i in enumerate(ascan_positions_um(config)):
        lo, hi = np.searchsorted(x_sorted, [x_i - reach_um, x_i + reach_um], side="left")
        near = by_x[lo:hi]
        near = near[np.argsort(rank[near], kind="stable")]  # depth order
        dx = x_i - phantom.x_um[near]
        beam = beam_weight(dx, phantom.y_um[near], w0)
        beam_amplitude = beam * amplitude[near]
        transmission = shadow_transmission(beam_amplitude) if shadowing else np.ones(near.size)
        weight = transmission * beam_amplitude
        # Zero weights (behind a mirror, E = 0) add exactly 0: leave them out.
        contributes = in_contribution_window(dx, phantom.y_um[near], w0) & (weight != 0)
        spectra[:, i] = spectrum(phantom.z_um[near][contributes], weight[contributes], config)
    return spectra


def render_reference(phantom: Phantom, config: ScannerConfig = DEFAULT_CONFIG) -> ReferenceRender:
    """Render a phantom to a B-scan with the float64 reference (physics.md §2)."""
    a_scans = inverse_dft(render_spectra(phantom, config) * hann_window(config.depth_pixels)[:, None])
    magnitude = ascan_magnitude(a_scans)
    db = to_decibels(magnitude)
    display = to_display(db)
    return ReferenceRender(a_scans=a_scans, magnitude=magnitude, db=db, display=display,
                           levels=quantise(display))
