"""Figures, written to files.

Each figure is its own ``matplotlib.figure.Figure``, saved with ``fig.savefig``: no pyplot, no
backend chosen, nothing of matplotlib's global state changed, so importing jaxafm leaves a
user's interactive plotting as it was, and no display is needed.
"""

from __future__ import annotations

import textwrap

import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Circle
from matplotlib.ticker import FormatStrFormatter, LogLocator, NullFormatter


def subplots(
    nrows: int = 1, ncols: int = 1, *, figsize: tuple, constrained_layout: bool = False, **kw
) -> tuple:
    """A new figure and its grid of axes, like ``pyplot.subplots`` but outside pyplot.

    Arguments:
        nrows, ncols: the grid of axes.
        figsize: width, height (inches).
        constrained_layout: let matplotlib place the axes and colour bars.
        **kw: passed to ``Figure.subplots`` (``squeeze``, ``gridspec_kw``, ...).

    Returns:
        ``(fig, axes)``; save with ``fig.savefig(path)``. Nothing else holds the figure: it is
        freed with its last reference.
    """
    fig = Figure(figsize=figsize, constrained_layout=constrained_layout)
    return fig, fig.subplots(nrows, ncols, **kw)


def _plain_log_ticks(axis) -> None:
    """Label a log axis at 1, 2 and 5 times each power of ten in plain numbers (``20``, not
    ``2 x 10^1``) and leave its minor ticks unlabelled, so that an axis spanning less than two
    decades reads without overlapping labels. ``axis``: ``ax.xaxis`` or ``ax.yaxis``."""
    axis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
    axis.set_major_formatter(FormatStrFormatter("%g"))
    axis.set_minor_formatter(NullFormatter())


