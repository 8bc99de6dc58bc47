"""The exact fit of operators linear in their weights (``jaxafm.nnls``): the solver against scipy's
``nnls`` and the KKT conditions, the streamed normal equations against the dense design matrix,
a Preisach plane fitted to NumPy relays, the real record against a gradient solver's optimum."""

from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pydantic
import pytest
import reference
from scipy.optimize import nnls

from jaxafm import Deadzone, GeneralizedPI, PrandtlIshlinskii, Preisach
from jaxafm.config.fit import ModelSpec
from jaxafm.identify import linear
from jaxafm.identify.fit import error_metrics, fit_operator, initial_operator
from jaxafm.instrument.records import read_record

REAL = Path(__file__).parents[1] / "jaxafm" / "data" / "real" / "piezo_sine_1hz.dat"


def drive(T=1200):
    """Amplitude-modulated sine in [0, 3.6] V: nested minor loops."""
    t = np.arange(T) / 100.0
    return 1.8 + 1.7 * (0.6 + 0.4 * np.cos(2 * np.pi * t / 5.0)) * np.sin(2 * np.pi * t)


def test_nonnegative_solve_equals_scipy_nnls():
    """Without a ridge, on a full-rank problem whose unconstrained solution has negative weights,
    block principal pivoting ends where scipy's Lawson-Hanson does (the solution is unique)."""
    rng = np.random.default_rng(0)
    A = rng.normal(size=(80, 15))
    d = A @ rng.normal(size=15) + 0.1 * rng.normal(size=80)
    assert np.any(np.linalg.lstsq(A, d, rcond=None)[0] < 0)
    want = nnls(A, d)[0]
    assert 0 < np.sum(want > 0) < 15
    w, _, how = linear.nonnegative_solve(A.T @ A, A.T @ d, ridge=0.0)
    assert how == "pivoting"
    np.testing.assert_allclose(w, want, atol=1e-10 * np.abs(want).max())
    w, _, how = linear.nonnegative_solve(A.T @ A, A.T @ d, ridge=0.0, max_steps=0)  # the fallback
    assert how == "scipy nnls"
    np.testing.assert_allclose(w, want, atol=1e-10 * np.abs(want).max())


def test_nonnegative_solve_meets_kkt_on_a_rank_deficient_gram():
    """Repeated and constant-sum columns (a drive that never separates two relays): the ridged
    problem's KKT conditions hold, ``w >= 0``, ``y = (G + ridge S^2) w - b`` zero where
    ``w > 0`` and ``>= 0`` where ``w = 0`` (S the column norms the ridge is scaled by)."""
    rng = np.random.default_rng(1)
    A = rng.normal(size=(60, 10))
    A = np.concatenate([A, A[:, :3], A[:, 3:4] + A[:, 4:5]], axis=1)
    d = A @ np.abs(rng.normal(size=14)) - 2.0 * A[:, 5] + 0.05 * rng.normal(size=60)
    G, b = A.T @ A, A.T @ d
    w, _, _ = linear.nonnegative_solve(G, b)
    y = (G + linear.RIDGE * np.diag(np.diag(G))) @ w - b
    tol = 1e-9 * np.abs(b).max()
    assert np.all(w >= 0)
    assert np.all(np.abs(y[w > 0]) <= tol)
    assert np.all(y[w == 0] >= -tol)
    assert np.sum(w == 0) >= 1  # the constraint is active somewhere


