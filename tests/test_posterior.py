"""Posteriors of fitted actuator models and their prediction bands (jaxafm.model.posterior,
jaxafm.identify.uncertainty.posterior_of), against closed forms and known coverage."""

from __future__ import annotations

import json
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
import yaml
from jax.flatten_util import ravel_pytree
from scipy.stats import norm
from typer.testing import CliRunner

from jaxafm.cli import app
from jaxafm.identify.fit import initial_operator
from jaxafm.identify.uncertainty import PRIOR_SD, posterior_of
from jaxafm.model.effects import Creep
from jaxafm.model.hysteresis import Linear
from jaxafm.model.io import read_model_and_posterior, read_model_file, save_model
from jaxafm.model.posterior import Posterior, band, check_level, linear_band, linearise
from jaxafm.model.scanner import Axis

SPAN_V, RANGE_NM = 10.0, 50.0  # the raw parameters' scale: any fixed pair, shared by the fits


def line_fit(u: np.ndarray, d: np.ndarray) -> Linear:
    """The ordinary least-squares straight line (numpy's, not jaxafm's)."""
    gain, offset = np.polyfit(u, d, 1)
    return Linear(jnp.asarray(gain), jnp.asarray(offset))


def test_the_iid_band_of_a_straight_line_is_the_textbook_prediction_interval():
    """For ordinary least squares the predictive variance at x0 = (u0, 1) is
    s^2 (1 + x0^T (X^T X)^-1 x0) (e.g. Seber & Lee 2003, sec. 5.3); the weak prior (precision
    s^2 / sigma_p^2 on each raw parameter) moves it by at most s^2 / (sigma_p^2 lambda_min)
    relative, lambda_min the smallest eigenvalue of J^T J."""
    rng = np.random.default_rng(0)
    u = np.linspace(0.0, 10.0, 400)
    d = 30.0 * u + 5.0 + rng.normal(0.0, 2.0, u.size)
    model = line_fit(u, d)
    y, J = linearise(model, SPAN_V, RANGE_NM, u)
    post = posterior_of(J, y - d, SPAN_V, RANGE_NM, "iid")
    u0 = np.array([-5.0, 0.0, 5.0, 20.0])  # inside and outside the fitted span
    y0, G0 = linearise(model, SPAN_V, RANGE_NM, u0)
    got = linear_band(y0, G0, post, 0.9)
    X, X0 = np.c_[u, np.ones_like(u)], np.c_[u0, np.ones_like(u0)]
    s2 = np.mean((X @ np.polyfit(u, d, 1)[:, None] - d[:, None]) ** 2)
    want = s2 * (1 + np.einsum("ti,ij,tj->t", X0, np.linalg.inv(X.T @ X), X0))
    prior_shift = s2 / (PRIOR_SD**2 * np.linalg.eigvalsh(J.T @ J)[0])
    assert prior_shift < 1e-3
    np.testing.assert_allclose(got.sd**2, want, rtol=prior_shift)
    lower, upper = got.bounds()
    np.testing.assert_allclose(upper - lower, 2 * norm.ppf(0.95) * np.sqrt(want), rtol=prior_shift)


@pytest.mark.parametrize(
    "kind, history",
    [("pi", None), ("gpi", None), ("preisach", None), ("preisach", [0.0, 7.5, 1.0]), ("gpi_creep", None)],
)
def test_the_linearisation_is_the_predictions_derivative(kind, history):
    """``linearise`` differentiates through the fit's evaluator (plays run once, outside the
    derivative), a Preisach plane's in closed form (with and without an input history before
    the drive); its prediction is ``model.predict`` and its Jacobian matches central differences
    of ``model.predict`` in each raw parameter (step 1e-5 of an order-one parameter: truncation
    about 1e-10 of the output's scale, round-off about 1e-11 of it)."""
    t = np.linspace(0.0, 8.0, 400)
    u = 4.0 + 3.0 * np.sin(2 * np.pi * 0.5 * t) * np.exp(-0.1 * t)
    d = 20.0 * u + 10.0 * np.tanh(u - 4.0)
    h = initial_operator(kind.removesuffix("_creep"), u, d, operators=6, levels=6, deadzones=2)
    start = Axis(h, creep=Creep.logarithmic(0.02, 0.5, 5.0)) if "creep" in kind else h
    raw, rebuild = start.free_parameters(SPAN_V, RANGE_NM)
    flat, unravel = ravel_pytree(raw)
    flat = flat + np.random.default_rng(8).normal(0.0, 0.3, flat.size)  # away from the start's zeros
    model = rebuild(unravel(flat))
    h = None if history is None else jnp.asarray(history)
    predict = lambda m: m.predict(jnp.asarray(u), jnp.asarray(t), h)
    y, G = linearise(model, SPAN_V, RANGE_NM, u, t, h)
    np.testing.assert_allclose(y, predict(model), rtol=1e-12, atol=1e-9)
    raw, rebuild = model.free_parameters(SPAN_V, RANGE_NM)
    flat, unravel = ravel_pytree(raw)
    step = 1e-5
    for k in range(flat.size):
        e = jnp.zeros_like(flat).at[k].set(step)
        up, down = (predict(rebuild(unravel(flat + s * e))) for s in (1, -1))
        np.testing.assert_allclose(G[:, k], (up - down) / (2 * step), rtol=1e-6, atol=1e-8 * np.ptp(y))


