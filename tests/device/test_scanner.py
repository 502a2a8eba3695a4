"""OpenCL scanner kernels against the float64 reference, including stiff and extreme scenes.

Every test runs both kernel variants (one work-item per A-scan, one
work-group per A-scan); those on the narrow scanner run them on each CPU
implementation present (PoCL, Intel's runtime: the test id names it), the
full-size scenes on the device octcl picks, and "Under Oclgrind" runs both variants and
both precisions on a small scene in the Oclgrind simulator, which checks
every memory access, data races and the API calls. Agreement is measured on the
complex A-scans: max |A_kernel − A_ref| relative to max |A_ref|. Float32
kernels with the default spreading width W = 8 sit at ~1e−6 (float32
accumulation over thousands of scatterers; the spreading itself is ~1e−8),
so 1e−5 is asserted; float64 kernels at ~1e−8 (the spreading kernel's own
error), so 1e−7 is asserted.
"""

import hashlib

import numpy as np
import pytest
from conftest import KERNEL_IMPLEMENTATIONS, OCLGRIND_LOG, implementation_device, oclgrind_reports

from octcl import _reference as ref
from octcl.config import ScannerConfig
from octcl.phantom import Phantom
from octcl.render import Rendering, display_vjp, render
from octcl.device.scanner import VARIANTS, KernelSettings, ScannerKernels

#: A narrow scanner (64 A-scans, 384 µm) keeps the float64 reference fast.
NARROW = ScannerConfig(a_scans=64, xmax_um=384.0)




@pytest.fixture(scope="module", params=VARIANTS)
def variant(request):
    return request.param


@pytest.fixture(scope="module", params=KERNEL_IMPLEMENTATIONS)
def implementation_name(request):
    """The narrow-scanner tests run on the CPU runtimes and every GPU present (conftest.KERNEL_IMPLEMENTATIONS)."""
    return request.param


@pytest.fixture(scope="module")
def device_under_test(implementation_name):
    return implementation_device(implementation_name)


@pytest.fixture(scope="module")
def kernels32(device_under_test, variant):
    return ScannerKernels(NARROW, KernelSettings(variant=variant), device=device_under_test)


@pytest.fixture(scope="module")
def kernels64(implementation_name, variant):
    device = implementation_device(implementation_name, double=True)
    return ScannerKernels(NARROW, KernelSettings(double=True, variant=variant), device=device)


_REFERENCES = {}


def reference(phantom, config):
    """The float64 reference rendering, made once per phantom and scanner: every implementation
    and variant is compared with the same one (the reference takes most of these tests' time)."""
    digest = hashlib.sha256(repr(config).encode())
    for name in ("x_um", "y_um", "z_um", "energy_pct"):
        digest.update(np.ascontiguousarray(getattr(phantom, name), dtype=np.float64).tobytes())
    key = digest.hexdigest()
    if key not in _REFERENCES:
        _REFERENCES[key] = render(phantom, config, backend="numpy")
    return _REFERENCES[key]


def kernel_rendering(kernels, phantom, for_adjoint=False):
    with np.errstate(divide="ignore"):  # E = 0 → u = −∞, a = 0
        log_energy = np.log(phantom.energy_pct)
    kernels.set_phantom(phantom.x_um, phantom.y_um, phantom.z_um, log_energy)
    return Rendering.from_a_scans(kernels.forward(for_adjoint))


def compare(kernels, phantom, tolerance):
    """Render with kernels and reference; assert agreement and finite gradients."""
    ours = kernel_rendering(kernels, phantom, for_adjoint=True)
    theirs = reference(phantom, kernels.config)
    assert np.isfinite(ours.a_scans).all() and np.isfinite(ours.display).all()
    scale = np.abs(theirs.a_scans).max()
    error = np.abs(ours.a_scans - theirs.a_scans).max() / scale if scale else np.abs(ours.a_scans).max()
    assert error < tolerance, f"relative A-scan error {error:.2e}"
    grad_display = np.random.default_rng(0).normal(size=ours.display.shape)
    grad_u, grad_z = kernels.adjoint(display_vjp(ours, grad_display))
    assert np.isfinite(grad_u).all() and np.isfinite(grad_z).all()
    return ours, theirs, grad_u, grad_z


