"""PNG reading and writing, B-scan arrays: strict checks with messages that name the file and the problem."""

import io
import os
import re
import struct
import zlib

import numpy as np
import pytest
from PIL import Image

from octcl._io import (GREY_LUT, MAX_IMAGE_FILE_BYTES, MAX_IMAGE_PIXELS, PNG_SIGNATURE, SCAN_SHAPE, ImageFormatError,
                       OutputError, _png_chunk, atomic_write, check_scan_levels, decode_scan_levels,
                       grey_rgba_pixels, read_image_bytes, read_png_pixels, read_png_rgb, read_scan, read_scan_pixels,
                       write_grey_png)

SHAPE = (256, 512)


def save(path, array, mode=None, **kwargs):
    image = Image.fromarray(array) if mode is None else Image.fromarray(array).convert(mode)
    image.save(path, **kwargs)
    return path


def test_grey_rgba_round_trip(tmp_path):
    levels = np.random.default_rng(0).integers(0, 256, SHAPE, dtype=np.uint8)
    write_grey_png(tmp_path / "scan.png", levels)
    with Image.open(tmp_path / "scan.png") as image:
        assert image.mode == "RGBA"
        rgba = np.asarray(image)
    np.testing.assert_array_equal(rgba[..., :3], np.repeat(levels[..., None], 3, axis=2))
    assert (rgba[..., 3] == 255).all()
    scan = read_scan(tmp_path / "scan.png", SHAPE)
    assert scan.dtype == np.float32
    np.testing.assert_array_equal(np.rint(scan * 255), levels)


@pytest.mark.parametrize("mode", ["L", "LA", "RGB", "RGBA"])
def test_every_8bit_colour_type_reads(tmp_path, mode):
    levels = np.arange(256 * 512, dtype=np.uint32).reshape(SHAPE).astype(np.uint8)
    path = save(tmp_path / f"{mode}.png", levels, mode)
    np.testing.assert_array_equal(read_png_rgb(path, SHAPE)[..., 0], levels)


def test_read_scan_averages_the_colour_channels(tmp_path):
    rgb = np.zeros(SHAPE + (3,), dtype=np.uint8)
    rgb[..., 0], rgb[..., 1], rgb[..., 2] = 30, 60, 90
    scan = read_scan(save(tmp_path / "colour.png", rgb), SHAPE)
    assert scan.dtype == np.float32
    np.testing.assert_allclose(scan, 60 / 255, rtol=1e-6)


def test_wrong_size_names_file_and_sizes(tmp_path):
    path = save(tmp_path / "small.png", np.zeros((200, 512), np.uint8))
    with pytest.raises(ImageFormatError, match=r"small\.png: image is 200x512 .* expected 256x512"):
        read_scan(path, SHAPE)


def test_sixteen_bit_is_refused(tmp_path):
    path = tmp_path / "deep.png"
    Image.fromarray(np.zeros(SHAPE, np.uint16) + 1000).save(path)
    with pytest.raises(ImageFormatError, match=r"deep\.png: 16-bit grey PNG; octcl reads 8-bit"):
        read_scan(path, SHAPE)


def test_palette_is_refused(tmp_path):
    path = save(tmp_path / "palette.png", np.zeros(SHAPE, np.uint8), "P")
    with pytest.raises(ImageFormatError, match=r"palette\.png: palette PNG"):
        read_scan(path, SHAPE)


def test_truncated_png_is_refused(tmp_path):
    whole = save(tmp_path / "whole.png", np.random.default_rng(1).integers(0, 256, SHAPE, dtype=np.uint8))
    data = whole.read_bytes()
    cut = tmp_path / "cut.png"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(ImageFormatError, match=r"cut\.png: truncated or corrupt PNG"):
        read_scan(cut, SHAPE)
    header_only = tmp_path / "header.png"
    header_only.write_bytes(data[:20])
    with pytest.raises(ImageFormatError, match=r"header\.png: truncated PNG"):
        read_scan(header_only, SHAPE)


def test_not_a_png_is_refused(tmp_path):
    path = tmp_path / "notes.png"
    path.write_text("x y z E\n")
    with pytest.raises(ImageFormatError, match=r"notes\.png: not a PNG file"):
        read_scan(path)
    jpeg = tmp_path / "photo.png"
    Image.fromarray(np.zeros(SHAPE, np.uint8)).save(jpeg, format="JPEG")
    with pytest.raises(ImageFormatError, match="not a PNG"):
        read_scan(jpeg)
    with pytest.raises(ImageFormatError, match="no such file"):
        read_scan(tmp_path / "missing.png")


