"""The Laplace posterior of an actuator fit against NUTS samples of the same posterior.

NUTS (numpyro, Hoffman & Gelman 2014) samples the posterior of a fit's raw parameters
``theta`` under the AR(1) noise model, its ``rho`` and innovation variance ``s_w^2`` fixed at
the fit's residuals':

    log p(theta | d) = -1/2 sum_t (w_t(theta) / s_w)^2 - 1/2 |theta - theta_hat|^2 / sigma_p^2,
    w_t = r_t - rho r_{t-1},  r = y(theta) - d.

Compared with it, parameter by parameter (means and sds):

- **Laplace at the mode**: the Gaussian at this posterior's mode (Gauss-Newton on the whitened
  residuals from the fit) with the inverse Gauss-Newton Hessian as covariance: the
  approximation alone, which differs from NUTS only where ``y`` is not linear in ``theta`` over
  the posterior's width (the softplus that keeps PI weights non-negative, near zero most).
- **What jaxafm saves**: the least-squares fit and its AR(1) covariance
  (:func:`jaxafm.identify.uncertainty.posterior_of`, ``ar1``), the sampling distribution of the
  estimate the fit made. Its mean is the unweighted least-squares solution, not the AR(1)
  posterior's mode; the gap says how far the two estimates lie apart on this record.

Cases: a PI model (8 plays) on the first 60 % of the shipped real record ``piezo_sine_1hz.dat``,
and on axis x of a record of the independent generator (``tests/independent.py``, a smooth
Preisach truth, 2 nm noise).

    python experiments/posterior_check.py          # ~5 min on one core; needs numpyro

Writes ``experiments/results/posterior_check/`` (``metrics.json``, ``posterior_check.png``).
"""

from __future__ import annotations

import json
from pathlib import Path

import benchutil  # noqa: F401  (puts tests/ on sys.path)
import jax
import jax.numpy as jnp
import numpy as np
from independent import make_case
from jax.flatten_util import ravel_pytree
from numpyro.infer import MCMC, NUTS

from jaxafm import plots
from jaxafm.identify.fit import evaluator, fit_operator, initial_operator
from jaxafm.identify.uncertainty import PRIOR_SD, posterior_of
from jaxafm.instrument.records import read_record
from jaxafm.model.posterior import linearise

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "experiments" / "results" / "posterior_check"
TRAIN, PLAYS = 0.6, 8
WARMUP, SAMPLES, CHAINS = 1000, 2000, 2
GOAL = 0.2  # the bound on |Laplace - NUTS|, relative to the NUTS sd


def records() -> dict:
    """name -> (t, u, d, history) of the two cases' training parts."""
    mapping = {"input_columns": [1], "output_columns": [5], "sample_rate_hz": 200.0, "output_unit": "um"}
    r = read_record(ROOT / "jaxafm" / "data" / "real" / "piezo_sine_1hz.dat", **mapping)
    gen = make_case(None, "control", 10_000, "preisach")
    split_r, split_g = int(TRAIN * len(r.t)), int(TRAIN * len(gen["t"]))
    return {
        "piezo_sine_1hz.dat (real)": (r.t[:split_r], r.u[:split_r], r.d[:split_r], [0.0]),
        "independent generator (Preisach truth)": (
            gen["t"][:split_g],
            gen["u"][:split_g, 0],
            gen["d"][:split_g, 0],
            None,
        ),
    }


