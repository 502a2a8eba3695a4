"""The display fit on the NumPy backend (host/stage1/display.py)."""

import os
import time

import numpy as np
import pytest

from octcl._io import read_scan
from octcl.config import ScannerConfig
from octcl.host.stage1.display import fit_field
from octcl.host.stage1.levels import target_levels
from octcl.host.stage1.operator import FieldOperator

#: A small scanner (32 rows, 16 A-scans of 6 µm) for the reference comparisons.
SMALL = ScannerConfig(depth_pixels=32, a_scans=16, xmax_um=96.0)


@pytest.fixture(scope="module")
def uniform_levels(official_data):
    return target_levels(read_scan(official_data / "Scan_Exp1_Uniform_A.png"))


def test_fit_field_reduces_the_loss(uniform_levels):
    calls = []
    fit = fit_field(uniform_levels, iterations=20, time_budget_s=60, threads=1,
                    progress=lambda i, n, loss: calls.append((i, n, loss)))
    assert fit.iterations == 20 and len(fit.losses) == 20 and len(calls) == 20
    assert calls[-1][:2] == (20, 20)
    assert fit.losses[-1] < 0.8 * fit.losses[0]
    assert fit.field.shape == (256, 512) and fit.field.dtype == np.complex128
    assert np.abs(FieldOperator().apply(fit.field)).max() == pytest.approx(1.0)
    assert np.abs(fit.display - fit.target_display).mean() < 0.02


@pytest.mark.clock
def test_fit_field_respects_the_time_budget(uniform_levels):
    start = time.perf_counter()
    fit = fit_field(uniform_levels, iterations=10**6, time_budget_s=1.0, threads=1)
    elapsed = time.perf_counter() - start
    assert 1 <= fit.iterations < 10**6
    assert fit.seconds <= elapsed
    # At most one step past the budget, then the final rendering.
    assert elapsed < 1.0 + 0.5


@pytest.mark.clock
def test_fit_field_times_its_thread_choices(uniform_levels):
    import torch

    before = torch.get_num_threads()
    fit = fit_field(uniform_levels, iterations=6, time_budget_s=60)
    assert fit.iterations == 6
    assert 1 <= fit.threads <= max(1, len(os.sched_getaffinity(0)))
    assert torch.get_num_threads() == before


@pytest.mark.parametrize("level", [0, 255])
def test_fit_field_of_a_flat_target_is_finite(level):
    fit = fit_field(np.full(SMALL.shape, level, dtype=np.uint8), SMALL, iterations=10, threads=1)
    assert np.isfinite(fit.field).all() and np.isfinite(fit.losses).all()
    assert np.isfinite(fit.display).all()


def test_fit_field_refuses_a_target_of_the_wrong_size():
    with pytest.raises(ValueError, match="256x512"):
        fit_field(np.zeros((10, 20), dtype=np.uint8))


@pytest.mark.clock
def test_fit_field_without_a_budget_takes_no_decision_from_the_clock(uniform_levels, slow_clock):
    import octcl.host.stage1.display as field_module

    fits = [fit_field(uniform_levels, iterations=8, time_budget_s=None, threads=1)]
    slow_clock(field_module)
    fits.append(fit_field(uniform_levels, iterations=8, time_budget_s=None, threads=1))
    assert [fit.iterations for fit in fits] == [8, 8]
    np.testing.assert_array_equal(fits[0].field, fits[1].field)
    np.testing.assert_array_equal(fits[0].losses, fits[1].losses)
    # With a budget the same clock ends the fit before its first step.
    assert fit_field(uniform_levels, iterations=8, time_budget_s=60.0, threads=1).iterations == 0


def test_fit_field_is_the_same_at_every_thread_count(uniform_levels):
    """Each 1-D FFT is one thread's and the sums are NumPy's own: 1 and 2 threads give the same bits."""
    fits = [fit_field(uniform_levels, iterations=30, time_budget_s=None, threads=threads) for threads in (1, 2)]
    np.testing.assert_array_equal(fits[0].field, fits[1].field)
    np.testing.assert_array_equal(fits[0].losses, fits[1].losses)


@pytest.mark.clock
def test_fit_field_ahead_of_its_clock_takes_no_decision_from_it(uniform_levels):
    """A budget the steps keep ahead of gives the fit without a budget, bit for bit."""
    unlimited = fit_field(uniform_levels, iterations=30, time_budget_s=None, threads=1)
    ahead = fit_field(uniform_levels, iterations=30, time_budget_s=20.0, threads=1)
    assert ahead.iterations == 30
    np.testing.assert_array_equal(ahead.field, unlimited.field)
