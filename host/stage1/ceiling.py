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

:func:`measure_ceiling` reports, for a target, the share of its pixels at
writable levels and the exact score of :func:`error_diffused`'s image, the
levels the linear regime aims at before the aim step: no phantom renders
the target better than its writable pixels allow, and that image is what
"at the ceiling" looks like. :func:`nearest_writable`'s image scored lower
on every real-like target measured (orange.png 0.9998906 against 0.9998953,
``octcl invert --json``) and is not scored by a run: an exact score is
0.2 s of a 5 s default run on two cores.
"""

from __future__ import annotations

import functools
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
    writable: unwritable levels are at least four apart), to the side of
    the error e it carries (the nearer writable level where e = 0), and
    passes on e − (its change): 7/16 to the right, 3/16, 5/16 and 1/16
    below-left, below and below-right. A writable pixel passes on what it
    received. Rows are visited left to right, top to bottom. A plain loop
    over Python floats, where a vectorised recurrence between unwritable
    pixels needs ``scipy.signal.lfilter``: ``python -c "import scipy.signal"``
    takes 0.9 s on two cores of an AMD EPYC (``import numpy`` 0.09 s), on
    every command's start. The loop took 0.17 s on two first-generation Zen
    cores, and a run asks for the same target's image twice (its aim, then
    its ceiling): the last two are kept (a copy is returned).
    """
    levels = np.asarray(levels, np.uint8)
    return _error_diffused(levels.tobytes(), levels.shape).copy()


@functools.lru_cache(maxsize=2)
def _error_diffused(data: bytes, shape: tuple) -> np.ndarray:
    levels = np.frombuffer(data, np.uint8).reshape(shape)
    aimed = levels.copy()
    writable = WRITABLE.tolist()
    nearer_side = np.sign(GREY_LUT.astype(np.int16) - np.arange(256)).tolist()
    columns = levels.shape[1]
    received = [0.0] * (columns + 2)  # what the rows above diffused onto this row, one padding column each side
    for row, line in enumerate(levels.tolist()):
        below = [0.0] * (columns + 2)
        carried = 0.0
        for column, level in enumerate(line):
            e = received[column + 1] + 7 / 16 * carried
            if not writable[level]:
                side = (1 if e > 0 else -1) if e != 0 else nearer_side[level]
                aimed[row, column] = level + side
                e -= side
            carried = e
            below[column] += 3 / 16 * e
            below[column + 1] += 5 / 16 * e
            below[column + 2] += 1 / 16 * e
        received = below
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
    diffused_score : float or None
        Exact score of :func:`error_diffused`'s image against the target; None where the caller's ``score`` left
        it out (a budget it would overrun).
    """

    writable_share: float
    diffused_score: float | None

    def as_dict(self) -> dict:
        return asdict(self)


def ceiling_image(levels: np.ndarray) -> np.ndarray | None:
    """The image :func:`measure_ceiling` scores for target ``levels`` (:func:`error_diffused`'s), or None for a
    target with every pixel writable, which is its own best image and is not scored."""
    return None if writable_share(levels) == 1.0 else error_diffused(levels)


def measure_ceiling(levels: np.ndarray, score) -> Ceiling:
    """The :class:`Ceiling` of target ``levels``; ``score(levels) -> float | None`` is the exact score against the
    target, or None for an image it leaves out.

    A target with every pixel writable is its own best image: its score is
    then 1.0 without being computed.
    """
    image = ceiling_image(levels)
    if image is None:
        return Ceiling(1.0, 1.0)
    diffused = score(image)
    return Ceiling(writable_share(levels), None if diffused is None else float(diffused))


__all__ = ["WRITABLE", "Ceiling", "aimed_levels", "ceiling_image", "error_diffused", "measure_ceiling", "nearest_writable",
           "writable_share"]
