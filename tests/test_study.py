"""Monte-Carlo studies: config checks, the image-position finder, results that do not depend
on chunk size or device count, resuming after a kill, and a small study through step C."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import yaml
from jax.sharding import Mesh

from jaxafm.cli import app
from jaxafm.config import ConfigError, StudyConfig, load_config
from jaxafm import study
from jaxafm.study import image_position, run

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "experiments" / "results" / "paper" / "model_scanner.json"  # step A's model of default_afm

SMALL = {
    "trials": 6, "trials_per_scanner": 3, "chunk": 2, "stages": ["A+B"],
    "scanner": {"hysteresis": {"loop_width": {"uniform": [0.1, 0.2]}}, "drift": {"x_nm_per_min": {"normal": [0, 3]}}},
    "particle_radius_nm": {"uniform": [10, 30]},
    "calibration": {"simulate": {"pixels": 32, "size_nm": 8000, "line_rate_hz": 2.0}, "model_file": str(MODEL)},
    "workspace": {"size_nm": 1500, "pixels": 96, "line_rate_hz": 8.0},
    "landmarks": {"n": 3, "start_px": 15, "step_px": 33, "interpolation": ["polynomial"], "m": 4, "degree": 2},
    "local_scan": {"points": 128},
}


def write(tmp_path: Path, name: str = "study.yaml", **changes) -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(SMALL | changes))
    return path


def results(folder: Path) -> dict:
    return dict(np.load(folder / "trials.npz"))


def assert_same(got: dict, want: dict, where: str = "") -> None:
    """Equal columns: flags and counts exactly, numbers to 1e-9 relative (differently compiled
    programs may round differently; on one machine the runs below agree bit for bit)."""
    assert set(got) == set(want)
    for k, v in want.items():
        np.testing.assert_allclose(got[k], v, rtol=1e-9, atol=1e-12, err_msg=f"{where} {k}")


def cli(*args, cache: Path) -> subprocess.Popen:
    """``jaxafm study ARGS`` in a new process; the processes share a compilation cache."""
    env = os.environ | {"JAX_COMPILATION_CACHE_DIR": str(cache), "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0"}
    return subprocess.Popen([sys.executable, "-c", "from jaxafm.cli import main; main()", "study", *map(str, args)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)


@pytest.mark.parametrize("change, key", [
    ({"particle_radius_nm": {"uniform": [-5, 10]}}, "particle_radius_nm"),
    ({"particle_radius_nm": {"uniform": [30, 10]}}, "min <= max"),
    ({"scanner": {"hysterisis": {"loop_width": 0.1}}}, "unknown effect 'hysterisis'"),
    ({"scanner": {"creep": {"gamma": {"normal": [0.01, 0.01]}}}}, "scanner.creep.gamma"),
    ({"scanner": {"noise": {"sigma": 1.0}}}, "scanner.noise.sigma"),
    ({"stages": ["push"]}, "'push' goes on from 'A+B+C'"),
])
def test_impossible_configs_fail_naming_the_key(tmp_path, change, key):
    path = write(tmp_path, **change)
    with pytest.raises(ConfigError, match=key.replace("+", r"\+").replace("[", r"\[")):
        load_config(path, StudyConfig)


def test_bad_config_fails_before_any_trial(tmp_path):
    from typer.testing import CliRunner

    out = tmp_path / "out"
    res = CliRunner().invoke(app, ["study", str(write(tmp_path, particle_radius_nm={"uniform": [-1, 5]})),
                                   "--out", str(out)])
    assert res.exit_code == 2 and "particle_radius_nm" in res.output and not out.exists()


def test_image_position_inverts_a_distorted_raster():
    """A survey whose true path is an affine map A p + b of the wanted pixel positions p: the
    particle at c appears at A^-1 (c - b) (exact: one Newton step on an affine map); one beyond
    the imaged area is not in the image."""
    origin, pixel = np.array([-500.0, -400.0]), np.array([7.0, 7.5])
    i, j = np.mgrid[0:64, 0:80]
    wanted = origin + np.stack([j, i], -1) * pixel
    A, b = np.array([[1.03, 0.02], [-0.01, 0.97]]), np.array([12.0, -8.0])
    path = wanted @ A.T + b
    c = np.array([-180.0, -40.0])
    got, inside = image_position(jnp.asarray(path), jnp.asarray(origin), jnp.asarray(pixel), jnp.asarray(c))
    np.testing.assert_allclose(got, np.linalg.solve(A, c - b), atol=1e-9)
    assert inside
    outside = np.array([-180.0, 900.0])  # beyond the last line: not in the image
    assert not image_position(jnp.asarray(path), jnp.asarray(origin), jnp.asarray(pixel), jnp.asarray(outside))[1]


@pytest.fixture(scope="module")
def baseline(tmp_path_factory):
    """The small study run uninterrupted, in this process (one CPU device), chunks of 2."""
    tmp = tmp_path_factory.mktemp("baseline")
    path = write(tmp)
    cfg = load_config(path, StudyConfig)
    metrics = run(cfg, path, tmp / "out", log=lambda m: None)
    return tmp / "out", metrics


def test_outputs_and_trial_file(baseline):
    out, metrics = baseline
    for f in ("metrics.json", "trials.csv", "trials.npz", "errors.png", "study.yaml", "scanners.json"):
        assert (out / f).is_file()
    table = np.genfromtxt(out / "trials.csv", delimiter=",", names=True)
    assert table.shape == (6,) and set(table["scanner"]) == {0, 1}
    np.testing.assert_allclose(table["AB_error_nm"], results(out)["AB_error_nm"], rtol=1e-9)
    assert metrics["trials"] == 6 and metrics["AB_error_median_nm"] > 0 and metrics["AB_error_p99_nm"] > 0
    assert 0 < metrics["AB_ran_pct"] <= 100  # one of the two drawn scanners may miss landmarks


def test_same_results_for_other_chunks_and_two_devices(baseline, tmp_path):
    """Chunks of 3 on two host devices, in a process with two (XLA_FLAGS), give the baseline's
    results (chunks of 2 on one device, in this process)."""
    path = write(tmp_path, chunk=3)
    script = f"""