def compare(t, u, d, history, seed: int) -> dict:
    """The PI fit of one record, the Laplace approximations (at the AR(1) posterior's mode, and
    the saved fit's) and NUTS samples of the AR(1) posterior."""
    h = None if history is None else jnp.asarray(history)
    res = fit_operator(initial_operator("pi", u, d, operators=PLAYS), u, d, t=t, history=h)
    span, d_range = float(np.ptp(u)), float(np.ptp(d))
    y, J = linearise(res.model, span, d_range, u, t, h)
    r = y - d
    saved = posterior_of(J, r, span, d_range, "ar1")
    rho = float(np.corrcoef(r[:-1], r[1:])[0, 1])
    sw = float(np.sqrt(np.mean((r[1:] - rho * r[:-1]) ** 2)))
    raw, rebuild = res.model.free_parameters(span, d_range)
    theta_hat, unravel = ravel_pytree(raw)
    forward = evaluator(res.model, jnp.asarray(u), None, h)
    d_j = jnp.asarray(d)

    def whitened(theta):  # the potential's terms: the whitened residuals / s_w, then the prior's
        e = forward(rebuild(unravel(theta))) - d_j
        return jnp.concatenate([(e[1:] - rho * e[:-1]) / sw, (theta - theta_hat) / PRIOR_SD])

    potential = jax.jit(lambda theta: 0.5 * jnp.sum(whitened(theta) ** 2))
    mode, mode_cov = _mode(jax.jit(whitened), jax.jit(jax.jacfwd(whitened)), theta_hat)
    mcmc = MCMC(
        NUTS(potential_fn=potential),
        num_warmup=WARMUP,
        num_samples=SAMPLES,
        num_chains=CHAINS,
        chain_method="sequential",
        progress_bar=False,
    )
    jitter = np.random.default_rng(seed).normal(size=(CHAINS, theta_hat.size))
    mcmc.run(jax.random.key(seed), init_params=jnp.asarray(mode + 0.1 * np.sqrt(np.diag(mode_cov)) * jitter))
    draws = np.asarray(mcmc.get_samples())
    nuts_mean, nuts_sd = draws.mean(0), draws.std(0)
    out = {"parameters": int(theta_hat.size), "samples": int(len(draws)), "rho": rho}
    out |= {"nuts_mean": nuts_mean.tolist(), "nuts_sd": nuts_sd.tolist()}
    for name, mean, cov in (("mode", mode, mode_cov), ("saved", np.asarray(theta_hat), saved.covariance)):
        sd = np.sqrt(np.diag(cov))
        gap, ratio = np.abs(mean - nuts_mean) / nuts_sd, sd / nuts_sd
        out[name] = {
            "mean": mean.tolist(),
            "sd": sd.tolist(),
            "mean_gap_over_nuts_sd": gap.tolist(),
            "sd_ratio": ratio.tolist(),
            "max_mean_gap_over_nuts_sd": float(gap.max()),
            "max_sd_error": float(np.max(np.abs(ratio - 1))),
        }
    return out


def _mode(whitened, jacobian, theta: np.ndarray, steps: int = 50) -> tuple:
    """The AR(1) posterior's mode by Gauss-Newton from ``theta`` and the inverse Gauss-Newton
    Hessian there: ``(mode, covariance)``."""
    theta = jnp.asarray(theta)
    for _ in range(steps):
        J, w = jacobian(theta), whitened(theta)
        step = jnp.linalg.solve(J.T @ J, J.T @ w)
        theta = theta - step
        if float(jnp.max(jnp.abs(step))) < 1e-10:
            break
    J = np.asarray(jacobian(theta))
    return np.asarray(theta), np.linalg.inv(J.T @ J)


def figure(out: dict, path: Path) -> None:
    """Per case and raw parameter: the Laplace sd over the NUTS sd and |mean gap| / NUTS sd, for
    the Laplace approximation at the mode and for the saved fit, with the 20 % bounds."""
    fig, axes = plots.subplots(1, len(out), figsize=(6.5 * len(out), 5.6), squeeze=False)
    for ax, (name, c) in zip(axes[0], out.items()):
        k = np.arange(c["parameters"])
        for which, colour in (("mode", "C0"), ("saved", "C1")):
            ax.plot(k, c[which]["sd_ratio"], "o", color=colour, label=f"{which}: Laplace sd / NUTS sd")
            ax.plot(
                k,
                c[which]["mean_gap_over_nuts_sd"],
                "x",
                color=colour,
                label=f"{which}: |mean gap| / NUTS sd",
            )
        for v in (1 - GOAL, 1 + GOAL, GOAL):
            ax.axhline(v, color="0.6", lw=0.8, ls="--")
        ax.set(xlabel="raw parameter (the order of free_parameters, raveled)", yscale="log", title=name)
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main() -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    out = {}
    for seed, (name, rec) in enumerate(records().items()):
        c = compare(*rec, seed)
        out[name] = c
        print(f"{name}: {c['parameters']} parameters, {c['samples']} draws; rho {c['rho']:.3f}")
        for which in ("mode", "saved"):
            m = c[which]
            print(
                f"  {which:5s}: largest |mean gap| {m['max_mean_gap_over_nuts_sd']:.3f} NUTS sd, "
                f"largest |sd error| {100 * m['max_sd_error']:.1f} %",
                flush=True,
            )
    (OUT / "metrics.json").write_text(json.dumps(out, indent=1))
    figure(out, OUT / "posterior_check.png")
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