def test_atomic_write_keeps_the_old_file_on_failure(tmp_path):
    path = tmp_path / "out.txt"
    path.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_write(path, "w") as handle:
            handle.write("new, half written")
            raise RuntimeError("disk full")
    assert path.read_text() == "old"
    assert os.listdir(tmp_path) == ["out.txt"]


def test_grey_lut_matches_matplotlib_gray_bytes():
    """uint8(255·lut) with lut[i] = (255·i/255)/255: the 24 indices that truncate."""
    index = np.arange(256)
    expected = ((255 * np.linspace(0, 1, 256))[1:-1] / 255 * 255).astype(np.uint8)
    np.testing.assert_array_equal(GREY_LUT[1:-1], expected)
    lowered = index[GREY_LUT != index]
    assert lowered.size == 24 and lowered[0] == 33 and lowered[-1] == 244


def npy_bytes(array, **kwargs) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array, **kwargs)
    return buffer.getvalue()


def test_scan_levels_from_npy_and_png_bytes(tmp_path):
    levels = np.random.default_rng(2).integers(0, 256, SHAPE, dtype=np.uint8)
    for data in (npy_bytes(levels), npy_bytes(np.asfortranarray(levels))):
        decoded = decode_scan_levels(data, SHAPE, "scan.npy")
        np.testing.assert_array_equal(decoded, levels)
        assert decoded.dtype == np.uint8 and decoded.flags.c_contiguous and decoded.flags.writeable
    write_grey_png(tmp_path / "scan.png", levels)
    np.testing.assert_array_equal(decode_scan_levels((tmp_path / "scan.png").read_bytes(), SHAPE, "scan.png"),
                                  levels)
    np.testing.assert_array_equal(check_scan_levels(levels, SHAPE), levels)


@pytest.mark.parametrize("array, message", [
    (np.zeros(SHAPE, np.float32), "float32 array; a B-scan is a 2-D uint8 array of grey levels (256x512, rows x "
                                  "columns) (floats are not scaled or rounded: save the levels as uint8)"),
    (np.zeros(SHAPE, np.uint16), "uint16 array; a B-scan is a 2-D uint8 array"),
    (np.zeros((512, 256), np.uint8), "array is 512x256 (rows x columns), expected 256x512"),
    (np.zeros(SHAPE + (3,), np.uint8), "3-D array of shape (256, 512, 3); a B-scan is a 2-D uint8 array"),
    (np.zeros((0,), np.uint8), "empty array (shape (0,)); a B-scan is a 2-D uint8 array"),
    (np.zeros((256, 0), np.uint8), "empty array (shape (256, 0))"),
    (np.full(SHAPE, None, dtype=object), "array of Python objects (dtype object)"),
])
def test_bad_arrays_are_refused_saying_what_they_are(array, message):
    with pytest.raises(ImageFormatError) as caught:
        check_scan_levels(array, SHAPE, "Male/Cheek/x.npy")
    assert str(caught.value).startswith("Male/Cheek/x.npy: ") and message in str(caught.value)
    if array.dtype != object:  # the same message from a .npy file of it
        with pytest.raises(ImageFormatError, match=re.escape(message)):
            decode_scan_levels(npy_bytes(array), SHAPE, "x.npy")


def test_bad_npy_files_are_refused():
    whole = npy_bytes(np.zeros(SHAPE, np.uint8))
    with pytest.raises(ImageFormatError, match=r"x\.npy: truncated \.npy file: its header announces a uint8 array "
                                               r"of shape \(256, 512\) \(131,072 bytes\) but 1,000 bytes follow"):
        decode_scan_levels(whole[:len(whole) - 131072 + 1000], SHAPE, "x.npy")
    with pytest.raises(ImageFormatError, match=r"x\.npy: corrupt \.npy header"):
        decode_scan_levels(whole[:20], SHAPE, "x.npy")
    objects = npy_bytes(np.array([1, "a"], dtype=object), allow_pickle=True)
    with pytest.raises(ImageFormatError, match=r"x\.npy: \.npy of Python objects \(dtype object\), not loaded"):
        decode_scan_levels(objects, SHAPE, "x.npy")
    with pytest.raises(ImageFormatError, match=r"x\.npy: empty file"):
        decode_scan_levels(b"", SHAPE, "x.npy")
    with pytest.raises(ImageFormatError, match=r"x\.npy: neither a PNG nor a \.npy file"):
        decode_scan_levels(b"x y z E\n", SHAPE, "x.npy")


