"""The SynthOCT score of predicted B-scans against reference B-scans.

For a scan, four maps are compared: the scan itself ("Struct") and the
official processor's OAC, SC and RSC maps (:mod:`octcl.maps`). Each map pair
gives two components, MS-SSIM (:func:`octcl._msssim.msssim_exact`, Wang,
Simoncelli & Bovik 2003) and 1 − LPIPS (v0.1 AlexNet, Zhang et al., CVPR
2018; :mod:`octcl._lpips`), eight in all. Over a set of scans the score is
the mean of the eight per-component medians.

A scan is a PNG or a ``.npy`` of its 2-D ``uint8`` grey levels (as the
SynthOCT challenge ships its real scans; :func:`octcl._io.read_scan_pixels`),
told by its first bytes. A ``.npy`` of levels L scores exactly as the opaque
grey PNG the scanner writes for L (:func:`octcl._io.write_grey_png`).

The official metric reads every map PNG with
``skimage.io.imread(path, as_gray=True)`` and ``img_as_float``; LPIPS takes
that float image, MS-SSIM takes ``(img * 255).astype(uint8)``. The truncation
is part of the metric: the grey value of level v is
(v/255)·0.2125 + (v/255)·0.7154 + (v/255)·0.0721, which falls just below
v/255 for 33 of the 256 levels, and those become v − 1.
"""

from __future__ import annotations

import csv
import functools
import io
from pathlib import Path

import numpy as np

from ._io import SCAN_SHAPE, SCAN_SUFFIXES

MAP_NAMES = ("Struct", "OAC", "SC", "RSC")
COMPONENTS = tuple(f"msssim_{name}" for name in MAP_NAMES) + tuple(
    f"one_minus_lpips_{name}" for name in MAP_NAMES
)
# Files in a scan directory that are maps of a scan, not scans.
MAP_FILE_SUFFIXES = ("_OAC.png", "_SC.png", "_RSC.png")
# skimage's rgb2gray luminance weights (ITU-R BT.709 primaries).
_LUMINANCE = (0.2125, 0.7154, 0.0721)


def _grey_as_official(pixels: np.ndarray) -> np.ndarray:
    """``imread(as_gray=True)`` then ``img_as_float``, from the decoded pixels.

    The steps of scikit-image: integer samples scaled to [0, 1] by
    multiplying with 1/max; RGBA blended onto a white background
    (``rgba2rgb``); RGB reduced to luminance (``rgb2gray``); grey images
    left as they are. The luminance is summed left to right,
    (R·0.2125 + G·0.7154) + B·0.0721, rather than through ``rgb2gray``'s
    matrix product, whose last-bit rounding depends on the BLAS build: that
    last bit decides the uint8 truncation of MS-SSIM's input, and the
    left-to-right sum is what reproduces the official metric values (to
    1e−16, where an optimised BLAS's rounding moves them by up to 1.3e−5).
    """
    from skimage.util import img_as_float64

    samples = img_as_float64(pixels)
    if samples.ndim == 2:
        return samples
    if samples.ndim != 3 or samples.shape[2] not in (3, 4):
        raise ValueError(f"expected a grey, RGB or RGBA image, got shape {pixels.shape}")
    if samples.shape[2] == 4:
        alpha = samples[..., 3:4]
        samples = np.clip((1 - alpha) * np.ones(3) + alpha * samples[..., :3], 0, 1)
    red, green, blue = (samples[..., channel] for channel in range(3))
    return (red * _LUMINANCE[0] + green * _LUMINANCE[1]) + blue * _LUMINANCE[2]


def grey_of_pixels(pixels: np.ndarray, source: str = "image") -> np.ndarray:
    """:func:`_grey_as_official` of a PNG's stored (H, W, C) pixels (:func:`octcl._io.read_png_pixels`).

    Raises :class:`octcl._io.ImageFormatError` starting with ``source`` for
    grey+alpha, which the official reading does not take.
    """
    from ._io import ImageFormatError

    if pixels.shape[2] == 2:
        raise ImageFormatError(f"{source}: grey+alpha PNG, which the official metric cannot read; "
                               "save it as 8-bit grey, RGB or RGBA")
    return _grey_as_official(pixels[:, :, 0] if pixels.shape[2] == 1 else pixels)


def _read_map_for_metrics(path) -> np.ndarray:
    """A map PNG as the official metric reads it: (H, W) float64 grey in [0, 1].

    The pixels are those ``skimage.io.imread`` decodes, read by octcl's
    strict reader (:func:`octcl._io.read_png_pixels`), which refuses what is
    not an 8-bit PNG and checks the size in the header before decoding.
    """
    from ._io import read_png_pixels

    return grey_of_pixels(read_png_pixels(path), str(path))


