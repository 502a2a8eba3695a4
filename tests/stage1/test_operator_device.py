"""Stage 1's field operator as OpenCL kernels (host/stage1/operator_device.py) against its float64 NumPy twin.

Every test runs on each OpenCL implementation present, in float32 and
float64 (the test id names both): PoCL and Intel's CPU runtime at the
default scanner (Nz = 256, Nx = 512, columns padded to P = 1024), Oclgrind
at a small one (Nx = 8, P = 16: most work-items of the lateral transforms
idle). Oclgrind interprets every work-item and checks every memory access,
data races and the API calls; each test run on it fails on any report.
SHORT (Nz = 64, Nx = 100) runs on all three.

Agreement is max |ours − twin's| relative to max |twin's| on random complex
fields N(0, 1) + i·N(0, 1): measured 1.6e−7 to 2.6e−7 (float32) and 4.7e−16
to 1.1e−15 (float64) for H and H⁺, so 1e−6 and 1e−13 are asserted; so is the
adjoint identity's gap |⟨H·x, y⟩ − ⟨x, Hᴴ·y⟩|/(‖H·x‖·‖y‖), measured 1.8e−10
to 1.8e−9 (float32) and 2.5e−18 to 1.1e−17 (float64).
"""

import re

import numpy as np
import pytest
from conftest import KERNEL_IMPLEMENTATIONS, OCLGRIND_LOG, implementation_device, oclgrind_reports

from octcl.device.runtime import implementation
from octcl.config import DEFAULT_CONFIG, ScannerConfig
from octcl.host.stage1.operator_device import FieldKernels

#: Oclgrind's scanner: 8 A-scans 6 µm apart, as tests/device/test_scanner.py's SMALL.
SMALL = ScannerConfig(a_scans=8, xmax_um=48.0)
#: Short A-scans: Nz = 64 gives the depth transforms 32 butterflies a stage for their 64 work-items;
#: Nx = 100, no power of two, pads to P = 128.
SHORT = ScannerConfig(depth_pixels=64, a_scans=100, xmax_um=600.0)

#: Relative max error asserted for each precision (module docstring).
TOLERANCE = {False: 1e-6, True: 1e-13}

CASES = [(name, double) for name in (*KERNEL_IMPLEMENTATIONS, "oclgrind") for double in (False, True)]


def case_id(case) -> str:
    name, double = case
    return f"{name}-{'float64' if double else 'float32'}"


@pytest.fixture(scope="module", params=CASES, ids=[case_id(case) for case in CASES])
def built_kernels(request):
    name, double = request.param
    config = SMALL if name == "oclgrind" else DEFAULT_CONFIG
    return FieldKernels(config, device=implementation_device(name, double), double=double)


def oclgrind_log_from(start: int) -> str:
    return OCLGRIND_LOG.read_bytes()[start:].decode(errors="replace") if OCLGRIND_LOG.exists() else ""


@pytest.fixture
def kernels(built_kernels, capfd):
    """The case's kernels; under Oclgrind the test errs at teardown on any report of what it ran.

    Every test checks its own runs: Oclgrind stops reporting for the rest of
    the process after 1000 errors, so a faulty kernel run by an earlier test
    would leave a later one nothing to read.
    """
    start = OCLGRIND_LOG.stat().st_size if OCLGRIND_LOG.exists() else 0
    yield built_kernels
    if implementation(built_kernels.device) == "oclgrind":
        reports = oclgrind_reports(oclgrind_log_from(start) + capfd.readouterr().err)
        assert not reports, "Oclgrind reports:\n" + "\n\n".join(reports)


def random_field(config: ScannerConfig, seed: int) -> np.ndarray:
    """F[n, i] with real and imaginary parts N(0, 1), (Nz, Nx) complex128."""
    rng = np.random.default_rng(seed)
    return rng.normal(size=config.shape) + 1j * rng.normal(size=config.shape)


def relative_error(ours: np.ndarray, theirs: np.ndarray) -> float:
    return float(np.abs(ours - theirs).max() / np.abs(theirs).max())


def run(kernels: FieldKernels, operation: str, field: np.ndarray) -> np.ndarray:
    """``kernels.<operation>`` of a host field, back on the host."""
    return kernels.to_host(getattr(kernels, operation)(kernels.to_device(field)))


def is_double(kernels: FieldKernels) -> bool:
    return kernels.real == np.float64


# ------------------------------------------------------------ against the twin
def test_the_kernels_pad_the_columns_to_a_power_of_two(kernels):
    nx = kernels.config.a_scans
    reach = (kernels.twin.taps.size - 1) // 2
    padded = kernels.twin.padded_columns
    assert padded & (padded - 1) == 0 and nx + 2 * reach <= padded < 2 * (nx + 2 * reach)


@pytest.mark.parametrize("operation", ["apply", "pseudo_inverse"])
def test_operation_matches_the_float64_twin(kernels, operation):
    field = random_field(kernels.config, seed=1)
    ours = run(kernels, operation, field)
    theirs = getattr(kernels.twin, operation)(field)
    assert np.isfinite(ours).all()
    error = relative_error(ours, theirs)
    assert error < TOLERANCE[is_double(kernels)], f"relative error {error:.2e}"


