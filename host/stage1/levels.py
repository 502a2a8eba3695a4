"""The target's 8-bit levels as what stage 1 fits: displays, magnitudes and their intervals.

The scanner writes level GREY_LUT[c] for colour index c = min(⌊256·D⌋, 255),
D = 1 + 20·log10(|A|/max|A|)/51 (``shared/physics.md`` §2 steps 9–10). A
level therefore stands for an interval of D, and of |A|/max|A|:

- :func:`target_display`, :func:`target_magnitude`: the interval's centre,
  de-quantised and de-logged (the display fit's goal and start,
  :mod:`octcl.host.stage1.display`);
- :func:`level_magnitude_bounds`, :func:`anchored_bounds`: the interval
  itself, [l, u] of |A|/max|A| per pixel (the projections' and the hinge
  fit's sets, :mod:`octcl.host.stage1.projections`,
  :mod:`octcl.host.stage1.hinge`), and :func:`interval_projection` P_𝓜 onto
  them.
"""

from __future__ import annotations

import numpy as np

from ... import _reference as ref
from ..._io import GREY_LUT
from ...config import ScannerConfig

#: Magnitude given to the pixels at the display floor (level 0) in the
#: initialisation, relative to the floor magnitude: 6 dB below the floor.
BELOW_FLOOR_FRACTION = 0.5


def target_levels(target, config: ScannerConfig | None = None) -> np.ndarray:
    """The target's 8-bit levels.

    Parameters
    ----------
    target : ndarray
        uint8 levels, or a float image as :func:`octcl._io.read_scan` returns
        it (level/255), which is rounded back to levels.
    config : ScannerConfig, optional
        If given, the target must have its shape (Nz, Nx).

    Returns
    -------
    ndarray of uint8, (Nz, Nx)
    """
    target = np.asarray(target)
    if target.ndim != 2:
        raise ValueError(f"expected a 2-D B-scan, got shape {target.shape}")
    if config is not None and target.shape != config.shape:
        raise ValueError(f"target is {target.shape[0]}x{target.shape[1]}, the scanner makes "
                         f"{config.shape[0]}x{config.shape[1]}")
    if target.dtype == np.uint8:
        return target
    if not np.issubdtype(target.dtype, np.floating) or not np.isfinite(target).all():
        raise ValueError(f"expected uint8 levels or a finite float image in [0, 1], got {target.dtype}")
    return np.clip(np.rint(target * 255.0), 0, 255).astype(np.uint8)


def display_interval_of_level() -> tuple[np.ndarray, np.ndarray]:
    """The display interval [low, high) of each 8-bit level: two arrays of 256.

    The scanner writes level GREY_LUT[c] for colour index c = min(⌊256·D⌋, 255),
    so a level L comes from D in the union of [c/256, (c+1)/256) over the
    indices c with GREY_LUT[c] = L (two indices for the 24 levels below a
    truncated index). The 24 truncated levels themselves never come out of
    the scanner; a target made otherwise (a real scan quantised plainly) has
    them, and for those the plain quantiser's interval [L/256, (L+1)/256) is
    given.
    """
    index = np.arange(256)
    low = index / 256.0
    high = (index + 1) / 256.0
    produced = np.zeros(256, dtype=bool)
    produced[GREY_LUT] = True
    low[produced] = np.inf
    high[produced] = -np.inf
    np.minimum.at(low, GREY_LUT, index / 256.0)
    np.maximum.at(high, GREY_LUT, (index + 1) / 256.0)
    return low, high


def display_of_level() -> np.ndarray:
    """D at the centre of the display interval of each 8-bit level (:func:`display_interval_of_level`).

    Level 0 is handled by :func:`target_display`.
    """
    low, high = display_interval_of_level()
    return 0.5 * (low + high)


def target_display(target) -> np.ndarray:
    """The target's display D*, de-quantised.

    Each level maps to the centre of the D interval it stands for
    (:func:`display_of_level`), except level 0, which maps to D* = 0: it
    holds the pixels at or below the display floor (|A| ≤ max|A|·10^{−51/20},
    plus the first 1/256 above it), whose magnitude is unknown. The loss of
    :func:`fit_field` treats these pixels as the inequality D ≤ 0 (it clamps
    the model's D at 0 there), not as an equality.

    Returns
    -------
    ndarray of float64, (Nz, Nx), in [0, 1]
    """
    levels = target_levels(target)
    display = display_of_level()[levels]
    display[levels == 0] = 0.0
    return display


