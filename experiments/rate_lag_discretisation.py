"""What a scanner lag of one pixel's time or less becomes in jaxafm's lag stage, at the line rates
of a speed series: one cause of the fitted rate lags' error on the independent generator.

jaxafm's first-order lags (``jaxafm.model.effects.lowpass``) are exact for an input held over
each step (a zero-order hold); a raster scan's drive, sampled once a pixel, is a ramp between
the samples. Through a zero-order hold a lag ``tau`` delays a ramp by

    L(tau, h) = h / (exp(h / tau) - 1)        (h the sample time)

not by ``tau``: ``tau - h / 2`` for ``tau >> h``, almost nothing for ``tau << h``. The
independent generator (``tests/independent_lattice.py``) lags its drive exactly for a ramp
(a first-order hold). This script fits, per line rate and true lag, the ``tau`` that makes
jaxafm's lag stage reproduce the generator's lagged line drive (least squares over 20 lines
after the first), compares it with the closed form ``L(tau, h) = tau_true``, and fits one
``tau`` to the three rates at once (what a speed series asks of step A). No hysteresis: the
lag stage alone.

    python experiments/rate_lag_discretisation.py

writes ``experiments/results/rate_lag_discretisation/metrics.json`` (the docs' table
``rate_lag_discretisation``).
"""

from __future__ import annotations

import json
from pathlib import Path

import benchutil  # noqa: F401  (puts tests/ on sys.path)
import jax.numpy as jnp
import numpy as np
from independent_lattice import lag_ramp
from scipy.optimize import brentq, minimize_scalar

from jaxafm.model.effects import lowpass

OUT = Path(__file__).resolve().parent / "results" / "rate_lag_discretisation"
RATES_HZ = (0.5, 1.0, 2.0)  # the generator's speed series
PIXELS, OVERSCAN = 64, 0.05  # the study's images and the generator's over-scan
TRUE_LAGS_S = (0.7e-3, 1.0e-3, 2.0e-3)  # the generator's drive lags span 0.7-2 ms
HALF_WIDTH_NM = 2500.0


def line_drive(rate_hz: float, lines: int = 21) -> tuple:
    """A raster's fast-axis drive (nm) sampled once a pixel, trace and retrace, and its times (s)."""
    n = PIXELS + 2 * int(round(OVERSCAN * PIXELS))
    h = 1.0 / (2 * rate_hz * n)
    one = np.concatenate([np.linspace(-1, 1, n), np.linspace(1, -1, n)]) * HALF_WIDTH_NM
    u = np.tile(one, lines)
    return u, np.arange(u.size) * h, h, 2 * n


def jaxafm_lag(u: np.ndarray, t: np.ndarray, tau: float) -> np.ndarray:
    return np.asarray(lowpass(jnp.asarray(u), jnp.asarray(t), jnp.asarray([tau]), jnp.asarray(u[0]))[0])


def fitted_tau(drives: list, true_tau: float) -> float:
    """The one ``tau`` (s) whose jaxafm lag best reproduces the generator's lag of every drive."""

    def cost(log_tau):
        return sum(
            float(np.sum((jaxafm_lag(u, t, np.exp(log_tau)) - lag_ramp(u, true_tau, h))[skip:] ** 2))
            for u, t, h, skip in drives
        )

    return float(np.exp(minimize_scalar(cost, bounds=(np.log(1e-5), np.log(0.1)), method="bounded").x))


def closed_form(true_tau: float, h: float) -> float:
    """The ``tau`` with ``h / (exp(h / tau) - 1) = true_tau``."""
    return brentq(lambda tau: h / np.expm1(h / tau) - true_tau, 1e-7, 1.0)


def main() -> None:
    rows = []
    for true_tau in TRUE_LAGS_S:
        drives = [line_drive(r) for r in RATES_HZ]
        for rate, drive in zip(RATES_HZ, drives):
            tau = fitted_tau([drive], true_tau)
            rows.append(
                {
                    "true_lag_s": true_tau,
                    "line_rate_hz": rate,
                    "sample_time_s": drive[2],
                    "fitted_lag_s": tau,
                    "closed_form_lag_s": closed_form(true_tau, drive[2]),
                    "relative_error_pct": 100 * (tau / true_tau - 1),
                }
            )
        tau = fitted_tau(drives, true_tau)
        rows.append(
            {
                "true_lag_s": true_tau,
                "line_rate_hz": "all",
                "fitted_lag_s": tau,
                "relative_error_pct": 100 * (tau / true_tau - 1),
            }
        )
    for r in rows:
        print(
            f"true {r['true_lag_s'] * 1e3:.1f} ms, {r['line_rate_hz']} Hz: fitted {r['fitted_lag_s'] * 1e3:.3f} ms "
            f"({r['relative_error_pct']:+.0f} %)"
            + (f", closed form {r['closed_form_lag_s'] * 1e3:.3f} ms" if "closed_form_lag_s" in r else "")
        )
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "metrics.json").write_text(
        json.dumps({"pixels": PIXELS, "overscan": OVERSCAN, "rows": rows}, indent=1)
    )


if __name__ == "__main__":
    main()
