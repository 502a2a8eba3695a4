"""Stage 2: the amplitude-capped decode of a complex field into a phantom."""

import numpy as np
import pytest

from octcl import _reference as ref
from octcl.config import ScannerConfig
from octcl.host.stage2.capped import CAP_STEP, children_per_cell, decode_field
from octcl.host.stage1.operator import FieldOperator, cell_depths_um
from octcl.phantom import CONTRACT_Y_LIMIT_UM
from conftest import random_field, reference_a_scans, SMALL_SCANNER as SMALL


def _relative_error(a_scans: np.ndarray, expected: np.ndarray) -> float:
    """‖a − s·e‖/‖s·e‖ with s the least-squares scale (the decode rescales the field)."""
    scale = np.vdot(expected, a_scans) / np.vdot(expected, expected)
    return float(np.linalg.norm(a_scans - scale * expected) / np.linalg.norm(scale * expected))


# ------------------------------------------------------------ cap and budget
def test_children_per_cell_fits_the_budget_with_the_first_cap_that_does():
    rng = np.random.default_rng(0)
    magnitude = rng.lognormal(sigma=1.5, size=(64, 64)) * (rng.random((64, 64)) > 0.1)
    budget = 10_000
    counts, cap = children_per_cell(magnitude, budget)
    assert counts.sum() <= budget
    assert np.array_equal(counts == 0, magnitude == 0)
    assert np.all(magnitude / np.maximum(counts, 1) <= cap * (1 + 1e-12))
    start = magnitude.sum() / budget
    steps = np.log(cap / start) / np.log(CAP_STEP)
    assert steps == pytest.approx(round(steps), abs=1e-9)
    if steps >= 1:  # the previous cap did not fit
        assert np.ceil(magnitude / (cap / CAP_STEP)).sum() > budget


def test_children_per_cell_keeps_the_brightest_cells_when_too_many():
    magnitude = np.arange(1.0, 11.0)
    counts, cap = children_per_cell(magnitude, 4)
    assert counts.tolist() == [0] * 6 + [1] * 4
    assert cap >= 10.0


def test_children_per_cell_splits_a_single_bright_cell():
    magnitude = np.zeros(10)
    magnitude[3] = 2.0
    counts, cap = children_per_cell(magnitude, 7)
    assert counts[3] == 7 and counts.sum() == 7
    assert cap == pytest.approx(2.0 / 7)


@pytest.mark.parametrize("bad", [np.zeros(5), np.array([1.0, -1.0]), np.array([1.0, np.nan])])
def test_children_per_cell_refuses_bad_magnitudes(bad):
    with pytest.raises(ValueError):
        children_per_cell(bad, 10)


# -------------------------------------------------------------- the phantom
def test_decode_meets_the_contract():
    config = ScannerConfig()
    rng = np.random.default_rng(3)
    field = random_field(config, 3) * (rng.random(config.shape) > 0.2)
    field[0, 0] = 50.0  # one very bright cell: split into many capped children
    budget = 200_000
    phantom = decode_field(field, config, max_scatterers=budget, seed=1)
    assert 0 < len(phantom) <= budget
    phantom.validate(config, y_limit_um=CONTRACT_Y_LIMIT_UM)
    assert np.all(np.abs(phantom.x_um) <= 1536) and np.all(np.abs(phantom.y_um) <= 3)
    assert np.all((phantom.z_um >= 0) & (phantom.z_um <= 1536))
    assert np.all((phantom.energy_pct >= 0) & (phantom.energy_pct <= 100))
    # Children sit on A-scan lines; the beam-weighted amplitude of the bright
    # cell's children is far below the shadowing scale (no child dominates).
    assert np.allclose(np.mod(phantom.x_um, 6.0), 0.0)
    beam_amplitude = phantom.amplitude * np.exp(-phantom.y_um**2 / 100)
    assert beam_amplitude.max() ** 2 <= 1e-4
    # The scale: the worst A-scan's Σ_j (B_ij·a_j)² is the shadow_loss, 1e−4.
    column = np.rint(phantom.x_um / 6.0 + 256).astype(int)
    column_power = np.bincount(column, weights=beam_amplitude**2, minlength=512)
    offsets_um = np.arange(-511, 512) * 6.0
    shadow_sum = np.convolve(column_power, np.exp(-2 * offsets_um**2 / 100), mode="same")
    assert shadow_sum.max() == pytest.approx(1e-4, rel=1e-9)
    bright = (phantom.x_um == -1536) & (phantom.z_um < 3)
    assert bright.sum() > 1
    assert np.ptp(beam_amplitude[bright]) <= 1e-9 * beam_amplitude[bright].max()


def test_decoded_cell_adds_up_to_its_complex_value():
    # A single bright cell split into children: their coherent sum renders as
    # the field operator's point response, with the cell's phase. (Shadowing
    # between the children, ~1e−4 here, is left out: this checks the sum.)
    config = SMALL
    field = np.zeros(config.shape, dtype=complex)
    field[12, 7] = 0.8 * np.exp(1.3j)
    phantom = decode_field(field, config, max_scatterers=200, seed=0)
    assert len(phantom) <= 200
    centre = ((phantom.x_um == ref.ascan_positions_um(config)[7])
              & (np.abs(phantom.z_um - cell_depths_um(config)[12]) < 3))
    assert centre.sum() > 50  # the cell itself holds most children
    expected = FieldOperator(config).apply(field)
    got = reference_a_scans(phantom, config, shadowing=False)
    assert _relative_error(got, expected) < 1e-5
    # Phase, not just magnitude: the brightest pixel carries the cell's phase.
    scale = np.vdot(expected, got) / np.vdot(expected, expected)
    assert abs(np.angle(scale)) < 1e-4


def test_decoded_speckle_field_renders_as_the_field():
    config = SMALL
    field = random_field(config, 5)
    phantom = decode_field(field, config, max_scatterers=2000, seed=2)
    expected = FieldOperator(config).apply(field)
    assert _relative_error(reference_a_scans(phantom, config), expected) < 2e-3


def test_decode_correction_reduces_the_error():
    config = SMALL
    field = random_field(config, 6)
    expected = FieldOperator(config).apply(field)
    errors = [_relative_error(reference_a_scans(decode_field(field, config, max_scatterers=2000,
                                                             corrections=count), config), expected)
              for count in (0, 4)]
    assert errors[1] < 0.3 * errors[0]


def test_decode_zero_field_is_an_error():
    with pytest.raises(ValueError, match="zero"):
        decode_field(np.zeros(SMALL.shape, dtype=complex), SMALL)


@pytest.mark.parametrize("change", [
    lambda f: f[:, :-1],
    lambda f: np.where(np.arange(f.size).reshape(f.shape) == 5, np.nan, f),
])
def test_decode_refuses_bad_fields(change):
    with pytest.raises(ValueError):
        decode_field(change(random_field(SMALL, 7)), SMALL)


@pytest.mark.parametrize("level", [0, 255])
def test_flat_targets_decode_to_finite_phantoms(level):
    from octcl.host.stage1.display import fit_field

    fit = fit_field(np.full(SMALL.shape, level, dtype=np.uint8), SMALL, iterations=10, threads=1)
    phantom = decode_field(fit.field, SMALL, max_scatterers=1000)
    phantom.validate(SMALL, y_limit_um=CONTRACT_Y_LIMIT_UM)
    assert 0 < len(phantom) <= 1000
    assert np.isfinite(phantom.as_array()).all()
