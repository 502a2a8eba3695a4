"""The official SynthOCT processor's maps (OAC, SC, RSC): exact levels and torch twins.

The challenge scores a phantom by comparing four maps of its scan with those of
the target: the scan itself (Struct) and three maps the official processor
derives from it (``physics.md`` section 3):

1. Linear intensity with a 40 dB display assumption, ``I = 10**(4 P)``, where
   ``P`` in [0, 1] is the grey B-scan (depth rows x A-scan columns).
2. OAC, the depth-resolved optical attenuation coefficient (Vermeer et al.,
   "Depth-resolved model-based reconstruction of attenuation coefficients in
   optical coherence tomography", Biomed. Opt. Express 5(1), 322-337, 2014),
   in the processor's half-pixel form::

       mu[z] = I[z] / (2 h (C[z] - I[z]/2 + 1e-10)),   C[z] = sum_{z' >= z} I[z']

   with the pixel size h = 6 um, so mu is in 1/um (multiply by 1e4 for 1/cm).
3. Speckle contrast over a 20 x 20 box, ``SC(X) = sqrt(max(<X^2> - <X>^2, 0))
   / (<X> + 1e-10)`` (``<.>`` is ``scipy.ndimage.uniform_filter`` with
   ``mode='reflect'``), a 10-pixel border cut off and padded back by edge
   repetition. SC map = SC(I), RSC map = SC(mu).
4. Display: ``clip((X - vmin) / (vmax - vmin + 1e-10), 0, 1)`` with
   [vmin, vmax] = [min mu, 99th percentile of mu] for OAC and [0.5, 5] for SC
   and RSC, saved by ``matplotlib.pyplot.imsave(cmap='gray')``, which
   rescales once more to the array's own [min, max] and maps through the
   256-entry grey colour table.

:func:`map_levels` reproduces the saved 8-bit levels bit for bit, including
the float32 arithmetic that numpy applies to the float32 scan, without
matplotlib. :func:`write_maps` reads the scan from a PNG or from a ``.npy``
of its 2-D ``uint8`` grey levels (as the SynthOCT challenge ships its real
scans), which gives the maps of the scanner's grey PNG of those levels
(:func:`octcl._io.read_scan`). :func:`maps_torch` is the differentiable counterpart used as a
loss: the same maps as continuous values in [0, 1].
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from scipy.ndimage import uniform_filter

from octcl._io import GREY_LUT, check_output_path, read_scan, write_grey_png

MAP_NAMES = ("OAC", "SC", "RSC")

#: Decades of intensity that the processor assumes the grey range spans
#: (40 dB / 10 dB per decade): I = 10**(LINEAR_DECADES * P).
LINEAR_DECADES = 4.0
#: Axial pixel size h of the processor, in um; it sets the unit of mu (1/um).
PIXEL_SIZE_UM = 6.0
#: The processor's guard against division by zero (OAC, SC and display).
EPSILON = 1e-10
#: Side of the square speckle-contrast box, in pixels.
SPECKLE_WINDOW = 20
#: Pixels cut from every side of a speckle-contrast map and refilled by edge
#: repetition (half the box: where the box reaches past the image).
SPECKLE_BORDER = SPECKLE_WINDOW // 2
#: Fixed display window [vmin, vmax] of the SC and RSC maps.
SPECKLE_DISPLAY_RANGE = (0.5, 5.0)
#: Percentile of mu shown as white in the OAC map (its minimum is black).
OAC_UPPER_PERCENTILE = 99.0
#: Entries in matplotlib's default colour table (rcParams['image.lut']).
GREY_LEVELS = 256
#: Relative variance floor delta of the torch twin's speckle contrast:
#: sqrt(var + (delta <X>)^2) / <X> = sqrt(SC^2 + delta^2). It keeps the
#: square root's gradient finite where the box is flat (var = 0); it raises
#: SC by at most delta^2 / (2 SC) = 1e-6 at SC = 0.5, the black end of the
#: display window, and below the window the map is black either way.
SPECKLE_VARIANCE_FLOOR = 1e-3


# ---------------------------------------------------------------------------
# Index maps shared by the exact path and the torch twin
# ---------------------------------------------------------------------------


def _border_replicate_index(length: int) -> np.ndarray:
    """Indices that cut SPECKLE_BORDER from both ends and repeat the new ends.

    ``x[_border_replicate_index(n)]`` equals
    ``np.pad(x[b:-b], b, mode='edge')`` for ``b = SPECKLE_BORDER``.
    """
    if length <= 2 * SPECKLE_BORDER:
        raise ValueError(
            f"a map needs more than {2 * SPECKLE_BORDER} pixels per side to cut its "
            f"{SPECKLE_BORDER}-pixel border, got {length}"
        )
    return np.clip(np.arange(length), SPECKLE_BORDER, length - 1 - SPECKLE_BORDER)


def _symmetric_pad_index(length: int) -> np.ndarray:
    """Indices of scipy's ``mode='reflect'`` extension for a SPECKLE_WINDOW box.

    scipy's 'reflect' repeats the edge sample (d c b a | a b c d | d c b a),
    period 2 n. A box of even size w = 20 at output i covers inputs
    i - w/2 ... i + w/2 - 1, so the line gets w/2 samples before it and
    w/2 - 1 after it.
    """
    before = SPECKLE_WINDOW // 2
    after = SPECKLE_WINDOW - before - 1
    position = np.arange(-before, length + after) % (2 * length)
    return np.where(position < length, position, 2 * length - 1 - position)


# ---------------------------------------------------------------------------
# Exact maps (numpy, bit-identical to the official processor)
# ---------------------------------------------------------------------------


def _as_scan_array(scan) -> np.ndarray:
    """The scan as a 2-D floating array, dtype kept (float32 from read_scan)."""
    scan = np.asarray(scan)
    if scan.ndim != 2 or scan.dtype.kind != "f":
        raise ValueError(f"expected a 2-D float B-scan, got {scan.dtype} {scan.shape}")
    return scan


def _power_of_ten(exponent: np.ndarray) -> np.ndarray:
    """``10 ** exponent`` as numpy's portable (C library) power computes it.

    numpy's AVX-512 power kernel differs from the C library's ``powf`` by one
    unit in the last place on about a fifth of float32 inputs, which moves a
    pixel or two of a saved map by one level. The C library's result
    reproduces every pixel of the nine official maps (the AVX-512 kernel's
    does not), and numpy's scalar arithmetic always calls the C library, so
    the power is taken per distinct exponent (an 8-bit grey scan has at most
    256 of them).
    """
    distinct, inverse = np.unique(exponent.ravel(), return_inverse=True)
    base = exponent.dtype.type(10.0)
    powers = np.array([base**value for value in distinct], dtype=exponent.dtype)
    return powers[inverse].reshape(exponent.shape)


def linear_intensity(scan: np.ndarray) -> np.ndarray:
    """Linear intensity I = 10**(4 P) of a grey B-scan P (40 dB assumption).

    Parameters
    ----------
    scan : (H, W) float array
        Grey levels P in [0, 1] (:func:`octcl._io.read_scan`); an array whose
        maximum exceeds 1 is taken as 0..255 and divided by 255, as the
        processor does.

    Returns
    -------
    (H, W) array of the scan's dtype, in [1, 1e4] (arbitrary intensity units).
    """
    scan = _as_scan_array(scan)
    if scan.max() > 1.0:
        scan = scan / 255.0
    return _power_of_ten(scan * LINEAR_DECADES)


def _attenuation(intensity):
    """mu = I / (2 h (C - I/2 + 1e-10)), C the cumulative sum of I from the bottom.

    Shared by numpy arrays and torch tensors (rows are axis -2).
    """
    if isinstance(intensity, torch.Tensor):
        from_bottom = torch.flip(torch.cumsum(torch.flip(intensity, (-2,)), dim=-2), (-2,))
    else:
        from_bottom = np.cumsum(intensity[..., ::-1, :], axis=-2)[..., ::-1, :]
    return intensity / (2 * PIXEL_SIZE_UM * (from_bottom - 0.5 * intensity + EPSILON))


def oac(scan: np.ndarray) -> np.ndarray:
    """Optical attenuation coefficient map mu of a B-scan, in 1/um.

    Vermeer et al. (Biomed. Opt. Express 5(1), 322, 2014) estimate the
    attenuation of depth pixel z from the light that remains below it,
    ``mu[z] = I[z] / (2 h sum_{z' > z} I[z'])``. The official processor
    counts pixel z itself by half (the midpoint of the pixel)::

        mu[z] = I[z] / (2 h (C[z] - 0.5 I[z] + 1e-10)),   C[z] = sum_{z' >= z} I[z']

    with I = 10**(4 P) (:func:`linear_intensity`) and h = 6 um
    (PIXEL_SIZE_UM). Since C[z] - I[z]/2 >= I[z]/2, mu lies in (0, 1/h].

    Parameters
    ----------
    scan : (H, W) float array
        Grey B-scan P in [0, 1], rows = depth (top = surface).

    Returns
    -------
    (H, W) array of the scan's dtype: mu in 1/um.
    """
    return _attenuation(linear_intensity(scan))


def speckle_contrast(values: np.ndarray) -> np.ndarray:
    """Local speckle contrast std/mean over a 20 x 20 box, border repaired.

    ``SC = sqrt(max(<X^2> - <X>^2, 0)) / (<X> + 1e-10)`` with ``<.>`` the
    20 x 20 box mean ``scipy.ndimage.uniform_filter(., 20, mode='reflect')``
    (computed in the array's dtype, as the processor does); then the 10
    outer rows and columns, where the box reaches past the image, are
    replaced by the nearest inner value (cut and ``np.pad(mode='edge')``).

    Parameters
    ----------
    values : (H, W) float array, H and W > 20
        Intensity I (SC map) or attenuation mu (RSC map).

    Returns
    -------
    (H, W) array of the input's dtype, dimensionless.
    """
    mean = uniform_filter(values, size=SPECKLE_WINDOW, mode="reflect")
    mean_square = uniform_filter(values**2, size=SPECKLE_WINDOW, mode="reflect")
    variance = mean_square - mean**2
    variance[variance < 0] = 0
    contrast = np.sqrt(variance) / (mean + EPSILON)
    rows = _border_replicate_index(contrast.shape[0])
    columns = _border_replicate_index(contrast.shape[1])
    return contrast[np.ix_(rows, columns)]


def map_values(scan: np.ndarray) -> dict[str, np.ndarray]:
    """The three maps before display: OAC = mu (1/um), SC = SC(I), RSC = SC(mu)."""
    intensity = linear_intensity(scan)
    attenuation = _attenuation(intensity)
    return {
        "OAC": attenuation,
        "SC": speckle_contrast(intensity),
        "RSC": speckle_contrast(attenuation),
    }


def display_window(name: str, values: np.ndarray) -> tuple:
    """The processor's [vmin, vmax] of a map: [min, 99th percentile] or [0.5, 5]."""
    if name == "OAC":
        return np.min(values), np.percentile(values, OAC_UPPER_PERCENTILE)
    return SPECKLE_DISPLAY_RANGE


def display_normalise(values: np.ndarray, vmin, vmax) -> np.ndarray:
    """``clip((X - vmin) / (vmax - vmin + 1e-10), 0, 1)`` in numpy's dtypes."""
    return np.clip((values - vmin) / (vmax - vmin + EPSILON), 0, 1)


def matplotlib_grey_levels(image: np.ndarray) -> np.ndarray:
    """8-bit grey levels that ``matplotlib.pyplot.imsave(path, image, cmap='gray')`` writes.

    imsave without vmin/vmax scales the array to its own range with
    ``Normalize``: the bounds become Python floats, the array keeps its float
    dtype, and ``x -= vmin; x /= (vmax - vmin)`` run in place with float64
    scalars (so in float64, rounded back to the array's dtype). A constant
    array (vmin == vmax) maps to 0 everywhere. The colour map then takes
    ``x *= 256``, sends 256 (x == 1) to 255, truncates to an index (below 0
    and above 255 take the end colours; NaN takes the transparent black
    'bad' colour, grey 0) and looks the index up in the 8-bit grey table
    (:data:`octcl._io.GREY_LUT`).

    Parameters
    ----------
    image : (H, W) float array

    Returns
    -------
    (H, W) uint8: the R = G = B value of the saved RGBA PNG.
    """
    scaled = np.array(image, copy=True)
    if scaled.dtype.kind != "f":
        raise ValueError(f"expected a float array, got {scaled.dtype}")
    vmin, vmax = scaled.min().item(), scaled.max().item()
    if vmin == vmax:
        scaled.fill(0)
    else:
        scaled -= np.float64(vmin)
        scaled /= np.float64(vmax) - np.float64(vmin)
    scaled *= GREY_LEVELS
    index = np.clip(scaled, 0, GREY_LEVELS - 1)
    index[np.isnan(scaled)] = 0
    return GREY_LUT[index.astype(np.intp)]


def map_levels(scan: np.ndarray) -> dict[str, np.ndarray]:
    """The official processor's saved maps of a B-scan, as 8-bit grey levels.

    Parameters
    ----------
    scan : (H, W) float array
        The B-scan as :func:`octcl._io.read_scan` reads it (float32 in
        [0, 1]; the float32 arithmetic is part of the result).

    Returns
    -------
    dict
        ``{"OAC", "SC", "RSC"}`` -> (H, W) uint8, identical to the grey
        value of the PNGs the processor saves.
    """
    levels = {}
    for name, values in map_values(scan).items():
        vmin, vmax = display_window(name, values)
        levels[name] = matplotlib_grey_levels(display_normalise(values, vmin, vmax))
    return levels


def write_maps(scan_path, out_dir=None) -> dict[str, Path]:
    """Write ``<stem>_OAC.png``, ``<stem>_SC.png`` and ``<stem>_RSC.png`` of a scan file.

    The scan is a PNG of any size, or a ``.npy`` of 256x512 ``uint8`` grey
    levels, read as the scanner's grey PNG of them (:func:`octcl._io.read_scan`):
    ``scan.npy`` gives the same map files as that ``scan.png``. Each map is
    an opaque grey RGBA PNG with the official processor's levels
    (:func:`map_levels`), written atomically next to the scan or in
    ``out_dir``.

    Returns
    -------
    dict
        Map name -> path written.

    Raises
    ------
    OutputError
        An output path cannot be written; checked before the scan is read.
    ImageFormatError
        The scan file cannot be read as a B-scan (:func:`octcl._io.read_scan_pixels`).
    """
    scan_path = Path(scan_path)
    out_dir = scan_path.parent if out_dir is None else Path(out_dir)
    paths = {name: check_output_path(out_dir / f"{scan_path.stem}_{name}.png") for name in MAP_NAMES}
    for name, levels in map_levels(read_scan(scan_path)).items():
        write_grey_png(paths[name], levels)
    return paths


# ---------------------------------------------------------------------------
# Differentiable twins (torch)
# ---------------------------------------------------------------------------


def _box_mean_torch(values: torch.Tensor) -> torch.Tensor:
    """20 x 20 box mean with scipy's 'reflect' extension, for (N, H, W) tensors."""
    height, width = values.shape[-2:]
    rows = torch.from_numpy(_symmetric_pad_index(height)).to(values.device)
    columns = torch.from_numpy(_symmetric_pad_index(width)).to(values.device)
    padded = values.index_select(-2, rows).index_select(-1, columns).unsqueeze(1)
    # Separable: a column box then a row box, 2 w instead of w^2 terms a pixel.
    column_mean = F.avg_pool2d(padded, (SPECKLE_WINDOW, 1), stride=1)
    return F.avg_pool2d(column_mean, (1, SPECKLE_WINDOW), stride=1).squeeze(1)


def _speckle_contrast_torch(values: torch.Tensor) -> torch.Tensor:
    """Twin of :func:`speckle_contrast` with a safe square root.

    ``sqrt(max(<X^2> - <X>^2, 0) + (delta <X>)^2) / (<X> + 1e-10)``,
    delta = SPECKLE_VARIANCE_FLOOR; the argument of the square root is at
    least (delta <X>)^2 > 0 for the positive maps here (I >= 1, mu > 0).
    """
    mean = _box_mean_torch(values)
    variance = torch.clamp(_box_mean_torch(values**2) - mean**2, min=0)
    floor = (SPECKLE_VARIANCE_FLOOR * mean) ** 2
    contrast = torch.sqrt(variance + floor) / (mean + EPSILON)
    rows = torch.from_numpy(_border_replicate_index(values.shape[-2])).to(values.device)
    columns = torch.from_numpy(_border_replicate_index(values.shape[-1])).to(values.device)
    return contrast.index_select(-2, rows).index_select(-1, columns)


def _image_extrema(values: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-image (min, max) over the last two axes, detached, shaped (N, 1, 1)."""
    flat = values.detach().flatten(-2)
    return flat.amin(-1)[:, None, None], flat.amax(-1)[:, None, None]


def _display_normalise_torch(values, vmin, vmax) -> torch.Tensor:
    """Display clip then imsave's rescale to the clipped array's own range.

    ``y = clip((X - vmin) / (vmax - vmin + 1e-10), 0, 1)``, then
    ``(y - min y) / (max y - min y)`` per image, or 0 where y is constant
    (matplotlib's Normalize). The second rescale's bounds are detached like
    the first's; the division is guarded so that the discarded branch of a
    constant image cannot produce an infinite gradient.
    """
    clipped = torch.clamp((values - vmin) / (vmax - vmin + EPSILON), 0, 1)
    low, high = _image_extrema(clipped)
    span = high - low
    stretched = (clipped - low) / torch.where(span > 0, span, torch.ones_like(span))
    return torch.where(span > 0, stretched, torch.zeros_like(stretched))


def maps_torch(scan: torch.Tensor, names=MAP_NAMES) -> dict[str, torch.Tensor]:
    """Differentiable OAC, SC and RSC maps, normalised to [0, 1] as displayed.

    The same maths as :func:`map_levels` in torch: I = 10**(4 P) = exp(4 ln10
    P); mu = I / (2 h (C - I/2 + 1e-10)); SC = std/mean over a 20 x 20 box
    (scipy 'reflect' extension by index gathering, box sums by average
    pooling), border cut and edge-padded; display normalisation
    ``clip((X - vmin) / (vmax - vmin + 1e-10), 0, 1)`` with [min mu, 99th
    percentile of mu] (linear interpolation, as ``np.percentile``) for OAC
    and [0.5, 5] for SC and RSC, then imsave's rescale of the clipped array
    to its own [min, max].

    The result y relates to the saved level L by L ~ min(floor(256 y), 255)
    (one level lower on the 24 truncated entries of the grey table), so
    L/255 - y lies within about +-1/255.

    Differences from the exact path, by design:

    - The normalisation bounds (min, percentile, and imsave's min and max)
      are detached, i.e. constants for the gradient. They are order
      statistics: their gradient would land on the one or two pixels that
      attain them and jump between pixels as the phantom changes, pulling
      the whole map's brightness through single pixels; held constant, every
      pixel is steered by its own value. Pixels clipped to 0 or 1 get no
      gradient, as in the displayed map they do not change.
    - The square root of the variance has a relative floor,
      ``sqrt(var + (1e-3 <X>)^2)``, so a flat box (var = 0) has a finite
      gradient; this raises SC by at most 1e-6 inside the display window.
    - Arithmetic is torch's in the input's dtype (no reproduction of numpy's
      float32 rounding or of the 8-bit quantisation).

    Parameters
    ----------
    scan : (H, W) or (N, H, W) float tensor
        Grey B-scan(s) P in [0, 1], rows = depth; H and W > 20.
    names : iterable of str
        The maps wanted, of ``"OAC"``, ``"SC"``, ``"RSC"`` (default all):
        only those are computed (the SC map alone took 21 ms where the three
        took 57 ms, a 256 × 512 scan's forward pass on one Zen 4 core).

    Returns
    -------
    dict
        ``{name: tensor}`` for each of ``names``, in :data:`MAP_NAMES`'s
        order: tensors of the input's shape in [0, 1].
    """
    if scan.dim() not in (2, 3) or not scan.is_floating_point():
        raise ValueError(
            f"expected a float (H, W) or (N, H, W) tensor, got {scan.dtype} {tuple(scan.shape)}"
        )
    names = set(names)
    if not names <= set(MAP_NAMES):
        raise ValueError(f"unknown maps {sorted(names - set(MAP_NAMES))}; the maps are {', '.join(MAP_NAMES)}")
    batch = scan if scan.dim() == 3 else scan.unsqueeze(0)
    intensity = torch.exp(batch * (LINEAR_DECADES * np.log(10.0)))
    attenuation = _attenuation(intensity) if names & {"OAC", "RSC"} else None
    speckle_low, speckle_high = SPECKLE_DISPLAY_RANGE
    maps = {}
    if "OAC" in names:
        oac_low, _ = _image_extrema(attenuation)
        oac_high = torch.quantile(
            attenuation.detach().flatten(-2), OAC_UPPER_PERCENTILE / 100, dim=-1
        )[:, None, None]
        maps["OAC"] = _display_normalise_torch(attenuation, oac_low, oac_high)
    if "SC" in names:
        maps["SC"] = _display_normalise_torch(_speckle_contrast_torch(intensity), speckle_low, speckle_high)
    if "RSC" in names:
        maps["RSC"] = _display_normalise_torch(_speckle_contrast_torch(attenuation), speckle_low, speckle_high)
    return maps if scan.dim() == 3 else {name: value[0] for name, value in maps.items()}
