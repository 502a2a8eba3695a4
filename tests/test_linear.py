"""The linear regime: level intervals, accelerated projections, the exact two-row decode."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from octcl import _reference as ref
from octcl._io import GREY_LUT
from octcl.config import DEFAULT_CONFIG, ScannerConfig
from octcl.host.stage1.operator import FieldOperator
from octcl.host.stage1.solve import default_schedules, display, project
from octcl.host.stage1.hinge import LEVEL_CHECK_EVERY, LEVEL_FIT_ITERATIONS, fit_levels
from octcl.host.stage1.levels import INTERVAL_MARGIN, level_magnitude_bounds
from octcl.host.stage1.projections import retrieve_field
from octcl.host.stage1.start import linear_start
from octcl.host.stage2.exact import SHADOW_BOUND, _carriers, decode_exact, rendered_cells, row_depths_um, row_offsets_um, split_on_carriers
from octcl.phantom import Phantom
from octcl.render import Rendering

#: A small scanner (32 rows, 16 A-scans of 6 µm) for the reference renders.
SMALL = ScannerConfig(depth_pixels=32, a_scans=16, xmax_um=96.0)


def _random_field(config: ScannerConfig, seed: int) -> np.ndarray:
    """A speckle-like field: complex Gaussian, brighter near the top."""
    rng = np.random.default_rng(seed)
    nz, nx = config.shape
    decay = np.exp(-np.arange(nz) / (nz / 3))[:, None]
    return decay * (rng.normal(size=(nz, nx)) + 1j * rng.normal(size=(nz, nx)))


def _reference(phantom: Phantom, config: ScannerConfig, shadowing: bool = True):
    """Complex A-scans of the float64 reference scanner and their Rendering."""
    spectra = ref.render_spectra(phantom, config, shadowing=shadowing)
    a_scans = np.fft.ifft(spectra * ref.hann_window(config.depth_pixels)[:, None], axis=0)
    return a_scans, Rendering.from_a_scans(a_scans)


# ------------------------------------------------------------- level bounds
@settings(max_examples=200, deadline=None)
@given(level=st.sampled_from(sorted(set(GREY_LUT.tolist()))), where=st.floats(0.0, 1.0))
def test_a_magnitude_inside_a_levels_interval_renders_that_level(level, where):
    """Any |A|/max|A| in [l, u] of a level the scanner makes shows as that level (max|A| = 1 elsewhere)."""
    lower, upper = (bound.item() for bound in level_magnitude_bounds(np.array([level], dtype=np.uint8)))
    assert 0 <= lower < upper <= 1
    magnitude = lower + where * (upper - lower) if level else where * upper
    magnitude = max(magnitude, 1e-300)
    levels = Rendering.from_a_scans(np.array([[1.0], [magnitude]])).levels
    assert levels[1, 0] == level


def test_the_margin_shrinks_every_interval_inside_the_plain_one():
    levels = np.arange(256, dtype=np.uint8)
    plain_low, plain_high = level_magnitude_bounds(levels, margin=0.0)
    low, high = level_magnitude_bounds(levels, margin=INTERVAL_MARGIN)
    assert np.all(plain_low <= low) and np.all(high < plain_high) and np.all(low < high)
    assert low[0] == 0.0 and high[255] < 1.0
    with pytest.raises(ValueError, match="margin"):
        level_magnitude_bounds(levels, margin=0.5)


# ------------------------------------------------------------------ decode
@settings(max_examples=50, deadline=None)
@given(st.lists(st.complex_numbers(max_magnitude=1e3, allow_nan=False, allow_infinity=False), min_size=1,
                max_size=40))
def test_split_on_carriers_is_non_negative_two_per_value_and_exact(values):
    values = np.array(values)
    rows = _carriers(DEFAULT_CONFIG)[:, :, 0]
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
    k0 = 2 * np.pi / DEFAULT_CONFIG.wavelength_um
    # Row 0's moved offsets keep their carrier phases, to the file's rounding (≤ 5e−5 µm: 4.8e−4 rad).
    np.testing.assert_allclose(np.exp(-2j * k0 * offsets[:, 0]), np.exp(-2j * k0 * offsets[:, 1]), atol=1e-3)
    depths = row_depths_um(DEFAULT_CONFIG)
    assert np.array_equal(depths, np.vectorize(lambda z: float(f"{z:.7e}"))(depths))  # what the file holds


def test_a_decoded_phantom_renders_as_its_field_after_the_file_round_trip(tmp_path):
    """The rows sit on the file's 8-digit depths, so the saved phantom renders the field's levels, every one."""
    field = _random_field(DEFAULT_CONFIG, 4)
    phantom = decode_exact(field, DEFAULT_CONFIG)
    phantom.save(tmp_path / "decoded.txt")
    loaded = Phantom.load(tmp_path / "decoded.txt")
    assert np.array_equal(loaded.z_um, phantom.z_um)
    _, rendering = _reference(loaded, DEFAULT_CONFIG)
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
    a_scans, _ = _reference(phantom, SMALL, shadowing=False)
    expected = FieldOperator(SMALL).apply(rendered_cells(weights, SMALL))
    np.testing.assert_allclose(a_scans, expected, atol=1e-12 * np.abs(expected).max())


@pytest.mark.parametrize("seed", [0, 1])
def test_decode_exact_renders_as_the_field_with_shadowing(seed):
    """The float64 scanner, shadowing included, renders the decoded phantom as A(F), to 1e−9."""
    field = _random_field(SMALL, seed)
    phantom = decode_exact(field, SMALL)
    nz, nx = SMALL.shape
    assert len(phantom) <= 2 * nz * nx and np.all(phantom.y_um == 0)
    assert np.all((phantom.z_um >= 0) & (phantom.z_um <= SMALL.depth_range_um))
    a_scans, rendering = _reference(phantom, SMALL)
    expected = FieldOperator(SMALL).apply(field)
    scale = np.vdot(expected, a_scans) / np.vdot(expected, expected)
    assert np.linalg.norm(a_scans - scale * expected) <= 1e-9 * np.linalg.norm(scale * expected)
    assert np.array_equal(rendering.levels, Rendering.from_a_scans(expected).levels)


def test_decode_exact_keeps_shadowing_under_its_bound():
    phantom = decode_exact(_random_field(SMALL, 2), SMALL)
    beam = ref.beam_weight(ref.ascan_positions_um(SMALL)[:, None] - phantom.x_um[None, :], phantom.y_um[None, :],
                           SMALL.beam_radius_um)
    shadow = ((beam * ref.amplitudes(phantom.energy_pct)[None, :]) ** 2).sum(axis=1)
    assert shadow.max() == pytest.approx(SHADOW_BOUND, rel=1e-6)


def test_shadowing_at_a_larger_scale_changes_the_rendering():
    """The bound matters: the same rows scaled up to Σ(B·a)² = 0.5 no longer render as the field."""
    field = _random_field(SMALL, 3)
    expected = FieldOperator(SMALL).apply(field)
    a_scans, _ = _reference(decode_exact(field, SMALL, shadow_bound=0.5), SMALL)
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


# --------------------------------------------------------------- retrieval
def _scanner_made_target(seed: int) -> np.ndarray:
    """Levels of the reference scanner's rendering of a random phantom on the full grid (a feasible target)."""
    rng = np.random.default_rng(seed)
    n = 40_000
    phantom = Phantom(rng.uniform(-1536, 1530, n), rng.uniform(-3, 3, n), rng.uniform(0, 1536, n),
                      rng.lognormal(-6, 1.5, n) * np.exp(-rng.uniform(0, 1536, n) / 500))
    return ref.render_reference(phantom).levels


