"""The nuisance projection (Frisch-Waugh-Lovell) against the full least-squares problem."""

import numpy as np

from jaxafm.identify.projection import project_out


def _block_design(z: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """The full nuisance design: each group's columns on its own samples, zero elsewhere."""
    labels = np.unique(groups)
    return np.concatenate([z * (groups == g)[:, None] for g in labels], axis=1)


def test_projection_is_the_weighted_residual_of_the_block_nuisance_fit():
    """``M v`` equals ``v - Z (Z^T W Z)^+ Z^T W v`` with the block-diagonal ``Z`` written out, for
    two nuisance columns per group, weights with zeros (masked samples projected with their
    group's coefficients) and a matrix ``v``."""
    rng = np.random.default_rng(0)
    n = 60
    groups = rng.integers(0, 5, n) * 3  # labels need not be 0..G-1
    z = np.stack([np.where(rng.random(n) < 0.5, 0.5, -0.5), rng.normal(size=n)], -1)
    w = np.where(rng.random(n) < 0.2, 0.0, rng.uniform(0.5, 2.0, n))
    v = rng.normal(size=(n, 3))
    full = _block_design(z, groups)
    expected = v - full @ np.linalg.pinv(full.T @ (w[:, None] * full)) @ full.T @ (w[:, None] * v)
    np.testing.assert_allclose(project_out(v, z, groups, w), expected, atol=1e-12)


def test_projected_fit_equals_the_full_fit():
    """Frisch-Waugh-Lovell: the wanted coefficients from the projected problem are those of the
    full regression with a nuisance column per group (one column, one group per sample pair)."""
    rng = np.random.default_rng(1)
    n = 40
    groups = np.repeat(np.arange(n // 2), 2)
    sign = np.tile([1.0, -1.0], n // 2)
    a = rng.normal(size=(n, 3))
    b = a @ [1.0, -2.0, 0.5] + sign * rng.normal(size=n // 2).repeat(2) + 0.01 * rng.normal(size=n)
    theta = np.linalg.lstsq(project_out(a, sign, groups), project_out(b, sign, groups), rcond=None)[0]
    full = np.linalg.lstsq(np.concatenate([a, _block_design(sign[:, None], groups)], 1), b, rcond=None)[0]
    np.testing.assert_allclose(theta, full[:3], atol=1e-10)


def test_one_group_and_unit_weights_by_default():
    """Without groups or weights: the plain residual of a least-squares fit of the columns (here
    a plane a + b x over the samples)."""
    x = np.linspace(-1.0, 1.0, 11)
    v = 2.0 + 3.0 * x + x**2
    plane = np.stack([np.ones_like(x), x], -1)
    np.testing.assert_allclose(project_out(v, plane), x**2 - np.mean(x**2), atol=1e-12)
