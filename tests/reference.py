"""Straightforward NumPy reference implementations: a relay grid, play loops, a whole scan.

A Python loop over time, NumPy over hysterons: the obvious way to write these
models. They are the baselines of the speed benchmarks and an independent
cross-check of the JAX operators in the tests.
"""

from __future__ import annotations

import numpy as np


def preisach_relay_grid(u, density, u_min, u_max, history=None):
    """Relay-grid Preisach model: every relay ``(alpha_i, beta_j)`` updated at every sample.

    Same plane and relay positions as :class:`jaxafm.Preisach` with
    ``smooth=False``; relays start from the state the plays' ``history`` gives.
    """
    density = np.asarray(density, dtype=float)
    n = density.shape[0]
    step = (u_max - u_min) / n
    centres = u_min + (np.arange(n) + 0.5) * step
    ii, jj = np.tril_indices(n)
    alpha, beta, mu = centres[ii], centres[jj], density[ii, jj]
    history = [u[0]] if history is None else list(history)
    # start: relay up iff it sits below history[0], i.e. s = (alpha+beta)/2 <= history[0]
    state = np.where((alpha + beta) / 2 <= history[0], 1.0, -1.0)
    for h in history[1:]:
        state = _relay_update(state, h, alpha, beta)
    out = np.empty(len(u))
    for t, ut in enumerate(u):
        state = _relay_update(state, ut, alpha, beta)
        out[t] = mu @ state
    return out


def _relay_update(state, ut, alpha, beta):
    state = np.where(ut >= alpha, 1.0, state)
    return np.where(ut <= beta, -1.0, state)


def preisach_spread_relays(u, density, u_min, u_max, m):
    """The smoothed Preisach plane (``smooth=True``) by its definition, as bare relays.

    Relay ``(alpha_i, beta_j)`` with weight ``mu`` spread evenly over ``+-D/2`` along
    its play line (``alpha - beta`` fixed) is approximated by ``m`` relays
    ``(alpha_i + delta, beta_j + delta)``, ``delta = ((l + 1/2) / m - 1/2) D``, each
    ``mu / m``. Virgin start at ``u[0]``: a relay is up iff ``(alpha + beta) / 2 <= u[0]``.
    The midpoint rule misses each line's partly-up relay by at most ``1 / (2 m)`` of its
    weight: ``|difference| <= sum_k max_j M[k, j] / m`` (``M[k, j] = density[j + k, j]``).
    """
    density = np.asarray(density, dtype=float)
    n = density.shape[0]
    D = (u_max - u_min) / n
    centres = u_min + (np.arange(n) + 0.5) * D
    ii, jj = np.tril_indices(n)
    delta = ((np.arange(m) + 0.5) / m - 0.5) * D
    alpha = (centres[ii][:, None] + delta).ravel()
    beta = (centres[jj][:, None] + delta).ravel()
    mu = np.repeat(density[ii, jj] / m, m)
    state = np.where((alpha + beta) / 2 <= u[0], 1.0, -1.0)
    out = np.empty(len(u))
    for t, ut in enumerate(u):
        state[ut >= alpha] = 1.0
        state[ut <= beta] = -1.0
        out[t] = mu @ state
    return out


def pi_loop(u, thresholds, weights, offset=0.0):
    """PI operator with a Python loop over time and NumPy over the plays (start at ``u[0]``)."""
    r = np.asarray(thresholds, dtype=float)
    p = np.full(r.shape, u[0], dtype=float)
    out = np.empty(len(u))
    for t, ut in enumerate(u):
        p = np.minimum(np.maximum(p, ut - r), ut + r)
        out[t] = offset + p @ weights
    return out


def play_loop(u, thresholds):
    """The play outputs (T, n): ``p_t = min(max(p_{t-1}, u_t - r), u_t + r)``, ``p_{-1} = u[0]``,
    one Python step per sample: the design matrix of a PI operator, ``y = offset + P @ w``."""
    r = np.asarray(thresholds, dtype=float)
    p = np.full(r.shape, u[0], dtype=float)
    out = np.empty((len(u), r.size))
    for t, ut in enumerate(u):
        p = np.minimum(np.maximum(p, ut - r), ut + r)
        out[t] = p
    return out


# --- the whole instrument, one sample at a time -------------------------------------------------


def _np(x):
    return np.asarray(x, dtype=float)


