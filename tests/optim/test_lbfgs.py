"""L-BFGS on one array (host/optim/lbfgs.py)."""

import numpy as np

from octcl.host.optim.lbfgs import minimise


def test_a_convex_quadratic_is_minimised():
    """½xᵀAx − bᵀx, A symmetric positive definite with condition number 100: the solution of Ax = b."""
    rng = np.random.default_rng(0)
    basis, _ = np.linalg.qr(rng.normal(size=(40, 40)))
    matrix = basis @ np.diag(np.geomspace(1, 100, 40)) @ basis.T
    target = rng.normal(size=40)
    x, taken = minimise(lambda x: (0.5 * x @ matrix @ x - target @ x, matrix @ x - target), np.zeros(40), 200)
    np.testing.assert_allclose(x, np.linalg.solve(matrix, target), rtol=0, atol=1e-6)


def test_a_complex_array_is_its_real_and_imaginary_parts():
    """f(z) = Σ|z − c|² has the gradient 2(z − c) = ∂f/∂Re + i·∂f/∂Im, and its minimum at c."""
    rng = np.random.default_rng(1)
    centre = rng.normal(size=(6, 5)) + 1j * rng.normal(size=(6, 5))
    z, _ = minimise(lambda z: (float(np.sum(np.abs(z - centre) ** 2)), 2 * (z - centre)),
                    np.zeros((6, 5), complex), 50)
    assert z.shape == (6, 5) and z.dtype == complex
    np.testing.assert_allclose(z, centre, atol=1e-8)


def test_rosenbrock_and_the_callback_that_stops_it():
    def rosenbrock(x):
        a, b = x
        return (1 - a) ** 2 + 100 * (b - a * a) ** 2, np.array([-2 * (1 - a) - 400 * a * (b - a * a),
                                                                200 * (b - a * a)])

    x, taken = minimise(rosenbrock, np.array([-1.2, 1.0]), 500)
    np.testing.assert_allclose(x, [1.0, 1.0], atol=1e-5)
    seen = []

    def stop_after_three(x):
        seen.append(x.copy())
        if len(seen) == 3:
            raise StopIteration

    _, taken = minimise(rosenbrock, np.array([-1.2, 1.0]), 500, callback=stop_after_three)
    assert taken == 3 and len(seen) == 3
    assert rosenbrock(seen[2])[0] < rosenbrock(seen[0])[0] < rosenbrock(np.array([-1.2, 1.0]))[0]


def test_a_stationary_start_stays():
    x, taken = minimise(lambda x: (float(x @ x), 2 * x), np.zeros(3), 10)
    assert taken == 0 and not x.any()


def test_an_iteration_tries_at_most_max_halvings_steps():
    """A loss whose gradient points uphill (its sign flipped): no step of −g decreases it, so the first iteration
    tries 1, ½, … (``max_halvings`` steps, each one evaluation) and the minimisation ends where it began."""
    evaluations = []

    def misleading(x):
        evaluations.append(x.copy())
        return float(x @ x), -2 * x

    start = np.array([1.0, -2.0])
    for max_halvings in (30, 8):
        evaluations.clear()
        x, taken = minimise(misleading, start, 10, max_halvings=max_halvings)
        assert taken == 0 and np.array_equal(x, start)
        assert len(evaluations) == 1 + max_halvings  # the start, then each step tried
        steps = [np.linalg.norm(trial - start) for trial in evaluations[1:]]
        np.testing.assert_allclose(np.array(steps[1:]) / steps[:-1], 0.5, rtol=1e-5)  # steps to 2^−29 of 2
