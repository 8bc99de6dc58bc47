"""Where a fitted model misses: residual decomposition, whiteness and cross-correlation tests,
the figures and the Markdown report of ``jaxafm diagnose``.

Residuals are ``r = measured - model`` in nm. Tests, for ``N`` residual samples:

- whiteness: the autocorrelation ``rho_k = sum_t r_t r_{t+k} / sum_t r_t^2`` at lags
  ``k = 1..K`` against the 95 % band ``+-1.96 / sqrt(N)`` of white noise, and the
  Ljung-Box statistic ``Q = N (N + 2) sum_k rho_k^2 / (N - k)``, chi-squared with ``K``
  degrees of freedom when ``r`` is white;
- input cross-correlation: ``rho_ru(k)`` between ``r`` and the input ``u`` (and its rate
  ``du/dt``) at lags ``-K..K``, against the same band: a model that has caught
  everything the input explains leaves none.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from scipy import stats

MAX_LAG = 50  # samples
BINS = 8


def _rms(x) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if np.size(x) else float("nan")


def autocorrelation(r: np.ndarray, max_lag: int = MAX_LAG) -> np.ndarray:
    """``rho_k``, k = 1..max_lag, of the mean-removed ``r`` (T,)."""
    r = r - r.mean()
    den = float(r @ r)
    return np.array([float(r[:-k] @ r[k:]) / den for k in range(1, max_lag + 1)])


def cross_correlation(r: np.ndarray, u: np.ndarray, max_lag: int = MAX_LAG) -> np.ndarray:
    """``rho_ru(k)`` for k = -max_lag..max_lag: ``r`` at t + k against ``u`` at t."""
    r, u = r - r.mean(), u - u.mean()
    den = np.sqrt(float(r @ r) * float(u @ u))
    out = []
    for k in range(-max_lag, max_lag + 1):
        a, b = (r[k:], u[: len(u) - k]) if k >= 0 else (r[:k], u[-k:])
        out.append(float(a @ b) / den)
    return np.array(out)


def tests(r: np.ndarray, u: np.ndarray, t: np.ndarray) -> dict:
    """Whiteness and input cross-correlation of residuals ``r`` (T, k), inputs ``u`` (T, k)."""
    out = {}
    n = r.shape[0]
    band = 1.96 / np.sqrt(n)
    acf = [autocorrelation(r[:, i]) for i in range(r.shape[1])]
    q = [n * (n + 2) * np.sum(a**2 / (n - np.arange(1, a.size + 1))) for a in acf]
    rate = np.gradient(u, t, axis=0)
    ccf_u = [cross_correlation(r[:, i], u[:, i]) for i in range(r.shape[1])]
    ccf_rate = [cross_correlation(r[:, i], rate[:, i]) for i in range(r.shape[1])]
    out["acf"], out["ccf_u"], out["ccf_rate"], out["band"] = acf, ccf_u, ccf_rate, band
    out["metrics"] = {
        "residual_acf_lag1": float(np.mean([a[0] for a in acf])),
        "residual_acf_outside_band_pct": float(100 * np.mean([np.abs(a) > band for a in acf])),
        "ljung_box_q": float(np.sum(q)),
        "ljung_box_p": float(stats.chi2.sf(np.sum(q), MAX_LAG * r.shape[1])),
        "input_ccf_max_abs": float(np.max(np.abs(ccf_u))),
        "input_rate_ccf_max_abs": float(np.max(np.abs(ccf_rate))),
        "correlation_band_95": float(band),
    }
    return out


def _binned(x: np.ndarray, r: np.ndarray, edges: np.ndarray) -> list:
    idx = np.clip(np.digitize(x, edges[1:-1]), 0, len(edges) - 2)
    return [_rms(r[idx == b]) for b in range(len(edges) - 1)]


def decompose(r: np.ndarray, u: np.ndarray, t: np.ndarray) -> dict:
    """rms residual (nm) by time (and its mean), by input level on each branch, and by input rate.

    Each entry: ``edges`` and ``rms_nm`` per bin (all axes together); branches split at
    the sign of ``du/dt`` (ascending: > 0).
    """
    rate = np.gradient(u, t, axis=0)
    tt = np.repeat(t[:, None], u.shape[1], 1)
    flat = lambda a: np.ravel(a)
    r_, u_, v_, t_ = flat(r), flat(u), flat(rate), flat(tt)
    out = {
        "time_s": np.linspace(t[0], t[-1], 11),
        "input_v": np.linspace(u_.min(), u_.max(), BINS + 1),
        "input_rate_v_per_s": np.linspace(0, np.abs(v_).max(), BINS + 1),
    }
    idx = np.clip(np.digitize(t_, out["time_s"][1:-1]), 0, 9)
    table = {
        "time_s": _binned(t_, r_, out["time_s"]),
        "time_s_mean": [float(np.mean(r_[idx == b])) for b in range(10)],
        "input_rate_v_per_s": _binned(np.abs(v_), r_, out["input_rate_v_per_s"]),
    }
    for name, sel in (("ascending", v_ > 0), ("descending", v_ <= 0)):
        table[f"input_v_{name}"] = _binned(u_[sel], r_[sel], out["input_v"])
    return {"edges": {k: v.tolist() for k, v in out.items()}, "rms_nm": table, "overall_rms_nm": _rms(r_)}


def where(dec: dict, split_s: float) -> list:
    """Sentences that say where the residual is concentrated, with the numbers."""
    e, tab, overall = dec["edges"], dec["rms_nm"], dec["overall_rms_nm"]
    lines = []
    time = np.array(tab["time_s"])
    lines.append(
        f"Over time the rms residual goes from {time[0]:.3g} nm (first tenth) to {time[-1]:.3g} nm "
        f"(last tenth), {time[-1] / time[0]:.2f}x, and its mean from {tab['time_s_mean'][0]:+.3g} nm to "
        f"{tab['time_s_mean'][-1]:+.3g} nm; the held-out part starts at {split_s:.3g} s."
    )
    best = None
    for branch in ("ascending", "descending"):
        vals = np.array(tab[f"input_v_{branch}"], dtype=float)
        if np.all(np.isnan(vals)):
            continue
        b = int(np.nanargmax(vals))
        if best is None or vals[b] > best[0]:
            best = (vals[b], branch, e["input_v"][b], e["input_v"][b + 1])
    lines.append(
        f"By input level, it is largest on the {best[1]} branch between {best[2]:.3g} and {best[3]:.3g} V: "
        f"{best[0]:.3g} nm rms against {overall:.3g} nm overall ({best[0] / overall:.2f}x)."
    )
    rate = np.array(tab["input_rate_v_per_s"], dtype=float)
    lo, hi = rate[0], rate[~np.isnan(rate)][-1]
    lines.append(
        f"By input rate, it is {lo:.3g} nm rms at the slowest and {hi:.3g} nm rms at the fastest "
        f"({hi / lo:.2f}x)."
    )
    return lines


def concentration(dec: dict) -> dict:
    """Flat metrics: the largest bin of each decomposition over the overall rms."""
    overall = dec["overall_rms_nm"]
    tab = dec["rms_nm"]
    by_level = np.nanmax(np.r_[tab["input_v_ascending"], tab["input_v_descending"]])
    return {
        "residual_rms_nm": overall,
        "residual_time_last_over_first": tab["time_s"][-1] / tab["time_s"][0],
        "residual_mean_change_nm": tab["time_s_mean"][-1] - tab["time_s_mean"][0],
        "residual_level_max_over_overall": float(by_level / overall),
        "residual_rate_fast_over_slow": float(
            np.nanmax(tab["input_rate_v_per_s"][-2:]) / tab["input_rate_v_per_s"][0]
        ),
    }


def figure(t, r_nominal, r_best, best: str, split: int, test: dict, dec: dict, rows: list, path) -> None:
    """Six panels: residual against time, input by branch, input rate; autocorrelation and
    input cross-correlation with their 95 % bands; held-out gap before and after each candidate."""
    fig, ax = plt.subplots(2, 3, figsize=(15, 8.5))
    a = ax[0, 0]
    for i in range(r_nominal.shape[1]):
        a.plot(t, r_nominal[:, i], lw=0.6, label=f"nominal, output {i + 1}")
    if r_best is not None:
        a.plot(t, r_best[:, 0], lw=0.6, color="k", alpha=0.7, label=f"with {best}, output 1")
    a.axvline(t[split], color="k", ls="--", lw=1)
    a.text(t[split], 0.97, "  train | held out", transform=a.get_xaxis_transform(), va="top")
    a.set(xlabel="time [s]", ylabel="residual measured - model [nm]", title="residual against time")
    a.legend(fontsize=7)
    a = ax[0, 1]
    e = np.array(dec["edges"]["input_v"])
    mid = 0.5 * (e[1:] + e[:-1])
    for branch, m in (("ascending", "^-"), ("descending", "v-")):
        a.plot(mid, dec["rms_nm"][f"input_v_{branch}"], m, label=branch)
    a.set(xlabel="input u [V]", ylabel="rms residual [nm]", title="by input level and branch")
    a.legend(fontsize=8)
    a = ax[0, 2]
    e = np.array(dec["edges"]["input_rate_v_per_s"])
    a.plot(0.5 * (e[1:] + e[:-1]), dec["rms_nm"]["input_rate_v_per_s"], "o-")
    a.set(xlabel="|du/dt| [V/s]", ylabel="rms residual [nm]", title="by input rate")
    a = ax[1, 0]
    for i, acf in enumerate(test["acf"]):
        a.plot(np.arange(1, acf.size + 1), acf, lw=1, label=f"output {i + 1}")
    a.axhspan(-test["band"], test["band"], color="0.85", label="95 % band (white)")
    a.set(xlabel="lag [samples]", ylabel="autocorrelation", title="whiteness of the nominal residual")
    a.legend(fontsize=8)
    a = ax[1, 1]
    lags = np.arange(-(test["ccf_u"][0].size // 2), test["ccf_u"][0].size // 2 + 1)
    for i, (cu, cr) in enumerate(zip(test["ccf_u"], test["ccf_rate"])):
        a.plot(lags, cu, lw=1, label=f"with u, output {i + 1}")
        a.plot(lags, cr, lw=1, ls=":", label=f"with du/dt, output {i + 1}")
    a.axhspan(-test["band"], test["band"], color="0.85", label="95 % band")
    a.set(xlabel="lag [samples]", ylabel="cross-correlation", title="residual against the input")
    a.legend(fontsize=7)
    candidate_bars(
        ax[1, 2], rows, rows[0]["heldout_gap_before_nm"] if rows else None, "held-out gap (rms) [nm]"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def candidate_row(name: str, nominal: dict, fit: dict, rules, **extra) -> dict:
    """One ranked candidate: held-out gaps before and after (nm), shrink (%), training BIC change and
    whether it is significant (``rules.min_shrink_pct``, ``rules.min_delta_bic``); ``fit`` is kept."""
    before, after = nominal["heldout_gap_nm"], fit["heldout_gap_nm"]
    shrink, dbic = 100 * (1 - after / before), float(fit["bic"] - nominal["bic"])
    return {
        "effect": name,
        "heldout_gap_before_nm": before,
        "heldout_gap_after_nm": after,
        "shrink_pct": shrink,
        "train_rms_after_nm": fit["train_rms_nm"],
        "delta_bic": dbic,
        "extra_parameters": fit["parameters"] - nominal["parameters"],
        **extra,
        "significant": bool(shrink >= rules.min_shrink_pct and dbic <= -rules.min_delta_bic),
        "fit": fit,
    }


def candidate_line(row: dict) -> str:
    """One candidate's result, for the log."""
    return (
        f"  + {row['effect']:16s} held-out gap {row['heldout_gap_after_nm']:8.3g} nm ({row['shrink_pct']:+6.1f} %), "
        f"delta BIC {row['delta_bic']:+9.1f}" + ("  significant" if row["significant"] else "")
    )