def actuator_fit(record, predictions: dict, split: int, path, title: str = "") -> None:
    """Measured and fitted loops on the held-out part, and the error against time.

    ``predictions`` maps a model name to its output (nm) over the whole record.
    """
    u, d, t = record.u, record.d, record.t
    d_range = float(d.max() - d.min())
    fig, (ax_loop, ax_err) = subplots(1, 2, figsize=(13, 6), gridspec_kw={"width_ratios": [1, 1.4]})
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
        ax_err.plot(t[window - 1 :], rolling, lw=1, label=f"{name}: held-out rms {held:.2f} %")
    ax_err.axvline(t[split], color="k", ls="--", lw=1)
    ax_err.text(t[split], 0.97, "  train | held out", transform=ax_err.get_xaxis_transform(), va="top")
    ax_err.set(
        xlabel="time [s]",
        ylabel="rms error over the last 1 s [% of output range]",
        yscale="log",
        title=f"model - measured (output range {d_range / 1e3:.1f} µm)",
    )
    ax_err.grid(True, which="both", alpha=0.3)
    ax_err.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=3)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def prediction_band(record, spread, start: int, path, title: str = "") -> None:
    """A prediction's error against time with its band (:class:`~jaxafm.model.posterior.Band`):
    measured - predicted (nm) from sample ``start`` on, the band about zero shaded, and the same
    over the first two seconds, where the loop's shape shows."""
    t, e = record.t[start:], (record.d - spread.mean)[start:]
    lower, upper = (b[start:] - spread.mean[start:] for b in spread.bounds())
    inside = 100 * float(np.mean((e >= lower) & (e <= upper)))
    pct = f"{100 * spread.level:g} %"
    fig, axes = subplots(2, 1, figsize=(12, 7))
    near = t <= t[0] + 2.0
    for ax, keep in zip(axes, (slice(None), near)):
        ax.fill_between(t[keep], lower[keep], upper[keep], color="C0", alpha=0.25, lw=0, label=f"{pct} band")
        ax.plot(t[keep], e[keep], color="k", lw=0.6, label=f"measured - predicted ({inside:.1f} % inside)")
        ax.axhline(0, color="0.5", lw=0.5)
        ax.set(xlabel="time [s]", ylabel="error [nm]")
        ax.grid(True, alpha=0.3)
    axes[0].legend(fontsize=8, loc="lower right")
    axes[0].set_title("the evaluated part")
    axes[1].set_title("its first 2 s")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def compensated_drive(t, u, cycle: int, wanted, model, path, title: str = "") -> None:
    """A compensating drive and what the model does with it: the drive (V) against time with
    its initialisation cycle shaded, the wanted and model outputs (µm), and their difference
    (nm) over the trajectory."""
    fig, (ax_u, ax_x, ax_e) = subplots(3, 1, figsize=(11, 8.5), sharex=True)
    ax_u.plot(t, u, lw=1)
    ax_u.axvspan(t[0], t[cycle - 1], color="0.85", label="initialisation cycle {u2, u1}")
    ax_u.set(ylabel="drive u [V]")
    ax_u.legend(fontsize=8, loc="upper right")
    ax_x.plot(t[cycle:], wanted / 1e3, color="0.6", lw=2.5, label="wanted")
    ax_x.plot(t[cycle:], model / 1e3, lw=0.9, label="model, driven by u")
    ax_x.set(ylabel="output [µm]")
    ax_x.legend(fontsize=8, loc="upper right")
    ax_e.plot(t[cycle:], model - wanted, lw=0.9)
    ax_e.set(xlabel="time [s]", ylabel="model - wanted [nm]")
    for ax in (ax_u, ax_x, ax_e):
        ax.grid(True, alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def raster_scan(trace, retrace, path, raster, path_file, title: str = "", every: int = 16) -> None:
    """Trace, retrace and their difference (nm) at the nominal pixel positions, and the true
    tip path: where every ``every``-th line and column of pixels really was, over the
    nominal grid. ``trace``/``retrace`` are ``AFMImage``; ``path`` (lines, pixels, 2) nm."""
    fig, axes = subplots(1, 4, figsize=(20, 5.2), constrained_layout=True)
    um = [e / 1e3 for e in trace.extent]
    for ax, image, name in ((axes[0], trace.z, "trace"), (axes[1], retrace.z, "retrace")):
        im = ax.imshow(image, origin="lower", extent=um, cmap="afmhot")
        fig.colorbar(im, ax=ax, label="height (nm)", shrink=0.85)
        ax.set_title(f"{name} (x rising)" if name == "trace" else f"{name} (x falling)")
    diff = trace.z - retrace.z
    lim = float(np.max(np.abs(diff))) or 1.0
    im = axes[2].imshow(diff, origin="lower", extent=um, cmap="RdBu_r", vmin=-lim, vmax=lim)
    fig.colorbar(im, ax=axes[2], label="trace - retrace (nm)", shrink=0.85)
    axes[2].set_title(f"difference (rms {np.sqrt(np.mean(diff**2)):.0f} nm)")
    ax = axes[3]
    nx, ny = np.meshgrid(trace.x, trace.y)
    for pick in (np.s_[::every, :], np.s_[:, ::every]):
        for a, b, style in (
            (nx, ny, dict(color="k", lw=0.6, ls=":")),
            (path[..., 0], path[..., 1], dict(color="C3", lw=1.0)),
        ):
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


def compensation(images: dict, raster, path, title: str = "", every: int = 16) -> None:
    """One column per drive: trace and retrace images (nm) of the same lattice at the nominal
    pixel positions (the paper's Fig. 6 and 7), and the fast-axis error of the tip (true
    minus wanted x, nm; its mean over the image removed) along every ``every``-th line."""
    names = list(images)
    fig, axes = subplots(
        3, len(names), figsize=(3.3 * len(names), 10), constrained_layout=True, squeeze=False
    )
    ext = [
        raster.origin[0] / 1e3,
        (raster.origin[0] + raster.size[0]) / 1e3,
        raster.origin[1] / 1e3,
        (raster.origin[1] + raster.size[1]) / 1e3,
    ]
    x = raster.origin[0] + raster.pixel_size[0] * np.arange(raster.pixels)
    errors = {
        n: np.stack([np.asarray(getattr(images[n], f"path_{k}"))[..., 0] - x for k in ("trace", "retrace")])
        for n in names
    }
    lim = max(float(np.abs(e - e.mean()).max()) for e in errors.values())
    for j, n in enumerate(names):
        for i, k in enumerate(("trace", "retrace")):
            ax = axes[i, j]
            im = ax.imshow(np.asarray(getattr(images[n], k)), origin="lower", extent=ext, cmap="afmhot")
            ax.set_title(f"{n}\n{k}" if i == 0 else k, fontsize=9)
            ax.set_xlabel("x nominal (µm)")
            if j == 0:
                ax.set_ylabel("y nominal (µm)")
        e = errors[n] - errors[n].mean()
        ax = axes[2, j]
        for i, (k, c) in enumerate((("trace", "C0"), ("retrace", "C3"))):
            ax.plot(x / 1e3, e[i, ::every].T, color=c, lw=0.6, alpha=0.7)
            ax.plot([], [], color=c, label=k)
        ax.set(
            xlabel="x nominal (µm)",
            ylim=(-1.05 * lim, 1.05 * lim),
            title=f"max |error| {100 * np.abs(e).max() / raster.size[0]:.2f} % of width",
        )
        if j == 0:
            ax.set_ylabel("true - wanted x (nm)")
            ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
    fig.colorbar(im, ax=axes[:2], label="height (nm)", shrink=0.6)
    if title:  # wrapped to the figure's width (about 11 characters of the title an inch)
        fig.suptitle(textwrap.fill(title, width=int(11 * fig.get_figwidth())))
    fig.savefig(path, dpi=110)


def landmarks(panels: dict, raster, path) -> None:
    """Step B: each workspace image with the indents intended (``D``, +) and found (``M``, o),
    their displacement magnified to be seen. ``panels`` maps a title to ``(images, D, M,
    D_found)``: ``D_found`` the intended positions of the indents found, pair by pair with ``M``."""
    panels = {k: v for k, v in panels.items() if v is not None}
    fig, axes = subplots(1, len(panels), figsize=(6.5 * len(panels), 6.2), squeeze=False)
    x0, y0 = raster.origin
    dx, dy = raster.pixel_size
    extent = np.array(
        [x0 - dx / 2, x0 + dx * (raster.pixels - 0.5), y0 - dy / 2, y0 + dy * (raster.lines - 0.5)]
    )
    for ax, (title, (images, D, M, D_found)) in zip(axes[0], panels.items()):
        z = np.asarray(images.trace)
        lo, hi = np.percentile(z, [1, 99.5])
        ax.imshow(z, origin="lower", extent=extent / 1e3, cmap="afmhot", vmin=lo, vmax=hi)
        ax.plot(D[:, 0] / 1e3, D[:, 1] / 1e3, "+", color="c", ms=10, mew=1.5, label="intended D")
        ax.plot(M[:, 0] / 1e3, M[:, 1] / 1e3, "o", mfc="none", color="lime", ms=9, label="found M")
        if len(M):
            err = np.linalg.norm(M - D_found, axis=1)
            spacing = np.median(np.linalg.norm(np.diff(D, axis=0), axis=1))
            gain = float(np.clip(0.4 * spacing / max(err.max(), 1e-9), 1, 20)) // 1
            ax.quiver(
                D_found[:, 0] / 1e3,
                D_found[:, 1] / 1e3,
                (M - D_found)[:, 0] / 1e3,
                (M - D_found)[:, 1] / 1e3,
                angles="xy",
                scale_units="xy",
                scale=1 / gain,
                color="w",
                width=0.004,
                label=f"M - D (x{gain:g})",
            )
            title += f"\n|M - D|: rms {np.sqrt(np.mean(err**2)):.0f} nm, max {err.max():.0f} nm"
        if len(M) < len(D):
            title += f"; {len(M)} of {len(D)} landmarks found"
        ax.set(title=title, xlabel="x [µm]", ylabel="y [µm]")
        ax.legend(fontsize=8, loc="upper right", framealpha=0.6)
    fig.suptitle("Step B: landmark grid pressed, re-scanned and found (particles are the bright dots)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def _examples(radii: np.ndarray, k: int = 3) -> np.ndarray:
    """Indices of ``k`` trials spread over the particle sizes: smallest, middle, largest."""
    order = np.argsort(radii)
    return order[np.linspace(0, len(order) - 1, k).round().astype(int)]


def local_scans(r, truth: np.ndarray, radii: np.ndarray, path) -> None:
    """Step C: the local-scan lines of three targets, about the centre each scan found, with
    the particle where it truly lies relative to the tip after the final move. ``r``: the
    trials' results (``jaxafm.position.trials.TrialResults``, NumPy arrays) with step C."""
    names = {0: ("search (x)", "0.6"), 1: ("centre (y)", "tab:blue"), 2: ("centre (x)", "tab:red")}
    picks = _examples(radii)
    fig, axes = subplots(1, len(picks), figsize=(5.2 * len(picks), 5.4))
    step_c, scan = r.step_c, r.step_c.scan
    for ax, i in zip(np.atleast_1d(axes), picks):
        c = scan.centre[i]
        n = int(scan.lines[i])
        for j in range(n):
            phase = int(scan.phases[i, j])
            a, b = scan.starts[i, j] - c, scan.ends[i, j] - c
            label, colour = names[phase]
            ax.plot(
                [a[0], b[0]],
                [a[1], b[1]],
                color=colour,
                lw=1.5,
                alpha=0.8,
                label=label if j == min(k for k in range(n) if int(scan.phases[i, k]) == phase) else None,
            )
        p = truth[i] - step_c.tip[i]
        ax.add_patch(Circle(p, radii[i], fill=False, color="k", lw=1.5, label="particle (true, vs tip)"))
        guess = scan.starts[i, 0] * 0.5 + scan.ends[i, 0] * 0.5 - c
        ax.plot(*guess, "x", color="tab:orange", ms=10, mew=2, label="target after A+B")
        ax.plot(0, 0, "k+", ms=14, mew=1.5, label="centre found")
        ax.set(
            title=f"R = {radii[i]:.1f} nm: {n} lines, error {step_c.error_nm[i]:.2f} nm "
            f"({step_c.error_nm[i] / radii[i]:.3f} R)",
            xlabel="x - centre found [nm]",
            ylabel="y - centre found [nm]",
            aspect="equal",
        )
        ax.legend(fontsize=7, loc="lower left")
    fig.suptitle("Step C: local scans (each line scanned there and back) on particles of three sizes")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def pushes(r, truth: np.ndarray, radii: np.ndarray, path) -> None:
    """The push: three examples (tip path, particle before and after, goal and its tolerance),
    and the miss distance of every particle in units of its radius. ``r``: the trials' results
    (``jaxafm.position.trials.TrialResults``, NumPy arrays) with the push."""
    picks = _examples(radii)
    final, goal = r.push.final, r.push_goal
    fig, axes = subplots(1, len(picks) + 1, figsize=(5 * (len(picks) + 1), 5))
    for ax, i in zip(axes, picks):
        o = truth[i]
        tip = r.push.first.path[i] - o
        ax.plot(tip[:, 0], tip[:, 1], "-", color="tab:blue", lw=1, label="tip (true), first push")
        ax.add_patch(
            Circle((0, 0), radii[i], fill=False, color="0.5", lw=1.5, ls="--", label="particle before")
        )
        ax.add_patch(Circle(final[i] - o, radii[i], fill=False, color="k", lw=1.5, label="particle after"))
        g = goal[i] - o
        ax.plot(*g, "*", color="tab:red", ms=12, label="goal")
        miss = np.linalg.norm(final[i] - goal[i])
        ax.set(
            title=f"R = {radii[i]:.1f} nm: miss {miss:.2f} nm",
            xlabel="x [nm]",
            ylabel="y [nm]",
            aspect="equal",
        )
        ax.legend(fontsize=7, loc="best")
    miss = np.linalg.norm(final - goal, axis=-1) / radii
    ax = axes[-1]
    ax.hist(miss, bins=40, color="tab:blue")
    ax.set(
        xlabel="miss / R",
        ylabel="particles",
        title=f"all {len(miss)} pushes: median miss {np.median(miss):.3f} R",
    )
    fig.suptitle("The pushing task after A+B+C (particle carried by the tip from contact on)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def stage_errors(errors: dict, path) -> None:
    """Cumulative distribution of the error at the target (nm) after each stage."""
    fig, ax = subplots(figsize=(8, 5))
    for name, e in errors.items():
        e = np.sort(np.asarray(e))
        ax.step(
            e, np.arange(1, e.size + 1) / e.size, where="post", label=f"{name} (median {np.median(e):.1f} nm)"
        )
    ax.axvline(20.0, color="k", ls=":", lw=1)
    ax.text(20.0, 0.02, " 20 nm", fontsize=8)
    ax.set(
        xscale="log",
        xlabel="error at the target [nm] (true tip to true particle centre)",
        ylabel="fraction of targets",
        title="Positioning error after each stage (one run, simulated AFM)",
    )
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def study_errors(errors: dict, radii: np.ndarray, path) -> None:
    """A study's error per stage: cumulative distribution (nm) and histogram of error / R."""
    fig, (ax, bx) = subplots(1, 2, figsize=(12, 4.8))
    rel = {name: e / radii for name, e in errors.items()}
    finite = np.concatenate([r[np.isfinite(r)] for r in rel.values()])
    bins = (
        np.logspace(np.log10(max(finite.min(), 1e-4)), np.log10(finite.max() * 1.01), 50)
        if finite.size
        else 10
    )
    for name, e in errors.items():
        ok = np.isfinite(e)
        if not ok.any():
            continue
        s = np.sort(e[ok])
        ax.step(
            s,
            np.arange(1, s.size + 1) / e.size,
            where="post",
            label=f"{name} (median {np.median(s):.2g} nm, {100 * ok.mean():.1f} % ran)",  # as the stage table
        )
        bx.hist(rel[name][ok], bins=bins, histtype="step", lw=1.5, label=name)
    ax.set(
        xscale="log",
        xlabel="error at the target [nm] (true tip to true particle centre)",
        ylabel="fraction of trials",
        title="Cumulative distribution per stage",
    )
    bx.axvline(0.1, color="k", ls=":", lw=1)
    bx.text(0.1, 0.97, " 0.1 R", fontsize=8, transform=bx.get_xaxis_transform(), va="top")
    bx.set(
        xscale="log",
        xlabel="error / particle radius R (push: miss / R)",
        ylabel="trials",
        title="Histogram of the error relative to the particle's radius",
    )
    for a in (ax, bx):
        a.grid(True, which="both", alpha=0.3)
        a.legend(fontsize=8, loc="upper left")
    fig.suptitle(f"Monte-Carlo positioning study, {len(radii)} trials (simulated AFM)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def push_reliability(scores: dict, predicted: np.ndarray, path, title: str = "") -> None:
    """A reliability diagram of predicted push success: per tenth of predicted probability, the
    observed success rate against the mean prediction (binomial 2-sd bars; the bin's trials
    beside it), and the predictions' histogram. ``scores``:
    :func:`~jaxafm.study.reliability.reliability`."""
    fig, (ax, bx) = subplots(1, 2, figsize=(12, 5), gridspec_kw={"width_ratios": [1.3, 1]})
    ax.plot([0, 100], [0, 100], color="0.6", lw=1, label="perfectly reliable")
    ax.fill_between([0, 100], [-5, 95], [5, 105], color="0.9", label="within 5 points")
    bins = scores["bins"]
    p = np.array([b["predicted_pct"] for b in bins])
    o = np.array([b["observed_pct"] for b in bins])
    n = np.array([b["trials"] for b in bins])
    sd = 200 * np.sqrt(np.clip(p / 100 * (1 - p / 100), 1e-9, None) / np.maximum(n, 1))
    ax.errorbar(p, o, yerr=sd, fmt="o", color="C0", capsize=3, label="observed (2 sd of a binomial)")
    for x, y, k in zip(p, o, n):
        ax.annotate(f"{k}", (x, y), textcoords="offset points", xytext=(6, -10), fontsize=7)
    ax.set(
        xlim=(0, 100),
        ylim=(0, 100),
        xlabel="predicted success [%] (mean over the bin)",
        ylabel="observed success [%]",
        title=f"Brier {scores['brier']:.4f} against {scores['brier_base_rate']:.4f} for the overall rate",
    )
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    q = np.asarray(predicted, float)
    bx.hist(100 * q[np.isfinite(q)], bins=np.linspace(0, 100, 41), color="C0")
    bx.set(
        xlabel="predicted success [%]", ylabel="trials", yscale="log", title=f"{scores['trials']} predictions"
    )
    bx.grid(True, alpha=0.3)
    fig.suptitle(title or "First push: predicted against observed success")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def step_a_validation(view, path, title: str = "") -> None:
    """Step A checked on its own data, as a microscopist reads it (``view``: a
    :class:`~jaxafm.jobs.calibrate.ValidationView`, nm and the scan's nominal frame throughout):

    - the trace with its background removed, and the chords the fit saw (cyan) and held out
      (magenta); the background removed (a plane, a bow and each line's offset);
    - the trace placed where the fitted scanner says the tip was, with the lattice's sites:
      straight rows and columns where the model is right;
    - each chord's midpoint offset from its feature's line through the site (the fit's
      residual, nm);
    - each feature's retrace-to-trace shift along the fast axis, as the images show it (the loop
      and the delays) and after correction (0 where the model explains them);
    - the held-out features' errors from their sites, raw and corrected, as arrows magnified to
      be seen (the factors in the legend).
    """
    fig, axes = subplots(2, 3, figsize=(17, 10.5), constrained_layout=True)
    ext = np.asarray(view.extent) / 1e3
    lo, hi = _validation_images(fig, axes[0, 0], axes[0, 1], view, ext)
    _validation_placed(axes[0, 2], view, lo, hi)
    _validation_chords(fig, axes[1, 0], view, ext)
    _validation_shifts(axes[1, 1], view)
    _validation_held_out(axes[1, 2], view)
    if title:
        fig.suptitle(title)
    fig.savefig(path, dpi=100, bbox_inches="tight")


def _validation_images(fig, ax, ax_background, view, ext) -> tuple:
    """The levelled trace with its chord ends, and the background removed; returns the height
    range (nm) the trace is shown over."""
    lo, hi = np.percentile(view.levelled, [1, 99])
    im = ax.imshow(view.levelled, origin="lower", extent=ext, cmap="afmhot", vmin=lo, vmax=hi)
    for ends, c, label in ((view.chords_fitted, "cyan", "fitted"), (view.chords_held, "magenta", "held out")):
        if len(ends):
            ax.plot(
                ends[..., 0].ravel() / 1e3,
                ends[..., 1].ravel() / 1e3,
                ".",
                ms=1.2,
                color=c,
                label=f"chord ends, {label}",
            )
    ax.legend(fontsize=8, loc="upper right", markerscale=6)
    ax.set(
        title="trace, background removed", xlabel="fast axis, nominal (µm)", ylabel="slow axis, nominal (µm)"
    )
    fig.colorbar(im, ax=ax, label="height (nm)", shrink=0.8)
    ax = ax_background
    im = ax.imshow(view.background, origin="lower", extent=ext, cmap="viridis")
    ax.set(
        title=f"background removed (plane, bow, line offsets: {np.ptp(view.background):.3g} nm)",
        xlabel="fast axis, nominal (µm)",
    )
    fig.colorbar(im, ax=ax, label="background height (nm)", shrink=0.8)
    return lo, hi


def _validation_placed(ax, view, lo, hi) -> None:
    """The trace placed where the fitted scanner put the tip, over the lattice's sites."""
    ax.imshow(
        view.placed,
        origin="lower",
        extent=np.asarray(view.placed_extent) / 1e3,
        cmap="afmhot",
        vmin=lo,
        vmax=hi,
    )
    ax.plot(view.sites[:, 0] / 1e3, view.sites[:, 1] / 1e3, "+", color="C2", ms=6, label="lattice sites")
    ax.legend(fontsize=8, loc="upper right")
    ax.set(
        title="trace where the fitted scanner put the tip", xlabel="x (µm)", ylabel="y (µm)", aspect="equal"
    )


def _validation_chords(fig, ax, view, ext) -> None:
    """Each chord's midpoint off its feature's line (the chord fit's residual, nm)."""
    lim = float(np.percentile(np.abs(view.chord_offsets), 98)) or 1.0
    sc = ax.scatter(
        view.chord_mid[:, 0] / 1e3,
        view.chord_mid[:, 1] / 1e3,
        c=view.chord_offsets,
        s=3,
        cmap="RdBu_r",
        vmin=-lim,
        vmax=lim,
    )
    ax.set(
        title=f"chord midpoints off their features' lines (rms {np.sqrt(np.mean(view.chord_offsets**2)):.3g} nm)",
        xlabel="fast axis, nominal (µm)",
        ylabel="slow axis, nominal (µm)",
        xlim=ext[:2],
        ylim=ext[2:],
        aspect="equal",
    )
    fig.colorbar(sc, ax=ax, label="midpoint offset (nm)", shrink=0.8)


def _validation_shifts(ax, view) -> None:
    """Each feature's retrace less trace position along the fast axis, raw and corrected."""
    for shift, c, label in (
        (view.shift_raw, "C3", "raw (as imaged)"),
        (view.shift_corrected, "C0", "corrected (model)"),
    ):
        ax.plot(
            view.shift_at / 1e3,
            shift,
            "o",
            ms=4,
            color=c,
            label=f"{label}: rms {np.sqrt(np.mean(shift**2)):.3g} nm",
        )
    ax.axhline(0, color="k", lw=0.5)
    ax.legend(fontsize=8)
    ax.set(
        title="each feature's retrace less trace position, along the fast axis",
        xlabel="fast axis, nominal (µm)",
        ylabel="retrace less trace (nm)",
    )


def _ellipses(ax, sites, ellipse, errors, scale: float) -> None:
    """At each of ``sites`` (n, 2) nm the ellipse ``x^T E^-1 x <= 1`` of ``ellipse`` (n, 2, 2)
    nm^2 (none where NaN), magnified by ``scale`` as the error arrows, and how many of the
    ``errors`` (n, 2) nm it holds."""
    from matplotlib.patches import Ellipse

    known = np.all(np.isfinite(ellipse), axis=(1, 2))
    inside = 0
    for site, E, e in zip(sites[known], ellipse[known], errors[known]):
        values, vectors = np.linalg.eigh(E)
        minor, major = 2 * np.sqrt(np.maximum(values, 0.0)) * scale / 1e3
        angle = np.degrees(np.arctan2(vectors[1, 1], vectors[0, 1]))  # of the major axis
        ax.add_patch(
            Ellipse(site / 1e3, major, minor, angle=angle, fill=False, color="C0", lw=0.6, alpha=0.7)
        )
        inside += int(e @ np.linalg.solve(E, e) <= 1.0)
    ax.plot([], [], color="C0", lw=0.6, label=f"predicted 90 % ellipse: holds {inside} of {known.sum()}")


def _validation_held_out(ax, view) -> None:
    """The held-out features' errors from their sites, raw and corrected, as magnified arrows."""
    sites = view.held_sites
    if len(sites):
        spacing = np.median(np.linalg.norm(np.diff(sites, axis=0), axis=1))
        for e, c, label in (
            (view.held_raw, "C3", "raw (nominal)"),
            (view.held_corrected, "C0", "corrected (model)"),
        ):
            rms = np.sqrt(np.mean(np.sum(e**2, axis=1)))
            scale = 0.4 * spacing / max(float(np.abs(e).max()), 1e-9)
            ax.quiver(
                sites[:, 0] / 1e3,
                sites[:, 1] / 1e3,
                e[:, 0] * scale / 1e3,
                e[:, 1] * scale / 1e3,
                color=c,
                angles="xy",
                scale_units="xy",
                scale=1,
                width=0.004,
                label=f"{label}, x{scale:.3g}: rms {rms:.3g} nm",
            )
            if c == "C0" and view.held_ellipse is not None:
                _ellipses(ax, sites, view.held_ellipse, e, scale)
        ax.plot(sites[:, 0] / 1e3, sites[:, 1] / 1e3, "k.", ms=2)
        ax.legend(fontsize=8, loc="upper right")
    what = "held-out features" if view.held_out else "every other site (fitted: no hold-out)"
    ax.set(
        title=f"{what} in this trace: error from their sites",
        xlabel="x (µm)",
        ylabel="y (µm)",
        aspect="equal",
    )


def position_coverage(coverage: dict, path, title: str = "") -> None:
    """The share of trials whose miss (the true A+B error; step C's find about the aim) fell within
    the radius their predicted spread gives at each nominal level, against the level
    (``coverage``: :func:`~jaxafm.study.learning.position_coverage`); on the diagonal a
    calibrated prediction."""
    fig, ax = subplots(figsize=(6, 5))
    levels = 100 * np.asarray(coverage["levels"])
    ax.plot([0, 100], [0, 100], color="0.6", lw=1, label="calibrated")
    what = {"true": ("true A+B error", "o-"), "find": ("step C's find about the aim", "s--")}
    for kind, (label, style) in what.items():
        for name, colour in (("all", "C0"), ("learnt", "C1")):
            v = coverage[kind][name]
            ax.plot(
                levels, v["covered_pct"], style, color=colour, label=f"{label}, {name}: {v['trials']} trials"
            )
    ax.set(
        xlim=(0, 100),
        ylim=(0, 100),
        xlabel="nominal level of the predicted radius [%]",
        ylabel="misses within it [%]",
        title=title or "A+B moves against the tracker's predicted spread",
    )
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def learning_curve(rounds: dict, path, title: str = "") -> None:
    """The A+B error of a scanner's trials against their place in its sequence, as step C's finds
    teach the moves (``rounds``: :func:`~jaxafm.study.learning.learning_rounds`): each scanner's
    median per round (thin) and the median over every scanner's trials per round (bold); and per
    scanner, the median of its first round against that of its trials aimed by ten finds or more."""
    fig, (ax, bx) = subplots(1, 2, figsize=(12, 5), gridspec_kw={"width_ratios": [1.6, 1]})
    k = rounds["first_trial"]
    for e in rounds["per_scanner"].values():
        ax.plot(k, e, color="0.6", lw=0.8, alpha=0.7)
    ax.plot(k, rounds["median_nm"], color="C0", lw=2.5, label="all scanners' trials")
    ax.set(
        xlabel="trial of the scanner (first of its round)",
        ylabel="A+B error, median of the round [nm]",
        yscale="log",
        title=f"rounds of {rounds['round_trials']}; thin: one scanner each",
    )
    _plain_log_ticks(ax.yaxis)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    first = {s: e[0] for s, e in rounds["per_scanner"].items()}
    learnt = rounds["per_scanner_learnt"]
    shown = [s for s in first if np.isfinite(learnt[s]) and first[s] > 0]
    x, y = np.array([first[s] for s in shown]), np.array([learnt[s] for s in shown])
    lim = (0.7 * min(x.min(), y.min()), 1.4 * max(x.max(), y.max())) if shown else (1, 10)
    bx.plot(lim, lim, color="0.6", lw=1, label="no change")
    bx.plot(lim, np.divide(lim, 2), color="0.6", lw=1, ls="--", label="halved")
    bx.scatter(x, y, color="C0", zorder=3)
    for s, a, b in zip(shown, x, y):
        bx.annotate(str(s), (a, b), textcoords="offset points", xytext=(4, 3), fontsize=7)
    never = rounds.get("unlearnt_scanners", [])
    bx.set(
        xscale="log",
        yscale="log",
        xlim=lim,
        ylim=lim,
        xlabel="first round, median [nm]",
        ylabel="aimed by 10 finds or more, median [nm]",
        title="per scanner" + (f" (never 10 finds: {', '.join(map(str, never))})" if never else ""),
    )
    _plain_log_ticks(bx.xaxis)
    _plain_log_ticks(bx.yaxis)
    bx.grid(True, which="both", alpha=0.3)
    bx.legend(fontsize=8)
    fig.suptitle(title or "A+B moves learning from step C's finds")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
