"""Thin host-side op around ``kernels/level_fit.cl``: stage 1's level intervals on an OpenCL device.

:class:`LevelKernels` runs, on the fields of a
:class:`~octcl.host.stage1.operator_device.FieldKernels` (A-scan by A-scan, (Nx, Nz)),
the projection P_𝓜 onto the aimed levels' intervals [l, u] of
:func:`octcl.host.stage1.levels.level_magnitude_bounds` (each pixel's magnitude
clipped, its phase kept: :func:`octcl.host.stage1.levels.interval_projection`), the
accelerated projections' update (:func:`octcl.host.stage1.projections.retrieve_field`)
and the hinge's residual r = A − P_𝓜(A) with ½·Σ|r|² (the loss of
:func:`octcl.host.stage1.hinge.fit_levels`), summed in a fixed order into a device
scalar by :class:`octcl.host.optim.lbfgs_device.VectorKernels`.
``tests/stage1/test_levels_device.py`` compares each kernel with NumPy in float64.
"""

from __future__ import annotations

import numpy as np

from ...device.programs import REDUCTION_WORK_GROUP, build
from .operator_device import FieldKernels
from ..optim.lbfgs_device import VectorKernels


def program_defines(work_group_size: int = REDUCTION_WORK_GROUP) -> tuple:
    """Compile-time constants of ``kernels/level_fit.cl`` (its header): the reductions' work-group size (the
    hinge runs in :class:`VectorKernels`' work-groups, into its partials)."""
    return (("REDUCTION_GROUP_SIZE", work_group_size),)


class LevelKernels:
    """P_𝓜, the projection step's update and the hinge residual on a :class:`FieldKernels`' device.

    Parameters
    ----------
    kernels : FieldKernels
        The device, its queue, precision and grid.

    Attributes
    ----------
    kernels : FieldKernels
    vectors : VectorKernels
        L-BFGS's vector operations on the same queue; its ``finish_sum``
        adds the hinge's group sums.
    """

    def __init__(self, kernels: FieldKernels):
        import pyopencl as cl

        self.kernels = kernels
        double = kernels.real == np.float64
        self.vectors = VectorKernels(kernels.context, kernels.queue, double)
        program = build(kernels.context, "level_fit", program_defines(self.vectors.work_group_size), double)
        self._interval_difference = cl.Kernel(program, "interval_difference")
        self._momentum_step = cl.Kernel(program, "momentum_step")
        self._hinge_residual = cl.Kernel(program, "hinge_residual")
        self.pixels = kernels.config.a_scans * kernels.config.depth_pixels

    def bounds_to_device(self, lower: np.ndarray, upper: np.ndarray):
        """The host's (Nz, Nx) bounds [l, u] as device arrays (Nx, Nz) of the kernels' real dtype."""
        return tuple(self.kernels.image_to_device(bound, self.kernels.real) for bound in (lower, upper))

    def interval_difference(self, a_scans, lower, upper, out=None):
        """D = P_𝓜(A) − A; returns ``out`` (a new device field when None). ``out`` may be ``a_scans``."""
        out = self.kernels.empty() if out is None else out
        self._interval_difference(self.kernels.queue, (self.pixels,), None, a_scans.data, lower.data, upper.data,
                                  out.data)
        return out

    def momentum_step(self, field, ahead, correction, step: float, momentum: float):
        """In place: F ← Y + α·X, then Y ← F_new + β·(F_new − F_old), X = ``correction``, α = ``step``,
        β = ``momentum``; returns its event."""
        real = self.kernels.real
        return self._momentum_step(self.kernels.queue, (self.pixels,), None, field.data, ahead.data,
                                   correction.data, real(step), real(momentum))

    def hinge_residual(self, a_scans, lower, upper, residual, scalars, slot: int):
        """residual = A − P_𝓜(A) (``residual`` may be ``a_scans``) and scalars[slot] = ½·Σ|r|², summed in a
        fixed order; returns the event of the sum."""
        vectors = self.vectors
        self._hinge_residual(self.kernels.queue, (vectors.groups * vectors.work_group_size,),
                             (vectors.work_group_size,), a_scans.data, lower.data, upper.data,
                             np.int32(self.pixels), residual.data, vectors.partials.data)
        return vectors.finish_sum(vectors.partials, scalars, slot)


__all__ = ["LevelKernels", "program_defines"]