def test_npy_scan_reads_as_the_grey_png_of_its_levels(tmp_path):
    """A .npy of levels gives the pixels, and so the scan, of the PNG the scanner writes for them, bit for bit."""
    assert SCAN_SHAPE == SHAPE
    levels = np.random.default_rng(3).integers(0, 256, SHAPE, dtype=np.uint8)
    levels[0, :256] = np.arange(256)
    write_grey_png(tmp_path / "scan.png", levels)
    png_pixels = read_png_pixels(tmp_path / "scan.png")
    assert png_pixels.shape == SHAPE + (4,)
    np.testing.assert_array_equal(grey_rgba_pixels(levels), png_pixels)
    np.save(tmp_path / "scan.npy", levels)
    np.save(tmp_path / "fortran.npy", np.asfortranarray(levels))
    # The kind is told by the bytes: a .npy named .png is a .npy, a PNG named .npy a PNG.
    (tmp_path / "npy_named.png").write_bytes((tmp_path / "scan.npy").read_bytes())
    (tmp_path / "png_named.npy").write_bytes((tmp_path / "scan.png").read_bytes())
    png_scan = read_scan(tmp_path / "scan.png", SHAPE)
    for name in ("scan.npy", "fortran.npy", "npy_named.png", "png_named.npy"):
        for shape in (SHAPE, None):
            pixels = read_scan_pixels(tmp_path / name, shape)
            assert pixels.dtype == np.uint8 and pixels.shape == SHAPE + (4,), name
            np.testing.assert_array_equal(pixels, png_pixels, err_msg=name)
            scan = read_scan(tmp_path / name, shape)
            assert scan.dtype == np.float32
            np.testing.assert_array_equal(scan, png_scan, err_msg=name)
    np.testing.assert_array_equal(np.rint(png_scan * 255), levels)  # the mean of 3 channels: not always L/255


def npy_scan_file(path, kind):
    """A file ``path`` holding a .npy that is not a B-scan, of ``kind``; returns the message its reading gives."""
    good = npy_bytes(np.zeros(SHAPE, np.uint8))
    arrays = {
        "float64": (np.zeros(SHAPE), "float64 array; a B-scan is a 2-D uint8 array of grey levels (256x512, rows "
                                     "x columns) (floats are not scaled or rounded: save the levels as uint8)"),
        "3-D": (np.zeros(SHAPE + (3,), np.uint8), "3-D array of shape (256, 512, 3); a B-scan is a 2-D uint8 array"),
        "255x512": (np.zeros((255, 512), np.uint8), "array is 255x512 (rows x columns), expected 256x512"),
        "empty": (np.zeros((0,), np.uint8), "empty array (shape (0,)); a B-scan is a 2-D uint8 array"),
    }
    if kind == "truncated":
        path.write_bytes(good[:len(good) - 131072 + 1000])
        return ("truncated .npy file: its header announces a uint8 array of shape (256, 512) (131,072 bytes) but "
                "1,000 bytes follow")
    if kind == "object":
        path.write_bytes(npy_bytes(np.full(SHAPE, None, dtype=object), allow_pickle=True))
        return ".npy of Python objects (dtype object), not loaded (that would run pickle)"
    array, message = arrays[kind]
    path.write_bytes(npy_bytes(array))
    return message


NPY_SCAN_FAULTS = ("float64", "3-D", "255x512", "truncated", "object", "empty")


@pytest.mark.parametrize("kind", NPY_SCAN_FAULTS)
def test_npy_that_is_not_a_scan_is_refused_naming_the_file(tmp_path, kind):
    """With or without an expected shape (a .npy without one must be a SynthOCT scan, 256x512)."""
    path = tmp_path / "Cheek" / "x.npy"
    path.parent.mkdir()
    message = npy_scan_file(path, kind)
    for shape in (SHAPE, None):
        for read in (read_scan_pixels, read_scan):
            with pytest.raises(ImageFormatError) as caught:
                read(path, shape)
            assert str(caught.value).startswith(f"{path}: {message}") and "\n" not in str(caught.value)


