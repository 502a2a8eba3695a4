"""The scanner's ceiling: writable levels, the nearest and the error-diffused images, their scores."""

import numpy as np
import pytest

from octcl._io import GREY_LUT
from octcl.host.stage1.ceiling import WRITABLE, Ceiling, aimed_levels, ceiling_image, error_diffused, measure_ceiling, nearest_writable, writable_share

#: The levels the colour map never writes (shared/physics.md §2, step 11).
UNWRITABLE = (33, 37, 41, 45, 49, 53, 57, 61, 66, 74, 82, 90, 98, 106, 114, 122, 132, 148, 164, 180, 196, 212,
              228, 244)


def naive_floyd_steinberg(levels: np.ndarray) -> np.ndarray:
    """Floyd–Steinberg pixel by pixel: an unwritable level goes to the side of the error it carries."""
    rows, columns = levels.shape
    error = np.zeros((rows + 1, columns + 2))
    aimed = levels.copy()
    nearest_side = np.sign(GREY_LUT.astype(int) - np.arange(256))
    for row in range(rows):
        for column in range(columns):
            e, level = error[row, column + 1], int(levels[row, column])
            if not WRITABLE[level]:
                side = int(np.sign(e)) if e != 0 else int(nearest_side[level])
                aimed[row, column] = level + side
                e -= side
            for d_row, d_column, weight in ((0, 1, 7 / 16), (1, -1, 3 / 16), (1, 0, 5 / 16), (1, 1, 1 / 16)):
                error[row + d_row, column + 1 + d_column] += weight * e
    return aimed


def test_the_scanner_writes_232_levels_and_never_the_24_others():
    assert WRITABLE.sum() == 232
    assert tuple(np.flatnonzero(~WRITABLE)) == UNWRITABLE


def test_nearest_writable_is_the_level_written_for_the_plain_quantisers_interval():
    levels = np.arange(256, dtype=np.uint8).reshape(16, 16)
    nearest = nearest_writable(levels)
    assert WRITABLE[nearest].all()
    changed = nearest != levels
    assert set(levels[changed]) == set(UNWRITABLE)
    assert np.all(np.abs(nearest.astype(int) - levels) <= 1) and np.array_equal(nearest[changed], GREY_LUT[levels[changed]])
    assert np.array_equal(nearest_writable(nearest), nearest)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_error_diffusion_is_floyd_steinberg_on_the_unwritable_pixels_alone(seed):
    rng = np.random.default_rng(seed)
    levels = rng.integers(0, 256, (24, 40)).astype(np.uint8)
    levels[rng.random(levels.shape) < 0.3] = rng.choice(UNWRITABLE)
    aimed = error_diffused(levels)
    assert np.array_equal(aimed, naive_floyd_steinberg(levels))
    assert WRITABLE[aimed].all()
    unwritable = ~WRITABLE[levels]
    assert np.array_equal(aimed[~unwritable], levels[~unwritable])
    assert np.all(np.abs(aimed[unwritable].astype(int) - levels[unwritable]) == 1)


def test_error_diffusion_keeps_the_local_mean_where_one_side_shifts_it():
    levels = np.full((64, 64), 37, np.uint8)  # a patch of an unwritable level
    assert abs(error_diffused(levels).mean() - 37) < 0.01
    assert abs(nearest_writable(levels).mean() - 37) == 1.0


def test_measure_ceiling_scores_the_error_diffused_image_and_spares_a_writable_target():
    def no_score(_):
        raise AssertionError("a writable target is its own best image: nothing to score")

    writable = GREY_LUT[np.random.default_rng(3).integers(0, 256, (8, 8))].astype(np.uint8)
    assert writable_share(writable) == 1.0
    assert measure_ceiling(writable, no_score) == Ceiling(1.0, 1.0)

    levels = writable.copy()
    levels[:2] = 33
    scored = []
    ceiling = measure_ceiling(levels, lambda image: scored.append(image.copy()) or float(len(scored)) / 10)
    assert ceiling.writable_share == pytest.approx(0.75)
    assert len(scored) == 1 and np.array_equal(scored[0], error_diffused(levels))
    # What a run reserves time for scoring (host/pipeline/invert.py) is the image scored here.
    assert ceiling_image(writable) is None and np.array_equal(ceiling_image(levels), scored[0])
    assert ceiling.as_dict() == {"writable_share": 0.75, "diffused_score": 0.1}


def test_the_aim_puts_the_brightest_pixel_at_255_where_the_target_does_not_reach_it():
    levels = np.full((8, 8), 100, np.uint8)
    levels[3, 4] = levels[5, 5] = 240
    levels[0, 0] = 33
    aimed = aimed_levels(levels)
    assert aimed[3, 4] == 255 and aimed[5, 5] == 240  # the first brightest pixel: the scanner's maximum
    others = np.ones(levels.shape, bool)
    others[3, 4] = False
    assert np.array_equal(aimed[others], error_diffused(levels)[others])
    levels[7, 7] = 255
    assert np.array_equal(aimed_levels(levels), error_diffused(levels))


def test_the_diffused_image_is_kept_for_a_second_call_and_handed_out_as_a_copy():
    levels = np.full((8, 16), 37, np.uint8)  # 37 is not writable: every pixel moves
    first = error_diffused(levels)
    first[:] = 0  # the caller's copy
    again = error_diffused(levels)
    assert np.isin(again, (36, 38)).all() and again is not first
    levels[0, 0] = 36  # other levels, another image
    assert error_diffused(levels)[0, 0] == 36
