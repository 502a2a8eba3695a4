"""The display fit's loss and its hand-derived gradient: the maths both backends compute.

:func:`display_loss` is the float64/float32 NumPy reference of
``kernels/display_loss.cl`` (:mod:`octcl.host.stage1.display_device`); the
display fit (:func:`octcl.host.stage1.display.fit_field`) minimises it.
The constants here are passed to the kernels as defines
(:func:`octcl.host.stage1.display_device.program_defines`), so the two
cannot disagree.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...render import DISPLAY_SLOPE
from .levels import target_display
from .operator import FieldOperator

#: c/P_m, the floor under the power in ℓ = ½·ln(P + c): 240 dB below the brightest pixel, far below the
#: display's 51 dB, so that an exactly cancelled pixel has a finite log and gradient.
LOG_FLOOR = 1e-24
#: Weight of the high-pass L1 term of the loss.
HIGH_PASS_WEIGHT = 0.5
#: Weight of the field-energy term of the loss (normalisation in :func:`~octcl.host.stage1.display.fit_field`).
#: Measured end to end (1500 steps, decode, OpenCL render with shadowing, the
#: eight-component score of the 8-bit scan) on Uniform_A / Layers_A / orange:
#: weight 0: 0.99625 / 0.99933 / 0.98889; 0.03: 0.99621 / 0.99933 / 0.99322;
#: 0.1: 0.99624 / 0.99903 / 0.99252; 0.3: 0.99603 / 0.99868 / 0.99039;
#: 1: 0.99453 / 0.99547 / 0.99483; 2: 0.98934 / 0.98505 / 0.97759. The
#: scan's own MS-SSIM on orange, the least noisy of these on the real scan,
#: was 0.99855 at weight 0 and 0.99952–0.99969 from 0.03 to 1: a little
#: energy penalty steadies the fit of a real scan, much of it costs detail.
ENERGY_WEIGHT = 0.1
#: Display values below this (in the units of D) give no gradient where the
#: target is visible: deeper than 51 dB under the display floor a speckle null
#: of the model is left to the pixels around it instead of a diverging log.
DISPLAY_GRADIENT_FLOOR = -1.0


def box3(image: np.ndarray) -> np.ndarray:
    """The 3×3 mean of an image, its edges replicated."""
    padded = np.pad(image, 1, mode="edge")
    rows = padded[:-2] + padded[1:-1] + padded[2:]
    return (rows[:, :-2] + rows[:, 1:-1] + rows[:, 2:]) / 9.0


def box3_adjoint(image: np.ndarray) -> np.ndarray:
    """The adjoint of :func:`box3`: each value spread over its 3×3 window of the padded image, the
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


def high_pass(image: np.ndarray) -> np.ndarray:
    """hp(X) = X − box3(X): the image minus its 3×3 mean (edges replicated)."""
    return image - box3(image)


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
        return cls(display, high_pass(display), display > 0, energy_weight)


def display_loss(field: np.ndarray, operator: FieldOperator, goal: DisplayGoal) -> tuple[float, np.ndarray]:
    """The display fit's loss of a field and its gradient, derived by hand (:func:`~octcl.host.stage1.display.fit_field`).

    With A = H·F, P = |A|², m the first brightest pixel, c = 10⁻²⁴·P_m
    (held constant, :data:`LOG_FLOOR`), s = :data:`octcl.render.DISPLAY_SLOPE` and N pixels:

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
    ``tests/stage1/test_display_loss.py`` checks it against finite differences and
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
    shifted = power + LOG_FLOOR * peak
    log_amplitude = 0.5 * np.log(shifted)
    display = 1.0 + DISPLAY_SLOPE * (log_amplitude - log_amplitude[brightest])
    floor = np.where(goal.visible, DISPLAY_GRADIENT_FLOOR, 0.0).astype(display.dtype)
    clamped = np.maximum(display, floor)
    error = clamped - goal.display
    residual = high_pass(clamped) - goal.high_pass
    count = error.size
    energy = float((field.real**2 + field.imag**2).sum(dtype=np.float64)) / count
    loss = (float(np.abs(error).sum(dtype=np.float64) + (error**2).sum(dtype=np.float64)) / count
            + HIGH_PASS_WEIGHT * float(np.abs(residual).sum(dtype=np.float64)) / count
            + goal.energy_weight * energy / float(peak))

    residual_sign = np.sign(residual)
    d_clamped = (np.sign(error) + 2.0 * error + HIGH_PASS_WEIGHT * (residual_sign - box3_adjoint(residual_sign))) \
        / count
    d_display = np.where(display >= floor, d_clamped, 0.0)
    d_log = DISPLAY_SLOPE * d_display
    d_log[brightest] -= DISPLAY_SLOPE * d_display.sum(dtype=np.float64)
    d_a_scans = (d_log / shifted) * a_scans
    d_a_scans[brightest] -= 2.0 * a_scans[brightest] * goal.energy_weight * energy / float(peak) ** 2
    gradient = operator.adjoint(d_a_scans) + (2.0 * goal.energy_weight / (count * float(peak))) * field
    return loss, gradient.astype(field.dtype, copy=False)