def numpy_height(sample):
    """A NumPy ``height(xy)`` for points ``(..., 2)`` nm of a jaxafm ``Grating`` or ``Plane``."""
    from jaxafm.instrument.samples import Grating, Plane

    if isinstance(sample, Plane):
        z0, slope = _np(sample.z0), _np(sample.slope)
        return lambda xy: z0 + xy @ slope
    if not isinstance(sample, Grating):
        raise NotImplementedError(f"no NumPy height for {type(sample).__name__}: give a height function")
    pitch, depth, duty, edge, angle, phase = (
        _np(getattr(sample, f)) for f in ("pitch", "depth", "duty", "edge_width", "angle", "phase")
    )
    c, s = np.cos(angle), np.sin(angle)

    def height(xy):
        across = c * xy[..., 0] + s * xy[..., 1]
        d = np.abs(np.mod(across - phase + pitch / 2, pitch) - pitch / 2)
        return depth * np.clip((duty * pitch / 2 - d) / edge + 0.5, 0.0, 1.0)

    return height


def numpy_grating_image(sample, tip):
    """A NumPy ``image(p)`` for a point ``(2,)`` nm: the exact tip image of a jaxafm ``Grating``
    (``Grating.imaged``), written again from its description: the best of the nearer top corner,
    the top plateau and the tangent contact of the apex sphere inside a wall, over the nearest
    line and its neighbours."""
    pitch, depth, duty, w, angle, phase = (
        _np(getattr(sample, f)) for f in ("pitch", "depth", "duty", "edge_width", "angle", "phase")
    )
    radius, theta = _np(tip.radius), _np(tip.half_angle)
    if depth < 0:  # grooves: lines of |depth| in between, lowered by |depth|
        duty, phase, low, depth = 1 - duty, phase + pitch / 2, depth, -depth
    else:
        low = 0.0
    foot, top = duty * pitch / 2 + w / 2, max(duty * pitch / 2 - w / 2, 0.0)
    peak, m = depth * min(max(foot / w, 0.0), 1.0), depth / w
    r_star, lift = radius * m / np.sqrt(1 + m**2), radius * (np.sqrt(1 + m**2) - 1)
    rt = radius * np.cos(theta)

    def profile(r):  # Tip.profile: the apex sphere up to rt, then the cone
        return radius - np.sqrt(max(radius**2 - min(r, rt) ** 2, 1e-12)) + max(r - rt, 0.0) / np.tan(theta)

    def image(p):
        u = np.cos(angle) * p[0] + np.sin(angle) * p[1]
        k = np.round((u - phase) / pitch)
        best = 0.0
        for j in (k - 1, k, k + 1):
            s = abs(u - phase - j * pitch)
            best = max(best, peak - profile(abs(s - top)))
            if s <= top:
                best = max(best, peak)
            if top <= s - r_star <= min(foot, pitch / 2) and m * np.tan(theta) <= 1:
                best = max(best, depth * (foot - s) / w + lift)
        return best + low

    return image


def _axis_numpy(axis):
    """One axis's parameters as NumPy: play radii, PI weights and offset, dead zone, lags."""
    from jaxafm.model.hysteresis import GeneralizedPI, PrandtlIshlinskii

    h, dz = axis.hysteresis, None
    if isinstance(h, GeneralizedPI):
        h, dz = h.pi, h.deadzone
    if not isinstance(h, PrandtlIshlinskii):
        raise NotImplementedError(f"the NumPy scan covers PI and generalised PI axes, not {type(h).__name__}")
    p = {
        "r": _np(h.thresholds),
        "w": _np(h.weights),
        "offset": _np(h.offset),
        "dz": None,
        "rate_tau": None if axis.rate_dependence is None else _np(axis.rate_dependence.tau),
        "creep_taus": None if axis.creep is None else _np(axis.creep.taus),
        "creep_w": None if axis.creep is None else _np(axis.creep.weights),
    }
    if dz is not None:
        p["dz"] = tuple(
            _np(getattr(dz, f))
            for f in ("centre", "slope", "upper", "upper_weights", "lower", "lower_weights")
        )
    return p


def _readout(a, plays):
    """PI output of the plays, then the dead-zone superposition if the axis has one (nm)."""
    y = a["offset"] + plays @ a["w"]
    if a["dz"] is None:
        return y
    c, g0, up, up_w, lo, lo_w = a["dz"]
    x = y - c
    return c + g0 * x + np.maximum(x - up, 0.0) @ up_w - np.maximum(lo - x, 0.0) @ lo_w


