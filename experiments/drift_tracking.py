"""A sequence of moves on a drifting scanner, each refined by the positions observed before it:
no refinement, a static offset field (gains, coupling, bow, offset), and the tracker with a drift
state (:class:`jaxafm.position.online.Tracker`).

The instrument: ``default_afm`` with a drift of (1.0, -0.6) nm/s and a wander of 0.3 nm/sqrt(s)
(an Ornstein-Uhlenbeck process, as the simulator draws it; the tracker assumes a random walk of
that diffusion), its true scanner of one of two hysteresis classes (``--truths``): the generalised
PI that step A fits, or a Preisach plane (``default_scanner(truth_class="preisach")``). The
software's model: the generalised-PI default without drift and noise, its x gain 10 % short
(``--gain``). ``--moves`` moves to random targets over a 3 um workspace, one every 5.1 s
(0.1 s move, 5 s dwell), each observed as a local scan's find would see it (1 nm scatter) and fed
back before the next (the field's coefficients a priori N(0, (300 nm)^2): gain errors up to 20 %
over the half-size). Printed and saved: each method's miss (the true tip's distance from the
target) by blocks of ten moves, the drift velocity the tracker found, and how well its predicted
sd matched the misses (rms of miss / sd; 1 is calibrated).

    python experiments/drift_tracking.py [--moves 100] [--out experiments/results/drift_tracking]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from jaxafm.instrument.afm import AFM, default_afm, run_cycle
from jaxafm.instrument.samples import Plane, Tip
from jaxafm.position.online import VELOCITY, Tracker
from jaxafm.position.positioning import Positioner, goto

ROOT = Path(__file__).resolve().parents[1]
CYCLE = np.array([[-10.0, -10.0], [10.0, 10.0]])
VELOCITY_NM_S, WANDER, FIND_NM, HALF_NM, DWELL_S = np.array([1.0, -0.6]), 0.3, 1.0, 1500.0, 5.0
#: the prior sd (nm) of each field coefficient: a gain error of 20 % over the workspace's half-size
PRIOR_NM = 0.2 * HALF_NM
METHODS = ("none", "static field", "tracker with drift")


def x_gain(scanner, g: float):
    """``scanner`` with its x hysteresis output scaled by ``g`` (as tests/test_tracking.py)."""
    h = scanner.x.hysteresis
    parts = lambda h: (h.pi.weights, h.pi.offset, h.deadzone.upper, h.deadzone.lower, h.deadzone.centre)
    return eqx.tree_at(
        lambda s: s.x.hysteresis, scanner, eqx.tree_at(parts, h, tuple(g * v for v in parts(h)))
    )


def sequence(truth: str, gain: float, moves: int, seed: int) -> dict:
    """Each method's misses (moves,) nm over one sequence on one instrument, and the tracker's end."""
    afm = default_afm(drift_nm_per_min=tuple(60 * VELOCITY_NM_S), drift_sigma=WANDER, truth_class=truth)
    model = x_gain(default_afm().scanner.without("drift", "noise"), gain)
    state = run_cycle(afm, Plane(), afm.initial_state((0.0, 0.0), 0.0, CYCLE), CYCLE, jax.random.key(0))
    twin = AFM(model, Tip(), afm.sensitivity, None, dilate=False)
    tw = run_cycle(twin, Plane(), twin.initial_state((0.0, 0.0), 0.0, CYCLE), CYCLE, jax.random.key(0))
    pos = Positioner(afm, model)
    step = eqx.filter_jit(lambda pos, stand, w, key: goto(pos, Plane(), stand, w, key, dwell=DWELL_S))
    out = {}
    for method in METHODS:
        stand = pos.start(state, tw.scanner)
        t0 = float(stand.afm.scanner.t)
        drifting = method == "tracker with drift"
        tracker = Tracker.start(
            np.zeros(2),
            HALF_NM,
            PRIOR_NM,
            FIND_NM,
            2.0 if drifting else 0.0,
            WANDER**2 if drifting else 0.0,
            t0,
        )
        rng = np.random.default_rng(seed)
        miss, z, times = [], [], []
        for k in range(moves):
            target = rng.uniform(-HALF_NM, HALF_NM, 2)
            offset, sd = tracker.predict(target[None], float(stand.afm.scanner.t) + 0.1 + DWELL_S)
            offset = offset[0] if method != "none" else np.zeros(2)
            xy, _, stand = step(pos, stand, jnp.asarray(target + offset), jax.random.key(k))
            xy = np.asarray(xy)
            times.append(float(stand.afm.scanner.t) - t0)
            miss.append(float(np.linalg.norm(xy - target)))
            z.extend((xy - target) / sd[0])
            seen = xy + rng.normal(0, FIND_NM, 2)
            now = [times[-1] + t0] if drifting else None
            tracker = tracker.observe(seen[None], (target + offset - seen)[None], now)
        out[method] = {"miss_nm": miss, "time_s": times}
        if method != "none":
            out[method]["miss_over_sd_rms_after_10"] = float(np.sqrt(np.mean(np.square(z[20:]))))
        if drifting:
            v = -tracker.mean[VELOCITY]
            out[method]["velocity_nm_s"] = v.tolist()
            out[method]["velocity_sd_nm_s"] = float(np.sqrt(tracker.cov[VELOCITY, VELOCITY]))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--moves", type=int, default=100)
    ap.add_argument("--gain", type=float, default=0.9, help="the model's x gain over the truth's")
    ap.add_argument("--truths", nargs="+", default=["generalised_pi", "preisach"])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", type=Path, default=ROOT / "experiments" / "results" / "drift_tracking")
    args = ap.parse_args()
    results = {
        "velocity_truth_nm_s": VELOCITY_NM_S.tolist(),
        # the drift in the commands' units: a model whose x gain is g of the truth's commands g of a move
        "velocity_commands_need_nm_s": (VELOCITY_NM_S * [args.gain, 1.0]).tolist(),
        "wander_nm_per_sqrt_s": WANDER,
        "gain": args.gain,
        "moves": args.moves,
    }
    fig, axes = plt.subplots(1, len(args.truths), figsize=(5.5 * len(args.truths), 4), squeeze=False)
    for truth, ax in zip(args.truths, axes[0]):
        tic = time.perf_counter()
        r = sequence(truth, args.gain, args.moves, args.seed)
        results[truth] = r
        print(f"truth {truth}: {args.moves} moves in {time.perf_counter() - tic:.1f} s")
        print(
            f"  {'method':<20s} "
            + " ".join(f"moves {k + 1:>3d}-{k + 10:<3d}" for k in range(0, args.moves, 10))
        )
        for method in METHODS:
            m = np.array(r[method]["miss_nm"])
            blocks = [np.median(m[k : k + 10]) for k in range(0, args.moves, 10)]
            print(f"  {method:<20s} " + " ".join(f"{b:12.2f} nm" for b in blocks))
            ax.semilogy(r[method]["time_s"], m, ".-", ms=3, lw=0.6, label=method)
        d = r["tracker with drift"]
        print(
            f"  drift velocity found {np.round(d['velocity_nm_s'], 3)} +- {d['velocity_sd_nm_s']:.3f} nm/s "
            f"(truth {VELOCITY_NM_S}, in the commands' units {results['velocity_commands_need_nm_s']}); "
            f"rms miss/sd after 10 moves: tracker "
            f"{d['miss_over_sd_rms_after_10']:.2f}, static {r['static field']['miss_over_sd_rms_after_10']:.2f}"
        )
        ax.set(
            xlabel="time since the model [s]",
            ylabel="miss of the true tip [nm]",
            title=f"true scanner: {truth}",
        )
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
    fig.suptitle(
        f"Moves refined by what was observed before them (model's x gain {args.gain:g} of the truth's)"
    )
    fig.tight_layout()
    args.out.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out / "misses.png", dpi=120)
    (args.out / "results.json").write_text(json.dumps(results, indent=1))
    print(f"wrote {args.out / 'results.json'} and misses.png")


if __name__ == "__main__":
    main()