def test_colour_png_is_refused_as_levels(tmp_path):
    rgb = np.zeros(SHAPE + (3,), dtype=np.uint8)
    rgb[:10, :10, 0] = 200
    data = save(tmp_path / "colour.png", rgb).read_bytes()
    with pytest.raises(ImageFormatError, match=r"colour\.png: colour PNG \(R, G and B differ at 100 pixels\)"):
        decode_scan_levels(data, SHAPE, "colour.png")
    with pytest.raises(ImageFormatError, match=r"c\.png: image is 200x512"):
        decode_scan_levels(save(tmp_path / "c.png", np.zeros((200, 512), np.uint8)).read_bytes(), SHAPE, "c.png")


def png_claiming(width: int, height: int) -> bytes:
    """A PNG whose header claims ``height`` x ``width`` 8-bit grey pixels and which holds none."""
    header = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return PNG_SIGNATURE + _png_chunk(b"IHDR", header) + _png_chunk(b"IDAT", zlib.compress(b"")) \
        + _png_chunk(b"IEND", b"")


@pytest.mark.parametrize("width, height", [(100_000, 100_000), (4097, 4096), (2**31 - 1, 2**31 - 1), (0, 256)])
def test_png_size_is_refused_by_its_header_before_decoding(tmp_path, width, height):
    """Every PNG reader, asked for a shape or not, refuses a claimed size it would not read, before Pillow sees it
    (Pillow would decode 89 million pixels before its own DecompressionBombError)."""
    from octcl.scorer import _read_map_for_metrics

    path = tmp_path / "bomb.png"
    path.write_bytes(png_claiming(width, height))
    expected = re.escape(f"bomb.png: image is {height}x{width} (rows x columns); octcl reads images of 1 to "
                         f"{MAX_IMAGE_PIXELS:,} pixels")
    for reader in (read_png_pixels, read_scan, _read_map_for_metrics):
        with pytest.raises(ImageFormatError, match=expected):
            reader(path)
    with pytest.raises(ImageFormatError, match=r"bomb\.png: image is \d+x\d+ \(rows x columns\), expected 256x512"):
        decode_scan_levels(path.read_bytes(), SHAPE, "bomb.png")


def test_largest_claimed_png_that_is_read(tmp_path):
    path = tmp_path / "tall.png"
    path.write_bytes(png_claiming(1, MAX_IMAGE_PIXELS))
    with pytest.raises(ImageFormatError, match=r"tall\.png: truncated or corrupt PNG"):  # read, found empty
        read_png_pixels(path)


def test_image_file_larger_than_the_limit_is_refused_unread(tmp_path):
    path = tmp_path / "large.png"
    with open(path, "wb") as handle:  # sparse: no disk used
        handle.write(png_claiming(512, 256))
        handle.truncate(MAX_IMAGE_FILE_BYTES + 1)
    message = rf"large\.png: {MAX_IMAGE_FILE_BYTES + 1:,} bytes, more than the {MAX_IMAGE_FILE_BYTES:,} an image"
    for read in (read_image_bytes, read_scan):
        with pytest.raises(ImageFormatError, match=message):
            read(path)
    with pytest.raises(ImageFormatError, match=r"is a directory, not a PNG file"):
        read_scan(tmp_path)


def test_output_that_is_a_directory_or_beyond_a_file_is_refused(tmp_path):
    (tmp_path / "file").write_text("old")
    with pytest.raises(OutputError, match=rf"^{re.escape(str(tmp_path))}: is a directory; give a file name$"):
        with atomic_write(tmp_path):
            pass
    with pytest.raises(OutputError, match=rf"cannot make its folder: {re.escape(str(tmp_path / 'file'))} is a file"):
        write_grey_png(tmp_path / "file" / "sub" / "x.png", np.zeros(SHAPE, np.uint8))
    assert sorted(os.listdir(tmp_path)) == ["file"] and (tmp_path / "file").read_text() == "old"


def test_atomic_write_passes_on_errors_about_other_files(tmp_path):
    """An OSError of the caller about another file is the caller's, not an output error."""
    with pytest.raises(FileNotFoundError) as caught:
        with atomic_write(tmp_path / "out.txt") as handle:
            handle.write((tmp_path / "missing.txt").read_bytes())
    assert not isinstance(caught.value, OutputError) and os.listdir(tmp_path) == []