def drive_numpy(
    afm,
    height,
    u,
    t,
    drift_normals=None,
    noise_normals=None,
    u0=(0.0, 0.0),
    t0=0.0,
    history=None,
    z0=0.0,
    probe=None,
):
    """The true tip path and the recorded height of the drive ``u`` (T, 2) V at times ``t`` (T,) s.

    A naive instrument simulation: a Python loop over samples, NumPy inside a
    sample. The AFM starts as ``afm.initial_state(u0, t0, history)`` (at rest at
    ``u0`` V at ``t0`` s after the drive ``history`` (H, 2) V; the feedback at
    ``z0`` nm), so ``drive_numpy(afm, ...)`` is ``afm.drive(sample, u, t, state, key)``
    of :mod:`jaxafm.instrument.afm` from that state. Per sample and axis: plays, PI and
    dead-zone readout, the rate-dependence lag, the creep lags (from the rest
    level); then coupling, bow, drift (velocity plus the exact Ornstein-Uhlenbeck
    step driven by ``drift_normals`` (T, 2)), noise (``std * noise_normals``
    (T, 2)), the probe height ``probe(p)`` (default ``max_q height(p + q) - lift_q`` over
    ``afm.tip.stencil()``, e.g. :func:`numpy_grating_image` for a grating), or ``height(p)``
    when ``afm.dilate`` is off, and the
    feedback lag. The lags hold each input over ``(t[n-1], t[n]]``, as
    :func:`jaxafm.model.effects.lowpass` does. ``height`` is a NumPy function of points
    (..., 2) nm, e.g. :func:`numpy_height` of the sample. The normals must be
    the draws the JAX scanner makes (see :func:`raster_normals`) for the results to agree.
    Returns ``path`` (T, 2) nm and ``recorded`` (T,) nm.
    """
    sc = afm.scanner
    u, t = _np(u), _np(t)
    axes = [_axis_numpy(sc.x), _axis_numpy(sc.y)]
    xy_c = None if sc.coupling is None else (_np(sc.coupling.xy), _np(sc.coupling.yx))
    bow = None if sc.bow is None else (_np(sc.bow.bx), _np(sc.bow.by))
    drift = sc.drift is not None
    if drift:
        vel, sigma, theta = (
            _np(sc.drift.velocity),
            _np(sc.drift.sigma),
            np.maximum(_np(sc.drift.theta), 1e-12),
        )
    noise_std = None if sc.noise is None else _np(sc.noise.std)
    q, lift = (_np(a) for a in afm.tip.stencil())
    if not afm.dilate:
        probe = height
    elif probe is None:
        probe = lambda p: np.max(height(p + q) - lift)
    fb_tau = None if afm.feedback is None else _np(afm.feedback.tau)

    # the state afm.initial_state(u0, t0, history) builds
    u0 = _np(u0)
    hist = np.reshape(u0, (1, 2)) if history is None else _np(history)
    plays, lag, creep, rest = [], [], [], []
    for k, a in enumerate(axes):
        p = np.full(a["r"].shape, hist[0, k])
        for h in hist[1:, k]:
            p = np.minimum(np.maximum(p, h - a["r"]), h + a["r"])
        plays.append(p)
        v0 = _readout(a, np.minimum(np.maximum(p, u0[k] - a["r"]), u0[k] + a["r"]))
        lag.append(v0)
        creep.append(np.full(np.shape(a["creep_taus"]), v0))
        rest.append(v0)
    wander, z, t_prev = np.zeros(2), float(z0), float(t0)

    path, recorded = np.empty((len(t), 2)), np.empty(len(t))
    for n in range(len(t)):
        dt = t[n] - t_prev
        t_prev = t[n]
        p = np.empty(2)
        for k, a in enumerate(axes):
            plays[k] = np.minimum(np.maximum(plays[k], u[n, k] - a["r"]), u[n, k] + a["r"])
            v = _readout(a, plays[k])
            if a["rate_tau"] is not None:
                e = np.exp(-dt / a["rate_tau"])
                lag[k] = e * lag[k] + (1 - e) * v
                v = lag[k]
            if a["creep_taus"] is not None:
                e = np.exp(-dt / a["creep_taus"])
                creep[k] = e * creep[k] + (1 - e) * v
                v = v + (creep[k] - rest[k]) @ a["creep_w"]
            p[k] = v
        if xy_c is not None:
            p = np.array([p[0] + xy_c[0] * p[1], p[1] + xy_c[1] * p[0]])
        if bow is not None:
            p = np.array([p[0] + bow[0] * p[1] ** 2, p[1] + bow[1] * p[0] ** 2])
        if drift:
            std = sigma * np.sqrt(-np.expm1(-2 * theta * dt) / (2 * theta))
            wander = np.exp(-theta * dt) * wander + std * drift_normals[n]
            p = p + vel * (t[n] - t0) + wander
        if noise_std is not None:
            p = p + noise_std * noise_normals[n]
        surf = probe(p)
        if fb_tau is not None:
            e = np.exp(-dt / fb_tau)
            surf = z = e * z + (1 - e) * surf
        path[n], recorded[n] = p, surf
    return path, recorded


