"""File input and output shared by every capability: atomic writes, PNG and B-scan arrays.

Every file octcl writes goes through :func:`atomic_write`: the data lands in a
temporary file beside the destination and is renamed over it only once it is
complete, so an interrupted or failed write never loses or corrupts an earlier
output.

PNG reading is strict. A B-scan is an 8-bit grey, grey+alpha, RGB or RGBA
PNG; anything else (16-bit samples, palettes, truncated or non-PNG files, a
wrong size) is refused with an :class:`ImageFormatError` that names the file
and the problem, instead of being silently converted.

A B-scan may also come as its 8-bit grey levels: a 2-D ``uint8`` NumPy
array, or a ``.npy`` file of one (as the SynthOCT challenge distributes its
real skin scans). :func:`decode_scan_levels` takes either file's bytes and
:func:`check_scan_levels` checks an array; nothing else is converted
either: a float array is refused rather than guessed to be in [0, 1] or
[0, 255], and a colour PNG rather than averaged into non-integer levels.
"""

from __future__ import annotations

import contextlib
import io
import os
import struct
import tempfile
import zlib
from pathlib import Path

import numpy as np

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"

# PNG colour types (PNG specification, section 11.2.2).
_COLOUR_TYPES = {0: "grey", 2: "RGB", 3: "palette", 4: "grey+alpha", 6: "RGBA"}


def _matplotlib_grey_lut() -> np.ndarray:
    """The 256 bytes matplotlib's ``'gray'`` colormap writes for colour indices 0…255.

    The official tools save images with ``matplotlib.pyplot.imsave(cmap='gray')``.
    Its lookup table is built as ``lut[i] = (255·i/255)/255`` in float64 and
    turned into bytes by truncation, ``uint8(lut·255)``, so 24 indices whose
    float value lands just below an integer (33, 37, …, 244) are written one
    level lower. Reproducing this table is what makes octcl's PNGs identical
    to the official ones.
    """
    index = (256 - 1) * np.linspace(0.0, 1.0, 256)
    lut = np.concatenate([[0.0], index[1:-1] / (256 - 1), [1.0]])
    return (lut * 255).astype(np.uint8)


#: Byte written for each colour index by matplotlib's grey colormap (see above).
GREY_LUT = _matplotlib_grey_lut()


class ImageFormatError(ValueError):
    """A PNG (or an array standing for one) that octcl cannot take as a B-scan or map; the message says why."""


@contextlib.contextmanager
def atomic_write(path, mode="wb"):
    """Open a temporary file beside ``path``; rename it over ``path`` on success.

    On any exception the temporary file is removed and ``path`` is untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, mode) as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp_name, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp_name)
        raise


def _png_header(head: bytes, source: str) -> tuple[int, int, int, int]:
    """Return (width, height, bit_depth, colour_type) from the IHDR chunk at the start of a PNG."""
    if head[:8] != PNG_SIGNATURE:
        raise ImageFormatError(f"{source}: not a PNG file (missing PNG signature)")
    if len(head) < 33 or head[12:16] != b"IHDR":
        raise ImageFormatError(f"{source}: truncated PNG (no complete IHDR header)")
    width, height, bit_depth, colour_type = struct.unpack(">IIBB", head[16:26])
    if zlib.crc32(head[12:29]) != struct.unpack(">I", head[29:33])[0]:
        raise ImageFormatError(f"{source}: corrupt PNG (IHDR checksum mismatch)")
    return width, height, bit_depth, colour_type


def _read_bytes(path: Path, kind: str) -> bytes:
    """The whole file, or an :class:`ImageFormatError` naming it when there is none."""
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise ImageFormatError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise ImageFormatError(f"{path}: is a directory, not a {kind}") from None


def read_png_pixels(path, shape: tuple[int, int] | None = None) -> np.ndarray:
    """Read an 8-bit PNG's pixels as stored: (rows, columns, channels) uint8.

    The channels are 1 (grey), 2 (grey+alpha), 3 (RGB) or 4 (RGBA).

    Parameters
    ----------
    path : str or Path
        The PNG file.
    shape : (rows, columns), optional
        The size the image must have, e.g. ``(256, 512)`` for a B-scan.

    Raises
    ------
    ImageFormatError
        Not a PNG, truncated or corrupt, not 8-bit, a palette image, or a
        size other than ``shape`` (:func:`decode_png_pixels`).
    """
    path = Path(path)
    return decode_png_pixels(_read_bytes(path, "PNG file"), shape, source=str(path))


def decode_png_pixels(data: bytes, shape: tuple[int, int] | None = None, source: str = "PNG") -> np.ndarray:
    """:func:`read_png_pixels` of a PNG file's bytes; messages start with ``source``."""
    from PIL import Image

    width, height, bit_depth, colour_type = _png_header(data[:33], source)
    kind = _COLOUR_TYPES.get(colour_type, f"colour type {colour_type}")
    if colour_type == 3:
        raise ImageFormatError(
            f"{source}: palette PNG; save the B-scan as 8-bit grey, RGB or RGBA"
        )
    if bit_depth != 8 or colour_type not in _COLOUR_TYPES:
        raise ImageFormatError(
            f"{source}: {bit_depth}-bit {kind} PNG; octcl reads 8-bit grey, RGB or RGBA"
        )
    if shape is not None and (height, width) != tuple(shape):
        raise ImageFormatError(
            f"{source}: image is {height}x{width} (rows x columns), expected "
            f"{shape[0]}x{shape[1]}"
        )
    try:
        with Image.open(io.BytesIO(data)) as image:
            image.load()
            pixels = np.asarray(image)
    except (OSError, SyntaxError, ValueError, zlib.error) as exc:
        raise ImageFormatError(f"{source}: truncated or corrupt PNG ({exc})") from None
    return pixels[:, :, None] if pixels.ndim == 2 else pixels


