"""Stage 1 as data: steps, schedules, and the solve that runs them (host/stage1/solve.py)."""

import numpy as np
import pytest

from octcl import _reference as ref
from octcl.config import ScannerConfig
from octcl.host.stage1.backend import NumpyBackend
from octcl.host.stage1.solve import FieldSchedule, FieldSolve, FieldStep, default_schedules, display, hinge, project
from octcl.host.stage1.hinge import fit_levels
from octcl.host.stage1.projections import retrieve_field
from octcl.phantom import Phantom

#: A small scanner (32 rows, 48 A-scans of 6 µm): each step in milliseconds.
SMALL = ScannerConfig(depth_pixels=32, a_scans=48, xmax_um=288.0)


@pytest.fixture(scope="module")
def small_levels():
    """The reference scanner's levels of a random phantom on the small grid: a target every step can reach."""
    rng = np.random.default_rng(4)
    n = 600
    phantom = Phantom(rng.uniform(-140, 140, n), rng.uniform(-3, 3, n), rng.uniform(0, SMALL.depth_pixels * 6.0, n),
                      rng.lognormal(-6, 1.5, n))
    return ref.render_reference(phantom, SMALL).levels


def test_a_schedule_is_composed_parsed_and_written_back():
    schedule = display(150) + project(100) + hinge(200)
    assert schedule == FieldSchedule.parse("display:150, project:100,hinge:200")
    assert str(schedule) == "display:150,project:100,hinge:200"
    assert schedule.iterations == 450 and schedule.display_iterations == 150
    assert (display(10) + (project(5) + hinge(3))).steps == (display(10), project(5), hinge(3))
    first, second = default_schedules(150)
    assert str(first) == "display:150,project:50,hinge:200,aim:4" and second.display_iterations == 75
    assert [str(schedule) for schedule in default_schedules(150, aim_rounds=0)] == [
        "display:150,project:50,hinge:200", "display:75,project:50,hinge:200"]  # the tissue regime's


@pytest.mark.parametrize("text, message", [("display", "NAME:ITERATIONS"), ("raar:20", "unknown stage-1 step"),
                                           ("display:0", "≥ 1"), ("project:-3", "NAME:ITERATIONS"),
                                           ("", "NAME:ITERATIONS")])
def test_a_bad_schedule_is_refused_naming_the_part(text, message):
    with pytest.raises(ValueError, match=message):
        FieldSchedule.parse(text)


def test_a_step_with_a_bad_share_is_refused():
    with pytest.raises(ValueError, match="share"):
        FieldStep("hinge", 10, share=1.5)


def test_the_steps_run_in_order_each_from_the_field_the_last_left(small_levels):
    """project then hinge: the same field as calling them in turn."""
    solve = FieldSolve(small_levels, small_levels, NumpyBackend(SMALL, threads=1)).run(project(30) + hinge(20))
    projected = retrieve_field(small_levels, SMALL, iterations=30)
    by_hand = fit_levels(projected.field, small_levels, SMALL, iterations=20)
    np.testing.assert_array_equal(solve.field, by_hand.field)
    assert [record.name for record in solve.history] == ["project", "hinge"]
    assert solve.history[0].identical == pytest.approx(projected.identical)


def test_a_step_that_loses_pixels_leaves_the_best_field_and_a_solve_stops_at_the_aim(small_levels):
    solve = FieldSolve(small_levels, small_levels, NumpyBackend(SMALL, threads=1)).run(project(60) + hinge(200))
    assert solve.identical == solve.best_identical == 1.0  # the small target is reached
    reached = solve.field.copy()
    # A short display fit from an exact field loses pixels: the best field stays. Nothing after the aim is
    # reached runs.
    solve.identical = 0.999  # as if one pixel were off, so that the display fit runs
    solve.run(FieldSchedule((display(3),)))
    assert solve.history[2].name == "display" and not solve.history[2].kept and solve.history[2].identical < 0.999
    np.testing.assert_array_equal(solve.best_field, reached)
    assert solve.best_identical == 1.0 and solve.identical < 0.999
    again = FieldSolve(small_levels, small_levels, NumpyBackend(SMALL, threads=1)).run(project(60) + hinge(200) + display(5))
    assert [record.name for record in again.history] == ["project", "hinge"]


