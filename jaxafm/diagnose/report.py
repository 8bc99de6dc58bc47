"""The report of a diagnosis: residual statistics, the figure, ``diagnosis.json``, the
metrics and ``report.md``.

Residuals are ``r = measured - model`` in nm. Statistics, for ``N`` residual samples:

- whiteness: the autocorrelation ``rho_k = sum_t r_t r_{t+k} / sum_t r_t^2`` at lags
  ``k = 1..K`` against the 95 % band ``+-1.96 / sqrt(N)`` of white noise, and the
  Ljung-Box statistic ``Q = N (N + 2) sum_k rho_k^2 / (N - k)``, chi-squared with ``K``
  degrees of freedom when ``r`` is white;
- input cross-correlation: ``rho_ru(k)`` between ``r`` and the input ``u`` (and its rate
  ``du/dt``) at lags ``-K..K``, against the same band: a model that has caught
  everything the input explains leaves none.

:func:`write` writes every kind's diagnosis (:class:`~jaxafm.diagnose.core.Diagnosis`): the
common sections, then what the kind's :meth:`~jaxafm.diagnose.core.DataKind.findings` adds.
Figures are drawn on their own :class:`matplotlib.figure.Figure` (no pyplot, no backend change).
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from scipy import stats

from .core import Diagnosis

MAX_LAG = 50  # samples


def rms(x) -> float:
    """``sqrt(mean(x^2))``, NaN for no samples."""
    return float(np.sqrt(np.mean(np.square(x)))) if np.size(x) else float("nan")


def noise_floor_nm(d) -> float:
    """The white-noise floor of samples ``d`` (T,) or (T, k) in nm rms: a robust estimate from
    their second differences. For white noise of standard deviation sigma,
    ``d[n+1] - 2 d[n] + d[n-1]`` has variance ``6 sigma^2``; a signal smooth on the scale of a
    sample adds little, and the median absolute deviation (``/ 0.6745`` for a normal
    distribution) ignores the few samples at corners and steps. Any roughness from sample to
    sample counts as floor. Several columns: the rms of their floors (what the gap's rms over
    all columns would be if the model were exact)."""
    dd = np.diff(np.asarray(d, float).reshape(len(d), -1), 2, axis=0)
    mad = np.median(np.abs(dd - np.median(dd, axis=0)), axis=0)
    return float(np.sqrt(np.mean((mad / 0.6745) ** 2 / 6)))


def above_floor(gap_nm: float, floor_nm: float) -> float:
    """The part of an rms gap above a noise floor (nm): ``sqrt(max(gap^2 - floor^2, 0))``
    (independent errors add in quadrature)."""
    return float(np.sqrt(max(gap_nm**2 - floor_nm**2, 0.0)))


def binned_rms(x: np.ndarray, r: np.ndarray, edges: np.ndarray) -> list:
    """rms of ``r`` in the bins of ``x`` between ``edges`` (the outer bins take what lies beyond)."""
    idx = np.clip(np.digitize(x, edges[1:-1]), 0, len(edges) - 2)
    return [rms(r[idx == b]) for b in range(len(edges) - 1)]


def autocorrelation(r: np.ndarray, max_lag: int = MAX_LAG) -> np.ndarray:
    """``rho_k``, k = 1..max_lag, of the mean-removed ``r`` (T,)."""
    r = r - r.mean()
    den = float(r @ r)
    if den == 0:  # a residual without variation (a perfect fit) is correlated with nothing
        return np.zeros(max_lag)
    return np.array([float(r[:-k] @ r[k:]) / den for k in range(1, max_lag + 1)])


def cross_correlation(r: np.ndarray, u: np.ndarray, max_lag: int = MAX_LAG) -> np.ndarray:
    """``rho_ru(k)`` for k = -max_lag..max_lag: ``r`` at t + k against ``u`` at t."""
    r, u = r - r.mean(), u - u.mean()
    den = np.sqrt(float(r @ r) * float(u @ u))
    if den == 0:
        return np.zeros(2 * max_lag + 1)
    out = []
    for k in range(-max_lag, max_lag + 1):
        a, b = (r[k:], u[: len(u) - k]) if k >= 0 else (r[:k], u[-k:])
        out.append(float(a @ b) / den)
    return np.array(out)


def residual_tests(r: np.ndarray, u: np.ndarray, t: np.ndarray) -> dict:
    """Whiteness and input cross-correlation of residuals ``r`` (T, k) nm against inputs ``u``
    (T, k) V at times ``t`` (T,) s (module docstring).

    Returns:
        ``acf``, ``ccf_u``, ``ccf_rate`` (one array per output), the 95 % ``band`` and the flat
        ``metrics``.
    """
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


def candidate_bars(a, candidates, base_gap_nm: float, xlabel: str, base: str = "nominal") -> None:
    """Each candidate's held-out gap after refitting (red: significant), against ``base_gap_nm``
    (nm), the gap of the model ``base`` the candidates were added to, on the axes ``a``; a
    candidate judged on another split (its label says which) has its own gap before, a tick."""
    if candidates:
        names = [c.effect + (f"\n(on {c.judged_on})" if c.judged_on else "") for c in candidates]
        a.barh(
            names,
            [c.heldout_gap_after_nm for c in candidates],
            color=["tab:red" if c.significant else "tab:gray" for c in candidates],
        )
        a.axvline(base_gap_nm, color="k", ls="--", lw=1, label=base)
        other = [(i, c.heldout_gap_before_nm) for i, c in enumerate(candidates) if c.judged_on]
        if other:
            i, before = zip(*other)
            a.scatter(before, i, marker="|", s=400, color="k", label=f"{base}, on the split that judged it")
        a.invert_yaxis()
        a.legend(fontsize=8)
    a.set(xlabel=xlabel, title=f"{base} + candidate (red: significant)")


def figure(diagnosis: Diagnosis, findings, path: Path) -> None:
    """The kind's panels, then the candidate bar chart, saved as ``path`` (110 dpi)."""
    data = diagnosis.data
    fig = Figure(figsize=data.figsize)
    axes = fig.subplots(*data.grid).ravel()
    data.panels(list(axes[:-1]), diagnosis, findings)
    base = diagnosis.base or diagnosis.nominal
    rung = next((r.effect for r in diagnosis.shapes if r.fit is base), None)
    name = f"nominal, {rung} shape" if rung else "nominal"
    candidate_bars(axes[-1], diagnosis.candidates, base.heldout_gap_nm, data.gap_label, name)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def _sizes(row: dict) -> str:
    """A fit's fitted sizes (``fitted`` in ``diagnosis.json``), in a few words with units."""
    return "; ".join(
        f"{k.replace('_', ' ')} " + ", ".join(f"{x:.3g}" for x in np.ravel(v))
        for k, v in row.get("fitted", {}).items()
    )