@functools.lru_cache(maxsize=1)
def _grey_of_level() -> np.ndarray:
    """Grey value the official reading gives each level of an opaque grey RGBA PNG."""
    levels = np.arange(256, dtype=np.uint8)
    rgba = np.stack([levels, levels, levels, np.full(256, 255, np.uint8)], axis=-1)
    grey = _grey_as_official(rgba[None])[0]
    grey.flags.writeable = False
    return grey


def levels_for_metrics(levels: np.ndarray) -> np.ndarray:
    """What :func:`_read_map_for_metrics` returns for these levels saved as grey RGBA.

    The reading is elementwise, so a 256-entry table gives it bit for bit
    without writing and decoding a PNG.
    """
    levels = np.asarray(levels)
    if levels.ndim != 2 or levels.dtype != np.uint8:
        raise ValueError(f"expected 2-D uint8 levels, got {levels.dtype} {levels.shape}")
    return _grey_of_level()[levels]


def _msssim_input(grey: np.ndarray) -> np.ndarray:
    """The official MS-SSIM input: ``(img * 255).astype(uint8)``, truncating."""
    return (grey * 255).astype(np.uint8)


class ScoreReference:
    """What the score takes from a reference's maps alone, computed once for a reference scored against many
    predictions: each map's LPIPS features (:func:`octcl._lpips.lpips_taps`) and MS-SSIM's reference side
    (:class:`octcl._msssim.MsssimReference`). :func:`score_grey_maps` with it gives the same bits as without,
    with half the AlexNet passes and two of each MS-SSIM scale's five local means.

    Parameters
    ----------
    ref_maps : dict
        {map name: float grey image as the metric reads it}, as :func:`score_grey_maps` takes them.
    """

    def __init__(self, ref_maps: dict):
        from ._lpips import lpips_taps
        from ._msssim import MsssimReference

        self.taps = {name: lpips_taps(ref_maps[name]) for name in MAP_NAMES}
        self.msssim = {name: MsssimReference(_msssim_input(ref_maps[name])) for name in MAP_NAMES}


def score_grey_maps(ref_maps: dict, pred_maps: dict, reference: ScoreReference | None = None) -> dict:
    """The eight components from {map name: float grey image as the metric reads it}.

    ``reference``: :class:`ScoreReference` of ``ref_maps``, for a reference
    scored against many predictions (the same components, in less time).
    """
    from ._lpips import lpips_distance
    from ._msssim import msssim_exact

    components = {}
    for name in MAP_NAMES:
        ref_side = None if reference is None else reference.msssim[name]
        components[f"msssim_{name}"] = msssim_exact(
            _msssim_input(ref_maps[name]) if ref_side is None else ref_side.levels, _msssim_input(pred_maps[name]),
            ref_side,
        )
    for name in MAP_NAMES:
        taps = None if reference is None else reference.taps[name]
        components[f"one_minus_lpips_{name}"] = 1.0 - lpips_distance(ref_maps[name], pred_maps[name], taps)
    return components


def score_maps(ref_maps: dict, pred_maps: dict) -> dict:
    """The eight components of a prediction's maps against the reference's.

    Parameters
    ----------
    ref_maps, pred_maps : dict
        {"Struct", "OAC", "SC", "RSC"} → (H, W) uint8 grey levels, as in the
        map PNGs.

    Returns
    -------
    dict
        ``msssim_<map>`` and ``one_minus_lpips_<map>`` for each map.
    """
    return score_grey_maps(
        {name: levels_for_metrics(ref_maps[name]) for name in MAP_NAMES},
        {name: levels_for_metrics(pred_maps[name]) for name in MAP_NAMES},
    )


def maps_for_metrics(struct: np.ndarray, scan: np.ndarray) -> dict:
    """The four maps of a scan, each as the official metric reads it.

    ``struct`` is the scan PNG as the metric reads it (:func:`_read_map_for_metrics`),
    ``scan`` as the processor reads it (:func:`octcl._io.read_scan`); the OAC,
    SC and RSC maps are the processor's of ``scan``, saved and read back.
    """
    from .maps import map_levels

    derived = map_levels(scan)
    return {"Struct": struct, **{name: levels_for_metrics(derived[name]) for name in ("OAC", "SC", "RSC")}}


def _scan_maps_for_metrics(path) -> dict:
    """The four maps of a scan file (PNG, or ``.npy`` read as its grey PNG), each as the official metric reads it."""
    from ._io import read_scan_pixels, rgb_of_pixels, scan_of_rgb

    pixels = read_scan_pixels(path, shape=SCAN_SHAPE)
    return maps_for_metrics(grey_of_pixels(pixels, str(path)), scan_of_rgb(rgb_of_pixels(pixels)))


