"""Step A on the default simulated AFM: the paper's Fig. 6 and 7, and our inverses against the paper's.

A lattice of known pitch is imaged after the initialisation cycle, the scanner is
identified from that one trace/retrace pair, the cycle is repeated, and the
lattice is imaged again with each inverse: the paper's polynomial + neural
network, and the end-to-end model with its analytic and numerical inverses.
Errors are measured against the true tip path, which only a simulation knows.

    python experiments/step_a_compensation.py [--pixels 256] [--out experiments/results/step_a]
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
import matplotlib.pyplot as plt  # noqa: E402

from jaxafm import calibration, features  # noqa: E402
from jaxafm.afm import Raster, default_afm, move, raster_scan  # noqa: E402
from jaxafm.inverse import Compensator, train_neural_inverse  # noqa: E402
from jaxafm.samples import Lattice, Plane  # noqa: E402


def position_errors(out: dict, raster: Raster) -> dict:
    """Fast-axis linearity error and position errors of a scan against its wanted pixels.

    The one translation of the whole image that no image can observe (the
    lattice's phase) is removed: errors are about the mean error of trace and
    retrace together.
    """
    wanted = np.stack(np.meshgrid(raster.origin[0] + raster.pixel_size[0] * np.arange(raster.pixels),
                                  raster.origin[1] + raster.pixel_size[1] * np.arange(raster.lines)), -1)
    e = np.stack([np.asarray(out["path_trace"]), np.asarray(out["path_retrace"])]) - wanted
    offset = e.reshape(-1, 2).mean(axis=0)
    e = e - offset
    width = raster.size[0]
    return {"linearity_error_pct": 100 * float(np.abs(e[..., 0]).max()) / width,
            "linearity_error_trace_pct": 100 * float(np.abs(e[0, ..., 0]).max()) / width,
            "linearity_error_retrace_pct": 100 * float(np.abs(e[1, ..., 0]).max()) / width,
            "x_rms_error_nm": float(np.sqrt(np.mean(e[..., 0] ** 2))),
            "y_max_error_nm": float(np.abs(e[..., 1]).max()), "y_rms_error_nm": float(np.sqrt(np.mean(e[..., 1] ** 2))),
            "offset_x_nm": float(offset[0]), "offset_y_nm": float(offset[1])}


def pitch_uniformity(out: dict, raster: Raster, pitch: float) -> dict:
    px = tuple(pitch / p for p in raster.pixel_size)
    result = {}
    for k in ("trace", "retrace"):
        f = features.lattice_features(np.asarray(out[k]), px, f"{k} image")
        spread = features.pitch_spread(features.local_pitch(f, raster.pixel_size))
        result |= {f"pitch_std_{k}_pct": spread["pitch_std_pct"], f"pitch_ptp_{k}_pct": spread["pitch_ptp_pct"]}
    return result


def paper_volts(poly: calibration.BranchPolynomials, u_range: np.ndarray, samples: int = 400):
    """The paper's inverse: per branch, a network trained on (position, voltage) pairs of the
    polynomial over the drive range ``u_range`` (2, 2) V of the scan (over-scan included)."""
    nets, seconds = {}, 0.0
    for name, coef, k in (("x_up", poly.x_up, 0), ("x_down", poly.x_down, 0), ("y", poly.y, 1)):
        u = np.linspace(*u_range[k], samples)
        nets[name], s = train_neural_inverse(np.polyval(coef, u), u)
        seconds += s

    def volts(xy, t):
        xy = jnp.asarray(xy)
        rising = jnp.diff(xy[:, 0], prepend=xy[0, 0] - 1.0) >= 0
        ux = jnp.where(rising, nets["x_up"](xy[:, 0]), nets["x_down"](xy[:, 0]))
        return jnp.stack([ux, nets["y"](xy[:, 1])], -1)

    return volts, seconds


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pixels", type=int, default=256)
    ap.add_argument("--size", type=float, default=8000.0, help="scan size, nm")
    ap.add_argument("--pitch", type=float, default=1000.0, help="lattice pitch, nm")
    ap.add_argument("--operators", type=int, default=16)
    ap.add_argument("--max-steps", type=int, default=30)
    ap.add_argument("--out", type=Path, default=Path("experiments/results/step_a"))
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)

    afm = default_afm()
    lattice = Lattice(jnp.full(2, a.pitch), jnp.asarray(a.pitch / 4), jnp.asarray(100.0), jnp.asarray(30.0),
                      jnp.zeros(()), jnp.array([130.0, 70.0]))
    raster = Raster(a.size, a.pixels, a.pixels, line_rate=1.0)
    cycle = np.array([[-afm.u_max, -afm.u_max], [afm.u_max, afm.u_max]])
    keys = jax.random.split(jax.random.key(0), 8)

    state = afm.initial_state((0.0, 0.0), 0.0, cycle)
    before = raster_scan(afm, lattice, state, raster, key=keys[0])
    scan = calibration.CalibrationScan(before["trace"], before["retrace"], raster, a.pitch,
                                       np.asarray(afm.sensitivity), afm.u_max, (0.0, 0.0), 0.0, cycle)

    u_range = np.stack([scan.volts(np.array([[0, -raster.margin], [0, raster.pixels + raster.margin]]))[:, 0],
                        scan.volts(np.array([[0, 0], [raster.lines - 1, 0]]))[:, 1]])
    t0 = time.perf_counter()
    poly = calibration.fit_polynomials(scan)
    paper, nn_seconds = paper_volts(poly, u_range)
    paper_fit_s = time.perf_counter() - t0
    print(f"paper: polynomials + networks in {paper_fit_s:.1f} s")
    ident = calibration.identify(scan, operators=a.operators, max_steps=a.max_steps)
    print(f"end-to-end identification: {ident.seconds:.1f} s, converged: {ident.converged}")

    # the twin: the fitted model replays every drive the instrument saw, so it knows its state
    model = ident.model
    twin = model.afm(scan)
    twin_state = raster_scan(twin, Plane(), twin.initial_state((0.0, 0.0), 0.0, cycle), raster,
                             key=calibration.KEY)["state"]

    def cycle_again(instrument, s, key):
        for target in cycle:
            _, s = move(instrument, lattice if instrument is afm else Plane(), s, target, 0.5, key=key)
        return s

    rows, images, metrics = [], {"uncompensated": before}, {}
    metrics |= {f"uncompensated_{k}": v for k, v in position_errors(before, raster).items()}
    metrics |= {f"uncompensated_{k}": v for k, v in pitch_uniformity(before, raster, a.pitch).items()}
    inverses = {"paper: polynomial + NN": (paper, paper_fit_s)}
    for method in ("analytic", "numerical"):
        inverses[f"end-to-end + {method}"] = (method, ident.seconds)
    for i, (name, (volts, fit_s)) in enumerate(inverses.items()):
        s = cycle_again(afm, before["state"], keys[1])
        if isinstance(volts, str):
            ts = cycle_again(twin, twin_state, calibration.KEY)
            volts = Compensator(model.scanner, ts.scanner, ts.u, u_range, volts,
                                history=jnp.asarray(cycle), u_max=afm.u_max)
        wanted = jnp.asarray(raster.wanted().reshape(-1, 2))
        t = s.scanner.t + 0.1 + raster.sample_time * jnp.arange(1, wanted.shape[0] + 1)
        start = time.perf_counter()
        u = jax.block_until_ready(volts(wanted, t))  # the raster's own drive, timed once
        inverse_s = time.perf_counter() - start
        out = raster_scan(afm, lattice, s, raster, volts=lambda xy, tt: u, key=keys[2])
        images[name] = out
        m = position_errors(out, raster) | pitch_uniformity(out, raster, a.pitch)
        key = ["paper", "analytic", "numerical"][i]
        metrics |= {f"{key}_{k}": v for k, v in m.items()} | {f"{key}_fit_s": fit_s, f"{key}_inverse_s": inverse_s}
        rows.append((name, m["linearity_error_trace_pct"], m["linearity_error_retrace_pct"], m["x_rms_error_nm"],
                     m["y_max_error_nm"], m["pitch_std_trace_pct"], fit_s, inverse_s))
    base = position_errors(before, raster)
    print(f"\n{'inverse':26s} {'lin. trace':>10s} {'lin. retrace':>12s} {'x rms':>8s} {'y max':>8s} "
          f"{'pitch std':>9s} {'fit':>7s} {'inverse':>8s}")
    print(f"{'none (nominal)':26s} {base['linearity_error_trace_pct']:9.2f}% {base['linearity_error_retrace_pct']:11.2f}% "
          f"{base['x_rms_error_nm']:6.1f}nm {base['y_max_error_nm']:6.1f}nm "
          f"{metrics['uncompensated_pitch_std_trace_pct']:8.2f}%")
    for r in rows:
        print(f"{r[0]:26s} {r[1]:9.2f}% {r[2]:11.2f}% {r[3]:6.1f}nm {r[4]:6.1f}nm {r[5]:8.2f}% {r[6]:6.1f}s {r[7]:7.2f}s")
    print("linearity: max |x error| over the image, % of the scan width; pitch std: local pitch spread, trace")

    metrics |= _parameters(afm, model)
    metrics |= {"pixels": a.pixels, "scan_size_nm": a.size, "pitch_nm": a.pitch,
                "stages": [s.message for s in ident.stages]}
    (a.out / "metrics.json").write_text(json.dumps(metrics, indent=1))
    _figure(images, raster, a.out / "fig6_fig7.png")
    eqx.tree_serialise_leaves(a.out / "model.eqx", model)
    print(f"wrote {a.out}/metrics.json, fig6_fig7.png")


def _parameters(afm, model) -> dict:
    """Fitted against true values for the parameters both have."""
    t, m = afm.scanner, model.scanner
    out = {"true_coupling_xy": float(t.coupling.xy), "fit_coupling_xy": float(m.coupling.xy),
           "true_coupling_yx": float(t.coupling.yx), "fit_coupling_yx": float(m.coupling.yx),
           "true_bow_x_per_nm": float(t.bow.bx), "fit_bow_x_per_nm": float(m.bow.bx),
           "true_bow_y_per_nm": float(t.bow.by), "fit_bow_y_per_nm": float(m.bow.by),
           "true_feedback_tau_s": float(afm.feedback.tau), "fit_feedback_tau_s": float(model.feedback.tau)}
    if m.x.creep is not None:
        out |= {"true_creep_gamma_x": _gamma(t.x.creep), "fit_creep_gamma_x": _gamma(m.x.creep)}
    return out


def _gamma(creep) -> float:
    """Creep per decade of a logarithmic bank: its mean weight times its lags per decade."""
    per_decade = 1 / np.diff(np.log10(np.asarray(creep.taus)))[0]
    return float(np.mean(creep.weights) * per_decade)


def _figure(images: dict, raster: Raster, path: Path) -> None:
    names = list(images)
    fig, axes = plt.subplots(2, len(names), figsize=(3.4 * len(names), 6.6), constrained_layout=True)
    ext = [raster.origin[0] / 1e3, (raster.origin[0] + raster.size[0]) / 1e3,
           raster.origin[1] / 1e3, (raster.origin[1] + raster.size[1]) / 1e3]
    for j, n in enumerate(names):
        for i, k in enumerate(("trace", "retrace")):
            ax = axes[i, j]
            ax.imshow(np.asarray(images[n][k]), origin="lower", extent=ext, cmap="afmhot")
            ax.set_title(f"{n}\n{k}" if i == 0 else k, fontsize=9)
            ax.set_xlabel("x nominal (µm)")
            if j == 0:
                ax.set_ylabel("y nominal (µm)")
    fig.suptitle("Step A: lattice image without (paper Fig. 6) and with compensation (Fig. 7)")
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    main()
