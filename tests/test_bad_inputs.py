"""Bad inputs, as a new user gives them (issue 22: nothing lost, nothing silent).

Every command (``fit``, ``calibrate``, ``run``, ``study``, ``diagnose``) and the public Python
entry points get malformed input: NaN and inf (YAML ``.nan``, ``.inf`` and the strings ``"nan"``,
``"inf"``) in every kind of number, zero or negative values where only positive ones make sense,
the same column as input and output, constant records, broken, truncated and hand-edited model
files, binary, empty and list-shaped configs, missing files, folders where files belong, images
that are not images, unknown keys and effect names, and output paths that cannot take results.

What each command case asserts (:func:`expect_cli_error`):

1. exit code 2;
2. no traceback, and the output starts with ``error:``;
3. the message names the key as the user wrote it (or the file) and the bad value;
4. every file under the test's folder (the config, the data, the user's ``notes.txt`` in the
   output folder) is still there with the same bytes, and no ``model_*.json`` appeared in the
   output folder (a failed run never leaves a model that looks valid);
5. the error comes before the work: within ``FAIL_FAST_S`` seconds.

What each Python case asserts (:func:`expect_value_error`): a ``ValueError`` (``ConfigError`` is
one; a missing file may also be an ``OSError``) whose message names the argument, key or file, and
no ``IndexError``, ``ZeroDivisionError``, ``KeyError``, ``TypeError`` or LAPACK text.

The output folder of every case holds the user's ``notes.txt``. Values the schema must refuse
(``nan_case``) run without ``--overwrite``: the config is checked before the folder. Every other
case (data and model files, output paths) runs with ``--overwrite``, so that the folder, which
holds no earlier run, cannot be the error; ``--overwrite`` must then leave the user's files alone.

The base configs below are valid (``test_base_config_is_valid``) and small, so a case fails
because of the one value it changes.
"""

import copy
import dataclasses
import hashlib
import json
import math
import re
import signal
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from jaxafm import config as configs
from jaxafm.cli import app

runner = CliRunner()

NAN, INF = math.nan, math.inf
FAIL_FAST_S = 20  # a bad input is reported before any simulation or fit: far below this
DELETE = object()  # an override that removes the key

# ---------------------------------------------------------------- what a message must hold

NAN_RE = r"(?<![a-zA-Z])\.?(?i:nan)(?![a-zA-Z])"
INF_RE = r"(?<![a-zA-Z])[-+]?\.?(?i:inf(?:inity)?)(?![a-zA-Z])"


def key(path: str) -> str:
    """A config key as the user wrote it, ``a.b.c``: its parts in order on one line of the message,
    each within 40 characters of the one before (``a.b.c``, ``a: b.c``, ``a.b[0].c``, ``a: ... in
    b.c``)."""
    parts = [r"(?<![\w])" + re.escape(p) + r"(?![a-z])" for p in path.split(".")]
    return r"[^\n]{0,40}?".join(parts)


def value(v) -> str:
    """The bad value as a message may print it."""
    if isinstance(v, float) and math.isnan(v):
        return NAN_RE
    if isinstance(v, float) and math.isinf(v):
        return INF_RE
    if isinstance(v, str) and v.lower() in ("nan", ".nan"):
        return NAN_RE
    if isinstance(v, str) and v.lower().lstrip("-+.") == "inf":
        return INF_RE
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        whole = float(v) == int(v)
        text = str(int(v)) if whole else repr(float(v))
        tail = r"(?:\.0+)?" if whole else ""
        return r"(?<![\w.])" + re.escape(text) + tail + r"(?!\d)(?!\.\d)"
    return re.escape(str(v))


def file(name: str) -> str:
    return re.escape(name)


def either(*patterns: str) -> str:
    return "(?:" + "|".join(f"(?:{p})" for p in patterns) + ")"


# ---------------------------------------------------------------- the contract's helpers


class _TooSlow(BaseException):
    """Raised by the alarm: the input was not refused before the work started. A BaseException, so
    that neither CliRunner nor the command's own error handling takes it for the command's error."""


class _deadline:
    def __init__(self, seconds: float = FAIL_FAST_S):
        self.seconds = seconds

    def __enter__(self):
        def ring(signum, frame):
            raise _TooSlow()

        self.before = signal.signal(signal.SIGALRM, ring)
        signal.setitimer(signal.ITIMER_REAL, self.seconds)
        return self

    def __exit__(self, *exc):
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, self.before)
        return False


def snapshot(root: Path) -> dict:
    return {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(root.rglob("*")) if p.is_file()}


def assert_unchanged(before: dict, after: dict, what: str = "") -> None:
    """Every file of ``before`` is still there with the same bytes."""
    for path, digest in before.items():
        assert path in after, f"{path} was deleted; {what}"
        assert after[path] == digest, f"{path} was changed; {what}"


def _where(exc_info) -> str:
    """The module and function an escaped exception came from (for the failure message)."""
    if not exc_info or exc_info[2] is None:
        return ""
    tb = exc_info[2]
    while tb.tb_next is not None:
        tb = tb.tb_next
    code = tb.tb_frame.f_code
    return f" at {Path(code.co_filename).name}:{tb.tb_lineno} in {code.co_name}"


def expect_cli_error(tmp_path: Path, args: list, names, out: Path) -> str:
    """Run ``jaxafm ARGS`` in-process and check the contract (module docstring); returns the output."""
    before = snapshot(tmp_path)
    models_before = set(out.glob("model_*.json")) if out.is_dir() else set()
    start = time.perf_counter()
    try:
        with _deadline():
            result = runner.invoke(app, [str(a) for a in args])
    except _TooSlow:
        pytest.fail(
            f"no error within {FAIL_FAST_S} s: the bad input was not refused before the work started",
            pytrace=False,
        )
    seconds = time.perf_counter() - start
    output = result.output
    escaped = result.exception if not isinstance(result.exception, SystemExit) else None
    what = (
        f"exit {result.exit_code} after {seconds:.1f} s"
        + (f", {type(escaped).__name__}: {escaped}{_where(result.exc_info)}" if escaped else "")
        + f"\n--- output ---\n{output[-3000:]}"
    )
    assert result.exit_code == 2, what
    assert "Traceback" not in output, what
    assert output.startswith("error:"), what
    text = output.replace(str(tmp_path), "<tmp>")  # the test folder's own name holds no bad value
    for pattern in names:
        assert re.search(pattern, text), f"the message lacks {pattern!r}; {what}"
    assert_unchanged(before, snapshot(tmp_path), what)
    if out.is_dir():
        left = set(out.glob("model_*.json")) - models_before
        assert not left, f"a failed run left model files {sorted(p.name for p in left)}; {what}"
    return output


def expect_value_error(call, match: str, also: tuple = ()) -> str:
    """``call()`` raises a ValueError (or one of ``also``) whose message matches ``match``."""
    try:
        with _deadline():
            with pytest.raises((ValueError, *also)) as info:
                call()
    except _TooSlow:
        pytest.fail(f"no error within {FAIL_FAST_S} s", pytrace=False)
    except Exception as e:  # the wrong kind of error: say which, and where it came from
        pytest.fail(f"{type(e).__name__} instead of ValueError: {e}{_where((None, e, e.__traceback__))}")
    message = str(info.value)
    assert re.search(match, message), f"{type(info.value).__name__}: {message!r} does not match {match!r}"
    assert "lapack" not in message.lower(), message
    return message


# ---------------------------------------------------------------- data files


def _record(n: int = 200, rate: float = 100.0) -> tuple:
    t = np.arange(n) / rate
    u = 5.0 + 4.0 * np.sin(2 * np.pi * t)  # V
    d = 0.8 * u + 0.3 * np.cos(2 * np.pi * t)  # um: a loop
    return t, u, d


def write_csv(path: Path, columns: dict) -> Path:
    names = list(columns)
    rows = np.stack([np.asarray(columns[k], dtype=float) for k in names], -1)
    lines = [",".join(names)] + [",".join(f"{v:.9g}" for v in row) for row in rows]
    path.write_text("\n".join(lines) + "\n")
    return path


def write_nanosurf(path: Path, z: np.ndarray, width_um: float, z_unit: str = "nm", way: str = "Fwd") -> Path:
    """A Nanosurf text export of the heights ``z``: ``way`` Fwd a trace, Bwd a retrace."""
    rows, cols = z.shape
    head = (
        f"Name : Topography_{way} ({cols}x{rows})\n\nImage Width : {cols}\nImage Height : {rows}\n\n"
        f"Real Width : {width_um:g} um\nReal Height : {width_um * rows / cols:g} um\nZ Unit : {z_unit}\n\n"
    )
    body = "\n".join(" ".join(f"{v:.6g}" for v in row) for row in z)
    path.write_text(head + body + "\n")
    return path


def lattice(n: int = 64, pitch_px: int = 8, shift: float = 0.0) -> np.ndarray:
    """A square lattice of 100 nm pillars, ``pitch_px`` pixels apart."""
    y, x = np.mgrid[0:n, 0:n].astype(float)
    xx, yy = (x + shift) % pitch_px - pitch_px / 2, y % pitch_px - pitch_px / 2
    return 100.0 * (xx**2 + yy**2 < (pitch_px / 4) ** 2)


def line_grating(lines: int = 24, pixels: int = 64, pitch_px: int = 16) -> np.ndarray:
    x = np.arange(pixels)
    return np.tile(30.0 * ((x % pitch_px) < pitch_px / 2), (lines, 1))


@pytest.fixture(scope="module")
def model_doc() -> dict:
    """A saved scanner model (``default_scanner``), as ``save_model`` writes it."""
    from jaxafm import default_scanner
    from jaxafm.model.io import save_model

    with tempfile.TemporaryDirectory() as d:
        save_model(default_scanner(), Path(d) / "m.json")
        return json.loads((Path(d) / "m.json").read_text())


