"""An independent generator of calibration-lattice AFM images (NumPy/SciPy only, no jaxafm).

Written from textbook definitions, not from jaxafm's simulator, so that step A's identification
can be scored on images its own model code did not make. Units: positions nm, time s, drive V.

**Scanner** (per axis i = x, y; the drive ``u_i(t)`` V is linear between the points of a uniform
time grid ``t_n = n h``):

1. Rate dependence, a first-order lag of the *drive* (the amplifier and the piezo's capacitance),
   ``tau v' + v = u``. For an input linear over each step this is solved exactly (first-order
   hold): ``v[n+1] = u[n+1] - tau s + (v[n] - u[n] + tau s) q``, ``s = (u[n+1] - u[n]) / h``,
   ``q = exp(-h / tau)``, at rest at ``u[0]``. At a line rate f the tip lags its drive by about
   tau, so trace and retrace part by ``2 tau v_tip``: the loop seen in the image grows with f.
2. Hysteresis, a discretised Preisach plane. Relays ``R_k`` with thresholds ``alpha_k >= beta_k``::

       R_k(t) = +1 if v(t) >= alpha_k,   -1 if v(t) <= beta_k,   R_k(t-) otherwise

   on a factorised density ``mu(alpha, beta) = N(alpha; a_up, s_up) N(beta; -a_dn, s_dn)`` over
   ``alpha >= beta``: up-thresholds and down-thresholds are independent Gaussians. The relays sit
   at the points ``alpha = a_up + s_up Phi^-1(p)``, ``beta = -a_dn + s_dn Phi^-1(q)`` of a jittered
   n x n grid of quantiles ``(p, q)`` (one random point per cell, so no two relays switch at once
   and the output has no staircase of whole rows), weight ``1 / n^2`` each; the points with
   ``alpha < beta`` are dropped. Start state: demagnetised about ``v[0]`` (``R = +1`` where
   ``(alpha + beta) / 2 < v[0]``, else -1). Output ``p_i = k_i v + S_i sum_k w_k R_k`` (nm): a
   reversible slope ``k_i`` (nm/V) and the relays' amplitude ``S_i`` (nm). On a major loop between
   ``-A`` and ``A`` the descending branch lies above the ascending one by (closed form)::

       W(u) = 2 S [F_dn(u) - F_dn(-A)] [F_up(A) - F_up(u)]

   (``F`` the Gaussians' CDFs: the relays with ``-A <= beta < u < alpha <= A``); ``s_up != s_dn``
   makes the two branches differ in shape (asymmetric hysteresis). ``k_i, S_i`` are set so that
   the major loop over the whole drive ``+-u_max`` spans ``2 u_max g_i`` (``g_i`` the true
   sensitivity) and is ``loop_pct`` of that span wide at ``u = 0``. :func:`preisach` evaluates the
   relays exactly run by run (between two reversals only relays in the opposite state switch, in
   threshold order); :func:`preisach_loop` is the literal time loop it is tested against.
3. Creep, logarithmic (Boltzmann superposition of the log law): every output increment creeps on::

       c(t_n) = p(t_n) + gamma sum_{j <= n} (p[j] - p[j-1]) log10(1 + (t_n - t_j) / t0),  t0 = 0.1 s

   so a step ``d0`` gives ``d0 (1 + gamma log10(1 + t / t0))``: gamma d0 per decade of time.
4. Coupling (linear): ``x = c_x + kappa_xy c_y``, ``y = c_y + kappa_yx c_x``.
5. Bow (optional, tube scanner, quadratic): ``x += b_x y^2``, ``y += b_y x^2`` (b in 1/nm).
6. Drift: ``+ v_drift t`` (nm/s, t from the scan's start).

**Raster** (:class:`Raster`): ``pixels`` per line, ``lines``, ``line_rate_hz`` (one trace and one
retrace per line period T), ``overscan`` (whole pixels ``n_os = overscan * pixels`` beyond the
image at each end of a line), ``angle_deg`` (the scan frame turned anticlockwise on the stage:
at 90 degrees the fast axis is the stage's y and the lines step towards -x) and ``direction``
(``up``: image row 0 scanned first). A half line holds ``n_line = pixels + 2 n_os`` samples at
the centres of equal slots: ``dt = 1 / (2 f n_line)``, the model grid ``h = dt / 2`` (so both the
line reversals and the pixel centres lie on it). The fast axis runs from ``-W/2 - n_os px`` to
``W/2 + n_os px`` and back at constant speed; the slow axis steps to the next line during the
retrace's last ``n_os`` samples (half a sample without overscan). Before the raster the drive runs
the initialisation cycle: from rest at 0 V to ``(-u_max, -u_max)`` in 1 s, to ``(u_max, u_max)`` in
2 s, held 1 s, to the raster's start in 1 s. The drive is the nominal raster: stage position over
the nominal sensitivity ``s_nom`` (nm/V, both axes); the tip goes where the scanner sends it.

**Sample** (:class:`Lattice`): a square lattice of pitch P turned by phi, sites
``o + R(phi) (m, n) P``; each feature a rounded square (half-width a at half height, corner radius
r) or a disc (radius a), a pit or a pillar of depth/height H with walls of angle theta_w. With the
signed distance d to the feature's half-height outline (rounded box:
``|max(|q| - (a - r), 0)| + min(max(q_x, q_y) - (a - r), 0) - r``), the profile is
``z0 = +-H clip(1/2 - d / w, 0, 1)``, ``w = H / tan(theta_w)``. Tip broadening: a sphere-capped
cone (apex radius R, half angle theta), ``T(rho) = R - sqrt(R^2 - rho^2)`` for ``rho <= R cos
theta``, else ``R (1 - sin theta) + (rho - R cos theta) / tan theta``. The recorded height is the
grey dilation ``max_s [z(p + s) - T(|s|)]``; for a convex feature whose outline's distance is
1-Lipschitz and changes at rate 1 along its normals it reduces exactly to one dimension,
``g(d) = max_rho [z0(d -+ rho) - T(rho)]`` (minus for a pillar: towards the top; plus for a pit:
out of it): exact where the outline is a union of discs of radius w/2 (``r >= w/2``) and every
broadened feature stays inside its own lattice cell (both checked).
The image samples ``g(d(tip))`` at the true tip position of every pixel centre.

**Image artefacts** (:class:`Artefacts`): background ``G . X + kappa |X|^2`` at the tip's stage
position X (a plane rising ``tilt_nm`` across the image, a bow of ``bow_nm`` at its corners), a
per-line offset (shared by trace and retrace, plus a smaller one of each), a first-order z-feedback
lag (``tau_z``, :func:`lag_ramp` along the time-ordered samples), white noise, ``spikes`` pixels of +-1-3 H, and
``saturated`` pixels driven beyond the ADC's ceiling (the image's top + 8 H) and clipped there.

:func:`draw_case` draws one case (a seed and a few magnitudes): one scanner and one lattice, scanned
at several line rates and angles; it returns the images, the metadata a user has and the truth.
:func:`write_case` writes them as a user would give them to jaxafm (jaxafm-image ``.npz`` or
TIFF, and ``data.json``); :func:`render_case` draws them; ``python tests/independent_lattice.py``
renders a few cases into ``/tmp/lattice_gen``.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Optional

import numpy as np
from scipy import ndimage, signal, special

U_MAX_V = 10.0
OVERSAMPLE = 2  # model steps per pixel sample: reversals and pixel centres on the grid
CREEP_T0_S = 0.1
RELAY_GRID = 200  # n: n x n relays per axis
INIT_LEG_S, INIT_HOLD_S = 1.0, 1.0
LINE_RATES_HZ = (0.5, 1.0, 2.0, 4.0)
ANGLES_DEG = (0.0, 90.0)
DRIVE_FRACTION = 0.9  # the raster with its overscan spans this fraction of +-u_max
FEATURES = ("square_pits", "round_pits", "round_pillars")
UNIDENTIFIABLE = ("one_speed", "few_features")

#: Per kind of lattice: image, lattice and magnitude defaults (each case draws within the ranges).
KINDS = {
    "coarse": {  # like the Nanosurf 10 um lattices: 50 um, 256 px, about 5 x 5 features
        "size_nm": 50_000.0,
        "pixels": 256,
        "pitch_nm": 10_000.0,
        "half_width_nm": {"square_pits": 2000.0, "round_pits": 2000.0, "round_pillars": 2800.0},
        "corner_radius_nm": 500.0,
        "depth_nm": 490.0,
        "wall_angle_deg": (60.0, 80.0),
        "tip_radius_nm": 20.0,
        "drift_nm_per_s": (0.2, 1.0),
        "noise_nm": 1.5,
        "line_offset_nm": 3.0,
    },
    "fine": {  # 1 um pitch on a 5 um image: many small features
        "size_nm": 5_000.0,
        "pixels": 256,
        "pitch_nm": 1_000.0,
        "half_width_nm": {"square_pits": 250.0, "round_pits": 250.0, "round_pillars": 250.0},
        "corner_radius_nm": 60.0,
        "depth_nm": 120.0,
        "wall_angle_deg": (55.0, 75.0),
        "tip_radius_nm": 8.0,
        "drift_nm_per_s": (0.02, 0.1),
        "noise_nm": 0.5,
        "line_offset_nm": 1.0,
    },
}


def rotation(angle_deg: float) -> np.ndarray:
    """The anticlockwise rotation by ``angle_deg``."""
    a = np.deg2rad(angle_deg)
    return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])


# ============================================================================ scanner
@dataclasses.dataclass(frozen=True)
class Relays:
    """One axis' Preisach plane: thresholds ``alpha >= beta`` (V), weights (sum <= 1), and the
    factorised Gaussian density they sample: up-thresholds ``N(up_mean, up_std)``, down-thresholds
    ``N(down_mean, down_std)``."""

    alpha: np.ndarray
    beta: np.ndarray
    weight: np.ndarray
    up_mean: float
    up_std: float
    down_mean: float
    down_std: float


def relay_plane(up_mean, up_std, down_mean, down_std, n: int = RELAY_GRID, seed: int = 0) -> Relays:
    """Relays at one jittered point of each cell of an n x n grid of quantiles, weight ``1/n^2``.

    ``alpha = up_mean + up_std Phi^-1(p)``, ``beta = down_mean + down_std Phi^-1(q)`` with
    ``p = (i + U) / n``, ``q = (j + U') / n`` (U, U' uniform per cell); ``alpha < beta`` dropped.
    """
    rng = np.random.default_rng(seed)
    i, j = (g.ravel() for g in np.meshgrid(np.arange(n), np.arange(n), indexing="ij"))
    alpha = up_mean + up_std * special.ndtri((i + rng.random(i.size)) / n)
    beta = down_mean + down_std * special.ndtri((j + rng.random(j.size)) / n)
    keep = alpha >= beta
    w = np.full(int(keep.sum()), 1.0 / n**2)
    return Relays(alpha[keep], beta[keep], w, up_mean, up_std, down_mean, down_std)


def demagnetised(relays: Relays, u0: float) -> np.ndarray:
    """The state demagnetised about ``u0``: +1 where ``(alpha + beta) / 2 < u0``, else -1."""
    return np.where(0.5 * (relays.alpha + relays.beta) < u0, 1.0, -1.0)


def preisach_loop(u, relays: Relays) -> np.ndarray:
    """``sum_k w_k R_k(t)`` by the relay rule, one time step at a time (the reference)."""
    u = np.asarray(u, float)
    state = demagnetised(relays, u[0])
    out = np.empty(u.size)
    for n, un in enumerate(u):
        state = np.where(un >= relays.alpha, 1.0, np.where(un <= relays.beta, -1.0, state))
        out[n] = relays.weight @ state
    return out


def monotone_runs(u, tol: float = 1e-9) -> list:
    """``(start, end, sign)`` of the runs of ``u`` between reversals (inclusive sample indices; a
    run starts at the previous run's last sample). Steps smaller than ``tol`` keep the direction."""
    step = np.sign(np.where(np.abs(np.diff(u)) > tol, np.diff(u), 0.0))
    if step.size == 0:
        return []
    nonzero = np.flatnonzero(step)
    first = step[nonzero[0]] if nonzero.size else 1.0
    filled = np.where(step != 0, step, np.nan)
    idx = np.where(~np.isnan(filled), np.arange(step.size), 0)
    np.maximum.accumulate(idx, out=idx)
    direction = np.where(np.isnan(filled[idx]), first, filled[idx])
    cuts = np.flatnonzero(np.diff(direction) != 0) + 1
    starts, ends = np.r_[0, cuts], np.r_[cuts, step.size]
    return [(int(s), int(e), float(direction[s])) for s, e in zip(starts, ends)]


def preisach(u, relays: Relays) -> np.ndarray:
    """``sum_k w_k R_k(t)``, exactly as :func:`preisach_loop`, run by run.

    On a rising run only relays at -1 switch, each when ``u`` reaches ``alpha``: the output is
    ``y_start + 2 sum {w : R = -1, alpha <= max u so far}``, a prefix sum in alpha order; a
    falling run likewise in beta order. The state is updated at the end of each run.
    """
    u = np.asarray(u, float)
    state = demagnetised(relays, u[0])
    w = relays.weight
    by_a, by_b = np.argsort(relays.alpha), np.argsort(relays.beta)
    a_sorted, b_sorted = relays.alpha[by_a], relays.beta[by_b]
    out = np.empty(u.size)
    out[0] = w @ state
    for s, e, sign in monotone_runs(u):
        seg = u[s + 1 : e + 1]
        if sign > 0:
            reach = np.maximum.accumulate(np.maximum(seg, u[s]))
            moving = np.where(state[by_a] < 0, w[by_a], 0.0)
            gained = np.r_[0.0, np.cumsum(moving)]
            k = np.searchsorted(a_sorted, reach, side="right")
            out[s + 1 : e + 1] = out[s] + 2 * gained[k]
            state[by_a[: k[-1]]] = 1.0
        else:
            reach = np.minimum.accumulate(np.minimum(seg, u[s]))
            moving = np.where(state[by_b] > 0, w[by_b], 0.0)
            lost = np.r_[np.cumsum(moving[::-1])[::-1], 0.0]
            k = np.searchsorted(b_sorted, reach, side="left")
            out[s + 1 : e + 1] = out[s] - 2 * lost[k]
            state[by_b[k[-1] :]] = -1.0
    return out


def loop_width_closed_form(u, amplitude, relays: Relays) -> np.ndarray:
    """``W(u) / S`` of the major loop between -A and A: ``2 [F_dn(u) - F_dn(-A)] [F_up(A) - F_up(u)]``."""
    f_up = lambda x: special.ndtr((x - relays.up_mean) / relays.up_std)
    f_dn = lambda x: special.ndtr((x - relays.down_mean) / relays.down_std)
    return 2 * (f_dn(u) - f_dn(-amplitude)) * (f_up(amplitude) - f_up(u))


def major_loop(relays: Relays, amplitude: float, n: int = 2001):
    """(u, ascending, descending) of the relays' sum on the major loop between -A and A (its
    second cycle, after the first has wiped out the start state)."""
    up = np.linspace(-amplitude, amplitude, n)
    cycle = np.concatenate([up, up[::-1][1:], up[1:], up[::-1][1:]])
    y = preisach(cycle, relays)
    m = 2 * (n - 1)
    return up, y[m : m + n], y[m + n - 1 :][::-1]


@dataclasses.dataclass(frozen=True)
class Axis:
    """One axis: ``p = k v + S sum w R`` nm (k nm/V, S nm); ``gain_nm_per_v`` the major loop's span
    over ``2 u_max``; ``loop_pct`` its width at u = 0 over that span."""

    relays: Relays
    reversible_nm_per_v: float
    hysteretic_nm: float
    gain_nm_per_v: float
    loop_pct: float


def make_axis(relays: Relays, gain_nm_per_v: float, loop_pct: float, u_max: float = U_MAX_V) -> Axis:
    """Set k and S so the major loop over +-u_max spans ``2 u_max gain`` and is ``loop_pct`` wide.

    With the relays' own width ``W_R`` at 0 and span ``D_R``: ``S = f 2 u_max g / W_R`` and
    ``k = (2 u_max g - S D_R) / (2 u_max)`` (needs ``f <= W_R / D_R``).
    """
    span = 2 * u_max * gain_nm_per_v
    if loop_pct == 0:
        return Axis(relays, gain_nm_per_v, 0.0, gain_nm_per_v, 0.0)
    u, asc, desc = major_loop(relays, u_max)
    centre = np.argmin(np.abs(u))
    w_r, d_r = desc[centre] - asc[centre], asc[-1] - asc[0]
    if loop_pct / 100 > w_r / d_r:
        raise ValueError(f"loop_pct {loop_pct} exceeds the relays' own loop, {100 * w_r / d_r:.1f} %")
    s = loop_pct / 100 * span / w_r
    return Axis(relays, (span - s * d_r) / (2 * u_max), s, gain_nm_per_v, loop_pct)


@dataclasses.dataclass(frozen=True)
class Scanner:
    """Two axes and the effects between them (module docstring, steps 1-6)."""

    axes: tuple
    tau_s: float = 0.0
    creep_per_decade: float = 0.0
    coupling: tuple = (0.0, 0.0)  # kappa_xy, kappa_yx
    bow_per_nm: tuple = (0.0, 0.0)  # b_x, b_y
    drift_nm_per_s: tuple = (0.0, 0.0)

    def truth(self) -> dict:
        axes = [
            {
                "gain_nm_per_v": a.gain_nm_per_v,
                "loop_pct": a.loop_pct,
                "reversible_nm_per_v": float(a.reversible_nm_per_v),
                "hysteretic_nm": float(a.hysteretic_nm),
                "relays": {
                    "count": int(a.relays.alpha.size),
                    "up_mean_v": a.relays.up_mean,
                    "up_std_v": float(a.relays.up_std),
                    "down_mean_v": float(a.relays.down_mean),
                    "down_std_v": float(a.relays.down_std),
                },
            }
            for a in self.axes
        ]
        return {
            "axes": axes,
            "rate_tau_s": self.tau_s,
            "creep_per_decade": self.creep_per_decade,
            "creep_t0_s": CREEP_T0_S,
            "coupling_xy_yx": list(self.coupling),
            "bow_per_nm": list(self.bow_per_nm),
            "drift_nm_per_s": list(self.drift_nm_per_s),
        }


def lag_ramp(u, tau: float, h: float) -> np.ndarray:
    """``tau v' + v = u`` along axis 0, ``u`` linear between samples h apart; exact, at rest at u[0]."""
    u = np.asarray(u, float)
    if tau <= 0:
        return u.copy()
    q = np.exp(-h / tau)
    c = tau / h * (1 - q)
    b, a = [1 - c, c - q], [1.0, -q]
    zi = signal.lfilter_zi(b, a).reshape((1,) + (1,) * (u.ndim - 1)) * u[:1]
    return signal.lfilter(b, a, u, axis=0, zi=zi)[0]


def log_creep(p, gamma: float, h: float, t0: float = CREEP_T0_S) -> np.ndarray:
    """``p + gamma sum_j dp_j log10(1 + (t - t_j) / t0)`` on a grid of step h (axis 0)."""
    p = np.asarray(p, float)
    if gamma == 0:
        return p.copy()
    kernel = np.log10(1 + np.arange(p.shape[0]) * h / t0)
    dp = np.diff(p, axis=0, prepend=p[:1])
    kernel = kernel.reshape((-1,) + (1,) * (p.ndim - 1))
    return p + gamma * signal.fftconvolve(dp, kernel, axes=0)[: p.shape[0]]


def scanner_path(scanner: Scanner, u, h: float) -> np.ndarray:
    """Tip positions (N, 2) nm in the stage frame for the drive ``u`` (N, 2) V on ``t = n h``."""
    v = lag_ramp(u, scanner.tau_s, h)
    p = np.stack(
        [
            a.reversible_nm_per_v * v[:, i] + a.hysteretic_nm * preisach(v[:, i], a.relays)
            if a.hysteretic_nm
            else a.reversible_nm_per_v * v[:, i]
            for i, a in enumerate(scanner.axes)
        ],
        axis=1,
    )
    c = log_creep(p, scanner.creep_per_decade, h)
    (kxy, kyx), (bx, by) = scanner.coupling, scanner.bow_per_nm
    x, y = c[:, 0] + kxy * c[:, 1], c[:, 1] + kyx * c[:, 0]
    x, y = x + bx * y**2, y + by * x**2
    t = np.arange(len(u)) * h
    return np.stack([x, y], axis=1) + t[:, None] * np.asarray(scanner.drift_nm_per_s)[None, :]


# ============================================================================ raster
@dataclasses.dataclass(frozen=True)
class Raster:
    """A raster scan (module docstring): size (width, height) nm, pixels per line, lines, line rate
    Hz, scan angle degrees, overscan (fraction of the width at each end; a whole number of pixels)
    and the slow-axis direction."""

    size_nm: tuple
    pixels: int
    lines: int
    line_rate_hz: float
    angle_deg: float = 0.0
    overscan: float = 0.05
    direction: str = "up"

    def __post_init__(self):
        if self.direction not in ("up", "down"):
            raise ValueError(f"direction must be 'up' or 'down', got {self.direction!r}")
        if not (self.line_rate_hz > 0 and self.pixels >= 2 and self.lines >= 2 and self.overscan >= 0):
            raise ValueError(f"bad raster {self}")

    @property
    def overscan_px(self) -> int:
        return int(round(self.overscan * self.pixels))

    @property
    def n_line(self) -> int:
        """Samples per half line (pixels and overscan)."""
        return self.pixels + 2 * self.overscan_px

    @property
    def pixel_size(self) -> tuple:
        return (self.size_nm[0] / self.pixels, self.size_nm[1] / self.lines)

    @property
    def dt(self) -> float:
        """Sample time per pixel, ``1 / (2 f n_line)``."""
        return 1.0 / (2 * self.line_rate_hz * self.n_line)

    def rotation(self) -> np.ndarray:
        return rotation(self.angle_deg)

    def meta(self) -> dict:
        """What the instrument records about the scan."""
        return {
            "size_nm": list(self.size_nm),
            "pixels": self.pixels,
            "lines": self.lines,
            "line_rate_hz": self.line_rate_hz,
            "angle_deg": self.angle_deg,
            "overscan": self.overscan_px / self.pixels,
            "scan_direction": self.direction,
            "sample_time_s": self.dt,
        }


@dataclasses.dataclass(frozen=True)
class Drive:
    """The drive of one scan on the model grid ``t = n h``: ``u`` (N, 2) V; ``trace``/``retrace``
    (lines, n_line) grid indices of the samples in time order, line 0 first; ``rows`` the image row
    of each line; ``nominal`` (n_line,) nm the scan-frame x of the samples in column order."""

    h: float
    u: np.ndarray
    trace: np.ndarray
    retrace: np.ndarray
    rows: np.ndarray
    nominal: np.ndarray
    raster_start: int


def _init_cycle(u_start, u_max: float, h: float):
    """The initialisation cycle's drive on the grid, ending at the raster's start ``u_start`` (2,)."""
    leg, hold = INIT_LEG_S, INIT_HOLD_S
    times = np.array([0.0, leg, 3 * leg, 3 * leg + hold, 4 * leg + hold])
    n = int(np.ceil(times[-1] / h))
    times[-1] = n * h  # the raster starts on the grid
    points = np.array([[0.0, 0.0], [-u_max, -u_max], [u_max, u_max], [u_max, u_max], u_start])
    t = np.arange(n) * h
    return np.stack([np.interp(t, times, points[:, i]) for i in range(2)], axis=1)


def raster_drive(raster: Raster, sensitivity_nm_per_v: float, u_max: float = U_MAX_V) -> Drive:
    """The initialisation cycle, then the raster (module docstring), as the nominal drive in V."""
    n_os, n_line, m = raster.overscan_px, raster.n_line, OVERSAMPLE
    (w, hgt), (px, py) = raster.size_nm, raster.pixel_size
    h = raster.dt / m
    x_ends = np.array([-w / 2 - n_os * px, w / 2 + n_os * px])
    k_lines = np.arange(raster.lines)
    y_lines = -hgt / 2 + (k_lines + 0.5) * py
    if raster.direction == "down":
        y_lines = y_lines[::-1]
    per_line = 2 * n_line * m
    i = np.arange(raster.lines * per_line + 1)
    k = np.minimum(i // per_line, raster.lines - 1)
    phase = (i - k * per_line) / per_line
    fast = x_ends[0] + (x_ends[1] - x_ends[0]) * np.where(phase <= 0.5, 2 * phase, 2 - 2 * phase)
    move = max(n_os, 0.5) / (2 * n_line)
    ramp = np.clip((phase - (1 - move)) / move, 0.0, 1.0)
    slow = y_lines[k] + (y_lines[np.minimum(k + 1, raster.lines - 1)] - y_lines[k]) * ramp
    u_raster = (raster.rotation() @ np.stack([fast, slow])).T / sensitivity_nm_per_v
    u_init = _init_cycle(u_raster[0], u_max, h)
    u = np.concatenate([u_init, u_raster])
    if np.abs(u).max() > u_max * (1 + 1e-9):
        raise ValueError(f"the raster needs {np.abs(u).max():.3g} V, beyond u_max = {u_max} V")
    j = np.arange(n_line) * m + m // 2
    start = len(u_init) + k_lines[:, None] * per_line
    rows = k_lines if raster.direction == "up" else k_lines[::-1]
    nominal = x_ends[0] + (np.arange(n_line) + 0.5) * px
    return Drive(h, u, start + j, start + n_line * m + j, rows, nominal, len(u_init))


# ============================================================================ sample
@dataclasses.dataclass(frozen=True)
class Lattice:
    """A square lattice of pits or pillars and the tip that images it (module docstring)."""

    pitch_nm: float
    angle_deg: float
    offset_nm: tuple
    shape: str  # "square" or "round"
    pits: bool
    half_width_nm: float  # at half height
    corner_radius_nm: float
    depth_nm: float
    wall_angle_deg: float
    tip_radius_nm: float
    tip_half_angle_deg: float = 15.0

    def __post_init__(self):
        if self.shape not in ("square", "round"):
            raise ValueError(f"shape must be 'square' or 'round', got {self.shape!r}")
        wall = self.wall_width_nm
        rounding = self.corner_radius_nm if self.shape == "square" else self.half_width_nm
        if not wall / 2 <= rounding <= self.half_width_nm:
            raise ValueError(
                f"the {self.shape} feature's corner radius and half-width must be at least half its wall "
                f"width, {wall / 2:.0f} nm (the 1-D tip dilation is exact for a union of such discs), "
                f"and the radius at most the half-width: {self}"
            )
        reach = (
            self.half_width_nm
            + wall / 2
            + tip_reach(self.depth_nm, self.tip_radius_nm, self.tip_half_angle_deg)
        )
        if reach > self.pitch_nm / 2:
            raise ValueError(
                f"features reach {reach:.0f} nm from their site (walls and tip), beyond half the pitch "
                f"{self.pitch_nm / 2:.0f} nm: the broadened features would touch"
            )

    @property
    def wall_width_nm(self) -> float:
        return self.depth_nm / np.tan(np.deg2rad(self.wall_angle_deg))

    def rotation(self) -> np.ndarray:
        return rotation(self.angle_deg)

    def truth(self) -> dict:
        return dataclasses.asdict(self) | {"wall_width_nm": self.wall_width_nm}


def tip_shape(rho, radius: float, half_angle_deg: float) -> np.ndarray:
    """Height of a sphere-capped cone above its apex at distance ``rho`` nm."""
    th = np.deg2rad(half_angle_deg)
    rho = np.asarray(rho, float)
    r_c = radius * np.cos(th)
    sphere = radius - np.sqrt(np.maximum(radius**2 - np.minimum(rho, r_c) ** 2, 0.0))
    cone = radius * (1 - np.sin(th)) + (rho - r_c) / np.tan(th)
    return np.where(rho <= r_c, sphere, cone)


def tip_reach(height: float, radius: float, half_angle_deg: float) -> float:
    """The distance at which the tip's flank is ``height`` above its apex."""
    th = np.deg2rad(half_angle_deg)
    r_c = radius * np.cos(th)
    if height <= radius * (1 - np.sin(th)):
        return float(np.sqrt(radius**2 - (radius - height) ** 2))
    return float(r_c + (height - radius * (1 - np.sin(th))) * np.tan(th))


def outline_distance(local, lattice: Lattice) -> np.ndarray:
    """Signed distance (nm, < 0 inside) of lattice-frame points (..., 2) to the half-height outline."""
    a = lattice.half_width_nm
    if lattice.shape == "round":
        return np.hypot(local[..., 0], local[..., 1]) - a
    r = lattice.corner_radius_nm
    q = np.abs(local) - (a - r)
    outside = np.hypot(np.maximum(q[..., 0], 0), np.maximum(q[..., 1], 0))
    return outside + np.minimum(np.maximum(q[..., 0], q[..., 1]), 0) - r


def wall_profile(d, lattice: Lattice) -> np.ndarray:
    """The unbroadened height ``+-H clip(1/2 - d / w, 0, 1)`` against the outline distance d."""
    z = lattice.depth_nm * np.clip(0.5 - np.asarray(d) / lattice.wall_width_nm, 0.0, 1.0)
    return -z if lattice.pits else z


def broadened_profile(lattice: Lattice, step_nm: Optional[float] = None):
    """``(d, g(d))``: the tip-broadened height against the outline distance on a fine grid,
    ``g(d) = max_rho [z0(d -+ rho) - T(rho)]`` (module docstring), from the feature's centre to
    where the tip no longer reaches it (0 beyond: ``np.interp`` keeps the end values)."""
    wall = lattice.wall_width_nm
    reach = tip_reach(lattice.depth_nm, lattice.tip_radius_nm, lattice.tip_half_angle_deg)
    step = step_nm or min(wall, lattice.tip_radius_nm, lattice.half_width_nm) / 40
    d = np.arange(-lattice.half_width_nm, wall / 2 + reach + 2 * step, step)  # g is flat beyond
    rho = np.arange(0.0, reach + step, step)
    tip = tip_shape(rho, lattice.tip_radius_nm, lattice.tip_half_angle_deg)
    toward = 1.0 if lattice.pits else -1.0  # a pit's tip rises out of it, a pillar's onto it
    g = np.empty_like(d)
    for s in range(0, d.size, 2048):
        dd = d[s : s + 2048, None]
        g[s : s + 2048] = np.max(wall_profile(dd + toward * rho[None, :], lattice) - tip[None, :], axis=1)
    return d, g


def lattice_local(xy, lattice: Lattice):
    """(site indices (..., 2), lattice-frame offsets (..., 2) nm) of the nearest site to stage points."""
    q = (np.asarray(xy) - np.asarray(lattice.offset_nm)) @ lattice.rotation() / lattice.pitch_nm
    m = np.rint(q)
    return m, (q - m) * lattice.pitch_nm


def topography(xy, lattice: Lattice, profile=None) -> np.ndarray:
    """The tip-broadened height (nm) recorded with the tip apex at stage points ``xy`` (..., 2)."""
    d_grid, g = profile if profile is not None else broadened_profile(lattice)
    _, local = lattice_local(xy, lattice)
    return np.interp(outline_distance(local, lattice), d_grid, g)


def lattice_sites(lattice: Lattice, corners) -> tuple:
    """(indices (M, 2), stage positions (M, 2) nm) of the sites within the box of ``corners`` (K, 2)."""
    q = (np.asarray(corners) - np.asarray(lattice.offset_nm)) @ lattice.rotation() / lattice.pitch_nm
    lo, hi = np.floor(q.min(0)) - 1, np.ceil(q.max(0)) + 1
    mn = np.stack(np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1), indexing="ij"), -1)
    mn = mn.reshape(-1, 2)
    xy = np.asarray(lattice.offset_nm) + mn * lattice.pitch_nm @ lattice.rotation().T
    c = np.asarray(corners)
    inside = np.all((xy >= c.min(0)) & (xy <= c.max(0)), axis=1)
    return mn[inside].astype(int), xy[inside]


