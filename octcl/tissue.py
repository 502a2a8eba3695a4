"""What a phantom is as tissue: its energies, the light its own shadowing leaves, its attenuation.

The scanner dims every scatterer by the transmission T the shallower ones
leave under the beam (``shared/physics.md`` §2 step 4): in A-scan i,
T_i(z) = Π_{z_m < z} (1 − min((B_im·a_m)², 1)), B_im = e^{−((x_i−x_m)² + y_m²)/w0²}.
A phantom whose energies are at tissue scale (E ≈ 1 %, the challenge's
"typical biological tissue") dims by tens of dB over the visible depth; one
whose energies are too small to shadow does not, and carries the scan's
dimming in energies that fall with depth instead. The figures here tell
the two apart and compare a phantom with another (its truth):

- :func:`transmission_map`: T at the top of each pixel row, (Nz, Nx);
- :func:`shadow_db`: −20·log10 T at the deepest row of each A-scan whose
  target level is ≥ :data:`VISIBLE_LEVEL` ("the bottom of the visible
  tissue"), the median over the A-scans that have one;
- :func:`band_densities`: Σ E·e^{−2y²/w0²} over the scatterers with
  |x| ≤ Xmax/2 in each :data:`BAND_UM` depth band (what the beam's shadowing
  sees of them: n·E, which the scan can tell, not E alone);
- :func:`attenuation_map`: µ = −d ln T/dz in mm⁻¹ per pixel, the phantom's
  own attenuation coefficient (OCT intensity decays as e^{−2µz});
- :func:`tissue_figures`: all of them, the energies' percentiles, and the
  median µ the target's own levels give (:func:`scan_attenuation`) beside
  the phantom's;
- :func:`scan_attenuation`: µ of a scan itself, the depth-resolved estimate
  from its intensities (what the OAC map is built on), in the same unit, so
  that a phantom's own attenuation can be set beside its target's.
"""

from __future__ import annotations

import math

import numpy as np

from . import _reference as ref
from .config import DEFAULT_CONFIG, ScannerConfig
from .phantom import Phantom

#: Target level from which a pixel counts as visible tissue for :func:`shadow_db`.
VISIBLE_LEVEL = 64
#: Depth band of :func:`band_densities`, µm (32 pixel rows).
BAND_UM = 192.0
#: A band has signal where this share of its target pixels is above level 0.
BAND_SIGNAL_SHARE = 0.4


def transmission_map(phantom: Phantom, config: ScannerConfig = DEFAULT_CONFIG) -> np.ndarray:
    """T_i at the top of each pixel row n (depth n·Δz), (Nz, Nx): the product over the scatterers above it within
    the float64 scanner's shadow reach (octcl._reference.SHADOW_EXACT_RADIUS_SQ); 0 below a mirror."""
    w0, pitch = config.beam_radius_um, config.lateral_pitch_um
    reach = ref.shadow_taps(config).size // 2
    positions = ref.ascan_positions_um(config)
    amplitude_sq = phantom.energy_pct / 100.0
    nearest = np.rint((phantom.x_um - positions[0]) / pitch).astype(np.int64)
    # A scatterer at depth z shadows the rows below it: the first row whose top n·Δz is deeper than z.
    first_row = np.floor(phantom.z_um / config.pixel_size_um).astype(np.int64) + 1
    log_loss = np.zeros((config.depth_pixels + 1, config.a_scans))
    for offset in range(-reach, reach + 1):
        line = nearest + offset
        inside = (line >= 0) & (line < config.a_scans) & (first_row <= config.depth_pixels)
        beam_sq = np.exp(-2 * ((positions[line[inside]] - phantom.x_um[inside]) ** 2 + phantom.y_um[inside] ** 2)
                         / w0**2)
        with np.errstate(divide="ignore"):
            loss = np.log1p(-np.minimum(beam_sq * amplitude_sq[inside], 1.0))
        np.add.at(log_loss, (first_row[inside], line[inside]), loss)
    return np.exp(np.cumsum(log_loss, axis=0)[:config.depth_pixels])


def shadow_db(transmission: np.ndarray, levels: np.ndarray) -> float | None:
    """Median over A-scans of −20·log10 T at their deepest row with level ≥ :data:`VISIBLE_LEVEL`; None if none has."""
    visible = levels >= VISIBLE_LEVEL
    lines = np.flatnonzero(visible.any(axis=0))
    if not lines.size:
        return None
    deepest = visible.shape[0] - 1 - np.argmax(visible[::-1, lines], axis=0)
    with np.errstate(divide="ignore"):
        return float(np.median(-20 * np.log10(transmission[deepest, lines])))