def test_a_parameter_the_data_do_not_see_keeps_the_prior_width_under_every_noise_model():
    """A Jacobian column of zeros (a parameter the residuals do not depend on): its raw sd is
    the prior's, PRIOR_SD, whatever the noise model; the other stays the closed form's."""
    rng = np.random.default_rng(1)
    x = rng.normal(size=300)
    J = np.c_[x, np.zeros_like(x)]
    r = rng.normal(0.0, 0.5, 300)
    for method in ("iid", "ar1", "blocks"):
        C = posterior_of(J, r, SPAN_V, RANGE_NM, method).covariance
        assert np.sqrt(C[1, 1]) == pytest.approx(PRIOR_SD, rel=1e-9), method
        assert np.sqrt(C[0, 0]) < 0.1 * PRIOR_SD, method  # 300 samples pin the first down
    iid = posterior_of(J, r, SPAN_V, RANGE_NM, "iid").covariance[0, 0]
    assert iid == pytest.approx(np.mean(r**2) / (x @ x), rel=1e-3)


def test_correlated_noise_needs_the_blocked_or_ar1_width_to_cover_the_offset():
    """Straight lines with AR(1) noise (rho 0.95): the sample mean's variance is about
    sigma^2 (1 + rho) / (n (1 - rho)), 39 times the i.i.d. one, so the i.i.d. Laplace interval
    of the offset covers the truth far less often than 90 %, the AR(1) sandwich about 90 % of
    the time (300 records: the binomial sd of a 90 % coverage is 1.7 %). The blocked one lies
    between: ten blocks of 80 samples hold the offset's variance with a downward bias when the
    noise stays correlated over about 40 samples (Cameron & Miller 2015, sec. VI)."""
    rng = np.random.default_rng(2)
    n, rho, records = 800, 0.95, 300
    u = np.linspace(0.0, 10.0, n)
    truth = Linear(jnp.asarray(30.0), jnp.asarray(5.0))
    z = norm.ppf(0.95)
    inside = {m: 0 for m in ("iid", "ar1", "blocks")}
    for _ in range(records):
        e = np.empty(n)
        e[0] = rng.normal(0, 2.0 / np.sqrt(1 - rho**2))
        for i in range(1, n):
            e[i] = rho * e[i - 1] + rng.normal(0, 2.0)
        d = 30.0 * u + 5.0 + e
        model = line_fit(u, d)
        y, J = linearise(model, SPAN_V, RANGE_NM, u)
        offset = float(model.offset)
        for m in inside:
            sd = np.sqrt(posterior_of(J, y - d, SPAN_V, RANGE_NM, m).covariance[1, 1]) * RANGE_NM
            inside[m] += abs(offset - float(truth.offset)) <= z * sd
    share = {m: v / records for m, v in inside.items()}
    assert share["iid"] < 0.5, share
    assert 0.85 <= share["ar1"] <= 0.95, share
    assert share["iid"] + 0.3 < share["blocks"] < share["ar1"], share