# -------------------------------------------------------------------- adjoint
def test_adjoint_identity_holds_for_the_kernels(kernels):
    """⟨H·x, y⟩ = ⟨x, Hᴴ·y⟩, both sides from the kernels, relative to ‖H·x‖·‖y‖. FieldKernels' Hᴴ runs
    apply's kernels (H is self-adjoint), so this is the test of that claim: a stencil or window off by one
    sample makes the transfer function complex and breaks the identity."""
    x, y = random_field(kernels.config, seed=2), random_field(kernels.config, seed=3)
    forward, backward = run(kernels, "apply", x), run(kernels, "adjoint", y)
    left, right = np.vdot(y, forward), np.vdot(backward, x)
    gap = abs(left - right) / (np.linalg.norm(forward) * np.linalg.norm(y))
    assert gap < TOLERANCE[is_double(kernels)], f"⟨Hx, y⟩ = {left:.6e}, ⟨x, Hᴴy⟩ = {right:.6e}"


# --------------------------------------------------------------- repeatability
@pytest.mark.parametrize("operation", ["apply", "pseudo_inverse"])
def test_operation_repeats_bit_for_bit_and_in_place(kernels, operation):
    """A second call gives the same bits, and so does writing the result over its input (``out=field``)."""
    device_field = kernels.to_device(random_field(kernels.config, seed=5))
    first = kernels.to_host(getattr(kernels, operation)(device_field))
    second = kernels.to_host(getattr(kernels, operation)(device_field))
    np.testing.assert_array_equal(first, second)
    in_place = getattr(kernels, operation)(device_field, out=device_field)
    assert in_place is device_field
    np.testing.assert_array_equal(kernels.to_host(in_place), first)


# --------------------------------------------------------------------- arrays
def test_fields_round_trip_a_scan_by_a_scan(kernels):
    """to_device stores F[n, i] at i·Nz + n in the kernels' precision; to_host gives (Nz, Nx) complex128 back."""
    field = random_field(kernels.config, seed=6)
    device_field = kernels.to_device(field)
    stored = field.astype(kernels.complex)
    assert device_field.shape == kernels.config.shape[::-1] and device_field.dtype == kernels.complex
    np.testing.assert_array_equal(device_field.get(), stored.T)
    back = kernels.to_host(device_field)
    assert back.dtype == np.complex128
    np.testing.assert_array_equal(back, stored)


def test_a_field_of_another_shape_is_refused_naming_both_shapes(kernels):
    grid = kernels.config.shape
    for shape in (grid[::-1], (grid[0], grid[1] + 1), (grid[0] * grid[1],)):
        message = f"field is {shape}, the scanner's grid is {grid}"
        with pytest.raises(ValueError, match=re.escape(message)):
            kernels.to_device(np.zeros(shape, dtype=np.complex128))


def test_depth_pixels_must_be_a_power_of_two():
    config = ScannerConfig(depth_pixels=250, a_scans=8, xmax_um=48.0)
    with pytest.raises(ValueError, match="power-of-two depth_pixels, got 250"):
        FieldKernels(config)


@pytest.mark.parametrize("double", [False, True], ids=["float32", "float64"])
@pytest.mark.parametrize("implementation", ["pocl", "intel"])
def test_short_a_scans_and_a_number_of_them_that_is_no_power_of_two(implementation, double):
    """SHORT: fewer depth butterflies a stage than work-items, and 28 padding columns."""
    kernels = FieldKernels(SHORT, device=implementation_device(implementation), double=double)
    assert kernels.twin.padded_columns == 128
    field = random_field(SHORT, seed=7)
    for operation in ("apply", "pseudo_inverse"):
        error = relative_error(run(kernels, operation, field), getattr(kernels.twin, operation)(field))
        assert error < TOLERANCE[double], f"{operation}: relative error {error:.2e}"


# ------------------------------------------------------------- under Oclgrind
@pytest.mark.parametrize("double", [False, True], ids=["float32", "float64"])
@pytest.mark.parametrize("config", [SMALL, SHORT], ids=["small", "short"])
@pytest.mark.parametrize("implementation", ["oclgrind"])
def test_kernels_under_oclgrind_report_nothing_and_match_the_twin(implementation, config, double, capfd):
    """H, Hᴴ and H⁺ on the small scanner and on SHORT: no Oclgrind report (out-of-bounds access,
    data race, barrier divergence, API misuse) and the twin's results."""
    start = OCLGRIND_LOG.stat().st_size if OCLGRIND_LOG.exists() else 0
    kernels = FieldKernels(config, device=implementation_device(implementation), double=double)
    field = random_field(config, seed=8)
    for operation in ("apply", "adjoint", "pseudo_inverse"):
        error = relative_error(run(kernels, operation, field), getattr(kernels.twin, operation)(field))
        assert error < TOLERANCE[double], f"{operation}: relative error {error:.2e}"
    reports = oclgrind_reports(oclgrind_log_from(start) + capfd.readouterr().err)
    assert not reports, "Oclgrind reports:\n" + "\n\n".join(reports)
