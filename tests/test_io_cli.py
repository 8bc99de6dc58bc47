"""Records, configs, saved models, the command line and package hygiene: conversions, round trips,
clear errors, and what importing jaxafm does (no JAX for configs and --help, no matplotlib state)."""

import json
import subprocess
import sys
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from typer.testing import CliRunner

from jaxafm import RateDependence, default_scanner
from jaxafm.cli import app
from jaxafm.config import ConfigError, load_config
from jaxafm.instrument.records import read_record
from jaxafm.model.io import load_model, save_model

runner = CliRunner()


def write(path, text):
    path.write_text(text)
    return path


# ---------------------------------------------------------------- records


def test_record_with_header_needs_no_mapping(tmp_path):
    f = write(tmp_path / "r.csv", "t,u,d\n0,0.5,10\n0.01,0.6,11\n0.02,0.7,12\n")
    r = read_record(f, delimiter=",")
    np.testing.assert_allclose(r.t, [0, 0.01, 0.02])
    np.testing.assert_allclose(r.d, [10, 11, 12])


def test_record_units_converted_to_nm_and_volts(tmp_path):
    f = write(tmp_path / "r.dat", "500 0 -1.5\n600 0 -1.25\n")
    r = read_record(
        f, input_columns=[1], output_columns=[3], sample_rate_hz=10, input_unit="mV", output_unit="um"
    )
    np.testing.assert_allclose(r.u, [0.5, 0.6])
    np.testing.assert_allclose(r.d, [-1500, -1250])
    np.testing.assert_allclose(r.t, [0, 0.1])
    assert "um -> nm" in r.meta["converted"]


def test_record_two_axes_by_header(tmp_path):
    f = write(tmp_path / "r.txt", "t ux uy x y\n0 1 2 3 4\n1 2 3 4 5\n")
    r = read_record(f)
    assert r.u.shape == (2, 2) and r.d.shape == (2, 2)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(input_columns=[1], output_columns=[2], sample_rate_hz=10), "output_unit is missing"),
        (dict(input_columns=[1], output_columns=[2], sample_rate_hz=10, output_unit="furlong"), "furlong"),
        (dict(input_columns=[1], output_columns=[9], sample_rate_hz=10, output_unit="nm"), "column 9"),
        (
            dict(input_columns=[1], output_columns=[2], output_unit="nm"),
            "time_column or sample_rate_hz|exactly one",
        ),
        (dict(input_columns=[0], output_columns=[2], sample_rate_hz=10, output_unit="nm"), "1-based"),
    ],
)
def test_record_bad_mapping(tmp_path, kwargs, match):
    f = write(tmp_path / "r.dat", "1 2\n3 4\n")
    with pytest.raises(ValueError, match=match):
        read_record(f, **kwargs)