def test_the_ar1_covariance_is_the_sandwich_with_the_dense_ar1_matrix():
    """The filtered form of J^T Sigma J (a backward recursion) equals the dense product with
    Sigma = s_w^2 L^-1 L^-T, L the whitening matrix (1 on the diagonal, -rho below it)."""
    rng = np.random.default_rng(4)
    n = 200
    J = np.c_[np.linspace(0, 1, n), np.ones(n), np.sin(np.arange(n) / 7.0)]
    r = np.empty(n)
    r[0] = rng.normal()
    for i in range(1, n):
        r[i] = 0.8 * r[i - 1] + rng.normal()
    post = posterior_of(J, r, SPAN_V, RANGE_NM, "ar1")
    rho = np.corrcoef(r[:-1], r[1:])[0, 1]
    sw2 = np.mean((r[1:] - rho * r[:-1]) ** 2)
    L = np.eye(n) - rho * np.eye(n, k=-1)
    Linv = np.linalg.inv(L)
    sigma = sw2 * Linv @ Linv.T
    P = np.mean(r**2) * np.eye(3) / PRIOR_SD**2
    Hinv = np.linalg.inv(J.T @ J + P)
    want = Hinv @ (J.T @ sigma @ J + np.mean(r**2) * P) @ Hinv
    np.testing.assert_allclose(post.covariance, want, rtol=1e-9)


def test_a_level_outside_zero_one_is_refused_by_name():
    for bad in (0, 1, 1.5, -0.1, True, "0.9"):
        with pytest.raises(ValueError, match=r"level: .* is not a probability in \(0, 1\)"):
            check_level(bad)


def test_a_model_without_uncertainty_asked_for_a_band_says_what_to_do():
    with pytest.raises(ValueError, match="has no uncertainty.*refit it with `jaxafm fit`"):
        band(Linear(jnp.asarray(1.0), jnp.asarray(0.0)), None, np.linspace(0, 1, 5))


def saved_line(path: Path, covariance) -> Path:
    """A straight-line model file with the given raw covariance."""
    post = Posterior(np.asarray(covariance, dtype=float), 2.0, SPAN_V, RANGE_NM, "iid", 1)
    save_model(Linear(jnp.asarray(30.0), jnp.asarray(5.0)), path, posterior=post)
    return path


def test_a_posterior_round_trips_through_the_model_file(tmp_path):
    C = np.array([[2e-6, 1e-7], [1e-7, 5e-6]])
    path = saved_line(tmp_path / "m.json", C)
    _, _, post = read_model_and_posterior(path)
    np.testing.assert_array_equal(post.covariance, C)
    assert (post.residual_sd_nm, post.method, post.input_span_v) == (2.0, "iid", SPAN_V)


@pytest.mark.parametrize(
    "covariance, message",
    [
        ([[1e-6, 0.0], [0.0, -1e-6]], "not positive definite"),
        ([[1e-6, 1e-7], [0.0, 1e-6]], "not symmetric"),
        ([[1e-6]], r"shape \(1, 1\), but the model has 2 raw parameters"),
    ],
)
def test_a_hand_edited_covariance_is_refused_on_load(tmp_path, covariance, message):
    path = saved_line(tmp_path / "m.json", np.eye(2) * 1e-6)
    doc = json.loads(path.read_text())
    doc["uncertainty"]["covariance"] = covariance
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=f"{path.name}.*uncertainty.covariance: {message}"):
        read_model_file(path)


def test_a_version_2_file_loads_as_a_model_without_uncertainty(tmp_path):
    path = saved_line(tmp_path / "m.json", np.eye(2) * 1e-6)
    doc = json.loads(path.read_text())
    doc["version"] = 2
    del doc["uncertainty"]
    path.write_text(json.dumps(doc))
    model, _, post = read_model_and_posterior(path)
    assert post is None and float(model.gain) == 30.0


def test_a_version_4_file_with_creep_loads_without_its_uncertainty_and_a_version_5_one_with(tmp_path):
    """A version-4 uncertainty is over creep weights of either sign, which the raw parameters of
    this version do not describe (they are >= 0); without creep it still holds."""
    line = Linear(jnp.asarray(30.0), jnp.asarray(5.0))
    axis = Axis(line, creep=Creep.logarithmic(0.01, 0.1, 10.0))
    for version, model, kept in ((5, axis, True), (4, axis, False), (4, line, True)):
        k = 2 + (model.creep.weights.size if model is axis else 0)
        path = tmp_path / f"m{version}_{k}.json"
        save_model(model, path, posterior=Posterior(np.eye(k) * 1e-6, 2.0, SPAN_V, RANGE_NM, "iid", 1))
        doc = json.loads(path.read_text())
        doc["version"] = version
        path.write_text(json.dumps(doc))
        assert (read_model_and_posterior(path)[2] is not None) == kept, (version, k)


