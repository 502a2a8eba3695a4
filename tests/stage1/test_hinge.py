"""The hinge fit (host/stage1/hinge.py): L-BFGS until every pixel renders at its aimed level, on the NumPy backend."""


import time

import numpy as np
import pytest

from octcl.host.stage1.operator import FieldOperator
from octcl.host.stage1.hinge import LEVEL_CHECK_EVERY, LEVEL_FIT_ITERATIONS, LevelStop, fit_levels
from octcl.render import Rendering
from conftest import random_field, SMALL_SCANNER as SMALL


# --------------------------------------------------------------- retrieval


def test_fit_levels_puts_every_pixel_at_its_level_and_the_brightest_at_one():
    """A field's own levels, from that field disturbed (a fifth of the pixels off their level): the hinge fit
    puts every pixel back at its level, its brightest pixel at |A| = 1 so that the display's normalisation
    holds, and stops as soon as the levels are all there."""
    operator = FieldOperator(SMALL)
    truth = random_field(SMALL, 5)
    levels = Rendering.from_a_scans(operator.apply(truth)).levels
    rng = np.random.default_rng(6)
    start = truth * (1 + 0.05 * (rng.normal(size=truth.shape) + 1j * rng.normal(size=truth.shape)))
    assert np.mean(Rendering.from_a_scans(operator.apply(start)).levels == levels) < 0.8
    fit = fit_levels(start, levels, SMALL)
    a_scans = operator.apply(fit.field)
    assert fit.identical == 1.0 and np.array_equal(Rendering.from_a_scans(a_scans).levels, levels)
    assert np.abs(a_scans).max() == pytest.approx(1.0)
    assert fit.iterations < LEVEL_FIT_ITERATIONS and fit.iterations % LEVEL_CHECK_EVERY == 0
    assert fit.clock_steps == 0
    cut = fit_levels(start, levels, SMALL, iterations=10_000, time_budget_s=0.0)
    assert cut.clock_steps == 1 and cut.iterations == 1
    with pytest.raises(ValueError, match="iterations"):
        fit_levels(start, levels, SMALL, iterations=0)


def test_the_level_check_asks_the_exact_levels_only_where_its_screen_lets_it():
    """A check whose screen says no leaves the exact levels out; one it lets through ends the fit only where
    the exact levels are the aim."""
    aim, off = np.zeros((2, 3), np.uint8), np.ones((2, 3), np.uint8)
    asked, screened = [], iter([False, True, True])
    stop = LevelStop(aim, lambda field: asked.append(field) or field, time.perf_counter(), None,
                     lambda field, aimed: next(screened))
    for _ in range(2 * LEVEL_CHECK_EVERY):
        stop(off)  # the screen turns the first check away; the exact levels turn the second
    assert len(asked) == 1 and stop.taken == 2 * LEVEL_CHECK_EVERY
    for _ in range(LEVEL_CHECK_EVERY - 1):
        stop(aim)
    with pytest.raises(StopIteration):
        stop(aim)
    assert len(asked) == 2 and stop.taken == 3 * LEVEL_CHECK_EVERY
