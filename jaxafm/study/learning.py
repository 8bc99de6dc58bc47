"""How the A+B moves learn from step C's finds over a study (:func:`learning_rounds`): the error
of a scanner's k-th target against k."""

from __future__ import annotations

import numpy as np

#: a trial counts as learnt once its offset came from at least this many finds
LEARNT_FINDS = 10


def learning_rounds(r: dict, round_trials: int) -> dict:
    """The A+B error (``AB_error_nm``) per round of each scanner's trials (columns ``scanner``,
    ``AB_learnt_from``; trials in order): ``first_trial`` (rounds,) the place of each round's
    first trial in its scanner's sequence, ``median_nm`` the median over every scanner's trials
    of that round, ``per_scanner`` {scanner: medians}, ``finds_median`` the median finds learnt
    from, ``per_scanner_learnt`` {scanner: the median of its trials learnt from at least
    :data:`LEARNT_FINDS` finds, NaN for none}. Then, over the scanners that reached that many
    finds (``learnt_scanners``; the others, ``unlearnt_scanners``, are left out of both sides,
    as their first rounds alone would weigh on one): the median of their first rounds
    (``first_round_median_nm``), of their learnt trials (``learnt_median_nm``), and the ratio."""
    scanner, e, finds = r["scanner"], r["AB_error_nm"], r["AB_learnt_from"]
    place = np.empty(len(scanner), int)
    for s in np.unique(scanner):
        idx = np.flatnonzero(scanner == s)
        place[idx] = np.arange(len(idx))
    which = place // round_trials
    rounds = np.arange(which.max() + 1)
    median = lambda v: float(np.nanmedian(v)) if np.isfinite(v).any() else float("nan")
    learnt = finds >= LEARNT_FINDS
    taught = np.isin(scanner, np.unique(scanner[learnt]))
    first = median(e[taught & (finds == 0)])
    after = median(e[learnt])
    return {
        "round_trials": round_trials,
        "first_trial": (rounds * round_trials).tolist(),
        "median_nm": [median(e[which == k]) for k in rounds],
        "finds_median": [float(np.median(finds[which == k])) for k in rounds],
        "per_scanner": {
            int(s): [median(e[(scanner == s) & (which == k)]) for k in rounds] for s in np.unique(scanner)
        },
        "per_scanner_learnt": {int(s): median(e[(scanner == s) & learnt]) for s in np.unique(scanner)},
        "learnt_scanners": sorted(int(s) for s in np.unique(scanner[taught])),
        "unlearnt_scanners": sorted(int(s) for s in np.unique(scanner[~taught])),
        "first_round_median_nm": first,
        "learnt_median_nm": after,
        "learnt_ratio": after / first if first > 0 else float("nan"),
    }


#: the nominal levels (probability) of the predicted A+B radius a study scores
COVERAGE_LEVELS = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.95)


def rayleigh_radius(level) -> np.ndarray:
    """The radius, in units of the per-axis sd ``s``, inside which a 2-D isotropic Gaussian error
    lies with probability ``level``: its length is Rayleigh, ``P(|e| <= s r) = 1 - exp(-r^2 / 2)``,
    so ``r = sqrt(-2 ln(1 - level))`` (1.18 at 50 %, 2.15 at 90 %)."""
    return np.sqrt(-2 * np.log1p(-np.asarray(level, float)))


def position_coverage(r: dict) -> dict:
    """How often a miss fell within the radius that the predicted spread ``AB_predicted_sd_nm``
    gives at each of :data:`COVERAGE_LEVELS` (:func:`rayleigh_radius`), for two misses: the A+B
    tip's true distance from its particle (``true``, ``AB_error_nm``), and where step C found the
    particle, in the software's frame, from where the move was aimed (``find``,
    ``ABC_centre - AB_target - AB_offset``, over the verified finds): what the tracker learns
    from. Each for all trials with both (``all``) and for those aimed by at least
    :data:`LEARNT_FINDS` finds (``learnt``): ``trials``, ``covered_pct`` per level, the median
    predicted sd and the median of miss / sd. A calibrated prediction covers each level's share."""
    xy = lambda name: np.stack([r[f"{name}_x_nm"], r[f"{name}_y_nm"]], -1)
    find = np.linalg.norm(xy("ABC_centre") - xy("AB_target") - xy("AB_offset"), axis=-1)
    misses = {"true": r["AB_error_nm"], "find": np.where(r["ABC_found"], find, np.nan)}
    sd, finds = r["AB_predicted_sd_nm"], r["AB_learnt_from"]
    radius = rayleigh_radius(COVERAGE_LEVELS)
    out = {"levels": list(COVERAGE_LEVELS)}
    for kind, e in misses.items():
        out[kind] = {}
        for name, keep in (("all", np.ones(e.shape, bool)), ("learnt", finds >= LEARNT_FINDS)):
            m = keep & np.isfinite(e) & np.isfinite(sd)
            z = e[m] / sd[m]
            out[kind][name] = {
                "trials": int(m.sum()),
                "covered_pct": [100 * float(np.mean(z <= k)) if m.any() else float("nan") for k in radius],
                "sd_median_nm": float(np.median(sd[m])) if m.any() else float("nan"),
                "miss_over_sd_median": float(np.median(z)) if m.any() else float("nan"),
            }
    return out
