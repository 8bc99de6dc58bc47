"""What a scanner lag of one pixel's time or less becomes in jaxafm's lag stage, at the line rates
of a speed series, through either of its holds (``jaxafm.model.effects.hold_weights``).

The zero hold is exact for an input held over each step; a raster scan's drive, sampled once a
pixel, is a ramp between the samples. Through the zero hold a lag ``tau`` delays a ramp by

    L(tau, h) = h / (exp(h / tau) - 1)        (h the sample time)

not by ``tau``: ``tau - h / 2`` for ``tau >> h``, almost nothing for ``tau << h``; through the
linear hold (step A's) by ``tau``. The independent generator (``tests/independent_lattice.py``,
SciPy's ``lfilter``) lags its drive exactly for a ramp. This script fits, per line rate and true
lag, the ``tau`` that makes jaxafm's lag stage reproduce the generator's lagged line drive (least
squares over 20 lines after the first) through each hold, compares the zero hold's with the closed
form ``L(tau, h) = tau_true``, and fits one ``tau`` to the three rates at once (what a speed
series asks of step A). No hysteresis: the lag stage alone.

A second part, with the generator's code alone: the generator lags the *drive* before its
Preisach hysteresis, jaxafm lags the hysteresis *output*. For drawn generator scanners (hysteresis
only), the one after-lag ``tau_eff`` that best turns ``P[u]`` into ``P[L_tau u]`` over the three
line rates (least squares on the fast-axis position over lines 2-6): what the order alone costs
a lag fitted after the hysteresis with the true Preisach.

A third part, on jaxafm's own simulated truth: the rate-dependent scanners of ``jaxafm study
configs/study_classes_speed.yaml`` lag their hysteresis output through the zero hold, stepped
once a pixel, and step A's model through the linear hold. Per scanner, the linear-hold lag that
best reproduces the truth's over the study's calibration lines (128 px, 10 % over-scan, 1 and
2 Hz at once), beside the true lag and the one step A fitted (the study's saved model).

    python experiments/rate_lag_discretisation.py

writes ``experiments/results/rate_lag_discretisation/metrics.json`` (the docs' tables
``rate_lag_discretisation``, ``rate_lag_order`` and ``rate_lag_truth``).
"""

from __future__ import annotations

import json
from pathlib import Path

import benchutil  # noqa: F401  (puts tests/ on sys.path)
import jax.numpy as jnp
import numpy as np
from independent_lattice import lag_ramp, make_scanner, preisach
from scipy.optimize import brentq, minimize_scalar

from jaxafm.model.effects import RateDependence
from jaxafm.model.io import load_model

OUT = Path(__file__).resolve().parent / "results" / "rate_lag_discretisation"
RATES_HZ = (0.5, 1.0, 2.0)  # the generator's speed series
PIXELS, OVERSCAN = 64, 0.05  # the study's images and the generator's over-scan
TRUE_LAGS_S = (0.7e-3, 1.0e-3, 2.0e-3)  # the generator's drive lags span 0.7-2 ms
HALF_WIDTH_NM = 2500.0


def line_drive(rate_hz: float, lines: int = 21, pixels: int = PIXELS, overscan: float = OVERSCAN) -> tuple:
    """A raster's fast-axis drive (nm) sampled once a pixel, trace and retrace, and its times (s)."""
    n = pixels + 2 * int(round(overscan * pixels))
    h = 1.0 / (2 * rate_hz * n)
    one = np.concatenate([np.linspace(-1, 1, n), np.linspace(1, -1, n)]) * HALF_WIDTH_NM
    u = np.tile(one, lines)
    return u, np.arange(u.size) * h, h, 2 * n


def jaxafm_lag(u: np.ndarray, t: np.ndarray, tau: float, hold: str) -> np.ndarray:
    lag = RateDependence(jnp.asarray(tau), hold=hold)
    return np.asarray(lag.run(jnp.asarray(u), jnp.asarray(t), lag.initial_state(u[0]), t[0])[0])


def fitted_tau(drives: list, true_tau: float, hold: str = "zero") -> float:
    """The one ``tau`` (s) whose jaxafm lag (through ``hold``) best reproduces the generator's lag
    of every drive."""

    def cost(log_tau):
        return sum(
            float(np.sum((jaxafm_lag(u, t, np.exp(log_tau), hold) - lag_ramp(u, true_tau, h))[skip:] ** 2))
            for u, t, h, skip in drives
        )

    return float(np.exp(minimize_scalar(cost, bounds=(np.log(1e-5), np.log(0.1)), method="bounded").x))


def closed_form(true_tau: float, h: float) -> float:
    """The ``tau`` with ``h / (exp(h / tau) - 1) = true_tau``."""
    return brentq(lambda tau: h / np.expm1(h / tau) - true_tau, 1e-7, 1.0)


ORDER_SEEDS = range(5)  # drawn generator scanners for the order part
ORDER_LAG_S = 1.0e-3


