"""Stage 1 of the inversion: a complex reflectivity field on the pixel grid.

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
product, Â[q, p] = w_q·ĝ_p·F̂[q, p]: :class:`FieldOperator`.

:func:`fit_field` finds F whose display D (steps 9–10: 20·log10|A|, the
brightest pixel at 0 dB, a 51 dB range) matches the target B-scan's. The
target gives only |A| (to 8-bit precision), so this is phase retrieval; the
phases are what the decoder (:mod:`octcl.host.decode`) turns into depths.

References
----------
Kingma & Ba, "Adam: a method for stochastic optimization", ICLR 2015.
Loshchilov & Hutter, "SGDR: stochastic gradient descent with warm restarts",
ICLR 2017 (cosine annealing).
Tikhonov & Arsenin, "Solutions of ill-posed problems", Winston 1977
(regularised inverse of the initialisation).
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass

import numpy as np
import scipy.fft

from .. import _reference as ref
from .._io import GREY_LUT
from ..config import DEFAULT_CONFIG, ScannerConfig
from ..render import DISPLAY_SLOPE, Rendering
from .adam import Adam

#: Adam's step size in (ln|F|, phase) units: 5 % in magnitude, 0.05 rad in phase.
LEARNING_RATE = 0.05
#: Weight of the high-pass L1 term of the loss.
HIGH_PASS_WEIGHT = 0.5
#: Weight of the field-energy term of the loss (normalisation in :func:`fit_field`).
#: Measured end to end (1500 steps, decode, OpenCL render with shadowing, the
#: eight-component score of the 8-bit scan) on Uniform_A / Layers_A / orange:
#: weight 0: 0.99625 / 0.99933 / 0.98889; 0.03: 0.99621 / 0.99933 / 0.99322;
#: 0.1: 0.99624 / 0.99903 / 0.99252; 0.3: 0.99603 / 0.99868 / 0.99039;
#: 1: 0.99453 / 0.99547 / 0.99483; 2: 0.98934 / 0.98505 / 0.97759. The
#: scan's own MS-SSIM on orange, the least noisy of these on the real scan,
#: was 0.99855 at weight 0 and 0.99952–0.99969 from 0.03 to 1: a little
#: energy penalty steadies the fit of a real scan, much of it costs detail.
ENERGY_WEIGHT = 0.1
#: Share of the time budget that the learning rate's clock term ignores
#: (:func:`fit_field`): the first steps, FFT plans and the initialisation
#: would otherwise put the clock ahead of the step count on every fit, and
#: the learning rate, in its last bits, would follow the clock.
CLOCK_MARGIN = 0.1
#: Tikhonov parameter of the initial inverse, relative to max |w·ĝ|².
#: MS-SSIM of the fitted display at the start / after 400 steps, Uniform_A and
#: orange: 1e−2: 0.9879 / 0.9996, 0.9919 / 0.9990; 1e−3: 0.9885 / 0.9997,
#: 0.9945 / 0.9988; 1e−4: 0.9669 / 0.9996, 0.9843 / 0.9991.
REGULARISATION = 1e-3
#: Display values below this (in the units of D) give no gradient where the
#: target is visible: deeper than 51 dB under the display floor a speckle null
#: of the model is left to the pixels around it instead of a diverging log.
DISPLAY_GRADIENT_FLOOR = -1.0
#: Magnitude given to the pixels at the display floor (level 0) in the
#: initialisation, relative to the floor magnitude: 6 dB below the floor.
BELOW_FLOOR_FRACTION = 0.5


# ------------------------------------------------------------------ target
def target_levels(target, config: ScannerConfig | None = None) -> np.ndarray:
    """The target's 8-bit levels.

    Parameters
    ----------
    target : ndarray
        uint8 levels, or a float image as :func:`octcl._io.read_scan` returns
        it (level/255), which is rounded back to levels.
    config : ScannerConfig, optional
        If given, the target must have its shape (Nz, Nx).

    Returns
    -------
    ndarray of uint8, (Nz, Nx)
    """
    target = np.asarray(target)
    if target.ndim != 2:
        raise ValueError(f"expected a 2-D B-scan, got shape {target.shape}")
    if config is not None and target.shape != config.shape:
        raise ValueError(f"target is {target.shape[0]}x{target.shape[1]}, the scanner makes "
                         f"{config.shape[0]}x{config.shape[1]}")
    if target.dtype == np.uint8:
        return target
    if not np.issubdtype(target.dtype, np.floating) or not np.isfinite(target).all():
        raise ValueError(f"expected uint8 levels or a finite float image in [0, 1], got {target.dtype}")
    return np.clip(np.rint(target * 255.0), 0, 255).astype(np.uint8)


def _display_of_level() -> np.ndarray:
    """D at the centre of the display interval of each 8-bit level.

    The scanner writes level GREY_LUT[c] for colour index c = min(⌊256·D⌋, 255),
    so a level L comes from D in the union of [c/256, (c+1)/256) over the
    indices c with GREY_LUT[c] = L (two indices for the 24 levels below a
    truncated index). The estimate is the centre of that union. The 24
    truncated levels themselves never come out of the scanner; a target made
    otherwise (a real scan quantised plainly) has them, and for those the
    plain quantiser's interval [L/256, (L+1)/256) is used. Level 0 is handled
    by :func:`target_display`.
    """
    index = np.arange(256)
    low = index / 256.0
    high = (index + 1) / 256.0
    produced = np.zeros(256, dtype=bool)
    produced[GREY_LUT] = True
    low[produced] = np.inf
    high[produced] = -np.inf
    np.minimum.at(low, GREY_LUT, index / 256.0)
    np.maximum.at(high, GREY_LUT, (index + 1) / 256.0)
    return 0.5 * (low + high)


def target_display(target) -> np.ndarray:
    """The target's display D*, de-quantised.

    Each level maps to the centre of the D interval it stands for
    (:func:`_display_of_level`), except level 0, which maps to D* = 0: it
    holds the pixels at or below the display floor (|A| ≤ max|A|·10^{−51/20},
    plus the first 1/256 above it), whose magnitude is unknown. The loss of
    :func:`fit_field` treats these pixels as the inequality D ≤ 0 (it clamps
    the model's D at 0 there), not as an equality.

    Returns
    -------
    ndarray of float64, (Nz, Nx), in [0, 1]
    """
    levels = target_levels(target)
    display = _display_of_level()[levels]
    display[levels == 0] = 0.0
    return display


def target_magnitude(target) -> np.ndarray:
    """De-logged target magnitude |A|/max|A| = 10^{51·(D* − 1)/20}.

    D* is :func:`target_display`. The pixels at level 0 lie below the display
    floor with unknown magnitude; they get a small value, half the floor
    magnitude (6 dB below it), which is only used to start the fit.

    Returns
    -------
    ndarray of float64, (Nz, Nx), in (0, 1]
    """
    display = target_display(target)
    magnitude = 10.0 ** (ref.DISPLAY_RANGE_DB * (display - 1.0) / 20.0)
    floor = 10.0 ** (-ref.DISPLAY_RANGE_DB / 20.0)
    return np.where(target_levels(target) == 0, BELOW_FLOOR_FRACTION * floor, magnitude)


# ---------------------------------------------------------------- operator
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


class FieldOperator:
    """The linear, shadowing-free scanner on the cell grid: F ↦ A (module docstring).

    The columns are zero-padded to P ≥ Nx + 2R (a fast FFT length) so that
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

    ``padded_columns`` sets P (≥ Nx + 2R); by default the first fast FFT
    length. It changes only :meth:`pseudo_inverse` (the circulant extension
    it inverts): the OpenCL op (:mod:`octcl.host.field_kernels`) pads to a
    power of two and is tested against this class at its P.
    """

    def __init__(self, config: ScannerConfig = DEFAULT_CONFIG, workers: int = 1, padded_columns: int | None = None):
        self.config = config
        self.cell_depth_um = cell_depths_um(config)
        self.taps = lateral_taps(config)
        reach = self.taps.size // 2
        smallest = config.a_scans + 2 * reach
        if padded_columns is not None and padded_columns < smallest:
            raise ValueError(f"padded_columns must be ≥ Nx + 2R = {smallest}, got {padded_columns}")
        self.padded_columns = scipy.fft.next_fast_len(smallest) if padded_columns is None else padded_columns
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


# --------------------------------------------------------------------- fit
@dataclass
class FieldFit:
    """Result of :func:`fit_field`.

    Attributes
    ----------
    field : ndarray of complex128, (Nz, Nx)
        F, scaled so that the brightest pixel of A(F) has |A| = 1.
    display : ndarray of float64, (Nz, Nx)
        D of A(F) (no shadowing), as :class:`octcl.render.Rendering` computes it.
    target_display : ndarray of float64, (Nz, Nx)
        D* (:func:`target_display`).
    losses : ndarray of float64
        The loss at each iteration.
    iterations : int
        Adam steps taken.
    seconds : float
        Wall time of the fit, initialisation included.
    threads : int
        FFT threads used (:attr:`FieldOperator.workers`).
    clock_steps : int
        Steps whose learning rate the clock set (the fit had fallen behind
        its time budget, :func:`fit_field`); 0: the fit took no decision
        from the clock.
    """

    field: np.ndarray
    display: np.ndarray
    target_display: np.ndarray
    losses: np.ndarray
    iterations: int
    seconds: float
    threads: int
    clock_steps: int


def _box3(image: np.ndarray) -> np.ndarray:
    """The 3×3 mean of an image, its edges replicated."""
    padded = np.pad(image, 1, mode="edge")
    rows = padded[:-2] + padded[1:-1] + padded[2:]
    return (rows[:, :-2] + rows[:, 1:-1] + rows[:, 2:]) / 9.0


def _box3_adjoint(image: np.ndarray) -> np.ndarray:
    """The adjoint of :func:`_box3`: each value spread over its 3×3 window of the padded image, the
    padding then folded back onto the edge it replicates."""
    nz, nx = image.shape
    spread = np.zeros((nz + 2, nx + 2), dtype=image.dtype)
    for row in range(3):
        for column in range(3):
            spread[row:row + nz, column:column + nx] += image
    spread[1] += spread[0]
    spread[-2] += spread[-1]
    spread[:, 1] += spread[:, 0]
    spread[:, -2] += spread[:, -1]
    return spread[1:-1, 1:-1] / 9.0


def _high_pass(image: np.ndarray) -> np.ndarray:
    """hp(X) = X − box3(X): the image minus its 3×3 mean (edges replicated)."""
    return image - _box3(image)


@dataclass
class DisplayGoal:
    """What :func:`display_loss` compares a field's display with: the de-quantised target.

    Attributes
    ----------
    display : ndarray, (Nz, Nx)
        D* (:func:`target_display`), in the fit's precision.
    high_pass : ndarray, (Nz, Nx)
        hp(D*).
    visible : ndarray of bool, (Nz, Nx)
        D* > 0: the pixels above level 0.
    energy_weight : float
        λ_E.
    """

    display: np.ndarray
    high_pass: np.ndarray
    visible: np.ndarray
    energy_weight: float

    @classmethod
    def of(cls, levels: np.ndarray, energy_weight: float = ENERGY_WEIGHT, dtype=np.float32) -> "DisplayGoal":
        display = target_display(levels).astype(dtype)
        return cls(display, _high_pass(display), display > 0, energy_weight)


def display_loss(field: np.ndarray, operator: FieldOperator, goal: DisplayGoal) -> tuple[float, np.ndarray]:
    """The display fit's loss of a field and its gradient, derived by hand (:func:`fit_field`).

    With A = H·F, P = |A|², m the first brightest pixel, c = 10⁻²⁴·P_m
    (held constant), s = :data:`octcl.render.DISPLAY_SLOPE` and N pixels:

        ℓ = ½·ln(P + c),  D = 1 + s·(ℓ − ℓ_m),
        D̃ = max(D, −1) where the target is visible, max(D, 0) at level 0,
        e = D̃ − D*,  r = hp(D̃) − hp(D*),
        L = Σ(|e| + e²)/N + ½·Σ|r|/N + λ_E·(Σ|F|²/N)/P_m.

    Backwards, with sgn(0) = 0 and the clamps passing the gradient where
    D is at or above their bound:

        ∂L/∂D̃ = (sgn e + 2e)/N + ½·hpᵀ(sgn r)/N,   hpᵀ(Y) = Y − box3ᵀ(Y),
        ∂L/∂ℓ = s·∂L/∂D − δ_m·s·Σ ∂L/∂D,
        G_A = ∂L/∂ℓ · A/(P + c) − δ_m·2A_m·λ_E·(Σ|F|²/N)/P_m²,
        G_F = Hᴴ·G_A + 2λ_E·F/(N·P_m),

    G = ∂L/∂Re + i·∂L/∂Im, so that dL = Re Σ conj(G)·dF (Wirtinger; for
    dℓ = Re(conj(A)·dA)/(P + c) and dP = 2·Re(conj(A)·dA)).
    ``tests/test_field.py`` checks it against finite differences and
    against torch's autograd of the same loss.

    Returns
    -------
    loss : float
    gradient : ndarray of complex, (Nz, Nx)
        G_F.
    """
    a_scans = operator.apply(field)
    power = a_scans.real**2 + a_scans.imag**2
    brightest = np.unravel_index(np.argmax(power), power.shape)
    peak = power[brightest]
    shifted = power + 1e-24 * peak
    log_amplitude = 0.5 * np.log(shifted)
    display = 1.0 + DISPLAY_SLOPE * (log_amplitude - log_amplitude[brightest])
    floor = np.where(goal.visible, DISPLAY_GRADIENT_FLOOR, 0.0).astype(display.dtype)
    clamped = np.maximum(display, floor)
    error = clamped - goal.display
    residual = _high_pass(clamped) - goal.high_pass
    count = error.size
    energy = float((field.real**2 + field.imag**2).sum(dtype=np.float64)) / count
    loss = (float(np.abs(error).sum(dtype=np.float64) + (error**2).sum(dtype=np.float64)) / count
            + HIGH_PASS_WEIGHT * float(np.abs(residual).sum(dtype=np.float64)) / count
            + goal.energy_weight * energy / float(peak))

    residual_sign = np.sign(residual)
    d_clamped = (np.sign(error) + 2.0 * error + HIGH_PASS_WEIGHT * (residual_sign - _box3_adjoint(residual_sign))) \
        / count
    d_display = np.where(display >= floor, d_clamped, 0.0)
    d_log = DISPLAY_SLOPE * d_display
    d_log[brightest] -= DISPLAY_SLOPE * d_display.sum(dtype=np.float64)
    d_a_scans = (d_log / shifted) * a_scans
    d_a_scans[brightest] -= 2.0 * a_scans[brightest] * goal.energy_weight * energy / float(peak) ** 2
    gradient = operator.adjoint(d_a_scans) + (2.0 * goal.energy_weight / (count * float(peak))) * field
    return loss, gradient.astype(field.dtype, copy=False)


def _available_cores() -> int:
    """CPU cores this process may use: those it may run on, at most ``OMP_NUM_THREADS`` where set.

    ``OMP_NUM_THREADS`` is how a process is given a share of a machine's
    cores: batch schedulers set it per job, and octcl's batch mode sets it
    in each Dask worker to the worker's thread count
    (:mod:`octcl.host.batch.runner`), so that two workers on two cores use
    one core each instead of both timing and fighting over both.
    """
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cores = os.cpu_count() or 1
    share = os.environ.get("OMP_NUM_THREADS", "")
    return min(cores, int(share)) if share.isdigit() and int(share) >= 1 else cores


def _thread_trials(threads: int | None, iterations: int) -> list[int]:
    """Thread counts for the first steps of a fit; after them the fastest is kept.

    Several threads beat one on an idle machine, but when other processes
    hold the cores every thread barrier waits for a descheduled thread:
    measured here, an element-wise op on a 256×512 image took 12 ms with 2
    OpenMP threads against 40 µs with 1. Timing real steps picks whichever
    holds now. The first step (FFT plans, allocations) is a warm-up and is
    not timed; then two steps with 1 thread and two with every core.
    """
    cores = _available_cores()
    if threads is not None or cores == 1 or iterations < 5:
        return []
    return [1, 1, 1, cores, cores]


def fit_field(target, config: ScannerConfig = DEFAULT_CONFIG, iterations: int = 1500,
              time_budget_s: float | None = 40.0, energy_weight: float = ENERGY_WEIGHT,
              threads: int | None = None, dtype=np.float32,
              progress=None, initial: np.ndarray | None = None, kernels=None) -> FieldFit:
    """Fit the complex field F of the linear scanner to a target B-scan (stage 1).

    Minimises, with Adam (Kingma & Ba 2015; step 0.05, cosine annealing),

        L(F) = mean|D − D*| + mean(D − D*)² + 0.5·mean|hp(D) − hp(D*)|
               + λ_E·mean|F|² / max|A|²,

    where A = A(F) (:class:`FieldOperator`), D = 1 + s·ln(|A|/max|A|) with
    s = 20/(51·ln 10) (the display without its clamp), D* the de-quantised
    target (:func:`target_display`) and hp(X) = X − box3(X) a high-pass.
    Where the target is at level 0, D is clamped at 0 (the inequality
    D ≤ 0: any magnitude below the floor is right); elsewhere it is clamped
    at −1 only, so a model pixel below the floor is still pulled up.

    The energy term is the field energy in units of the brightest rendered
    pixel, the unit the display itself uses; like the image terms it is
    scale-free, so it does not shrink F but penalises the field's shape:
    energy the scanner does not show (cancellation between neighbouring
    cells, components in the weak directions of the operator). At the end of
    a fit with λ_E = 0.1 (:data:`ENERGY_WEIGHT`, measured there) it is
    0.005–0.009 against about 0.001 for the image terms: a regulariser.

    F is parameterised by ρ = ln|F| and θ = arg F: the display is logarithmic
    over 51 dB and Adam's step is ≈ the step size in parameter units, so a
    step is a 5 % magnitude or 0.05 rad phase change at every brightness (in
    Re/Im the same step would swamp the cells 51 dB below the brightest).

    The start is the Tikhonov inverse (:meth:`FieldOperator.pseudo_inverse`)
    of the de-logged target magnitude (:func:`target_magnitude`) with zero
    phase: a non-negative image is mostly low-frequency, so the operator's
    pass band carries it and A(F₀) already has the target's speckle.
    Measured (MS-SSIM of the fitted display, 8-bit; about 20 ms of CPU a
    step in torch then, so 100 steps ≈ 2 s), for this start, the de-logged magnitude with
    random phases as F₀, and the inverse of the magnitude with random phases:

    ============  =========================  =========================
    steps         Uniform_A                  orange
    ============  =========================  =========================
    1             0.9885 / 0.8438 / 0.8951   0.9945 / 0.6959 / 0.7958
    100           0.9986 / 0.9944 / 0.9946   0.9965 / 0.9760 / 0.9752
    400           0.9997 / 0.9992 / 0.9990   0.9988 / 0.9967 / 0.9952
    ============  =========================  =========================

    so the random-phase starts are not offered.

    The learning rate follows lr₀·½(1 + cos(π·τ)) with
    τ = max(i/N, (t/T − m)/(1 − m)): i of N ``iterations`` taken, t of
    T = ``time_budget_s`` seconds used, m = :data:`CLOCK_MARGIN`. The
    schedule completes whichever ends first, and the clock takes over only
    where the fit falls behind the time it was given: a fit whose steps keep
    ahead of the clock's term (all of them on two idle cores: 1500 steps in
    11–12 s of a 45 s share) takes no decision from the clock. Then, or
    without a time budget, the fit depends on nothing but the target and
    the iterations: it is the same, bit for bit, at any thread count (each
    1-D FFT is one thread's, the sums NumPy's own; ``scripts/check_determinism.py``).

    The loss's gradient is derived by hand (:func:`display_loss`) and the
    step is :class:`octcl.host.adam.Adam`: no torch, whose import and
    first optimiser (``python -c "import torch;
    torch.optim.Adam([torch.zeros(1, requires_grad=True)])"``) take 3.0 s on
    two cores of an AMD EPYC, ``import torch`` alone 1.2 s.

    Parameters
    ----------
    target : ndarray
        The target B-scan: uint8 levels or a float image from
        :func:`octcl._io.read_scan` (see :func:`target_levels`).
    config : ScannerConfig
        Scanner geometry; the target must have its shape (Nz, Nx).
    iterations : int
        Most Adam steps.
    time_budget_s : float or None
        Most wall time in seconds, initialisation included; the loop stops
        at the first step that ends past it. None: no time limit, all
        ``iterations`` run.
    energy_weight : float
        λ_E, the weight of the field-energy term.
    threads : int, optional
        FFT threads (:attr:`FieldOperator.workers`). By default 1 and all
        available cores are each timed on two steps and the faster is kept
        (see :func:`_thread_trials`); a fit of fewer than 5 steps, or on one
        core, uses 1.
    dtype : numpy.float32 or numpy.float64
        Precision of the fit (complex64 or complex128 FFTs). float32 took
        15.2 ms a step against 18.1 ms for float64 on Uniform A
        (``python scripts/bench_field_steps.py --threads 1``,
        two cores of an AMD EPYC).
    progress : callable, optional
        Called as ``progress(iteration, iterations, loss)`` after each step
        (on a device, for the steps since the last read, every few steps).
    initial : ndarray of complex, (Nz, Nx), optional
        The start; default the regularised inverse above.
    kernels : FieldKernels, optional
        Run the steps as OpenCL kernels on its device
        (:class:`octcl.host.display_kernels.DisplayFitKernels`), in its
        precision (``dtype`` is then the kernels'); ``threads`` then serves
        the host's FFTs of the start and the result only.

    Returns
    -------
    FieldFit
    """
    start = time.perf_counter()
    if iterations < 1 or not (time_budget_s is None or time_budget_s > 0):
        raise ValueError(f"need iterations ≥ 1 and time_budget_s > 0, got {iterations}, {time_budget_s}")
    if dtype not in (np.float32, np.float64):
        raise ValueError(f"dtype must be numpy.float32 or numpy.float64, got {dtype}")
    levels = target_levels(target, config)
    operator = FieldOperator(config, workers=threads or 1)
    if kernels is not None:
        dtype = kernels.real
    goal = DisplayGoal.of(levels, energy_weight, dtype)
    if initial is None:
        initial = operator.pseudo_inverse(target_magnitude(levels))
    initial = initial / np.abs(operator.apply(initial)).max()
    magnitude = np.abs(initial)
    floor = 1e-12 * magnitude.max()  # ln|F| of an exactly cancelled cell
    log_magnitude = np.log(np.maximum(magnitude, floor)).astype(dtype)
    phase = np.angle(initial).astype(dtype)
    schedule = _CosineSchedule(iterations, time_budget_s, start)
    if kernels is None:
        log_magnitude, phase, losses = _fit_on_host(operator, goal, log_magnitude, phase, schedule, threads, progress)
    else:
        log_magnitude, phase, losses = _fit_on_device(kernels, goal, log_magnitude, phase, schedule, progress)

    field = np.exp(log_magnitude.astype(np.float64)) * np.exp(1j * phase.astype(np.float64))
    a_scans = operator.apply(field)
    field /= np.abs(a_scans).max()
    display = Rendering.from_a_scans(a_scans).display
    return FieldFit(field=field, display=display, target_display=goal.display.astype(np.float64),
                    losses=np.asarray(losses, dtype=np.float64), iterations=len(losses),
                    seconds=time.perf_counter() - start, threads=operator.workers, clock_steps=schedule.clock_steps)


class _CosineSchedule:
    """The display fit's learning rate lr₀·½(1 + cos πτ), τ the larger of the steps' share and the clock's
    (:func:`fit_field`), and whether the fit may take another step."""

    def __init__(self, iterations: int, time_budget_s: float | None, start: float):
        self.iterations, self.time_budget_s, self.start = iterations, time_budget_s, start
        self.clock_steps = 0

    def time_fraction(self) -> float:
        return 0.0 if self.time_budget_s is None else (time.perf_counter() - self.start) / self.time_budget_s

    def go_on(self, taken: int) -> bool:
        return taken < self.iterations and self.time_fraction() < 1.0

    def rate(self, taken: int) -> float:
        clock = (self.time_fraction() - CLOCK_MARGIN) / (1.0 - CLOCK_MARGIN)
        self.clock_steps += clock > taken / self.iterations
        fraction = min(1.0, max(taken / self.iterations, clock))
        return LEARNING_RATE * 0.5 * (1.0 + math.cos(math.pi * fraction))


def _fit_on_host(operator: FieldOperator, goal: DisplayGoal, log_magnitude, phase, schedule: _CosineSchedule,
                 threads: int | None, progress):
    """The display fit's steps in NumPy (:func:`display_loss`, :class:`~octcl.host.adam.Adam`): ρ, θ, losses."""
    adam = Adam((log_magnitude.shape, phase.shape), dtype=log_magnitude.dtype)
    losses = []
    trials = _thread_trials(threads, schedule.iterations)
    trial_seconds = {}
    while schedule.go_on(len(losses)):
        trial = len(losses)
        if trial < len(trials):
            operator.workers = trials[trial]
        elif trial == len(trials) and trial_seconds:
            operator.workers = min(trial_seconds, key=trial_seconds.get)
        step_start = time.perf_counter()
        lr = schedule.rate(len(losses))
        field = np.exp(log_magnitude) * (np.cos(phase) + 1j * np.sin(phase))
        loss, gradient = display_loss(field, operator, goal)
        # ∂L/∂ln|F| = Re(conj(G)·F), ∂L/∂arg F = Re(conj(G)·iF) = −Im(conj(G)·F).
        along = np.conj(gradient) * field
        adam.step((log_magnitude, phase), (along.real, -along.imag), (lr, lr))
        losses.append(loss)
        if 0 < trial < len(trials):
            trial_seconds[trials[trial]] = trial_seconds.get(trials[trial], 0.0) + time.perf_counter() - step_start
        if progress is not None:
            progress(len(losses), schedule.iterations, loss)
    return log_magnitude, phase, losses


def _fit_on_device(kernels, goal: DisplayGoal, log_magnitude, phase, schedule: _CosineSchedule, progress):
    """The display fit's steps as OpenCL kernels (:class:`~octcl.host.display_kernels.DisplayFitKernels`): ρ, θ,
    losses. The loop enqueues steps without reading the device; it reads the losses every
    :data:`~octcl.host.display_kernels.LOSS_READ_EVERY` steps for ``progress`` and at the end. The clock is the
    host's: a step is enqueued while the schedule allows, and the queue is drained every
    ``LOSS_READ_EVERY`` steps so that the clock sees the device's pace."""
    from .display_kernels import LOSS_READ_EVERY, DisplayFitKernels

    fit = DisplayFitKernels(kernels, goal, log_magnitude, phase, schedule.iterations)
    reported = 0
    while schedule.go_on(fit.steps):
        fit.step(schedule.rate(fit.steps))
        if fit.steps % LOSS_READ_EVERY == 0:
            reported = _report_losses(fit.losses(), reported, schedule.iterations, progress)  # waits for the queue
    losses = fit.losses()
    _report_losses(losses, reported, schedule.iterations, progress)
    log_magnitude, phase = fit.parameters()
    return log_magnitude, phase, losses


def _report_losses(losses: np.ndarray, reported: int, planned: int, progress) -> int:
    """``progress(step, planned, loss)`` for each step after the first ``reported``; returns the steps reported."""
    for index in range(reported, len(losses)) if progress is not None else ():
        progress(index + 1, planned, float(losses[index]))
    return len(losses)