def rgb_of_pixels(pixels: np.ndarray) -> np.ndarray:
    """(rows, columns, 3) RGB of :func:`read_png_pixels`' pixels: alpha dropped, grey repeated."""
    colour = pixels[:, :, :1] if pixels.shape[2] <= 2 else pixels[:, :, :3]
    return np.ascontiguousarray(np.broadcast_to(colour, pixels.shape[:2] + (3,)), dtype=np.uint8)


def read_png_rgb(path, shape: tuple[int, int] | None = None) -> np.ndarray:
    """Read an 8-bit PNG as a (rows, columns, 3) uint8 RGB array, alpha dropped.

    Parameters and errors as :func:`read_png_pixels`.
    """
    return rgb_of_pixels(read_png_pixels(path, shape))


def scan_of_rgb(rgb: np.ndarray) -> np.ndarray:
    """The task contract's reading of RGB levels: each channel ``level / 255`` in float32, then their mean.

    This is also matplotlib's ``imread`` followed by the mean over RGB, as
    the official processor reads a scan.
    """
    return np.mean(np.divide(rgb, 255, dtype=np.float32), axis=2)


def read_scan(path, shape: tuple[int, int] | None = None) -> np.ndarray:
    """Read a B-scan PNG as float32 in [0, 1]: RGB scaled by 1/255, then averaged (:func:`scan_of_rgb`)."""
    return scan_of_rgb(read_png_rgb(path, shape))


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    """A PNG chunk: length, type, data, CRC-32 of type and data (PNG specification, section 5.3)."""
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def write_grey_png(path, levels: np.ndarray) -> None:
    """Write 8-bit grey levels as an opaque grey RGBA PNG (as the scanner does).

    The file is assembled here (IHDR, one IDAT of unfiltered rows deflated
    at zlib level 1, IEND) rather than by Pillow: for a 256×512 B-scan that
    takes 5 ms against Pillow's 50 ms plus 40–80 ms to import it, a fifth of
    ``octcl render``'s own time, and the file is smaller (99 kB against
    126 kB). The write is atomic: ``path`` is replaced only by a complete
    file.
    """
    levels = np.asarray(levels)
    if levels.ndim != 2 or levels.dtype != np.uint8:
        raise ValueError(f"expected a 2-D uint8 image, got {levels.dtype} {levels.shape}")
    height, width = levels.shape
    rows = np.empty((height, 1 + 4 * width), np.uint8)
    rows[:, 0] = 0  # filter type None
    rgba = rows[:, 1:].reshape(height, width, 4)
    rgba[..., :3] = levels[..., None]
    rgba[..., 3] = 255
    header = struct.pack(">IIBBBBB", width, height, 8, 6, 0, 0, 0)  # 8-bit RGBA, no interlace
    with atomic_write(path) as handle:
        handle.write(PNG_SIGNATURE + _png_chunk(b"IHDR", header)
                     + _png_chunk(b"IDAT", zlib.compress(rows.tobytes(), 1)) + _png_chunk(b"IEND", b""))


#: The first bytes of a ``.npy`` file (NumPy's format, version-independent).
NPY_MAGIC = b"\x93NUMPY"


