"""The linear regime's exact two-row decode (host/stage2/exact.py) against the float64 reference scanner."""

import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from octcl import _reference as ref
from octcl.config import DEFAULT_CONFIG
from octcl.host.stage1.operator import FieldOperator
from octcl.host.stage2.exact import DECODE_CORRECTIONS, DECODE_TOLERANCE, SHADOW_BOUND, row_carriers, decode_exact, rendered_cells, row_depths_um, row_offsets_um, split_on_carriers
from octcl.phantom import Phantom
from octcl.render import Rendering
from conftest import random_field, reference_rendering, SMALL_SCANNER as SMALL


# ------------------------------------------------------------------ decode
@settings(max_examples=50, deadline=None)
@given(st.lists(st.complex_numbers(max_magnitude=1e3, allow_nan=False, allow_infinity=False), min_size=1,
                max_size=40))
@example([-1 - 1j])  # on row 0's carrier at −3π/4, to 4e−16: once outside both sectors beside it
def test_split_on_carriers_is_non_negative_two_per_value_and_exact(values):
    values = np.array(values)
    rows = row_carriers(DEFAULT_CONFIG)[:, :, 0]
    # One set of carriers for every value, and a set per value (each row's own, as the decode uses them).
    for carriers, per_value in ((rows[:, 7], rows[:, 7][:, None]),
                                (rows[:, np.arange(values.size) % rows.shape[1]], None)):
        weights = split_on_carriers(values, carriers)
        assert np.all(weights >= 0)
        assert np.all((weights > 0).sum(axis=0) <= 2)
        error = np.abs((weights * (carriers if per_value is None else per_value)).sum(axis=0) - values)
        assert np.all(error <= 1e-12 * (1 + np.abs(values)))


def test_rows_sit_at_their_offsets_inside_the_depth_range_on_the_files_grid():
    offsets = row_offsets_um(DEFAULT_CONFIG)
    assert offsets.shape == (4, DEFAULT_CONFIG.depth_pixels)
    assert np.all(offsets[:, 0] >= 0)  # row 0 is at z = 0
    k0 = DEFAULT_CONFIG.k0_rad_per_um
    # Row 0's moved offsets keep their carrier phases, to the file's rounding (≤ 5e−5 µm: 4.8e−4 rad).
    np.testing.assert_allclose(np.exp(-2j * k0 * offsets[:, 0]), np.exp(-2j * k0 * offsets[:, 1]), atol=1e-3)
    depths = row_depths_um(DEFAULT_CONFIG)
    assert np.array_equal(depths, np.vectorize(lambda z: float(f"{z:.7e}"))(depths))  # what the file holds


def test_a_decoded_phantom_renders_as_its_field_after_the_file_round_trip(tmp_path):
    """The rows sit on the file's 8-digit depths, so the saved phantom renders the field's levels, every one."""
    field = random_field(DEFAULT_CONFIG, 4)
    phantom = decode_exact(field, DEFAULT_CONFIG)
    phantom.save(tmp_path / "decoded.txt")
    loaded = Phantom.load(tmp_path / "decoded.txt")
    assert np.array_equal(loaded.z_um, phantom.z_um)
    _, rendering = reference_rendering(loaded, DEFAULT_CONFIG)
    expected = Rendering.from_a_scans(FieldOperator(DEFAULT_CONFIG).apply(field)).levels
    assert np.array_equal(rendering.levels, expected)


def test_rendered_cells_is_the_reference_scanners_rendering_of_the_rows():
    """The grid model of the rows (no Taylor expansion) against the float64 scanner without shadowing."""
    rng = np.random.default_rng(1)
    weights = rng.random((4,) + SMALL.shape) * (rng.random((4,) + SMALL.shape) < 0.5)
    depth_um = np.arange(SMALL.depth_pixels) * np.pi / (SMALL.depth_pixels * np.diff(ref.wavenumbers(SMALL))[0])
    d, row, column = np.nonzero(weights)
    phantom = Phantom(ref.ascan_positions_um(SMALL)[column], np.zeros(row.size),
                      depth_um[row] + row_offsets_um(SMALL)[d, row], 100 * weights[d, row, column] ** 2)
    a_scans, _ = reference_rendering(phantom, SMALL, shadowing=False)
    expected = FieldOperator(SMALL).apply(rendered_cells(weights, SMALL))
    np.testing.assert_allclose(a_scans, expected, atol=1e-12 * np.abs(expected).max())


