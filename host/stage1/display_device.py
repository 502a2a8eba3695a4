"""Thin host-side op around ``kernels/display_loss.cl`` and ``kernels/adam.cl``: the display fit's step on a device.

:class:`DisplayFitKernels` holds one display fit's state on the device (the
polar parameters ρ = ln|F| and θ = arg F, Adam's moments, the field, the
target's display) and enqueues one step: A = H·F
(:class:`octcl.host.stage1.operator_device.FieldKernels`), the loss and G_A
(``kernels/display_loss.cl``), Hᴴ·G_A, then Adam's update of ρ and θ and
the new F (``kernels/adam.cl``). Nothing is read back during a step: each
step writes its loss into a device array that :meth:`DisplayFitKernels.losses`
reads when the caller asks (:func:`octcl.host.stage1.display.fit_field` does every
:data:`LOSS_READ_EVERY` steps, for its progress). The NumPy twins are
:func:`octcl.host.stage1.display_loss.display_loss` and :class:`octcl.host.optim.adam.Adam`;
``tests/stage1/test_display_device.py`` compares them on every OpenCL
implementation present.
"""

from __future__ import annotations

import numpy as np

from ...device.programs import REDUCTION_WORK_GROUP, build, reduction_work_group
from ...render import DISPLAY_SLOPE
from ..optim.adam import Adam
from .display_loss import DISPLAY_GRADIENT_FLOOR, HIGH_PASS_WEIGHT, LOG_FLOOR, DisplayGoal
from .operator_device import FieldKernels

#: Work-groups of a pass over the pixels on a CPU device: each work-item then sums 32 pixels of a 256×512 scan
#: in a loop (a CPU runs a work-group's barriers as loops over its work-items, so fewer, longer work-items pay
#: fewer of them). A GPU gets a work-group per 8·REDUCTION_WORK_GROUP pixels.
CPU_PASS_GROUPS = 64
#: The device fit reads its losses back every this many steps (progress, and nothing else, needs them).
LOSS_READ_EVERY = 25
#: The slots of the fit's device array ``stats``, in order (``kernels/display_loss.cl``'s header): P_m,
#: Σ|F|², Σ(|e| + e²), Σ|r|, Σ ∂L/∂D. The kernels get each slot's index as a define of its name.
STAT_SLOTS = ("STAT_PEAK", "STAT_ENERGY", "STAT_ERROR", "STAT_RESIDUAL", "STAT_DISPLAY_GRADIENT")