def test_record_errors_name_the_problem(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        read_record(tmp_path / "missing.dat")
    f = write(tmp_path / "nan.dat", "1 2\nnan 4\n")
    with pytest.raises(ValueError, match="row 2"):
        read_record(f, input_columns=[1], output_columns=[2], sample_rate_hz=1, output_unit="nm")
    f = write(tmp_path / "nohead.dat", "a b c\n1 2 3\n")
    with pytest.raises(ValueError, match="does not name"):
        read_record(f)
    f = write(tmp_path / "short.dat", "".join(f"{i} {i}\n" for i in range(15)))
    r = read_record(f, input_columns=[1], output_columns=[2], sample_rate_hz=1, output_unit="nm")
    with pytest.raises(ValueError, match="too few"):
        r.split(0.5)


# ---------------------------------------------------------------- configs

GOOD = """
simulate: {duration_s: 3, sample_rate_hz: 100, modulation_period_s: 1.5}
models:
  - {name: line, kind: linear}
  - {name: pi, kind: pi, operators: 6}
output: {out}
"""


@pytest.mark.parametrize(
    "text, match",
    [
        ("simulate: {}\nmodels: [{name: a, kind: pi, operatorz: 3}]\n", r"models\.0\.operatorz: unknown key"),
        (
            "simulate: {}\nmodels: [{name: a, kind: preisach, levels: 1}]\n",
            r"models\.0\.levels.*greater than or equal to 2.*got 1",
        ),
        ("simulate: {effects: [gravity]}\nmodels: [{name: a, kind: pi}]\n", "unknown effect 'gravity'"),
        ("simulate: {effects: [drift]}\nmodels: [{name: a, kind: pi}]\n", "not one of the simulated axis"),
        ("models: [{name: a, kind: pi}]\n", "exactly one of 'data'"),
        ("simulate: {}\nmodels: [{name: a, kind: pi, solver: magic.newton}]\n", r"models\.0\.solver"),
        ("simulate: {}\ntrain_fraction: 1.5\nmodels: [{name: a, kind: pi}]\n", "train_fraction"),
        ("- just\n- a list\n", "mapping"),
    ],
)
def test_config_errors_name_key_and_value(tmp_path, text, match):
    f = write(tmp_path / "c.yaml", text)
    with pytest.raises(ConfigError, match=match) as e:
        load_config(f)
    assert str(f) in str(e.value)


@pytest.mark.parametrize(
    "config, command, schema",
    [
        ("calibrate_nanosurf_square_pits.yaml", "calibrate", "CalibrateConfig"),
        ("study.yaml", "study", "StudyConfig"),
        ("paper.yaml", "run", "RunConfig"),
    ],
)
def test_a_config_read_without_its_schema_says_which_command_it_is_for(config, command, schema):
    """load_config without a schema reads a file as ``jaxafm fit``'s; a shipped config of another
    command fails that and the error says which command's config it is and how to read it."""
    with pytest.raises(ConfigError) as e:
        load_config(ROOT / "configs" / config)
    message = str(e.value)
    assert f"valid config of `jaxafm {command}` (load_config(path, {schema}))" in message
    assert message.count("valid config of") == 1 and " and `jaxafm" not in message


def test_a_broken_fit_config_gets_no_other_commands_hint(tmp_path):
    f = write(tmp_path / "c.yaml", "simulate: {}\ntrain_fraction: 1.5\nmodels: [{name: a, kind: pi}]\n")
    with pytest.raises(ConfigError, match="train_fraction") as e:
        load_config(f)
    assert "valid config of" not in str(e.value)


def test_config_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        load_config(tmp_path / "nope.yaml")


# ---------------------------------------------------------------- saved models


def test_saved_scanner_round_trips(tmp_path):
    s = default_scanner()
    save_model(s, tmp_path / "s.json")
    back = load_model(tmp_path / "s.json")
    t = jnp.linspace(0, 1, 50)
    u = jnp.stack([5 * jnp.sin(6 * t), 5 * jnp.cos(6 * t)], -1)
    key = jax.random.key(3)
    run = eqx.filter_jit(lambda m, u, t, k: m(u, t, k))  # compiled once for both (the same structure)
    np.testing.assert_array_equal(np.asarray(run(s, u, t, key)), np.asarray(run(back, u, t, key)))
    assert back.effects == s.effects


def test_a_saved_creep_keeps_its_onset_and_a_file_without_one_reads_as_none(tmp_path):
    from jaxafm.model.effects import Creep

    s = default_scanner()
    onset = eqx.tree_at(lambda m: m.x.creep, s, s.x.creep.with_onset(0.3))
    save_model(onset, tmp_path / "s.json")
    back = load_model(tmp_path / "s.json").x.creep
    assert float(back.onset) == pytest.approx(0.3, rel=1e-15)
    np.testing.assert_array_equal(np.asarray(back.weights), np.asarray(onset.x.creep.weights))
    saved = json.loads((tmp_path / "s.json").read_text())
    del saved["model"]["fields"]["x"]["fields"]["creep"]["fields"]["onset"]  # as written before onsets
    write(tmp_path / "old.json", json.dumps(saved))
    assert isinstance(load_model(tmp_path / "old.json").x.creep, Creep)
    assert load_model(tmp_path / "old.json").x.creep.onset is None


def test_a_saved_lag_keeps_its_hold_and_a_version_3_file_reads_as_the_zero_hold(tmp_path):
    lagged = eqx.tree_at(
        lambda s: s.x.rate_dependence,
        default_scanner(),
        RateDependence(jnp.asarray(2e-3), hold="linear"),
        is_leaf=lambda v: v is None,
    )
    save_model(lagged, tmp_path / "s.json")
    assert load_model(tmp_path / "s.json").x.rate_dependence.hold == "linear"
    saved = json.loads((tmp_path / "s.json").read_text())
    lag = saved["model"]["fields"]["x"]["fields"]["rate_dependence"]["fields"]
    del lag["hold"]
    saved["version"] = 3  # as a version-3 file: its lags have no hold
    write(tmp_path / "old.json", json.dumps(saved))
    assert load_model(tmp_path / "old.json").x.rate_dependence.hold == "zero"


def test_load_model_rejects_other_files(tmp_path):
    f = write(tmp_path / "x.json", json.dumps({"format": "other"}))
    with pytest.raises(ValueError, match="not a saved jaxafm model"):
        load_model(f)


# ---------------------------------------------------------------- command line


def test_cli_fit_writes_metrics_with_units(tmp_path):
    out = tmp_path / "run"
    cfg = write(tmp_path / "c.yaml", GOOD.replace("{out}", str(out)))
    result = runner.invoke(app, ["fit", str(cfg)])
    assert result.exit_code == 0, result.output
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["pi_heldout_rms_error_pct"] < metrics["line_heldout_rms_error_pct"]
    assert {"output_range_nm", "pi_fit_s", "pi_heldout_max_error_nm"} <= set(metrics)
    assert (out / "fit.png").stat().st_size > 0
    assert load_model(out / "model_pi.json").weights.shape == (6,)
    assert "held-out rms" in result.output


def test_cli_never_overwrites_without_asking(tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    keep = write(out / "precious.txt", "keep me")
    cfg = write(tmp_path / "c.yaml", GOOD.replace("{out}", str(out)))
    result = runner.invoke(app, ["fit", str(cfg)])
    assert result.exit_code == 2
    assert "--overwrite" in result.output
    assert keep.read_text() == "keep me"


def test_cli_bad_config_is_a_message_not_a_traceback(tmp_path):
    cfg = write(tmp_path / "c.yaml", "simulate: {}\nmodels: [{name: a, kind: pi, levls: 3}]\n")
    result = runner.invoke(app, ["fit", str(cfg)])
    assert result.exit_code == 2
    assert "levls" in result.output and "Traceback" not in result.output


# ---------------------------------------------------------------- review findings stay fixed


def test_invalid_run_creates_no_output_folder(tmp_path):
    out = tmp_path / "never"
    cfg = write(tmp_path / "c.yaml", GOOD.replace("{out}", str(out)) + "settle_s: 100\n")
    result = runner.invoke(app, ["fit", str(cfg)])
    assert result.exit_code == 2 and "settle_s" in result.output
    assert not out.exists()


@pytest.mark.parametrize("history, match", [("[]", "history_v"), ("[.nan]", "finite")])
def test_config_history_checked(tmp_path, history, match):
    f = write(tmp_path / "c.yaml", f"simulate: {{}}\nhistory_v: {history}\nmodels: [{{name: a, kind: pi}}]\n")
    with pytest.raises(ConfigError, match=match):
        load_config(f)


def test_commented_header_and_sample_rate(tmp_path):
    f = write(tmp_path / "r.txt", "# t u d\n0 0.5 10\n1 0.6 11\n")
    r = read_record(f)
    np.testing.assert_allclose(r.u, [0.5, 0.6])
    np.testing.assert_allclose(r.t, [0, 1])
    np.testing.assert_allclose(read_record(f, sample_rate_hz=4.0).t, [0, 0.25])


def test_fit_refuses_two_axis_record(tmp_path):
    rows = "".join(f"{i * 0.1} {np.sin(i)} {np.cos(i)} {i} {2 * i}\n" for i in range(60))
    write(tmp_path / "xy.txt", "t ux uy x y\n" + rows)
    cfg = write(
        tmp_path / "c.yaml",
        f"data: {{path: xy.txt}}\nmodels: [{{name: a, kind: pi}}]\noutput: {tmp_path / 'o'}\n",
    )
    result = runner.invoke(app, ["fit", str(cfg)])
    assert result.exit_code == 2 and "one axis" in result.output


def test_axis_needs_increasing_times():
    from jaxafm import Axis, Linear

    ax = Axis(Linear(jnp.asarray(1.0), jnp.asarray(0.0)))
    with pytest.raises(ValueError, match="times t must be strictly increasing"):
        ax(jnp.zeros(3), jnp.array([0.0, 2.0, 1.0]))


# ---------------------------------------------------------------- package hygiene

ROOT = Path(__file__).resolve().parents[1]

JAX_FREE = {
    "validating a config": (
        "from jaxafm.config import RunConfig, load_config; "
        f"load_config({str(ROOT / 'configs' / 'paper.yaml')!r}, RunConfig)"
    ),
    "jaxafm --help": (
        "from typer.testing import CliRunner; from jaxafm.cli import app; "
        "r = CliRunner().invoke(app, ['run', '--help']); assert r.exit_code == 0, r.output"
    ),
    "import jaxafm": "import jaxafm; jaxafm.EFFECTS; dir(jaxafm)",
}


def _python(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("what", sorted(JAX_FREE))
def test_config_and_cli_help_import_no_jax(what):
    proc = _python(JAX_FREE[what] + "\nimport sys; assert 'jax' not in sys.modules, 'jax imported'")
    assert proc.returncode == 0, proc.stderr[-2000:]


def test_float64_is_switched_on_by_the_jax_parts_only():
    code = (
        "import jax, jaxafm, jaxafm.config, jaxafm.plots; assert not jax.config.jax_enable_x64; "
        "from jaxafm import default_scanner; assert jax.config.jax_enable_x64"
    )
    proc = _python(code)
    assert proc.returncode == 0, proc.stderr[-2000:]


def test_plots_leave_matplotlib_settings_alone(tmp_path):
    """Importing jaxafm and drawing a figure neither choose a backend nor start pyplot."""
    code = (  # the raw rcParams entry: matplotlib.get_backend() itself may start pyplot
        "import sys, matplotlib; backend = lambda: dict.__getitem__(matplotlib.rcParams, 'backend'); "
        "before = backend(); import numpy as np, jaxafm.plots as P; "
        f"P.stage_errors({{'A': np.arange(5.0)}}, {str(tmp_path / 'e.png')!r}); "
        "assert backend() == before, backend(); "
        "assert 'matplotlib.pyplot' not in sys.modules, 'pyplot imported'"
    )
    proc = _python(code)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert (tmp_path / "e.png").stat().st_size > 0


def test_public_names_load_on_first_use():
    import jaxafm

    assert set(jaxafm.__all__) <= set(dir(jaxafm))  # __all__ against its one list: tests/test_layout.py
    for name in jaxafm.__all__:
        assert getattr(jaxafm, name) is not None
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        jaxafm.nothing  # noqa: B018


@pytest.mark.parametrize(
    "schema, entry",
    [
        ("ActuatorFitConfig", "simulate: {{}}\nmodels: [{{name: a, kind: gpi, {key}: {value}}}]\n"),
        ("CalibrateConfig", "simulate: {{}}\nmodels: [{{name: a, kind: gpi, {key}: {value}}}]\n"),
        ("DiagnoseConfig", "simulate: {{}}\nnominal: {{kind: gpi, {key}: {value}}}\n"),
    ],
)
def test_every_command_takes_the_same_hysteresis_limits(tmp_path, schema, entry):
    """One hysteresis-model spec: the same largest model for fit, calibrate/run/study and diagnose."""
    import jaxafm.config as C

    for key, most in (("operators", C.common.MAX_OPERATORS), ("levels", C.common.MAX_LEVELS)):
        f = write(tmp_path / "c.yaml", entry.format(key=key, value=most))
        load_config(f, getattr(C, schema))
        f = write(tmp_path / "c.yaml", entry.format(key=key, value=most + 1))
        with pytest.raises(ConfigError, match=rf"{key}: Input should be less than or equal to {most}"):
            load_config(f, getattr(C, schema))
