"""How often held-out measurements fall inside the prediction bands of fitted actuator models,
for the three noise models of :func:`jaxafm.identify.uncertainty.posterior_of`.

Each model kind is fitted (:func:`jaxafm.identify.fit.fit_operator`, as ``jaxafm fit`` does) on
the first 60 % of a record; its posterior is made with each noise model from the training
residuals alone, and its 90 % and 50 % bands (:mod:`jaxafm.model.posterior`) are scored on the
held-out 40 %: the share of measured samples inside (the coverage; a calibrated band holds
90 % and 50 %) and the mean width over the held-out rms error (a calibrated Gaussian 90 % band
is 3.3 times the rms wide). Records:

- the three shipped real records (``jaxafm/data/real/README.md``), and the two 1 Hz records of
  one piezo stack predicted across (fitted on one, scored on the other after its first
  ``SKIP_S`` s, one sensor offset re-estimated on the next ``OFFSET_S`` s and not scored);
- ``--generator N`` records of the independent generator (``tests/independent.py``: NumPy/SciPy
  physics that shares no code with jaxafm; axis x of its cases in their listed order), where
  the truth is a Preisach or PI operator with one effect, noise 2 nm.

    python experiments/uncertainty_coverage.py                   # real records + 50 generator records
    python experiments/uncertainty_coverage.py --generator 0     # the real records alone (~1 min)

Writes ``experiments/results/uncertainty_coverage/`` (``metrics.json``, ``coverage.png``).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import benchutil  # noqa: F401  (puts tests/ on sys.path)
import jax.numpy as jnp
import numpy as np
from independent import cases, make_case

from jaxafm import plots
from jaxafm.identify.fit import fit_operator, initial_operator
from jaxafm.identify.uncertainty import posterior_of
from jaxafm.instrument.records import read_record
from jaxafm.jobs.fit import MODEL_CREEP
from jaxafm.model.effects import Creep
from jaxafm.model.posterior import METHODS, linear_band, linearise
from jaxafm.model.scanner import Axis

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "experiments" / "results" / "uncertainty_coverage"
TRAIN = 0.6
SKIP_S, OFFSET_S = 1.0, 4.0  # cross-record: start-up not scored; the offset's samples not scored
LEVELS = (0.9, 0.5)
PIEZO = {"input_columns": [1], "output_columns": [5], "sample_rate_hz": 200.0, "output_unit": "um"}
STEP = {"delimiter": ",", "time_column": 2, "input_columns": [4], "output_columns": [3], "output_unit": "um"}
REAL = {  # name -> (file, mapping, history (V), settling samples)
    "sine": ("piezo_sine_1hz.dat", PIEZO, [0.0], 20),
    "ramped": ("piezo_ramped_sine_1hz.dat", PIEZO, None, 10),
    "step": ("piezo_step_sine_5khz.csv", STEP, None, 0),
}
CROSS = (("sine", "ramped"), ("ramped", "sine"))
MODELS = ("pi", "gpi", "gpi_creep")


def start_model(kind: str, u, d):
    """The start of a fit of ``kind`` (``gpi_creep``: a generalised PI with logarithmic creep),
    as ``jaxafm fit`` builds it."""
    h = initial_operator(kind.removesuffix("_creep"), u, d, operators=20, deadzones=3)
    return Axis(h, creep=Creep.logarithmic(**MODEL_CREEP)) if "creep" in kind else h


def fitted(kind: str, t, u, d, history, settle: int) -> tuple:
    """``(model, posteriors, seconds)``: ``kind`` fitted to the record's first :data:`TRAIN`,
    one posterior per noise model, and the wall times (s) of the fit and of what ``jaxafm fit``
    adds to it (the linearisation and the default, AR(1), posterior)."""
    split = int(round(TRAIN * len(t)))
    h = None if history is None else jnp.asarray(history)
    start = start_model(kind, u[:split], d[:split])
    res = fit_operator(start, u[:split], d[:split], t=t[:split], history=h, settle=settle)
    span, d_range = float(np.ptp(u[:split])), float(np.ptp(d[settle:split]))
    clock = time.perf_counter()
    y, G = linearise(res.model, span, d_range, u[:split], t[:split], h)
    r = y[settle:] - d[settle:split]
    posteriors = {"ar1": posterior_of(G[settle:], r, span, d_range, "ar1")}
    seconds = (res.seconds, time.perf_counter() - clock)
    posteriors |= {m: posterior_of(G[settle:], r, span, d_range, m) for m in METHODS if m != "ar1"}
    return res.model, posteriors, seconds


def scores(model, posteriors: dict, t, u, d, history, first: int, offset_until: int = 0) -> dict:
    """Per noise model: coverage (%) of the 90 % and 50 % bands and the 90 % band's mean width
    over the rms error, on samples ``first`` on; the prediction shifted by the mean error on
    samples ``offset_until`` to ``first`` where ``offset_until`` > 0 (another record's sensor
    zero)."""
    post = next(iter(posteriors.values()))
    h = None if history is None else jnp.asarray(history)
    y, G = linearise(model, post.input_span_v, post.output_range_nm, u, t, h)
    if offset_until:
        y = y + np.mean(d[offset_until:first] - y[offset_until:first])
    e = d[first:] - y[first:]
    rms = float(np.sqrt(np.mean(e**2)))
    out = {"rms_error_nm": rms}
    for method, p in posteriors.items():
        band = linear_band(y, G, p)
        for level in LEVELS:
            out[f"{method}_coverage_{round(100 * level)}_pct"] = 100 * band.coverage(d, level, first)
        out[f"{method}_width_90_over_rms"] = band.width(0.9, first) / rms
        out[f"{method}_residual_sd_nm"] = p.residual_sd_nm
    return out


def real_records() -> dict:
    """Every real record's held-out scores and the cross-record ones, per model kind."""
    records = {
        name: read_record(ROOT / "jaxafm" / "data" / "real" / file, **mapping)
        for name, (file, mapping, *_) in REAL.items()
    }
    out, models = {}, {}
    for name, (_, _, history, settle) in REAL.items():
        r = records[name]
        for kind in MODELS:
            model, posts, (fit_s, post_s) = fitted(kind, r.t, r.u, r.d, history, settle)
            models[(name, kind)] = (model, posts)
            split = int(round(TRAIN * len(r.t)))
            s = scores(model, posts, r.t, r.u, r.d, history, split)
            out[f"{name}/{kind}"] = s | {"fit_s": fit_s, "posterior_s": post_s}
            _print(f"{name}/{kind}", s)
    for source, target in CROSS:
        r = records[target]
        first, offset = (int(np.searchsorted(r.t, r.t[0] + s)) for s in (SKIP_S + OFFSET_S, SKIP_S))
        for kind in MODELS:
            model, posts = models[(source, kind)]
            s = scores(model, posts, r.t, r.u, r.d, REAL[target][2], first, offset)
            out[f"{source}->{target}/{kind}"] = s
            _print(f"{source}->{target}/{kind}", s)
    return out


