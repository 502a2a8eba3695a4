"""Rendering a phantom to a B-scan: the public ``render`` and the display maths.

The Virtual Scanner turns complex A-scans A (``kernels/scanner.cl`` or the
float64 reference) into the display

    D = max(dB − max(dB) + 51, 0) / 51,   dB = 20·log10 |A|,

and 8-bit PNG levels. :func:`display_vjp` is the adjoint of that map, so a
loss on D (or on the 8-bit image through a straight-through estimator) can be
pulled back to the A-scans and, by the kernels' adjoint, to every scatterer.
"""

from __future__ import annotations

import functools
import threading
from dataclasses import dataclass

import numpy as np

from . import _reference as ref
from .config import DEFAULT_CONFIG, ScannerConfig
from .phantom import Phantom

#: ∂D/∂ln|A| for a pixel above the display floor: 20 / (51·ln 10).
DISPLAY_SLOPE = 20.0 / (ref.DISPLAY_RANGE_DB * np.log(10.0))


@dataclass
class Rendering:
    """A rendered B-scan, (Nz, Nx) arrays.

    Attributes
    ----------
    a_scans : ndarray of complex128
        The complex A-scans A[n, i] (depth row n, A-scan i).
    magnitude : ndarray of float64
        |A| with exact zeros replaced by 1e−10.
    display : ndarray of float64
        D in [0, 1].
    levels : ndarray of uint8
        The 8-bit levels the scanner writes to its PNG.
    """

    a_scans: np.ndarray
    magnitude: np.ndarray
    display: np.ndarray
    levels: np.ndarray

    @classmethod
    def from_a_scans(cls, a_scans: np.ndarray) -> "Rendering":
        """Steps 8–11 of the scanner from complex A-scans."""
        magnitude = ref.ascan_magnitude(a_scans)
        display = ref.to_display(ref.to_decibels(magnitude))
        return cls(a_scans=a_scans, magnitude=magnitude, display=display, levels=ref.quantise(display))


#: Straight-through slope of the 8-bit image Q = level/255 ≈ floor(256·D)/255 w.r.t. D.
STRAIGHT_THROUGH_SLOPE = 256.0 / 255.0


def display_vjp(rendering: Rendering, grad_display: np.ndarray, through_levels: bool = False) -> np.ndarray:
    """Pull ∂L/∂D back to Ā = ∂L/∂Re A + i·∂L/∂Im A.

    With ``through_levels`` the incoming gradient is ∂L/∂Q for the 8-bit
    image Q = level/255 the scorer sees; quantisation is passed straight
    through with the slope of its linear part, ∂Q/∂D := 256/255.

    For a pixel above the floor, D = 1 + DISPLAY_SLOPE·(ln|A| − ln max|A|), so

        ∂L/∂|A|_n = g_n·s/|A|_n  and, at the brightest pixel, −s·Σ_n g_n / max|A|,

    summed over unclipped pixels n (s = DISPLAY_SLOPE). Clipped pixels
    (D = 0) and floored zeros pass no gradient. Then Ā = ∂L/∂|A|·A/|A|.
    """
    magnitude = rendering.magnitude
    unclipped = (rendering.display > 0) & (np.abs(rendering.a_scans) > 0)
    slope = DISPLAY_SLOPE * (STRAIGHT_THROUGH_SLOPE if through_levels else 1.0)
    grad = np.where(unclipped, grad_display, 0.0) * slope
    grad_magnitude = grad / magnitude
    brightest = np.unravel_index(np.argmax(magnitude), magnitude.shape)
    grad_magnitude[brightest] -= grad.sum() / magnitude[brightest]
    return grad_magnitude * rendering.a_scans / magnitude


def render(phantom: Phantom, config: ScannerConfig = DEFAULT_CONFIG, backend: str = "opencl",
           device=None, settings=None) -> Rendering:
    """Render a phantom with the Virtual Scanner.

    Parameters
    ----------
    phantom : Phantom
        The scatterers; validated against ``config`` first.
    config : ScannerConfig
        Scanner geometry and optics.
    backend : {"opencl", "numpy"}
        The OpenCL kernels (default) or the float64 NumPy reference.
    device : str, optional
        OpenCL device choice (see :mod:`octcl.device.runtime`).
    settings : KernelSettings, optional
        Accuracy knobs of the kernels.

    Returns
    -------
    Rendering
    """
    phantom.validate(config)
    if backend == "numpy":
        reference = ref.render_reference(phantom, config)
        return Rendering(a_scans=reference.a_scans, magnitude=reference.magnitude,
                         display=reference.display, levels=reference.levels)
    if backend != "opencl":
        raise ValueError(f"unknown backend {backend!r}; use 'opencl' or 'numpy'")
    from .device.runtime import select_device
    from .device.scanner import KernelSettings

    if device is None or isinstance(device, str):
        device = select_device(device)
    kernels, lock = _scanner_kernels(config, settings or KernelSettings(), device)
    with np.errstate(divide="ignore"):
        log_energy = np.log(phantom.energy_pct)
    with lock:
        kernels.set_phantom(phantom.x_um, phantom.y_um, phantom.z_um, log_energy)
        a_scans = kernels.forward()
    return Rendering.from_a_scans(a_scans)


@functools.lru_cache(maxsize=8)
def _scanner_kernels(config: ScannerConfig, settings, device):
    """The OpenCL scanner for a configuration, kernel settings and device, made once per process.

    Making one builds the programs (or takes them from PyOpenCL's binary
    cache) in the device's context and uploads the spreading tables; kept,
    it makes every later :func:`render` only lay out the phantom and run
    the forward kernel. The lock serialises renders that share it (its
    phantom layout is state).
    """
    from .device.scanner import ScannerKernels

    return ScannerKernels(config, settings, device), threading.Lock()
