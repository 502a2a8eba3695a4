"""Levels chosen for the score (host/stage1/aim.py): moves of unwritable pixels, kept where the score gains."""

import itertools

import numpy as np
import pytest

from octcl._io import GREY_LUT
from octcl.host.stage1.aim import BATCH, SPACING_PX, AimSearch
from octcl.host.stage1.ceiling import WRITABLE, error_diffused


def test_a_target_the_scanner_could_write_has_nothing_to_move():
    def no_score(_):
        raise AssertionError("nothing to move: nothing to score")

    levels = GREY_LUT[np.random.default_rng(0).integers(0, 256, (256, 512))].astype(np.uint8)
    assert AimSearch(levels, no_score).done


@pytest.fixture(scope="module")
def target():
    """A smooth full-size target with a tenth of its pixels at unwritable levels."""
    rng = np.random.default_rng(1)
    rows = np.linspace(40, 220, 256)[:, None] + rng.normal(0, 8, (256, 512))
    levels = np.clip(rows, 0, 255).astype(np.uint8)
    unwritable = np.flatnonzero(~WRITABLE)
    picks = rng.random(levels.shape) < 0.1
    levels[picks] = rng.choice(unwritable[(unwritable > 30) & (unwritable < 240)], picks.sum())
    return levels


def test_a_move_that_gains_is_kept(target):
    gains = itertools.count(1)
    search = AimSearch(target, lambda levels: float(next(gains)))
    aim = error_diffused(target)
    moved, score = search.step(aim, 0.0)
    assert score == 1.0
    changed = moved != aim
    assert 0 < changed.sum() <= BATCH
    assert not WRITABLE[target[changed]].any()  # only unwritable pixels move, each to its other side
    assert np.array_equal(moved[changed].astype(int) + aim[changed], 2 * target[changed].astype(int))
    rows, columns = np.nonzero(changed)  # pixels a round moves are apart: their effects on the score add up
    apart = np.maximum(abs(rows[:, None] - rows[None]), abs(columns[:, None] - columns[None]))
    assert (apart[~np.eye(rows.size, dtype=bool)] > SPACING_PX).all()
    # A moved pixel is decided: the next move leaves it and its neighbourhood where they are (the one gradient
    # no longer predicts what moving them would do).
    again, _ = search.step(moved, score)
    assert np.array_equal(again[changed], moved[changed]) and not np.array_equal(again, moved)
    later_rows, later_columns = np.nonzero(again != moved)
    apart = np.maximum(abs(later_rows[:, None] - rows[None]), abs(later_columns[:, None] - columns[None]))
    assert (apart > SPACING_PX).all()


def test_one_gradient_serves_the_whole_search(target, monkeypatch):
    from octcl.host.stage3 import loss

    built = []

    class Counted(loss.DisplayLoss):
        def __call__(self, display, lpips="compute"):
            built.append(display)
            return super().__call__(display, lpips)

    monkeypatch.setattr(loss, "DisplayLoss", Counted)
    scores = iter([2.0, 3.0, 4.0, 0.0])  # kept three times, then rejected: the search stops
    search = AimSearch(target, lambda levels: next(scores))
    aim, score = error_diffused(target), 1.0
    while not search.done:
        aim, score = search.step(aim, score)
    assert score == 4.0 and len(built) == 1


def test_a_move_that_does_not_gain_is_refused_and_ends_the_search(target):
    search = AimSearch(target, lambda levels: 1.0)
    aim = error_diffused(target)
    kept, score = search.step(aim, 1.0)
    assert score == 1.0 and kept is aim and search.done


def test_rounds_run_until_the_first_rejected_one_and_keep_each_gain(target):
    scores = iter([1.0, 2.0, 3.0, 0.0])  # the start's score, kept twice, then rejected: the search stops
    search = AimSearch(target, lambda levels: next(scores))
    start = error_diffused(target)
    done = search.rounds(start, rounds=10)
    assert done.taken == 3 and done.clock_steps == 0 and search.done
    assert len(done.kept) == 3 and done.kept[0] is start
    for before, after in zip(done.kept, done.kept[1:]):
        assert 0 < np.count_nonzero(before != after) <= BATCH


@pytest.mark.clock
def test_a_deadline_the_first_round_cannot_meet_leaves_the_rounds_out(target):
    import time

    def no_score(_):
        raise AssertionError("no round: nothing to score")

    done = AimSearch(target, no_score).rounds(error_diffused(target), rounds=4, deadline=time.perf_counter())
    assert done.taken == 0 and done.clock_steps == 1 and len(done.kept) == 1