def check_scan_levels(levels, shape: tuple[int, int], source: str = "array") -> np.ndarray:
    """Check that ``levels`` are a B-scan's grey levels: a 2-D ``uint8`` array of ``shape``.

    Returns the array itself (C-contiguous). Raises :class:`ImageFormatError`
    starting with ``source``, saying what the array is: empty, of Python
    objects, not 2-D (a colour image is 3-D), another size, or not 8-bit
    (floats are refused: 0.5 could be a level or a fraction of 255, and
    guessing would change every pixel).
    """
    expected = f"a B-scan is a 2-D uint8 array of grey levels ({shape[0]}x{shape[1]}, rows x columns)"
    if not isinstance(levels, np.ndarray):
        raise ImageFormatError(f"{source}: a {type(levels).__name__}, not a NumPy array; {expected}")
    if levels.size == 0:
        raise ImageFormatError(f"{source}: empty array (shape {levels.shape}); {expected}")
    if levels.dtype == object:
        raise ImageFormatError(f"{source}: array of Python objects (dtype object); {expected}")
    if levels.ndim != 2:
        raise ImageFormatError(f"{source}: {levels.ndim}-D array of shape {levels.shape}; {expected}")
    if levels.shape != tuple(shape):
        raise ImageFormatError(
            f"{source}: array is {levels.shape[0]}x{levels.shape[1]} (rows x columns), expected "
            f"{shape[0]}x{shape[1]}")
    if levels.dtype != np.uint8:
        hint = " (floats are not scaled or rounded: save the levels as uint8)" \
            if levels.dtype.kind in "fc" else ""
        raise ImageFormatError(f"{source}: {levels.dtype} array; {expected}{hint}")
    return np.ascontiguousarray(levels)


def _decode_npy(data: bytes, source: str) -> np.ndarray:
    """A ``.npy`` file's array, without unpickling, with its truncation named."""
    stream = io.BytesIO(data)
    try:
        version = np.lib.format.read_magic(stream)
        header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
        array_shape, fortran_order, dtype = header(stream)
    except ValueError as exc:
        raise ImageFormatError(f"{source}: corrupt .npy header ({exc})") from None
    if dtype.hasobject:
        raise ImageFormatError(
            f"{source}: .npy of Python objects (dtype object), not loaded (that would run pickle); "
            f"a B-scan is a 2-D uint8 array of grey levels")
    stored = len(data) - stream.tell()
    needed = int(np.prod(array_shape, dtype=np.int64)) * dtype.itemsize
    if stored < needed:
        raise ImageFormatError(
            f"{source}: truncated .npy file: its header announces a {dtype} array of shape "
            f"{array_shape} ({needed:,} bytes) but {stored:,} bytes follow")
    array = np.frombuffer(data, dtype=dtype, count=needed // dtype.itemsize if dtype.itemsize else 0,
                          offset=stream.tell())
    return array.reshape(array_shape, order="F" if fortran_order else "C")


def decode_scan_levels(data: bytes, shape: tuple[int, int], source: str) -> np.ndarray:
    """A B-scan file's bytes (PNG or ``.npy``) as its (rows, columns) ``uint8`` grey levels.

    A PNG is read as :func:`decode_png_pixels` reads it and must be grey (R = G
    = B: every scanner writes grey; the mean of unequal channels is no
    8-bit level). A ``.npy`` must hold what :func:`check_scan_levels`
    accepts. The kind is told by the first bytes, not the file name.

    Raises
    ------
    ImageFormatError
        Empty, neither PNG nor ``.npy``, or not a usable B-scan; the message
        starts with ``source`` and says why.
    """
    if not data:
        raise ImageFormatError(f"{source}: empty file")
    if data.startswith(NPY_MAGIC):
        return check_scan_levels(_decode_npy(data, source), shape, source).copy()
    if data.startswith(PNG_SIGNATURE[:4]):
        rgb = rgb_of_pixels(decode_png_pixels(data, shape, source))
        coloured = np.count_nonzero((rgb[..., 0] != rgb[..., 1]) | (rgb[..., 0] != rgb[..., 2]))
        if coloured:
            raise ImageFormatError(
                f"{source}: colour PNG (R, G and B differ at {coloured:,} pixels); a B-scan is grey")
        return np.ascontiguousarray(rgb[..., 0])
    raise ImageFormatError(f"{source}: neither a PNG nor a .npy file (it starts with {data[:8]!r})")
