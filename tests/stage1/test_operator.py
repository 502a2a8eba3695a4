"""The field operator H, Hᴴ and H⁺ against the float64 reference scanner (host/stage1/operator.py)."""


import numpy as np
import pytest

from octcl import _reference as ref
from octcl.config import ScannerConfig
from octcl.host.stage1.operator import FieldOperator, cell_depths_um, lateral_taps
from octcl.phantom import Phantom
from conftest import reference_a_scans, SMALL_SCANNER as SMALL


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
    field = amplitude * np.exp(-2j * config.k0_rad_per_um * z_um)
    expected = reference_a_scans(phantom, config, shadowing=False)
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
