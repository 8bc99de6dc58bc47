"""A push's odds from two models of its miss, scored on the same committed study's first pushes:
what the affine model of :mod:`jaxafm.position.push_odds` buys over a model in the push's
distance alone.

- **distance**: the miss along the push and across it, each a straight line in the push's
  distance ``L`` with its own scatter, the two taken as independent (Student-t predictives of
  ``n - 2`` degrees of freedom); it cannot follow a miss that depends on the push's direction.
- **affine** (the library's): the miss vector ``b + M d + eps`` in the push's vector ``d``, a
  bivariate Student-t predictive of ``n - 3`` degrees of freedom; where pushes learn, in what
  each push commanded, ``(c - d) + b + M c + eps``.

Both learn from the same pushes in the same order (the earlier trials' first pushes on each
scanner that touched their particles, their true misses), both take the contact odds by
Laplace's rule, and both integrate the miss over the tolerance's circle by
:func:`~jaxafm.position.push_odds.success_probability`. Scored like the study's odds
(:func:`~jaxafm.study.reliability.reliability`): per tenth of prediction and by the Brier score.

    python experiments/push_odds_models.py [--studies study study_wide ...]

Reads each committed study's ``experiments/results/STUDY/trials.npz`` (default: study,
study_wide, study_classes, study_push_learning, the runs without a push gate that keep their
trials) and writes ``experiments/results/push_odds_models/metrics.json``, one entry a study.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from jaxafm.position import push_odds
from jaxafm.position.online import Predictive, online_regression
from jaxafm.study.monte_carlo import predicted_push_success, push_commands, push_vectors
from jaxafm.study.reliability import reliability

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "experiments" / "results"
OUT = RESULTS / "push_odds_models"
#: the committed studies without a push gate that keep their trials
STUDIES = ["study", "study_wide", "study_classes", "study_push_learning"]


def distance_odds(r: dict, tolerance_radii: float) -> np.ndarray:
    """Each trial's first-push odds from the model in the push's distance alone (module
    docstring), from the earlier trials on its scanner."""
    p = np.full(len(r["trial"]), np.nan)
    for s in np.unique(r["scanner"]):
        idx = np.flatnonzero(r["scanner"] == s)
        along, across = r["push_first_along_nm"][idx], r["push_first_across_nm"][idx]
        made = np.isfinite(along) & np.isfinite(across)
        touched = made & r["push_contact"][idx].astype(bool)
        L = r["push_distance_nm"][idx] / push_odds.PUSH_UNIT_NM
        X = np.column_stack([np.ones_like(L), L])
        parts = [online_regression(X, y, touched, push_odds.MIN_PUSHES - 3) for y in (along, across)]
        cov = np.zeros((len(idx), 2, 2))
        cov[:, 0, 0], cov[:, 1, 1] = parts[0].cov[:, 0, 0], parts[1].cov[:, 0, 0]
        mean = np.column_stack([parts[0].mean[:, 0], parts[1].mean[:, 0]])
        landing = push_odds.success_probability(
            Predictive(mean, cov, parts[0].dof), tolerance_radii * r["radius_nm"][idx]
        )
        p[idx] = push_odds.contact_odds(touched, made) * landing
    return np.where(np.isfinite(r["push_first_error_nm"]), p, np.nan)


def residual_sd(r: dict) -> dict:
    """Each scanner's rms residual (nm, per component) of its touching first pushes' misses about
    each model fitted to all of them by least squares: the scatter each model leaves."""
    out = {"distance": [], "affine": []}
    push = push_vectors(r)
    command = push_commands(r)
    along, across = r["push_first_along_nm"], r["push_first_across_nm"]
    miss = push_odds.from_components(along, across, push) - (command - push)
    for s in np.unique(r["scanner"]):
        i = np.flatnonzero((r["scanner"] == s) & r["push_contact"].astype(bool) & np.isfinite(along))
        L = r["push_distance_nm"][i]
        fits = {
            "distance": (np.column_stack([np.ones_like(L), L]), np.column_stack([along[i], across[i]])),
            "affine": (np.column_stack([np.ones_like(L), command[i]]), miss[i]),
        }
        for name, (X, Y) in fits.items():
            residual = Y - X @ np.linalg.lstsq(X, Y, rcond=None)[0]
            out[name].append(float(np.sqrt(np.mean(residual**2))))
    return out


def score_study(folder: Path) -> dict:
    """Both models' scores on one study's first pushes, printed as they come."""
    r = dict(np.load(folder / "trials.npz"))
    tol = json.loads((folder / "metrics.json").read_text())["push_tolerance_radii"]
    first = r["push_contact"].astype(bool) & (r["push_first_error_nm"] <= tol * r["radius_nm"])
    scores = {}
    scatter = residual_sd(r)
    for name, p in {"distance": distance_odds(r, tol), "affine": predicted_push_success(r, tol)}.items():
        score = scores[name] = reliability(p, first) | {"residual_sd_nm": scatter[name]}
        worst = max(abs(b["observed_pct"] - b["predicted_pct"]) for b in score["bins"] if b["trials"] >= 100)
        print(
            f"{folder.name} {name}: {score['trials']} trials given odds, Brier {score['brier']:.4f} (overall "
            f"rate's {score['brier_base_rate']:.4f}); largest gap over the tenths with >= 100 trials "
            f"{worst:.1f} points; residual sd per scanner {np.round(scatter[name], 1).tolist()} nm"
        )
        for b in score["bins"]:
            print(
                f"   {100 * b['lo']:3.0f}-{100 * b['hi']:3.0f} %  {b['trials']:5d} trials  predicted "
                f"{b['predicted_pct']:5.1f} %  observed {b['observed_pct']:5.1f} %"
            )
    return scores


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--studies", nargs="+", default=STUDIES)
    args = ap.parse_args(argv)
    out = {name: score_study(RESULTS / name) for name in args.studies}
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "metrics.json").write_text(json.dumps(out, indent=1))
    print(f"wrote {OUT / 'metrics.json'}")


if __name__ == "__main__":
    main()
