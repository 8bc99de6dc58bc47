"""A simulated scan of a 2-D calibration grating through the default AFM (compare the paper's Fig. 6).

    python experiments/simulated_grating_scan.py [--pixels 256] [--out experiments/results/simulated_grating_scan]

Writes the figure (trace, retrace, difference, true tip path), both images in
the jaxafm image format and a metrics.json with the distortions measured from the path.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxafm import plots
from jaxafm.instrument.afm import Raster, default_afm, raster_scan
from jaxafm.instrument.images import from_scan, save_image
from jaxafm.instrument.samples import Lattice


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--pixels", type=int, default=256)
    ap.add_argument("--line-rate", type=float, default=1.0, help="Hz")
    ap.add_argument("--out", type=Path, default=Path("experiments/results/simulated_grating_scan"))
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)

    afm = default_afm()
    sample = Lattice(
        jnp.full(2, 2000.0),
        jnp.asarray(600.0),
        jnp.asarray(100.0),
        edge_width=jnp.asarray(80.0),
        phase=jnp.full(2, 1000.0),
    )
    raster = Raster((8000.0, 8000.0), args.pixels, args.pixels, line_rate=args.line_rate)
    cycle = [[-afm.u_max, -afm.u_max], [afm.u_max, afm.u_max]]  # the paper's initialisation cycle
    state = afm.initial_state(u0=(afm.u_max, afm.u_max), history=cycle)
    start = time.perf_counter()
    scan = raster_scan(
        afm, sample, state, raster, key=jax.random.key(0)
    )  # checks the range, compiles the drive
    jax.block_until_ready(scan)
    seconds = time.perf_counter() - start

    trace, retrace = from_scan(scan, raster, "trace"), from_scan(scan, raster, "retrace")
    for name, image in (("trace", trace), ("retrace", retrace)):
        save_image(image, args.out / f"{name}.npz", overwrite=True)
    path = np.asarray(scan.path_trace)
    nominal = np.stack(np.meshgrid(trace.x, trace.y), axis=-1)
    err = path - nominal
    diff = trace.z - retrace.z
    metrics = {
        "pixels": args.pixels,
        "scan_size_nm": 8000.0,
        "line_rate_hz": args.line_rate,
        "frame_time_s": float(scan.t_retrace.max() - scan.t_trace.min()),
        "simulate_seconds_incl_compile": seconds,
        "position_error_rms_nm": float(np.sqrt(np.mean(np.sum(err**2, axis=-1)))),
        "position_error_max_nm": float(np.max(np.linalg.norm(err, axis=-1))),
        "x_error_range_nm": [float(err[..., 0].min()), float(err[..., 0].max())],
        "y_error_range_nm": [float(err[..., 1].min()), float(err[..., 1].max())],
        "trace_retrace_offset_rms_nm": float(
            np.sqrt(
                np.mean(np.sum((np.asarray(scan.path_trace) - np.asarray(scan.path_retrace)) ** 2, axis=-1))
            )
        ),
        "trace_minus_retrace_rms_nm": float(np.sqrt(np.mean(diff**2))),
    }
    (args.out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    plots.raster_scan(
        trace,
        retrace,
        path,
        raster,
        args.out / "scan.png",
        title=f"Simulated {args.pixels} x {args.pixels} scan of a 2 µm-pitch pillar grating, "
        f"default scanner, {args.line_rate:g} Hz lines, after the {{-10 V, +10 V}} cycle",
    )
    for k, v in metrics.items():
        print(f"{k:34s} {v}")
    print(f"wrote {args.out}/scan.png")


if __name__ == "__main__":
    main()
