"""Stage 3's ``hinge`` phase: L-BFGS on every scatterer's amplitude and carrier phase until each pixel renders
at its aimed level.

Stage 1's hinge fit (:func:`octcl.host.stage1.hinge.fit_levels`) puts a
field's pixels at their levels; this is the same fit on a phantom, through
the scanner with its shadowing. With A(z, u) the rendered A-scans and
[l_p, u_p] the magnitudes that render pixel p at its aimed level, anchored
at the rendering's brightest pixel when the phase begins
(:func:`octcl.host.stage1.levels.anchored_bounds`, scaled by that max|A|: the
anchor pinned there, every other upper bound below it),

    loss = ½·Σ_p w_p·dist(|A_p|, [l_p, u_p])²,
    Ā_p = ∂loss/∂Re A_p + i·∂loss/∂Im A_p = w_p·(|A_p| − clip(|A_p|, l_p, u_p))·A_p/|A_p|,
    w_p = (u_p/u_anchor)^(−2γ)   (times the anchor's weight at the anchor, where a run may weigh it more),

and the scanner's adjoint (:meth:`octcl.device.scanner.ScannerKernels.adjoint`)
takes Ā to ∂loss/∂u and ∂loss/∂z per scatterer, shadowing included.

The weights change how L-BFGS gets there, not where: the loss is 0 exactly
where every pixel is inside its interval, whatever they are. In the unknowns
ln a, a pixel's own scatterers meet a curvature of about w_p·|A_p|², and
over the display's 51 dB the |A_p|² span a factor of 1.3e5: at γ = 0 (each
pixel's distance in absolute magnitude) the dark pixels are the last to
move, and a skin's scan ended with 1–3 % of its pixels a level off, most of
them dark (median level 20) and beside a pixel at level 0. γ = 1 (each
distance relative to its pixel's magnitude) evens the curvatures but lets
the deep, dark pixels pull as hard on the bright scatterers above them,
through the shadowing, as on their own; γ = ½ halves the span in decibels.
Whole default tissue runs, two Zen 4 cores (docs/benchmarks.md, "The hinge
weighs dark pixels more"): on skins 6 and 7 the main hinge at γ = ½ ended at
98.7 % and 99.4 % of pixels at their level (0.999944, 0.999984) against
96.9 % and 98.5 % (0.999912, 0.999963) at 0; at γ = 1 and ¾ below the pixel
phase's best on skin 6; but over its first hinge iterations γ = ½ dipped
lower (skin 6 0.99967 against 0.99986 at 31 s), and 30 s runs of
orange.png, it mirrored and through a gamma scored 0.99960, 0.99920, 0.99924
against 0.99947, 0.99951, 0.99962, and a default run of orange.png fell
at γ = ½ after 150 iterations at 0 and did not come back. So the tissue
schedule runs its whole hinge at γ = 0 and then goes on at ½, where the
restarts gain on orange.png too (:data:`octcl.host.pipeline.invert.TISSUE_SCHEDULE`).

The unknowns are ln a_j = u_j/2 and the carrier phase φ_j = 2·k0·z_j (rad),
where a scatterer shows a_j·e^{−iφ_j}: a step of 0.01 in either moves its
contribution by 1 % along or across itself, so L-BFGS's first steps weigh
them alike (in (u, z µm) a unit step in z turns the carrier by 9.7 rad).

Why L-BFGS. Adam's step is a fixed length in each unknown: the tissue
regime's pixel phase (lr_u 0.02, about one level of a pixel's amplitude)
leaves pixels one or two levels off, and the full loss after it holds them
there (a whole default tissue run of a skin phantom's scan, seed 8: 172 s,
92.8 % of pixels at their level, 0.99988). Stage 3 alone for 21 s from the
tissue start, the hinge between the pixel phase and the full loss: skin 8
0.99985 → 0.99988 (93.4 → 95.4 % at their level), orange.png 0.99930 →
0.99966; after 60 pixel steps instead of 120 it scored lower on all three
targets tried (``scripts/bench_tissue_refine.py --phases``, two Zen 4 cores;
docs/benchmarks.md, "Stage 3's hinge phase", with whole runs).
"""

from __future__ import annotations

import numpy as np

from ...config import DEFAULT_CONFIG, ScannerConfig
from ..stage1.levels import INTERVAL_MARGIN, anchored_bounds


