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
