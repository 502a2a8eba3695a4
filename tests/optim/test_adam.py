"""Adam on NumPy arrays (host/optim/adam.py), as stage 1's display fit and stage 3 use it."""

import numpy as np

from octcl.host.optim.adam import Adam


def test_adam_matches_the_textbook_update():
    """One step from zero moments moves every parameter by −lr·sign(g) (bias-corrected Adam)."""
    adam = Adam([(3,), (2,)], beta1=0.9, beta2=0.999, epsilon=1e-20)
    first, second = np.array([1.0, 2.0, 3.0]), np.array([0.5, -0.5])
    adam.step((first, second), (np.array([1e-12, -4.0, 0.0]), np.array([3.0, -1e-9])), (0.1, 0.01))
    np.testing.assert_allclose(first, [0.9, 2.1, 3.0])
    np.testing.assert_allclose(second, [0.49, -0.49])


def test_adam_keeps_its_moments_in_the_parameters_precision():
    adam = Adam([(4,)], dtype=np.float32)
    parameter = np.ones(4, dtype=np.float32)
    adam.step((parameter,), (np.full(4, 0.5, dtype=np.float32),), (0.1,))
    assert parameter.dtype == adam.first[0].dtype == adam.second[0].dtype == np.float32
    np.testing.assert_allclose(parameter, 0.9, rtol=1e-6)