def score(ref, pred) -> dict:
    """Score one predicted B-scan against its reference (both 256×512, each a PNG or a ``.npy`` of levels).

    Returns
    -------
    dict
        The eight components ``msssim_<map>``, ``one_minus_lpips_<map>`` for
        map in Struct, OAC, SC, RSC, and ``mean``, their mean.
    """
    components = score_grey_maps(_scan_maps_for_metrics(ref), _scan_maps_for_metrics(pred))
    components["mean"] = float(np.mean([components[name] for name in COMPONENTS]))
    return components


def score_directories(ref_dir, pred_dir, progress=None) -> dict:
    """Score every reference scan in ``ref_dir`` against the scan of the same name in ``pred_dir``.

    Parameters
    ----------
    ref_dir, pred_dir : str or Path
        Reference scans are the ``*.png`` of ``ref_dir`` except the map files
        ``*_OAC.png``, ``*_SC.png``, ``*_RSC.png``, and the ``*.npy``. The
        prediction of ``NAME.png`` or ``NAME.npy`` is the file of the same
        name in ``pred_dir``, else ``NAME`` with the other suffix: a scan
        may be a PNG on one side and a ``.npy`` on the other.
    progress : callable, optional
        Called as ``progress(i, n, name)`` after scan ``i`` of ``n`` (from 1).

    Returns
    -------
    dict
        ``scans``: {file name: result of :func:`score`}; ``medians``: the
        median of each component over the scans; ``score``: the mean of the
        eight medians (the global SynthOCT score).

    Raises
    ------
    FileNotFoundError
        ``ref_dir`` has no scans, or a scan has no prediction (all such files
        are named).
    ValueError
        ``ref_dir`` holds one scan twice, as ``NAME.png`` and ``NAME.npy``
        (all such pairs are named).
    """
    ref_dir, pred_dir = Path(ref_dir), Path(pred_dir)
    names = sorted(
        path.name for suffix in SCAN_SUFFIXES for path in ref_dir.glob(f"*{suffix}")
        if not path.name.endswith(MAP_FILE_SUFFIXES)
    )
    if not names:
        raise FileNotFoundError(f"{ref_dir}: no reference scans (*.npy, or *.png other than map files)")
    stems = {}
    for name in names:
        stems.setdefault(Path(name).stem, []).append(name)
    twice = [" and ".join(pair) for pair in stems.values() if len(pair) > 1]
    if twice:
        raise ValueError(f"{ref_dir}: the same reference scan twice: {'; '.join(twice)}; keep one of each")
    preds = {name: _prediction(pred_dir, name) for name in names}
    missing = [name for name, pred in preds.items() if pred is None]
    if missing:
        raise FileNotFoundError(f"{pred_dir}: no prediction for {', '.join(missing)}")
    scans = {}
    for index, name in enumerate(names, start=1):
        scans[name] = score(ref_dir / name, preds[name])
        if progress is not None:
            progress(index, len(names), name)
    medians, global_ = global_score(scans.values())
    return {"scans": scans, "medians": medians, "score": global_}


def _prediction(pred_dir: Path, ref_name: str) -> Path | None:
    """The prediction of the reference scan ``ref_name``: the same name, else the other scan suffix; or None."""
    ref = Path(ref_name)
    candidates = [ref.name] + [ref.stem + suffix for suffix in SCAN_SUFFIXES if suffix != ref.suffix]
    return next((pred_dir / name for name in candidates if (pred_dir / name).is_file()), None)


def global_score(scans) -> tuple[dict, float]:
    """(per-component medians, their mean) over ``scans``, each a dict holding the eight COMPONENTS.

    The mean of the eight per-component medians is the SynthOCT global score.
    """
    scans = list(scans)
    medians = {component: float(np.median([scan[component] for scan in scans])) for component in COMPONENTS}
    return medians, float(np.mean(list(medians.values())))


def write_score_csv(result: dict, path) -> None:
    """Write a :func:`score_directories` result as CSV (atomically).

    One row per scan (``scan``, the eight components, ``mean``), then a row
    ``median`` with the per-component medians and, under ``mean``, the global
    score (the mean of those medians).
    """
    from ._io import atomic_write

    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(["scan", *COMPONENTS, "mean"])
    for name, components in result["scans"].items():
        writer.writerow([name, *(repr(components[c]) for c in COMPONENTS), repr(components["mean"])])
    writer.writerow(["median", *(repr(result["medians"][c]) for c in COMPONENTS), repr(result["score"])])
    with atomic_write(path) as handle:
        handle.write(buffer.getvalue().encode())