def band_densities(phantom: Phantom, config: ScannerConfig = DEFAULT_CONFIG) -> np.ndarray:
    """Σ E·e^{−2y²/w0²} (%) of the scatterers with |x| ≤ Xmax/2 in each :data:`BAND_UM` band from z = 0."""
    bands = int(math.ceil(config.depth_range_um / BAND_UM))
    inside = np.abs(phantom.x_um) <= config.xmax_um / 2
    band = np.minimum((phantom.z_um[inside] // BAND_UM).astype(np.int64), bands - 1)
    weight = phantom.energy_pct[inside] * np.exp(-2 * phantom.y_um[inside] ** 2 / config.beam_radius_um**2)
    return np.bincount(band, weights=weight, minlength=bands)


def bands_with_signal(levels: np.ndarray, config: ScannerConfig = DEFAULT_CONFIG) -> np.ndarray:
    """Whether each :data:`BAND_UM` band has signal: ≥ :data:`BAND_SIGNAL_SHARE` of its pixels above level 0."""
    rows = int(round(BAND_UM / config.pixel_size_um))
    bands = int(math.ceil(levels.shape[0] / rows))
    return np.array([np.mean(levels[b * rows:(b + 1) * rows] > 0) >= BAND_SIGNAL_SHARE for b in range(bands)])


def attenuation_map(transmission: np.ndarray, config: ScannerConfig = DEFAULT_CONFIG) -> np.ndarray:
    """µ = −d ln T/dz (mm⁻¹) of each pixel row, from T at its top and at the next row's (the last row repeats)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        log_t = np.log(np.maximum(transmission, 1e-300))
    step = np.diff(log_t, axis=0, append=log_t[-1:])
    step[-1] = step[-2] if step.shape[0] > 1 else 0.0
    return -step / config.pixel_size_um * 1000.0


def scan_attenuation(magnitude: np.ndarray, config: ScannerConfig = DEFAULT_CONFIG) -> np.ndarray:
    """µ (mm⁻¹) of each pixel of a scan, by the depth-resolved estimator on its intensities I = |A|², (Nz, Nx).

    µ[z] = I[z] / (2Δ·(Σ_{z' > z} I[z'] + I[z]/2)), Δ the pixel size in mm: the estimator of Vermeer et al.,
    "Depth-resolved model-based reconstruction of attenuation coefficients in optical coherence tomography",
    Biomed. Opt. Express 5(1), 322–337, 2014, in the half-pixel form of the SynthOCT processor's OAC map
    (:mod:`octcl.maps`). It assumes all the light is gone below the scan: where a line's intensity decays as
    e^{−2µz} without end it gives tanh(µΔ)/Δ ≈ µ, and it overestimates at the bottom of the data. The OAC map
    reads the grey levels as 40 dB; ``magnitude`` here is |A|/max|A| as the scanner displays it over its own
    51 dB (:func:`octcl.host.stage1.levels.target_magnitude` of a target's levels), so that µ is in the unit of
    :func:`attenuation_map`, the phantom's own.
    """
    intensity = np.asarray(magnitude, dtype=np.float64) ** 2
    below = np.cumsum(intensity[::-1], axis=0)[::-1] - intensity / 2  # Σ_{z' > z} I + I/2
    with np.errstate(divide="ignore", invalid="ignore"):
        attenuation = np.where(below > 0, intensity / (2 * below), 0.0)
    return attenuation / config.pixel_size_um * 1000.0


def tissue_figures(phantom: Phantom, levels: np.ndarray, config: ScannerConfig = DEFAULT_CONFIG,
                   transmission: np.ndarray | None = None) -> dict:
    """The figures of the module docstring for ``phantom`` against the target ``levels`` (its visible tissue);
    ``transmission``: its :func:`transmission_map`, where the caller has it already."""
    from .host.stage1.levels import target_magnitude

    transmission = transmission_map(phantom, config) if transmission is None else transmission
    energy = phantom.energy_pct
    attenuation = attenuation_map(transmission, config)
    visible = levels >= VISIBLE_LEVEL
    scans_own = scan_attenuation(target_magnitude(levels), config)
    return {"scatterers": int(len(phantom)),
            "energy_pct": {f"p{q}": float(np.percentile(energy, q)) for q in (5, 50, 95)} | {"max": float(energy.max())},
            "shadow_db": shadow_db(transmission, levels),
            "attenuation_per_mm_median": float(np.median(attenuation[visible])) if visible.any() else None,
            "scan_attenuation_per_mm_median": float(np.median(scans_own[visible])) if visible.any() else None,
            "band_um": BAND_UM, "band_densities_pct": band_densities(phantom, config).tolist(),
            "bands_with_signal": bands_with_signal(levels, config).tolist()}


__all__ = ["BAND_SIGNAL_SHARE", "BAND_UM", "VISIBLE_LEVEL", "attenuation_map", "band_densities", "bands_with_signal",
           "scan_attenuation", "shadow_db", "tissue_figures", "transmission_map"]
