"""Multi-scale structural similarity (MS-SSIM) as the SynthOCT scorer computes it.

The official metric is ``sewar.full_ref.msssim`` with its defaults, applied to
8-bit images. :func:`msssim_exact` reproduces it on uint8 input to
float64 rounding (its window applied as two 1-D passes: within 1e−15 of the
official values); :func:`msssim_torch` is the same computation in torch, differentiable,
on float images in [0, 1].

MS-SSIM (Wang, Simoncelli & Bovik, "Multiscale structural similarity for
image quality assessment", Asilomar Conference on Signals, Systems and
Computers, 2003). For images x, y at scale j = 1 … M, with Gaussian-weighted
local means μ, variances σ² and covariance σ_xy over an 11×11 window
(σ = 1.5, 'valid' extent, no padding),

    cs_j   = mean over the window positions of (2 σ_xy + C2) / (σ_x² + σ_y² + C2)
    ssim_j = mean of (2 μ_x μ_y + C1)(2 σ_xy + C2)
                     / ((μ_x² + μ_y² + C1)(σ_x² + σ_y² + C2))

with C1 = (0.01·255)², C2 = (0.03·255)², and

    MS-SSIM = Re( Π_{j<M} cs_j^{w_j} · ssim_M^{w_M} ),
    w = (0.0448, 0.2856, 0.3001, 0.2363, 0.1333),

the powers taken as complex numbers, so a negative cs_j (anti-correlated
structure) contributes a phase e^{iπ w_j} rather than a NaN. Between scales
both images go through a 2×2 box filter (``scipy.ndimage.uniform_filter`` of
size 2, mode 'reflect', i.e. out[i] = (x[i−1] + x[i]) / 2 with x[−1] = x[0]
along each axis) and keep every second row and column, starting at 0.

As in sewar, the number of scales drops below 5 (weights truncated) when the
shorter side is too small for the window at the coarsest scale; a 256×512
B-scan uses all five (16×32 at scale 5).
"""

from __future__ import annotations

import math

import numpy as np

MSSSIM_WEIGHTS = (0.0448, 0.2856, 0.3001, 0.2363, 0.1333)
WINDOW_SIZE = 11
WINDOW_SIGMA = 1.5
K1 = 0.01
K2 = 0.03
DATA_RANGE = 255.0

# Smallest magnitude |cs| or |ssim| used by msssim_torch; see its docstring.
_TORCH_MAGNITUDE_FLOOR = 1e-6