def target_magnitude(target) -> np.ndarray:
    """De-logged target magnitude |A|/max|A| = 10^{51·(D* − 1)/20}.

    D* is :func:`target_display`. The pixels at level 0 lie below the display
    floor with unknown magnitude; they get a small value, half the floor
    magnitude (6 dB below it), which is only used to start the fit.

    Returns
    -------
    ndarray of float64, (Nz, Nx), in (0, 1]
    """
    display = target_display(target)
    magnitude = 10.0 ** (ref.DISPLAY_RANGE_DB * (display - 1.0) / 20.0)
    floor = 10.0 ** (-ref.DISPLAY_RANGE_DB / 20.0)
    return np.where(target_levels(target) == 0, BELOW_FLOOR_FRACTION * floor, magnitude)



#: Share of each level's interval (in dB) given up at each end.
INTERVAL_MARGIN = 0.1


def level_magnitude_bounds(levels: np.ndarray, margin: float = INTERVAL_MARGIN) -> tuple[np.ndarray, np.ndarray]:
    """The interval [l, u] of |A|/max|A| that renders each 8-bit level.

    The scanner writes level GREY_LUT[c] for colour index c = min(⌊256·D⌋, 255),
    D = 1 + 20·log10(|A|/max|A|)/51 (clamped at 0). A level L therefore comes
    from D in the union of [c/256, (c + 1)/256) over the indices c with
    GREY_LUT[c] = L, i.e. |A|/max|A| in [10^{51(D_lo − 1)/20}, 10^{51(D_hi − 1)/20});
    the 24 levels the colour map skips (a target quantised plainly has them)
    take the plain quantiser's interval [L/256, (L + 1)/256). Level 0 holds
    everything at or below the floor: l = 0.

    Parameters
    ----------
    levels : ndarray of uint8
    margin : float
        Share of each interval's width in D (so in dB) removed at each end,
        in [0, 0.5).

    Returns
    -------
    lower, upper : ndarray of float64, the shape of ``levels``
    """
    if not 0 <= margin < 0.5:
        raise ValueError(f"margin must be in [0, 0.5), got {margin}")
    index = np.arange(256)
    low, high = np.full(256, np.inf), np.full(256, -np.inf)
    np.minimum.at(low, GREY_LUT, index / 256.0)
    np.maximum.at(high, GREY_LUT, (index + 1) / 256.0)
    skipped = ~np.isfinite(low)
    low[skipped], high[skipped] = index[skipped] / 256.0, (index[skipped] + 1) / 256.0
    width = high - low
    low, high = low + margin * width, high - margin * width

    def magnitude(display):
        return 10.0 ** (ref.DISPLAY_RANGE_DB * (display - 1.0) / 20.0)

    lower, upper = magnitude(low)[levels], magnitude(high)[levels]
    lower[levels == 0] = 0.0
    return lower, upper


def anchored_bounds(aim: np.ndarray, magnitude: np.ndarray, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`level_magnitude_bounds` of ``aim`` with one pixel pinned at |A| = 1: of the pixels at the highest
    aimed level, the brightest in ``magnitude``. Every upper bound is ≤ 1, so a field inside these bounds
    has max|A| = 1 exactly and renders each pixel at the level its bounds say: the display's division by
    its own maximum is then part of the constraints."""
    lower, upper = level_magnitude_bounds(aim, margin)
    anchor = np.unravel_index(np.argmax(np.where(aim == aim.max(), magnitude, -1.0)), aim.shape)
    lower[anchor] = upper[anchor] = 1.0
    return lower, upper


def interval_projection(a_scans: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """P_𝓜: each pixel's magnitude clipped into [lower, upper], its phase kept (phase 0 at exactly 0)."""
    magnitude = np.abs(a_scans)
    clipped = np.clip(magnitude, lower, upper)
    return np.where(magnitude > 0, a_scans * (clipped / np.where(magnitude > 0, magnitude, 1.0)), clipped)