@pytest.mark.clock
def test_under_a_budget_each_step_gets_its_share(small_levels):
    """A budget far too small for the steps: the display fit and the projections are cut by the clock (the
    hinge fit may reach the aim first), and the whole ends near the budget."""
    import time

    solve = FieldSolve(small_levels, small_levels, NumpyBackend(SMALL, threads=1))
    start = time.perf_counter()
    solve.run(display(10**5) + project(10**5) + hinge(10**5), time_budget_s=0.3)
    assert time.perf_counter() - start < 0.3 + 0.2
    assert [record.clock_steps for record in solve.history[:2]] == [1, 1]
    assert all(record.iterations < 10**5 for record in solve.history)


def test_the_aim_step_needs_a_score_and_a_field_at_its_aim(small_levels):
    from octcl.host.stage1.solve import aim

    plain = small_levels.copy()
    plain[::3, ::5] = 37  # unwritable: something to move
    with pytest.raises(ValueError, match="exact score"):
        FieldSolve(plain, plain, NumpyBackend(SMALL, threads=1)).run(project(2) + aim(3))

    def no_score(_):
        raise AssertionError("the field is not at its aim yet: nothing to score")

    solve = FieldSolve(plain, plain, NumpyBackend(SMALL, threads=1), score=no_score).run(project(2) + aim(3))
    assert solve.best_identical < 1.0 and solve.history[-1].name == "aim" and solve.history[-1].iterations == 0


class _KeptMoves:
    """An aim search whose rounds keep the given aims in turn (the search itself: tests/stage1/test_aim.py)."""

    def __init__(self, aims):
        self.aims, self.done = list(aims), False

    def rounds(self, aim, rounds, deadline=None, progress=None):
        from octcl.host.stage1.aim import AimRounds

        kept, self.aims, self.done = [aim, *self.aims], [], True
        return AimRounds(kept, len(kept) - 1, 0)


def _moved_aims(levels, count):
    """``count`` aims, each moving 3 more mid-grey pixels of ``levels`` one writable level up."""
    from octcl.host.stage1.ceiling import WRITABLE

    writable = np.flatnonzero(WRITABLE)
    up = {int(level): int(writable[np.searchsorted(writable, level, side="right")]) for level in writable[:-1]}
    candidates = np.flatnonzero((levels > 100) & (levels < 200))
    aims, aim = [], levels.copy()
    for round_ in range(count):
        for pixel in candidates[3 * round_:3 * round_ + 3]:
            aim.flat[pixel] = up[int(aim.flat[pixel])]
        aims.append(aim.copy())
    return aims


def test_the_field_follows_the_last_aim_the_rounds_kept(small_levels):
    from octcl.host.stage1.solve import aim

    solve = FieldSolve(small_levels, small_levels, NumpyBackend(SMALL, threads=1), score=lambda levels: 0.0)
    solve.run(project(60) + hinge(200))
    assert solve.best_identical == 1.0
    moves = _moved_aims(small_levels, 2)
    solve.aim_search = _KeptMoves(moves)
    solve.run(FieldSchedule((aim(5),)))
    assert solve.history[-1].iterations == 2
    np.testing.assert_array_equal(solve.aim, moves[-1])
    assert solve.share_at_aim(solve.field) == solve.best_identical == 1.0


def test_where_the_field_cannot_follow_the_last_aim_an_earlier_one_is_kept(small_levels, monkeypatch):
    from octcl.host.stage1.solve import aim

    solve = FieldSolve(small_levels, small_levels, NumpyBackend(SMALL, threads=1), score=lambda levels: 0.0)
    solve.run(project(60) + hinge(200))
    moves = _moved_aims(small_levels, 3)
    solve.aim_search = _KeptMoves(moves)
    follows = solve.reach
    tried = []

    def reach_all_but_the_last(levels, field):
        tried.append(levels)
        return None if np.array_equal(levels, moves[-1]) else follows(levels, field)

    monkeypatch.setattr(solve, "reach", reach_all_but_the_last)
    solve.run(FieldSchedule((aim(5),)))
    assert len(tried) == 2
    np.testing.assert_array_equal(solve.aim, moves[1])
    assert solve.share_at_aim(solve.field) == 1.0
    # None reached: the aim and the field stay where the rounds started.
    start_field = solve.field.copy()
    start_aim = solve.aim.copy()
    solve.aim_search = _KeptMoves(_moved_aims(start_aim, 2))
    monkeypatch.setattr(solve, "reach", lambda levels, field: None)
    solve.run(FieldSchedule((aim(5),)))
    np.testing.assert_array_equal(solve.aim, start_aim)
    np.testing.assert_array_equal(solve.field, start_field)