def site_pixels(tip, sites, iterations: int = 5, pad: int = 4) -> np.ndarray:
    """Where stage points ``sites`` (M, 2) lie in an image whose pixel centres the tip visited at
    ``tip`` (rows, cols, 2) nm: (col, row) per site, sub-pixel (Newton steps on the bilinear
    interpolant of the tip path, extended ``pad`` px linearly beyond the image), NaN for a site
    outside the image."""
    rows, cols = tip.shape[:2]
    sites = np.asarray(sites, float)
    grid = np.pad(tip, ((pad, pad), (pad, pad), (0, 0)), mode="reflect", reflect_type="odd")
    nearest = np.argmin(np.sum((tip.reshape(-1, 2)[None] - sites[:, None]) ** 2, axis=-1), axis=1)
    at = np.stack([nearest % cols, nearest // cols], -1).astype(float)

    def path(points):  # (K, 2) (col, row) -> (K, 2) nm
        coords = [
            np.clip(points[:, 1] + pad, 0, rows + 2 * pad - 1),
            np.clip(points[:, 0] + pad, 0, cols + 2 * pad - 1),
        ]
        return np.stack([ndimage.map_coordinates(grid[..., i], coords, order=1) for i in range(2)], -1)

    for _ in range(iterations):
        (a, c), (b, d) = (
            (path(at + [0.5, 0]) - path(at - [0.5, 0])).T,
            (path(at + [0, 0.5]) - path(at - [0, 0.5])).T,
        )
        r = sites - path(at)  # solve [[a, b], [c, d]] step = r
        det = a * d - b * c
        ok = np.abs(det) > 1e-12
        det = np.where(ok, det, 1.0)
        at = (
            at
            + ok[:, None]
            * np.stack([d * r[:, 0] - b * r[:, 1], a * r[:, 1] - c * r[:, 0]], -1)
            / det[:, None]
        )
    outside = np.any((at < -0.5) | (at > np.array([cols, rows]) - 0.5), axis=1)
    return np.where(outside[:, None], np.nan, at)


# ============================================================================ image artefacts
@dataclasses.dataclass(frozen=True)
class Artefacts:
    """Height artefacts (module docstring): background (stage frame), line offsets, z lag, noise,
    spikes and saturated pixels. ``tilt_direction_deg``: where the plane rises, in the stage."""

    tilt_nm: float = 0.0
    tilt_direction_deg: float = 0.0
    bow_nm: float = 0.0
    line_offset_nm: float = 0.0
    feedback_tau_s: float = 0.0
    noise_nm: float = 0.0
    spikes: int = 0
    saturated: int = 0

    def background(self, xy, size_nm: float) -> np.ndarray:
        """``G . X + kappa |X|^2``: a plane rising ``tilt_nm`` over ``size_nm``, a bow of
        ``bow_nm`` at the corners of a ``size_nm`` square centred on the stage's zero."""
        a = np.deg2rad(self.tilt_direction_deg)
        grad = self.tilt_nm / size_nm * np.array([np.cos(a), np.sin(a)])
        kappa = self.bow_nm / (size_nm**2 / 2)
        return np.asarray(xy) @ grad + kappa * np.sum(np.asarray(xy) ** 2, axis=-1)


def _line_artefacts(z, art: Artefacts, dt: float, rng):
    """The z-feedback lag along the time-ordered samples (:func:`lag_ramp`: the heights linear
    between samples; an edge's first moment moves by exactly tau), then per-line offsets:
    ``z`` (lines, 2, n_line) in time order (trace, retrace). Returns them and the offsets (lines, 2)."""
    if art.feedback_tau_s > 0:
        z = lag_ramp(z.reshape(-1), art.feedback_tau_s, dt).reshape(z.shape)
    shared = rng.normal(0.0, art.line_offset_nm, (z.shape[0], 1, 1))
    own = rng.normal(0.0, art.line_offset_nm / 2, (z.shape[0], 2, 1))
    return z + shared + own, (shared + own)[..., 0]


def _pixel_artefacts(images, art: Artefacts, depth: float, rng):
    """Noise, spikes (+-1-3 depth) and saturated pixels (beyond the ceiling, clipped to it) on the
    (2, lines, pixels) trace and retrace; returns them, the masks and the ceiling."""
    images = images + rng.normal(0.0, art.noise_nm, images.shape)
    ceiling = float(images.max() + 8 * depth)
    spikes = np.zeros(images.shape, bool)
    saturated = np.zeros(images.shape, bool)
    flat_idx = rng.choice(images.size, art.spikes + art.saturated, replace=False)
    for n, f in enumerate(flat_idx):
        where = np.unravel_index(f, images.shape)
        if n < art.spikes:
            images[where] += rng.choice([-1.0, 1.0]) * rng.uniform(1.0, 3.0) * depth
            spikes[where] = True
        else:
            images[where] += rng.uniform(12.0, 20.0) * depth
            saturated[where] = True
    return np.minimum(images, ceiling), spikes, saturated, ceiling


# ============================================================================ one scan
@dataclasses.dataclass
class Scan:
    """One trace/retrace pair: images (lines, pixels) nm, row 0 at the lowest scan-frame y and
    columns along the scan-frame x (the retrace stored in the same column order); ``meta`` what
    the user has; ``truth`` what the code under test must not see."""

    trace: np.ndarray
    retrace: np.ndarray
    meta: dict
    truth: dict


def _apparent_loop_px(tip_trace, tip_retrace, raster: Raster) -> float:
    """Mean over lines of (retrace - trace) tip position along the fast axis at the middle column, px."""
    fast = raster.rotation()[:, 0]
    c = raster.pixels // 2
    return float(np.mean((tip_retrace[:, c] - tip_trace[:, c]) @ fast) / raster.pixel_size[0])


def scan(
    scanner: Scanner,
    lattice: Lattice,
    raster: Raster,
    art: Artefacts,
    sensitivity_nm_per_v: float,
    rng,
    profile=None,
) -> Scan:
    """Scan ``lattice`` with ``scanner`` along ``raster`` (after the initialisation cycle);
    ``profile``: the lattice's :func:`broadened_profile`, if already made."""
    drive = raster_drive(raster, sensitivity_nm_per_v)
    path = scanner_path(scanner, drive.u, drive.h)
    order = np.stack([drive.trace, drive.retrace], axis=1)  # (lines, 2, n_line), time order
    tip = path[order]
    z = topography(tip, lattice, profile) + art.background(tip, raster.size_nm[0])
    z, offsets = _line_artefacts(z, art, raster.dt, rng)
    n_os, cols = raster.overscan_px, slice(raster.overscan_px, raster.overscan_px + raster.pixels)

    def image_order(a):  # (lines, 2, n_line, ...) time order -> trace, retrace in image layout
        a = a[np.argsort(drive.rows)]
        return a[:, 0], a[:, 1, ::-1]

    z_t, z_r = image_order(z)
    images, spikes, saturated, ceiling = _pixel_artefacts(
        np.stack([z_t[:, cols], z_r[:, cols]]), art, lattice.depth_nm, rng
    )
    tip_t, tip_r = image_order(tip)
    t_t, t_r = image_order(order * drive.h)
    truth = {
        "tip_trace_nm": tip_t[:, cols],
        "tip_retrace_nm": tip_r[:, cols],
        "t_trace_s": t_t[:, cols],
        "t_retrace_s": t_r[:, cols],
        "tip_trace_full_nm": tip_t,  # with the overscan columns, in column order
        "tip_retrace_full_nm": tip_r,
        "nominal_x_full_nm": drive.nominal,
        "raster_start_s": drive.raster_start * drive.h,
        "line_offsets_nm": offsets[np.argsort(drive.rows)],  # (rows, [trace, retrace])
        "spikes": spikes,
        "saturated": saturated,
        "ceiling_nm": ceiling,
        "apparent_loop_px": _apparent_loop_px(tip_t[:, cols], tip_r[:, cols], raster),
        "overscan_px": n_os,
    }
    return Scan(images[0], images[1], raster.meta(), truth)


# ============================================================================ cases
def _draw(rng, value, low, high, signed: bool = False) -> float:
    """``value`` if given, else U(low, high) (with a random sign if ``signed``)."""
    if value is not None:
        return float(value)
    v = rng.uniform(low, high)
    return float(v * rng.choice([-1.0, 1.0])) if signed else float(v)


def make_scanner(
    rng,
    nominal_nm_per_v: float,
    loop_pct=None,
    tau_s=None,
    creep_per_decade=None,
    coupling=None,
    drift_nm_per_s=None,
    bow_per_nm=0.0,
    u_max: float = U_MAX_V,
    drift_range=(0.2, 1.0),
) -> Scanner:
    """Draw a scanner: per axis a Preisach plane (``a_up, a_dn`` 0.1-0.2 u_max, spreads 0.4-0.55
    u_max with an asymmetry of 10-30 %), gain nominal x U(0.9, 1.1), loop 5-15 %; tau 0.5-2 ms,
    creep 1-2 %/decade, coupling 0.5-2 % (each sign), drift in ``drift_range`` nm/s (random
    direction). A given magnitude (a number; 0 switches the effect off) replaces the draw."""
    axes = []
    pct = _draw(rng, loop_pct, 5.0, 15.0)
    for _ in range(2):
        spread, asym = rng.uniform(0.4, 0.55) * u_max, rng.uniform(0.1, 0.3) * rng.choice([-1, 1])
        relays = relay_plane(
            rng.uniform(0.1, 0.2) * u_max,
            spread * (1 + asym),
            -rng.uniform(0.1, 0.2) * u_max,
            spread * (1 - asym),
            seed=int(rng.integers(2**31)),
        )
        axes.append(make_axis(relays, nominal_nm_per_v * rng.uniform(0.9, 1.1), pct, u_max))
    speed = _draw(rng, drift_nm_per_s, *drift_range)
    heading = rng.uniform(0, 2 * np.pi)
    kappa = (
        (_draw(rng, None, 0.005, 0.02, True), _draw(rng, None, 0.005, 0.02, True))
        if coupling is None
        else tuple(np.broadcast_to(np.asarray(coupling, float), (2,)))
    )
    return Scanner(
        tuple(axes),
        tau_s=_draw(rng, tau_s, 0.5e-3, 2e-3),
        creep_per_decade=_draw(rng, creep_per_decade, 0.01, 0.02),
        coupling=tuple(float(k) for k in kappa),
        bow_per_nm=tuple(float(b) for b in np.broadcast_to(np.asarray(bow_per_nm, float), (2,))),
        drift_nm_per_s=(speed * np.cos(heading), speed * np.sin(heading)),
    )


def make_lattice(rng, kind: str, feature: str, few_features: bool = False) -> Lattice:
    """Draw a lattice of ``kind`` (:data:`KINDS`): turned by U(-5, 5) degrees, a random phase, depth
    x U(0.9, 1.1), walls in the kind's range; ``few_features``: turned by U(-1, 1) degrees with a
    site near the image centre (a 3 x 3 lattice in an image 3 pitches wide)."""
    k = KINDS[kind]
    pitch = k["pitch_nm"]
    angle = rng.uniform(-1.0, 1.0) if few_features else rng.uniform(-5.0, 5.0)
    phase = rng.uniform(-0.03, 0.03, 2) if few_features else rng.uniform(-0.5, 0.5, 2)
    return Lattice(
        pitch_nm=pitch,
        angle_deg=float(angle),
        offset_nm=tuple(float(v) for v in rotation(angle) @ (phase * pitch)),
        shape="square" if feature.startswith("square") else "round",
        pits=feature.endswith("pits"),
        half_width_nm=k["half_width_nm"][feature],
        corner_radius_nm=k["corner_radius_nm"],
        depth_nm=float(k["depth_nm"] * rng.uniform(0.9, 1.1)),
        wall_angle_deg=float(rng.uniform(*k["wall_angle_deg"])),
        tip_radius_nm=k["tip_radius_nm"],
    )


def make_artefacts(rng, kind: str, depth: float, on: bool = True) -> Artefacts:
    """Tilt 0.3-0.8 depth over the image, bow 0.1-0.4 depth (either sign), the kind's line offsets
    and noise, 3 spikes, 2 saturated pixels; no z lag. ``on=False``: none."""
    if not on:
        return Artefacts()
    k = KINDS[kind]
    return Artefacts(
        tilt_nm=float(rng.uniform(0.3, 0.8) * depth),
        tilt_direction_deg=float(rng.uniform(0, 360)),
        bow_nm=float(rng.uniform(0.1, 0.4) * depth * rng.choice([-1, 1])),
        line_offset_nm=k["line_offset_nm"],
        noise_nm=k["noise_nm"],
        spikes=3,
        saturated=2,
    )


_WHY = {
    "one_speed": "one line rate at one angle: rate dependence cannot be told from hysteresis, nor the "
    "slow axis' loop from the fast one's",
    "few_features": "a 3 x 3 lattice at one speed: fewer features than the scanner model has parameters",
}


def draw_case(
    seed: int,
    kind: str = "coarse",
    *,
    feature: Optional[str] = None,
    line_rates_hz=LINE_RATES_HZ,
    angles_deg=ANGLES_DEG,
    pixels: Optional[int] = None,
    size_nm: Optional[float] = None,
    overscan: float = 0.05,
    direction: str = "up",
    magnitudes: Optional[dict] = None,
    artefacts=True,
    unidentifiable: Optional[str] = None,
    few_features: bool = False,
) -> dict:
    """One case: a scanner and a lattice drawn from ``seed``, scanned at every angle and line rate.

    Arguments:
        seed: the draw.
        kind: "coarse" (10 um pitch, 50 um image) or "fine" (1 um pitch, 5 um): :data:`KINDS`.
        feature: one of :data:`FEATURES`; default drawn from the seed.
        line_rates_hz, angles_deg: one scan per (angle, rate), angle-major.
        pixels, size_nm: pixels (= lines) per image and its width nm; default the kind's.
        overscan, direction: the raster's (:class:`Raster`).
        magnitudes: keyword arguments of :func:`make_scanner` (``loop_pct``, ``tau_s``,
            ``creep_per_decade``, ``coupling``, ``drift_nm_per_s``, ``bow_per_nm``): a number
            fixes the effect, 0 switches it off, absent draws it.
        artefacts: True (drawn, :func:`make_artefacts`), False (none) or an :class:`Artefacts`.
        unidentifiable: "one_speed" (one scan: 1 Hz, 0 degrees) or "few_features" (an image 3
            pitches wide, a 3 x 3 lattice, one scan): :data:`UNIDENTIFIABLE`.
        few_features: the 3 x 3 lattice at every angle and line rate given.

    Returns:
        ``{"scans", "meta", "truth", "scanner", "lattice"}``: the :class:`Scan` list; ``meta`` what
        a user knows (nominal pitch, pits or pillars, the nominal sensitivity, the drive range and
        initialisation cycle); ``truth`` the scanner (:meth:`Scanner.truth`), the lattice, the sites
        the scans reach (``site_index``, ``sites_nm`` in the stage frame; each scan's truth adds
        ``sites_px_trace``/``sites_px_retrace``, where they lie in its images, NaN outside), the
        artefacts, and ``unidentifiable``: why the case cannot be identified, or None; the drawn
        :class:`Scanner` and :class:`Lattice`.

    Raises:
        ValueError: an unknown kind, feature or ``unidentifiable``.
    """
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {list(KINDS)}, got {kind!r}")
    if unidentifiable not in (None, *UNIDENTIFIABLE):
        raise ValueError(f"unidentifiable must be None or one of {UNIDENTIFIABLE}, got {unidentifiable!r}")
    rng = [np.random.default_rng([seed, k]) for k in range(4)]
    feature = feature or FEATURES[int(rng[0].integers(len(FEATURES)))]
    if feature not in FEATURES:
        raise ValueError(f"feature must be one of {FEATURES}, got {feature!r}")
    k = KINDS[kind]
    few_features = few_features or unidentifiable == "few_features"
    size = size_nm or (3 * k["pitch_nm"] if few_features else k["size_nm"])
    n_px = pixels or k["pixels"]
    if unidentifiable is not None:
        line_rates_hz, angles_deg = (1.0,), (0.0,)
    travel = size * (1 + 2 * round(overscan * n_px) / n_px)
    sensitivity = travel / 2 / (DRIVE_FRACTION * U_MAX_V)
    scanner = make_scanner(rng[1], sensitivity, drift_range=k["drift_nm_per_s"], **(magnitudes or {}))
    lattice = make_lattice(rng[2], kind, feature, few_features)
    art = (
        artefacts
        if isinstance(artefacts, Artefacts)
        else make_artefacts(rng[3], kind, lattice.depth_nm, artefacts)
    )
    rasters = [
        Raster((size, size), n_px, n_px, float(f), float(a), overscan, direction)
        for a in angles_deg
        for f in line_rates_hz
    ]
    profile = broadened_profile(lattice)
    scans = [
        scan(scanner, lattice, r, art, sensitivity, np.random.default_rng([seed, 100 + i]), profile)
        for i, r in enumerate(rasters)
    ]
    reached = np.concatenate(
        [np.stack([s.truth["tip_trace_nm"], s.truth["tip_retrace_nm"]]).reshape(-1, 2) for s in scans]
    )
    index, sites = lattice_sites(lattice, reached)
    for s in scans:
        s.truth["sites_px_trace"] = site_pixels(s.truth["tip_trace_nm"], sites)
        s.truth["sites_px_retrace"] = site_pixels(s.truth["tip_retrace_nm"], sites)
    meta = {
        "kind": kind,
        "feature": feature,
        "pitch_nm": lattice.pitch_nm,
        "pits": lattice.pits,
        "sensitivity_nm_per_v": [sensitivity, sensitivity],
        "u_max_v": U_MAX_V,
        "history_v": [[-U_MAX_V, -U_MAX_V], [U_MAX_V, U_MAX_V]],
        "init_cycle_s": {"leg": INIT_LEG_S, "hold": INIT_HOLD_S},
    }
    truth = {
        "seed": seed,
        "scanner": scanner.truth(),
        "lattice": lattice.truth(),
        "site_index": index,
        "sites_nm": sites,
        "artefacts": dataclasses.asdict(art),
        "unidentifiable": _WHY.get(unidentifiable),
    }
    return {"scans": scans, "meta": meta, "truth": truth, "scanner": scanner, "lattice": lattice}


# ============================================================================ files, figures
def flatten(z, mask=None, iterations: int = 6, cut: float = 3.0) -> np.ndarray:
    """``z`` less a robust least-squares fit of ``1, x, y, x^2, xy, y^2`` (image coordinates):
    refitted on the pixels within ``cut`` robust standard deviations of the last fit (the level
    between the features), starting from ``mask`` (True: use) or every pixel."""
    rows, cols = np.indices(z.shape)
    x, y = cols / z.shape[1] - 0.5, rows / z.shape[0] - 0.5
    basis = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], -1).reshape(-1, 6)
    use = np.ones(z.size, bool) if mask is None else np.asarray(mask).ravel()
    flat = z.ravel()
    for _ in range(iterations):
        coef = np.linalg.lstsq(basis[use], flat[use], rcond=None)[0]
        r = flat - basis @ coef
        sigma = 1.4826 * np.median(np.abs(r[use] - np.median(r[use])))
        use = np.abs(r - np.median(r[use])) <= cut * max(sigma, 1e-12)
    return (flat - basis @ coef).reshape(z.shape)


