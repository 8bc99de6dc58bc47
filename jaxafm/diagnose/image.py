"""Gap diagnosis on one image of a 1-D grating: edge positions against the scanner's distortion.

The edges of every row (``line_grating.grating_edges``) are fitted by linear least squares,
``x_nom = phase + n p - sum_k c_k P_k(s) - [candidate terms]`` (``line_grating``'s model):
the nominal, hysteresis-only scanner has the fast-axis nonlinearity ``c_2, c_3`` (one branch
of the loop) and the grating's pitch ``p`` and two edge phases. Candidates add one column
each: ``coupling`` the skew ``x += s y``, ``bow`` ``x += b P_2(y)``, ``creep`` an x scale
that changes over the frame. Training rows: the first ``train_fraction`` in scan order;
held out: the later rows. Gap: rms edge residual (nm) on the held-out rows; BIC and
significance as in :mod:`jaxafm.diagnose`.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from ..identify.line_grating import _design, grating_edges
from . import report as gap_report

NOMINAL = ("c2", "c3", "phase_rise", "phase_fall", "pitch")
COLUMN = {"coupling": "skew", "bow": "bow", "creep": "drift"}
NOT_IN_ONE_IMAGE = {
    "drift": "in one image a steady x drift shifts each row in proportion to its time, the same column as "
    "coupling (skew): image twice, or in both slow-axis directions, to tell them apart",
    "asymmetry": "one image holds one branch of the loop; its shape is the nominal nonlinearity: needs trace "
    "and retrace",
    "rate_dependence": "needs images at two scan speeds",
    "feedback_lag": "its edge shift v tau is the same on every edge of one image and the edge phases absorb it: "
    "needs trace and retrace, or two scan speeds",
    "tip": "its widening of the grooves is the same on every row and the two edge phases absorb it: needs a "
    "tip characteriser or a sample of known width",
    "noise": "white noise is what the residual should be; it is no candidate",
    "hysteresis": "already in the nominal model",
}


def _fit(a, b, names, cols, train):
    """Least squares on the training edges; residual (all edges) nm, training rss, BIC."""
    idx = [names.index(c) for c in cols]
    x = a[:, idx]
    theta = np.linalg.lstsq(x[train], b[train], rcond=None)[0]
    r = b - x @ theta
    n, k = int(train.sum()), len(idx)
    rss = float(r[train] @ r[train])
    return {
        "residual": r,
        "theta": dict(zip(cols, theta.tolist())),
        "parameters": k,
        "train_rms_nm": float(np.sqrt(rss / n)),
        "bic": n * np.log(max(rss, 1e-300) / n) + k * np.log(n),
    }


def diagnose_image(image, candidates, train_fraction: float, rules) -> dict:
    """Nominal and nominal + candidate fits to the edges of ``image`` (an ``AFMImage``)."""
    name = str(image.meta.get("source", "image"))
    e = grating_edges(image.z, image.pixel_size, name)
    rows = np.unique(e.row)
    cut = rows[int(round(train_fraction * len(rows)))] if len(rows) > 1 else 0
    train = e.row < cut
    if train.sum() < 20 or (~train).sum() < 20 or len(rows) < 8:
        raise ValueError(
            f"{name}: {len(rows)} rows with edges ({int(train.sum())} training and "
            f"{int((~train).sum())} held-out edges at train_fraction={train_fraction}): too few to "
            "split; scan more lines or change train_fraction in the config"
        )
    a, names, _, _ = _design(e, 3, True, False)
    nominal = _fit(a, e.x_nm, names, list(NOMINAL), train)
    nominal["heldout_gap_nm"] = _gap(nominal["residual"], ~train)
    out, skipped = [], {}
    for c in candidates:
        if c not in COLUMN:
            skipped[c] = NOT_IN_ONE_IMAGE[c]
            continue
        fit = _fit(a, e.x_nm, names, list(NOMINAL) + [COLUMN[c]], train)
        fit["heldout_gap_nm"] = _gap(fit["residual"], ~train)
        out.append(gap_report.candidate_row(c, nominal, fit, rules, fitted=fit["theta"]))
    out.sort(key=lambda r: -r["shrink_pct"])
    verdict = next((r["effect"] for r in out if r["significant"]), None)
    return {
        "edges": e,
        "train": train,
        "first_heldout_row": int(cut),
        "nominal": nominal,
        "candidates": out,
        "skipped": skipped,
        "verdict": verdict,
    }


def _gap(r, sel) -> float:
    return float(np.sqrt(np.mean(r[sel] ** 2)))


def decompose(res: dict) -> dict:
    """rms edge residual (nm) by position in the scan field (x), by row, rising vs falling edges."""
    e, r = res["edges"], res["nominal"]["residual"]
    xe = np.linspace(e.x_nm.min(), e.x_nm.max(), 9)
    ye = np.linspace(e.row.min(), e.row.max() + 1, 11)
    return {
        "edges": {"x_nm": xe.tolist(), "row": ye.tolist()},
        "rms_nm": {
            "x_nm": gap_report._binned(e.x_nm, r, xe),
            "row": gap_report._binned(e.row, r, ye),
            "rising": gap_report._rms(r[e.rising]),
            "falling": gap_report._rms(r[~e.rising]),
        },
        "overall_rms_nm": gap_report._rms(r),
    }


def where(dec: dict, first_heldout_row: int) -> list:
    tab, overall = dec["rms_nm"], dec["overall_rms_nm"]
    x = np.array(tab["x_nm"])
    b = int(np.nanargmax(x))
    rows = np.array(tab["row"])
    return [
        f"Across the scan field (x) the rms edge residual is largest between {dec['edges']['x_nm'][b]:.0f} and "
        f"{dec['edges']['x_nm'][b + 1]:.0f} nm: {x[b]:.3g} nm against {overall:.3g} nm overall.",
        f"Down the frame (rows, in scan order) it goes from {rows[0]:.3g} nm (first tenth) to {rows[-1]:.3g} nm "
        f"(last tenth); the held-out rows start at row {first_heldout_row}.",
        f"Rising edges {tab['rising']:.3g} nm, falling edges {tab['falling']:.3g} nm rms "
        "(a lag or a tip would move the two kinds apart).",
    ]


def row_tests(res: dict) -> dict:
    """Whiteness of the per-row mean residual down the frame (a slow-axis miss correlates rows)."""
    e, r = res["edges"], res["nominal"]["residual"]
    rows = np.unique(e.row)
    mean = np.array([r[e.row == k].mean() for k in rows])
    acf = gap_report.autocorrelation(mean, min(20, len(rows) // 3))
    band = 1.96 / np.sqrt(len(rows))
    return {
        "acf": acf,
        "band": band,
        "metrics": {
            "row_mean_residual_acf_lag1": float(acf[0]),
            "row_mean_residual_acf_outside_band_pct": float(100 * np.mean(np.abs(acf) > band)),
            "correlation_band_95": float(band),
        },
    }


def figure(res: dict, dec: dict, test: dict, path) -> None:
    e, r = res["edges"], res["nominal"]["residual"]
    fig, ax = plt.subplots(2, 2, figsize=(12, 8.5))
    a = ax[0, 0]
    sc = a.scatter(
        e.x_nm / 1e3,
        e.row,
        c=r,
        s=6,
        cmap="coolwarm",
        vmin=-3 * dec["overall_rms_nm"],
        vmax=3 * dec["overall_rms_nm"],
    )
    a.axhline(res["first_heldout_row"] - 0.5, color="k", ls="--", lw=1)
    fig.colorbar(sc, ax=a, label="edge residual [nm]")
    a.set(
        xlabel="x [µm]",
        ylabel="row (scan order)",
        title="nominal residual in the scan field (--: held out above)",
    )
    a = ax[0, 1]
    for k, m in ((True, "rising"), (False, "falling")):
        rows = np.unique(e.row)
        a.plot(
            rows, [r[(e.row == j) & (e.rising == k)].mean() for j in rows], ".-", lw=0.8, label=f"{m} edges"
        )
    if res["verdict"]:
        best = next(c for c in res["candidates"] if c["effect"] == res["verdict"])["fit"]["residual"]
        a.plot(rows, [best[e.row == j].mean() for j in rows], "k-", lw=1, label=f"with {res['verdict']}")
    a.set(xlabel="row (scan order)", ylabel="mean residual per row [nm]", title="down the frame")
    a.legend(fontsize=8)
    a = ax[1, 0]
    a.plot(np.arange(1, test["acf"].size + 1), test["acf"], "o-")
    a.axhspan(-test["band"], test["band"], color="0.85", label="95 % band (white)")
    a.set(xlabel="lag [rows]", ylabel="autocorrelation", title="whiteness of the per-row mean residual")
    a.legend(fontsize=8)
    gap_report.candidate_bars(
        ax[1, 1], res["candidates"], res["nominal"]["heldout_gap_nm"], "held-out gap (rms edge residual) [nm]"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_outputs(res: dict, image, rules, out: Path, log=print) -> dict:
    """``diagnosis.json``, ``metrics.json``, ``residuals.png`` and ``report.md``; returns the metrics."""
    import dataclasses

    nominal, rows = res["nominal"], res["candidates"]
    dec, test = decompose(res), row_tests(res)
    verdict, metrics = gap_report.summary(res, nominal, rows)
    n_train = int(res["train"].sum())
    metrics |= {"train_edges": n_train, "heldout_edges": int((~res["train"]).sum())}
    metrics |= test["metrics"] | {
        "residual_rms_nm": dec["overall_rms_nm"],
        "residual_rising_nm": dec["rms_nm"]["rising"],
        "residual_falling_nm": dec["rms_nm"]["falling"],
    }
    doc = {
        "data": {
            "source": str(image.meta.get("source", "image")),
            "kind": "1-D grating image",
            "pixels": list(image.shape),
            "pixel_size_nm": list(image.pixel_size),
            "train_samples": n_train,
            "heldout_samples": int((~res["train"]).sum()),
            "heldout_from_row": res["first_heldout_row"],
            "counts": "edges",
            "units": "nm (edge positions, gaps)",
        },
        "nominal": {
            "model": "hysteresis-only scanner: fast-axis nonlinearity c2, c3 + grating pitch and phases",
            "train_rms_nm": nominal["train_rms_nm"],
            "heldout_gap_nm": nominal["heldout_gap_nm"],
            "parameters": nominal["parameters"],
            "fitted": nominal["theta"],
        },
        "verdict": verdict,
        "candidates": [{k: v for k, v in c.items() if k != "fit"} for c in rows],
        "skipped": res["skipped"],
        "rules": dataclasses.asdict(rules),
        "where": where(dec, res["first_heldout_row"]),
        "decomposition": dec,
    }
    figure(res, dec, test, out / "residuals.png")
    gap_report.save(doc, metrics, out, _markdown(doc, metrics), log)
    return metrics


def _markdown(doc: dict, metrics: dict) -> str:
    text = gap_report.markdown_head(doc)
    text += [
        f"- Whiteness down the frame: lag-1 autocorrelation of the per-row mean residual "
        f"{metrics['row_mean_residual_acf_lag1']:.2f}, {metrics['row_mean_residual_acf_outside_band_pct']:.0f} % "
        f"of lags outside the 95 % band (+-{metrics['correlation_band_95']:.2f}).",
        "- One image shows one branch at one speed: what it cannot show is listed as 'not tried' above.",
        "",
        "![residuals](residuals.png)",
        "",
    ]
    return "\n".join(text)