def raster_drive(afm, raster, u0=(0.0, 0.0), t0=0.0, move_time=0.1, move_samples=32):
    """The drive (T, 2) V and times (T,) s of ``jaxafm.instrument.afm.raster_scan`` from rest at ``u0``, ``t0``:
    the ``move`` ramp to the first point (``move_samples`` samples), then the raster, nominal volts."""
    wanted = raster.wanted()
    L, _, n, _ = wanted.shape
    u_scan = wanted.reshape(-1, 2) / _np(afm.sensitivity)
    u0 = _np(u0)
    u_move = u0 + np.arange(1, move_samples + 1)[:, None] / move_samples * (u_scan[0] - u0)
    t_move = t0 + move_time / move_samples * np.arange(1, move_samples + 1)
    t_scan = t_move[-1] + raster.sample_time * np.arange(1, L * 2 * n + 1)
    return np.concatenate([u_move, u_scan]), np.concatenate([t_move, t_scan])


def raster_normals(key, raster, move_samples=32):
    """The standard normals ``(drift, noise)``, each (T, 2), that ``raster_scan(..., key=key)`` draws
    for the move and then the scan, in the order of :func:`raster_drive`."""
    import jax

    T_scan = raster.lines * 2 * (raster.pixels + 2 * raster.margin)
    drift, noise = [], []
    for k, T in zip(jax.random.split(key), (move_samples, T_scan)):
        k_drift, k_noise = jax.random.split(k)
        drift.append(np.asarray(jax.random.normal(k_drift, (T, 2))))
        noise.append(np.asarray(jax.random.normal(k_noise, (T, 2))))
    return np.concatenate(drift), np.concatenate(noise)


def raster_scan_numpy(
    afm,
    height,
    raster,
    drift_normals=None,
    noise_normals=None,
    u0=(0.0, 0.0),
    t0=0.0,
    history=None,
    move_time=0.1,
    move_samples=32,
    lines=None,
    probe=None,
):
    """:func:`drive_numpy` over :func:`raster_drive`: the NumPy counterpart of ``raster_scan``
    from ``afm.initial_state(u0, t0, history)`` with nominal volts.

    Returns ``trace``, ``retrace`` (lines, pixels) nm, ``path_trace``, ``path_retrace``
    (lines, pixels, 2) nm, and the whole drive's ``path`` (T, 2), ``recorded`` (T,)
    and ``t`` (T,). ``lines`` runs only the move and the first ``lines`` lines
    (a prefix of the same scan, e.g. for timing); ``probe`` as for :func:`drive_numpy`.
    """
    u, t = raster_drive(afm, raster, u0, t0, move_time, move_samples)
    L, n = raster.lines if lines is None else lines, 2 * (raster.pixels + 2 * raster.margin)
    T = move_samples + L * n
    cut = lambda a: None if a is None else a[:T]
    path, rec = drive_numpy(
        afm, height, u[:T], t[:T], cut(drift_normals), cut(noise_normals), u0, t0, history, probe=probe
    )
    out = {"path": path, "recorded": rec, "t": t[:T]}
    P, m = raster.pixels, raster.margin
    for i, name in enumerate(("trace", "retrace")):
        for key, a in ((name, rec[move_samples:]), (f"path_{name}", path[move_samples:])):
            img = a.reshape((L, 2, n // 2) + a.shape[1:])[:, i, m : m + P]
            img = img[:, ::-1] if i == 1 else img
            out[key] = img[::-1] if raster.direction == "down" else img
    return out