def generator_records(n: int) -> dict:
    """The held-out scores of ``n`` independent-generator records (axis x), per model kind."""
    out = {}
    for case in cases()[:n]:
        effect, level, seed = case["effect"], case["level"], case["seed"]
        rec = make_case(effect, level, seed, case["truth_hysteresis"])
        t, u, d = rec["t"], rec["u"][:, 0], rec["d"][:, 0]
        for kind in ("pi", "gpi_creep"):
            model, posts, _ = fitted(kind, t, u, d, None, 0)
            s = scores(model, posts, t, u, d, None, int(round(TRAIN * len(t))))
            name = f"{effect or 'control'} {level} {seed} ({case['truth_hysteresis']})"
            out[f"generator {name}/{kind}"] = s
            _print(f"gen {name}/{kind}", s)
    return out


def _print(name: str, s: dict) -> None:
    cells = "  ".join(
        f"{m} {s[f'{m}_coverage_90_pct']:5.1f}/{s[f'{m}_coverage_50_pct']:5.1f}% x{s[f'{m}_width_90_over_rms']:.2f}"
        for m in METHODS
    )
    print(f"{name:34s} rms {s['rms_error_nm']:8.1f} nm  {cells}", flush=True)


def summary(gen: dict) -> dict:
    """Per noise model and model kind over the generator records: median coverage, the share
    of records whose 90 % coverage lies in 85-95 %, the median width over rms."""
    out = {}
    for kind in ("pi", "gpi_creep"):
        rows = [s for k, s in gen.items() if k.endswith(f"/{kind}")]
        for m in METHODS:
            c90 = np.array([s[f"{m}_coverage_90_pct"] for s in rows])
            out[f"generator/{kind}/{m}"] = {
                "records": len(rows),
                "median_coverage_90_pct": float(np.median(c90)),
                "median_coverage_50_pct": float(np.median([s[f"{m}_coverage_50_pct"] for s in rows])),
                "share_90_within_85_95_pct": 100 * float(np.mean((c90 >= 85) & (c90 <= 95))),
                "median_width_90_over_rms": float(np.median([s[f"{m}_width_90_over_rms"] for s in rows])),
            }
    return out


