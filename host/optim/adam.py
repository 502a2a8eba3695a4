"""Adam (Kingma & Ba, "Adam: a method for stochastic optimization", ICLR 2015) on NumPy arrays, in place.

Stage 1's display fit and stage 3's refinement both step with it. It is
written here rather than taken from ``torch.optim``: those steps run on
NumPy arrays (and, on a device, in kernels), and constructing a
``torch.optim`` optimiser imports ``torch._dynamo``: ``python -c "import
torch; torch.optim.Adam([torch.zeros(1, requires_grad=True)])"`` takes
3.0 s on two cores of an AMD EPYC against 1.2 s for ``import torch``, for
ten lines of arithmetic.
"""

from __future__ import annotations

import numpy as np


class Adam:
    """Adam on a list of parameter arrays, in place, with per-array learning rates.

    m ← β1·m + (1 − β1)·g,  v ← β2·v + (1 − β2)·g²,
    θ ← θ − lr·(m / (1 − β1^t)) / (sqrt(v / (1 − β2^t)) + ε).

    Parameters
    ----------
    shapes : iterable of tuple
        The shapes of the parameters, in the order :meth:`step` takes them.
    beta1, beta2 : float
        Decay rates of the first and second moments.
    epsilon : float
        Guard of the denominator.
    dtype : numpy dtype
        Of the moments (the parameters' own).
    """

    #: (β1, β2, ε) of the paper, the defaults (``kernels/adam.cl`` is built with them).
    DEFAULTS = (0.9, 0.999, 1e-8)

    def __init__(self, shapes, beta1: float = DEFAULTS[0], beta2: float = DEFAULTS[1], epsilon: float = DEFAULTS[2],
                 dtype=np.float64):
        self.beta1, self.beta2, self.epsilon = beta1, beta2, epsilon
        self.first = [np.zeros(shape, dtype=dtype) for shape in shapes]
        self.second = [np.zeros(shape, dtype=dtype) for shape in shapes]
        self.steps = 0

    def step(self, params, grads, lrs) -> None:
        """One step of every parameter array ``params[k]`` along ``grads[k]`` at learning rate ``lrs[k]``."""
        self.steps += 1
        first_correction = 1 - self.beta1**self.steps
        second_correction = 1 - self.beta2**self.steps
        for param, grad, lr, m, v in zip(params, grads, lrs, self.first, self.second):
            m *= self.beta1
            m += (1 - self.beta1) * grad
            v *= self.beta2
            v += (1 - self.beta2) * grad**2
            param -= lr * (m / first_correction) / (np.sqrt(v / second_correction) + self.epsilon)


__all__ = ["Adam"]
