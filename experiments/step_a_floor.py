"""Where step A's tip-path error on the independent generator comes from: the data, or the model.

For a few of ``experiments/step_a_independent.py``'s cases (the same draws), numbers in pixels,
each the rms of the tip path against the generator's truth after the one rigid motion no image
can see, for each model class step A fits (``--classes``: the generalised PI, ``gpi``, and the
Preisach plane, ``preisach``):

- **step A**: the ``jaxafm calibrate`` fit of the case with that class as its richest model (for
  ``gpi`` as the study runs it), over every pixel, and split into the pixels inside the features'
  chords' reach (where the images hold the path) and those outside it (the image's margins,
  where the model extrapolates); beside it the held-out features' residual;
- **floor**: the richest model of the class step A can fit (generalised PI: 16 plays, 3 dead
  zones a side inside the reach; Preisach: 16 levels over the drive; every effect: creep,
  coupling, bow, drift, rate dependence, and the generalised PI's asymmetry) fitted by
  Levenberg-Marquardt straight to the true tip path, with the rigid motion free: no image, no
  feature finding, no held-out split. What no identification from images can beat;
- **floor, hysteresis only** (``gpi``): the same, on the case drawn again with the generator's
  lag, creep, coupling and drift switched off, its Preisach hysteresis alone.

Each fit's rate-dependence lag of the x axis (a speed series' fast axis) is kept beside the
generator's drive lag: whether the model, fitted to the true path itself, holds the true lag;
and its creep (per decade, and its onset when fitted) beside the generator's.

With ``--creep-onset`` step A and the floor fit creep's onset too (``creep_onset`` in the
model, keys ending ``_creep_onset``), and the floor is fitted once more to the case drawn without
the generator's creep (``..._no_creep``, the fixed-shape creep): what the creep's shape costs the
fitted lag.

    python experiments/step_a_floor.py [--seeds 100 106 116] [--classes gpi preisach] [--steps 300]
        [--no-floor] [--creep-onset]

writes experiments/results/step_a_independent/floor.json (the tables of docs/step_a.md); a class's
numbers replace those of an earlier run, the other class's stay.
"""

from __future__ import annotations

import argparse
import json
import time

import benchutil  # noqa: F401  (puts tests/ on sys.path)
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import step_a_independent as S

from jaxafm.identify.fit import clear_caches
from jaxafm.identify.scan_model import ScanModelSpec, feature_reach, nominal_scan_model
from jaxafm.jobs.calibrate import identification_metrics, identify_model

#: the richest model of each class step A may fit (as the study's MODEL and PREISACH, with every
#: effect): kind, effects, plays or levels, dead zones a side
RICHEST = {
    "gpi": ("gpi", ("asymmetry", "creep", "coupling", "bow", "drift", "rate_dependence"), 16, 3),
    "preisach": ("preisach", ("creep", "coupling", "bow", "drift", "rate_dependence"), 16, 0),
}
#: step A's configured richest model of each class
CONFIGURED = {"gpi": S.MODEL, "preisach": S.PREISACH}
#: the generator's effects besides hysteresis, switched off for the hysteresis-only floor
HYSTERESIS_ONLY = {"tau_s": 0, "creep_per_decade": 0, "coupling": 0, "drift_nm_per_s": 0, "bow_per_nm": 0}


def floor(scans, case, steps: int, model_class: str = "gpi", creep_onset: bool = False) -> dict:
    """The richest model of ``model_class`` fitted straight to the case's true tip path (module
    docstring): its rms (px) over every pixel, inside and outside the features' reach, and the
    solver's steps."""
    kind, effects, size, zones = RICHEST[model_class]
    reach = feature_reach(scans)
    spec = ScanModelSpec(
        kind, effects, size, zones, size, rotation=None, deadzone_reach=reach, creep_onset=creep_onset
    )
    raw, rebuild = nominal_scan_model(scans[0], spec, scans).as_float64().free_parameters(scans[0])
    true = [
        jnp.asarray(np.stack([s.truth["tip_trace_nm"], s.truth["tip_retrace_nm"]])) for s in case["scans"]
    ]
    pixel = scans[0].raster.pixel_size[0]

    def residuals(p, _):
        model, (turn, dx, dy) = rebuild(p[0]), p[1]
        c, s = jnp.cos(turn), jnp.sin(turn)
        moved = lambda a: a @ jnp.asarray([[c, s], [-s, c]]) + jnp.stack([dx, dy])
        return jnp.concatenate(
            [(moved(jnp.stack(model.paths(scan))) - t).ravel() / pixel for scan, t in zip(scans, true)]
        )

    solver = optx.LevenbergMarquardt(rtol=1e-8, atol=1e-8)
    sol = optx.least_squares(residuals, solver, (raw, jnp.zeros(3)), max_steps=steps, throw=False)
    model = rebuild(sol.value[0])
    inside, outside, _ = S.path_error_by_reach(model, scans, case)
    return {
        "all_px": S.path_error(model, scans, case),
        "inside_px": inside,
        "outside_px": outside,
        "x_rate_lag_s": _x_lag(model),
        **_x_creep(model),
        "steps": int(sol.stats["num_steps"]),
    }


def _x_lag(model) -> float | None:
    """The fitted rate-dependence lag (s) of the stage's x axis (the 0-degree scans' fast axis)."""
    lag = model.scanner.x.rate_dependence
    return None if lag is None else float(lag.tau)


def _x_creep(model) -> dict:
    """The fitted creep of the stage's x axis: per decade (fraction) and its onset (s)."""
    creep = model.scanner.x.creep
    if creep is None:
        return {}
    onset = None if creep.onset is None else float(creep.onset)
    return {"x_creep_per_decade": float(creep.per_decade), "x_creep_onset_s": onset}