@pytest.mark.parametrize("umask", [0o022, 0o077, 0o002])
def test_outputs_get_the_mode_open_gives(tmp_path, umask):
    """Every writer's file has the permissions open() gives a new file under the umask, also when it replaces
    a file with other permissions."""
    from octcl.phantom import Phantom

    previous = os.umask(umask)
    try:
        with open(tmp_path / "by_open", "w"):
            pass
        (tmp_path / "old.txt").write_text("old")
        os.chmod(tmp_path / "old.txt", 0o600)
        with atomic_write(tmp_path / "old.txt") as handle:
            handle.write(b"new")
        write_grey_png(tmp_path / "scan.png", np.zeros(SHAPE, np.uint8))
        Phantom([0.0], [0.0], [1.0], [1.0]).save(tmp_path / "folder" / "phantom.txt")
    finally:
        os.umask(previous)
    expected = 0o666 & ~umask
    assert os.stat(tmp_path / "by_open").st_mode & 0o777 == expected
    for name in ("old.txt", "scan.png", "folder/phantom.txt"):
        assert os.stat(tmp_path / name).st_mode & 0o777 == expected, name


def temporaries(folder) -> list[str]:
    return sorted(name for name in os.listdir(folder) if name.endswith(".tmp"))


def test_killed_writer_leaves_a_hidden_temporary_that_a_later_write_removes_once_stale(tmp_path):
    """SIGKILL in the middle of a write: the output is untouched; the temporary file it leaves is removed by the
    next write to the same output once older than STALE_TEMPORARY_AGE_S, and kept while younger (it could be a
    live writer's)."""
    import signal
    import subprocess
    import sys
    import time

    from octcl._io import STALE_TEMPORARY_AGE_S

    out = tmp_path / "out.txt"
    out.write_text("earlier")
    killed = ("import os, signal, sys\nfrom octcl._io import atomic_write\n"
              "with atomic_write(sys.argv[1]) as handle:\n"
              "    handle.write(b'half a file'); handle.flush(); os.kill(os.getpid(), signal.SIGKILL)\n")
    for _ in range(2):
        result = subprocess.run([sys.executable, "-c", killed, str(out)], timeout=60)
        assert result.returncode == -signal.SIGKILL
    left = temporaries(tmp_path)
    assert len(left) == 2 and all(re.fullmatch(r"\.out\.txt\.[0-9a-f]{16}\.tmp", name) for name in left)
    assert out.read_text() == "earlier"
    other = tmp_path / ".other.txt.0123456789abcdef.tmp"  # another output's: never touched here
    other.write_text("x")
    stale = time.time() - STALE_TEMPORARY_AGE_S - 60
    for name in (left[0], other.name):
        os.utime(tmp_path / name, (stale, stale))
    with atomic_write(out) as handle:
        handle.write(b"new")
    assert out.read_text() == "new"
    assert temporaries(tmp_path) == sorted([left[1], other.name])


_CHECKPOINTING_WRITER = """
import sys
from octcl.phantom import Phantom
path, writer, versions = sys.argv[1], float(sys.argv[2]), int(sys.argv[3])
for version in range(versions):
    rows = 2000 + 37 * version
    Phantom([writer] * rows, [0.0] * rows, [float(version)] * rows, [1.0] * rows).save(path)
"""


def test_two_writers_and_a_reader_never_see_a_partial_file(tmp_path):
    """Two processes save phantoms to one output as fast as they can (two `octcl invert` runs given the same -o,
    each checkpointing), while this one loads it again and again: every load is a whole phantom one writer
    saved (its row count and values say which), and no temporary file is left."""
    import subprocess
    import sys

    from octcl.phantom import Phantom

    path = tmp_path / "phantom.txt"
    Phantom([0.0], [0.0], [0.0], [1.0]).save(path)
    writers = [subprocess.Popen([sys.executable, "-c", _CHECKPOINTING_WRITER, str(path), str(writer), "60"])
               for writer in (1, 2)]
    seen = set()
    try:
        while any(writer.poll() is None for writer in writers):
            phantom = Phantom.load(path)
            writer, version = phantom.x_um[0], phantom.z_um[0]
            assert (phantom.x_um == writer).all() and (phantom.z_um == version).all()
            if writer:
                assert len(phantom) == 2000 + 37 * version
                seen.add((writer, version))
    finally:
        for writer in writers:
            writer.wait(timeout=120)
    assert [writer.returncode for writer in writers] == [0, 0]
    assert len({writer for writer, _ in seen}) == 2 and len(seen) >= 10  # both writers were read, often
    assert os.listdir(tmp_path) == ["phantom.txt"]
