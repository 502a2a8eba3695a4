"""The target of an inversion: one array, read from its file once, that every stage reads from.

The file is a PNG or a ``.npy`` of the scan's 2-D ``uint8`` grey levels (as
the SynthOCT challenge ships its real scans), told by its first bytes. A
target is a uint8 array in one of two forms:

- (Nz, Nx): the 8-bit levels of a grey B-scan as the Virtual Scanner saves
  it, an opaque grey RGBA PNG (every official scan is one), or as a ``.npy``
  holds them, which therefore reads as the scanner's PNG of them;
- (Nz, Nx, C): the pixels of any other PNG as stored, C = 1 (grey), 3 (RGB)
  or 4 (RGBA).

The stages read it as the task and the official tools read the file:

- :func:`target_scan`, the task contract's float32 scan (RGB, alpha
  dropped, level/255, mean of the channels), for stage 1, the loss and the
  OAC, SC and RSC maps;
- :func:`target_struct_for_metrics`, the Struct map as the official metric
  reads the file (``skimage.io.imread``, :mod:`octcl.scorer`), for the exact
  score.

The forms are not interchangeable for the second: the metric reads a grey
PNG's level v as v/255, an RGB(A) one through luminance weights that put 33
of the 256 levels just below v/255, where its MS-SSIM input becomes v − 1.
:func:`read_target` therefore returns the 2-D form only for opaque grey
RGB(A) files, so that ``invert(read_target(path))`` and ``invert(path)``
are the same inversion, bit for bit, and a grey scan travels as Nz·Nx bytes.
"""

from __future__ import annotations

import numpy as np

from octcl._io import (NPY_MAGIC, ImageFormatError, decode_png_pixels, decode_scan_levels, read_image_bytes,
                       rgb_of_pixels, scan_of_rgb)
from octcl.config import DEFAULT_CONFIG, ScannerConfig

#: Channel counts of the (Nz, Nx, C) form: grey, RGB, RGBA.
PIXEL_CHANNELS = (1, 3, 4)


def _pixels(target: np.ndarray) -> np.ndarray:
    """The target as (Nz, Nx, C) pixels; the 2-D form as one grey channel."""
    target = np.asarray(target)
    if target.dtype != np.uint8 or not (target.ndim == 2 or (target.ndim == 3 and target.shape[2] in PIXEL_CHANNELS)):
        raise ValueError(f"a target is a uint8 (Nz, Nx) or (Nz, Nx, C) array with C in {PIXEL_CHANNELS}, "
                         f"got {target.dtype} {target.shape}")
    return target[:, :, None] if target.ndim == 2 else target


def check_target(target, config: ScannerConfig = DEFAULT_CONFIG, name: str = "target") -> np.ndarray:
    """``target`` as a uint8 array if it is a B-scan :func:`octcl.host.pipeline.invert.invert` can invert.

    Raises
    ------
    ImageFormatError
        Naming ``name``: not a uint8 array of one of the two forms (module
        docstring), not (Nz, Nx), or one uniform level. The scanner's display
        puts its brightest pixel at level 255 and spans 51 dB below it, so an
        all-black or uniform grey image is not one of its B-scans, and an
        all-white one would need every pixel equally bright: no phantom
        renders such an image, and its OAC and speckle maps are undefined
        (0/0), so it is refused rather than inverted into noise.
    """
    try:
        pixels = _pixels(target)
    except ValueError as exc:
        raise ImageFormatError(f"{name}: {exc}") from None
    if pixels.shape[:2] != config.shape:
        raise ImageFormatError(f"{name}: image is {pixels.shape[0]}x{pixels.shape[1]} (rows x columns), "
                               f"expected {config.shape[0]}x{config.shape[1]}")
    colour = pixels[:, :, :3]
    low, high = int(colour.min()), int(colour.max())
    if low == high:
        described = {0: "black", 255: "white"}.get(low, f"grey level {low}")
        raise ImageFormatError(
            f"{name}: every pixel is {described}; a B-scan has structure (its brightest pixel is "
            "level 255 and its speckle spans the 51 dB display range), so there is nothing to invert")
    return np.asarray(target)


def read_target(path, config: ScannerConfig = DEFAULT_CONFIG) -> np.ndarray:
    """Read and check a target B-scan file (:func:`check_target`), in the smaller form that reads the same.

    The file is a PNG or a ``.npy`` of (Nz, Nx) ``uint8`` levels, read once
    and decoded by :func:`decode_target`, as a batch reads its targets.

    Returns
    -------
    ndarray of uint8
        (Nz, Nx) levels for an opaque grey RGB or RGBA file or a ``.npy``,
        else the (Nz, Nx, C) pixels as stored (module docstring).

    Raises
    ------
    ImageFormatError
        Naming the file: missing or unreadable; not a PNG or ``.npy``,
        truncated, not 8-bit, a palette or grey+alpha image (the official
        metric reads neither), a ``.npy`` that is not a 2-D ``uint8`` array,
        not (Nz, Nx), or uniform.
    """
    return decode_target(read_image_bytes(path), config, str(path))


def decode_target(data: bytes, config: ScannerConfig = DEFAULT_CONFIG, name: str = "target") -> np.ndarray:
    """A target file's bytes as :func:`read_target` reads the file: PNG, or ``.npy`` of (Nz, Nx) levels.

    A ``.npy`` holds the 8-bit grey levels of a B-scan (as the SynthOCT
    challenge ships its real scans), read as the 2-D form
    (:func:`octcl._io.decode_scan_levels`). The kind is told by the first
    bytes. Messages start with ``name``. This is how a batch's workers read
    targets that travel to them as bytes.
    """
    if data.startswith(NPY_MAGIC):
        return check_target(decode_scan_levels(data, config.shape, name), config, name)
    return _target_of_pixels(decode_png_pixels(data, config.shape, name), config, name)


def _target_of_pixels(pixels: np.ndarray, config: ScannerConfig, name: str) -> np.ndarray:
    """A PNG's stored pixels as a checked target in the smaller form that reads the same."""
    channels = pixels.shape[2]
    if channels not in PIXEL_CHANNELS:
        raise ImageFormatError(f"{name}: grey+alpha PNG, which the official metric cannot read; "
                               "save the B-scan as 8-bit grey, RGB or RGBA")
    opaque_grey = channels >= 3 and (pixels[:, :, 1] == pixels[:, :, 0]).all() \
        and (pixels[:, :, 2] == pixels[:, :, 0]).all() and (channels == 3 or (pixels[:, :, 3] == 255).all())
    return check_target(pixels[:, :, 0].copy() if opaque_grey else pixels, config, name)


def target_scan(target: np.ndarray) -> np.ndarray:
    """The float32 scan the task contract reads from the target's PNG (:func:`octcl._io.read_scan`)."""
    return scan_of_rgb(rgb_of_pixels(_pixels(target)))


def target_struct_for_metrics(target: np.ndarray) -> np.ndarray:
    """The target's Struct map as the official metric reads its PNG: float64 grey in [0, 1]."""
    from octcl import scorer

    target = np.asarray(target)
    pixels = _pixels(target)
    if target.ndim == 2:  # an opaque grey RGBA file
        return scorer.levels_for_metrics(target)
    return scorer.grey_of_pixels(pixels)


__all__ = ["PIXEL_CHANNELS", "check_target", "decode_target", "read_target", "target_scan", "target_struct_for_metrics"]