def _gaussian_window(size: int = WINDOW_SIZE, sigma: float = WINDOW_SIGMA) -> np.ndarray:
    """The normalised (size, size) Gaussian window, built as sewar's ``fspecial``.

    Values below ``eps·max`` are zeroed before normalising (none are, for
    11×11 and σ = 1.5); the grid is the one MATLAB's ``fspecial`` uses.
    """
    offsets = np.mgrid[-size // 2 + 1 : size // 2 + 1, -size // 2 + 1 : size // 2 + 1]
    window = np.exp(-((offsets[0] ** 2 + offsets[1] ** 2) / (2.0 * sigma**2)))
    window[window < np.finfo(window.dtype).eps * window.max()] = 0
    return window / window.sum()


def _scale_count(shape: tuple[int, ...], requested: int = len(MSSSIM_WEIGHTS)) -> int:
    """Number of scales: as many as requested while the coarsest side stays ≥ the window."""
    shortest = min(shape[-2], shape[-1])
    if shortest < WINDOW_SIZE:
        raise ValueError(
            f"image is {shape[-2]}x{shape[-1]}; MS-SSIM needs at least "
            f"{WINDOW_SIZE} pixels on each side"
        )
    return min(requested, int(np.floor(np.log2(shortest / WINDOW_SIZE))) + 1)


def _local_mean(image: np.ndarray, profile: np.ndarray) -> np.ndarray:
    """Gaussian-weighted local means of ``image`` over the 'valid' window positions: two 1-D passes of the
    window's normalised profile (see :func:`_ssim_and_cs`)."""
    from scipy.ndimage import correlate1d

    reach = profile.size // 2
    rows = correlate1d(image, profile, axis=0, mode="constant")[reach:-reach]
    return correlate1d(rows, profile, axis=1, mode="constant")[:, reach:-reach]


def _reference_stats(ref: np.ndarray, window: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The reference's side of one scale's SSIM terms: its local means μ_x and local means of squares."""
    profile = window.sum(axis=0)
    return _local_mean(ref, profile), _local_mean(ref * ref, profile)


def _ssim_and_cs(ref: np.ndarray, pred: np.ndarray, window: np.ndarray,
                 ref_stats: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[float, float]:
    """Mean SSIM and mean contrast-structure term of one scale ('valid' window).

    sewar convolves with the 2-D window rotated by 180° (the same window:
    it is symmetric). The Gaussian is separable, exp(−(x² + y²)/2σ²) =
    exp(−x²/2σ²)·exp(−y²/2σ²), so the local means are taken as two 1-D
    passes of its normalised profile: a 256×512 scale's SSIM terms took
    10.9 ms, where its five local means by ``convolve2d`` took 97.7 ms
    (``python scripts/bench_field_steps.py`` on two cores of an AMD EPYC),
    within 1e−12 of the official MS-SSIM values (``tests/test_msssim.py``).
    ``ref_stats``: :func:`_reference_stats` of ``ref``, for a reference
    compared with many images (the same arithmetic, so the same bits).
    """
    profile = window.sum(axis=0)  # the normalised 1-D Gaussian: the window is its outer product
    mean_ref, mean_of_ref_sq = _reference_stats(ref, window) if ref_stats is None else ref_stats
    mean_pred = _local_mean(pred, profile)
    mean_ref_sq, mean_pred_sq, mean_cross = mean_ref * mean_ref, mean_pred * mean_pred, mean_ref * mean_pred
    var_ref = mean_of_ref_sq - mean_ref_sq
    var_pred = _local_mean(pred * pred, profile) - mean_pred_sq
    covariance = _local_mean(ref * pred, profile) - mean_cross

    c1 = (K1 * DATA_RANGE) ** 2
    c2 = (K2 * DATA_RANGE) ** 2
    ssim_map = ((2 * mean_cross + c1) * (2 * covariance + c2)) / (
        (mean_ref_sq + mean_pred_sq + c1) * (var_ref + var_pred + c2)
    )
    cs_map = (2 * covariance + c2) / (var_ref + var_pred + c2)
    return float(np.mean(ssim_map)), float(np.mean(cs_map))


def _downsample(image: np.ndarray) -> np.ndarray:
    """The next scale: a 2×2 box filter (scipy's ``uniform_filter``, 'reflect') and every second row and column."""
    from scipy.ndimage import uniform_filter

    return uniform_filter(image, 2)[::2, ::2]


def _checked_levels(name: str, image) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 2 or image.dtype != np.uint8:
        raise ValueError(f"{name}: expected a 2-D uint8 image, got {image.dtype} {image.shape}")
    return image


class MsssimReference:
    """A reference image's side of :func:`msssim_exact` at every scale, for a reference compared with many images.

    Each scale's image and its local means and means of squares (two of the
    five local means a scale takes) are computed once; :func:`msssim_exact`
    with ``reference=`` gives the same bits as without: four 256×512 pairs,
    a score's, took 0.068 s with it and 0.110 s without (orange.png's maps
    against its error-diffused image's, median of 15, two Zen 4 cores).
    """

    def __init__(self, ref_levels: np.ndarray):
        self.levels = _checked_levels("ref_levels", ref_levels)
        window = _gaussian_window()
        image, self.scales = self.levels.astype(np.float64), []
        for _ in range(_scale_count(self.levels.shape)):
            self.scales.append((image, _reference_stats(image, window)))
            image = _downsample(image)


def msssim_exact(ref_levels: np.ndarray, pred_levels: np.ndarray, reference: MsssimReference | None = None) -> float:
    """MS-SSIM of two 8-bit images as ``sewar.full_ref.msssim``, to float64 rounding.

    Parameters
    ----------
    ref_levels, pred_levels : (H, W) uint8 arrays
        The reference and the predicted image (grey levels 0…255).
    reference : MsssimReference, optional
        ``MsssimReference(ref_levels)``, computed once for many comparisons
        (``ref_levels`` is then not read again). The result is the same.

    Returns
    -------
    float
        Re(Π_{j<5} cs_j^{w_j} · ssim_5^{w_5}), see the module docstring; 1 for
        identical images.
    """
    pred_levels = _checked_levels("pred_levels", pred_levels)
    if reference is None:
        reference = MsssimReference(ref_levels)
    if reference.levels.shape != pred_levels.shape:
        raise ValueError(f"images differ in size: {reference.levels.shape} and {pred_levels.shape}")
    scales = len(reference.scales)
    weights = np.array(MSSSIM_WEIGHTS[:scales])
    window = _gaussian_window()
    pred = pred_levels.astype(np.float64)
    ssims, css = [], []
    for ref, ref_stats in reference.scales:
        ssim, cs = _ssim_and_cs(ref, pred, window, ref_stats)
        ssims.append(ssim)
        css.append(cs)
        pred = _downsample(pred)
    # numpy's complex power, as sewar, so a negative term gives the same phase.
    cs_terms = np.array(css[: scales - 1], dtype=np.float64).astype(complex) ** weights[: scales - 1]
    ssim_term = np.array(ssims[scales - 1], dtype=np.float64).astype(complex) ** weights[scales - 1]
    return float((np.prod(cs_terms) * ssim_term).real)


def msssim_torch(ref, pred):
    """Differentiable MS-SSIM of float images in [0, 1] (the twin of :func:`msssim_exact`).

    The maths of :func:`msssim_exact` on ``255·image``, without rounding to
    8-bit levels; computed in float64 for float64 input, else in float32.

    Parameters
    ----------
    ref, pred : torch.Tensor, (H, W) or (N, H, W)
        Float images in [0, 1]; gradients flow to both.

    Returns
    -------
    torch.Tensor
        A scalar for (H, W) input, shape (N,) for a batch.

    Notes
    -----
    The official value raises cs_j and ssim_M to fractional powers as complex
    numbers and keeps the real part. For real terms t_j that is exactly

        Π_j |t_j|^{w_j} · cos(π Σ_{j: t_j < 0} w_j),

    which is what is computed here, so negative terms give the official
    value instead of NaN. The magnitudes are clamped from below at 1e-6:
    d|t|^w/d|t| = w|t|^{w−1} is infinite at t = 0 for w < 1, so without the
    clamp a term that crosses zero gives an infinite or NaN gradient. Below
    the clamp the value is that of |t| = 1e-6 and the gradient through that
    term is zero. On flat (all-black, all-white, grey) images every cs term
    is 1, there being no variance, and ssim is at least C1/(255² + C1), so
    such images keep finite, unclamped gradients.
    """
    import torch
    import torch.nn.functional as F

    if ref.shape != pred.shape:
        raise ValueError(f"images differ in size: {tuple(ref.shape)} and {tuple(pred.shape)}")
    if ref.dim() not in (2, 3):
        raise ValueError(f"expected (H, W) or (N, H, W) images, got shape {tuple(ref.shape)}")
    batched = ref.dim() == 3
    dtype = torch.float64 if torch.float64 in (ref.dtype, pred.dtype) else torch.float32
    # (N, 1, H, W) on the 0…255 scale of the 8-bit metric.
    ref = (ref.to(dtype) * DATA_RANGE).reshape(-1, 1, *ref.shape[-2:])
    pred = (pred.to(dtype) * DATA_RANGE).reshape(-1, 1, *pred.shape[-2:])

    scales = _scale_count(tuple(ref.shape))
    weights = MSSSIM_WEIGHTS[:scales]
    # The 2-D window is the outer product of this 1-D profile with itself, so
    # two 1-D passes give the same local means (to rounding) at 2/11 the cost.
    profile = _gaussian_window()[WINDOW_SIZE // 2]
    profile = torch.as_tensor(profile / profile.sum(), dtype=dtype, device=ref.device)
    column, row = profile.view(1, 1, -1, 1), profile.view(1, 1, 1, -1)
    c1 = (K1 * DATA_RANGE) ** 2
    c2 = (K2 * DATA_RANGE) ** 2

    def local_means(*images):
        stacked = torch.cat(images, dim=1)
        flat = stacked.reshape(-1, 1, *stacked.shape[-2:])
        filtered = F.conv2d(F.conv2d(flat, column), row)
        return filtered.reshape(stacked.shape[0], len(images), *filtered.shape[-2:]).unbind(1)

    terms = []
    for scale in range(scales):
        mean_ref, mean_pred, mean_ref2, mean_pred2, mean_refpred = local_means(
            ref, pred, ref * ref, pred * pred, ref * pred
        )
        mean_ref_sq, mean_pred_sq, mean_cross = mean_ref * mean_ref, mean_pred * mean_pred, mean_ref * mean_pred
        var_ref = mean_ref2 - mean_ref_sq
        var_pred = mean_pred2 - mean_pred_sq
        covariance = mean_refpred - mean_cross
        cs_map = (2 * covariance + c2) / (var_ref + var_pred + c2)
        if scale < scales - 1:
            terms.append(cs_map.mean(dim=(1, 2)))
            # uniform_filter(size 2, 'reflect') then [::2, ::2]: the first row and
            # column repeated once, then 2×2 average pooling.
            ref, pred = (F.avg_pool2d(F.pad(image, (1, 0, 1, 0), mode="replicate"), 2) for image in (ref, pred))
        else:
            luminance = (2 * mean_cross + c1) / (mean_ref_sq + mean_pred_sq + c1)
            terms.append((luminance * cs_map).mean(dim=(1, 2)))

    terms = torch.stack(terms, dim=1)
    exponents = torch.tensor(weights, dtype=dtype, device=terms.device)
    magnitude = torch.prod(terms.abs().clamp(min=_TORCH_MAGNITUDE_FLOOR) ** exponents, dim=1)
    phase = math.pi * torch.sum(exponents * (terms < 0), dim=1)
    value = magnitude * torch.cos(phase)
    return value if batched else value[0]
