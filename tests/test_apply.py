"""Applying what was fitted: self-describing model files, `jaxafm predict` and `jaxafm compensate`.

Truth from outside the code under test: the fit table's own held-out numbers (predict must
reproduce them exactly), the wanted trajectory (a model driven by its own compensating drive
must follow it: model(inverse(x)) = x), and hand-made files that break the rules."""

import json
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from jaxafm import default_scanner
from jaxafm.cli import app
from jaxafm.model.hysteresis import Linear, PrandtlIshlinskii, Preisach
from jaxafm.model.io import describe, read_model_file, save_model

runner = CliRunner()
CYCLE = np.concatenate([np.linspace(-10, 10, 201), np.linspace(10, -10, 201)])  # V, one major loop
CYCLE_T = np.arange(len(CYCLE)) * 0.005  # s


def invoke(*args):
    result = runner.invoke(app, [str(a) for a in args])
    return result


def write(path: Path, doc: dict) -> Path:
    path.write_text(yaml.safe_dump(doc))
    return path


MODELS = {
    "linear": lambda: Linear(jnp.asarray(500.0), jnp.asarray(20.0)),
    "pi": lambda: PrandtlIshlinskii.with_loop_width(8, 20.0, 10_000.0, 0.15),
    "gpi": lambda: default_scanner().x.hysteresis,
    "preisach": lambda: Preisach.uniform(12, -10.0, 10.0, total=5_000.0),
    "gpi_creep": lambda: default_scanner().x,  # an Axis: generalised PI + logarithmic creep
}


def saved(kind: str, folder: Path) -> Path:
    """``kind``'s model saved with what ``jaxafm fit`` records: the ranges of a full cycle."""
    model = MODELS[kind]()
    from jaxafm.model.apply import predict

    d = predict(model, CYCLE, CYCLE_T)
    path = folder / f"model_{kind}.json"
    save_model(model, path, describe(model, CYCLE, d, source="a hand-made major loop"))
    return path


@pytest.mark.parametrize("kind", sorted(MODELS))
def test_compensate_then_predict_round_trips(tmp_path, kind):
    """Per model kind: the drive `compensate` writes for a triangle of decreasing amplitude
    inside the fitted range, read back by `predict` (as a controller would load it), puts the
    model on the wanted trajectory within 0.05 % of the fitted output range (the goal; the CSV's
    10 significant digits limit it far below that)."""
    model = saved(kind, tmp_path)
    lo, hi = read_model_file(model)[1]["output_range_nm"][0]
    amplitudes = [0.3 * (hi - lo) * f for f in (1.0, 0.6, 0.3, 0.1)]  # reachable on every branch
    triangle = {"amplitudes_nm": amplitudes, "period_s": 0.5, "sample_rate_hz": 200.0}
    cfg = write(tmp_path / "c.yaml", {"model": model.name, "trajectory": {"triangle": triangle}})
    result = invoke("compensate", cfg, "--out", tmp_path / "comp")
    assert result.exit_code == 0, result.output
    metrics = json.loads((tmp_path / "comp" / "metrics.json").read_text())
    assert metrics["method"] == ("analytic" if kind in ("linear", "pi", "gpi") else "numerical")
    drive = {"path": "comp/drive.csv", "delimiter": ",", "input_columns": ["u_v"], "time_column": "t_s"}
    pcfg = write(tmp_path / "p.yaml", {"model": model.name, "data": drive})
    result = invoke("predict", pcfg, "--out", tmp_path / "pred")
    assert result.exit_code == 0, result.output
    predicted = np.genfromtxt(tmp_path / "pred" / "prediction.csv", delimiter=",", names=True)
    tracking = np.genfromtxt(tmp_path / "comp" / "tracking.csv", delimiter=",", names=True)
    cycle = len(predicted) - len(tracking)
    np.testing.assert_allclose(predicted["t_s"][cycle:], tracking["t_s"])
    error = np.abs(predicted["predicted_nm"][cycle:] - tracking["wanted_nm"])
    assert error.max() < 0.0005 * (hi - lo), f"{kind}: worst {error.max():.3g} nm"
    u = np.genfromtxt(tmp_path / "comp" / "drive.csv", delimiter=",", names=True)["u_v"]
    assert u[0] == -10.0 and u[cycle - 1] == 10.0  # the cycle {u2, u1} over the fitted input range