def random_phantom(count, rng, energy=(0.1, 5.0), half_width_um=150.0):
    return Phantom(rng.uniform(-half_width_um, half_width_um, count), rng.uniform(-3, 3, count),
                   rng.uniform(0, 1536, count), rng.uniform(*energy, count))


@pytest.mark.parametrize("precision, tolerance", [("float32", 1e-5), ("float64", 1e-7)])
def test_random_scene_matches_reference(precision, tolerance, kernels32, kernels64):
    kernels = kernels32 if precision == "float32" else kernels64
    phantom = random_phantom(4000, np.random.default_rng(1))
    ours, theirs, _, _ = compare(kernels, phantom, tolerance)
    index_diff = ref.colour_index(ours.display).astype(int) - ref.colour_index(theirs.display)
    assert np.mean(index_diff == 0) >= 0.999 and np.abs(index_diff).max() <= 1


@pytest.mark.parametrize("double, tolerance", [(False, 1e-5), (True, 1e-7)])
def test_the_widest_spreading_builds_and_matches_the_reference(double, tolerance, device_under_test):
    """W = 16: the work-item kernels compute 16 weights in 256-bit pieces (8 floats, 4 doubles),
    the widest that PoCL's LLVM compiles the vector builtins for without AVX-512."""
    kernels = ScannerKernels(NARROW, KernelSettings(spread_width=16, double=double, variant="work-item"),
                             device=device_under_test)
    compare(kernels, random_phantom(2000, np.random.default_rng(4)), tolerance)


@pytest.mark.parametrize("double, tolerance", [(False, 1e-5), (True, 1e-7)])
def test_bins_that_lanes_do_not_divide(double, tolerance, device_under_test):
    """A 13 µm beam makes bins of P = 10 A-scans, and 64 A-scans end in a bin of 4: the work-item
    kernels' last lanes of a bin (10 = 8 + 2 floats, 4 + 4 + 2 doubles) and of the B-scan stay idle,
    and forward and adjoint still agree with the reference and with the work-group variant."""
    config = ScannerConfig(a_scans=64, xmax_um=384.0, beam_radius_um=13.0)
    phantom = random_phantom(2000, np.random.default_rng(5), half_width_um=190.0)
    gradients = []
    for variant in VARIANTS:
        kernels = ScannerKernels(config, KernelSettings(double=double, variant=variant), device=device_under_test)
        assert kernels.ascans_per_bin == 10
        gradients.append(compare(kernels, phantom, tolerance)[2:])
    for item, group in zip(*gradients):
        assert np.abs(item - group).max() <= 100 * tolerance * np.abs(group).max()