def negative_weight(doc: dict) -> dict:
    """``doc`` with the x axis's first play weight edited by hand to a negative number."""
    doc = copy.deepcopy(doc)
    weights = doc["model"]["fields"]["x"]["fields"]["hysteresis"]["fields"]["pi"]["fields"]["weights"]
    weights["array"][0] = -abs(weights["array"][0])
    return doc


def nan_weight(doc: dict) -> dict:
    doc = copy.deepcopy(doc)
    weights = doc["model"]["fields"]["y"]["fields"]["hysteresis"]["fields"]["pi"]["fields"]["weights"]
    weights["array"][1] = NAN
    return doc


def axis_model(path: Path) -> Path:
    """A one-axis model file: a straight-line PI of 100 nm/V fitted (as its file says) on 1-9 V
    and 100-900 nm."""
    from jaxafm import PrandtlIshlinskii
    from jaxafm.model.io import describe, save_model

    u = 5.0 + 4.0 * np.sin(np.linspace(0, 4 * np.pi, 200))
    model = PrandtlIshlinskii.uniform(4, 4.0, 100.0)
    save_model(model, path, describe(model, u, 100.0 * u, source="a test"))
    return path


def saved_image(path: Path, z: np.ndarray, pixel_size: tuple, bad_pixel: bool = False) -> Path:
    """A jaxafm image file (``save_image``'s format) written as is: a NaN pixel or a pixel size
    ``save_image`` would refuse, with the source it was made from in its metadata."""
    z = np.array(z, dtype=float)
    if bad_pixel:
        z[2, 3] = NAN
    doc = {
        "format": "jaxafm-image",
        "version": 1,
        "pixel_size_nm": list(pixel_size),
        "origin_nm": [0.0, 0.0],
        "meta": {"source": "simulated: a lattice of pillars"},
    }
    with open(path, "wb") as f:
        np.savez_compressed(f, z=z, meta_json=np.asarray(json.dumps(doc)))
    return path


