"""How far a push-like move really goes on each scanner of a study, through step A's model and
step B's map: where a study's pushes fall short, and whether a check in the wanted frame sees it.

For each scanner of a study (``--config``, default ``configs/study.yaml``; its step A model read
from the committed run's ``scanners/`` in ``experiments/results/<config's name>/``, its A+B
survey and landmark map made again as the study makes them), the tip is brought to one place
``PLACE`` with the study's 500 nm approach, then moved as a push moves it:
back ``BACK`` nm, a dwell of 0.1 s, and forward ``BACK + TRAVEL`` nm at 200 nm/s, along +x, -x,
+y and -y. Printed and written: the true travel's relative error (true travel over wanted, less
one), and how short a check that arrives at the goal as the study's does sees the push fall:
the true position of the goal reached afresh with the approach, less the true end of the push,
along the push (what the wanted frame there shows of the shortfall, in nm).

With ``--lead-in L`` the start is reached as a push with ``push.lead_in_nm: L`` reaches it
(through ``L`` nm beyond and before it along the push), not by backing straight from the place.
With ``--truth-model`` the moves go through the scanner's own truth (its drift, noise and
mechanical mode left out: no inverse undoes them) in place of step A's model, and the twin
starts from the instrument's state: what is left is not the model's.

    python experiments/push_shortfall.py [--scanners 0 3 9] [--approach 1000]
    python experiments/push_shortfall.py --config configs/study_classes_speed.yaml --scanners 0 1 2 3 5 9 13
        [--lead-in 500 | --truth-model]

Writes ``experiments/results/push_shortfall/shortfall.json`` (with ``--approach A``:
``shortfall_approach_A.json``; with ``--scanners``, their numbers added to the name; with another
``--config``, its name; ``_lead_in_L`` with ``--lead-in``, ``_truth_model`` with
``--truth-model``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp

from jaxafm.config import StudyConfig
from jaxafm.config.common import load_config
from jaxafm.instrument.samples import Particles
from jaxafm.jobs import study as job
from jaxafm.jobs.folder import Output
from jaxafm.position.positioning import Positioner, Stand, goto

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "study.yaml"
#: where every move is made (nm, the wanted frame), how far the tip backs and how far it then travels
PLACE, BACK, TRAVEL = (300.0, -200.0), 60.0, 200.0
SPEED, SAMPLES = 200.0, 512  # nm/s and samples of the forward move, as the study's push
DIRECTIONS = {"+x": (1.0, 0.0), "-x": (-1.0, 0.0), "+y": (0.0, 1.0), "-y": (0.0, -1.0)}


def one_move(pos, stand, d: jax.Array, approach: float, lead_in: float = 0.0) -> dict:
    """The push-like move along ``d`` from ``PLACE`` (reached with ``approach``; the start
    through ``lead_in`` nm along ``d``, as a push reaches it): the true travel's relative error,
    where the move truly starts and ends along ``d`` against where it should, both from the tip's
    true place there (nm: the frame a particle at the place is found in), and the shortfall a
    check arriving at the goal sees (nm)."""
    nowhere = Particles(jnp.full((1, 2), 1e6), jnp.ones(1))  # nothing to touch
    place, key = jnp.asarray(PLACE), jax.random.key(0)
    at_place, _, ready = goto(pos, nowhere, stand, place, key, approach=approach)
    start, goal = place - BACK * d, place + TRAVEL * d
    at_start, _, s = goto(pos, nowhere, ready, start, key, dwell=0.1, approach=lead_in, along=d)
    frac = jnp.arange(1, SAMPLES + 1) / SAMPLES
    wanted = start + frac[:, None] * (goal - start)
    t = s.afm.scanner.t + (BACK + TRAVEL) / SPEED / SAMPLES * jnp.arange(1, SAMPLES + 1)
    path, _, s = pos.drive(nowhere, s, wanted, t, key)
    seen_at, _, _ = goto(pos, nowhere, s, goal, key, approach=approach)
    travel = float((path[-1] - at_start) @ d)
    return {
        "travel_error": travel / (BACK + TRAVEL) - 1.0,
        "start_error_nm": float((at_start - at_place) @ d + BACK),
        "end_error_nm": float((path[-1] - at_place) @ d - TRAVEL),
        "seen_short_nm": float((seen_at - path[-1]) @ d),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--config", type=Path, default=CONFIG, help="a study config (default: configs/study.yaml)"
    )
    parser.add_argument("--scanners", type=int, nargs="*", default=None, help="default: every scanner")
    parser.add_argument("--approach", type=float, default=None, help="nm (default: the study's)")
    parser.add_argument("--lead-in", type=float, default=None, help="nm (default: the study's push)")
    parser.add_argument("--truth-model", action="store_true", help="the truth in place of step A's model")
    args = parser.parse_args()
    cfg = load_config(args.config, StudyConfig)
    draws = job.scanner_draws(cfg)
    # read: the study saved its models there
    models = Output(ROOT / "experiments" / "results" / args.config.stem)
    approach = args.approach or cfg.landmarks.approach_nm
    lead_in = cfg.push.lead_in_nm if args.lead_in is None else args.lead_in
    rows = {}
    for s in range(cfg.scanners) if args.scanners is None else args.scanners:
        surveys, _ = job.prepare_scanner(cfg, args.config, s, draws[s], models, lambda m: None)
        pos, stand = surveys["A+B"].positioner, surveys["A+B"].stand
        if args.truth_model:
            pos = Positioner(pos.afm, pos.afm.scanner.without("drift", "noise", "vibration"), pos.frame)
            still = lambda a: eqx.tree_at(lambda st: st.vibration, a, ())  # the mode left out
            twin = stand.afm.scanner
            stand = Stand(
                stand.afm,
                eqx.tree_at(lambda st: (st.x, st.y), twin, (still(twin.x), still(twin.y))),
                stand.wanted,
            )
        rows[s] = {
            name: one_move(pos, stand, jnp.asarray(d), approach, lead_in) for name, d in DIRECTIONS.items()
        }
        print(
            f"scanner {s:2d}: travel "
            + ", ".join(f"{k} {100 * v['travel_error']:+6.1f} %" for k, v in rows[s].items())
            + " | a check sees it short by "
            + ", ".join(f"{k} {v['seen_short_nm']:+6.1f} nm" for k, v in rows[s].items()),
            flush=True,
        )
    out = ROOT / "experiments" / "results" / "push_shortfall"
    out.mkdir(parents=True, exist_ok=True)
    setup = {
        "config": str(args.config),
        "place_nm": PLACE,
        "back_nm": BACK,
        "travel_nm": TRAVEL,
        "speed_nm_per_s": SPEED,
        "approach_nm": approach,
        "lead_in_nm": lead_in,
        "model": "the truth" if args.truth_model else "step A's",
    }
    name = "shortfall" + ("" if args.config.resolve() == CONFIG else f"_{args.config.stem}")
    name += "" if args.approach is None else f"_approach_{approach:g}"
    name += "" if args.scanners is None else "_scanners_" + "_".join(map(str, args.scanners))
    name += "" if args.lead_in is None else f"_lead_in_{lead_in:g}"
    name += "_truth_model" if args.truth_model else ""
    (out / f"{name}.json").write_text(json.dumps({"setup": setup, "scanners": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