def test_phase_error_below_a_milliradian_up_to_the_bottom(kernels32):
    """Float32 kernels keep the carrier phase of deep scatterers: the host reduces φ = −2·k0·z in float64."""
    for z_um in (0.3, 700.123456, 1535.987654, 1536.0):
        phantom = Phantom([0.0], [0.0], [z_um], [1.0])
        ours = kernel_rendering(kernels32, phantom).a_scans[:, NARROW.a_scans // 2]
        theirs = reference(phantom, NARROW).a_scans[:, NARROW.a_scans // 2]
        peak = np.argmax(np.abs(theirs))
        assert abs(np.angle(ours[peak] / theirs[peak])) < 1e-3


def test_mirror_blacks_out_everything_below(kernels32):
    """E = 100 at the beam centre of an A-scan: t = 1, every deeper scatterer there adds exactly 0."""
    rng = np.random.default_rng(2)
    centre = NARROW.a_scans // 2  # A-scan at x = 0
    mirror_z = 600.0
    above = Phantom(rng.uniform(-2, 2, 200), np.zeros(200), rng.uniform(0, mirror_z - 1, 200), np.full(200, 2.0))
    below = Phantom(rng.uniform(-2, 2, 200), np.zeros(200), rng.uniform(mirror_z + 1, 1536, 200), np.full(200, 2.0))
    mirror = Phantom([0.0], [0.0], [mirror_z], [100.0])
    with_below = concat(above, mirror, below)
    ours, _, grad_u, grad_z = compare(kernels32, with_below, 1e-5)
    without_below = kernel_rendering(kernels32, concat(above, mirror))
    np.testing.assert_array_equal(ours.a_scans[:, centre], without_below.a_scans[:, centre])
    # Scatterers below the mirror are only seen by the other A-scans: finite, non-zero gradients.
    assert np.abs(grad_z[-200:]).max() > 0


def test_zero_and_tiny_energies(kernels32):
    rng = np.random.default_rng(3)
    phantom = random_phantom(1000, rng)
    phantom.energy_pct[::3] = 0.0
    phantom.energy_pct[1::3] = 1e-12
    _, _, grad_u, grad_z = compare(kernels32, phantom, 1e-5)
    assert np.all(grad_z[::3] == 0)


def test_coincident_depths_follow_the_scanners_tie_order(kernels32):
    """Equal depths shadow each other in the order of NumPy's classic argsort, as the reference does."""
    rng = np.random.default_rng(4)
    count = 600
    phantom = Phantom(rng.uniform(-20, 20, count), rng.uniform(-3, 3, count),
                      np.repeat([100.0, 400.0, 400.0 + 1e-9, 900.0], count // 4),
                      rng.uniform(20, 90, count))
    compare(kernels32, phantom, 1e-5)


def test_depth_limits_wrap_like_the_dft(kernels32):
    rng = np.random.default_rng(5)
    count = 400
    phantom = Phantom(rng.uniform(-150, 150, count), rng.uniform(-3, 3, count),
                      np.where(np.arange(count) % 2, 0.0, 1536.0), rng.uniform(0.1, 5, count))
    ours, _, _, _ = compare(kernels32, phantom, 1e-5)
    # The DFT wraps: scatterers at 1536 µm also light the first rows.
    assert ours.magnitude[0].max() > ours.magnitude[NARROW.depth_pixels // 2].max()


def test_elevation_at_ten_microns(kernels32):
    rng = np.random.default_rng(6)
    phantom = random_phantom(1000, rng)
    phantom.y_um[:] = np.where(np.arange(1000) % 2, 10.0, -10.0)
    compare(kernels32, phantom, 1e-5)


def test_single_scatterer_and_empty_phantom(kernels32):
    compare(kernels32, Phantom([12.3], [1.0], [321.0], [5.0]), 1e-5)
    empty = Phantom([], [], [], [])
    ours, theirs, grad_u, grad_z = compare(kernels32, empty, 1e-5)
    np.testing.assert_array_equal(ours.levels, theirs.levels)
    assert grad_u.size == 0 and grad_z.size == 0


def test_all_scatterers_in_one_window(variant):
    """300,000 scatterers within one A-scan's contribution window (full-size scanner)."""
    rng = np.random.default_rng(7)
    count = 300_000
    phantom = Phantom(rng.uniform(-5, 5, count), rng.uniform(-3, 3, count),
                      rng.uniform(0, 1536, count), np.full(count, 1e-3))
    compare(ScannerKernels(settings=KernelSettings(variant=variant)), phantom, 1e-5)


def test_full_phantom_at_the_caps(variant):
    """300,000 rows at the limits: |x| = 1536, |y| = 3, z ∈ {0, 1536}, E = 100 (mirrors)."""
    count = 300_000
    index = np.arange(count)
    phantom = Phantom(np.where(index % 2, 1536.0, -1536.0), np.where(index % 3, 3.0, -3.0),
                      np.where(index % 5, 1536.0, 0.0), np.full(count, 100.0))
    compare(ScannerKernels(settings=KernelSettings(variant=variant)), phantom, 1e-5)


def concat(*phantoms):
    return Phantom(*(np.concatenate([getattr(p, name) for p in phantoms])
                     for name in ("x_um", "y_um", "z_um", "energy_pct")))


# ---------------------------------------------------------------- gradients
def smooth_loss(rendering, target, weight):
    """½·Σ w·(D − target)²: smooth in D (no quantisation)."""
    return 0.5 * np.sum(weight * (rendering.display - target) ** 2)


@pytest.mark.parametrize("energy", [(0.1, 5.0), (20.0, 90.0)], ids=["weak-shadowing", "strong-shadowing"])
def test_gradients_match_reference_finite_differences(energy, kernels32):
    """∂L/∂z and ∂L/∂u of float32 kernels vs float64 central differences of the reference.

    The sample is drawn among the scatterers with the largest gradients (a
    gradient far below the loss's rounding noise cannot be checked by finite
    differences); relative error ≤ 1e−3 is required.
    """
    rng = np.random.default_rng(8)
    phantom = random_phantom(800, rng, energy=energy, half_width_um=60.0)
    target = rng.uniform(0, 1, NARROW.shape)
    weight = rng.uniform(0, 1, NARROW.shape)
    rendering = kernel_rendering(kernels32, phantom, for_adjoint=True)
    grad_u, grad_z = kernels32.adjoint(display_vjp(rendering, weight * (rendering.display - target)))
    log_energy = np.log(phantom.energy_pct)
    for name, grad, step in (("z", grad_z, 2e-5), ("u", grad_u, 1e-5)):
        for j in rng.choice(np.argsort(-np.abs(grad))[:100], 5, replace=False):
            losses = []
            for sign in (1, -1):
                z_um, energy_pct = phantom.z_um.copy(), phantom.energy_pct.copy()
                if name == "z":
                    z_um[j] += sign * step
                else:
                    energy_pct[j] = np.exp(log_energy[j] + sign * step)
                shifted = Phantom(phantom.x_um, phantom.y_um, z_um, energy_pct)
                losses.append(smooth_loss(reference(shifted, NARROW), target, weight))
            finite_difference = (losses[0] - losses[1]) / (2 * step)
            assert abs(grad[j] - finite_difference) <= 1e-3 * abs(finite_difference), (
                f"∂L/∂{name}[{j}]: adjoint {grad[j]:.6e}, finite difference {finite_difference:.6e}")


def test_mirror_gradients_are_finite_and_exact(kernels64):
    """With a mirror (t = 1) the suffix-product adjoint still matches finite differences."""
    rng = np.random.default_rng(9)
    phantom = concat(random_phantom(300, rng, energy=(1.0, 10.0), half_width_um=30.0),
                     Phantom([0.0], [0.0], [700.0], [100.0]))
    target = rng.uniform(0, 1, NARROW.shape)
    weight = rng.uniform(0, 1, NARROW.shape)
    rendering = kernel_rendering(kernels64, phantom, for_adjoint=True)
    grad_u, grad_z = kernels64.adjoint(display_vjp(rendering, weight * (rendering.display - target)))
    assert np.isfinite(grad_u).all() and np.isfinite(grad_z).all()
    shallower = np.flatnonzero(phantom.z_um < 700.0)
    j = shallower[np.argmax(np.abs(grad_u[shallower]))]
    losses = []
    for sign in (1, -1):
        energy_pct = phantom.energy_pct.copy()
        energy_pct[j] *= np.exp(sign * 1e-5)
        losses.append(smooth_loss(reference(Phantom(phantom.x_um, phantom.y_um, phantom.z_um, energy_pct), NARROW),
                                  target, weight))
    finite_difference = (losses[0] - losses[1]) / 2e-5
    assert abs(grad_u[j] - finite_difference) <= 1e-3 * abs(finite_difference)


def test_min_transmission_stops_early_with_bounded_error(kernels32):
    """The skip knob: stopping once T ≤ τ changes pixels by at most ~τ of the shallow signal."""
    rng = np.random.default_rng(10)
    phantom = random_phantom(3000, rng, energy=(5.0, 30.0))
    exact = kernel_rendering(kernels32, phantom)
    skipping = ScannerKernels(NARROW, KernelSettings(min_transmission=1e-3, variant=kernels32.variant),
                              device=kernels32.device)
    approx = kernel_rendering(skipping, phantom)
    error = np.abs(approx.a_scans - exact.a_scans).max() / np.abs(exact.a_scans).max()
    assert 0 < error < 1e-2


def test_settings_are_validated():
    with pytest.raises(ValueError, match="spread_width"):
        KernelSettings(spread_width=1)
    with pytest.raises(ValueError, match="shadow_radius_sq"):
        KernelSettings(shadow_radius_sq=2.0)
    with pytest.raises(ValueError, match="power-of-two"):
        ScannerKernels(ScannerConfig(depth_pixels=250))


def test_straight_through_levels_scale_the_display_gradient(kernels32):
    phantom = random_phantom(500, np.random.default_rng(11))
    rendering = kernel_rendering(kernels32, phantom)
    grad = np.random.default_rng(12).normal(size=rendering.display.shape)
    np.testing.assert_allclose(display_vjp(rendering, grad, through_levels=True),
                               display_vjp(rendering, grad) * 256 / 255)


@pytest.mark.official
@pytest.mark.parametrize("kind", ["uniform", "layers"])
def test_official_phantoms_match_the_reference_pixel_for_pixel(kind, variant, official_reference):
    """Done-when of the kernels: ≥ 99.9 % identical 8-bit pixels, colour index never off by more than 1."""
    ours = render(Phantom.baseline(kind, 42), settings=KernelSettings(variant=variant))
    theirs = official_reference(kind, 42)
    identical = np.mean(ours.levels == theirs.levels)
    index_error = np.abs(ref.colour_index(ours.display).astype(int) - ref.colour_index(theirs.display))
    assert identical >= 0.999 and index_error.max() <= 1, f"{identical:.5%} identical, max {index_error.max()}"


# ------------------------------------------------------- overall energy scale
def _uniform_scene(energy_pct, count=300_000 * NARROW.a_scans // 512, seed=13):
    """The full scanner's scatterer density (300,000 over 512 A-scans) on the narrow scanner."""
    rng = np.random.default_rng(seed)
    half_width = NARROW.xmax_um / 2
    return Phantom(rng.uniform(-half_width, half_width, count), rng.uniform(-3, 3, count),
                   rng.uniform(0, 1536, count), np.broadcast_to(energy_pct, (count,)))


def _assert_renders_as_reference(kernels, phantom):
    ours = kernel_rendering(kernels, phantom)
    theirs = reference(phantom, kernels.config)
    index_error = np.abs(ref.colour_index(ours.display).astype(int) - ref.colour_index(theirs.display))
    identical = np.mean(ours.levels == theirs.levels)
    assert identical >= 0.999 and index_error.max() <= 1, f"{identical:.5%} identical, max {index_error.max()}"


@pytest.mark.parametrize("energy_pct", [1.0, 1e-20, 1e-80, 1e-200, 1e-300])
def test_uniform_energy_renders_as_the_reference_at_any_scale(kernels32, energy_pct):
    """The display is normalised to its brightest pixel, so one energy for all renders the
    same scan at any scale (shadowing aside); float32 kernels keep that down to E = 1e−300 %."""
    _assert_renders_as_reference(kernels32, _uniform_scene(energy_pct))


def test_energies_spanning_the_whole_legal_range(kernels32):
    rng = np.random.default_rng(14)
    count = 300_000 * NARROW.a_scans // 512
    _assert_renders_as_reference(kernels32, _uniform_scene(10.0 ** rng.uniform(-300, 2, count)))


@pytest.mark.parametrize("energy_pct", [5e-324, 1e-320, 2.2250738585072014e-308],
                         ids=["smallest-subnormal", "subnormal", "smallest-normal"])
def test_smallest_positive_float64_energies(kernels32, energy_pct):
    """E/100 underflows (to 0 or to a coarse subnormal) in the scanner's a = sqrt(E/100): the kernels follow."""
    _assert_renders_as_reference(kernels32, _uniform_scene(energy_pct))


def test_gradients_of_a_scaled_phantom_match_finite_differences(kernels32):
    """Energies × 1e−250: the display and ∂L/∂z, ∂L/∂u do not depend on the scale."""
    rng = np.random.default_rng(15)
    phantom = random_phantom(800, rng, energy=(1e-250, 5e-250), half_width_um=60.0)
    target = rng.uniform(0, 1, NARROW.shape)
    weight = rng.uniform(0, 1, NARROW.shape)
    rendering = kernel_rendering(kernels32, phantom, for_adjoint=True)
    grad_u, grad_z = kernels32.adjoint(display_vjp(rendering, weight * (rendering.display - target)))
    assert np.isfinite(grad_u).all() and np.isfinite(grad_z).all()
    log_energy = np.log(phantom.energy_pct)
    for name, grad, step in (("z", grad_z, 2e-5), ("u", grad_u, 1e-5)):
        for j in rng.choice(np.argsort(-np.abs(grad))[:100], 3, replace=False):
            losses = []
            for sign in (1, -1):
                z_um, energy_pct = phantom.z_um.copy(), phantom.energy_pct.copy()
                if name == "z":
                    z_um[j] += sign * step
                else:
                    energy_pct[j] = np.exp(log_energy[j] + sign * step)
                shifted = Phantom(phantom.x_um, phantom.y_um, z_um, energy_pct)
                losses.append(smooth_loss(reference(shifted, NARROW), target, weight))
            finite_difference = (losses[0] - losses[1]) / (2 * step)
            assert abs(grad[j] - finite_difference) <= 1e-3 * abs(finite_difference), (
                f"∂L/∂{name}[{j}]: adjoint {grad[j]:.6e}, finite difference {finite_difference:.6e}")


# ------------------------------------------------------------------ variants
def test_variants_agree_and_repeat_bit_for_bit(device_under_test):
    """Both variants give the same A-scans and gradients to float32 rounding; each repeats exactly."""
    phantom = random_phantom(3000, np.random.default_rng(16), energy=(1.0, 40.0))
    results = {}
    for variant in VARIANTS:
        kernels = ScannerKernels(NARROW, KernelSettings(variant=variant), device=device_under_test)
        runs = []
        for _ in range(2):
            rendering = kernel_rendering(kernels, phantom, for_adjoint=True)
            runs.append((rendering.a_scans, *kernels.adjoint(display_vjp(rendering, rendering.display - 0.5))))
        for first, second in zip(*runs):
            np.testing.assert_array_equal(first, second)
        results[variant] = runs[0]
    (a_item, u_item, z_item), (a_group, u_group, z_group) = results.values()
    assert np.abs(a_item - a_group).max() <= 1e-5 * np.abs(a_item).max()
    for item, group in ((u_item, u_group), (z_item, z_group)):
        assert np.abs(item - group).max() <= 1e-4 * np.abs(item).max()


def test_variant_follows_the_device_type(device_under_test):
    """'auto' takes the work-item variant on a CPU device and the work-group one on any other (a GPU); the
    depth order, a single work-item, runs on the scanner's own device on a CPU and on a CPU device beside a
    GPU. Holds on every device type: each asserts what its own type gets."""
    import pyopencl as cl

    from octcl.device.scanner import sort_device_for

    automatic = ScannerKernels(NARROW, device=device_under_test)
    on_cpu = bool(device_under_test.type & cl.device_type.CPU)
    assert automatic.variant == ("work-item" if on_cpu else "work-group")
    assert automatic.work_group_size <= device_under_test.max_work_group_size
    sorter = sort_device_for(device_under_test)
    if on_cpu:
        assert sorter == device_under_test
    else:
        assert sorter is None or sorter.type & cl.device_type.CPU
    beside_a_gpu = sort_device_for(_FakeGpu())
    assert beside_a_gpu is None or beside_a_gpu.type & cl.device_type.CPU


class _FakeGpu:
    """Stands in for a GPU device where only the type is read."""

    @property
    def type(self):
        import pyopencl as cl

        return cl.device_type.GPU

    name = "Fake GPU"


def test_single_work_item_sort_refuses_a_gpu():
    from octcl.device.depth_order import introsort_argsort_opencl

    with pytest.raises(ValueError, match="CPU devices only"):
        introsort_argsort_opencl(np.array([3, 1, 1, 2] * 10), device=_FakeGpu())


def test_variant_is_validated():
    with pytest.raises(ValueError, match="variant"):
        KernelSettings(variant="warp")


# ---------------------------------------------------------- contribution windows
def test_contribution_ranges_follow_the_reference_window_test():
    """The host's window ends are exactly the A-scans the reference's own float64 test admits."""
    from octcl.device.scanner import contribution_ranges

    config = ScannerConfig()
    rng = np.random.default_rng(17)
    pitch, w0 = config.lateral_pitch_um, config.beam_radius_um
    edge = np.sqrt(3) * w0  # scatterers exactly on or next to the window's edge
    x_um = np.concatenate([rng.uniform(-1536, 1536, 20_000), np.array([-1536.0, 1536.0, 0.0]),
                           (rng.integers(-256, 256, 2000) * pitch + edge * rng.choice([-1, 1], 2000))
                           * (1 + rng.choice([-1e-16, 0, 1e-16], 2000))])
    y_um = np.concatenate([rng.uniform(-10, 10, 20_000), np.array([0.0, 0.0, 10.0]), np.zeros(2000)])
    ranges = contribution_ranges(x_um, y_um, config)
    ascan_x_um = ref.ascan_positions_um(config)
    inside = ref.in_contribution_window(ascan_x_um[None, :] - x_um[:, None], y_um[:, None], w0)
    first = np.where(inside.any(axis=1), inside.argmax(axis=1), 1)
    last = np.where(inside.any(axis=1), config.a_scans - 1 - inside[:, ::-1].argmax(axis=1), 0)
    np.testing.assert_array_equal(ranges, np.stack([first, last], axis=1))


# ------------------------------------------------------------- under Oclgrind
#: Oclgrind interprets every work-item, so its scenes are small: 8 A-scans 6 µm apart.
SMALL = ScannerConfig(a_scans=8, xmax_um=48.0)


@pytest.fixture(scope="module", params=["oclgrind"])
def oclgrind_device(request):
    return implementation_device(request.param)


@pytest.mark.parametrize("double, tolerance", [(False, 1e-5), (True, 1e-7)], ids=["float32", "float64"])
def test_kernels_under_oclgrind_report_nothing_and_match_the_reference(oclgrind_device, variant, double,
                                                                      tolerance, capfd):
    """Forward and adjoint on a random scene and on a stiff one (a mirror, zero and tiny energies):
    no Oclgrind report (out-of-bounds access, data race, barrier divergence, API misuse), A-scans
    and pixels as the reference's, gradients as its finite differences.

    Oclgrind 21.10's ldexp(floatn, int) reads lanes 1 … n − 1 of the scalar exponent from past its
    end: the work-item kernels once passed one there and matched the reference on 9 % of pixels."""
    start = OCLGRIND_LOG.stat().st_size if OCLGRIND_LOG.exists() else 0
    kernels = ScannerKernels(SMALL, KernelSettings(variant=variant, double=double), device=oclgrind_device)
    rng = np.random.default_rng(18)
    random_scene = random_phantom(300, rng, half_width_um=24.0)
    stiff = concat(random_phantom(200, rng, energy=(1.0, 40.0), half_width_um=24.0),
                   Phantom([0.0], [0.0], [700.0], [100.0]))
    stiff.energy_pct[:40:2] = 0.0
    stiff.energy_pct[1:40:2] = 1e-12
    for phantom in (random_scene, stiff):
        ours, theirs, _, _ = compare(kernels, phantom, tolerance)
        assert np.mean(ours.levels == theirs.levels) >= 0.999
    target = rng.uniform(0, 1, SMALL.shape)
    rendering = kernel_rendering(kernels, random_scene, for_adjoint=True)
    _, grad_z = kernels.adjoint(display_vjp(rendering, rendering.display - target))
    for j in np.argsort(-np.abs(grad_z))[:3]:
        losses = []
        for sign in (1, -1):
            z_um = random_scene.z_um.copy()
            z_um[j] += sign * 2e-5
            shifted = Phantom(random_scene.x_um, random_scene.y_um, z_um, random_scene.energy_pct)
            losses.append(smooth_loss(reference(shifted, SMALL), target, 1.0))
        finite_difference = (losses[0] - losses[1]) / 4e-5
        assert abs(grad_z[j] - finite_difference) <= 1e-3 * abs(finite_difference)
    log = OCLGRIND_LOG.read_bytes()[start:].decode(errors="replace") if OCLGRIND_LOG.exists() else ""
    reports = oclgrind_reports(log + capfd.readouterr().err)
    assert not reports, "Oclgrind reports:\n" + "\n\n".join(reports)


def test_kernels_made_on_a_thread_render_as_those_made_here():
    """scanner_in_background: the same kernels on octcl's device, made beside the caller (a run's stage 1)."""
    from octcl.device.scanner import scanner_in_background

    future = scanner_in_background(NARROW)
    phantom = Phantom([12.3, -40.0], [1.0, 0.0], [321.0, 640.0], [5.0, 0.5])
    ours, theirs = future.result(timeout=120), ScannerKernels(NARROW)
    assert ours.context is theirs.context  # one context per device and process: buffers pass between them
    for kernels in (ours, theirs):
        kernels.set_phantom(phantom.x_um, phantom.y_um, phantom.z_um, np.log(phantom.energy_pct))
    np.testing.assert_array_equal(ours.forward(), theirs.forward())


def test_an_error_making_them_on_a_thread_is_the_futures(monkeypatch):
    from octcl.device import scanner
    from octcl.device.runtime import OpenCLUnavailableError

    with pytest.raises(ValueError, match="power-of-two"):  # raised on the thread
        scanner.scanner_in_background(ScannerConfig(depth_pixels=250)).result(timeout=120)

    def no_device(choice=None):
        raise OpenCLUnavailableError("no OpenCL device")

    monkeypatch.setattr(scanner, "select_device", no_device)  # raised before the thread starts
    assert isinstance(scanner.scanner_in_background(NARROW).exception(timeout=10), OpenCLUnavailableError)
