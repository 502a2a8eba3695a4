"""The scanner's ceiling on a target: the pixels no phantom can render, and the levels aimed at instead.

The scanner writes the byte of matplotlib's ``gray`` colour map for its
colour index (``shared/physics.md`` §2 step 11): 232 distinct levels, so 24
(33, 37, …, 228, 244) are never written (:data:`WRITABLE`). A target
quantised plainly (a real scan, or floor(256·D) of a rendering) has pixels
at those levels, and no phantom renders them: one level up or down is the
best. Which side matters to the speckle-contrast maps (SC, RSC), which see
the local mean and spread of the levels.

- :func:`nearest_writable` moves each such pixel to the level the scanner
  writes for the display value the plain quantiser read as its level
  (``GREY_LUT[L]``, one of L ± 1): what the projections aimed at before the
  side was chosen.
- :func:`error_diffused` chooses the side by Floyd–Steinberg error
  diffusion on the level image (Floyd & Steinberg, "An adaptive algorithm
  for spatial greyscale", Proc. SID 17(2), 1976): pixels are visited in
  raster order, each carrying the error diffused onto it; a writable pixel
  keeps its level and passes its error on, an unwritable one takes L + 1
  where the error it carries is positive, else L − 1 (ties go to
  :func:`nearest_writable`'s side), and passes on L + e − q. The local mean
  of the levels is kept, which a fixed side shifts by a level wherever
  such pixels cluster.

:func:`measure_ceiling` reports, for a target and before any inversion,
the share of its pixels at writable levels and the exact score of the two
images above: no phantom renders the target better than its writable
pixels allow, and these images are what "at the ceiling" looks like.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from octcl._io import GREY_LUT

#: WRITABLE[L]: whether the scanner ever writes 8-bit level L.
WRITABLE = np.zeros(256, bool)
WRITABLE[GREY_LUT] = True


def writable_share(levels: np.ndarray) -> float:
    """Share of pixels at levels the scanner writes (1.0 for any scan the scanner rendered)."""
    return float(np.mean(WRITABLE[np.asarray(levels, np.uint8)]))


def nearest_writable(levels: np.ndarray) -> np.ndarray:
    """``levels`` with each unwritable level L replaced by ``GREY_LUT[L]``, the level the scanner writes for
    the display interval [L/256, (L + 1)/256) a plain quantiser read as L."""
    levels = np.asarray(levels, np.uint8)
    return np.where(WRITABLE[levels], levels, GREY_LUT[levels]).astype(np.uint8)


def error_diffused(levels: np.ndarray) -> np.ndarray:
    """``levels`` with the side of each unwritable level chosen by Floyd–Steinberg error diffusion (module docstring).

    Only unwritable pixels change; each becomes L − 1 or L + 1 (both
    writable: unwritable levels are at least four apart). Rows are visited
    left to right. Within a row the error a pixel passes on is
    p_c = e_c + 7/16·p_{c−1} − q_c, e_c what the rows above diffused onto
    it and q_c its change of level (0 for a writable pixel): a linear
    recurrence between unwritable pixels (:func:`scipy.signal.lfilter`),
    decided at each unwritable one.
    """
    from scipy.signal import lfilter

    levels = np.asarray(levels, np.uint8)
    rows, columns = levels.shape
    aimed = levels.copy()
    carried = np.zeros(columns + 2)  # what the rows above diffused onto this row, one padding column each side
    nearest_side = np.sign(GREY_LUT.astype(np.int16) - np.arange(256))
    right = 7 / 16

    def run(values, before):  # p_c = values_c + 7/16·p_{c−1}, p_{−1} = before
        return lfilter([1.0], [1.0, -right], values, zi=[right * before])[0]

    for row in range(rows):
        received = carried[1:-1]
        passed = np.empty(columns)
        done, before = 0, 0.0
        for column in np.flatnonzero(~WRITABLE[levels[row]]):
            if column > done:
                passed[done:column] = run(received[done:column], before)
                before = passed[column - 1]
            e = received[column] + right * before
            level = int(levels[row, column])
            side = int(np.sign(e)) if e != 0 else int(nearest_side[level])
            aimed[row, column] = level + side
            passed[column] = before = e - side
            done = column + 1
        if done < columns:
            passed[done:] = run(received[done:], before)
        carried = np.zeros(columns + 2)
        carried[0:columns] += 3 / 16 * passed    # below-left
        carried[1:columns + 1] += 5 / 16 * passed  # below
        carried[2:columns + 2] += 1 / 16 * passed  # below-right
    return aimed


def aimed_levels(levels: np.ndarray) -> np.ndarray:
    """The levels a phantom is made to render: :func:`error_diffused`, with the brightest pixel at 255.

    The display divides by the B-scan's own maximum, so the scanner writes
    255 at its brightest pixel whatever the rest: a target whose highest
    level is below 255 (a real scan need not reach it) cannot be rendered
    there, and its brightest pixel (the first in row-major order) is aimed
    at 255 instead.
    """
    aimed = error_diffused(levels)
    if aimed.max() < 255:
        aimed[np.unravel_index(np.argmax(levels), aimed.shape)] = 255
    return aimed


@dataclass(frozen=True)
class Ceiling:
    """What a target allows, measured before inverting it (module docstring).

    Attributes
    ----------
    writable_share : float
        Share of the target's pixels at levels the scanner writes.
    nearest_score : float
        Exact score of :func:`nearest_writable`'s image against the target.
    diffused_score : float
        Exact score of :func:`error_diffused`'s image against the target.
    """

    writable_share: float
    nearest_score: float
    diffused_score: float

    def as_dict(self) -> dict:
        return asdict(self)


def measure_ceiling(levels: np.ndarray, score) -> Ceiling:
    """The :class:`Ceiling` of target ``levels``; ``score(levels) -> float`` is the exact score against the target.

    A target with every pixel writable is its own best image: both scores
    are then 1.0 without being computed.
    """
    share = writable_share(levels)
    if share == 1.0:
        return Ceiling(1.0, 1.0, 1.0)
    return Ceiling(share, float(score(nearest_writable(levels))), float(score(error_diffused(levels))))


__all__ = ["WRITABLE", "Ceiling", "aimed_levels", "error_diffused", "measure_ceiling", "nearest_writable",
           "writable_share"]
