"""Accelerated projections onto the levels' intervals (host/stage1/projections.py), on the NumPy backend."""


import numpy as np
import pytest

from octcl.host.stage1.operator import FieldOperator
from octcl.host.stage1.projections import retrieve_field
from octcl.render import Rendering
from conftest import scanner_made_target


# --------------------------------------------------------------- retrieval


def test_retrieve_field_matches_most_levels_of_a_scanner_made_target():
    """300 projections from the regularised start put most pixels at their level."""
    levels = scanner_made_target(0)
    fit = retrieve_field(levels)
    a_scans = FieldOperator().apply(fit.field)
    assert fit.iterations == 300 and fit.clock_steps == 0
    assert np.abs(a_scans).max() == pytest.approx(1.0)
    assert fit.identical == pytest.approx(np.mean(Rendering.from_a_scans(a_scans).levels == levels))
    start = retrieve_field(levels, iterations=1)
    assert fit.identical > 0.9 and fit.identical > start.identical + 0.1


def test_retrieve_field_stays_bounded_on_an_official_scan(official_data):
    """At a full step (α = 1) the momentum iteration diverges on Uniform A (the field grows to ~1e93 and
    35 % of the levels are the target's); at α = 0.8 it converges (56 %), the field within a few times
    the rendering's norm."""
    from octcl.host.pipeline.target import read_target

    fit = retrieve_field(read_target(official_data / "Scan_Exp1_Uniform_A.png"))
    a_scans = FieldOperator().apply(fit.field)
    assert np.linalg.norm(fit.field) < 20 * np.linalg.norm(a_scans)
    assert fit.identical > 0.5


@pytest.mark.clock
def test_retrieve_field_is_deterministic_and_stops_at_its_budget():
    levels = scanner_made_target(1)
    first, second = retrieve_field(levels, iterations=20), retrieve_field(levels, iterations=20)
    np.testing.assert_array_equal(first.field, second.field)
    calls = []
    cut = retrieve_field(levels, iterations=10_000, time_budget_s=0.2, progress=lambda i, n: calls.append((i, n)))
    assert cut.clock_steps == 1 and 1 <= cut.iterations < 10_000 and calls[-1] == (cut.iterations, 10_000)
    with pytest.raises(ValueError, match="iterations"):
        retrieve_field(levels, iterations=0)
    with pytest.raises(ValueError, match="scanner makes"):
        retrieve_field(levels[:10])
