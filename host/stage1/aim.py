"""Levels chosen for the score: which side of each unwritable level a phantom renders.

Where the target has a level the scanner never writes (:mod:`octcl.host.stage1.ceiling`),
a phantom renders L − 1 or L + 1. Error diffusion chooses the sides so that
the local mean of the levels is kept (:func:`octcl.host.stage1.ceiling.error_diffused`,
the start). :class:`AimSearch` then moves sides where the exact score
(:class:`octcl.host.stage3.loss.ExactScore`) gains, guided by the gradient of
the differentiable twin of one of the score's terms, the SC map's LPIPS,
through the straight-through quantiser (:class:`octcl.host.stage3.loss.DisplayLoss`
with :data:`SCORE_WEIGHTS`).

A round: with g = ∂loss/∂D at the display D(a₀) of the search's first aim
a₀ (each level at the centre of its display interval), the change of loss
from moving pixel p to its other side a'_p is predicted as
g_p·(D(a'_p) − D(a₀_p)); the :data:`BATCH` pixels of most negative prediction,
each more than :data:`SPACING_PX` from the others taken and from every
pixel moved before, move together, and the move is kept only if the exact
score of the new levels is higher; a moved pixel is not moved again. The
score is not additive over pixels (MS-SSIM and LPIPS see neighbourhoods,
and the speckle-contrast maps the local spread), so the prediction holds
for a few pixels at a time, and for pixels apart: on orange.png the first
16 moved 8.0e−6 nearest the top of the ranking, 10.5e−6 at least 16 pixels
apart; on a plainly quantised skin rendering (seed 5) 2.9e−6 and 7.6e−6
(spacings of 0, 4, 8, 16 and 32 pixels measured; 32 lost on orange).

What the gradient misses: the score sees 8-bit maps, the loss continuous
ones. Moved one at a time from the error-diffused aim (``scripts/bench_aim.py
--singles 4``, docs/bench/aim_singles), the first four pixels of the first
round, all predicted to gain, changed the score by −8.2e−6 to +8.1e−7 on
orange.png and plainly quantised skins 0 and 3, and 4 of the 12 gained.
Each move changed 1 − LPIPS of the SC and RSC maps by up to 3.2e−5 either
way, their MS-SSIM by up to 5.7e−6, the Struct terms by at most 4e−7: the
speckle-contrast maps' 8-bit levels over each window around the pixel move
or do not, which the slope of the continuous maps does not tell.

Which terms propose. Until octcl 0.8.12 the proposal's loss held every term
the loss has of the score (MS-SSIM of the Struct and OAC maps, LPIPS of all
four); since the speckle-contrast terms are what a move changes, the loss
is now the SC map's LPIPS alone: its map needs the intensity only, and one
AlexNet pass instead of four. On nine real-like targets (``scripts/bench_aim.py
--rounds 4``: orange.png, it mirrored, it through a gamma of 0.9, plainly
quantised skin renderings, seeds 0–5; two Zen 4 cores) the gradient took
0.12 s (median) against 0.40 s and the first round 0.44 s against 0.85 s;
the searches gained 1.04e−5, 1.34e−5, 0 and 7.3e−6 on orange.png, it
mirrored, through the gamma and seed 5, against 1.08e−5, 1.38e−5, 0 and
7.6e−6, and nothing on the other five either way. The RSC map's LPIPS
alone, and the two together, gained as much (4.6e−6 on seed 5 with RSC
alone; the pair 0.22 s a gradient). In a batch of 20 plainly quantised
skins (``scripts/bench_batch.py --scans 20 --deadline --plain --modes
local:2x1``) the scans' CPU time fell from 115.1 to 97.0 s and the
throughput rose from 1067 to 1247 scans an hour; 5 scans' scores moved,
by −1.6e−6 to +2.3e−6 (docs/benchmarks.md, "The aim's proposal from the SC
map").

Every round moves :data:`BATCH` pixels, and the search stops at the first
round the exact score rejects. Until octcl 0.8.5 a rejected round halved
the batch and the search stopped after two rejections in a row: of nine
real-like targets (``scripts/bench_aim.py --rounds 8``: orange.png, it
mirrored left to right, it through a gamma of 0.9, plainly quantised skin
renderings, seeds 0–5; two first-generation EPYC cores) a halved batch
gained twice, 2.3e−7 and 2.8e−7, and every search paid one exact score
(0.45–0.48 s) for its second rejection; the gains of the first kept
rounds were 6.1e−6 to 1.3e−5. The search's rounds, per target, are in
docs/benchmarks.md ("The aim stops at its first rejected round").

One gradient serves the whole search. A gradient at each kept aim (octcl
0.8.0) cost 0.75–0.8 s a kept round on two cores, more than the round's
exact score (0.45 s), and bought little: pixels away from those moved keep
their prediction, and those near them are left out. Measured end to end
(``scripts/bench_versions.py``, docs/benchmarks.md, "The aim's one
gradient", two first-generation EPYC cores): orange.png 14.08 → 12.85 s
of wall time at 0.9999070 → 0.9999061; a plainly quantised skin rendering
(seed 5) 16.23 → 14.43 s at 0.9998879 → 0.9998862; on five other skin
renderings every round was rejected either way, same scores. A search that
gains nothing costs the loss's construction (0.3 s there), its gradient
(0.8 s) and two exact scores (0.45 s each).

The rounds judge levels only: the field follows the aim the search ends
at once, after the last round (:meth:`octcl.host.stage1.solve.FieldSolve.reach`),
and an earlier kept aim where it cannot. A hinge fit after each kept move
took 60–80 L-BFGS iterations (0.6–1.4 s on two cores, orange.png) where
projections then a hinge fit take 20 and 10 (0.2 s) once.

Only unwritable pixels move: a writable pixel's own level is the best side
there is. A target the scanner could have written has none, and the search
costs nothing there.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ...torch_import import torch_import_s
from .ceiling import WRITABLE
from .levels import display_of_level
from ..stage3.schedule import LossWeights

#: The loss whose gradient proposes moves: LPIPS of the SC map alone, the score's term that a move changes most
#: (module docstring, "Which terms propose").
SCORE_WEIGHTS = LossWeights(pixel=0.0, sc_l1=0.0, oac_l1=0.0, oac_lpips=0.0, oac_msssim=0.0, struct_msssim=0.0,
                            struct_lpips=0.0, sc_lpips=1.0, rsc_lpips=0.0)
#: Pixels a round moves together (module docstring).
BATCH = 16
#: Least distance in pixels (along rows or columns) between two pixels a round moves (module docstring).
SPACING_PX = 16
#: Seconds of a search's first round beyond torch's import (:func:`octcl.torch_import.torch_import_s`,
#: known per machine), before it has a pace: the loss's LPIPS network and target maps, a gradient and an exact
#: score (2–3 s on two cores with the import's 1.0–1.2 s).
AIM_FIRST_ROUND_S = 1.5


@dataclass
class AimRounds:
    """What :meth:`AimSearch.rounds` did.

    Attributes
    ----------
    kept : list of ndarray of uint8
        The aims the rounds kept, in order, the first the aim they started from.
    taken : int
        Rounds run.
    clock_steps : int
        1 where the deadline left rounds out, else 0.
    """

    kept: list
    taken: int
    clock_steps: int


@dataclass
class AimSearch:
    """Moves of unwritable pixels to their other side, kept where the exact score gains (module docstring).

    Parameters
    ----------
    levels : ndarray of uint8, (Nz, Nx)
        The target's levels.
    score : callable
        ``score(levels) -> float``, the exact score against the target.
    """

    levels: np.ndarray
    score: object
    rejected: bool = False

    def __post_init__(self):
        self.movable = ~WRITABLE[self.levels]  # only the target's unwritable pixels move
        self._blocked = np.zeros(self.levels.shape, bool)  # within SPACING_PX of a pixel a kept move moved
        self._change = None  # the predicted loss change per pixel (flat), from the one gradient

    @property
    def done(self) -> bool:
        return self.rejected or not self.movable.any()

    def _other_side(self, aim: np.ndarray) -> np.ndarray:
        """Each pixel's level on the other side of its target level: L ± 1 ↔ L ∓ 1."""
        return (2 * self.levels.astype(np.int16) - aim).astype(np.uint8)

    def predicted_change(self, aim: np.ndarray) -> np.ndarray:
        """g_p·(D(a'_p) − D(a_p)) for every pixel at the first aim this is asked for, 0 where it may not move
        (module docstring): computed once."""
        if self._change is None:
            from ..stage3.loss import DisplayLoss, scan_of_levels

            other = self._other_side(aim)
            display_of = display_of_level()
            gradient = DisplayLoss(scan_of_levels(self.levels), SCORE_WEIGHTS)(display_of[aim]).grad_display
            self._change = np.where(self.movable, gradient * (display_of[other] - display_of[aim]), 0.0).ravel()
        return self._change

    def proposal(self, aim: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``aim`` with up to :data:`BATCH` pixels on their other side, and their flat indices: in order of most
        negative predicted change, each more than :data:`SPACING_PX` from those taken before it and from every
        pixel a kept move moved."""
        change = np.where(self._blocked.ravel(), 0.0, self.predicted_change(aim))
        order = np.argsort(change, kind="stable")
        order = order[change[order] < 0]
        rows, columns = np.divmod(order, aim.shape[1])
        taken = []
        for index in range(order.size):
            if len(taken) == BATCH:
                break
            if all(max(abs(rows[index] - rows[t]), abs(columns[index] - columns[t])) > SPACING_PX for t in taken):
                taken.append(index)
        picks = order[taken]
        proposed = aim.copy()
        proposed.flat[picks] = self._other_side(aim).flat[picks]
        return proposed, picks

    def step(self, aim: np.ndarray, aim_score: float) -> tuple[np.ndarray, float]:
        """One round from ``aim`` (whose exact score is ``aim_score``): the aim kept and its score.

        The aim kept is the proposal where its exact score is higher, else ``aim`` itself.
        """
        proposed, picks = self.proposal(aim)
        if not picks.size:  # nothing predicted to gain
            self.rejected = True
            return aim, aim_score
        proposed_score = float(self.score(proposed))
        if proposed_score > aim_score:
            # A moved pixel is decided, and the gradient no longer predicts its neighbours' moves.
            for row, column in zip(*np.divmod(picks, aim.shape[1])):
                self._blocked[max(0, row - SPACING_PX):row + SPACING_PX + 1,
                              max(0, column - SPACING_PX):column + SPACING_PX + 1] = True
            return proposed, proposed_score
        self.rejected = True
        return aim, aim_score

    def rounds(self, aim: np.ndarray, rounds: int, deadline: float | None = None, progress=None) -> AimRounds:
        """Up to ``rounds`` rounds from ``aim`` until the search is done.

        With a ``deadline`` (:func:`time.perf_counter`), a round starts only
        while it would end by then at the rounds' measured pace (the first:
        torch's import where it is still to come and
        :data:`AIM_FIRST_ROUND_S`). ``progress(taken, rounds)`` after each.
        """
        start, kept, aim_score, taken, clock_steps = time.perf_counter(), [aim], None, 0, 0
        while taken < rounds and not self.done:
            now = time.perf_counter()
            pace = (now - start) / taken if taken else torch_import_s() + AIM_FIRST_ROUND_S
            if deadline is not None and now + pace > deadline:
                clock_steps = 1
                break
            if aim_score is None:
                aim_score = float(self.score(aim))
            aimed, aim_score = self.step(kept[-1], aim_score)
            if aimed is not kept[-1]:
                kept.append(aimed)
            taken += 1
            if progress is not None:
                progress(taken, rounds)
        return AimRounds(kept, taken, clock_steps)


__all__ = ["AIM_FIRST_ROUND_S", "AimRounds", "AimSearch", "BATCH", "SCORE_WEIGHTS", "SPACING_PX"]