@pytest.mark.parametrize(
    "kind, samples, history",
    [("pi", 700, None), ("preisach", 700, None), ("preisach", 50, [0.0, 3.6])],
)
def test_streamed_normal_equations_equal_the_dense_design_matrix(kind, samples, history):
    """The Gram matrix made block by block (a record that is not a whole number of blocks, or
    shorter than one; a settled start; a history; the symmetric product cut into chunks) equals
    ``A_c^T A_c`` of the centred dense design matrix; the right-hand side and the means likewise."""
    u = drive(samples)
    d = 3.0 * u + np.sin(u)
    model = initial_operator(kind, u, d, operators=7, levels=7)
    settle = 37 if samples > 64 else 5
    eq = linear.normal_equations(model, u, d, history=history, settle=settle, block=64)
    h = None if history is None else jnp.asarray(history)
    A = np.asarray(model.design_matrix(jnp.asarray(u), h))[settle:]
    Ac, dc = A - A.mean(0), d[settle:] - d[settle:].mean()
    scale = np.abs(Ac.T @ Ac).max()
    np.testing.assert_allclose(eq.gram, Ac.T @ Ac, atol=1e-12 * scale)
    np.testing.assert_allclose(eq.rhs, Ac.T @ dc, atol=1e-12 * np.abs(Ac.T @ dc).max())
    np.testing.assert_allclose(eq.mean_row, A.mean(0), atol=1e-14)
    assert eq.samples == samples - settle
    assert eq.centred_ss == pytest.approx(dc @ dc, rel=1e-12)
    with pytest.raises(ValueError, match=f"settle={samples} samples .*record has {samples}"):
        linear.normal_equations(model, u, d, settle=samples)


def test_plays_that_never_move_get_no_weight_under_a_large_offset():
    """A drive of +-0.5 V under plays up to 2 V wide (the wider ones never move) and an output
    offset of -2.8e5 nm: the columns of the still plays are constant, so their weights are zero,
    and the fit trains as well as scipy's ``nnls`` on the dense moving plays, up to the ridge's
    cost at scipy's weights (its reported loss included)."""
    u = 1.8 + 0.5 * np.sin(2 * np.pi * np.arange(800) / 100.0)
    d = 1000.0 * u + 50.0 * np.sin(3 * u) - 2.8e5
    start = PrandtlIshlinskii(jnp.linspace(0.0, 2.0, 12), jnp.full(12, 1.0), jnp.asarray(0.0))
    A = np.asarray(start.design_matrix(jnp.asarray(u)))
    still = np.ptp(A, axis=0) == 0
    assert still.sum() >= 8
    res = fit_operator(start, u, d, solver="jaxafm.nnls")
    np.testing.assert_array_equal(np.asarray(res.model.weights)[still], 0.0)
    Am = A[:, ~still] - A[:, ~still].mean(0)
    want = nnls(Am, d - d.mean())[0]
    rss_want = np.sum((Am @ want - (d - d.mean())) ** 2)
    ridge_cost = linear.RIDGE * np.sum((np.linalg.norm(Am, axis=0) * want) ** 2)
    rss = np.sum((np.asarray(res.model(jnp.asarray(u))) - d) ** 2)
    assert rss <= rss_want + ridge_cost + 1e-9 * np.sum((d - d.mean()) ** 2)
    assert res.loss * len(u) * np.ptp(d) ** 2 == pytest.approx(rss, abs=1e-12 * np.sum((d - d.mean()) ** 2))


def test_preisach_fitted_to_numpy_relays_to_the_bound_the_ridge_allows():
    """A bare relay grid (8 levels, a random density) switched relay by relay in NumPy, no noise:
    the exact fit on the same grid trains to within the bias its ridge allows, ``rss <= ridge
    sum_i (s_i w_i)^2`` (the truth is feasible; ``s_i`` the centred column norms), with a
    non-negative density and the loss it reports."""
    u = drive(1207)[7:]  # not from the plane's centre: a bare relay centred there is a tie
    n = 8
    plane = initial_operator("preisach", u, u, levels=n)
    start = Preisach(plane.density, plane.u_min, plane.u_max, jnp.asarray(0.0), smooth=False)
    density = np.tril(np.random.default_rng(2).random((n, n)))
    d = 5.0 + reference.preisach_relay_grid(u, density, float(plane.u_min), float(plane.u_max))
    res = fit_operator(start, u, d, solver="jaxafm.nnls")
    assert res.converged and res.solver == "jaxafm.nnls"
    A = np.asarray(start.design_matrix(jnp.asarray(u)))
    s = np.linalg.norm(A - A.mean(0), axis=0)
    truth = density[np.tril_indices(n)]
    bound = linear.RIDGE * np.sum((s * truth) ** 2)
    rss = np.sum((np.asarray(res.model(jnp.asarray(u))) - d) ** 2)
    assert rss <= bound * (1 + 1e-9)
    # the loss it reports, from the normal equations: exact but for round-off on the centred sum
    centred_ss = np.sum((d - d.mean()) ** 2)
    assert res.loss * len(u) * np.ptp(d) ** 2 == pytest.approx(rss, abs=1e-12 * centred_ss)
    assert bool(jnp.all(res.model.density >= 0))