def _jsonable(v):
    if isinstance(v, dict):
        return {k: _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, np.generic):
        return v.item()
    return v


def _write_npz_image(path: Path, z, s: Scan, direction: str) -> None:
    """A jaxafm-image ``.npz``: ``z`` (nm) and ``meta_json`` (pixel size, origin, meta)."""
    (w, h), (dx, dy) = (
        s.meta["size_nm"],
        (s.meta["size_nm"][0] / s.meta["pixels"], s.meta["size_nm"][1] / s.meta["lines"]),
    )
    doc = {
        "format": "jaxafm-image",
        "version": 1,
        "pixel_size_nm": [dx, dy],
        "origin_nm": [-w / 2 + dx / 2, -h / 2 + dy / 2],
        "meta": {"source": path.name, "direction": direction, **s.meta},
    }
    np.savez_compressed(path, z=np.asarray(z, float), meta_json=np.asarray(json.dumps(_jsonable(doc))))


def _write_image(folder: Path, stem: str, s: Scan, direction: str, fmt: str):
    """Write one image; returns its path and its entry in the calibrate ``data.scans`` list."""
    z = getattr(s, direction)
    if fmt == "npz":
        path = folder / f"{stem}_{direction}.npz"
        _write_npz_image(path, z, s, direction)
        return path, path.name
    import tifffile

    path = folder / f"{stem}_{direction}.tif"
    tifffile.imwrite(path, np.asarray(z, np.float32))
    given = {"size_nm": s.meta["size_nm"], "z_unit": "nm", "line_rate_hz": s.meta["line_rate_hz"]}
    return path, {"path": path.name, **given, "fast_axis": "x", "first_row": "bottom", "direction": direction}