def test_retrieve_field_matches_most_levels_of_a_scanner_made_target():
    """300 projections from the regularised start put most pixels at their level."""
    levels = _scanner_made_target(0)
    fit = retrieve_field(levels)
    a_scans = FieldOperator().apply(fit.field)
    assert fit.iterations == 300 and fit.clock_steps == 0
    assert np.abs(a_scans).max() == pytest.approx(1.0)
    assert fit.identical == pytest.approx(np.mean(Rendering.from_a_scans(a_scans).levels == levels))
    start = retrieve_field(levels, iterations=1)
    assert fit.identical > 0.9 and fit.identical > start.identical + 0.1


def test_fit_levels_puts_every_pixel_at_its_level_and_the_brightest_at_one():
    """A field's own levels, from that field disturbed (a fifth of the pixels off their level): the hinge fit
    puts every pixel back at its level, its brightest pixel at |A| = 1 so that the display's normalisation
    holds, and stops as soon as the levels are all there."""
    operator = FieldOperator(SMALL)
    truth = _random_field(SMALL, 5)
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


def test_linear_start_stops_trying_once_a_candidate_renders_every_aimed_level(official_data):
    """On an official scan (the scanner rendered it), the first candidate renders every level: the
    half-length one is left out; without the hinge fit both run, neither at every level."""
    from octcl.host.pipeline.target import read_target, target_scan

    levels = target_scan(read_target(official_data / "Scan_Exp2_Layers_A.png"))
    found = linear_start(levels, lambda rendered: 0.0, schedules=default_schedules(150), threads=1)
    assert [c["identical"] for c in found.candidates] == [1.0]
    assert [step["name"] for step in found.candidates[0]["steps"]][:2] == ["display", "project"]
    plain = linear_start(levels, lambda rendered: 0.0, threads=1,
                         schedules=(display(150) + project(100), display(75) + project(100)))
    assert len(plain.candidates) == 2 and max(c["identical"] for c in plain.candidates) < 1.0


