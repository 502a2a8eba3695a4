"""Stage 1's field operator A = H·F: the linear, shadowing-free scanner on the cell grid.

Without shadowing (T = 1) the Virtual Scanner (``shared/physics.md`` §2) is
linear in the complex weights a_j·e^{−2i·k0·z_j} of its scatterers. Put one
scatterer in every cell of the B-scan grid, at the A-scan position x_i,
elevation y = 0 and the depth

    z_n = n·π/(Nz·δk)   (≈ 5.99991·n µm for the task's scanner),

where 2·δk·z_n = 2π·n/Nz falls exactly on a DFT bin, and call its complex
weight F[n, i] = a·e^{−2i·k0·z_n}. Steps 3 and 5–8 then become a circular
convolution in depth (the DFT wraps) and a 5-tap convolution across A-scans:

    A[n, i] = Σ_{n', i'} F[n', i']·g[i − i']·h[n − n'],
    h = IDFT_q(w_q),   g[d] = exp(−(d·Δx)²/w0²) where (d·Δx)² < 3·w0², else 0,

with w the Hann window in FFT order (so |d| ≤ 2 for Δx = 6 µm, w0 = 10 µm).
In the Fourier domain of depth (q) and of the zero-padded columns (p) it is a
product, Â[q, p] = w_q·ĝ_p·F̂[q, p]: :class:`FieldOperator`, the float64
NumPy reference of the OpenCL op :class:`octcl.host.stage1.operator_device.FieldKernels`,
at the same padding.

References
----------
Tikhonov & Arsenin, "Solutions of ill-posed problems", Winston 1977
(the regularised inverse, :meth:`FieldOperator.pseudo_inverse`).
"""

from __future__ import annotations

import math

import numpy as np
import scipy.fft

from ... import _reference as ref
from ...config import DEFAULT_CONFIG, ScannerConfig

#: Tikhonov parameter of the initial inverse, relative to max |w·ĝ|².
#: MS-SSIM of the fitted display at the start / after 400 steps, Uniform_A and
#: orange: 1e−2: 0.9879 / 0.9996, 0.9919 / 0.9990; 1e−3: 0.9885 / 0.9997,
#: 0.9945 / 0.9988; 1e−4: 0.9669 / 0.9996, 0.9843 / 0.9991.
REGULARISATION = 1e-3


def cell_depths_um(config: ScannerConfig = DEFAULT_CONFIG) -> np.ndarray:
    """Depth z_n = n·π/(Nz·δk) of the cell centres in µm, n = 0 … Nz−1.

    At these depths 2·δk·z_n = 2π·n/Nz, so a scatterer's depth kernel is
    sampled exactly on its own row: z_n = n·Δz·(Nz − 1)(Nz + 1)/Nz².
    """
    k = ref.wavenumbers(config)
    dk = k[1] - k[0]
    return np.arange(config.depth_pixels) * np.pi / (config.depth_pixels * dk)


def lateral_taps(config: ScannerConfig = DEFAULT_CONFIG) -> np.ndarray:
    """Beam weights g[d] = exp(−(d·Δx)²/w0²) for the A-scan offsets d = −R … R.

    R is the largest offset inside the contribution window
    (d·Δx)² < 3·w0² (step 3 at y = 0); R = 2 for the task's scanner.
    """
    w0, pitch = config.beam_radius_um, config.lateral_pitch_um
    reach = math.ceil(math.sqrt(ref.CONTRIBUTION_RADIUS_SQ) * w0 / pitch)
    offsets_um = np.arange(-reach, reach + 1) * pitch
    inside = ref.in_contribution_window(offsets_um, np.zeros_like(offsets_um), w0)
    offsets_um = offsets_um[inside]
    return ref.beam_weight(offsets_um, np.zeros_like(offsets_um), w0)


def padded_column_count(config: ScannerConfig, reach: int) -> int:
    """P, the padded columns of H⁺: the first power of two ≥ Nx + 2R (1024 for Nx = 512), what the OpenCL
    op's radix-4/radix-2 FFTs take."""
    return 1 << (config.a_scans + 2 * reach - 1).bit_length()


