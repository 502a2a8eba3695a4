"""The level intervals of |A|/max|A| that render each 8-bit level (host/stage1/levels.py)."""


import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from octcl._io import GREY_LUT
from octcl.config import ScannerConfig
from octcl.host.stage1.levels import INTERVAL_MARGIN, level_magnitude_bounds
from octcl.render import Rendering

#: A small scanner (32 rows, 16 A-scans of 6 µm) for the reference renders.
SMALL = ScannerConfig(depth_pixels=32, a_scans=16, xmax_um=96.0)


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
