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


#: the odds below which :func:`gate` withholds a push, each scored
GATE_ODDS = (0.5, 0.9, 0.99)


def gate(predicted: np.ndarray, succeeded: np.ndarray, tried: np.ndarray) -> list:
    """What withholding every push whose ``predicted`` (k,) success is below each of
    :data:`GATE_ODDS` would have done, over the pushes ``tried`` (k,) bool, ``succeeded`` (k,)
    bool: per threshold ``min_odds``, the share of the tried pushes made (``made_pct``; a push
    without odds is made) and the success of those made (``success_of_made_pct``). Read from
    pushes that were all made, so the odds of each came from every push before it; a gate in the
    study itself learns only from the pushes it made (``learning.min_push_odds``)."""
    p = np.asarray(predicted, float)
    tried, ok = np.asarray(tried, bool), np.asarray(succeeded, bool)
    rows = []
    for th in GATE_ODDS:
        made = tried & ~(p < th)
        rows.append(
            {
                "min_odds": th,
                "made_pct": 100 * float(made.sum() / max(tried.sum(), 1)),
                "success_of_made_pct": 100 * float(ok[made].mean()) if made.any() else float("nan"),
            }
        )
    return rows