class FieldOperator:
    """The linear, shadowing-free scanner on the cell grid: F ↦ A (module docstring).

    The columns are zero-padded to P ≥ Nx + 2R so that
    the lateral convolution does not wrap; the depth convolution wraps, as the
    scanner's DFT does.

    Attributes
    ----------
    config : ScannerConfig
    cell_depth_um : ndarray, (Nz,)
        :func:`cell_depths_um`.
    taps : ndarray, (2R+1,)
        :func:`lateral_taps`.
    padded_columns : int
        P.
    transfer : ndarray of complex128, (Nz, P)
        w_q·ĝ_p, the 2-D DFT of the point response.
    workers : int
        Threads of the FFTs (``scipy.fft``'s ``workers``). Each 1-D transform
        is one thread's, so the result has the same bits at any count.

    ``padded_columns`` sets P (≥ Nx + 2R); by default
    :func:`padded_column_count`, the power of two the OpenCL op
    (:mod:`octcl.host.stage1.operator_device`) pads to, so that the two
    backends invert the same circulant extension and the kernel tests
    compare like with like. P changes only :meth:`pseudo_inverse`.
    """

    def __init__(self, config: ScannerConfig = DEFAULT_CONFIG, workers: int = 1, padded_columns: int | None = None):
        self.config = config
        self.cell_depth_um = cell_depths_um(config)
        self.taps = lateral_taps(config)
        reach = self.taps.size // 2
        smallest = config.a_scans + 2 * reach
        if padded_columns is not None and padded_columns < smallest:
            raise ValueError(f"padded_columns must be ≥ Nx + 2R = {smallest}, got {padded_columns}")
        self.padded_columns = padded_column_count(config, reach) if padded_columns is None else padded_columns
        kernel = np.zeros(self.padded_columns)
        kernel[np.arange(-reach, reach + 1)] = self.taps  # offset d at column d mod P
        window = ref.hann_window(config.depth_pixels)
        self.transfer = window[:, None] * np.fft.fft(kernel)[None, :]
        self._transfers = {(single, conjugate): (np.conj(self.transfer) if conjugate else self.transfer)
                           .astype(np.complex64 if single else np.complex128)
                           for single in (False, True) for conjugate in (False, True)}
        self.workers = workers
        self._inverses = {}  # regularisation → conj(H)/(|H|² + λ), for pseudo_inverse

    def apply(self, field: np.ndarray) -> np.ndarray:
        """A-scans A[n, i] ((Nz, Nx), complex of the field's precision) of the field F[n, i]."""
        nz, nx = self.config.shape
        spectrum = scipy.fft.fft2(field, s=(nz, self.padded_columns), workers=self.workers)
        return scipy.fft.ifft2(spectrum * self._transfer_as(spectrum), workers=self.workers)[:, :nx]

    def adjoint(self, a_scans: np.ndarray) -> np.ndarray:
        """Hᴴ: the adjoint of :meth:`apply` (⟨H·F, A⟩ = ⟨F, Hᴴ·A⟩), (Nz, Nx).

        The crop's adjoint pads the columns with zeros; the 2-D circular
        convolution's is the one with the conjugate transfer function.
        """
        nz, nx = self.config.shape
        spectrum = scipy.fft.fft2(a_scans, s=(nz, self.padded_columns), workers=self.workers)
        return scipy.fft.ifft2(spectrum * self._transfer_as(spectrum, conjugate=True), workers=self.workers)[:, :nx]

    def _transfer_as(self, spectrum: np.ndarray, conjugate: bool = False) -> np.ndarray:
        """The transfer function (or its conjugate) in the spectrum's precision: complex64 keeps a float32
        fit in float32."""
        single = spectrum.dtype == np.complex64
        return self._transfers[single, conjugate]

    def pseudo_inverse(self, a_scans: np.ndarray, regularisation: float = REGULARISATION) -> np.ndarray:
        """Tikhonov-regularised inverse: the F minimising ‖A(F) − a_scans‖² + λ·‖F‖².

        In the Fourier domain F̂ = conj(H)·Â/(|H|² + λ), H = w_q·ĝ_p, with
        λ = ``regularisation``·max|H|²; the padding columns are dropped.
        """
        nz, nx = self.config.shape
        spectrum = scipy.fft.fft2(a_scans, s=(nz, self.padded_columns), workers=self.workers)
        return scipy.fft.ifft2(spectrum * self.inverse_transfer(regularisation), workers=self.workers)[:, :nx]

    def inverse_transfer(self, regularisation: float = REGULARISATION) -> np.ndarray:
        """conj(H)/(|H|² + λ), λ = ``regularisation``·max|H|²: :meth:`pseudo_inverse`'s product, (Nz, P)."""
        inverse = self._inverses.get(regularisation)
        if inverse is None:
            damping = regularisation * np.max(np.abs(self.transfer)) ** 2
            inverse = self._inverses[regularisation] = np.conj(self.transfer) / (np.abs(self.transfer) ** 2 + damping)
        return inverse

