"""Monte-Carlo studies: config checks, the image-position finder, results that do not depend
on chunk size or device count, resuming after a kill, and a small study through step C."""

import dataclasses
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import yaml
from jax.sharding import Mesh
from matplotlib.backends.backend_agg import FigureCanvasAgg
from typer.testing import CliRunner

from jaxafm.cli import app
from jaxafm.config import ConfigError, StudyConfig, load_config
from jaxafm.instrument.afm import default_afm
from jaxafm.jobs import Output
from jaxafm.jobs import study as job
from jaxafm.jobs.run import workspace_layout
from jaxafm.model.io import save_model
from jaxafm.plots import _plain_log_ticks, subplots
from jaxafm.position import survey
from jaxafm.position.online import learn_field, learn_push, quadratic
from jaxafm.study import monte_carlo as study
from jaxafm.study.learning import learning_rounds, position_coverage, rayleigh_radius
from jaxafm.study.monte_carlo import Unsurveyed, image_position, nearest_pixel

# step A's model, written beside each config by write() (no committed result is read): the
# nominal scanner with a known misfit, its major loops 12 % of range wide where the instrument's
# are 15 % (a path-dependent error the landmarks cannot take out), drift and noise left out
MODEL = "model_scanner.json"

SMALL = {
    "trials": 6,
    "trials_per_scanner": 3,
    "chunk": 2,
    "stages": ["A+B"],
    "scanner": {
        "hysteresis": {"loop_width": {"uniform": [0.1, 0.2]}},
        "drift": {"x_nm_per_min": {"normal": [0, 3]}},
    },
    "particle_radius_nm": {"uniform": [10, 30]},
    "calibration": {
        "simulate": {"pixels": 32, "size_nm": 8000, "line_rate_hz": 2.0},
        "model_file": MODEL,
    },
    "workspace": {"size_nm": 1500, "pixels": 96, "line_rate_hz": 8.0},
    "landmarks": {
        "n": 3,
        "start_px": 15,
        "step_px": 33,
        "interpolation": ["polynomial"],
        "m": 4,
        "degree": 2,
    },
    "local_scan": {"points": 128},
}


# the baseline study's scanners: the fitted model's class, then a Preisach plane
CLASSES = ["generalised_pi", "preisach"]


def write(tmp_path: Path, name: str = "study.yaml", **changes) -> Path:
    """SMALL with ``changes`` as ``tmp_path / name``, and step A's model (``MODEL``) beside it."""
    save_model(default_afm(loop_width=0.12).scanner.without("drift", "noise"), tmp_path / MODEL)
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


