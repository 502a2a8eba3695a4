"""Targets as arrays: read from a PNG once, in the form that every stage reads as it reads the file."""

import numpy as np
import pytest
from PIL import Image

from octcl import scorer
from octcl._io import ImageFormatError, read_scan
from octcl.host.target import check_target, read_target, target_scan, target_struct_for_metrics

SHAPE = (256, 512)


@pytest.fixture(scope="module")
def layers_path(official_data):
    return official_data / "Scan_Exp2_Layers_A.png"


@pytest.fixture
def target_files(layers_path, tmp_path):
    """The official (opaque grey RGBA) scan and the same levels saved as each other kind of PNG.

    ``coloured`` has R, G and B apart, ``translucent`` an alpha below 255:
    for both the metric's luminance reading differs from the levels'.
    """
    rgba = np.asarray(Image.open(layers_path))
    levels = rgba[..., 0]
    files = {"official": layers_path}
    variants = {
        "rgb": rgba[..., :3],
        "grey": levels,
        "coloured": np.stack([levels, levels // 2, 255 - levels], axis=-1),
        "translucent": np.concatenate([rgba[..., :3], np.full(SHAPE + (1,), 200, np.uint8)], axis=-1),
    }
    for kind, pixels in variants.items():
        files[kind] = tmp_path / f"{kind}.png"
        Image.fromarray(pixels).save(files[kind])
    return files


def test_opaque_grey_files_read_as_levels(target_files):
    levels = read_target(target_files["official"])
    assert levels.dtype == np.uint8 and levels.shape == SHAPE
    np.testing.assert_array_equal(levels, np.asarray(Image.open(target_files["official"]))[..., 0])
    np.testing.assert_array_equal(read_target(target_files["rgb"]), levels)
    assert read_target(target_files["grey"]).shape == SHAPE + (1,)
    assert read_target(target_files["coloured"]).shape == SHAPE + (3,)
    assert read_target(target_files["translucent"]).shape == SHAPE + (4,)


@pytest.mark.parametrize("kind", ["official", "rgb", "grey", "coloured", "translucent"])
def test_target_reads_as_the_file(target_files, kind):
    """The contract's scan and the metric's Struct map of the array are those of the file, bit for bit."""
    path = target_files[kind]
    target = read_target(path)
    np.testing.assert_array_equal(target_scan(target), read_scan(path, SHAPE))
    np.testing.assert_array_equal(target_struct_for_metrics(target), scorer._read_map_for_metrics(path))


def test_grey_png_and_grey_rgba_are_different_targets(target_files):
    """The metric reads 33 levels of an RGBA scan just below v/255, a grey PNG's exactly at v/255."""
    rgba, grey = (target_struct_for_metrics(read_target(target_files[k])) for k in ("official", "grey"))
    np.testing.assert_array_equal(target_scan(read_target(target_files["official"])),
                                  target_scan(read_target(target_files["grey"])))
    assert not np.array_equal(scorer._msssim_input(rgba), scorer._msssim_input(grey))


def test_grey_alpha_file_is_refused(tmp_path):
    path = tmp_path / "la.png"
    Image.fromarray(np.arange(256 * 512, dtype=np.uint32).reshape(SHAPE).astype(np.uint8)).convert("LA").save(path)
    with pytest.raises(ImageFormatError, match="grey\\+alpha") as info:
        read_target(path)
    assert str(path) in str(info.value)


@pytest.mark.parametrize("array, message", [
    (np.zeros(SHAPE, np.float32), "uint8"),
    (np.zeros(SHAPE + (2,), np.uint8), "uint8 \\(Nz, Nx\\) or \\(Nz, Nx, C\\)"),
    (np.arange(128 * 512).reshape(128, 512).astype(np.uint8), "128x512 .* expected 256x512"),
    (np.full(SHAPE, 255, np.uint8), "every pixel is white"),
    (np.full(SHAPE + (4,), 7, np.uint8), "every pixel is grey level 7"),
])
def test_bad_arrays_are_refused_naming_the_target(array, message):
    with pytest.raises(ImageFormatError, match=message) as info:
        check_target(array, name="scan 17")
    assert str(info.value).startswith("scan 17: ")