def test_predict_reproduces_the_fit_tables_held_out_numbers(tmp_path):
    """`fit` on the shipped real record, then `predict` of its held-out part with the saved model:
    the same rms and max errors, to the last bit (the model file carries the history it assumed)."""
    record = {"path": "builtin:piezo_sine_1hz.dat", "input_columns": [1], "output_columns": [5]}
    record |= {"sample_rate_hz": 200.0, "output_unit": "um"}
    fit = {
        "data": record,
        "history_v": [0.0],
        "train_fraction": 0.6,
        "models": [{"name": "pi", "kind": "pi"}],
    }
    fit["models"][0] |= {"operators": 8, "max_steps": 200}
    result = invoke("fit", write(tmp_path / "fit.yaml", fit), "--out", tmp_path / "fit")
    assert result.exit_code == 0, result.output
    cfg = {"model": "fit/model_pi.json", "data": record, "evaluate_from": 0.6}
    result = invoke("predict", write(tmp_path / "p.yaml", cfg), "--out", tmp_path / "pred")
    assert result.exit_code == 0, result.output
    fitted = json.loads((tmp_path / "fit" / "metrics.json").read_text())
    predicted = json.loads((tmp_path / "pred" / "metrics.json").read_text())
    for key in ("rms_error_nm", "max_error_nm", "rms_error_pct", "max_error_pct"):
        assert predicted[key] == fitted[f"pi_heldout_{key}"], key
    about = read_model_file(tmp_path / "fit" / "model_pi.json")[1]
    assert about["history_v"] == [0.0] and about["units"] == {"input": "V", "output": "nm", "time": "s"}
    assert about["input_range_v"][0][0] >= 0 and about["input_range_v"][0][1] <= 3.6 + 1e-9
    assert "piezo_sine_1hz.dat" in about["fitted_to"]["source"]


def test_predict_warns_with_the_share_outside_the_fitted_range(tmp_path):
    """A record whose input goes beyond the fitted range by construction (a quarter of its
    samples above +10 V) gets a warning that says so."""
    model = saved("pi", tmp_path)
    t = np.arange(400) * 0.01
    u = np.where(np.arange(400) < 300, 8 * np.sin(2 * np.pi * t), 12.0 + np.arange(400) * 1e-3)
    np.savetxt(tmp_path / "r.csv", np.c_[t, u], delimiter=",", header="t_s,u_v", comments="")
    drive = {"path": "r.csv", "delimiter": ",", "input_columns": ["u_v"], "time_column": "t_s"}
    result = invoke(
        "predict", write(tmp_path / "p.yaml", {"model": model.name, "data": drive}), "--out", tmp_path / "o"
    )
    assert result.exit_code == 0, result.output
    assert "WARNING: 25.0 % of the record's input samples lie outside the range" in result.output


@pytest.mark.parametrize(
    "trajectory, match",
    [
        ({"triangle": {"amplitudes_nm": [9000.0]}}, r"outside the output range the model was fitted on"),
        ("t,x\n0,1\n1,2\n", r"must name the columns with their units, t_s and x_<unit>"),
        ("t_s,x_nm\n0,1\n0,2\n", r"increasing t_s"),
    ],
    ids=["beyond-the-range", "no-units", "time-not-increasing"],
)
def test_compensate_refuses_a_trajectory_it_cannot_trust(tmp_path, trajectory, match):
    model = saved("pi", tmp_path)
    if isinstance(trajectory, str):
        (tmp_path / "x.csv").write_text(trajectory)
        trajectory = {"path": "x.csv"}
    result = invoke("compensate", write(tmp_path / "c.yaml", {"model": model.name, "trajectory": trajectory}))
    assert result.exit_code == 2 and "Traceback" not in result.output
    assert __import__("re").search(match, result.output), result.output
    assert not (tmp_path / "runs").exists()


def test_model_files_that_cannot_be_used_are_refused(tmp_path):
    """Another format version, and a model that does not say its fitted range (compensate needs
    it to know where the model may be trusted)."""
    path = saved("pi", tmp_path)
    doc = json.loads(path.read_text())
    (tmp_path / "v9.json").write_text(json.dumps(doc | {"version": 9}))
    with pytest.raises(ValueError, match="version 9 is not one this jaxafm reads"):
        read_model_file(tmp_path / "v9.json")
    save_model(MODELS["pi"](), tmp_path / "bare.json")  # no ranges
    cfg = {"model": "bare.json", "trajectory": {"triangle": {"amplitudes_nm": [100.0]}}}
    result = invoke("compensate", write(tmp_path / "c.yaml", cfg))
    assert result.exit_code == 2 and "does not say the input and output range" in result.output