def cli(*args, devices: int = 1) -> subprocess.Popen:
    """``jaxafm study ARGS`` in a new process with ``devices`` host devices (XLA_FLAGS)."""
    env = os.environ | {"XLA_FLAGS": f"--xla_force_host_platform_device_count={devices}"}
    return subprocess.Popen(
        [sys.executable, "-c", "from jaxafm.cli import main; main()", "study", *map(str, args)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
    )


def chunk_files(out: Path) -> list:
    return sorted((out / "chunks").glob("trials_*.npz"))  # not a chunk still being written (.tmp...)


@pytest.mark.parametrize(
    "change, key",
    [
        ({"particle_radius_nm": {"uniform": [-5, 10]}}, "particle_radius_nm"),
        ({"particle_radius_nm": {"uniform": [30, 10]}}, "min <= max"),
        ({"scanner": {"hysterisis": {"loop_width": 0.1}}}, "unknown effect 'hysterisis'"),
        ({"scanner": {"creep": {"gamma": {"normal": [0.01, 0.01]}}}}, "scanner.creep.gamma"),
        ({"scanner": {"noise": {"sigma": 1.0}}}, "scanner.noise.sigma"),
        ({"stages": ["push"]}, "'push' goes on from 'A+B+C'"),
        ({"truth_classes": ["presiach"]}, "truth_classes"),
        ({"truth_classes": ["preisach", "preisach"]}, "names a class twice"),
        (
            {"scanner": {"vibration": {"frequency_hz": {"uniform": [100, 200]}}}},
            "scanner.vibration: only scanners of the truth class 'resonant'",
        ),
        ({"learning": {"round_trials": 8}}, "learning: step C's finds"),
        ({"stages": ["A+B", "A+B+C"], "learning": {"round_trials": 0}}, "learning.round_trials"),
        ({"stages": ["A+B", "A+B+C"], "learning": {"round_trials": 3}}, "chunk: 2 is not a whole number"),
        ({"stages": ["A+B", "A+B+C"], "learning": {"round_trials": 2, "pushes": True}}, "learning.pushes"),
        (
            {
                "stages": ["A+B", "A+B+C", "push"],
                "push": {"corrections": 0},
                "learning": {"round_trials": 2, "pushes": True},
            },
            "push.corrections >= 1",
        ),
        (
            {"stages": ["A+B", "A+B+C"], "learning": {"round_trials": 2, "min_push_odds": 0.99}},
            "learning.min_push_odds: 0.99 gates the pushes",
        ),
        (
            {"stages": ["A+B", "A+B+C"], "learning": {"round_trials": 2, "min_push_odds": 1.5}},
            "min_push_odds",
        ),
    ],
)
def test_impossible_configs_fail_naming_the_key(tmp_path, change, key):
    path = write(tmp_path, **change)
    with pytest.raises(ConfigError, match=key.replace("+", r"\+").replace("[", r"\[")):
        load_config(path, StudyConfig)


def test_bad_config_fails_before_any_trial(tmp_path):
    out = tmp_path / "out"
    res = CliRunner().invoke(
        app, ["study", str(write(tmp_path, particle_radius_nm={"uniform": [-1, 5]})), "--out", str(out)]
    )
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
    assert not image_position(
        jnp.asarray(path), jnp.asarray(origin), jnp.asarray(pixel), jnp.asarray(outside)
    )[1]


def test_nearest_pixel_is_the_nearest_of_all_pixels_on_a_distorted_raster():
    """Coarse to fine against the search of every pixel, on a 256 x 256 raster with a hysteretic
    fast axis (a 6 % bulge), a 2 % skew and a slow-axis scale that drifts by 5 %, at 2000 points
    inside it, near its edges and far outside."""
    i, j = np.mgrid[0:256, 0:256].astype(float)
    x = 10.0 * (j + 0.06 * 256 * np.sin(np.pi * j / 255) * (1 - j / 255)) + 0.02 * 10 * i
    y = 10.0 * i * (1 + 0.05 * i / 255)
    path = jnp.asarray(np.stack([x, y], -1))
    rng = np.random.default_rng(0)
    points = rng.uniform([-800, -800], [3400, 3500], (2000, 2))
    got = np.stack(jax.vmap(lambda p: jnp.stack(nearest_pixel(path, p)))(jnp.asarray(points)))
    flat = np.asarray(path).reshape(-1, 2)
    every = np.concatenate(  # the search of every pixel, 100 points at a time
        [((flat[None] - p[:, None]) ** 2).sum(-1).argmin(1) for p in np.split(points, 20)]
    )
    np.testing.assert_array_equal(got, np.stack(np.divmod(every, 256), -1))


@pytest.fixture(scope="module")
def baseline(tmp_path_factory):
    """The small study run uninterrupted, in this process (one CPU device), chunks of 2. Then
    the study that test_killed_two_device_study_resumes_to_the_same_results resumes starts in
    its own process, to run while the tests after this one do (a thread kills it)."""
    tmp = tmp_path_factory.mktemp("baseline")
    path = write(tmp, truth_classes=CLASSES)
    cfg = load_config(path, StudyConfig)
    metrics = job.run(cfg, path, Output(tmp / "out"), log=lambda m: None)
    killed = start_killed(tmp_path_factory.mktemp("killed"))
    yield tmp / "out", metrics, killed
    killed[2].kill()  # a no-op once the thread has killed it
    killed[3].join()
    killed[2].stdout.close()


def start_killed(tmp: Path) -> tuple:
    """``jaxafm study`` in chunks of 3 (two chunks, a scanner each) in a process with two host
    devices, and a thread that kills it (SIGKILL) as soon as its first chunk is written."""
    path, out = write(tmp, chunk=3, truth_classes=CLASSES), tmp / "out"
    proc = cli(path, "--out", out, devices=2)

    def kill_after_the_first_chunk():
        while proc.poll() is None and not chunk_files(out):
            time.sleep(0.05)
        proc.send_signal(signal.SIGKILL)
        proc.wait()

    watcher = threading.Thread(target=kill_after_the_first_chunk, daemon=True)
    watcher.start()
    return path, out, proc, watcher


def test_outputs_and_trial_file(baseline):
    out, metrics, _ = baseline
    for f in ("metrics.json", "trials.csv", "trials.npz", "errors.png", "scanners.json"):
        assert (out / f).is_file()
    table = np.genfromtxt(out / "trials.csv", delimiter=",", names=True)
    assert table.shape == (6,) and set(table["scanner"]) == {0, 1}
    np.testing.assert_allclose(table["AB_error_nm"], results(out)["AB_error_nm"], rtol=1e-9)
    assert metrics["trials"] == 6 and metrics["AB_error_median_nm"] > 0 and metrics["AB_error_p99_nm"] > 0
    assert 0 < metrics["AB_ran_pct"] <= 100  # one of the two drawn scanners may miss landmarks
    scanners = json.loads((out / "scanners.json").read_text())
    assert [scanners[s]["truth_class"] for s in ("0", "1")] == CLASSES
    # the run's time in two parts, each scanner's and their sums, within the whole command's
    for k in ("step_a_and_surveys_s", "trials_s"):
        assert all(v[k] > 0 for v in scanners.values())
        assert metrics[k] == pytest.approx(sum(v[k] for v in scanners.values()))
    assert metrics["step_a_and_surveys_s"] + metrics["trials_s"] <= metrics["wall_s"]
    for s, truth in enumerate(CLASSES):  # each class's success from its scanner's trials
        mine = table["scanner"] == s
        ok = table["AB_error_nm"][mine] <= 0.1 * table["radius_nm"][mine]
        assert metrics["truth_classes"][truth] == {
            "trials": 3,
            "AB_success_pct": pytest.approx(100 * ok.mean()),
        }


def test_scanners_take_the_truth_classes_in_turn(tmp_path):
    """Scanner s is of class s mod 4 and holds only its class's parameters; the family's draws
    are those of a study of one class (another class draws the same loops, creep, ...)."""
    scanner = SMALL["scanner"] | {
        "rate_dependence": {"tau_s": {"uniform": [0.001, 0.005]}},
        "vibration": {"frequency_hz": {"uniform": [100, 400]}},
    }
    classes = ["generalised_pi", "preisach", "rate_dependent", "resonant"]
    cfg = load_config(write(tmp_path, trials=24, truth_classes=classes, scanner=scanner), StudyConfig)
    one = load_config(write(tmp_path, "one.yaml", trials=24), StudyConfig)
    for s, (d, base) in enumerate(zip(job.scanner_draws(cfg), job.scanner_draws(one))):
        assert d["truth_class"] == classes[s % 4]
        assert ("rate_tau" in d) == (d["truth_class"] == "rate_dependent")
        assert ("vibration_hz" in d) == ("vibration_damping" in d) == (d["truth_class"] == "resonant")
        assert {k: v for k, v in d.items() if k in base} == base | {"truth_class": d["truth_class"]}


def test_study_through_step_c_and_the_push(tmp_path, monkeypatch):
    """The nominal scanner (step A's model misses its loop width), four trials through A+B,
    the local scan and the push, with two of the nine landmarks (a corner and the centre) lost
    from the survey image: step B maps on the seven left, step C brings the tip within 0.1 R of
    the true centre, far closer than A+B alone, and the push carries the particle to near its
    goal (100-300 nm away)."""
    path = write(
        tmp_path, trials=4, trials_per_scanner=4, chunk=4, stages=["A+B", "A+B+C", "push"], scanner={}
    )
    cfg = load_config(path, StudyConfig)
    D = workspace_layout(cfg)[2]
    find = survey.find_features

    def losing_two(z, raster, count, pits, *args, **kwargs):
        found = find(z, raster, count, pits, *args, **kwargs)
        lost = np.linalg.norm(found[:, None] - D[[0, 4]][None], axis=-1).min(axis=1) < 150.0  # nm
        return found[~lost] if pits else found

    monkeypatch.setattr(survey, "find_features", losing_two)
    contexts, info = job.prepare_scanner(
        cfg, path, 0, job.scanner_draws(cfg)[0], Output(tmp_path), lambda m: None
    )
    assert info["AB_landmarks_found"] == 7 and not isinstance(contexts["A+B"], Unsurveyed)
    np.testing.assert_allclose(
        np.sort(np.asarray(contexts["A+B"].positioner.frame.commands), 0),
        np.sort(D[[1, 2, 3, 5, 6, 7, 8]], 0),
    )
    draws = job.trial_draws(cfg, workspace_layout(cfg)[2])
    settings = job.trial_settings(cfg)
    mesh = Mesh(np.array(jax.devices()[:1]), ("trials",))
    # a first pass of 1 line stops every local scan early (each takes 2 or more: one per axis),
    # so every trial runs again, alone, from the start with every line
    monkeypatch.setattr(study, "FIRST_PASS_LINES", 1)
    r = study.run_chunk(contexts, draws, mesh, settings)
    assert np.all(r["ABC_lines"] > 1)
    # measured: A+B 26-30 nm, A+B+C 0.3-0.6 nm in 3 lines each, push misses 5-12 nm
    assert np.all(r["ABC_found"])
    assert np.all(r["ABC_error_nm"] < 0.1 * draws["radius_nm"])
    assert np.median(r["ABC_error_nm"]) < np.median(r["AB_error_nm"]) / 5
    assert np.all(r["push_contact"]) and np.all(r["push_error_nm"] < 0.1 * draws["push_distance_nm"])
    np.testing.assert_allclose(
        np.hypot(r["push_first_along_nm"], r["push_first_across_nm"]), r["push_first_error_nm"]
    )
    np.testing.assert_allclose(np.hypot(r["ABC_miss_x_nm"], r["ABC_miss_y_nm"]), r["ABC_error_nm"])
    # the two passes give what one pass with every line gives: each trial alone, in one pass
    # (measured: the same to the last bit)
    monkeypatch.setattr(study, "FIRST_PASS_LINES", cfg.local_scan.max_lines)
    one = [
        study.run_chunk(contexts, {k: v[i : i + 1] for k, v in draws.items()}, mesh, settings)
        for i in range(4)
    ]
    assert_same(r, {k: np.concatenate([o[k] for o in one]) for k in r})


def test_learning_aims_later_rounds_by_the_finds_of_earlier_ones(tmp_path):
    """The nominal scanner with step A's model 3 % off its loops (A+B misses of some 25 nm), four
    trials in rounds of two: the first round learns from nothing; the second aims at its
    targets plus the field learnt from the first round's finds (learn_field, by hand), and
    lands nearer its particles than its targets alone did."""
    path = write(
        tmp_path,
        trials=4,
        trials_per_scanner=4,
        chunk=4,
        stages=["A+B", "A+B+C"],
        scanner={},
        learning={"round_trials": 2, "prior_nm": 100.0, "noise_nm": 5.0},
    )
    cfg = load_config(path, StudyConfig)
    contexts, _ = job.prepare_scanner(
        cfg, path, 0, job.scanner_draws(cfg)[0], Output(tmp_path), lambda m: None
    )
    draws = job.trial_draws(cfg, workspace_layout(cfg)[2])
    settings = job.trial_settings(cfg)
    mesh = Mesh(np.array(jax.devices()[:1]), ("trials",))
    r = study.run_chunk(contexts, draws, mesh, settings)
    without = study.run_chunk(contexts, draws, mesh, dataclasses.replace(settings, learning=None))
    np.testing.assert_array_equal(r["AB_learnt_from"], [0, 0, 2, 2])
    assert np.all(r["ABC_found"][:2])
    xy = lambda name, rows: np.stack([r[f"{name}_x_nm"][rows], r[f"{name}_y_nm"][rows]], -1)
    offset = xy("AB_offset", slice(None))
    np.testing.assert_array_equal(offset[:2], 0.0)
    work = settings.work
    field = learn_field(
        xy("AB_target", slice(0, 2)),
        xy("ABC_centre", slice(0, 2)) - xy("AB_target", slice(0, 2)),
        np.asarray(work.centre),
        max(work.size) / 2,
        100.0,
        5.0,
    )
    np.testing.assert_allclose(offset[2:], field(xy("AB_target", slice(2, 4))), rtol=1e-9)
    # the predicted spread, by hand: the field's sd at the target (the prior's, 100 nm per
    # coefficient, in the first round; the ridge posterior's after it) and a find's 5 nm in
    # quadrature, times the variance factor: the first round's innovations (its offsets, against
    # the prior's zero) in units of their covariance S = 100^2 Q Q^T + 5^2 I, with 4 pseudo-axes
    Q = lambda rows: quadratic(xy("AB_target", rows), np.asarray(work.centre), max(work.size) / 2)
    q1, q2 = Q(slice(0, 2)), Q(slice(2, 4))
    nu = xy("ABC_centre", slice(0, 2)) - xy("AB_target", slice(0, 2))
    chi2 = np.sum(nu * np.linalg.solve(100.0**2 * q1 @ q1.T + 25.0 * np.eye(2), nu))
    post = 25.0 * np.linalg.inv(q1.T @ q1 + (5.0 / 100.0) ** 2 * np.eye(6))
    sd2 = np.sqrt((chi2 + 4) / (4 + 4)) * np.sqrt(np.einsum("ki,ij,kj->k", q2, post, q2) + 25.0)
    sd1 = np.sqrt(100.0**2 * np.sum(q1**2, -1) + 25.0)
    np.testing.assert_allclose(r["AB_predicted_sd_nm"], np.r_[sd1, sd2], rtol=1e-9)
    for k in r:  # the first round is the study without learning
        if k in without:
            np.testing.assert_allclose(r[k][:2], without[k][:2], rtol=1e-9, err_msg=k)
    assert np.all(r["AB_error_nm"][2:] < without["AB_error_nm"][2:]), (
        r["AB_error_nm"],
        without["AB_error_nm"],
    )


def test_pushes_learn_from_the_checks_of_earlier_rounds(tmp_path):
    """Four trials through the push in rounds of two, the pushes learning: the first round
    commands what is wanted, as a study without learning pushes does; the second commands its
    pushes through the field that the first round's checked pushes support (learn_push, by hand)."""
    path = write(
        tmp_path,
        trials=4,
        trials_per_scanner=4,
        chunk=4,
        stages=["A+B", "A+B+C", "push"],
        scanner={},
        learning={"round_trials": 2, "prior_nm": 100.0, "noise_nm": 5.0, "pushes": True},
    )
    cfg = load_config(path, StudyConfig)
    contexts, _ = job.prepare_scanner(
        cfg, path, 0, job.scanner_draws(cfg)[0], Output(tmp_path), lambda m: None
    )
    draws = job.trial_draws(cfg, workspace_layout(cfg)[2])
    settings = job.trial_settings(cfg)
    r = study.run_chunk(contexts, draws, Mesh(np.array(jax.devices()[:1]), ("trials",)), settings)
    xy = lambda name, rows: np.stack([r[f"{name}_x_nm"][rows], r[f"{name}_y_nm"][rows]], -1)
    wanted = np.stack([draws["push_dx"], draws["push_dy"]], -1) * draws["push_distance_nm"][:, None]
    first = study.observed(
        xy("AB_target", slice(0, 2)),
        xy("ABC_centre", slice(0, 2)),
        r["ABC_found"][:2],
        xy("push_command", slice(0, 2)),
        xy("push_seen_moved", slice(0, 2)),
    )
    assert len(first.commands) == 2  # both checks found their particle moved
    np.testing.assert_array_equal(r["push_learnt_from"], [0, 0, 2, 2])
    np.testing.assert_allclose(xy("push_command", slice(0, 2)), wanted[:2], rtol=1e-12)
    field = learn_push(first.commands, first.moved, 100.0, 5.0)
    by_hand = np.stack([np.asarray(field.command(w)) for w in wanted[2:]])
    np.testing.assert_allclose(xy("push_command", slice(2, 4)), by_hand, rtol=1e-9)
    assert np.all(np.abs(by_hand - wanted[2:]) > 0.01)  # they were changed


def test_a_check_teaches_a_push_only_when_it_saw_the_particle_moved():
    # four first pushes of 200 nm along x: seen moved by 190 nm (teaches), by 60 nm (the tip
    # missed it: under half the command), not found (NaN), and by 120 nm (teaches)
    command = np.array([[200.0, 0.0], [200.0, 0.0], [0.0, 200.0], [-200.0, 0.0]])
    moved = np.array([[190.0, 1.0], [60.0, 0.0], [np.nan, np.nan], [-120.0, 0.0]])
    seen = study.observed(np.zeros((4, 2)), np.ones((4, 2)), np.array([1, 0, 1, 0], bool), command, moved)
    np.testing.assert_array_equal(seen.commands, command[[0, 3]])
    np.testing.assert_array_equal(seen.moved, moved[[0, 3]])
    np.testing.assert_array_equal(seen.offsets, np.ones((2, 2)))


def test_noise_ceiling_against_drawn_noise():
    # the share of trials whose white position noise alone ends them beyond 0.1 R, against
    # 400,000 draws of a Gaussian per axis (radii 5-12 nm, sigma 0.1-0.5 nm: from under 0.001 % to
    # 46 % of a trial beyond)
    rng = np.random.default_rng(0)
    R = np.array([5.0, 5.0, 8.0, 12.0, 6.0])
    sigma = np.array([0.4, 0.1, 0.3, 0.5, 0.2])
    n = rng.normal(size=(400_000, R.size, 2)) * sigma[:, None]
    within = np.mean(np.linalg.norm(n, axis=-1) <= 0.1 * R)
    assert study.noise_ceiling_pct(R, sigma) == pytest.approx(100 * within, abs=0.2)
    assert study.noise_ceiling_pct(R, np.zeros_like(R)) == 100.0


def test_learning_rounds_by_hand():
    # three scanners of four trials in rounds of two; the learnt side is trials with >= 10
    # finds; scanner 2 never reaches 10 and is left out of both sides of the ratio
    r = {
        "scanner": np.array([0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 2]),
        "AB_error_nm": np.array([40.0, 60.0, 10.0, 20.0, 80.0, np.nan, 30.0, 50.0, 900, 900, 900, 900]),
        "AB_learnt_from": np.array([0, 0, 2, 12, 0, 0, 1, 11, 0, 0, 0, 0]),
    }
    got = learning_rounds(r, 2)
    assert got["first_trial"] == [0, 2]
    np.testing.assert_allclose(
        got["median_nm"], [80.0, 40.0]
    )  # (40, 60, 80, 900, 900); (10, 20, 30, 50, 900, 900)
    assert got["per_scanner"] == {0: [50.0, 15.0], 1: [80.0, 40.0], 2: [900.0, 900.0]}
    assert got["per_scanner_learnt"][0] == 20.0 and got["per_scanner_learnt"][1] == 50.0
    assert np.isnan(got["per_scanner_learnt"][2])
    assert got["learnt_scanners"] == [0, 1] and got["unlearnt_scanners"] == [2]
    assert got["first_round_median_nm"] == 60.0 and got["learnt_median_nm"] == 35.0  # (40, 60, 80); (20, 50)
    assert got["learnt_ratio"] == pytest.approx(35.0 / 60.0)


@pytest.mark.parametrize("span", [(3.0, 60.0), (2.0, 120.0), (0.5, 800.0)])
def test_log_axis_labels_are_plain_numbers_that_do_not_overlap(span):
    # the learning figure's axes span one to three decades of nm; matplotlib's default labels
    # the minor ticks of such an axis in 2 x 10^1 form, overlapping each other
    fig, ax = subplots(figsize=(4, 3))
    FigureCanvasAgg(fig)
    ax.set(xscale="log", xlim=span)
    _plain_log_ticks(ax.xaxis)
    renderer = fig.canvas.get_renderer()
    fig.canvas.draw()
    lo, hi = span
    shown = [t for t in ax.get_xticklabels(which="both") if t.get_visible() and t.get_text()]
    labels = [t for t in shown if lo <= t.get_position()[0] <= hi]
    expected = sorted(m * 10.0**k for k in range(-1, 4) for m in (1, 2, 5) if lo <= m * 10.0**k <= hi)
    assert sorted(float(t.get_text()) for t in labels) == pytest.approx(expected)
    boxes = sorted((t.get_window_extent(renderer) for t in labels), key=lambda b: b.x0)
    assert len(boxes) >= 3
    assert all(a.x1 < b.x0 for a, b in zip(boxes, boxes[1:]))


def test_a_rounds_push_odds_come_from_the_scanners_earlier_pushes():
    # eight earlier first pushes of 200-400 nm along x, all made and touching: falling 12 nm short
    # (beyond the 5 nm tolerance of R = 5 nm at 1 R) gives the next round's pushes odds near 0;
    # landing within 0.3 nm gives odds near 1 (the contact rule's 9/10 times the landing's ~1);
    # withheld earlier pushes do not count, and with fewer than six made the pushes get 1 (no odds:
    # made)
    rng = np.random.default_rng(6)
    push = rng.uniform(200, 400, 8)[:, None] * [1.0, 0.0]
    rows = {"distance": np.array([250.0, 350.0]), "direction": np.array([[1.0, 0.0], [1.0, 0.0]])}
    rows["radius"] = np.array([5.0, 5.0])

    def history(short, made=np.ones(8, bool)):
        miss = np.column_stack([short + rng.normal(0, 0.3, 8), rng.normal(0, 0.3, 8)])
        return study.push_rows(push, miss, np.ones(8, bool), made)

    assert np.all(study._round_odds(history(-12.0), rows, 1.0) < 1e-6)
    np.testing.assert_allclose(study._round_odds(history(0.0), rows, 1.0), 0.9, atol=1e-3)
    np.testing.assert_array_equal(study._round_odds(history(-12.0, np.arange(8) < 5), rows, 1.0), 1.0)


def test_a_rounds_push_odds_follow_the_push_field_it_commands_through():
    # a scanner whose pushes move their particle by 0.95 of the command along x: eight earlier
    # pushes of 200-400 nm commanded as wanted fell 10-20 nm short; the round's pushes, commanded
    # through the field that learnt the 5 % (c = d / 0.95), land on their goals: odds near 0.9
    # (the contact rule's 9/10), near 0 without the field
    rng = np.random.default_rng(7)
    push = rng.uniform(200, 400, 8)[:, None] * [1.0, 0.0]
    miss = -0.05 * push + rng.normal(0, 0.3, (8, 2))
    earlier = study.push_rows(push, miss, np.ones(8, bool), np.ones(8, bool))
    rows = {"distance": np.array([250.0, 350.0]), "direction": np.array([[1.0, 0.0], [1.0, 0.0]])}
    rows["radius"] = np.array([5.0, 5.0])
    shortfall = jnp.zeros((4, 2)).at[0, 0].set(-5.0)  # 5 nm short per 100 nm commanded along x
    field = study.online.PushField(shortfall)
    np.testing.assert_allclose(field.command(jnp.array([250.0, 0.0])), [250.0 / 0.95, 0.0], rtol=1e-6)
    np.testing.assert_allclose(study._round_odds(earlier, rows, 1.0, field), 0.9, atol=2e-3)
    assert np.all(study._round_odds(earlier, rows, 1.0) < 1e-6)


def test_position_coverage_of_gaussian_errors_is_the_nominal_level():
    # A+B miss vectors drawn from isotropic 2-D Gaussians of known per-axis sd (1-30 nm): the
    # share within each level's Rayleigh radius is that level, to the binomial error of 20,000
    # trials (at most 0.35 points sd; 1.5 points allowed); the same errors against half their sd
    # are covered far less (90 % nominal: P(|e| <= 1.07 s) = 44 %); learnt trials are those aimed
    # by 10 finds or more. The find's miss, step C's centre less the aim (target + offset), drawn
    # the same way with half the sd, over the verified finds (every other trial) alone
    rng = np.random.default_rng(5)
    n = 20_000
    sd = rng.uniform(1.0, 30.0, n)
    e = np.linalg.norm(sd[:, None] * rng.normal(size=(n, 2)), axis=-1)
    target, offset = rng.uniform(-1000, 1000, (n, 2)), rng.normal(0, 50, (n, 2))
    centre = target + offset + sd[:, None] / 2 * rng.normal(size=(n, 2))
    xy = lambda name, v: {f"{name}_x_nm": v[:, 0], f"{name}_y_nm": v[:, 1]}
    r = (
        {"AB_error_nm": e, "AB_predicted_sd_nm": sd, "AB_learnt_from": np.arange(n) % 20}
        | {"ABC_found": np.arange(n) % 2 == 0}
        | xy("ABC_centre", centre)
        | xy("AB_target", target)
        | xy("AB_offset", offset)
    )
    got = position_coverage(r)
    np.testing.assert_allclose(got["true"]["all"]["covered_pct"], 100 * np.asarray(got["levels"]), atol=1.5)
    assert got["true"]["learnt"]["trials"] == n // 2 and got["find"]["all"]["trials"] == n // 2
    within = 100 * (1 - np.exp(-((2 * rayleigh_radius(np.asarray(got["levels"]))) ** 2) / 2))
    np.testing.assert_allclose(got["find"]["all"]["covered_pct"], within, atol=2.0)
    assert rayleigh_radius(0.9) == pytest.approx(2.146, abs=1e-3)
    narrow = position_coverage(r | {"AB_predicted_sd_nm": sd / 2})
    assert narrow["true"]["all"]["covered_pct"][-2] < 60.0


def test_killed_two_device_study_resumes_to_the_same_results(baseline):
    """The study in chunks of 3 (two chunks, a scanner each), run by ``jaxafm study`` in a
    process with two host devices (the chunk padded to 4 trials, 2 a device), killed after its
    first chunk: refused with another config (naming the changed key, touching nothing), and run
    again with its own (in this process: one device; no --resume needed) it resumes, giving the
    baseline's results (chunks of 2, one device) without redoing the done chunk."""
    path, out, proc, watcher = baseline[2]
    watcher.join()
    log = proc.communicate()[0]
    assert proc.returncode == -signal.SIGKILL, log[-3000:]  # killed, not ended by itself
    assert "6 trials on 2 scanner(s), 2 device(s), chunks of 3" in log
    first = chunk_files(out)
    assert len(first) == 1, "the study ended before it could be killed"
    stamps = {f.name: f.stat().st_mtime_ns for f in first}
    other = write(path.parent, "other.yaml", chunk=3, seed=7)
    again = CliRunner().invoke(app, ["study", str(other), "--out", str(out)])
    assert again.exit_code == 2 and "keys: seed" in again.output and "--overwrite" in again.output
    assert chunk_files(out) == first and not (out / "trials.npz").exists()  # nothing touched
    resumed = CliRunner().invoke(app, ["study", str(path), "--out", str(out)])
    assert resumed.exit_code == 0, resumed.output[-3000:]
    done = sum(int(f.stem.split("_")[2]) - int(f.stem.split("_")[1]) for f in first)
    assert "resuming the unfinished `jaxafm study`" in resumed.output
    assert f"resuming: {done} done" in resumed.output
    assert {f.name: f.stat().st_mtime_ns for f in first} == stamps  # done chunks not recomputed
    assert_same(results(out), results(baseline[0]), "killed on two devices, resumed on one:")