def test_pi_on_the_real_record_reaches_the_optimum_levenberg_marquardt_approaches():
    """The real piezo record's training part, a 20-play PI: the exact fit's residual sum of squares
    is at most LM's plus the ridge's cost at LM's weights (both are feasible for the ridged
    problem the exact fit minimises), and it predicts the held-out part as well (within 1 %)."""
    rec = read_record(REAL, input_columns=[1], output_columns=[5], sample_rate_hz=200, output_unit="um")
    u, d = np.asarray(rec.u), np.asarray(rec.d)
    n = int(0.6 * len(u))
    start = initial_operator("pi", u[:n], d[:n], operators=20)
    exact = fit_operator(start, u[:n], d[:n], solver="jaxafm.nnls")
    lm = fit_operator(start, u[:n], d[:n], solver="optimistix.levenberg_marquardt")
    assert lm.converged, lm.message
    A = np.asarray(start.design_matrix(jnp.asarray(u[:n])))
    s = np.linalg.norm(A - A.mean(0), axis=0)
    ridge_cost = linear.RIDGE * np.sum((s * np.asarray(lm.model.weights)) ** 2)
    scale = n * np.ptp(d[:n]) ** 2
    assert exact.loss * scale <= lm.loss * scale + ridge_cost
    held = [
        error_metrics(np.asarray(r.model(jnp.asarray(u)))[n:], d[n:])["rms_error_nm"] for r in (exact, lm)
    ]
    assert held[0] <= 1.01 * held[1]


def test_the_linear_solver_refuses_models_that_are_not_linear_in_their_weights():
    """A generalised PI's dead zones are not weights: a clear error from the API and from a config."""
    u = drive(200)
    pi = initial_operator("pi", u, 2 * u, operators=4)
    gpi = GeneralizedPI(pi, Deadzone.identity(np.array([-1.0]), np.array([1.0]), 3.6))
    with pytest.raises(TypeError, match="'jaxafm.nnls' fits operators .* not a GeneralizedPI"):
        fit_operator(gpi, u, 2 * u, solver="jaxafm.nnls")
    assert isinstance(pi, PrandtlIshlinskii)
    with pytest.raises(pydantic.ValidationError, match="solver 'jaxafm.nnls' .* not kind 'gpi'"):
        ModelSpec(name="g", kind="gpi", solver="jaxafm.nnls")
    with pytest.raises(pydantic.ValidationError, match="not kind 'preisach' with creep: true"):
        ModelSpec(name="p", kind="preisach", creep=True, solver="jaxafm.nnls")


@pytest.mark.parametrize("where", ["u", "d"])
def test_a_non_finite_sample_is_refused_with_its_place(where):
    """The plays run compiled, where they cannot look at their input: the normal equations check
    the record first and name the bad sample."""
    u = drive(300)
    model = initial_operator("preisach", u, 2 * u, levels=6)
    bad = {"u": u.copy(), "d": 2 * u}
    bad[where][17] = np.nan
    name = {"u": "input u", "d": "output d"}[where]
    with pytest.raises(ValueError, match=rf"{name} must be finite, but element \(17,\) is"):
        linear.normal_equations(model, bad["u"], bad["d"])
