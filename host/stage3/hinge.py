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

(w_p = 1, but at the anchor where a run may weigh it more),

and the scanner's adjoint (:meth:`octcl.device.scanner.ScannerKernels.adjoint`)
takes Ā to ∂loss/∂u and ∂loss/∂z per scatterer, shadowing included.

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
        The anchor pixel's weight in the sum, every other pixel's being 1 (``scripts/bench_hinge_trace.py``
        measures others: docs/benchmarks.md, "Where the hinge loses time").
    """

    def __init__(self, aim: np.ndarray, start_a_scans: np.ndarray, margin: float = INTERVAL_MARGIN,
                 anchor_weight: float = 1.0):
        magnitude = np.abs(start_a_scans)
        scale = float(magnitude.max())
        if not scale > 0:
            raise ValueError("the start rendering is dark: no pixel to anchor the levels' bounds at")
        lower, upper = anchored_bounds(aim, magnitude / scale, margin)
        self.lower, self.upper = lower * scale, upper * scale
        self.weight = np.where(lower == upper, float(anchor_weight), 1.0)

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


#: L-BFGS pairs kept in a hinge phase (stage 1's hinge fit keeps 10, :data:`octcl.host.stage1.hinge.LEVEL_FIT_MEMORY`):
#: 10 pairs of 2·295,000 float64 unknowns are 94 MB.
HINGE_MEMORY = 10

__all__ = ["HINGE_MEMORY", "HingeUnknowns", "LevelHinge"]
