"""The display fit's loss and its hand-derived gradient (host/stage1/display_loss.py)."""


import numpy as np
import pytest

from octcl.host.stage1.display_loss import DisplayGoal, box3, box3_adjoint, display_loss
from octcl.host.stage1.operator import FieldOperator
from octcl.render import DISPLAY_SLOPE
from conftest import SMALL_SCANNER as SMALL


def _small_goal(seed: int = 0):
    """Random levels on the small scanner, the first rows at level 0 (the clamp at 0), in float64."""
    rng = np.random.default_rng(seed)
    levels = rng.integers(0, 256, SMALL.shape).astype(np.uint8)
    levels[:3] = 0
    field = rng.normal(size=SMALL.shape) + 1j * rng.normal(size=SMALL.shape)
    return levels, DisplayGoal.of(levels, dtype=np.float64), field, rng


def test_display_loss_gradient_matches_finite_differences():
    """Re⟨G, δF⟩ against the central difference of the loss along random directions δF."""
    _, goal, field, rng = _small_goal()
    operator = FieldOperator(SMALL)
    _, gradient = display_loss(field, operator, goal)
    step = 1e-6
    for _ in range(20):
        direction = rng.normal(size=SMALL.shape) + 1j * rng.normal(size=SMALL.shape)
        difference = (display_loss(field + step * direction, operator, goal)[0]
                      - display_loss(field - step * direction, operator, goal)[0]) / (2 * step)
        assert np.real(np.vdot(gradient, direction)) == pytest.approx(difference, rel=1e-6, abs=1e-12)


def test_display_loss_gradient_matches_torch_autograd():
    """The same loss written in torch (as stage 1 was before its gradient was derived by hand)."""
    import torch

    _, goal, field, _ = _small_goal(1)
    operator = FieldOperator(SMALL)
    loss, gradient = display_loss(field, operator, goal)

    def high_pass(image):
        padded = torch.nn.functional.pad(image[None, None], (1, 1, 1, 1), mode="replicate")
        return image - torch.nn.functional.avg_pool2d(padded, 3, stride=1)[0, 0]

    variable = torch.tensor(field, requires_grad=True)
    spectrum = torch.fft.fft2(variable, s=(SMALL.depth_pixels, operator.padded_columns))
    a_scans = torch.fft.ifft2(spectrum * torch.as_tensor(operator.transfer))[:, :SMALL.a_scans]
    power = a_scans.real**2 + a_scans.imag**2
    log_amplitude = 0.5 * torch.log(power + 1e-24 * power.detach().max())
    display = 1.0 + DISPLAY_SLOPE * (log_amplitude - log_amplitude.max())
    visible = torch.as_tensor(goal.visible)
    display = torch.where(visible, display.clamp(min=-1.0), display.clamp(min=0.0))
    target = torch.as_tensor(goal.display)
    error = display - target
    torch_loss = (error.abs().mean() + (error**2).mean() + 0.5 * (high_pass(display) - high_pass(target)).abs().mean()
                  + goal.energy_weight * (variable.abs()**2).mean() / power.max())
    torch_loss.backward()
    assert loss == pytest.approx(torch_loss.item(), rel=1e-12)
    # torch's gradient of a real loss in a complex tensor is ∂L/∂Re + i·∂L/∂Im, as G is.
    np.testing.assert_allclose(gradient, variable.grad.numpy(), rtol=0, atol=1e-12 * np.abs(gradient).max())


def test_box3_adjoint():
    rng = np.random.default_rng(3)
    image, other = rng.normal(size=(7, 5)), rng.normal(size=(7, 5))
    assert np.vdot(other, box3(image)) == pytest.approx(np.vdot(box3_adjoint(other), image), rel=1e-12)