@pytest.fixture
def data(tmp_path, model_doc) -> Path:
    """Every data file a case may point to, under ``tmp_path/data``."""
    d = tmp_path / "data"
    d.mkdir()
    t, u, v = _record()
    write_csv(d / "record.csv", {"time_s": t, "drive_v": u, "sensor_um": v})
    write_csv(d / "constant_output.csv", {"time_s": t, "drive_v": u, "sensor_um": np.full_like(t, 4.2)})
    write_csv(d / "constant_input.csv", {"time_s": t, "drive_v": np.full_like(t, 3.0), "sensor_um": v})
    write_csv(d / "falling.csv", {"time_s": t, "drive_v": u, "sensor_um": -v})
    nan_rows = v.copy()
    nan_rows[50:53] = NAN
    write_csv(d / "nan_rows.csv", {"time_s": t, "drive_v": u, "sensor_um": nan_rows})
    (d / "binary.csv").write_bytes(bytes(range(256)) * 8)
    write_nanosurf(d / "trace.txt", lattice(), 8.0)
    write_nanosurf(d / "retrace.txt", lattice(shift=0.3), 8.0, way="Bwd")
    write_nanosurf(d / "retrace_small.txt", lattice()[:, :32], 4.0, way="Bwd")
    write_nanosurf(d / "volts.txt", lattice(), 8.0, z_unit="V")
    nan_image = lattice()
    nan_image[3, 4] = NAN
    write_nanosurf(d / "nan_image.txt", nan_image, 8.0)
    (d / "not_an_image.tif").write_text("these are my notes, not a TIFF\n")
    (d / "not_an_image.txt").write_text("shopping list: milk, eggs\n")
    (d / "photo.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(64))
    for rate in ("slow", "fast"):
        write_nanosurf(d / f"{rate}_trace.txt", line_grating(), 2.0)
        write_nanosurf(d / f"{rate}_retrace.txt", np.roll(line_grating(), 1, axis=1), 2.0, way="Bwd")
    write_nanosurf(d / "fast_retrace_small.txt", line_grating(pixels=32), 1.0, way="Bwd")
    (d / "scanner.json").write_text(json.dumps(model_doc))
    (d / "negative_weight.json").write_text(json.dumps(negative_weight(model_doc)))
    (d / "nan_weight.json").write_text(json.dumps(nan_weight(model_doc)))
    text = json.dumps(model_doc)
    (d / "truncated.json").write_text(text[: len(text) // 2])
    (d / "not_json.json").write_text("model: this is YAML, not JSON\n")
    (d / "other.json").write_text(json.dumps({"name": "my settings", "colour": "blue"}))
    (d / "list.json").write_text(json.dumps([1, 2, 3]))
    (d / "binary.json").write_bytes(bytes(range(256)))
    (d / "folder").mkdir()
    (d / "folder" / "keep.txt").write_text("a file in a folder\n")
    axis_model(d / "axis.json")
    tt = np.arange(60) / 50.0
    x = 500.0 + 200.0 * np.sin(2 * np.pi * tt)
    write_csv(d / "trajectory.csv", {"t_s": tt, "x_nm": x})
    write_csv(d / "trajectory_xy.csv", {"t_s": tt, "x_nm": x, "y_nm": x})
    write_csv(d / "trajectory_nan.csv", {"t_s": tt, "x_nm": np.where(np.arange(60) == 6, NAN, x)})
    write_csv(d / "trajectory_backwards.csv", {"t_s": np.where(np.arange(60) == 9, tt[7], tt), "x_nm": x})
    u150 = 150.0 * np.sin(2 * np.pi * tt)
    write_csv(
        d / "record_150v.csv", {"time_s": tt, "drive_v": u150, "sensor_um": 0.5 * np.sin(2 * np.pi * tt)}
    )
    saved_image(d / "nan_pixel.npz", lattice(16, 4), (250.0, 250.0), bad_pixel=True)
    saved_image(d / "zero_pixel.npz", lattice(16, 4), (0.0, 250.0))
    (d / "results.txt").write_text("my earlier results: do not delete\n")
    return d


# ---------------------------------------------------------------- the base configs (valid, small)

BASES = {
    "fit": lambda: {
        "simulate": {
            "effects": ["hysteresis"],
            "duration_s": 2.0,
            "sample_rate_hz": 100.0,
            "noise_nm": 1.0,
            "seed": 0,
        },
        "train_fraction": 0.6,
        "models": [{"name": "line", "kind": "linear"}],
    },
    "fit-data": lambda: {
        "data": {
            "path": "data/record.csv",
            "delimiter": ",",
            "input_columns": ["drive_v"],
            "output_columns": ["sensor_um"],
            "time_column": "time_s",
            "output_unit": "um",
        },
        "train_fraction": 0.6,
        "models": [{"name": "pi", "kind": "pi", "operators": 4, "max_steps": 5}],
    },
    "calibrate": lambda: {
        "simulate": {"pixels": 32, "size_nm": 4000.0, "line_rate_hz": 10.0, "seed": 0},
        "grating": {"pitch_nm": 1000.0},
        "models": [{"name": "pi", "kind": "pi", "operators": 4, "effects": []}],
        "solver": {"max_steps": 1, "blur_px": [1.0]},
        "compensate": None,
    },
    "calibrate-data": lambda: {
        "data": {
            "trace": "data/trace.txt",
            "retrace": "data/retrace.txt",
            "sensitivity_nm_per_v": [500.0, 500.0],
            "u_max_v": 10.0,
            "line_rate_hz": 1.0,
            "history_v": [[-10.0, -10.0], [10.0, 10.0]],
        },
        "grating": {"pitch_nm": 1000.0},
        "models": [{"name": "pi", "kind": "pi", "operators": 4, "effects": []}],
        "solver": {"max_steps": 1, "blur_px": [1.0]},
        "compensate": None,
    },
    "run": lambda: {
        "calibration": {
            "simulate": {"pixels": 32, "size_nm": 8000.0, "line_rate_hz": 10.0, "seed": 0},
            "grating": {"pitch_nm": 1000.0},
            "model": {"name": "pi", "kind": "pi", "operators": 4, "effects": []},
            "solver": {"max_steps": 1, "blur_px": [1.0]},
        },
        "drift_nm_per_min": [3.0, -1.8],
        "workspace": {"size_nm": 2000.0, "centre_nm": [0.0, 0.0], "pixels": 32, "line_rate_hz": 10.0},
        "landmarks": {
            "n": 2,
            "start_px": 8,
            "step_px": 16,
            "depth_nm": 50.0,
            "interpolation": ["polynomial"],
            "m": 2,
            "degree": 1,
        },
        "particles": {"radius_nm": [10.0, 20.0], "per_cell": 1, "seed": 1},
        "local_scan": {"points": 16, "line_time_s": 0.5, "margin_nm": 40.0, "max_lines": 3},
        "push": {"distance_nm": [100.0, 300.0], "speed_nm_per_s": 200.0, "tolerance_radii": 1.0},
        "stages": ["open_loop"],
        "seed": 0,
    },
    "study": lambda: {
        "trials": 2,
        "trials_per_scanner": 2,
        "chunk": 2,
        "stages": ["open_loop"],
        "scanner": {"creep": {"gamma": {"uniform": [0.005, 0.02]}}},
        "particle_radius_nm": {"uniform": [10.0, 20.0]},
        "calibration": {
            "simulate": {"pixels": 32, "size_nm": 8000.0, "line_rate_hz": 10.0, "seed": 0},
            "grating": {"pitch_nm": 1000.0},
            "model": {"name": "pi", "kind": "pi", "operators": 4, "effects": []},
            "solver": {"max_steps": 1, "blur_px": [1.0]},
        },
        "workspace": {"size_nm": 2000.0, "centre_nm": [0.0, 0.0], "pixels": 32, "line_rate_hz": 10.0},
        "landmarks": {
            "n": 2,
            "start_px": 8,
            "step_px": 16,
            "depth_nm": 50.0,
            "interpolation": ["polynomial"],
            "m": 2,
            "degree": 1,
        },
        "local_scan": {"points": 16, "line_time_s": 0.5, "margin_nm": 40.0, "max_lines": 3},
        "seed": 0,
    },
    "diagnose": lambda: {
        "simulate": {
            "withheld": "creep",
            "magnitude": 0.01,
            "duration_s": 4.0,
            "sample_rate_hz": 50.0,
            "noise_nm": 2.0,
            "seed": 0,
        },
        "candidates": ["creep", "drift"],
        "train_fraction": 0.6,
        "max_steps": 5,
    },
    "diagnose-data": lambda: {
        "data": {
            "path": "data/record.csv",
            "delimiter": ",",
            "input_columns": ["drive_v"],
            "output_columns": ["sensor_um"],
            "time_column": "time_s",
            "output_unit": "um",
        },
        "candidates": ["creep"],
        "max_steps": 5,
    },
    "diagnose-image": lambda: {
        "image": {"path": "data/slow_trace.txt"},
        "candidates": ["tip"],
        "max_steps": 5,
    },
    "compensate": lambda: {
        "model": "data/axis.json",
        "trajectory": {"path": "data/trajectory.csv"},
        "cycle_s": 0.5,
    },
    "predict": lambda: {
        "model": "data/axis.json",
        "data": {
            "path": "data/record.csv",
            "delimiter": ",",
            "input_columns": ["drive_v"],
            "output_columns": ["sensor_um"],
            "time_column": "time_s",
            "output_unit": "um",
        },
    },
    "diagnose-scans": lambda: {
        "scans": {
            "grating": {"pitch_nm": 500.0, "edge_width_nm": 20.0},
            "pairs": [
                {"trace": "data/slow_trace.txt", "retrace": "data/slow_retrace.txt", "line_rate_hz": 1.0},
                {"trace": "data/fast_trace.txt", "retrace": "data/fast_retrace.txt", "line_rate_hz": 4.0},
            ],
        },
        "candidates": ["feedback_lag"],
        "max_steps": 5,
    },
}
SCHEMAS = {
    "fit": "ActuatorFitConfig",
    "calibrate": "CalibrateConfig",
    "run": "RunConfig",
    "study": "StudyConfig",
    "diagnose": "DiagnoseConfig",
    "compensate": "CompensateConfig",
    "predict": "PredictConfig",
}


def command_of(base: str) -> str:
    return base.split("-")[0]


def override(cfg: dict, changes: dict) -> dict:
    """``cfg`` with ``changes`` ``{"a.b.0.c": value}`` made (``DELETE`` removes the key)."""
    cfg = copy.deepcopy(cfg)
    for path, new in changes.items():
        *parents, last = path.split(".")
        node = cfg
        for p in parents:
            if isinstance(node, list):
                node = node[int(p)]
            else:
                if node.get(p) is None:  # absent, or null in the base (e.g. compensate)
                    node[p] = {}
                node = node[p]
        last = int(last) if isinstance(node, list) else last
        if new is DELETE:
            del node[last]
        else:
            node[last] = new
    return cfg


@pytest.mark.parametrize("base", sorted(BASES))
def test_base_config_is_valid(tmp_path, data, base):
    """The control: every base config passes its schema, so a case fails for the value it changes."""
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(BASES[base]()))
    configs.load_config(path, getattr(configs, SCHEMAS[command_of(base)]))


# ---------------------------------------------------------------- the command cases


@dataclasses.dataclass
class Case:
    """One command run: the base config, what changes in it (or the config file's whole content),
    what the message must name, and the output folder's options."""

    base: str
    changes: dict = dataclasses.field(default_factory=dict)
    names: tuple = ()
    content: object = None  # str or bytes: the config file as written, instead of base + changes
    overwrite: bool = True
    out: str = "out"  # the --out folder (holding the user's notes.txt), relative to tmp_path
    args: tuple = ()


def case(id_: str, *args, **kwargs):
    return pytest.param(Case(*args, **kwargs), id=id_)


def nan_case(id_: str, base: str, path: str, bad, replace=None, *extra):
    """``path`` set to ``bad`` (``replace``: the whole value, for a list holding it); the message
    names the key and the bad value."""
    return case(
        id_,
        base,
        {path: bad if replace is None else replace},
        (key(path), value(bad), *extra),
        overwrite=False,
    )


FIT = [
    nan_case("fit-simulate.duration_s-.nan", "fit", "simulate.duration_s", NAN),
    nan_case("fit-simulate.sample_rate_hz-inf-string", "fit", "simulate.sample_rate_hz", "inf"),
    nan_case("fit-simulate.amplitude_v-nan-string", "fit", "simulate.amplitude_v", "nan"),
    nan_case("fit-simulate.frequency_hz-.inf", "fit", "simulate.frequency_hz", INF),
    nan_case("fit-simulate.modulation_period_s-.nan", "fit", "simulate.modulation_period_s", NAN),
    nan_case("fit-simulate.noise_nm-negative", "fit", "simulate.noise_nm", -2.0),
    nan_case("fit-simulate.duration_s-zero", "fit", "simulate.duration_s", 0.0),
    nan_case("fit-simulate.seed-too-large", "fit", "simulate.seed", 2**40),
    nan_case("fit-settle_s-.inf", "fit", "settle_s", INF),
    nan_case("fit-train_fraction-.nan", "fit", "train_fraction", NAN),
    nan_case("fit-history_v-.nan", "fit", "history_v", NAN, [0.0, NAN]),
    case(
        "fit-simulate.effects-unknown",
        "fit",
        {"simulate.effects": ["hysteresis", "hysterisis"]},
        (key("simulate.effects"), "hysterisis"),
    ),
    case(
        "fit-models.0.operators-zero",
        "fit",
        {"models.0": {"name": "p", "kind": "pi", "operators": 0}},
        (key("operators"), value(0)),
    ),
    case("fit-models-unknown-key", "fit", {"models.0.levls": 20}, (key("levls"),)),
    case("fit-top-unknown-key", "fit", {"train_fracton": 0.5}, (key("train_fracton"),)),
    nan_case("fit-data.sample_rate_hz-.nan", "fit-data", "data.sample_rate_hz", NAN),
    case(
        "fit-data-same-column-in-and-out",
        "fit-data",
        {"data.output_columns": ["drive_v"]},
        (either(key("output_columns"), key("input_columns")), "drive_v"),
    ),
    case(
        "fit-data-constant-record",
        "fit-data",
        {"data.path": "data/constant_output.csv"},
        (file("constant_output.csv"),),
    ),
    case(
        "fit-data-constant-input",
        "fit-data",
        {"data.path": "data/constant_input.csv"},
        (file("constant_input.csv"),),
    ),
    case("fit-data-falling-output-pi", "fit-data", {"data.path": "data/falling.csv"}, (file("falling.csv"),)),
    case("fit-data-nan-rows", "fit-data", {"data.path": "data/nan_rows.csv"}, (file("nan_rows.csv"),)),
    case("fit-data-missing-file", "fit-data", {"data.path": "data/nowhere.csv"}, (file("nowhere.csv"),)),
    case("fit-data-directory-as-file", "fit-data", {"data.path": "data/folder"}, (file("folder"),)),
    case("fit-data-binary-file", "fit-data", {"data.path": "data/binary.csv"}, (file("binary.csv"),)),
    case(
        "fit-data-output_unit-wrong",
        "fit-data",
        {"data.output_unit": "furlong"},
        (key("output_unit"), "furlong"),
    ),
    case("fit-data-input_unit-wrong", "fit-data", {"data.input_unit": "kV"}, (key("input_unit"), "kV")),
    case(
        "fit-data-input_columns-zero",
        "fit-data",
        {"data.input_columns": [0]},
        (key("input_columns"), value(0)),
    ),
    case(
        "fit-data-column-not-in-file",
        "fit-data",
        {"data.output_columns": ["sensor_nm"]},
        (key("output_columns"), "sensor_nm"),
    ),
]

CALIBRATE = [
    nan_case("calibrate-solver.blur_px-negative", "calibrate", "solver.blur_px", -3, [-3]),
    case(
        "calibrate-solver.blur_px-negative-overwrite",
        "calibrate",
        {"solver.blur_px": [-3]},
        (key("blur_px"), value(-3)),
        overwrite=True,
    ),
    nan_case("calibrate-solver.blur_px-.nan", "calibrate", "solver.blur_px", NAN, [2.0, NAN]),
    nan_case("calibrate-solver.blur_px-too-wide", "calibrate", "solver.blur_px", 100, [100.0]),
    nan_case("calibrate-solver.path_tolerance_nm-zero", "calibrate", "solver.path_tolerance_nm", 0.0),
    nan_case("calibrate-solver.path_tolerance_nm-.inf", "calibrate", "solver.path_tolerance_nm", INF),
    case(
        "calibrate-solver.coarsen-not-dividing",
        "calibrate",
        {"solver.coarsen": 3},
        (key("solver.coarsen"), value(3), "32"),
    ),
    case(
        "calibrate-solver.coarsen-too-coarse",
        "calibrate",
        {"solver.coarsen": 8},
        (key("solver.coarsen"), value(8), "pitch"),
    ),
    nan_case("calibrate-solver.coarsen-zero", "calibrate", "solver.coarsen", 0),
    case(
        "calibrate-models.0-asymmetry-without-dead-zones",
        "calibrate",
        {"models.0": {"name": "p", "kind": "preisach", "levels": 4, "effects": ["asymmetry", "creep"]}},
        (key("models.0"), "'asymmetry'", "'preisach'", "kind: gpi"),
    ),
    case(
        "calibrate-solver.max_steps-more-than-stages",
        "calibrate",
        {"solver.max_steps": [20, 12, 8]},
        (key("solver.max_steps"), r"\[20, 12, 8\]", "2 stages", "images, blur 1 px"),
    ),
    nan_case("calibrate-solver.max_steps-zero-in-list", "calibrate", "solver.max_steps", 0, [20, 0]),
    nan_case("calibrate-simulate.size_nm-.nan", "calibrate", "simulate.size_nm", NAN),
    nan_case("calibrate-simulate.line_rate_hz-inf-string", "calibrate", "simulate.line_rate_hz", "inf"),
    nan_case("calibrate-grating.pitch_nm-.nan", "calibrate", "grating.pitch_nm", NAN),
    nan_case("calibrate-grating.pitch_nm-.inf", "calibrate", "grating.pitch_nm", INF),
    nan_case("calibrate-grating.pitch_nm-negative", "calibrate", "grating.pitch_nm", -1000.0),
    nan_case("calibrate-grating.off_line_chords_sd-zero", "calibrate", "grating.off_line_chords_sd", 0),
    nan_case("calibrate-grating.off_line_chords_sd-.nan", "calibrate", "grating.off_line_chords_sd", NAN),
    nan_case("calibrate-compensate.scan_fraction-.nan", "calibrate", "compensate.scan_fraction", NAN),
    case(
        "calibrate-simulate.withheld-unknown",
        "calibrate",
        {"simulate.withheld": ["warp"]},
        (key("simulate.withheld"), "warp"),
    ),
    case(
        "calibrate-models.effects-not-fittable",
        "calibrate",
        {"models.0.effects": ["noise"]},
        (key("effects"), "noise"),
    ),
    case(
        "calibrate-solver.name-unknown",
        "calibrate",
        {"solver.name": "newton"},
        (key("solver.name"), "newton"),
    ),
    nan_case(
        "calibrate-data.sensitivity-.nan", "calibrate-data", "data.sensitivity_nm_per_v", NAN, [NAN, 500.0]
    ),
    nan_case(
        "calibrate-data.sensitivity-negative",
        "calibrate-data",
        "data.sensitivity_nm_per_v",
        -500,
        [-500.0, 500.0],
    ),
    nan_case(
        "calibrate-data.sensitivity-inf-string",
        "calibrate-data",
        "data.sensitivity_nm_per_v",
        "inf",
        [500.0, "inf"],
    ),
    case(
        "calibrate-data-drive-far-outside-u_max",
        "calibrate-data",
        {"data.sensitivity_nm_per_v": [50.0, 50.0]},
        (either(key("sensitivity_nm_per_v"), key("u_max_v")), value(50)),
    ),
    *(  # a scan setting given against the file's own header (the real lattice: -45 deg, 5 %, 2 s, Up)
        case(
            f"calibrate-data.{k}-against-the-header",
            "calibrate-data",
            {
                "data.trace": "builtin:lattice_square_pits_nanosurf.nid",
                "data.retrace": "builtin:lattice_square_pits_nanosurf.nid",
                "data.line_rate_hz": 0.5,  # as the header says: one setting against it at a time
                f"data.{k}": v,
                "grating": {"pitch_nm": 10000.0, "pits": True},
            },
            (key(f"data.{k}"), value(v), re.escape(entry)),
        )
        for k, v, entry in [
            ("angle_deg", 0.0, "Rotation=-45"),
            ("overscan", 0.1, "Overscan=5 %"),
            ("line_rate_hz", 1.0, "Time/Line=2 s"),
            ("lines", "down", "Scan direction=Up"),
        ]
    ),
    nan_case("calibrate-data.line_rate_hz-.nan", "calibrate-data", "data.line_rate_hz", NAN),
    nan_case("calibrate-data.u_max_v-.inf", "calibrate-data", "data.u_max_v", INF),
    nan_case(
        "calibrate-data.history_v-.nan", "calibrate-data", "data.history_v", NAN, [[NAN, -10.0], [10.0, 10.0]]
    ),
    case(
        "calibrate-data-mismatched-images",
        "calibrate-data",
        {"data.retrace": "data/retrace_small.txt"},
        (file("retrace_small.txt"),),
    ),
    case(
        "calibrate-data-trace-missing",
        "calibrate-data",
        {"data.trace": "data/nowhere.txt"},
        (file("nowhere.txt"),),
    ),
    case(
        "calibrate-data-trace-not-an-image",
        "calibrate-data",
        {"data.trace": "data/not_an_image.tif"},
        (file("not_an_image.tif"),),
    ),
    case(
        "calibrate-data-trace-is-a-folder", "calibrate-data", {"data.trace": "data/folder"}, (file("folder"),)
    ),
    case(
        "calibrate-data-trace-wrong-z-unit",
        "calibrate-data",
        {"data.trace": "data/volts.txt"},
        (file("volts.txt"),),
    ),
    case(
        "calibrate-data-grating.pitch_nm-missing",
        "calibrate-data",
        {"grating": {"pits": False}},
        (key("grating.pitch_nm"), "datasheet"),
    ),
    case(
        "calibrate-data-and-simulate",
        "calibrate-data",
        {"simulate": {"pixels": 32}},
        (key("data"), key("simulate")),
    ),
]

RUN = [
    nan_case("run-workspace.size_nm-.nan", "run", "workspace.size_nm", NAN),
    nan_case("run-workspace.size_nm-negative", "run", "workspace.size_nm", -2000.0),
    nan_case("run-workspace.centre_nm-.nan", "run", "workspace.centre_nm", NAN, [NAN, 0.0]),
    case(
        "run-workspace.centre_nm-.nan-overwrite",
        "run",
        {"workspace.centre_nm": [NAN, 0.0]},
        (key("workspace.centre_nm"), NAN_RE),
        overwrite=True,
    ),
    nan_case("run-workspace.centre_nm-inf-string", "run", "workspace.centre_nm", "inf", [0.0, "inf"]),
    nan_case("run-workspace.line_rate_hz-.nan", "run", "workspace.line_rate_hz", NAN),
    nan_case("run-drift_nm_per_min-.nan", "run", "drift_nm_per_min", NAN, [NAN, -1.8]),
    nan_case("run-drift_nm_per_min-inf-string", "run", "drift_nm_per_min", "inf", [3.0, "inf"]),
    nan_case("run-particles.radius_nm-.nan", "run", "particles.radius_nm", NAN, [NAN, 20.0]),
    nan_case("run-particles.radius_nm-.inf", "run", "particles.radius_nm", INF, [10.0, INF]),
    nan_case("run-particles.radius_nm-zero", "run", "particles.radius_nm", 0, [0.0, 20.0]),
    nan_case("run-particles.seed-negative", "run", "particles.seed", -1),
    nan_case("run-seed-negative", "run", "seed", -5),  # numpy seeds must be >= 0
    nan_case("run-push.distance_nm-.nan", "run", "push.distance_nm", NAN, [NAN, 300.0]),
    nan_case("run-push.speed_nm_per_s-.nan", "run", "push.speed_nm_per_s", NAN),
    nan_case("run-local_scan.line_time_s-.inf", "run", "local_scan.line_time_s", INF),
    nan_case("run-local_scan.margin_nm-nan-string", "run", "local_scan.margin_nm", "nan"),
    nan_case("run-landmarks.depth_nm-.nan", "run", "landmarks.depth_nm", NAN),
    nan_case("run-landmarks.step_px-.nan", "run", "landmarks.step_px", NAN),
    nan_case("run-landmarks.start_px-negative", "run", "landmarks.start_px", -4),
    nan_case("run-calibration.simulate.size_nm-.nan", "run", "calibration.simulate.size_nm", NAN),
    nan_case("run-calibration.grating.pitch_nm-.inf", "run", "calibration.grating.pitch_nm", INF),
    case(
        "run-calibration.solver.blur_px-negative",
        "run",
        {"calibration.solver.blur_px": [-3]},
        (key("blur_px"), value(-3)),
    ),
    case(
        "run-model_file-missing",
        "run",
        {"calibration.model_file": "data/nowhere.json"},
        (key("model_file"), file("nowhere.json")),
    ),
    case(  # issue 41, item 9
        "run-model_file-with-drift-and-noise",
        "run",
        {"calibration.model_file": "data/scanner.json"},
        (key("calibration.model_file"), file("scanner.json"), "drift", "noise"),
    ),
    case(
        "run-model_file-not-a-model",
        "run",
        {"calibration.model_file": "data/other.json"},
        (file("other.json"),),
    ),
    case(
        "run-model_file-truncated",
        "run",
        {"calibration.model_file": "data/truncated.json"},
        (file("truncated.json"),),
    ),
    case(
        "run-model_file-negative-weight",
        "run",
        {"calibration.model_file": "data/negative_weight.json"},
        (file("negative_weight.json"),),
    ),
    case(
        "run-model_file-json-list", "run", {"calibration.model_file": "data/list.json"}, (file("list.json"),)
    ),
    case("run-model_file-is-a-folder", "run", {"calibration.model_file": "data/folder"}, (file("folder"),)),
    case(
        "run-calibration.simulate.withheld",
        "run",
        {"calibration.simulate.withheld": ["creep"]},
        (key("withheld"), "creep"),
    ),
    case("run-stages-unknown", "run", {"stages": ["A+B+C+D"]}, (key("stages"), re.escape("A+B+C+D"))),
    case(
        "run-workspace-beyond-the-calibrated-area",
        "run",
        {"workspace.centre_nm": [5000.0, 0.0]},
        (key("workspace"), either(value(5000), value(6000))),  # the centre, or its reach: 5000 + 2000 / 2
        overwrite=False,
    ),
    case("run-workspace-unknown-key", "run", {"workspace.siez_nm": 100.0}, (key("workspace.siez_nm"),)),
]

STUDY = [
    case(
        "study-scanner.creep.gamma-uniform-.nan",
        "study",
        {"scanner.creep.gamma": {"uniform": [NAN, 0.02]}},
        (key("scanner.creep.gamma"), NAN_RE),
    ),
    case(
        "study-scanner.drift.x-fixed-.nan",
        "study",
        {"scanner.drift": {"x_nm_per_min": NAN}},
        (key("scanner.drift.x_nm_per_min"), NAN_RE),
    ),
    case(
        "study-scanner.drift.x-normal-.inf",
        "study",
        {"scanner.drift": {"x_nm_per_min": {"normal": [INF, 1.0]}}},
        (key("scanner.drift.x_nm_per_min"), INF_RE),
    ),
    case(
        "study-scanner.noise.std-uniform-inf-string",
        "study",
        {"scanner.noise": {"std_nm": {"uniform": [0.1, "inf"]}}},
        (key("scanner.noise.std_nm"), INF_RE),
    ),
    case(
        "study-particle_radius_nm-uniform-.nan",
        "study",
        {"particle_radius_nm": {"uniform": [NAN, 20.0]}},
        (key("particle_radius_nm"), NAN_RE),
    ),
    case(
        "study-particle_radius_nm-normal-std-.nan",
        "study",
        {"particle_radius_nm": {"normal": [15.0, NAN]}},
        (key("particle_radius_nm"), NAN_RE),
    ),
    case(
        "study-particle_radius_nm-loguniform-zero",
        "study",
        {"particle_radius_nm": {"loguniform": [0.0, 20.0]}},
        (key("particle_radius_nm"), value(0)),
    ),
    case("study-scanner-unknown-effect", "study", {"scanner.creeep": {"gamma": 0.01}}, (key("creeep"),)),
    case(
        "study-scanner-unknown-parameter", "study", {"scanner.creep.beta": 0.01}, (key("scanner.creep.beta"),)
    ),
    case(
        "study-scanner.hysteresis-out-of-range",
        "study",
        {"scanner.hysteresis": {"loop_width": {"uniform": [0.1, 0.9]}}},
        (key("scanner.hysteresis.loop_width"), value(0.9)),
    ),
    nan_case("study-workspace.centre_nm-.nan", "study", "workspace.centre_nm", NAN, [0.0, NAN]),
    nan_case("study-workspace.size_nm-.nan", "study", "workspace.size_nm", NAN),
    nan_case("study-trials-zero", "study", "trials", 0),
    nan_case("study-seed-negative", "study", "seed", -1),
    case(
        "study-stages-push-without-ABC", "study", {"stages": ["open_loop", "push"]}, (key("stages"), "push")
    ),
    case(
        "study-model_file-missing",
        "study",
        {"calibration.model_file": "data/nowhere.json", "stages": ["open_loop", "A"]},
        (key("model_file"), file("nowhere.json")),
    ),
    case(  # issue 41, item 9
        "study-model_file-with-drift-and-noise",
        "study",
        {"calibration.model_file": "data/scanner.json", "stages": ["open_loop", "A"]},
        (key("calibration.model_file"), file("scanner.json"), "drift", "noise"),
    ),
    case(
        "study-model_file-truncated",
        "study",
        {"calibration.model_file": "data/truncated.json", "stages": ["open_loop", "A"]},
        (file("truncated.json"),),
    ),
    case(
        "study-model_file-negative-weight",
        "study",
        {"calibration.model_file": "data/negative_weight.json", "stages": ["open_loop", "A"]},
        (file("negative_weight.json"),),
    ),
    case(
        "study-overwrite-keeps-users-study.yaml",
        "study",
        {"scanner.creep.gamma": {"uniform": [NAN, 0.02]}},
        (key("scanner.creep.gamma"), NAN_RE),
        overwrite=True,
        out="mine",
    ),
    case(
        "study-resume-and-overwrite",
        "study",
        {},
        (re.escape("--resume"), re.escape("--overwrite")),
        overwrite=True,
        args=("--resume",),
    ),
    case(
        "study-resume-without-a-study",
        "study",
        {},
        (re.escape("--resume"), r"[/\\]out\b"),
        args=("--resume",),
        overwrite=False,
    ),
]

LATTICE = "builtin:lattice_square_pits_nanosurf.nid"  # pits 10 um apart, scanned Up

DIAGNOSE = [
    *(  # issue 41, item 6: the pitch checked as calibrate checks it
        case(
            f"diagnose-image-lattice-pitch-{pitch}",
            "diagnose-image",
            {"image": {"path": LATTICE, "kind": "lattice", "pitch_nm": pitch}},
            (key("image.pitch_nm"), value(pitch), r"lie 99\d\d nm apart"),
        )
        for pitch in (5000, 7000, 20000)
    ),
    case(  # issue 41, item 7
        "diagnose-image-first_row-against-the-file",
        "diagnose-image",
        {"image": {"path": LATTICE, "kind": "lattice", "pitch_nm": 10000, "first_row": "top"}},
        (key("first_row"), "top", r"Scan direction.{0,5}Up"),
    ),
    nan_case("diagnose-simulate.magnitude-.nan", "diagnose", "simulate.magnitude", NAN),
    case(
        "diagnose-simulate.magnitude-.nan-overwrite",
        "diagnose",
        {"simulate.magnitude": NAN},
        (key("simulate.magnitude"), NAN_RE),
        overwrite=True,
    ),
    nan_case("diagnose-simulate.magnitude-inf-string", "diagnose", "simulate.magnitude", "inf"),
    nan_case("diagnose-simulate.magnitude-negative", "diagnose", "simulate.magnitude", -0.01),
    nan_case("diagnose-simulate.duration_s-.nan", "diagnose", "simulate.duration_s", NAN),
    nan_case("diagnose-simulate.sample_rate_hz-.inf", "diagnose", "simulate.sample_rate_hz", INF),
    nan_case("diagnose-simulate.noise_nm-.nan", "diagnose", "simulate.noise_nm", NAN),
    nan_case("diagnose-simulate.seed-too-large", "diagnose", "simulate.seed", 2**64),
    nan_case("diagnose-settle_s-.inf", "diagnose", "settle_s", INF),
    nan_case("diagnose-train_fraction-.nan", "diagnose", "train_fraction", NAN),
    nan_case("diagnose-min_shrink_pct-.nan", "diagnose", "min_shrink_pct", NAN),
    nan_case("diagnose-history_v-.nan", "diagnose", "history_v", NAN, [NAN]),
    case(
        "diagnose-simulate.withheld-unknown",
        "diagnose",
        {"simulate.withheld": "warp"},
        (key("simulate.withheld"), "warp"),
    ),
    case(
        "diagnose-candidates-unknown", "diagnose", {"candidates": ["creeep"]}, (key("candidates"), "creeep")
    ),
    case(
        "diagnose-nominal.effects-unknown",
        "diagnose",
        {"nominal.effects": ["hysteresis", "slop"]},
        (key("nominal.effects"), "slop"),
    ),
    case(
        "diagnose-data-same-column-in-and-out",
        "diagnose-data",
        {"data.output_columns": ["drive_v"]},
        (either(key("output_columns"), key("input_columns")), "drive_v"),
    ),
    case(
        "diagnose-data-constant-record",
        "diagnose-data",
        {"data.path": "data/constant_output.csv"},
        (file("constant_output.csv"),),
    ),
    case(
        "diagnose-data-constant-input",
        "diagnose-data",
        {"data.path": "data/constant_input.csv"},
        (file("constant_input.csv"),),
    ),
    case(
        "diagnose-data-nan-rows", "diagnose-data", {"data.path": "data/nan_rows.csv"}, (file("nan_rows.csv"),)
    ),
    case(
        "diagnose-data-output_unit-missing",
        "diagnose-data",
        {"data.output_unit": DELETE},
        (key("output_unit"),),
    ),
    case(
        "diagnose-image-not-an-image",
        "diagnose-image",
        {"image.path": "data/not_an_image.txt"},
        (file("not_an_image.txt"),),
    ),
    case("diagnose-image-png", "diagnose-image", {"image.path": "data/photo.png"}, (file("photo.png"),)),
    case(
        "diagnose-image-missing", "diagnose-image", {"image.path": "data/nowhere.txt"}, (file("nowhere.txt"),)
    ),
    case(
        "diagnose-image-nan-pixel",
        "diagnose-image",
        {"image.path": "data/nan_image.txt"},
        (file("nan_image.txt"),),
    ),
    case(
        "diagnose-image-wrong-z-unit",
        "diagnose-image",
        {"image.path": "data/volts.txt"},
        (file("volts.txt"),),
    ),
    case(
        "diagnose-scans-mismatched-images",
        "diagnose-scans",
        {"scans.pairs.1.retrace": "data/fast_retrace_small.txt"},
        (either(file("fast_retrace_small.txt"), key("scans.pairs")),),
    ),
    nan_case("diagnose-scans.pairs.line_rate_hz-.nan", "diagnose-scans", "scans.pairs.0.line_rate_hz", NAN),
    nan_case("diagnose-scans.pairs.overscan-.nan", "diagnose-scans", "scans.pairs.1.overscan", NAN),
    nan_case("diagnose-scans.grating.pitch_nm-.nan", "diagnose-scans", "scans.grating.pitch_nm", NAN),
    nan_case(
        "diagnose-scans.grating.edge_width_nm-.inf", "diagnose-scans", "scans.grating.edge_width_nm", INF
    ),
    case(
        "diagnose-scans.grating.lattice-pitch-unknown",
        "diagnose-scans",
        {"scans.grating.kind": "lattice", "scans.grating.pitch_nm": "unknown"},
        (key("scans.grating.pitch_nm"), value("unknown"), "allowed"),
        overwrite=False,
    ),
    case(
        "diagnose-scans.grating.lattice-pitch-missing",
        "diagnose-scans",
        {"scans.grating.kind": "lattice", "scans.grating.pitch_nm": DELETE},
        (key("scans.grating.pitch_nm"), "lattice", "allowed"),
        overwrite=False,
    ),
    case(
        "diagnose-scans.simulate.line_rates_hz-.nan",
        "diagnose",
        {
            "simulate": DELETE,
            "scans": {
                "simulate": {
                    "withheld": "feedback_lag",
                    "magnitude": 3e-4,
                    "line_rates_hz": [1.0, NAN],
                    "lines": 8,
                    "pixels": 64,
                }
            },
        },
        (key("scans.simulate.line_rates_hz"), NAN_RE),
    ),
    case(
        "diagnose-scans.simulate.magnitude-.inf",
        "diagnose",
        {
            "simulate": DELETE,
            "scans": {"simulate": {"withheld": "feedback_lag", "magnitude": INF, "lines": 8, "pixels": 64}},
        },
        (key("scans.simulate.magnitude"), INF_RE),
    ),
]

COMPENSATE = [  # issue 41, items 5 and 12
    case(
        "compensate-one-axis-model-two-axis-trajectory",
        "compensate",
        {"trajectory.path": "data/trajectory_xy.csv"},
        (file("trajectory_xy.csv"), "y_nm", "one axis"),
    ),
    case(
        "compensate-trajectory-nan-row",
        "compensate",
        {"trajectory.path": "data/trajectory_nan.csv"},
        (file("trajectory_nan.csv"), "x_nm", r"data row 7\b", NAN_RE),
    ),
    case(
        "compensate-trajectory-times-not-increasing",
        "compensate",
        {"trajectory.path": "data/trajectory_backwards.csv"},
        (file("trajectory_backwards.csv"), "t_s", r"data row 10\b", r"data row 9\b"),
    ),
]

PREDICT = [  # issue 41, item 8
    case(
        "predict-far-outside-the-fitted-range",
        "predict",
        {"data.path": "data/record_150v.csv"},
        (file("axis.json"), r"\d+ % of the record's input samples", r"rms error", r"limit"),
    ),
]

BINARY = bytes(range(256)) * 4
GENERIC = [
    g
    for command in ("fit", "calibrate", "run", "study", "diagnose")
    for g in (
        case(
            f"{command}-binary-config", command, content=BINARY, names=(file("config.yaml"),), overwrite=False
        ),
        case(f"{command}-empty-config", command, content="", names=(file("config.yaml"),), overwrite=False),
        case(
            f"{command}-config-is-a-yaml-list",
            command,
            content="- 1\n- 2\n",
            names=(file("config.yaml"),),
            overwrite=False,
        ),
        case(
            f"{command}-config-not-yaml",
            command,
            content="models: [1, 2\n",
            names=(file("config.yaml"),),
            overwrite=False,
        ),
        case(
            f"{command}-out-is-an-existing-file",
            command,
            names=(file("results.txt"),),
            out="data/results.txt",
        ),
    )
] + [
    case(
        "fit-config-missing",
        "fit",
        content=None,
        names=(file("config.yaml"),),
        args=("--missing-config",),
        overwrite=False,
    ),
    case(
        "run-config-is-a-folder",
        "run",
        content=None,
        names=(file("data"),),
        args=("--config-is-data",),
        overwrite=False,
    ),
    case("fit-out-below-a-file", "fit", names=(file("results.txt"),), out="data/results.txt/run1"),
    case(
        "calibrate-out-below-a-file", "calibrate", names=(file("results.txt"),), out="data/results.txt/run1"
    ),
    case("diagnose-out-below-a-file", "diagnose", names=(file("results.txt"),), out="data/results.txt/run1"),
]


def _invoke_case(tmp_path: Path, c: Case) -> str:
    command = command_of(c.base)
    config = tmp_path / "config.yaml"
    args = [a for a in c.args if not a.startswith("--missing") and not a.startswith("--config-is")]
    if "--missing-config" in c.args:
        pass  # config.yaml is never written
    elif "--config-is-data" in c.args:
        config = tmp_path / "data"
    elif c.content is None:
        cfg = override(BASES[c.base](), c.changes)
        cfg["output"] = str(tmp_path / "config_output")
        config.write_text(yaml.safe_dump(cfg, sort_keys=False))
    elif isinstance(c.content, bytes):
        config.write_bytes(c.content)
    else:
        config.write_text(c.content)
    out = tmp_path / c.out
    if c.out in ("out", "mine"):
        out.mkdir()
        (out / "notes.txt").write_text("my notes: never to be deleted\n")
        if c.out == "mine":  # the user's own study config and model beside the outputs
            (out / "study.yaml").write_text("# my own study, with comments\ntrials: 2\n")
            (out / "model_mine.json").write_text('{"mine": true}\n')
    return expect_cli_error(
        tmp_path,
        [command, config, "--out", out, *(["--overwrite"] if c.overwrite else []), *args],
        c.names,
        out,
    )


@pytest.mark.parametrize("c", FIT)
def test_fit(tmp_path, data, c):
    _invoke_case(tmp_path, c)


@pytest.mark.parametrize("c", CALIBRATE)
def test_calibrate(tmp_path, data, c):
    _invoke_case(tmp_path, c)


@pytest.mark.parametrize("c", RUN)
def test_run(tmp_path, data, c):
    _invoke_case(tmp_path, c)


@pytest.mark.parametrize("c", STUDY)
def test_study(tmp_path, data, c):
    _invoke_case(tmp_path, c)


@pytest.mark.parametrize("c", DIAGNOSE)
def test_diagnose(tmp_path, data, c):
    _invoke_case(tmp_path, c)


@pytest.mark.parametrize("c", COMPENSATE)
def test_compensate(tmp_path, data, c):
    _invoke_case(tmp_path, c)


@pytest.mark.parametrize("c", PREDICT)
def test_predict(tmp_path, data, c):
    _invoke_case(tmp_path, c)


@pytest.mark.parametrize("c", GENERIC)
def test_any_command(tmp_path, data, c):
    _invoke_case(tmp_path, c)


def test_fit_out_folder_not_writable(tmp_path, data):
    """A read-only output folder is refused before the fit (skipped where the user can write
    anywhere, e.g. as root)."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("my notes\n")
    out.chmod(0o555)
    try:
        probe = out / ".probe"
        try:
            probe.write_text("")
            probe.unlink()
            pytest.skip("this user can write into a read-only folder (root)")
        except PermissionError:
            pass
        config = tmp_path / "config.yaml"
        config.write_text(yaml.safe_dump(BASES["fit"]()))
        expect_cli_error(tmp_path, ["fit", config, "--out", out, "--overwrite"], (file("out"),), out)
    finally:
        out.chmod(0o755)


# ---------------------------------------------------------------- the Python entry points


def _scan():
    """A small, valid CalibrationScan of a synthetic lattice (8 px pitch)."""
    from jaxafm.identify import CalibrationScan
    from jaxafm.instrument.afm import Raster

    raster = Raster((8000.0, 8000.0), 64, 64, line_rate=1.0)
    return CalibrationScan(lattice(), lattice(shift=0.3), raster, 1000.0, (500.0, 500.0), 10.0)


def _drive(n: int = 200, amplitude: float = 10.0):
    t = np.arange(n) * 1e-3
    u = amplitude * np.stack([np.sin(2 * np.pi * 5 * t), np.cos(2 * np.pi * 5 * t)], -1)
    return u, t


def _loop(n: int = 200):
    u = 5.0 + 4.0 * np.sin(np.linspace(0, 4 * np.pi, n))
    return u, 100.0 * u + 5.0 * np.cos(np.linspace(0, 4 * np.pi, n))


def _pi():
    from jaxafm import PrandtlIshlinskii

    return PrandtlIshlinskii.uniform(4, 4.0, 100.0)


def _afm_state():
    from jaxafm import default_afm

    afm = default_afm()
    return afm, afm.initial_state()


def _load_config(tmp_path, text, schema="RunConfig", name="config.yaml"):
    path = tmp_path / name
    path.write_bytes(text) if isinstance(text, bytes) else path.write_text(text)
    return lambda: configs.load_config(path, getattr(configs, schema))


def _yaml(base, changes):
    return yaml.safe_dump(override(BASES[base](), changes))


def _read_record(name, **kw):
    from jaxafm.instrument.records import read_record

    spec = (
        dict(
            delimiter=",",
            input_columns=["drive_v"],
            output_columns=["sensor_um"],
            time_column="time_s",
            output_unit="um",
        )
        | kw
    )
    return lambda d: read_record(d / name, **spec)


def _read_image(name, **kw):
    from jaxafm.instrument.images import read_image

    return lambda d: read_image(d / name, **kw)


def _load_model(name):
    from jaxafm.model.io import load_model

    return lambda d: load_model(d / name)


# (id, call(data folder) -> None, regex the message must hold, other exception types allowed)
FILES = [
    ("load_config-binary", lambda d: _load_config(d, BINARY)(), file("config.yaml"), ()),
    ("load_config-empty", lambda d: _load_config(d, "")(), file("config.yaml"), ()),
    ("load_config-yaml-list", lambda d: _load_config(d, "- a\n- b\n")(), file("config.yaml"), ()),
    ("load_config-missing", lambda d: configs.load_config(d / "nowhere.yaml"), file("nowhere.yaml"), ()),
    ("load_config-directory", lambda d: configs.load_config(d / "folder"), file("folder"), ()),
    (
        "load_config-run-centre-.nan",
        lambda d: _load_config(d, _yaml("run", {"workspace.centre_nm": [NAN, 0.0]}))(),
        key("workspace.centre_nm") + r"[\s\S]*" + NAN_RE,
        (),
    ),
    (
        "load_config-run-drift-.inf",
        lambda d: _load_config(d, _yaml("run", {"drift_nm_per_min": [INF, 0.0]}))(),
        key("drift_nm_per_min") + r"[\s\S]*" + INF_RE,
        (),
    ),
    (
        "load_config-calibrate-blur-negative",
        lambda d: _load_config(d, _yaml("calibrate", {"solver.blur_px": [-3]}), "CalibrateConfig")(),
        key("solver.blur_px") + r"[\s\S]*-3",
        (),
    ),
    (
        "load_config-calibrate-sensitivity-nan-string",
        lambda d: _load_config(
            d, _yaml("calibrate-data", {"data.sensitivity_nm_per_v": ["nan", 500]}), "CalibrateConfig"
        )(),
        key("data.sensitivity_nm_per_v") + r"[\s\S]*" + NAN_RE,
        (),
    ),
    (
        "load_config-study-distribution-.nan",
        lambda d: _load_config(d, _yaml("study", {"scanner.creep.gamma": {"fixed": NAN}}), "StudyConfig")(),
        key("scanner.creep.gamma") + r"[\s\S]*" + NAN_RE,
        (),
    ),
    (
        "load_config-diagnose-magnitude-.nan",
        lambda d: _load_config(d, _yaml("diagnose", {"simulate.magnitude": NAN}), "DiagnoseConfig")(),
        key("simulate.magnitude") + r"[\s\S]*" + NAN_RE,
        (),
    ),
    ("read_record-missing", lambda d: _read_record("nowhere.csv")(d), file("nowhere.csv"), (OSError,)),
    ("read_record-directory", lambda d: _read_record("folder")(d), file("folder"), (OSError,)),
    ("read_record-binary", lambda d: _read_record("binary.csv")(d), file("binary.csv"), ()),
    ("read_record-nan-rows", lambda d: _read_record("nan_rows.csv")(d), file("nan_rows.csv"), ()),
    (
        "read_record-sample_rate-inf",
        lambda d: _read_record("record.csv", time_column=None, sample_rate_hz=INF)(d),
        r"sample_rate_hz",
        (),
    ),
    (
        "read_record-sample_rate-nan",
        lambda d: _read_record("record.csv", time_column=None, sample_rate_hz=NAN)(d),
        r"sample_rate_hz",
        (),
    ),
    (
        "read_record-same-column-in-and-out",
        lambda d: _read_record("record.csv", output_columns=["drive_v"])(d),
        r"input_columns|output_columns",
        (),
    ),
    ("read_record-wrong-unit", lambda d: _read_record("record.csv", output_unit="furlong")(d), "furlong", ()),
    (
        "read_image-not-a-tiff",
        lambda d: _read_image("not_an_image.tif", size_nm=(1e3, 1e3))(d),
        file("not_an_image.tif"),
        (),
    ),
    (
        "read_image-not-a-nanosurf-text",
        lambda d: _read_image("not_an_image.txt")(d),
        file("not_an_image.txt"),
        (),
    ),
    ("read_image-png", lambda d: _read_image("photo.png")(d), file("photo.png"), ()),
    ("read_image-missing", lambda d: _read_image("nowhere.txt")(d), file("nowhere.txt"), (OSError,)),
    ("read_image-directory", lambda d: _read_image("folder")(d), file("folder"), (OSError,)),
    ("read_image-binary-npz", lambda d: _read_image("binary.csv")(d), file("binary.csv"), ()),
    ("read_image-nan-pixel", lambda d: _read_image("nan_image.txt")(d), file("nan_image.txt"), ()),
    ("read_image-wrong-z-unit", lambda d: _read_image("volts.txt")(d), file("volts.txt"), ()),
    # issue 41, item 10: a jaxafm image file's own errors name the file, not the source it was made from
    (
        "read_image-npz-nan-pixel",
        lambda d: _read_image("nan_pixel.npz")(d),
        r"^\S*" + file("nan_pixel.npz"),
        (),
    ),
    (
        "read_image-npz-zero-pixel-size",
        lambda d: _read_image("zero_pixel.npz")(d),
        r"^\S*" + file("zero_pixel.npz"),
        (),
    ),
    ("load_model-truncated", lambda d: _load_model("truncated.json")(d), file("truncated.json"), ()),
    ("load_model-not-json", lambda d: _load_model("not_json.json")(d), file("not_json.json"), ()),
    ("load_model-binary", lambda d: _load_model("binary.json")(d), file("binary.json"), ()),
    ("load_model-json-list", lambda d: _load_model("list.json")(d), file("list.json"), ()),
    ("load_model-other-json", lambda d: _load_model("other.json")(d), file("other.json"), ()),
    (
        "load_model-negative-weight",
        lambda d: _load_model("negative_weight.json")(d),
        file("negative_weight.json"),
        (),
    ),
    ("load_model-nan-weight", lambda d: _load_model("nan_weight.json")(d), file("nan_weight.json"), ()),
    ("load_model-missing", lambda d: _load_model("nowhere.json")(d), file("nowhere.json"), (OSError,)),
    ("load_model-directory", lambda d: _load_model("folder")(d), file("folder"), (OSError,)),
]


@pytest.mark.parametrize("call, match, also", [pytest.param(*f[1:], id=f[0]) for f in FILES])
def test_files(data, call, match, also):
    before = snapshot(data)
    expect_value_error(lambda: call(data), match, also)
    assert_unchanged(before, snapshot(data), "reading a bad file changed a file")


def test_load_model_unknown_type(tmp_path, model_doc):
    doc = copy.deepcopy(model_doc)
    doc["model"]["fields"]["noise"]["type"] = "Wobble"
    (tmp_path / "wobble.json").write_text(json.dumps(doc))
    expect_value_error(lambda: _load_model("wobble.json")(tmp_path), file("wobble.json") + r"[\s\S]*Wobble")


def test_load_model_renamed_field(tmp_path, model_doc):
    doc = copy.deepcopy(model_doc)
    fields = doc["model"]["fields"]["noise"]["fields"]
    fields["sigma"] = fields.pop("std")
    (tmp_path / "renamed.json").write_text(json.dumps(doc))
    expect_value_error(lambda: _load_model("renamed.json")(tmp_path), file("renamed.json"))


def test_save_model_into_a_folder_that_is_a_file(tmp_path, data):
    from jaxafm import default_scanner
    from jaxafm.model.io import save_model

    before = snapshot(data)
    expect_value_error(
        lambda: save_model(default_scanner(), data / "results.txt" / "model.json"),
        file("results.txt"),
        (OSError,),
    )
    assert_unchanged(before, snapshot(data))


def _call(name, *args, **kwargs):
    import jaxafm

    return lambda: getattr(jaxafm, name)(*args, **kwargs)


def _scanner_drive(u_nan=False, t_nan=False):
    import jax

    from jaxafm import default_scanner

    u, t = _drive()
    if u_nan:
        u[10, 0] = NAN
    if t_nan:
        t = t.copy()
        t[5] = NAN
    return lambda: default_scanner()(u, t, key=jax.random.key(0))


def _raster(**kw):
    from jaxafm import Raster

    spec = dict(size=(1000.0, 1000.0), pixels=8, lines=8) | kw
    return lambda: Raster(**spec)


def _raster_scan(**kw):
    import jax

    from jaxafm import Plane, Raster, raster_scan

    def go():
        afm, state = _afm_state()
        raster = Raster(**(dict(size=(1000.0, 1000.0), pixels=8, lines=4, line_rate=10.0) | kw))
        return raster_scan(afm, Plane(), state, raster, key=jax.random.key(0))

    return go


def _move(target):
    import jax

    from jaxafm import Plane, move

    def go():
        afm, state = _afm_state()
        return move(afm, Plane(), state, np.asarray(target, dtype=float), key=jax.random.key(0))

    return go


def _line_scan(**kw):
    import jax

    from jaxafm import Plane, line_scan

    def go():
        afm, state = _afm_state()
        spec = dict(start=[0.0, 0.0], end=[500.0, 0.0], points=16, speed=1000.0) | kw
        return line_scan(afm, Plane(), state, key=jax.random.key(0), **spec)

    return go


def _fit(u=None, d=None, **kw):
    from jaxafm.identify import fit_operator

    def go():
        uu, dd = _loop()
        return fit_operator(_pi(), uu if u is None else u, dd if d is None else d, **({"max_steps": 5} | kw))

    return go


def _identify(**kw):
    """``identify`` of a small model; ``kw`` overrides fields of its ScanModelSpec or FitPlan."""
    from jaxafm.identify import FitPlan, ScanModelSpec, identify

    given = {"kind": "pi", "operators": 4, "effects": (), "max_steps": 1, "blur_px": (1.0,)} | kw
    fields = {cls: {f.name for f in dataclasses.fields(cls)} for cls in (ScanModelSpec, FitPlan)}
    assert set(given) <= set.union(*fields.values()), set(given) - set.union(*fields.values())
    pick = lambda cls: cls(**{k: v for k, v in given.items() if k in fields[cls]})
    return lambda: identify(_scan(), pick(ScanModelSpec), pick(FitPlan), log=lambda *a: None)


def _calibration_scan(**kw):
    from jaxafm.identify import CalibrationScan
    from jaxafm.instrument.afm import Raster

    spec = dict(pitch=1000.0, sensitivity=(500.0, 500.0), u_max=10.0) | kw
    raster = Raster((8000.0, 8000.0), 64, 64, line_rate=1.0)
    return lambda: CalibrationScan(
        lattice(), lattice(), raster, spec["pitch"], spec["sensitivity"], spec["u_max"]
    )


def _initial_state(history):
    def go():
        afm, _ = _afm_state()
        return afm.initial_state(history=history)

    return go


_CONSTANT = np.full(200, 3.0)
# (id, a factory of the call, regex the message must hold)
PYTHON = [
    (
        "default_scanner-drift-.nan",
        lambda: _call("default_scanner", drift_nm_per_min=(NAN, 0.0)),
        r"drift_nm_per_min",
    ),
    (
        "default_scanner-drift-inf",
        lambda: _call("default_scanner", drift_nm_per_min=(0.0, INF)),
        r"drift_nm_per_min",
    ),
    ("default_scanner-loop_width-negative", lambda: _call("default_scanner", loop_width=-0.1), r"loop_width"),
    ("default_scanner-u_range-zero", lambda: _call("default_scanner", u_range=0.0), r"u_range"),
    ("default_scanner-travel-inf", lambda: _call("default_scanner", travel=INF), r"travel"),
    ("default_scanner-noise_std-negative", lambda: _call("default_scanner", noise_std=-1.0), r"noise_std"),
    ("default_scanner-creep_gamma-nan", lambda: _call("default_scanner", creep_gamma=NAN), r"creep_gamma"),
    ("default_scanner-coupling-nan", lambda: _call("default_scanner", coupling=NAN), r"coupling"),
    ("scanner-drive-nan", lambda: _scanner_drive(u_nan=True), r"\bu\b|drive"),
    ("scanner-times-nan", lambda: _scanner_drive(t_nan=True), r"\bt\b|times"),
    ("default_afm-tip_radius-negative", lambda: _call("default_afm", tip_radius=-10.0), r"tip_radius"),
    ("default_afm-feedback_tau-nan", lambda: _call("default_afm", feedback_tau=NAN), r"feedback_tau"),
    (
        "default_afm-tip_half_angle-95",
        lambda: _call("default_afm", tip_half_angle_deg=95.0),
        r"tip_half_angle",
    ),
    ("default_afm-u_range-negative", lambda: _call("default_afm", u_range=-10.0), r"u_range"),
    ("Raster-centre-nan", lambda: _raster(centre=(NAN, 0.0)), r"centre"),
    ("Raster-centre-inf", lambda: _raster(centre=(0.0, INF)), r"centre"),
    ("Raster-pixels-nan", lambda: _raster(pixels=NAN), r"pixels"),
    ("Raster-size-nan", lambda: _raster(size=(NAN, 1000.0)), r"size"),
    ("Raster-line_rate-inf", lambda: _raster(line_rate=INF), r"line_rate"),
    ("Raster-overscan-nan", lambda: _raster(overscan=NAN), r"overscan"),
    ("raster_scan-nan-centre", lambda: _raster_scan(centre=(NAN, 0.0)), r"centre"),
    ("raster_scan-beyond-the-range", lambda: _raster_scan(size=(50_000.0, 50_000.0)), r"range"),
    ("move-u_target-nan", lambda: _move([NAN, 0.0]), r"u_target"),
    ("move-u_target-far-outside-the-range", lambda: _move([100.0, 0.0]), r"range"),
    ("line_scan-start-nan", lambda: _line_scan(start=[NAN, 0.0]), r"start"),
    ("line_scan-speed-nan", lambda: _line_scan(speed=NAN), r"speed"),
    ("initial_state-history-nan", lambda: _initial_state([[NAN, 0.0], [10.0, 10.0]]), r"history"),
    ("fit_operator-constant-output", lambda: _fit(d=np.full(200, 42.0)), r"\bd\b"),
    ("fit_operator-constant-input", lambda: _fit(u=_CONSTANT), r"\bu\b"),
    ("fit_operator-nan-input", lambda: _fit(u=np.where(np.arange(200) == 7, NAN, _loop()[0])), r"\bu\b"),
    ("fit_operator-inf-output", lambda: _fit(d=np.where(np.arange(200) == 7, INF, _loop()[1])), r"\bd\b"),
    ("fit_operator-lengths-differ", lambda: _fit(d=_loop()[1][:150]), r"\bu\b[\s\S]*\bd\b|\bd\b[\s\S]*\bu\b"),
    ("fit_operator-max_steps-zero", lambda: _fit(max_steps=0), r"max_steps"),
    ("fit_operator-settle-negative", lambda: _fit(settle=-5), r"settle"),
    ("fit_operator-unknown-solver", lambda: _fit(solver="newton"), r"newton"),
    ("identify-blur_px-negative", lambda: _identify(blur_px=(-3.0,)), r"blur_px"),
    ("identify-blur_px-nan", lambda: _identify(blur_px=(2.0, NAN)), r"blur_px"),
    ("identify-max_steps-zero", lambda: _identify(max_steps=0), r"max_steps"),
    (
        "identify-path_tolerance_nm-negative",
        lambda: _identify(path_tolerance_nm=-2.0),
        r"path_tolerance_nm[\s\S]*-2",
    ),
    (
        "identify-path_tolerance_nm-nan",
        lambda: _identify(path_tolerance_nm=NAN),
        r"path_tolerance_nm[\s\S]*nan",
    ),
    ("identify-unknown-solver", lambda: _identify(solver="newton"), r"newton"),
    ("identify-unknown-kind", lambda: _identify(kind="bouc-wen"), r"bouc-wen"),
    ("identify-unknown-effect", lambda: _identify(effects=("wobble",)), r"wobble"),
    ("identify-operators-zero", lambda: _identify(operators=0), r"operators"),
    ("identify-coarsen-zero", lambda: _identify(coarsen=0), r"coarsen[\s\S]*\b0\b"),
    ("identify-coarsen-not-dividing", lambda: _identify(coarsen=3), r"coarsen[\s\S]*\b3\b[\s\S]*64"),
    ("identify-coarsen-too-coarse", lambda: _identify(coarsen=8), r"coarsen[\s\S]*\b8\b[\s\S]*pitch"),
    ("CalibrationScan-pitch-nan", lambda: _calibration_scan(pitch=NAN), r"pitch"),
    (
        "CalibrationScan-sensitivity-negative",
        lambda: _calibration_scan(sensitivity=(-500.0, 500.0)),
        r"sensitivity",
    ),
    ("CalibrationScan-u_max-inf", lambda: _calibration_scan(u_max=INF), r"u_max"),
]


@pytest.mark.parametrize("factory, match", [pytest.param(*p[1:], id=p[0]) for p in PYTHON])
def test_python(factory, match):
    expect_value_error(factory(), match)


# ---------------------------------------------------------------- issue 41: the last silent answers


def test_first_row_against_the_files_scan_direction():
    """Item 7: a .nid file whose header says the scan went Up has its row 0 at the bottom;
    ``first_row="top"`` contradicts it and is refused, as a contradicting size or height unit is."""
    from jaxafm.config import resolve_data_path
    from jaxafm.instrument.images import read_image

    path = resolve_data_path(LATTICE, Path("."))
    expect_value_error(lambda: read_image(path, first_row="top"), r"first_row[\s\S]*top[\s\S]*Up")
    assert read_image(path, first_row="bottom").shape == read_image(path).shape  # agreeing: fine


def _drive_of(volts: float, n: int = 200):
    t = np.arange(n) * 1e-3
    return volts * np.stack([np.sin(2 * np.pi * 5 * t), np.cos(2 * np.pi * 5 * t)], -1), t


@pytest.mark.parametrize("call", ["scanner", "predict"])
def test_a_drive_far_beyond_the_scanners_range_warns(call):
    """Item 8: a +-10 V scanner driven over +-100 V answers with a warning that names the drive's
    range and the span the scanner's hysteresis covers; within its range, no warning."""
    import warnings

    import jax

    from jaxafm import default_scanner, predict

    scanner = default_scanner(u_range=10.0)
    apply = {
        "scanner": lambda u, t: scanner(u, t, key=jax.random.key(0)),
        "predict": lambda u, t: predict(scanner, u, t),
    }[call]
    with pytest.warns(UserWarning, match=r"-100(\.0)? to 100(\.0)? V[\s\S]*20(\.0)? V"):
        apply(*_drive_of(100.0))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        apply(*_drive_of(10.0))


def test_a_model_files_non_finite_parameter_is_named_as_one():
    """Item 15 (last part): a NaN weight in a model file is a broken file (edited by hand?), not
    a record's bad samples: the message names the file and the parameter, and gives no advice
    about samples."""
    from jaxafm.model.io import load_model

    with tempfile.TemporaryDirectory() as d:
        from jaxafm import default_scanner
        from jaxafm.model.io import save_model

        save_model(default_scanner(), Path(d) / "m.json")
        doc = nan_weight(json.loads((Path(d) / "m.json").read_text()))
        (Path(d) / "nan.json").write_text(json.dumps(doc))
        message = expect_value_error(
            lambda: load_model(Path(d) / "nan.json"), file("nan.json") + r"[\s\S]*weights"
        )
    assert "samples" not in message, message


def _afm_call(name: str, **wrong):
    import jax

    from jaxafm import Plane, Raster, default_afm, line_scan, move, raster_scan

    def go():
        afm = default_afm()
        given = {"sample": Plane(), "state": afm.initial_state()} | wrong
        if name == "raster_scan":
            raster = Raster(size=(1000.0, 1000.0), pixels=8, lines=4, line_rate=10.0)
            return raster_scan(afm, given["sample"], given["state"], raster, key=jax.random.key(0))
        if name == "move":
            return move(afm, given["sample"], given["state"], np.zeros(2), key=jax.random.key(0))
        return line_scan(
            afm, given["sample"], given["state"], [0.0, 0.0], [100.0, 0.0], 8, 100.0, key=jax.random.key(0)
        )

    return go


def _empty(call: str):
    import jax

    from jaxafm import default_scanner, predict

    s = default_scanner()
    return {
        "scanner": lambda: s(np.zeros((0, 2)), np.zeros(0), key=jax.random.key(0)),
        "scanner.run": lambda: s.run(
            np.zeros((0, 2)), np.zeros(0), s.initial_state(np.zeros(2)), jax.random.key(0)
        ),
        "axis": lambda: s.x(np.zeros(0), np.zeros(0)),
        "operator": lambda: s.x.hysteresis(np.zeros(0)),
        "predict": lambda: predict(s, np.zeros((0, 2)), np.zeros(0)),
    }[call]


@pytest.mark.parametrize("call", ["scanner", "scanner.run", "axis", "operator", "predict"])
def test_an_empty_drive_is_named(call):
    """Item 11: a scanner, an axis or an operator called with no samples names the input."""
    expect_value_error(_empty(call), r"\bu\b[\s\S]*no samples|no samples[\s\S]*\bu\b")


@pytest.mark.parametrize("name", ["raster_scan", "move", "line_scan"])
@pytest.mark.parametrize(
    "wrong", [{"state": None}, {"state": "state"}, {"sample": None}, {"sample": "plane"}]
)
def test_a_scan_with_no_sample_or_state_names_it(name, wrong):
    """Item 11: ``None`` or a string where the sample or the state belongs names the argument
    and what it must be (a TypeError: the wrong kind of object)."""
    (argument,) = wrong
    expect_value_error(
        _afm_call(name, **wrong), rf"\b{argument}\b[\s\S]*{type(wrong[argument]).__name__}", (TypeError,)
    )