def figure(real: dict, gen: dict, path: Path) -> None:
    """90 % coverage per record and model for the three noise models, with the 85-95 % goal
    shaded; the generator's records as a histogram per noise model (colour) and model kind
    (line style)."""
    fig, (ax, axg) = plots.subplots(1, 2, figsize=(15, 6.5), gridspec_kw={"width_ratios": [2.2, 1]})
    names = list(real)
    x = np.arange(len(names))
    for i, m in enumerate(METHODS):
        ax.bar(x + (i - 1) * 0.27, [real[n][f"{m}_coverage_90_pct"] for n in names], 0.27, label=m)
    ax.axhspan(85, 95, color="0.85", zorder=0, label="goal 85-95 %")
    ax.set_xticks(x, names, rotation=60, ha="right", fontsize=8)
    ax.set(ylabel="held-out samples inside the 90 % band [%]", ylim=(0, 100))
    ax.set_title("real records (fitted/model, or fitted->scored/model)", pad=28)
    ax.legend(fontsize=8, loc="lower center", bbox_to_anchor=(0.5, 1.0), ncol=4, frameon=False)
    bins = np.linspace(0, 100, 41)
    for kind, style in (("pi", "-"), ("gpi_creep", ":")):
        rows = [s for k, s in gen.items() if k.endswith(f"/{kind}")]
        for colour, m in enumerate(METHODS):
            values = [s[f"{m}_coverage_90_pct"] for s in rows]
            axg.hist(
                values, bins=bins, histtype="step", lw=1.5, ls=style, color=f"C{colour}", label=f"{kind}, {m}"
            )
    axg.axvspan(85, 95, color="0.85", zorder=0)
    axg.set(xlabel="held-out samples inside the 90 % band [%]", ylabel="records")
    axg.set_title(f"independent generator ({len(gen) // 2} records, axis x)", pad=28)
    axg.legend(fontsize=7, loc="upper center")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--generator", type=int, default=50, help="independent-generator records (default 50)")
    ap.add_argument("--figure", action="store_true", help="only redraw the figure from metrics.json")
    args = ap.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    if args.figure:
        metrics = json.loads((OUT / "metrics.json").read_text())
        return figure(metrics["real"], metrics["generator"], OUT / "coverage.png")
    real = real_records()
    gen = generator_records(args.generator)
    metrics = {"real": real, "generator": gen, "generator_summary": summary(gen) if gen else {}}
    (OUT / "metrics.json").write_text(json.dumps(metrics, indent=1))
    for k, v in metrics["generator_summary"].items():
        print(k, {a: round(b, 1) for a, b in v.items()})
    figure(real, gen, OUT / "coverage.png")
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
