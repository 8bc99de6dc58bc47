"""Figures, written to files (matplotlib, no display needed)."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def actuator_fit(record, predictions: dict, split: int, path, title: str = "") -> None:
    """Measured and fitted loops on the held-out part, and the error against time.

    ``predictions`` maps a model name to its output (nm) over the whole record.
    """
    u, d, t = record.u, record.d, record.t
    d_range = float(d.max() - d.min())
    fig, (ax_loop, ax_err) = plt.subplots(1, 2, figsize=(13, 6), gridspec_kw={"width_ratios": [1, 1.4]})
    ax_loop.plot(u[split:], d[split:] / 1e3, color="0.6", lw=2.5, label="measured")
    for name, pred in predictions.items():
        ax_loop.plot(u[split:], pred[split:] / 1e3, lw=0.8, label=name)
    ax_loop.set(xlabel="input u [V]", ylabel="output d [µm]", title="held-out part: loops")
    ax_loop.legend(fontsize=8)
    window = min(len(t), max(1, int(round(1.0 / np.median(np.diff(t))))))  # 1 s of samples
    for name, pred in predictions.items():
        e = 100 * (pred - d) / d_range
        held = float(np.sqrt(np.mean(e[split:] ** 2)))
        rolling = np.sqrt(np.convolve(e**2, np.ones(window) / window, mode="valid"))
        ax_err.plot(t[window - 1:], rolling, lw=1, label=f"{name}: held-out rms {held:.2f} %")
    ax_err.axvline(t[split], color="k", ls="--", lw=1)
    ax_err.text(t[split], 0.97, "  train | held out", transform=ax_err.get_xaxis_transform(), va="top")
    ax_err.set(xlabel="time [s]", ylabel="rms error over the last 1 s [% of output range]", yscale="log",
               title=f"model - measured (output range {d_range / 1e3:.1f} µm)")
    ax_err.grid(True, which="both", alpha=0.3)
    ax_err.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=3)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
