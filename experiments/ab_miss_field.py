"""What a study's A+B misses are made of, scanner by scanner, and whether step C's finds show them.

Reads the trials of a finished ``jaxafm study`` (default: the committed run of
``configs/study.yaml``) and prints, per scanner: the true miss after A+B (true tip less true
particle centre; its mean and the rms left about a quadratic field in the target's position),
and what step C found (the offset from the target to where it found the particle, in the wanted
frame): its correlation with minus the true miss along x and y, and its mean difference from it.
Then the covariance one could learn from step C's finds: each trial's miss predicted as minus the
offset that a quadratic field in the target's position, fitted to the earlier trials' finds on its
scanner, gives there (:func:`jaxafm.position.online.online_regression`), and the share of true
misses inside the 90 % region of that prediction (Hotelling's T^2 for a new case of two outputs:
``d^2 <= 2 nu / (nu - 1) F_{2, nu - 1}(0.9)``, ``nu`` its degrees of freedom). Nothing is written.

    python experiments/ab_miss_field.py [trials.npz]
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from scipy import stats

from jaxafm.position.online import online_regression

ROOT = Path(__file__).resolve().parents[1]


def quadratic_left(target: np.ndarray, miss: np.ndarray) -> np.ndarray:
    """The rms (nm) per axis of ``miss`` (k, 2) about its least-squares quadratic in ``target`` (k, 2) nm."""
    X = quadratic(target)
    left = miss - X @ np.linalg.lstsq(X, miss, rcond=None)[0]
    return np.sqrt(np.mean(left**2, axis=0))


def quadratic(target: np.ndarray) -> np.ndarray:
    """The quadratic field's regressors (k, 6) at ``target`` (k, 2) nm, in µm."""
    x, y = (np.nan_to_num(target) / 1000.0).T
    return np.column_stack([np.ones_like(x), x, y, x * y, x**2, y**2])


def learnt_coverage(r: dict, target, miss, offset, level: float = 0.9) -> float:
    """The share (%) of true misses inside the ``level`` region predicted from step C's earlier
    finds on each scanner (module docstring), over the trials given one."""
    inside = []
    for s in np.unique(r["scanner"]):
        idx = np.flatnonzero(r["scanner"] == s)
        found = r["ABC_found"][idx] & np.all(np.isfinite(offset[idx]), axis=1)
        pred = online_regression(quadratic(target[idx]), offset[idx], found)
        has = np.isfinite(pred.dof) & np.all(np.isfinite(miss[idx]), axis=1)
        e = miss[idx][has] + pred.mean[has]
        d2 = np.einsum("ki,ki->k", e, np.linalg.solve(pred.cov[has], e[..., None])[..., 0])
        nu = pred.dof[has]
        inside.append(d2 <= 2 * nu / (nu - 1) * stats.f.ppf(level, 2, nu - 1))
    return 100 * float(np.mean(np.concatenate(inside)))


def main() -> None:
    path = Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT / "experiments/results/study/trials.npz"
    r = dict(np.load(path))
    pair = lambda name: np.stack([r[f"{name}_x_nm"], r[f"{name}_y_nm"]], -1)
    target, miss, found = pair("AB_target"), pair("AB_miss"), pair("ABC_centre")
    offset = found - target
    print(
        f"{'scanner':>7s} {'trials':>6s} {'mean miss x, y [nm]':>20s} {'left by a quadratic':>20s} "
        f"{'corr(offset, -miss) x, y':>25s} {'offset + miss, mean x, y [nm]':>30s}"
    )
    for s in np.unique(r["scanner"]):
        ok = (r["scanner"] == s) & r["ABC_found"] & np.all(np.isfinite(miss), axis=1)
        if ok.sum() < 10:
            print(f"{s:7d} {ok.sum():6d}  too few trials found by step C")
            continue
        m, o = miss[ok], offset[ok]
        corr = [np.corrcoef(o[:, a], -m[:, a])[0, 1] for a in (0, 1)]
        bias = (o + m).mean(0)
        left = quadratic_left(target[ok], m)
        print(
            f"{s:7d} {ok.sum():6d} {m[:, 0].mean():9.2f} {m[:, 1].mean():9.2f} {left[0]:9.2f} {left[1]:9.2f} "
            f"{corr[0]:12.2f} {corr[1]:11.2f} {bias[0]:14.2f} {bias[1]:14.2f}"
        )
    share = learnt_coverage(r, target, miss, offset)
    print(f"true misses inside the 90 % region learnt from step C's earlier finds: {share:.1f} %")


if __name__ == "__main__":
    main()
