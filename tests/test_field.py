"""Stage 1: the target's de-quantisation, the linear field operator and the field fit."""

import os
import time

import numpy as np
import pytest

from octcl import _reference as ref
from octcl._io import GREY_LUT, read_png_rgb, read_scan
from octcl.config import ScannerConfig
from octcl.host.stage1.display import fit_field
from octcl.host.stage1.display_loss import DisplayGoal, _box3, _box3_adjoint, display_loss
from octcl.host.stage1.levels import target_display, target_levels, target_magnitude
from octcl.host.stage1.operator import FieldOperator, cell_depths_um, lateral_taps
from octcl.render import DISPLAY_SLOPE
from octcl.phantom import Phantom

#: A small scanner (32 rows, 16 A-scans of 6 µm) for the reference comparisons.
SMALL = ScannerConfig(depth_pixels=32, a_scans=16, xmax_um=96.0)


def _reference_a_scans(phantom: Phantom, config: ScannerConfig, shadowing: bool) -> np.ndarray:
    """Complex A-scans of the float64 reference scanner, as octcl.render builds them."""
    spectra = ref.render_spectra(phantom, config, shadowing=shadowing)
    return np.fft.ifft(spectra * ref.hann_window(config.depth_pixels)[:, None], axis=0)


def test_target_display_inverts_the_quantiser():
    # Every level the scanner writes maps to a D that the scanner writes as that level.
    levels = np.unique(GREY_LUT)
    display = target_display(levels[None, :])[0]
    assert levels[0] == 0 and display[0] == 0.0
    assert np.array_equal(ref.quantise(display[1:]), levels[1:])


def test_target_display_of_levels_the_scanner_never_writes():
    # A real scan quantised plainly has the 24 truncated levels; each maps into its own bin.
    levels = np.arange(256, dtype=np.uint8)[None, :]
    display = target_display(levels)[0]
    assert np.all(np.diff(display[1:]) > 0)
    assert np.all((display[1:] >= np.arange(1, 256) / 256) & (display[1:] <= np.arange(3, 258) / 256))


def test_target_levels_of_a_read_scan(official_data):
    path = official_data / "Scan_Exp1_Uniform_A.png"
    levels = target_levels(read_scan(path))
    assert levels.dtype == np.uint8
    assert np.array_equal(levels, read_png_rgb(path)[..., 0])


def test_target_magnitude_is_the_delogged_display():
    levels = np.array([[0, 128, 255]], dtype=np.uint8)
    magnitude = target_magnitude(levels)
    floor = 10 ** (-51 / 20)
    assert magnitude[0, 0] == pytest.approx(0.5 * floor)
    assert magnitude[0, 1] == pytest.approx(10 ** (51 * (128.5 / 256 - 1) / 20))
    assert magnitude[0, 2] == pytest.approx(10 ** (51 * (255.5 / 256 - 1) / 20))


def test_cell_depths_fall_on_dft_bins():
    config = ScannerConfig()
    z = cell_depths_um(config)
    dk = np.diff(ref.wavenumbers(config))[0]
    assert np.allclose(2 * dk * z, 2 * np.pi * np.arange(256) / 256, rtol=0, atol=1e-12)
    assert z[1] == pytest.approx(5.99991, abs=1e-5)


def test_lateral_taps_are_the_contribution_window():
    taps = lateral_taps(ScannerConfig())
    assert taps.size == 5  # (2·6)² < 3·10² ≤ (3·6)²
    assert np.allclose(taps, np.exp(-(np.arange(-2, 3) * 6.0) ** 2 / 100))


def test_operator_matches_the_reference_scanner():
    # One scatterer per cell at (x_i, 0, z_n): its complex weight is a·e^{−2i·k0·z_n}.
    config = SMALL
    nz, nx = config.shape
    rng = np.random.default_rng(1)
    amplitude = rng.uniform(0.0, 0.1, (nz, nx))
    rows, columns = np.meshgrid(np.arange(nz), np.arange(nx), indexing="ij")
    z_um = cell_depths_um(config)[rows]
    phantom = Phantom(ref.ascan_positions_um(config)[columns], np.zeros(nz * nx), z_um,
                      100 * amplitude**2)
    field = amplitude * np.exp(-2j * (2 * np.pi / config.wavelength_um) * z_um)
    expected = _reference_a_scans(phantom, config, shadowing=False)
    got = FieldOperator(config).apply(field)
    assert np.abs(got - expected).max() <= 1e-9 * np.abs(expected).max()


