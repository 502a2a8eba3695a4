"""File input and output shared by every capability: atomic writes and PNG.

Every file octcl writes goes through :func:`atomic_write`: the data lands in a
temporary file beside the destination and is renamed over it only once it is
complete, so an interrupted or failed write never loses or corrupts an earlier
output.

PNG reading is strict. A B-scan is an 8-bit grey, grey+alpha, RGB or RGBA
PNG; anything else (16-bit samples, palettes, truncated or non-PNG files, a
wrong size) is refused with an :class:`ImageFormatError` that names the file
and the problem, instead of being silently converted.
"""

from __future__ import annotations

import contextlib
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


def _png_header(path: Path) -> tuple[int, int, int, int]:
    """Return (width, height, bit_depth, colour_type) from the IHDR chunk."""
    try:
        with open(path, "rb") as handle:
            head = handle.read(33)
    except FileNotFoundError:
        raise ImageFormatError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise ImageFormatError(f"{path}: is a directory, not a PNG file") from None
    if head[:8] != PNG_SIGNATURE:
        raise ImageFormatError(f"{path}: not a PNG file (missing PNG signature)")
    if len(head) < 33 or head[12:16] != b"IHDR":
        raise ImageFormatError(f"{path}: truncated PNG (no complete IHDR header)")
    width, height, bit_depth, colour_type = struct.unpack(">IIBB", head[16:26])
    if zlib.crc32(head[12:29]) != struct.unpack(">I", head[29:33])[0]:
        raise ImageFormatError(f"{path}: corrupt PNG (IHDR checksum mismatch)")
    return width, height, bit_depth, colour_type


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
        size other than ``shape``.
    """
    from PIL import Image

    path = Path(path)
    width, height, bit_depth, colour_type = _png_header(path)
    kind = _COLOUR_TYPES.get(colour_type, f"colour type {colour_type}")
    if colour_type == 3:
        raise ImageFormatError(
            f"{path}: palette PNG; save the B-scan as 8-bit grey, RGB or RGBA"
        )
    if bit_depth != 8 or colour_type not in _COLOUR_TYPES:
        raise ImageFormatError(
            f"{path}: {bit_depth}-bit {kind} PNG; octcl reads 8-bit grey, RGB or RGBA"
        )
    if shape is not None and (height, width) != tuple(shape):
        raise ImageFormatError(
            f"{path}: image is {height}x{width} (rows x columns), expected "
            f"{shape[0]}x{shape[1]}"
        )
    try:
        with Image.open(path) as image:
            image.load()
            pixels = np.asarray(image)
    except (OSError, SyntaxError, ValueError, zlib.error) as exc:
        raise ImageFormatError(f"{path}: truncated or corrupt PNG ({exc})") from None
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