def test_a_decode_is_the_same_to_the_bit_at_any_fft_thread_count():
    """The depth DFTs over 2 or 3 threads give the phantom of 1 thread, bit for bit (a run passes its own
    thread count, and its phantom must not depend on it)."""
    field = random_field(SMALL, 2)
    one = decode_exact(field, SMALL, workers=1)
    for workers in (2, 3):
        other = decode_exact(field, SMALL, workers=workers)
        assert all(np.array_equal(getattr(one, name), getattr(other, name))
                   for name in ("x_um", "y_um", "z_um", "energy_pct"))


@pytest.mark.parametrize("seed", [0, 1])
def test_decode_exact_renders_as_the_field_with_shadowing(seed, monkeypatch):
    """The float64 scanner, shadowing included, renders the decoded phantom as A(F), at the field's levels: to
    1e−9 with every update of the placed field (``tolerance`` 0), and within ``DECODE_TOLERANCE`` of max|A| with
    the default, which stops after fewer of them."""
    from octcl.host.stage2 import exact

    renders = []
    monkeypatch.setattr(exact, "rendered_cells", lambda *args: renders.append(1) or rendered_cells(*args))
    field = random_field(SMALL, seed)
    expected = FieldOperator(SMALL).apply(field)
    counts = {}
    for tolerance in (0.0, DECODE_TOLERANCE):
        renders.clear()
        phantom = decode_exact(field, SMALL, tolerance=tolerance)
        counts[tolerance] = len(renders)
        nz, nx = SMALL.shape
        assert len(phantom) <= 2 * nz * nx and np.all(phantom.y_um == 0)
        assert np.all((phantom.z_um >= 0) & (phantom.z_um <= SMALL.depth_range_um))
        a_scans, rendering = reference_rendering(phantom, SMALL)
        scale = np.vdot(expected, a_scans) / np.vdot(expected, expected)
        if tolerance == 0:
            assert np.linalg.norm(a_scans - scale * expected) <= 1e-9 * np.linalg.norm(scale * expected)
        else:
            assert np.abs(a_scans - scale * expected).max() <= tolerance * np.abs(scale * expected).max()
        assert np.array_equal(rendering.levels, Rendering.from_a_scans(expected).levels)
    assert counts[0.0] == DECODE_CORRECTIONS + 1 and counts[DECODE_TOLERANCE] < counts[0.0]


def test_decode_exact_keeps_shadowing_under_its_bound():
    phantom = decode_exact(random_field(SMALL, 2), SMALL)
    beam = ref.beam_weight(ref.ascan_positions_um(SMALL)[:, None] - phantom.x_um[None, :], phantom.y_um[None, :],
                           SMALL.beam_radius_um)
    shadow = ((beam * ref.amplitudes(phantom.energy_pct)[None, :]) ** 2).sum(axis=1)
    assert shadow.max() == pytest.approx(SHADOW_BOUND, rel=1e-6)


def test_shadowing_at_a_larger_scale_changes_the_rendering():
    """The bound matters: the same rows scaled up to Σ(B·a)² = 0.5 no longer render as the field."""
    field = random_field(SMALL, 3)
    expected = FieldOperator(SMALL).apply(field)
    a_scans, _ = reference_rendering(decode_exact(field, SMALL, shadow_bound=0.5), SMALL)
    scale = np.vdot(expected, a_scans) / np.vdot(expected, expected)
    assert np.linalg.norm(a_scans - scale * expected) > 1e-3 * np.linalg.norm(scale * expected)


def test_decode_exact_refuses_what_it_cannot_decode():
    with pytest.raises(ValueError, match="grid"):
        decode_exact(np.ones((3, 3)), SMALL)
    with pytest.raises(ValueError, match="zero"):
        decode_exact(np.zeros(SMALL.shape), SMALL)
    with pytest.raises(ValueError, match="non-finite"):
        decode_exact(np.full(SMALL.shape, np.nan), SMALL)
    with pytest.raises(ValueError, match="shadow_bound"):
        decode_exact(np.ones(SMALL.shape), SMALL, shadow_bound=0.0)


def test_energy_floor_is_a_normal_float32_amplitude():
    from octcl.host.stage2.exact import ENERGY_FLOOR_PCT

    amplitude = math.sqrt(ENERGY_FLOOR_PCT / 100)
    assert amplitude > np.finfo(np.float32).tiny