def test_retrieve_field_stays_bounded_on_an_official_scan(official_data):
    """At a full step (α = 1) the momentum iteration diverges on Uniform A (the field grows to ~1e93 and
    35 % of the levels are the target's); at α = 0.8 it converges (56 %), the field within a few times
    the rendering's norm."""
    from octcl.host.pipeline.target import read_target

    fit = retrieve_field(read_target(official_data / "Scan_Exp1_Uniform_A.png"))
    a_scans = FieldOperator().apply(fit.field)
    assert np.linalg.norm(fit.field) < 20 * np.linalg.norm(a_scans)
    assert fit.identical > 0.5


def test_retrieve_field_is_deterministic_and_stops_at_its_budget():
    levels = _scanner_made_target(1)
    first, second = retrieve_field(levels, iterations=20), retrieve_field(levels, iterations=20)
    np.testing.assert_array_equal(first.field, second.field)
    calls = []
    cut = retrieve_field(levels, iterations=10_000, time_budget_s=0.2, progress=lambda i, n: calls.append((i, n)))
    assert cut.clock_steps == 1 and 1 <= cut.iterations < 10_000 and calls[-1] == (cut.iterations, 10_000)
    with pytest.raises(ValueError, match="iterations"):
        retrieve_field(levels, iterations=0)
    with pytest.raises(ValueError, match="scanner makes"):
        retrieve_field(levels[:10])


def test_energy_floor_is_a_normal_float32_amplitude():
    from octcl.host.stage2.exact import ENERGY_FLOOR_PCT

    amplitude = math.sqrt(ENERGY_FLOOR_PCT / 100)
    assert amplitude > np.finfo(np.float32).tiny


def test_linear_start_keeps_the_best_scoring_candidate():
    levels = _scanner_made_target(2)
    scores = iter([0.5, 0.9, 0.7])  # the second candidate (half the steps) scores best
    calls = []
    schedules = tuple(display(steps) + project(20) for steps in (10, 5, 20))
    found = linear_start(levels, lambda rendered: next(scores), schedules=schedules, threads=1,
                         progress=lambda step, steps: calls.append((step, steps)))
    assert [c["schedule"] for c in found.candidates] == ["display:10,project:20", "display:5,project:20",
                                                         "display:20,project:20"]
    assert [c["score"] for c in found.candidates] == [0.5, 0.9, 0.7]
    assert found.schedule == schedules[1] and found.clock_steps == 0 and found.threads == 1
    assert calls[-1] == (35 + 60, 35 + 60)
    # The chosen field is the second candidate's, as its steps made it.
    from octcl.host.stage1.display import fit_field

    again = retrieve_field(levels, iterations=20, initial=fit_field(levels, iterations=5, time_budget_s=None,
                                                                    threads=1).field)
    np.testing.assert_array_equal(found.field, again.field)


def test_linear_start_leaves_out_candidates_the_budget_cannot_hold():
    levels = _scanner_made_target(2)
    found = linear_start(levels, lambda rendered: float(np.mean(rendered == levels)),
                         schedules=default_schedules(400), time_budget_s=0.5, threads=1)
    assert len(found.candidates) == 1 and found.clock_steps >= 1
    display_record = found.candidates[0]["steps"][0]
    assert display_record["name"] == "display" and display_record["iterations"] < 400  # cut by its share