@pytest.mark.parametrize(
    "command, changes, names",
    [
        ("predict", {"evaluate_from": ".nan"}, ["evaluate_from"]),
        ("predict", {"evaluate_from": 1.0}, ["evaluate_from", "1.0"]),
        ("predict", {"model": "missing.json"}, ["model", "missing.json", "does not exist"]),
        ("predict", {"model": "notes.txt"}, ["model", "notes.txt", "not JSON"]),
        ("predict", {"model": "negative.json"}, ["model", "negative.json", "monotone"]),
        (
            "predict",
            {"data": {"path": "r.csv", "delimiter": ",", "input_columns": ["t_s"], "time_column": "t_s"}},
            ["t_s", "mapped twice"],
        ),
        ("compensate", {"method": "newton"}, ["method", "newton"]),
        ("compensate", {"trajectory": {"triangle": {"amplitudes_nm": [-5.0]}}}, ["amplitudes_nm", "-5.0"]),
        ("compensate", {"trajectory": {}}, ["trajectory", "exactly one of"]),
        ("compensate", {"model": "negative.json"}, ["model", "negative.json", "monotone"]),
        ("compensate", {"cycle_s": 0}, ["cycle_s", "0"]),
        ("compensate", {"check_models": ["missing.json"]}, ["model", "missing.json"]),
    ],
    ids=lambda v: v if isinstance(v, str) else None,
)
def test_bad_input_to_predict_and_compensate(tmp_path, command, changes, names):
    """Each refused before the output folder is made, with the key or file and the value named,
    and no file of the user's changed."""
    model = saved("pi", tmp_path)
    doc = json.loads(model.read_text())
    doc["model"]["fields"]["weights"]["array"][0] = -1e4  # partial sums < 0: not monotone
    (tmp_path / "negative.json").write_text(json.dumps(doc))
    (tmp_path / "notes.txt").write_text("my notes")
    t = np.arange(100) * 0.01
    np.savetxt(tmp_path / "r.csv", np.c_[t, np.sin(t)], delimiter=",", header="t_s,u_v", comments="")
    base = {
        "predict": {
            "model": model.name,
            "data": {"path": "r.csv", "delimiter": ",", "input_columns": ["u_v"]},
        },
        "compensate": {"model": model.name, "trajectory": {"triangle": {"amplitudes_nm": [100.0]}}},
    }[command]
    if command == "predict":
        base["data"]["time_column"] = "t_s"
    text = yaml.safe_dump(base | changes).replace("'.nan'", ".nan")
    (tmp_path / "c.yaml").write_text(text)
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    result = invoke(command, tmp_path / "c.yaml", "--out", tmp_path / "out")
    assert result.exit_code == 2 and "Traceback" not in result.output, result.output
    for name in names:
        assert name in result.output, (name, result.output)
    assert {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()} == before
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("method", ["analytic", "numerical"])
def test_a_scanner_follows_its_compensated_raster(tmp_path, method):
    """A two-axis scanner (generalised PI with creep on each axis, coupling, bow, mean drift)
    saved with the ranges step A records, a raster trajectory: the scanner driven by the written
    drive.csv (read back by `predict`) follows the raster within 0.05 % of its fitted range."""
    model = default_scanner()
    u = np.stack([CYCLE, CYCLE[::-1]], -1) * 0.8  # V: +-8 V on both axes
    from jaxafm.model.apply import predict

    d = predict(model, u, CYCLE_T)
    path = tmp_path / "model_scanner.json"
    save_model(model, path, describe(model, u, d, source="a hand-made cycle"))
    span = np.ptp(d, axis=0)
    raster = {"size_nm": [float(0.4 * s) for s in span], "pixels": 24, "lines": 6, "line_rate_hz": 4.0}
    cfg = {"model": path.name, "trajectory": {"raster": raster}, "method": method}
    result = invoke("compensate", write(tmp_path / "c.yaml", cfg), "--out", tmp_path / "comp")
    assert result.exit_code == 0, result.output
    drive = {
        "path": "comp/drive.csv",
        "delimiter": ",",
        "input_columns": ["ux_v", "uy_v"],
        "time_column": "t_s",
    }
    result = invoke(
        "predict", write(tmp_path / "p.yaml", {"model": path.name, "data": drive}), "--out", tmp_path / "p"
    )
    assert result.exit_code == 0, result.output
    predicted = np.genfromtxt(tmp_path / "p" / "prediction.csv", delimiter=",", names=True)
    tracking = np.genfromtxt(tmp_path / "comp" / "tracking.csv", delimiter=",", names=True)
    cycle = len(predicted) - len(tracking)
    for axis, k in (("x", 0), ("y", 1)):
        error = np.abs(predicted[f"predicted{axis}_nm"][cycle:] - tracking[f"wanted_{axis}_nm"])
        assert error.max() < 0.0005 * span[k], f"{method} {axis}: worst {error.max():.3g} nm"
