"""Small loops against the major loop: each loop's gap at mid input over its own span, against its
amplitude, for the real PICMA stack and for the simulated scanner's truth classes.

The real record (`piezo_ramped_sine_1hz.dat`: a 1 Hz sine whose amplitude falls and rises, 200
samples a second) is cut into its cycles between successive input minima; each cycle's gap is
the descending minus the ascending branch at the cycle's middle input. The simulated truths
(`default_scanner(truth_class=...)`, x axis, hysteresis alone, loop width 0.15) run the
initialisation cycle, then three cycles of a centred sine of each amplitude; the last is
measured the same way. A truth whose small loops are as wide for their span as its major loop,
or wider, is not a piezo stack's shape.

    python experiments/minor_loop_widths.py [--out experiments/results/minor_loop_widths]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax.numpy as jnp
import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from jaxafm import default_scanner
from jaxafm.instrument.records import read_record

ROOT = Path(__file__).resolve().parents[1]
RECORD = ROOT / "jaxafm" / "data" / "real" / "piezo_ramped_sine_1hz.dat"
FRACTIONS = (0.1, 0.2, 0.3, 0.5, 0.7, 1.0)


def relative_width(u: np.ndarray, d: np.ndarray) -> tuple:
    """One cycle's gap at its middle input over its span, and its input span (V)."""
    middle = (u.min() + u.max()) / 2
    a, b = sorted((int(np.argmax(u)), int(np.argmin(u))))
    branches = (np.arange(a, b + 1), np.r_[b : len(u), 0 : a + 1])
    at = [np.interp(middle, np.sort(u[i]), d[i][np.argsort(u[i])]) for i in branches]
    return abs(at[0] - at[1]) / np.ptp(d), np.ptp(u)


def real_stack() -> np.ndarray:
    """(cycles, 2): each whole cycle's relative width and input span (V)."""
    rec = read_record(RECORD, input_columns=[1], output_columns=[5], sample_rate_hz=200.0, output_unit="um")
    u, d = np.asarray(rec.u).ravel()[10:], np.asarray(rec.d).ravel()[10:]  # the README: drop the first rows
    minima = [i for i in range(100, len(u) - 100) if u[i] == u[i - 100 : i + 101].min()]
    return np.array(
        [relative_width(u[a:b], d[a:b]) for a, b in zip(minima[:-1], minima[1:]) if 150 < b - a < 250]
    )


def simulated(truth: str, u_range: float = 10.0) -> list:
    """The relative width of a centred sine loop at each of ``FRACTIONS`` of the range."""
    h = default_scanner(truth_class=truth).x.hysteresis
    cycle = [np.linspace(0, u_range, 101), np.linspace(u_range, -u_range, 201), np.linspace(-u_range, 0, 101)]
    t = np.linspace(0, 3, 601)
    out = []
    for f in FRACTIONS:
        u = np.concatenate(cycle + [u_range * f * np.sin(2 * np.pi * t)])
        y = np.asarray(h(jnp.asarray(u)))
        out.append(relative_width(u[-200:], y[-200:])[0])
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=ROOT / "experiments" / "results" / "minor_loop_widths")
    args = ap.parse_args()
    real = real_stack()
    fraction = real[:, 1] / real[:, 1].max()
    largest = real[np.argmax(real[:, 1]), 0]
    results = {
        "real_stack": {"amplitude_fraction": fraction.tolist(), "relative_width": real[:, 0].tolist()},
        "fractions": list(FRACTIONS),
    }
    print(
        f"{'amplitude':>10s} {'real stack':>11s} "
        + " ".join(f"{t:>15s}" for t in ("generalised_pi", "preisach"))
    )
    sims = {t: simulated(t) for t in ("generalised_pi", "preisach")}
    results |= sims
    for i, f in enumerate(FRACTIONS):
        k = np.argmin(np.abs(fraction - f))
        print(
            f"{f:10.1f} {100 * real[k, 0]:9.1f} % ({fraction[k]:.2f}) "
            + " ".join(f"{100 * sims[t][i]:13.1f} %" for t in sims)
        )
    k = np.argmin(np.abs(fraction - 0.2))
    ratios = {"real_stack": real[k, 0] / largest} | {t: v[1] / v[-1] for t, v in sims.items()}
    results["ratio_at_a_fifth"] = ratios
    print(
        "at a fifth of the amplitude, over the largest loop's: "
        + ", ".join(f"{t} {r:.2f}" for t, r in ratios.items())
    )
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "widths.json").write_text(json.dumps(results, indent=1))
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(
        fraction,
        100 * real[:, 0],
        ".",
        color="k",
        ms=4,
        label="real stack (piezo_ramped_sine_1hz.dat), each cycle",
    )
    for t, v in sims.items():
        ax.plot(FRACTIONS, 100 * np.array(v), "o-", label=f"simulated truth: {t}")
    ax.set(
        xlabel="loop amplitude / largest loop's",
        ylabel="gap at mid input / loop span [%]",
        title="Small loops against the major loop",
    )
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out / "widths.png", dpi=120)
    print(f"wrote {args.out / 'widths.json'} and widths.png")


if __name__ == "__main__":
    main()