def step_a(spec: dict, pixels: int, kind: str, model_class: str, creep_onset: bool = False) -> dict:
    """Step A's fit of the case with ``model_class`` as its richest model (its creep's onset
    fitted too with ``creep_onset``), scored (module docstring)."""
    jax.clear_caches()
    clear_caches()
    model = CONFIGURED[model_class] | ({"creep_onset": True} if creep_onset else {})
    case, scans, cfg = S.draw_and_read(spec, pixels, kind, model=model)
    began = time.perf_counter()
    ident = identify_model(scans, cfg.models[0], cfg.solver, cfg.grating, log=lambda *_: None)
    inside, outside, share = S.path_error_by_reach(ident.model, scans, case)
    held_out = identification_metrics(ident)["held_out_rms_nm"]
    size = ident.spec.levels if ident.spec.kind == "preisach" else ident.spec.operators
    return {
        "all_px": S.path_error(ident.model, scans, case),
        "inside_px": inside,
        "outside_px": outside,
        "inside_share": share,
        "held_out_px": held_out / scans[0].raster.pixel_size[0],
        "plausible": ident.plausible,
        "model": f"{ident.spec.kind} {size} + {', '.join(ident.spec.effects)}",
        "edge_delay_s": float(ident.model.edge_delay),
        "x_rate_lag_s": _x_lag(ident.model),
        **_x_creep(ident.model),
        "seconds": time.perf_counter() - began,
    }


def _suffix(model_class: str, creep_onset: bool) -> str:
    """The ending of a class's keys in floor.json: none for ``gpi``, ``_preisach`` for the
    Preisach class; then ``_creep_onset`` with the creep's onset fitted."""
    return ("" if model_class == "gpi" else f"_{model_class}") + ("_creep_onset" if creep_onset else "")


def run(
    seed: int,
    steps: int,
    pixels: int,
    kind: str,
    model_class: str,
    floors: bool = True,
    creep_onset: bool = False,
) -> dict:
    """One case's numbers for ``model_class`` (module docstring), keyed as floor.json keeps them:
    ``step_a``, ``floor``, ``floor_hysteresis_only`` for ``gpi``; ``step_a_preisach``,
    ``floor_preisach`` for ``preisach``; step A's alone unless ``floors``. With ``creep_onset``
    the model's creep onset is fitted too (keys ending ``_creep_onset``), and the class's floor is
    also fitted to the case drawn without the generator's creep (``floor..._no_creep``)."""
    spec = next(c for c in S.plan(20, 3) if c["seed"] == seed)
    out = {"seed": seed, "rates_hz": list(spec["rates"]), "angles_deg": list(spec["angles"])}
    suffix = _suffix(model_class, creep_onset)
    out["step_a" + suffix] = step_a(spec, pixels, kind, model_class, creep_onset)
    if not floors:
        return out
    case, scans, _ = S.draw_and_read(spec, pixels, kind)
    out["true_rate_lag_s"] = case["truth"]["scanner"]["rate_tau_s"]
    out["true_creep_per_decade"] = case["truth"]["scanner"]["creep_per_decade"]
    out["floor" + suffix] = floor(scans, case, steps, model_class, creep_onset)
    if creep_onset:
        case, scans, _ = S.draw_and_read(spec, pixels, kind, magnitudes={"creep_per_decade": 0})
        out["floor" + suffix.replace("_creep_onset", "_no_creep")] = floor(scans, case, steps, model_class)
    elif model_class == "gpi":
        case, scans, _ = S.draw_and_read(spec, pixels, kind, magnitudes=HYSTERESIS_ONLY)
        out["floor_hysteresis_only"] = floor(scans, case, steps)
    return out


def main() -> None:
    a = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    a.add_argument("--seeds", type=int, nargs="+", default=[100, 106, 116])
    a.add_argument("--classes", nargs="+", choices=sorted(RICHEST), default=["gpi"])
    a.add_argument("--steps", type=int, default=300, help="Levenberg-Marquardt steps of each floor fit")
    a.add_argument("--pixels", type=int, default=64)
    a.add_argument("--kind", default="fine")
    a.add_argument("--no-floor", action="store_true", help="fit step A alone, keep the floors floor.json has")
    a.add_argument(
        "--creep-onset",
        action="store_true",
        help="fit creep's onset too, and the floor also without the generator's creep",
    )
    args = a.parse_args()
    out = S.OUT / "floor.json"
    for seed in args.seeds:
        for model_class in args.classes:
            r = run(
                seed, args.steps, args.pixels, args.kind, model_class, not args.no_floor, args.creep_onset
            )
            rows = (
                json.loads(out.read_text()) if out.exists() else []
            )  # read again: another run may have written
            earlier = next((row for row in rows if row["seed"] == seed), {})
            rows = [row for row in rows if row["seed"] != seed] + [earlier | r]
            out.write_text(json.dumps(sorted(rows, key=lambda row: row["seed"]), indent=1, default=float))
            suffix = _suffix(model_class, args.creep_onset)
            a_, f_ = r["step_a" + suffix], (earlier | r)["floor" + suffix]
            print(
                f"seed {seed}, {model_class}: step A {a_['all_px']:.2f} px (inside the reach "
                f"{a_['inside_px']:.2f}, outside {a_['outside_px'] or 0:.2f}, held-out features "
                f"{a_['held_out_px']:.2f}); floor {f_['all_px']:.2f} px",
                flush=True,
            )


if __name__ == "__main__":
    main()