def test_operator_adjoint_and_pseudo_inverse():
    operator = FieldOperator(SMALL)
    rng = np.random.default_rng(2)
    field = rng.normal(size=SMALL.shape) + 1j * rng.normal(size=SMALL.shape)
    other = rng.normal(size=SMALL.shape) + 1j * rng.normal(size=SMALL.shape)
    a_scans = operator.apply(field)
    # ⟨H·F, A⟩ = ⟨F, Hᴴ·A⟩
    assert np.vdot(other, a_scans) == pytest.approx(np.vdot(operator.adjoint(other), field), rel=1e-12)
    # In single precision the operator keeps complex64 and agrees to float32 rounding.
    single = operator.apply(field.astype(np.complex64))
    assert single.dtype == np.complex64
    assert np.abs(single - a_scans).max() <= 1e-5 * np.abs(a_scans).max()
    # The regularised inverse reproduces A-scans in the operator's range; a
    # field clear of the first and last R columns spills nothing past the
    # scan's edges, so its A-scans are such.
    reach = operator.taps.size // 2
    field[:, :reach] = field[:, -reach:] = 0
    a_scans = operator.apply(field)
    recovered = operator.apply(operator.pseudo_inverse(a_scans, regularisation=1e-12))
    assert np.linalg.norm(recovered - a_scans) <= 1e-6 * np.linalg.norm(a_scans)


def _small_goal(seed: int = 0):
    """Random levels on the small scanner, the first rows at level 0 (the clamp at 0), in float64."""
    rng = np.random.default_rng(seed)
    levels = rng.integers(0, 256, SMALL.shape).astype(np.uint8)
    levels[:3] = 0
    field = rng.normal(size=SMALL.shape) + 1j * rng.normal(size=SMALL.shape)
    return levels, DisplayGoal.of(levels, dtype=np.float64), field, rng


def test_display_loss_gradient_matches_finite_differences():
    """Re⟨G, δF⟩ against the central difference of the loss along random directions δF."""
    _, goal, field, rng = _small_goal()
    operator = FieldOperator(SMALL)
    _, gradient = display_loss(field, operator, goal)
    step = 1e-6
    for _ in range(20):
        direction = rng.normal(size=SMALL.shape) + 1j * rng.normal(size=SMALL.shape)
        difference = (display_loss(field + step * direction, operator, goal)[0]
                      - display_loss(field - step * direction, operator, goal)[0]) / (2 * step)
        assert np.real(np.vdot(gradient, direction)) == pytest.approx(difference, rel=1e-6, abs=1e-12)


def test_display_loss_gradient_matches_torch_autograd():
    """The same loss written in torch (as stage 1 was before its gradient was derived by hand)."""
    import torch

    _, goal, field, _ = _small_goal(1)
    operator = FieldOperator(SMALL)
    loss, gradient = display_loss(field, operator, goal)

    def high_pass(image):
        padded = torch.nn.functional.pad(image[None, None], (1, 1, 1, 1), mode="replicate")
        return image - torch.nn.functional.avg_pool2d(padded, 3, stride=1)[0, 0]

    variable = torch.tensor(field, requires_grad=True)
    spectrum = torch.fft.fft2(variable, s=(SMALL.depth_pixels, operator.padded_columns))
    a_scans = torch.fft.ifft2(spectrum * torch.as_tensor(operator.transfer))[:, :SMALL.a_scans]
    power = a_scans.real**2 + a_scans.imag**2
    log_amplitude = 0.5 * torch.log(power + 1e-24 * power.detach().max())
    display = 1.0 + DISPLAY_SLOPE * (log_amplitude - log_amplitude.max())
    visible = torch.as_tensor(goal.visible)
    display = torch.where(visible, display.clamp(min=-1.0), display.clamp(min=0.0))
    target = torch.as_tensor(goal.display)
    error = display - target
    torch_loss = (error.abs().mean() + (error**2).mean() + 0.5 * (high_pass(display) - high_pass(target)).abs().mean()
                  + goal.energy_weight * (variable.abs()**2).mean() / power.max())
    torch_loss.backward()
    assert loss == pytest.approx(torch_loss.item(), rel=1e-12)
    # torch's gradient of a real loss in a complex tensor is ∂L/∂Re + i·∂L/∂Im, as G is.
    np.testing.assert_allclose(gradient, variable.grad.numpy(), rtol=0, atol=1e-12 * np.abs(gradient).max())


def test_box3_adjoint():
    rng = np.random.default_rng(3)
    image, other = rng.normal(size=(7, 5)), rng.normal(size=(7, 5))
    assert np.vdot(other, _box3(image)) == pytest.approx(np.vdot(_box3_adjoint(other), image), rel=1e-12)


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


def test_fit_field_respects_the_time_budget(uniform_levels):
    start = time.perf_counter()
    fit = fit_field(uniform_levels, iterations=10**6, time_budget_s=1.0, threads=1)
    elapsed = time.perf_counter() - start
    assert 1 <= fit.iterations < 10**6
    assert fit.seconds <= elapsed
    # At most one step past the budget, then the final rendering.
    assert elapsed < 1.0 + 0.5


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


def test_fit_field_ahead_of_its_clock_takes_no_decision_from_it(uniform_levels):
    """A budget the steps keep ahead of gives the fit without a budget, bit for bit."""
    unlimited = fit_field(uniform_levels, iterations=30, time_budget_s=None, threads=1)
    ahead = fit_field(uniform_levels, iterations=30, time_budget_s=20.0, threads=1)
    assert ahead.iterations == 30
    np.testing.assert_array_equal(ahead.field, unlimited.field)