runner = CliRunner()


def invoke(*args):
    return runner.invoke(app, [str(a) for a in args])


def write(path: Path, doc: dict) -> Path:
    path.write_text(yaml.safe_dump(doc))
    return path


def test_fit_then_predict_gives_a_band_that_covers_white_noise_as_stated(tmp_path):
    """A straight-line actuator with white Gaussian noise (numpy): the model class is right, so
    `jaxafm fit`'s 90 % band holds about 90 % of the held-out samples (1200 of them: binomial
    sd 0.9 %), `jaxafm predict` writes the same band as columns and scores it, `jaxafm
    compensate` expects the actuator within the noise's 90 % half-width of the wanted path; asked
    for a band of a model without one, `predict` refuses by the key."""
    rng = np.random.default_rng(3)
    t = np.arange(3000) * 1e-3
    u = 5.0 + 4.0 * np.sin(2 * np.pi * 2.0 * t)
    d = 40.0 * u + 3.0 + rng.normal(0.0, 5.0, t.size)
    np.savetxt(tmp_path / "r.csv", np.c_[t, u, d], delimiter=",", header="t_s,u_v,d_nm", comments="")
    record = {"path": "r.csv", "delimiter": ",", "time_column": "t_s"}
    record |= {"input_columns": ["u_v"], "output_columns": ["d_nm"], "output_unit": "nm"}
    fit = {"data": record, "train_fraction": 0.6, "models": [{"name": "line", "kind": "linear"}]}
    result = invoke("fit", write(tmp_path / "fit.yaml", fit), "--out", tmp_path / "fit")
    assert result.exit_code == 0, result.output
    fitted = json.loads((tmp_path / "fit" / "metrics.json").read_text())
    assert 87.0 <= fitted["line_heldout_coverage_90_pct"] <= 93.0, fitted
    assert 46.0 <= fitted["line_heldout_coverage_50_pct"] <= 54.0, fitted
    assert fitted["line_heldout_band_90_width_nm"] == pytest.approx(2 * norm.ppf(0.95) * 5.0, rel=0.05)
    cfg = {"model": "fit/model_line.json", "data": record, "evaluate_from": 0.6, "level": 0.5}
    result = invoke("predict", write(tmp_path / "p.yaml", cfg), "--out", tmp_path / "pred")
    assert result.exit_code == 0, result.output
    predicted = json.loads((tmp_path / "pred" / "metrics.json").read_text())
    assert predicted["coverage_pct"] == pytest.approx(fitted["line_heldout_coverage_50_pct"], abs=1e-9)
    rows = np.genfromtxt(tmp_path / "pred" / "prediction.csv", delimiter=",", names=True)
    inside = (rows["measured_nm"] >= rows["lower_nm"]) & (rows["measured_nm"] <= rows["upper_nm"])
    assert 100 * inside[1800:].mean() == pytest.approx(predicted["coverage_pct"])
    assert (tmp_path / "pred" / "predict_band.png").is_file()
    triangle = {"amplitudes_nm": [100.0, 50.0], "period_s": 1.0, "sample_rate_hz": 1000.0}
    comp = {"model": "fit/model_line.json", "trajectory": {"triangle": triangle}, "cycle_s": 0.5}
    result = invoke("compensate", write(tmp_path / "c.yaml", comp), "--out", tmp_path / "comp")
    assert result.exit_code == 0, result.output
    expected = json.loads((tmp_path / "comp" / "metrics.json").read_text())["expected_error_90_nm"]
    assert expected == pytest.approx(norm.ppf(0.95) * 5.0, rel=0.05)  # the noise's 90 % half-width
    doc = json.loads((tmp_path / "fit" / "model_line.json").read_text())
    doc["uncertainty"] = None
    (tmp_path / "bare.json").write_text(json.dumps(doc))
    cfg |= {"model": "bare.json"}
    result = invoke("predict", write(tmp_path / "p2.yaml", cfg), "--out", tmp_path / "pred2")
    assert result.exit_code != 0
    assert "level: 0.5 asks for a band, but the model file" in result.output
    assert "holds no uncertainty" in result.output