def check_relative_exponent(relative_exponent: float) -> None:
    """Raise ValueError unless γ is in [0, 1] (module docstring)."""
    if not 0.0 <= relative_exponent <= 1.0:
        raise ValueError(f"relative_exponent must be in [0, 1], got {relative_exponent!r}")


class LevelHinge:
    """½·Σ_p dist(|A_p|, [l_p, u_p])² with the bounds anchored at a start rendering (module docstring).

    Parameters
    ----------
    aim : ndarray of uint8, (Nz, Nx)
        The levels each pixel is to render.
    start_a_scans : ndarray of complex, (Nz, Nx)
        The rendering whose brightest pixel at the highest aimed level anchors the bounds (|A| units).
    margin : float
        Share of each level's interval given up at each end (:func:`~octcl.host.stage1.levels.level_magnitude_bounds`).
    anchor_weight : float
        The anchor pixel's weight in the sum, every other pixel's being 1 at γ = 0 (``scripts/bench_hinge_trace.py``
        measures others: docs/benchmarks.md, "Where the hinge loses time").
    relative_exponent : float
        γ in [0, 1] (module docstring): each pixel's weight (u_p/u_anchor)^(−2γ).
    """

    def __init__(self, aim: np.ndarray, start_a_scans: np.ndarray, margin: float = INTERVAL_MARGIN,
                 anchor_weight: float = 1.0, relative_exponent: float = 0.0):
        check_relative_exponent(relative_exponent)
        magnitude = np.abs(start_a_scans)
        scale = float(magnitude.max())
        if not scale > 0:
            raise ValueError("the start rendering is dark: no pixel to anchor the levels' bounds at")
        lower, upper = anchored_bounds(aim, magnitude / scale, margin)
        self.lower, self.upper = lower * scale, upper * scale
        # upper is u_p/u_anchor here (the anchor's bounds are 1), > 0 at every level, level 0 included.
        self.weight = np.where(lower == upper, float(anchor_weight), 1.0) * upper ** (-2.0 * relative_exponent)

    def __call__(self, a_scans: np.ndarray) -> tuple[float, np.ndarray]:
        """(loss, Ā) of a rendering's complex A-scans."""
        magnitude = np.abs(a_scans)
        residual = magnitude - np.clip(magnitude, self.lower, self.upper)
        with np.errstate(divide="ignore", invalid="ignore"):
            a_bar = np.where(magnitude > 0, self.weight * residual / magnitude, 0.0) * a_scans
        return 0.5 * float((self.weight * residual**2).sum()), a_bar


class HingeUnknowns:
    """The hinge phase's unknowns x = (ln a, φ) = (u/2, 2·k0·z) of n scatterers, one float64 vector of 2n."""

    def __init__(self, config: ScannerConfig = DEFAULT_CONFIG):
        self.phase_per_um = 2.0 * config.k0_rad_per_um

    def pack(self, z_um: np.ndarray, log_energy: np.ndarray) -> np.ndarray:
        return np.concatenate([0.5 * log_energy, self.phase_per_um * z_um])

    def unpack(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(z_um, log_energy) of x, new arrays."""
        count = x.size // 2
        return x[count:] / self.phase_per_um, 2.0 * x[:count]

    def gradient(self, grad_u: np.ndarray, grad_z: np.ndarray) -> np.ndarray:
        """∂/∂x from ∂/∂u and ∂/∂z (chain rule: u = 2·x₁, z = x₂/(2·k0))."""
        return np.concatenate([2.0 * grad_u, grad_z / self.phase_per_um])


#: Steps a hinge iteration tries at most (1 to 1/128 of L-BFGS's), where stage 1's fit tries 30: each is a render and
#: an adjoint, and an iteration that needs smaller steps gains too little to pay for them. A whole default run of
#: skin 12 (its hinge 150 iterations at γ = 0, then 150 at ½) took 3–13 renders an iteration over the main hinge's
#: last iterations and about 13 (2 s) over each of its first restart's sixty, 120 s without moving the score; with
#: 8, see docs/benchmarks.md ("The hinge weighs dark pixels more").
HINGE_MAX_HALVINGS = 8
#: L-BFGS pairs kept in a hinge phase (stage 1's hinge fit keeps 10, :data:`octcl.host.stage1.hinge.LEVEL_FIT_MEMORY`):
#: 10 pairs of 2·295,000 float64 unknowns are 94 MB.
HINGE_MEMORY = 10

__all__ = ["HINGE_MAX_HALVINGS", "HINGE_MEMORY", "HingeUnknowns", "LevelHinge", "check_relative_exponent"]
