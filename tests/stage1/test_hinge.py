"""The hinge fit (host/stage1/hinge.py): L-BFGS until every pixel renders at its aimed level, on the NumPy backend."""


import numpy as np
import pytest

from octcl.host.stage1.operator import FieldOperator
from octcl.host.stage1.hinge import LEVEL_CHECK_EVERY, LEVEL_FIT_ITERATIONS, fit_levels
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
