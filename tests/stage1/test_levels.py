"""The target's levels as displays, magnitudes and intervals (host/stage1/levels.py)."""


import numpy as np
import pytest

from octcl import _reference as ref
from octcl._io import GREY_LUT, read_png_rgb, read_scan
from octcl.config import ScannerConfig
from octcl.host.stage1.levels import target_display, target_levels, target_magnitude

#: A small scanner (32 rows, 16 A-scans of 6 µm) for the reference comparisons.
SMALL = ScannerConfig(depth_pixels=32, a_scans=16, xmax_um=96.0)


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
