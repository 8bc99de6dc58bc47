"""How well predicted probabilities match what happened: the reliability diagram's bins and the
Brier score (Brier 1950; Murphy 1973 for the diagram), against the Brier score of predicting
every trial's outcome by the overall rate."""

from __future__ import annotations

import numpy as np

#: the reliability diagram's bins of predicted probability: tenths
BINS = np.linspace(0.0, 1.0, 11)


def reliability(predicted: np.ndarray, happened: np.ndarray) -> dict:
    """Scores of the probabilities ``predicted`` (k,) (NaN: no prediction, left out) for the
    outcomes ``happened`` (k,) bool: ``trials`` scored, ``brier`` (mean squared difference),
    ``brier_base_rate`` (that of predicting every trial by the scored trials' overall rate, the
    outcomes' variance) and ``bins``: per tenth of predicted probability with trials in it, its
    ``lo`` and ``hi`` edges, ``trials``, ``predicted_pct`` (mean) and ``observed_pct``."""
    p = np.asarray(predicted, float)
    keep = np.isfinite(p)
    p, y = p[keep], np.asarray(happened, bool)[keep].astype(float)
    out = {"trials": int(p.size), "brier": np.nan, "brier_base_rate": np.nan, "bins": []}
    if not p.size:
        return out
    out["brier"] = float(np.mean((p - y) ** 2))
    out["brier_base_rate"] = float(np.mean(y) * (1 - np.mean(y)))
    which = np.clip(np.searchsorted(BINS, p, side="right") - 1, 0, len(BINS) - 2)
    for b in np.unique(which):
        m = which == b
        out["bins"].append(
            {
                "lo": float(BINS[b]),
                "hi": float(BINS[b + 1]),
                "trials": int(m.sum()),
                "predicted_pct": 100 * float(p[m].mean()),
                "observed_pct": 100 * float(y[m].mean()),
            }
        )
    return out