import jax
from pathlib import Path
from jaxafm.config import load_config, StudyConfig
from jaxafm.study import run
assert len(jax.devices()) == 2
path = Path(r"{path}")
run(load_config(path, StudyConfig), path, Path(r"{tmp_path / 'two'}"), log=lambda m: None)
"""
    env = os.environ | {"XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    done = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    want = results(baseline[0])
    assert_same(results(tmp_path / "two"), want, "two devices")


def test_killed_study_resumes_to_the_same_results(baseline, tmp_path):
    path, out = write(tmp_path), tmp_path / "out"
    proc = cli(path, "--out", out, cache=tmp_path / "cache")
    chunks = out / "chunks"
    while proc.poll() is None and not any(chunks.glob("*.npz")):
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    first = sorted(chunks.glob("*.npz"))
    assert 1 <= len(first) < 4, "the study ended before it could be killed"
    stamps = {f.name: f.stat().st_mtime_ns for f in first}
    again = cli(path, "--out", out, cache=tmp_path / "cache")  # without --resume: refused, nothing touched
    assert again.wait() == 2 and "not empty" in again.stdout.read()
    resumed = cli(path, "--out", out, "--resume", cache=tmp_path / "cache")
    log = resumed.communicate()[0]
    assert resumed.returncode == 0, log[-3000:]
    done = sum(int(f.stem.split("_")[2]) - int(f.stem.split("_")[1]) for f in first)
    assert f"resuming: {done} done" in log
    assert {f.name: f.stat().st_mtime_ns for f in first} == stamps  # done chunks not recomputed
    assert_same(results(out), results(baseline[0]))


def test_resume_refuses_a_changed_config(baseline, tmp_path):
    import shutil

    out = tmp_path / "out"
    shutil.copytree(baseline[0], out)
    path = write(tmp_path, seed=7)
    cfg = load_config(path, StudyConfig)
    with pytest.raises(ValueError, match="keys: seed"):
        run(cfg, path, out, log=lambda m: None, resume=True)


def test_study_through_step_c_and_the_push(tmp_path, monkeypatch):
    """The nominal scanner (the one the stored model was identified on), four trials through A+B,
    the local scan and the push: step C brings the tip within 0.1 R of the true centre, far closer
    than A+B alone, and the push carries the particle to near its goal (100-300 nm away)."""
    path = write(tmp_path, trials=4, trials_per_scanner=4, chunk=4, stages=["A+B", "A+B+C", "push"], scanner={})
    cfg = load_config(path, StudyConfig)
    contexts, _ = study.prepare_scanner(cfg, path, 0, study.scanner_draws(cfg)[0], tmp_path, lambda m: None)
    draws = study.trial_draws(cfg, study._layout(cfg)[2])
    mesh = Mesh(np.array(jax.devices()[:1]), ("trials",))
    r = study.run_chunk(cfg, contexts, draws, mesh)
    # measured: A+B 16-25 nm, A+B+C 0.8-1.1 nm in 3 lines each, push misses 6-14 nm
    assert np.all(r["ABC_found"])
    assert np.all(r["ABC_error_nm"] < 0.1 * draws["radius_nm"])
    assert np.median(r["ABC_error_nm"]) < np.median(r["AB_error_nm"]) / 5
    assert np.all(r["push_contact"]) and np.all(r["push_error_nm"] < 0.1 * draws["push_distance_nm"])
    # a first pass of 2 lines stops every local scan early; the second pass, from the start with
    # every line, then gives what the first pass of 6 lines gave (measured: to 1.1e-12 nm)
    monkeypatch.setattr(study, "FIRST_PASS_LINES", 2)
    assert_same(study.run_chunk(cfg, contexts, draws, mesh), r)
