"""Models fitted on one real record, applied to another of the same actuator: what fitting on
one major loop costs on minor loops.

The two shipped records of one piezo stack (``jaxafm/data/real/README.md``):
``piezo_sine_1hz.dat`` (a 1 Hz sine of constant amplitude: one major loop, repeated) and
``piezo_ramped_sine_1hz.dat`` (the same sine with an amplitude that falls to zero and rises
again: nested minor loops). Each model kind is fitted (``jaxafm fit``'s job) on the first 60 %
of each record, then applied (``jaxafm.model.apply.predict``) to the whole of the other; the
scores are rms and max error in % of the scored record's output range, on the whole record
after its first second (start-up and initial loading curve), with one constant sensor offset
re-estimated (reported: the two records' sensor zeros differ), and on its minor-loop windows alone.

    python experiments/cross_record.py

Writes ``experiments/results/cross_record/`` (``metrics.json``, ``cross_record.png`` and one
fit folder per record).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from jaxafm import plots
from jaxafm.config import ActuatorFitConfig
from jaxafm.identify.fit import error_metrics
from jaxafm.instrument.records import read_record
from jaxafm.jobs import fit as fit_job
from jaxafm.jobs import run_folder
from jaxafm.model.apply import predict
from jaxafm.model.io import read_model_file

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "experiments" / "results" / "cross_record"
MAPPING = {"input_columns": [1], "output_columns": [5], "sample_rate_hz": 200.0, "output_unit": "um"}
SKIP_S = 1.0  # s scored by no one: the sensor start-up and the initial loading curve
RECORDS = {  # name -> (file, history before t = 0, samples of start-up transient, minor-loop windows (s))
    "sine": ("piezo_sine_1hz.dat", [0.0], 20, []),
    "ramped": (
        "piezo_ramped_sine_1hz.dat",
        None,
        10,
        [(15.25, 19.4), (25.4, 29.75), (47.25, 51.35), (55.96, 60.25)],
    ),
}
MODELS = [
    {"name": "pi", "kind": "pi", "operators": 20},
    {"name": "gpi", "kind": "gpi", "operators": 20, "deadzones": 3},
    {"name": "preisach", "kind": "preisach", "levels": 30},
    {"name": "gpi_creep", "kind": "gpi", "operators": 20, "deadzones": 3, "creep": True},
]


def fit(name: str) -> Path:
    """The models fitted on the first 60 % of record ``name``; their folder."""
    file, history, settle, _ = RECORDS[name]
    raw = {"data": {"path": f"builtin:{file}"} | MAPPING, "history_v": history, "settle_s": settle / 200.0}
    cfg = ActuatorFitConfig.model_validate(raw | {"train_fraction": 0.6, "models": MODELS})
    out = OUT / f"fit_{name}"
    with run_folder(out, "fit", Path(__file__), cfg, overwrite=True) as folder:
        fit_job.run(cfg, Path(__file__), folder.output)
    return out


def scores(pred: np.ndarray, record, skip_s: float, windows: list) -> dict:
    """rms and max error in % of the record's output range, after its first ``skip_s`` (the
    sensor's start-up and the initial loading curve): as predicted, and with one constant
    sensor offset re-estimated on the scored part (the two records' sensor zeros differ);
    overall, and on the minor-loop windows alone."""
    keep = record.t >= skip_s
    d, t, e = record.d[keep], record.t[keep], (pred - record.d)[keep]
    span = float(d.max() - d.min())
    offset = float(e.mean())
    out = {"offset_nm": -offset, "raw_rms_error_pct": 100 * float(np.sqrt(np.mean(e**2))) / span}
    out |= {
        f"all_{k}": v for k, v in error_metrics(pred[keep] - offset, d, span).items() if k.endswith("pct")
    }
    if windows:
        inside = np.any([(t >= a) & (t <= b) for a, b in windows], axis=0)
        part = error_metrics(pred[keep][inside] - offset, d[inside], span)
        out |= {f"minor_{k}": v for k, v in part.items() if k.endswith("pct")}
    return out


def main() -> None:
    folders = {name: fit(name) for name in RECORDS}
    records = {
        name: read_record(ROOT / "jaxafm" / "data" / "real" / file, **MAPPING)
        for name, (file, *_) in RECORDS.items()
    }
    metrics, predictions = {}, {}
    head = (
        "model",
        "fitted on",
        "scored on",
        "offset nm",
        "raw rms %",
        "rms %",
        "max %",
        "minor rms %",
        "minor max %",
    )
    print("{:10s} {:9s} {:9s} {:>9s} {:>9s} {:>7s} {:>7s} {:>11s} {:>11s}".format(*head))
    for source, folder in folders.items():
        for spec in MODELS:
            model, _ = read_model_file(folder / f"model_{spec['name']}.json")
            for target, record in records.items():
                _, history, _, windows = RECORDS[target]
                pred = predict(model, record.u, record.t, None if history is None else np.asarray(history))
                s = scores(pred, record, SKIP_S, windows)
                key = f"{spec['name']}_on_{source}_scored_on_{target}"
                metrics |= {f"{key}_{k}": v for k, v in s.items()}
                predictions[(spec["name"], source, target)] = pred
                row = [
                    s.get(f"{part}_{k}_error_pct", np.nan)
                    for part in ("all", "minor")
                    for k in ("rms", "max")
                ]
                line = "{:10s} {:9s} {:9s} {:9.0f} {:9.3f} {:7.3f} {:7.3f} {:11.3f} {:11.3f}"
                print(line.format(spec["name"], source, target, s["offset_nm"], s["raw_rms_error_pct"], *row))
    (OUT / "metrics.json").write_text(json.dumps(metrics, indent=1))
    figure(records["ramped"], predictions, OUT / "cross_record.png")
    print(f"wrote {OUT}")


def figure(record, predictions: dict, path: Path) -> None:
    """The ramped record's first minor-loop window: measured and the GPI models fitted on each
    record, as loops and as errors over time."""
    a, b = RECORDS["ramped"][3][0]
    w = (record.t >= a - 1) & (record.t <= b + 1)
    fig, (ax_loop, ax_err) = plots.subplots(1, 2, figsize=(13, 5.5))
    ax_loop.plot(record.u[w], record.d[w] / 1e3, color="0.6", lw=2.5, label="measured")
    keep = record.t >= SKIP_S
    span = float(record.d[keep].max() - record.d[keep].min())
    for source in ("sine", "ramped"):
        pred = predictions[("gpi", source, "ramped")]
        pred = pred - np.mean((pred - record.d)[keep])  # the offset the table re-estimates
        ax_loop.plot(record.u[w], pred[w] / 1e3, lw=0.9, label=f"gpi fitted on the {source} record")
        ax_err.plot(
            record.t[w],
            100 * (pred[w] - record.d[w]) / span,
            lw=0.9,
            label=f"gpi fitted on the {source} record",
        )
    ax_loop.set(
        xlabel="input u [V]",
        ylabel="output d [µm]",
        title=f"ramped record, {a - 1:g}-{b + 1:g} s: minor loops",
    )
    ax_loop.legend(fontsize=8)
    ax_err.axvspan(a, b, color="0.9", label="amplitude falling")
    ax_err.set(xlabel="time [s]", ylabel="model - measured [% of output range]", title="error over time")
    ax_err.grid(True, alpha=0.3)
    ax_err.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    main()