def write_case(case: dict, folder, fmt: str = "npz", truth: bool = True) -> dict:
    """Write a case as a user would give it to jaxafm.

    Per scan ``scanN_<angle>deg_<rate>hz_{trace,retrace}.npz`` (the jaxafm image format: heights
    nm, pixel size, origin, direction, line rate) or ``.tif`` (float32 nm, row 0 the bottom line,
    lines along rows; needs tifffile); ``data.json``: the calibrate ``data`` and ``grating``
    sections (JSON is YAML) and the case's ``meta``; with ``truth``, ``truth.json`` (parameters,
    sites) and ``truth.npz`` (per scan ``scanN_<key>``: the true tip path and time of every pixel,
    the sites in pixels, the spike and saturation masks).

    Returns:
        ``{"data": path, "images": [(trace, retrace), ...], "truth": path or None}``.

    Raises:
        ValueError: ``fmt`` neither "npz" nor "tiff".
    """
    if fmt not in ("npz", "tiff"):
        raise ValueError(f"fmt must be 'npz' or 'tiff', got {fmt!r}")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    entries, images, arrays = [], [], {}
    for i, s in enumerate(case["scans"]):
        stem = f"scan{i}_{s.meta['angle_deg']:g}deg_{s.meta['line_rate_hz']:g}hz"
        (trace, t_entry), (retrace, r_entry) = (
            _write_image(folder, stem, s, d, fmt) for d in ("trace", "retrace")
        )
        images.append((trace, retrace))
        how = {k: s.meta[k] for k in ("line_rate_hz", "angle_deg", "overscan")}
        entries.append({"trace": t_entry, "retrace": r_entry, **how, "lines": s.meta["scan_direction"]})
        arrays |= {f"scan{i}_{k}": v for k, v in s.truth.items() if isinstance(v, np.ndarray)}
    m = case["meta"]
    data = {"scans": entries} | {k: m[k] for k in ("sensitivity_nm_per_v", "u_max_v", "history_v")}
    grating = {"pitch_nm": m["pitch_nm"], "pits": m["pits"], "rotation_deg": "fit"}
    (folder / "data.json").write_text(
        json.dumps(_jsonable({"data": data, "grating": grating, "meta": m}), indent=1)
    )
    truth_path = None
    if truth:
        truth_path = folder / "truth.json"
        scans = [{k: v for k, v in s.truth.items() if not isinstance(v, np.ndarray)} for s in case["scans"]]
        truth_path.write_text(json.dumps(_jsonable(case["truth"] | {"scans": scans}), indent=1))
        np.savez_compressed(folder / "truth.npz", **arrays)
    return {"data": folder / "data.json", "images": images, "truth": truth_path}


