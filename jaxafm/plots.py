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


def raster_scan(trace, retrace, path, raster, path_file, title: str = "", every: int = 16) -> None:
    """Trace, retrace and their difference (nm) at the nominal pixel positions, and the true
    tip path: where every ``every``-th line and column of pixels really was, over the
    nominal grid. ``trace``/``retrace`` are ``AFMImage``; ``path`` (lines, pixels, 2) nm."""
    fig, axes = plt.subplots(1, 4, figsize=(20, 5.2), constrained_layout=True)
    um = [e / 1e3 for e in trace.extent]
    for ax, image, name in ((axes[0], trace.z, "trace"), (axes[1], retrace.z, "retrace")):
        im = ax.imshow(image, origin="lower", extent=um, cmap="afmhot")
        fig.colorbar(im, ax=ax, label="height (nm)", shrink=0.85)
        ax.set_title(f"{name} (x rising)" if name == "trace" else f"{name} (x falling)")
    diff = trace.z - retrace.z
    lim = float(np.max(np.abs(diff))) or 1.0
    im = axes[2].imshow(diff, origin="lower", extent=um, cmap="RdBu_r", vmin=-lim, vmax=lim)
    fig.colorbar(im, ax=axes[2], label="trace - retrace (nm)", shrink=0.85)
    axes[2].set_title(f"difference (rms {np.sqrt(np.mean(diff ** 2)):.0f} nm)")
    ax = axes[3]
    nx, ny = np.meshgrid(trace.x, trace.y)
    for pick in (np.s_[::every, :], np.s_[:, ::every]):
        for a, b, style in ((nx, ny, dict(color="k", lw=0.6, ls=":")), (path[..., 0], path[..., 1],
                                                                   dict(color="C3", lw=1.0))):
            seg_a, seg_b = a[pick] / 1e3, b[pick] / 1e3
            lines = zip(seg_a, seg_b) if pick[1] == slice(None) else zip(seg_a.T, seg_b.T)
            for xa, yb in lines:
                ax.plot(xa, yb, **style)
    ax.plot([], [], color="k", lw=0.6, ls=":", label="nominal pixel grid")
    ax.plot([], [], color="C3", label="true tip path (trace)")
    ax.set_aspect("equal")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.12), ncol=2, frameon=False)
    ax.set_title("where the tip really was")
    for a in axes:
        a.set_xlabel("x (µm)")
        a.set_ylabel("y (µm)")
    if title:
        fig.suptitle(title)
    fig.savefig(path_file, dpi=110)
    plt.close(fig)


def compensation(images: dict, raster, path, title: str = "", every: int = 16) -> None:
    """One column per drive: trace and retrace images (nm) of the same lattice at the nominal
    pixel positions (the paper's Fig. 6 and 7), and the fast-axis error of the tip (true
    minus wanted x, nm; its mean over the image removed) along every ``every``-th line."""
    names = list(images)
    fig, axes = plt.subplots(3, len(names), figsize=(3.3 * len(names), 10), constrained_layout=True,
                             squeeze=False)
    ext = [raster.origin[0] / 1e3, (raster.origin[0] + raster.size[0]) / 1e3,
           raster.origin[1] / 1e3, (raster.origin[1] + raster.size[1]) / 1e3]
    x = (raster.origin[0] + raster.pixel_size[0] * np.arange(raster.pixels))
    errors = {n: np.stack([np.asarray(images[n][f"path_{k}"])[..., 0] - x for k in ("trace", "retrace")])
              for n in names}
    lim = max(float(np.abs(e - e.mean()).max()) for e in errors.values())
    for j, n in enumerate(names):
        for i, k in enumerate(("trace", "retrace")):
            ax = axes[i, j]
            im = ax.imshow(np.asarray(images[n][k]), origin="lower", extent=ext, cmap="afmhot")
            ax.set_title(f"{n}\n{k}" if i == 0 else k, fontsize=9)
            ax.set_xlabel("x nominal (µm)")
            if j == 0:
                ax.set_ylabel("y nominal (µm)")
        e = errors[n] - errors[n].mean()
        ax = axes[2, j]
        for i, (k, c) in enumerate((("trace", "C0"), ("retrace", "C3"))):
            ax.plot(x / 1e3, e[i, ::every].T, color=c, lw=0.6, alpha=0.7)
            ax.plot([], [], color=c, label=k)
        ax.set(xlabel="x nominal (µm)", ylim=(-1.05 * lim, 1.05 * lim),
               title=f"max |error| {100 * np.abs(e).max() / raster.size[0]:.2f} % of width")
        if j == 0:
            ax.set_ylabel("true - wanted x (nm)")
            ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
    fig.colorbar(im, ax=axes[:2], label="height (nm)", shrink=0.6)
    if title:
        fig.suptitle(title)
    fig.savefig(path, dpi=110)
    plt.close(fig)
