"""The geodesic Levenberg-Marquardt solver (``jaxafm.identify.geodesic``) against problems whose
answers are known without it: a linear least-squares problem (numpy's lstsq), Rosenbrock's
valley (minimum at (1, 1)), an exponential decay fitted to its own exact samples, and the second
directional derivative of a function written out by hand."""

import jax.numpy as jnp
import numpy as np
import pytest

from jaxafm.identify import geodesic


def _linear(x, packed):
    A, b = packed
    return A @ x - b


def _rosenbrock(x, packed):
    return jnp.stack([10 * (x[1] - x[0] ** 2), 1 - x[0]])


def _decay(x, packed):
    t, y = packed
    return x[0] * jnp.exp(-t / x[1]) + x[2] - y


def _curved(x, packed):
    return jnp.stack([x[0] ** 2, x[0] * x[1], jnp.sin(x[1])])


@pytest.mark.parametrize("curvature", geodesic.CURVATURES)
def test_linear_least_squares_is_numpys(curvature):
    rng = np.random.default_rng(0)
    A, b = rng.normal(size=(40, 5)), rng.normal(size=40)
    x, steps, ok = geodesic.solve(_linear, np.zeros(5), (A, b), 50, 1e-10, 1e-12, curvature)
    assert ok and steps < 50
    np.testing.assert_allclose(x, np.linalg.lstsq(A, b, rcond=None)[0], atol=1e-8)


@pytest.mark.parametrize("curvature", geodesic.CURVATURES)
def test_rosenbrock_valley_reaches_its_minimum(curvature):
    x, _, ok = geodesic.solve(_rosenbrock, np.array([-1.2, 1.0]), None, 200, 1e-12, 1e-14, curvature)
    assert ok
    np.testing.assert_allclose(x, [1.0, 1.0], atol=1e-6)


def test_exponential_decay_parameters_come_back_from_exact_samples():
    t = np.linspace(0.0, 5.0, 200)
    truth = np.array([3.0, 0.7, 0.5])  # amplitude, time constant (s), offset
    y = truth[0] * np.exp(-t / truth[1]) + truth[2]
    x, _, ok = geodesic.solve(_decay, np.array([1.0, 2.0, 0.0]), (t, y), 100, 1e-12, 1e-14)
    assert ok
    np.testing.assert_allclose(x, truth, rtol=1e-7)


def test_second_directional_derivative_is_the_hand_written_one():
    x, v = np.array([0.3, -1.1]), np.array([0.7, 0.4])
    # r = (x0^2, x0 x1, sin x1): r_vv = (2 v0^2, 2 v0 v1, -sin(x1) v1^2)
    want = [2 * v[0] ** 2, 2 * v[0] * v[1], -np.sin(x[1]) * v[1] ** 2]
    np.testing.assert_allclose(geodesic.compiled(_curved)[2](x, v, None), want, rtol=1e-12)


def test_a_step_limit_and_a_start_that_is_not_finite_are_reported():
    x, steps, ok = geodesic.solve(_rosenbrock, np.array([-1.2, 1.0]), None, 3, 1e-12, 1e-14)
    assert steps == 3 and not ok
    x0 = np.array([np.nan, 1.0])
    x, steps, ok = geodesic.solve(_rosenbrock, x0, None, 10, 1e-12, 1e-14)
    assert steps == 0 and not ok
    with pytest.raises(ValueError, match="curvature must be one of jvp, difference, got 'hessian'"):
        geodesic.solve(_rosenbrock, np.zeros(2), None, 10, 1e-8, 1e-8, "hessian")


def _undefined_beyond_one(x, packed):
    # r = x0 - 2, finite everywhere; its derivative is not defined (0 * inf) from x0 = 1 on
    return jnp.stack([x[0] - 2 + 0 * jnp.sqrt(jnp.maximum(1 - x[0], 0.0))])


@pytest.mark.parametrize("curvature", geodesic.CURVATURES)
def test_a_point_without_a_jacobian_is_not_taken(curvature):
    """The minimum (2) lies where the Jacobian is NaN: the solver stays where it is defined
    (x0 < 1), moving towards it, and returns without raising; started there it does not move."""
    x, _, ok = geodesic.solve(_undefined_beyond_one, np.zeros(1), None, 50, 1e-12, 1e-14, curvature)
    assert 0 < x[0] < 1 and not ok
    x, steps, ok = geodesic.solve(_undefined_beyond_one, np.array([1.5]), None, 50, 1e-12, 1e-14, curvature)
    assert x[0] == 1.5 and steps == 0 and not ok