def render_case(case: dict, path, scans=None, row: Optional[int] = None) -> Path:
    """A PNG of the chosen scans (default all): per scan the raw trace, the flattened trace and
    retrace (:func:`flatten`; colour range 1-99 %), and one line of both, raw."""
    from matplotlib.figure import Figure

    chosen = range(len(case["scans"])) if scans is None else scans
    fig = Figure(figsize=(16, 3.6 * len(chosen)), layout="constrained")
    for r, i in enumerate(chosen):
        s = case["scans"][i]
        (w, h), line = s.meta["size_nm"], s.meta["lines"] // 2 if row is None else row
        extent = (-w / 2e3, w / 2e3, -h / 2e3, h / 2e3)
        title = f"{s.meta['angle_deg']:g} deg, {s.meta['line_rate_hz']:g} Hz"
        for c, (z, label) in enumerate(
            [
                (s.trace, "trace raw"),
                (flatten(s.trace), "trace flattened"),
                (flatten(s.retrace), "retrace flattened"),
            ]
        ):
            ax = fig.add_subplot(len(chosen), 4, 4 * r + c + 1)
            lo, hi = np.percentile(z, [1, 99])
            ax.imshow(z, origin="lower", cmap="afmhot", extent=extent, vmin=lo, vmax=hi)
            ax.set_title(f"{title}: {label}", fontsize=9)
            ax.set_xlabel("scan x [um]", fontsize=8)
        ax = fig.add_subplot(len(chosen), 4, 4 * r + 4)
        x = (np.arange(s.meta["pixels"]) + 0.5) * w / s.meta["pixels"] / 1e3 - w / 2e3
        ax.plot(x, s.trace[line], lw=0.8, label="trace")
        ax.plot(x, s.retrace[line], lw=0.8, label="retrace")
        ax.set_ylim(*np.percentile(np.r_[s.trace[line], s.retrace[line]], [0.5, 99.5]) + np.array([-30, 30]))
        ax.set_title(f"row {line}, raw; apparent loop {s.truth['apparent_loop_px']:.2f} px", fontsize=9)
        ax.set_xlabel("scan x [um]", fontsize=8)
        ax.set_ylabel("z [nm]", fontsize=8)
        ax.legend(fontsize=7)
    t = case["truth"]["scanner"]
    fig.suptitle(
        f"{case['meta']['kind']} {case['meta']['feature']}, seed {case['truth']['seed']}: loop "
        f"{t['axes'][0]['loop_pct']:.1f} %, tau {1e3 * t['rate_tau_s']:.2f} ms, creep "
        f"{100 * t['creep_per_decade']:.2f} %/decade, coupling {t['coupling_xy_yx'][0]:+.3f} "
        f"{t['coupling_xy_yx'][1]:+.3f}, drift {np.hypot(*t['drift_nm_per_s']):.2f} nm/s"
    )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=70)
    return path


if __name__ == "__main__":
    out = Path("/tmp/lattice_gen")
    coarse = draw_case(0, "coarse", feature="square_pits")
    render_case(coarse, out / "coarse_square_pits_slow_fast.png", scans=[0, 3, 4, 7])
    pillars = draw_case(1, "coarse", feature="round_pillars", line_rates_hz=(0.5, 4.0))
    render_case(pillars, out / "coarse_round_pillars.png")
    fine = draw_case(2, "fine", feature="round_pits", line_rates_hz=(1.0, 4.0))
    render_case(fine, out / "fine_round_pits.png")
    few = draw_case(3, "coarse", feature="square_pits", unidentifiable="few_features")
    render_case(few, out / "few_features.png")
    print("written to", out)