def candidate_bars(a, candidates: list, nominal_gap_nm, xlabel: str) -> None:
    """Each candidate's held-out gap after refitting (red: significant), against the nominal's."""
    if candidates:
        a.barh(
            [c["effect"] for c in candidates],
            [c["heldout_gap_after_nm"] for c in candidates],
            color=["tab:red" if c["significant"] else "tab:gray" for c in candidates],
        )
        a.axvline(nominal_gap_nm, color="k", ls="--", lw=1, label="nominal")
        a.invert_yaxis()
        a.legend(fontsize=8)
    a.set(xlabel=xlabel, title="nominal + candidate (red: significant)")


def markdown_head(doc: dict) -> list:
    """Report lines: title, verdict, candidate table, where the gap is (sentences)."""
    v = doc["verdict"]
    head = (
        f"**Verdict: {v['effect']}** - adding it shrinks the held-out gap from "
        f"{v['heldout_gap_before_nm']:.3g} nm to {v['heldout_gap_after_nm']:.3g} nm rms ({v['shrink_pct']:.1f} %)."
        if v["effect"]
        else f"**Verdict: {v['text']}** (held-out gap {doc['nominal']['heldout_gap_nm']:.3g} nm rms)."
    )
    lines = [
        f"# Sim-to-real gap diagnosis: {doc['data']['source']}",
        "",
        head,
        "",
        f"Nominal model: {doc['nominal']['model']}; trained on {doc['data']['train_samples']} {doc['data']['counts']}, "
        f"held out {doc['data']['heldout_samples']} (later in the scan). A candidate is significant when "
        f"it shrinks the held-out gap by >= {doc['rules']['min_shrink_pct']:g} % and lowers the training BIC "
        f"by >= {doc['rules']['min_delta_bic']:g}.",
        "",
        "| rank | effect | held-out gap before [nm] | after [nm] | shrink [%] | delta BIC (train) "
        "| extra params | significant |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for i, r in enumerate(doc["candidates"], 1):
        lines.append(
            f"| {i} | {r['effect']} | {r['heldout_gap_before_nm']:.3g} | {r['heldout_gap_after_nm']:.3g} | "
            f"{r['shrink_pct']:.1f} | {r['delta_bic']:.1f} | {r['extra_parameters']} | "
            f"{'yes' if r['significant'] else 'no'} |"
        )
    for name, why in doc["skipped"].items():
        lines.append(f"| - | {name} | - | - | - | - | - | not tried: {why} |")
    return lines + ["", "## Where the nominal model misses", ""] + [f"- {s}" for s in doc["where"]]


def markdown(doc: dict, metrics: dict) -> str:
    """The one-minute report of a record: :func:`markdown_head`, the tests, the figure."""
    lines = markdown_head(doc)
    lines += [
        f"- Whiteness: lag-1 autocorrelation {metrics['residual_acf_lag1']:.2f}, "
        f"{metrics['residual_acf_outside_band_pct']:.0f} % of lags 1-{MAX_LAG} outside the 95 % band "
        f"(+-{metrics['correlation_band_95']:.3f}); Ljung-Box p = {metrics['ljung_box_p']:.2g}.",
        f"- Input cross-correlation: max |rho| {metrics['input_ccf_max_abs']:.2f} with u, "
        f"{metrics['input_rate_ccf_max_abs']:.2f} with du/dt (band +-{metrics['correlation_band_95']:.3f}).",
        "",
        "![residuals](residuals.png)",
        "",
    ]
    return "\n".join(lines)


def write_outputs(res: dict, record, model: str, rules, settle: int, out: Path, log=print) -> dict:
    """``diagnosis.json``, ``metrics.json``, ``residuals.png`` and ``report.md`` of a record's
    diagnosis (``jaxafm.diagnose.diagnose_record``); returns the metrics."""
    u, d = (np.asarray(a, dtype=float).reshape(len(record), -1) for a in (record.u, record.d))
    nominal, rows, split = res["nominal"], res["candidates"], res["split"]
    r = nominal["residual"][settle:]
    test = tests(r, u[settle:], record.t[settle:])
    dec = decompose(r, u[settle:], record.t[settle:])
    verdict, metrics = summary(res, nominal, rows)
    metrics |= {"train_samples": int(split - settle), "heldout_samples": int(len(record) - split)}
    metrics |= test["metrics"] | concentration(dec)
    doc = {
        "data": {
            "source": record.meta["source"],
            "samples": len(record),
            "outputs": d.shape[1],
            "train_samples": int(split - settle),
            "heldout_samples": int(len(record) - split),
            "heldout_from_s": float(record.t[split]),
            "counts": "samples",
            "units": "nm (gaps, residuals), V, s",
        },
        "nominal": {
            "model": model,
            "train_rms_nm": nominal["train_rms_nm"],
            "heldout_gap_nm": nominal["heldout_gap_nm"],
            "parameters": nominal["parameters"],
        },
        "verdict": verdict,
        "candidates": [{k: v for k, v in row.items() if k != "fit"} for row in rows],
        "skipped": res["skipped"],
        "rules": dataclasses.asdict(rules),
        "where": where(dec, float(record.t[split])),
        "decomposition": dec,
    }
    top = next((row for row in rows if row["effect"] == res["verdict"]), None)
    best = top["fit"]["residual"][settle:] if top else None
    figure(
        record.t[settle:],
        nominal["residual"][settle:],
        best,
        res["verdict"],
        split - settle,
        test,
        dec,
        rows,
        out / "residuals.png",
    )
    save(doc, metrics, out, markdown(doc, metrics), log)
    return metrics


def summary(res: dict, nominal: dict, rows: list) -> tuple:
    """The verdict (effect, text, gaps) and the metrics every diagnosis writes."""
    top = next((row for row in rows if row["effect"] == res["verdict"]), None)
    verdict = {
        "effect": res["verdict"],
        "text": res["verdict"] or "no significant unmodelled effect",
        **(
            {k: top[k] for k in ("heldout_gap_before_nm", "heldout_gap_after_nm", "shrink_pct")}
            if top
            else {}
        ),
    }
    metrics = {
        "nominal_train_rms_nm": nominal["train_rms_nm"],
        "nominal_heldout_gap_nm": nominal["heldout_gap_nm"],
        "nominal_parameters": nominal["parameters"],
        "verdict": verdict["text"],
        "verdict_shrink_pct": top["shrink_pct"] if top else 0.0,
        "verdict_heldout_gap_after_nm": top["heldout_gap_after_nm"] if top else nominal["heldout_gap_nm"],
    }
    for row in rows:
        for k in ("heldout_gap_after_nm", "shrink_pct", "delta_bic"):
            metrics[f"{row['effect']}_{k}"] = row[k]
    return verdict, metrics


def save(doc: dict, metrics: dict, out: Path, report, log=print) -> None:
    """Write ``diagnosis.json``, ``metrics.json`` and ``report.md`` (text, or its lines) and log the verdict."""
    (out / "diagnosis.json").write_text(json.dumps(doc, indent=1))
    (out / "metrics.json").write_text(json.dumps(metrics, indent=1))
    (out / "report.md").write_text(report if isinstance(report, str) else "\n".join(report))
    v = doc["verdict"]
    log(
        f"verdict: {v['text']}"
        + (
            f" (held-out gap {v['heldout_gap_before_nm']:.3g} -> {v['heldout_gap_after_nm']:.3g} nm, "
            f"{v['shrink_pct']:.1f} %)"
            if v["effect"]
            else ""
        )
    )