def order_row(seed: int, tau: float = ORDER_LAG_S, lines: int = 6) -> dict:
    """The after-lag ``tau_eff`` (s) that best reproduces the generator's drive lag ``tau`` of a
    Preisach axis (module docstring, second part), over a +-8 V triangle at the series' rates."""
    axis = make_scanner(
        np.random.default_rng(seed), 300.0, creep_per_decade=0, coupling=0, drift_nm_per_s=0
    ).axes[0]
    hysteresis = lambda v: axis.reversible_nm_per_v * v + axis.hysteretic_nm * preisach(v, axis.relays)
    n = PIXELS + 2 * int(round(OVERSCAN * PIXELS))
    runs = []
    for rate in RATES_HZ:
        per = 4 * n  # two model steps a pixel, as the generator's grid
        h = 1.0 / (2 * rate * n) / 2
        phase = (np.arange(lines * per + 1) % per) / per
        u = 8.0 * np.where(phase <= 0.5, 4 * phase - 1, 3 - 4 * phase)
        runs.append((hysteresis(u), hysteresis(lag_ramp(u, tau, h)), h, 2 * per))

    def cost(log_tau):
        return sum(float(np.sum((lag_ramp(p, np.exp(log_tau), h) - w)[skip:] ** 2)) for p, w, h, skip in runs)

    fitted = float(np.exp(minimize_scalar(cost, bounds=(np.log(1e-6), np.log(0.1)), method="bounded").x))
    return {"seed": seed, "loop_pct": axis.loop_pct, "true_lag_s": tau, "after_lag_s": fitted,
            "relative_error_pct": 100 * (fitted / tau - 1)}  # fmt: skip


STUDY = Path(__file__).resolve().parent / "results" / "study_classes_speed"
STUDY_LAG_SCANNERS = (2, 6, 10, 14)  # its rate-dependent scanners
STUDY_RATES_HZ, STUDY_PIXELS, STUDY_OVERSCAN = (1.0, 2.0), 128, 0.1  # its calibration scans


def truth_row(scanner: int) -> dict:
    """A rate-dependent scanner of ``jaxafm study configs/study_classes_speed.yaml``: its true lag
    (``scanners.json``; jaxafm's simulator steps it through the zero hold, once a pixel), the
    x lag its step A model fitted (``scanners/model_*.json``; through the linear hold), and the
    linear-hold lag that best reproduces the truth's lag of the study's calibration line drives
    at its two rates at once (the lag stage alone, no hysteresis)."""
    true_tau = json.loads((STUDY / "scanners.json").read_text())[str(scanner)]["rate_tau"]
    model = load_model(STUDY / "scanners" / f"model_{scanner:05d}.json")
    drives = [line_drive(r, 6, STUDY_PIXELS, STUDY_OVERSCAN) for r in STUDY_RATES_HZ]
    lagged = [jaxafm_lag(u, t, true_tau, "zero") for u, t, _, _ in drives]  # the truth's, once

    def cost(log_tau):
        return sum(
            float(np.sum((jaxafm_lag(u, t, np.exp(log_tau), "linear") - z)[skip:] ** 2))
            for (u, t, _, skip), z in zip(drives, lagged)
        )

    same = float(np.exp(minimize_scalar(cost, bounds=(np.log(1e-5), np.log(0.1)), method="bounded").x))
    return {"scanner": scanner, "true_lag_s": true_tau, "step_a_lag_s": float(model.x.rate_dependence.tau),
            "linear_hold_equivalent_s": same}  # fmt: skip


def main() -> None:
    rows = []
    for true_tau in TRUE_LAGS_S:
        drives = [line_drive(r) for r in RATES_HZ]
        for rate, group in [(r, [d]) for r, d in zip(RATES_HZ, drives)] + [("all", drives)]:
            row = {"true_lag_s": true_tau, "line_rate_hz": rate}
            if rate != "all":
                h = group[0][2]
                row.update(sample_time_s=h, closed_form_lag_s=closed_form(true_tau, h))
            for hold, key in (("zero", ""), ("linear", "_linear")):
                tau = fitted_tau(group, true_tau, hold)
                row.update(
                    {f"fitted_lag{key}_s": tau, f"relative_error{key}_pct": 100 * (tau / true_tau - 1)}
                )
            rows.append(row)
            print(
                f"true {true_tau * 1e3:.1f} ms, {rate} Hz: zero hold {row['fitted_lag_s'] * 1e3:.3f} ms "
                f"({row['relative_error_pct']:+.0f} %), linear hold {row['fitted_lag_linear_s'] * 1e3:.4f} ms "
                f"({row['relative_error_linear_pct']:+.2f} %)"
            )
    order = [order_row(seed) for seed in ORDER_SEEDS]
    for r in order:
        print(
            f"order, scanner {r['seed']} (loop {r['loop_pct']:.1f} %): drive lag {r['true_lag_s'] * 1e3:.2f} ms "
            f"before the Preisach = {r['after_lag_s'] * 1e3:.3f} ms after it ({r['relative_error_pct']:+.1f} %)"
        )
    truth = [truth_row(s) for s in STUDY_LAG_SCANNERS]
    for r in truth:
        print(
            f"study_classes_speed scanner {r['scanner']}: true lag {r['true_lag_s'] * 1e3:.2f} ms (zero hold), "
            f"the same through the linear hold {r['linear_hold_equivalent_s'] * 1e3:.2f} ms, "
            f"step A's {r['step_a_lag_s'] * 1e3:.2f} ms"
        )
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "metrics.json").write_text(
        json.dumps(
            {"pixels": PIXELS, "overscan": OVERSCAN, "rows": rows, "order": order, "truth": truth}, indent=1
        )
    )


if __name__ == "__main__":
    main()