def program_defines(config, energy_weight: float, group_size: int = REDUCTION_WORK_GROUP, cpu: bool = True) -> tuple:
    """Compile-time constants of ``kernels/display_loss.cl`` and ``kernels/adam.cl`` (their headers)."""
    pixels = config.a_scans * config.depth_pixels
    groups = min(CPU_PASS_GROUPS, -(-pixels // group_size)) if cpu else -(-pixels // (8 * group_size))
    beta1, beta2, epsilon = Adam.DEFAULTS
    return (("NZ", config.depth_pixels), ("NX", config.a_scans), ("REDUCTION_GROUP_SIZE", group_size),
            ("PARTIALS", groups), ("DISPLAY_SLOPE", repr(float(DISPLAY_SLOPE))),
            ("FLOOR_VISIBLE", repr(float(DISPLAY_GRADIENT_FLOOR))), ("HIGH_PASS_WEIGHT", repr(float(HIGH_PASS_WEIGHT))),
            ("ENERGY_WEIGHT", repr(float(energy_weight))), ("LOG_FLOOR", repr(float(LOG_FLOOR))),
            ("ADAM_BETA1", repr(beta1)), ("ADAM_BETA2", repr(beta2)), ("ADAM_EPSILON", repr(epsilon)),
            *((name, slot) for slot, name in enumerate(STAT_SLOTS)))


class DisplayFitKernels:
    """One display fit on the device (module docstring).

    Parameters
    ----------
    field_kernels : FieldKernels
        The operator, its device and precision.
    goal : DisplayGoal
        The target's display; ``goal.energy_weight`` is λ_E.
    log_magnitude, phase : ndarray, (Nz, Nx)
        ρ and θ of the start.
    iterations : int
        Steps at most (the size of the loss array).
    """

    def __init__(self, field_kernels: FieldKernels, goal: DisplayGoal, log_magnitude: np.ndarray,
                 phase: np.ndarray, iterations: int):
        import pyopencl as cl
        import pyopencl.array as cl_array

        self.ops = ops = field_kernels
        config, queue = ops.config, ops.queue
        group = reduction_work_group(ops.device)
        defines = program_defines(config, goal.energy_weight, group, bool(ops.device.type & cl.device_type.CPU))
        self.group_size, self.partials = group, dict(defines)["PARTIALS"]
        double = ops.real == np.float64
        loss_program = build(ops.context, "display_loss", defines, double)
        adam_program = build(ops.context, "adam", defines, double)
        self._kernels = {name: cl.Kernel(loss_program, name) for name in (
            "peak_partials", "finish_peak", "display_error", "high_pass_residual", "display_gradient",
            "finish_loss", "a_scan_gradient")}
        self._adam = cl.Kernel(adam_program, "adam_polar_step")

        def zeros(count, dtype):
            return cl_array.zeros(queue, count, dtype)

        real = ops.real
        self.goal_display = ops.image_to_device(goal.display, real)
        self.goal_high_pass = ops.image_to_device(goal.high_pass, real)
        self.visible = ops.image_to_device(goal.visible, np.int8)
        self.log_magnitude = ops.image_to_device(log_magnitude, real)
        self.phase = ops.image_to_device(phase, real)
        self.moments = [zeros(self.log_magnitude.shape, real) for _ in range(4)]
        start = np.exp(np.asarray(log_magnitude, dtype=real)) * (np.cos(phase) + 1j * np.sin(phase))
        self.field = ops.to_device(start.astype(ops.complex))
        self.a_scans, self.a_scan_grad, self.field_grad = ops.empty(), ops.empty(), ops.empty()
        self.clamped = zeros(self.log_magnitude.shape, real)
        self.passes = zeros(self.log_magnitude.shape, np.int8)
        self.residual_sign = zeros(self.log_magnitude.shape, real)
        self.display_grad = zeros(self.log_magnitude.shape, real)
        self.partial_power, self.partial_index = zeros(self.partials, real), zeros(self.partials, np.int32)
        self.partial_energy, self.partial_error = zeros(self.partials, real), zeros(self.partials, real)
        self.partial_residual, self.partial_display_grad = zeros(self.partials, real), zeros(self.partials, real)
        self.stats, self.brightest = zeros(len(STAT_SLOTS), real), zeros(1, np.int32)
        self.loss_history = zeros(max(1, iterations), real)
        self.steps = 0

    def gradient(self):
        """Enqueue the loss of the current field (into ``losses[steps]``) and G_A, then Hᴴ·G_A into ``field_grad``."""
        ops, queue, k = self.ops, self.ops.queue, self._kernels
        pixels = self.partials * self.group_size
        local = (self.group_size,)
        ops.apply(self.field, self.a_scans)
        k["peak_partials"](queue, (pixels,), local, self.a_scans.data, self.field.data, self.partial_power.data,
                           self.partial_index.data, self.partial_energy.data)
        k["finish_peak"](queue, local, local, self.partial_power.data, self.partial_index.data,
                         self.partial_energy.data, self.stats.data, self.brightest.data)
        k["display_error"](queue, (pixels,), local, self.a_scans.data, self.stats.data, self.brightest.data,
                           self.goal_display.data, self.visible.data, self.clamped.data, self.passes.data,
                           self.partial_error.data)
        k["high_pass_residual"](queue, (pixels,), local, self.clamped.data, self.goal_high_pass.data,
                                self.residual_sign.data, self.partial_residual.data)
        k["display_gradient"](queue, (pixels,), local, self.clamped.data, self.passes.data, self.goal_display.data,
                              self.residual_sign.data, self.display_grad.data, self.partial_display_grad.data)
        k["finish_loss"](queue, local, local, self.partial_error.data, self.partial_residual.data,
                         self.partial_display_grad.data, self.stats.data, self.loss_history.data,
                         np.int32(min(self.steps, self.loss_history.size - 1)))
        k["a_scan_gradient"](queue, (self.field.size,), None, self.a_scans.data, self.display_grad.data,
                             self.stats.data, self.brightest.data, self.a_scan_grad.data)
        ops.adjoint(self.a_scan_grad, self.field_grad)

    def step(self, lr: float):
        """Enqueue one step at learning rate ``lr`` (the loss of the field before it goes to ``losses``); returns
        the event of its last kernel."""
        self.gradient()
        self.steps += 1
        beta1, beta2, _ = Adam.DEFAULTS
        real = self.ops.real
        return self._adam(self.ops.queue, (self.field.size,), None, self.field_grad.data, self.field.data,
                          self.log_magnitude.data, self.phase.data, *(moment.data for moment in self.moments),
                          self.stats.data, real(lr), real(1 - beta1**self.steps), real(1 - beta2**self.steps))

    def losses(self) -> np.ndarray:
        """The losses of the steps so far (reads the device)."""
        return self.loss_history.get()[:self.steps].astype(np.float64)

    def parameters(self) -> tuple[np.ndarray, np.ndarray]:
        """ρ and θ, (Nz, Nx), in the kernels' precision (reads the device)."""
        return self.log_magnitude.get().T, self.phase.get().T


__all__ = ["DisplayFitKernels", "LOSS_READ_EVERY", "STAT_SLOTS", "program_defines"]