def _table(rows: list, skipped: dict) -> list:
    """The candidates' Markdown table rows (rank, gaps, shrink, delta BIC, parameters, fitted sizes)."""
    lines = [
        "| rank | effect | held-out gap before [nm] | after [nm] | shrink [%] | delta BIC (train) "
        "| extra params | fitted | significant |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for i, r in enumerate(rows, 1):
        lines.append(
            f"| {i} | {r['effect']}{f' (judged on {s})' if (s := r.get('judged_on')) else ''} "
            f"| {r['heldout_gap_before_nm']:.3g} | {r['heldout_gap_after_nm']:.3g} | "
            f"{r['shrink_pct']:.1f} | {r['delta_bic']:.1f} | {r['extra_parameters']} | {_sizes(r) or '-'} | "
            f"{'yes' if r['significant'] else 'no'}"
            + (" (stopped at its step limit)" if r.get("stopped_at_step_limit") else "")
            + (
                " (trains worse than without it: a solver failure)"
                if r.get("trains_worse_than_without")
                else ""
            )
            + " |"
        )
    for name, why in skipped.items():
        lines.append(f"| - | {name} | - | - | - | - | - | - | not tried: {why} |")
    return lines


def markdown(doc: dict, notes: list) -> str:
    """The one-minute report: title, verdict, warnings on the split, the hysteresis shapes and the
    candidate tables, where the gap is, the kind's ``notes``, the figure."""
    v = doc["verdict"]
    head = (
        f"**Verdict: {v['text']}** - adding {v['effect']} shrinks the held-out gap from "
        f"{v['heldout_gap_before_nm']:.3g} nm to {v['heldout_gap_after_nm']:.3g} nm rms ({v['shrink_pct']:.1f} %; "
        f"{v['total_shrink_pct']:.1f} % from the nominal model's {doc['nominal']['heldout_gap_nm']:.3g} nm)."
        if v["effect"]
        else f"**Verdict: {v['text']}** (held-out gap {doc['nominal']['heldout_gap_nm']:.3g} nm rms"
        + (
            f", {v['total_shrink_pct']:.1f} % less with the richer hysteresis)."
            if v["hysteresis_shape"]
            else ")."
        )
    )
    lines = [f"# Sim-to-real gap diagnosis: {doc['data']['source']}", "", head, ""]
    lines += [f"> **Warning:** {w}" for w in doc["warnings"]] + ([""] if doc["warnings"] else [])
    lines += [
        f"Nominal model: {doc['nominal']['model']}; trained on {doc['data']['train_samples']} {doc['data']['counts']}, "
        f"held out {doc['data']['heldout_samples']} ({doc['data'].get('heldout_where', 'later in the scan')}). "
        f"A candidate is significant when it shrinks the held-out gap by >= {doc['rules']['min_shrink_pct']:g} % "
        f"and lowers the training BIC by >= {doc['rules']['min_delta_bic']:g}.",
        "",
    ]
    if doc["hysteresis_shapes"]:
        lines += [
            "## Hysteresis shape",
            "",
            "Each richer operator against the one below it (the effects are then added to the richest "
            "significant one; a last row rechecks that operator with the effect found in both models):",
            "",
        ] + _table(doc["hysteresis_shapes"], {})
        lines += ["", "## Effects", ""]
    lines += _table(doc["candidates"], doc["skipped"])
    if doc.get("compared_on_one_split"):
        lines += [
            "",
            "The significant effects above were judged on different held-out parts, so their shrinks "
            "do not rank them: each was refitted on the split below and the verdict is the best there:",
            "",
        ] + _table(doc["compared_on_one_split"], {})
    if doc.get("decided_by_evidence"):
        lines += [
            "",
            f"Their held-out gaps lie within {doc['rules']['min_shrink_pct']:g} % of each other, so the held-out "
            "part cannot separate them: the lowest training delta BIC decides, every fit's residual scored "
            "under the same noise model (a coloured misfit beside white noise, a drift's walk and rate on top): "
            + ", ".join(f"{e} {b:.1f}" for e, b in doc["decided_by_evidence"].items())
            + ".",
        ]
    lines += ["", "## Where the nominal model misses", ""] + [f"- {s}" for s in doc["where"]]
    return "\n".join(lines + list(notes) + ["", "![residuals](residuals.png)", ""])


def write(diagnosis: Diagnosis, save: Callable, log=print) -> dict:
    """Write ``residuals.png``, ``diagnosis.json`` and ``report.md``, and log the verdict;
    ``metrics.json`` is the caller's to write from what this returns.

    Arguments:
        diagnosis: any kind's :class:`~jaxafm.diagnose.core.Diagnosis`.
        save: ``save(name, writer)`` writes the file ``name``, ``writer(path)`` writing its
            bytes to ``path`` (:meth:`jaxafm.jobs.Output.write`: into an output folder, recorded).
        log: called with the verdict line.

    Returns:
        The metrics (flat; names carry their units).
    """
    data, nominal = diagnosis.data, diagnosis.nominal
    found = data.findings(diagnosis)
    metrics = diagnosis.metrics() | found.metrics
    doc = {
        "data": data.describe(),
        "nominal": {"model": data.model, **nominal.summary()},
        "verdict": diagnosis.verdict_json(),
        "warnings": list(diagnosis.warnings),
        "hysteresis_shapes": [c.to_json() for c in diagnosis.shapes],
        "candidates": [c.to_json() for c in diagnosis.candidates],
        "skipped": dict(diagnosis.skipped),
        **({"compared_on_one_split": [c.to_json() for c in diagnosis.contest]} if diagnosis.contest else {}),
        **(
            {"decided_by_evidence": {c.effect: c.evidence for c in diagnosis.evidence_decided}}
            if diagnosis.evidence_decided
            else {}
        ),
        "rules": dataclasses.asdict(diagnosis.rules),
        "where": found.where,
    }
    if found.decomposition is not None:
        doc["decomposition"] = found.decomposition
    save("residuals.png", lambda path: figure(diagnosis, found, path))
    save("diagnosis.json", lambda path: path.write_text(json.dumps(doc, indent=1)))
    save("report.md", lambda path: path.write_text(markdown(doc, found.notes)))
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
    return metrics
