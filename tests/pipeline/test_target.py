"""Targets as arrays: read from a PNG once, in the form that every stage reads as it reads the file."""

import numpy as np
import pytest
from PIL import Image

from octcl import scorer
from octcl._io import ImageFormatError, read_png_pixels, read_scan, write_grey_png
from octcl.host.pipeline.target import check_target, read_target, target_scan, target_struct_for_metrics

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


def test_npy_target_reads_as_the_grey_png_of_its_levels(layers_path, tmp_path):
    """A .npy of levels: the 2-D target of the scanner's PNG of them, read as that PNG by every stage."""
    levels = np.asarray(Image.open(layers_path))[..., 0]
    np.save(tmp_path / "layers.npy", levels)
    write_grey_png(tmp_path / "layers.png", levels)
    np.testing.assert_array_equal(read_png_pixels(tmp_path / "layers.png"), read_png_pixels(layers_path))
    target = read_target(tmp_path / "layers.npy")
    assert target.dtype == np.uint8 and target.shape == SHAPE and target.flags.writeable
    np.testing.assert_array_equal(target, read_target(tmp_path / "layers.png"))
    np.testing.assert_array_equal(target, read_target(layers_path))
    np.testing.assert_array_equal(target_scan(target), read_scan(tmp_path / "layers.png", SHAPE))
    np.testing.assert_array_equal(target_struct_for_metrics(target),
                                  scorer._read_map_for_metrics(tmp_path / "layers.png"))
    # The kind is told by the bytes, not the name.
    (tmp_path / "named.png").write_bytes((tmp_path / "layers.npy").read_bytes())
    np.testing.assert_array_equal(read_target(tmp_path / "named.png"), target)


@pytest.mark.parametrize("array, message", [
    (np.zeros(SHAPE), "float64 array; a B-scan is a 2-D uint8 array of grey levels (256x512, rows x columns)"),
    (np.zeros(SHAPE + (3,), np.uint8), "3-D array of shape (256, 512, 3); a B-scan is a 2-D uint8 array"),
    (np.zeros((255, 512), np.uint8), "array is 255x512 (rows x columns), expected 256x512"),
    (np.full(SHAPE, None, dtype=object), ".npy of Python objects (dtype object), not loaded"),
    (np.zeros(SHAPE, np.uint8), "every pixel is black"),
])
def test_npy_that_is_not_a_target_is_refused_naming_the_file(tmp_path, array, message):
    path = tmp_path / "x.npy"
    np.save(path, array, allow_pickle=array.dtype == object)
    with pytest.raises(ImageFormatError) as info:
        read_target(path)
    assert str(info.value).startswith(f"{path}: {message}")


def test_png_targets_read_and_fail_as_before(tmp_path, target_files):
    """Reading the file's bytes once changes nothing for PNGs: the same arrays, the same messages."""
    from octcl.config import DEFAULT_CONFIG
    from octcl.host.pipeline.target import _target_of_pixels

    for kind, path in target_files.items():  # the earlier reading: the PNG's pixels, then the smaller form
        before = _target_of_pixels(read_png_pixels(path, SHAPE), DEFAULT_CONFIG, str(path))
        after = read_target(path)
        assert after.shape == before.shape, kind
        np.testing.assert_array_equal(after, before, err_msg=kind)
    (tmp_path / "text.png").write_text("x y z E\n")
    with pytest.raises(ImageFormatError, match=r"text\.png: not a PNG file \(missing PNG signature\)$"):
        read_target(tmp_path / "text.png")
    with pytest.raises(ImageFormatError, match=r"missing\.png: no such file$"):
        read_target(tmp_path / "missing.png")
    with pytest.raises(ImageFormatError, match=r"is a directory, not a PNG file$"):
        read_target(tmp_path)
