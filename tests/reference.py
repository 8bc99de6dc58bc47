"""Straightforward NumPy reference implementations: a relay grid, play loops, a whole scan.

A Python loop over time, NumPy over hysterons: the obvious way to write these
models. They are the baselines of the speed benchmarks and an independent
cross-check of the JAX operators in the tests.

Two kinds of baseline. The first ones written (``preisach_relay_grid``, ``pi_loop``,
``drive_numpy`` / ``raster_scan_numpy``) do everything inside the loop over samples,
the relay grid even O(n^2) relays per sample. The fair ones use the algorithm jaxafm
uses and loop only over what is sequential: ``preisach_play_loop`` runs the n plays of
Krejci's representation in the loop and reads the output out of all of them at once;
``drive_numpy_vectorised`` (``raster_scan_numpy(..., vectorised=True)``) loops over
samples only for the plays, the first-order lags (rate dependence, creep, feedback) and
the drift's wander, and runs the readout, coupling, bow, noise and the probe over a block
of ``BLOCK`` samples at once.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

BLOCK = 4096  # samples the vectorised baselines handle at once: their temporaries stay in cache


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


def play_start(thresholds, history):
    """The plays (n,) after the inputs ``history`` (H,): every play starts at ``history[0]``,
    then ``p = min(max(p, h - r), h + r)`` for each later ``h``."""
    r = np.asarray(thresholds, dtype=float)
    p = np.full(r.shape, float(history[0]))
    for h in history[1:]:
        p = np.minimum(np.maximum(p, h - r), h + r)
    return p


def clamp_loop(lo, hi, p, out=None):
    """``P[t] = min(max(P[t-1], lo[t]), hi[t])`` from ``P[-1] = p``: one Python step per row of
    the bounds ``lo``, ``hi`` (T, n), written in place into ``out`` (T, n) (default: a new array),
    which it returns."""
    out = np.empty(np.shape(lo)) if out is None else out
    mx, mn = np.maximum, np.minimum
    for lo_t, hi_t, out_t in zip(lo, hi, out):
        mn(mx(p, lo_t, out=out_t), hi_t, out=out_t)
        p = out_t
    return out


def play_loop(u, thresholds, history=None, block=BLOCK):
    """The play outputs (T, n): ``p_t = min(max(p_{t-1}, u_t - r), u_t + r)``, one Python step per
    sample (:func:`clamp_loop`), the bounds ``u -+ r`` computed ``block`` samples at a time; the
    plays start at :func:`play_start` of ``history`` (default ``[u[0]]``). The design matrix of a
    PI operator, ``y = offset + P @ w``."""
    u, r = np.asarray(u, dtype=float), np.asarray(thresholds, dtype=float)
    p = play_start(r, u[:1] if history is None else np.asarray(history, dtype=float))
    out = np.empty((u.size, r.size))
    for i in range(0, u.size, block):
        ub = u[i : i + block, None]
        p = clamp_loop(ub - r, ub + r, p, out[i : i + block])[-1]
    return out


def pi_play_loop(u, thresholds, weights, offset=0.0, history=None, block=BLOCK):
    """PI operator as jaxafm runs it: the plays in the loop (:func:`play_loop`), then the readout
    ``offset + P @ weights`` over all samples at once (:func:`pi_loop` reads out inside the loop)."""
    return offset + play_loop(u, thresholds, history, block) @ np.asarray(weights, dtype=float)


def preisach_play_loop(u, density, u_min, u_max, history=None, smooth=False, block=BLOCK):
    """Preisach model through Krejci's play representation: O(n) per sample, as jaxafm runs it.

    The plane of :class:`jaxafm.Preisach` (``n`` levels over ``[u_min, u_max]``, step
    ``D = (u_max - u_min) / n``; relay ``(alpha_i, beta_j)``, ``i >= j``, at
    ``alpha_i = u_min + (i + 1/2) D``, ``beta_j = u_min + (j + 1/2) D``). Relay ``(j + k, j)``
    lies on play line ``k``: it is up exactly when the play of radius ``k D / 2`` sits at or
    above its centre ``s_kj = (alpha + beta) / 2 = u_min + (2 j + k + 1) D / 2``. So:

    1. the n plays, one Python step per sample (:func:`play_loop`, from ``history``, bounds
       ``block`` samples at a time);
    2. per line ``k``, over all samples at once: the weight ``F_k(p)`` of the line's relays up,
       from the cumulative sums ``C`` (from 0) of the line's relay weights. Bare relays
       (``smooth=False``): ``C[i]``, with ``i`` the number of centres at or below ``p``,
       ``floor((p - s_k0) / D) + 1`` clipped to the line. ``smooth=True`` (each relay's weight
       spread evenly over ``s_kj +- D/2``): the piecewise-linear ``np.interp`` of ``C`` over
       the relays' edges;
    3. ``y = sum_k 2 F_k(p_k) - F_k(inf)`` (relays at +-1, no offset).
    """
    density = np.asarray(density, dtype=float)
    n = density.shape[0]
    D = (u_max - u_min) / n
    P = play_loop(u, np.arange(n) * D / 2, history, block)
    y = np.zeros(P.shape[0])
    for k in range(n):
        j = np.arange(n - k)
        C = np.concatenate([[0.0], np.cumsum(density[j + k, j])])
        s = u_min + (2 * j + k + 1) * D / 2
        if smooth:
            F = np.interp(P[:, k], np.append(s - D / 2, s[-1] + D / 2), C)
        else:
            F = C[np.clip(np.floor((P[:, k] - s[0]) / D).astype(np.intp) + 1, 0, n - k)]
        y += 2 * F - C[-1]
    return y


def linear_recurrence(a, b, z0):
    """``z_n = a_n z_{n-1} + b_n`` from ``z_{-1} = z0``, one Python step per sample: the exact
    first-order lag (``a = exp(-dt / tau)``, ``b = (1 - a) v``) and the Ornstein-Uhlenbeck step.

    ``a``, ``b`` (T,): one state, on Python floats (faster than NumPy on one number);
    (T, K): K states, a NumPy row per step, in place. Returns ``z`` shaped like ``b``.
    """
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    if b.ndim == 1:
        z, out = float(z0), []
        for a_n, b_n in zip(a.tolist(), b.tolist()):
            z = a_n * z + b_n
            out.append(z)
        return np.array(out)
    out = np.empty(b.shape)
    z = np.broadcast_to(np.asarray(z0, dtype=float), b.shape[1:])
    mul, add = np.multiply, np.add
    for a_n, b_n, out_n in zip(a, b, out):
        add(mul(z, a_n, out=out_n), b_n, out=out_n)
        z = out_n
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


def _grating_tip(sample, tip):
    """The constants of a jaxafm ``Grating``'s exact tip image (``Grating.imaged``), from its
    description: grooves (``depth < 0``) become lines of ``|depth|`` in between, lowered by ``low``;
    ``top`` is the half-width of the plateau, ``foot`` of the base, ``m`` the wall slope, ``r_star``
    and ``lift`` where and how high the apex sphere touches a wall, ``rt`` where the apex sphere
    meets the cone."""
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
    return SimpleNamespace(
        pitch=pitch,
        depth=depth,
        w=w,
        angle=angle,
        phase=phase,
        low=low,
        foot=foot,
        top=top,
        peak=peak,
        m=m,
        r_star=radius * m / np.sqrt(1 + m**2),
        lift=radius * (np.sqrt(1 + m**2) - 1),
        radius=radius,
        theta=theta,
        rt=radius * np.cos(theta),
    )


def numpy_grating_image(sample, tip):
    """A NumPy ``image(p)`` for a point ``(2,)`` nm: the exact tip image of a jaxafm ``Grating``
    (``Grating.imaged``), written again from its description: the best of the nearer top corner,
    the top plateau and the tangent contact of the apex sphere inside a wall, over the nearest
    line and its neighbours. One point per call, on scalars (:func:`numpy_grating_images` does
    the same for many points at once)."""
    g = _grating_tip(sample, tip)
    pitch, depth, w, angle, phase, low = g.pitch, g.depth, g.w, g.angle, g.phase, g.low
    foot, top, peak, m, r_star, lift = g.foot, g.top, g.peak, g.m, g.r_star, g.lift
    radius, theta, rt = g.radius, g.theta, g.rt

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


def numpy_grating_images(sample, tip):
    """:func:`numpy_grating_image` for many points: ``image(p)`` (..., 2) nm -> (...) nm, each
    branch of the scalar version a masked ``np.maximum`` over all points at once."""
    g = _grating_tip(sample, tip)
    wall = g.m * np.tan(g.theta) <= 1  # the apex sphere can touch a wall

    def profile(r):  # Tip.profile: the apex sphere up to rt, then the cone
        sphere = g.radius - np.sqrt(np.maximum(g.radius**2 - np.minimum(r, g.rt) ** 2, 1e-12))
        return sphere + np.maximum(r - g.rt, 0.0) / np.tan(g.theta)

    def image(p):
        u = np.cos(g.angle) * p[..., 0] + np.sin(g.angle) * p[..., 1]
        k = np.round((u - g.phase) / g.pitch)
        best = np.zeros(u.shape)
        for j in (k - 1, k, k + 1):
            s = np.abs(u - g.phase - j * g.pitch)
            best = np.maximum(best, g.peak - profile(np.abs(s - g.top)))
            best = np.where(s <= g.top, np.maximum(best, g.peak), best)
            if wall:
                touch = (g.top <= s - g.r_star) & (s - g.r_star <= min(g.foot, g.pitch / 2))
                best = np.where(touch, np.maximum(best, g.depth * (g.foot - s) / g.w + g.lift), best)
        return best + g.low

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


def _instrument_numpy(afm):
    """The AFM's parameters as NumPy: both axes (:func:`_axis_numpy`), ``coupling`` (xy, yx),
    ``bow`` (bx, by), ``drift`` (velocity, sigma, theta floored at 1e-12), ``noise_std`` and
    ``feedback_tau``; ``None`` for an effect that is off."""
    sc = afm.scanner
    d = sc.drift
    return SimpleNamespace(
        axes=[_axis_numpy(sc.x), _axis_numpy(sc.y)],
        coupling=None if sc.coupling is None else (_np(sc.coupling.xy), _np(sc.coupling.yx)),
        bow=None if sc.bow is None else (_np(sc.bow.bx), _np(sc.bow.by)),
        drift=None if d is None else (_np(d.velocity), _np(d.sigma), np.maximum(_np(d.theta), 1e-12)),
        noise_std=None if sc.noise is None else _np(sc.noise.std),
        feedback_tau=None if afm.feedback is None else _np(afm.feedback.tau),
    )


def _axis_start(a, history, u0):
    """One axis at rest at ``u0`` V after ``history`` (H,) V, as ``Axis.initial_state``: the plays
    after the history, and the output ``v0`` nm of the plays moved on to ``u0`` (where the lags
    and the creep start relaxed)."""
    p = play_start(a["r"], history)
    return p, _readout(a, np.minimum(np.maximum(p, u0 - a["r"]), u0 + a["r"]))


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
    inst = _instrument_numpy(afm)
    u, t = _np(u), _np(t)
    axes, xy_c, bow, noise_std, fb_tau = inst.axes, inst.coupling, inst.bow, inst.noise_std, inst.feedback_tau
    drift = inst.drift is not None
    if drift:
        vel, sigma, theta = inst.drift
    q, lift = (_np(a) for a in afm.tip.stencil())
    if not afm.dilate:
        probe = height
    elif probe is None:
        probe = lambda p: np.max(height(p + q) - lift)

    # the state afm.initial_state(u0, t0, history) builds
    u0 = _np(u0)
    hist = np.reshape(u0, (1, 2)) if history is None else _np(history)
    plays, lag, creep, rest = [], [], [], []
    for k, a in enumerate(axes):
        p, v0 = _axis_start(a, hist[:, k], u0[k])
        plays.append(p)
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


def _readout_rows(a, P):
    """:func:`_readout` of many samples at once: plays ``P`` (T, n) -> outputs (T,) nm."""
    y = a["offset"] + P @ a["w"]
    if a["dz"] is None:
        return y
    c, g0, up, up_w, lo, lo_w = a["dz"]
    x = (y - c)[:, None]
    return c + g0 * x[:, 0] + np.maximum(x - up, 0.0) @ up_w - np.maximum(lo - x, 0.0) @ lo_w


def _start_state(inst, u0, t0, history, z0):
    """What the vectorised drive carries from block to block, at rest as
    ``afm.initial_state(u0, t0, history)`` with the feedback at ``z0``: the plays of both axes
    (concatenated), their rest outputs ``v0`` (where the lags and the creep start relaxed), the
    rate-dependence lags, the state of :func:`linear_recurrence` over the creep lags of both axes
    and the drift's wander, the feedback ``z``, the last sample's time ``t`` and the drift's
    time origin."""
    hist = np.reshape(u0, (1, 2)) if history is None else _np(history)
    plays, v0 = zip(*(_axis_start(a, hist[:, k], u0[k]) for k, a in enumerate(inst.axes)))
    lin = [
        np.full(a["creep_taus"].size, v0[k]) for k, a in enumerate(inst.axes) if a["creep_taus"] is not None
    ]
    lin += [np.zeros(2)] if inst.drift is not None else []
    return SimpleNamespace(
        plays=np.concatenate(plays),
        rest=np.array(v0),
        lag=np.array(v0),
        lin=np.concatenate(lin) if lin else np.zeros(0),
        z=float(z0),
        t=float(t0),
        origin=float(t0),
    )


def _hysteresis_rows(axes, u, plays):
    """Both axes' hysteresis outputs (T, 2) nm for the drive ``u`` (T, 2) V from ``plays`` (both
    axes concatenated), and the plays after: the plays of both axes in one :func:`clamp_loop`,
    then each axis's readout of all samples at once."""
    r = np.concatenate([a["r"] for a in axes])
    col = np.repeat(np.arange(len(axes)), [a["r"].size for a in axes])  # the axis of each play
    P = clamp_loop(u[:, col] - r, u[:, col] + r, plays)
    edges = np.cumsum([0] + [a["r"].size for a in axes])
    v = np.stack([_readout_rows(a, P[:, i:j]) for a, i, j in zip(axes, edges[:-1], edges[1:])], axis=1)
    return v, P[-1]


def _lag(v, dt, tau, z0):
    """First-order lag of ``v`` (T,) held over each step ``dt`` (T,) s, from ``z0``."""
    e = np.exp(-dt / tau)
    return linear_recurrence(e, (1 - e) * v, z0)


def _creep_and_wander(inst, v, dt, rest, lin, drift_normals):
    """The creep outputs (T, 2) nm of both axes, the drift's wander (T, 2) nm (zeros when off)
    and the recurrence's state after: every creep lag (creeping from ``rest``) and the wander's
    exact Ornstein-Uhlenbeck step in one :func:`linear_recurrence` from ``lin``, their
    coefficients computed for all samples first."""
    a, b = [], []
    for k, ax in enumerate(inst.axes):
        if ax["creep_taus"] is not None:
            e = np.exp(-dt[:, None] / ax["creep_taus"])
            a.append(e)
            b.append((1 - e) * v[:, k : k + 1])
    if inst.drift is not None:
        _, sigma, theta = inst.drift
        a.append(np.broadcast_to(np.exp(-theta * dt)[:, None], (dt.size, 2)))
        b.append(sigma * np.sqrt(-np.expm1(-2 * theta * dt) / (2 * theta))[:, None] * drift_normals)
    if not a:
        return v, np.zeros_like(v), lin
    Z = linear_recurrence(np.hstack(a), np.hstack(b), lin)
    out, i = v.copy(), 0
    for k, ax in enumerate(inst.axes):
        if ax["creep_taus"] is not None:
            K = ax["creep_taus"].size
            out[:, k] += (Z[:, i : i + K] - rest[k]) @ ax["creep_w"]
            i += K
    return out, (Z[:, i:] if inst.drift is not None else np.zeros_like(v)), Z[-1]


def _probe_rows(afm, height, probe):
    """The probe height of many points (T, 2) -> (T,) nm: ``probe`` if given, ``height`` without
    dilation, else ``max_q height(p + q) - lift_q`` over ``afm.tip.stencil()``."""
    if probe is not None:
        return probe
    if not afm.dilate:
        return height
    q, lift = (_np(a) for a in afm.tip.stencil())
    return lambda P: np.max(height(P[:, None, :] + q) - lift, axis=1)


def _drive_block(inst, probe, u, t, drift_normals, noise_normals, s):
    """One block of :func:`drive_numpy_vectorised` from the state ``s`` (:func:`_start_state`),
    which it moves on to the block's last sample: the path (T, 2) nm and recorded height (T,) nm."""
    dt = np.diff(t, prepend=s.t)
    v, s.plays = _hysteresis_rows(inst.axes, u, s.plays)
    for k, a in enumerate(inst.axes):
        if a["rate_tau"] is not None:
            v[:, k] = _lag(v[:, k], dt, a["rate_tau"], s.lag[k])
            s.lag[k] = v[-1, k]
    p, wander, s.lin = _creep_and_wander(inst, v, dt, s.rest, s.lin, drift_normals)
    if inst.coupling is not None:
        p = np.stack([p[:, 0] + inst.coupling[0] * p[:, 1], p[:, 1] + inst.coupling[1] * p[:, 0]], axis=1)
    if inst.bow is not None:
        p = np.stack([p[:, 0] + inst.bow[0] * p[:, 1] ** 2, p[:, 1] + inst.bow[1] * p[:, 0] ** 2], axis=1)
    if inst.drift is not None:
        p = p + inst.drift[0] * (t - s.origin)[:, None] + wander
    if inst.noise_std is not None:
        p = p + inst.noise_std * noise_normals
    surf = probe(p)
    if inst.feedback_tau is not None:
        surf = _lag(surf, dt, inst.feedback_tau, s.z)
        s.z = surf[-1]
    s.t = t[-1]
    return p, surf


def drive_numpy_vectorised(
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
    block=BLOCK,
):
    """:func:`drive_numpy`, looping over samples only where a sample needs the one before it.

    The same model, arguments and returns, but ``probe`` maps many points (T, 2) nm to heights
    (T,) nm (e.g. :func:`numpy_grating_images`). Python loops over samples: the plays of both
    axes (one :func:`clamp_loop`), the rate-dependence lags, the creep lags of both axes together
    with the drift's wander (one :func:`linear_recurrence`), the feedback lag. Over all samples
    of a block at once: the PI and dead-zone readout, the lag coefficients ``exp(-dt / tau)``,
    coupling, bow, the drift's velocity and kicks, noise and the probe heights. The drive runs
    ``block`` samples at a time, carrying the state from one block to the next, so that the
    temporaries stay in cache.
    """
    inst, probe = _instrument_numpy(afm), _probe_rows(afm, height, probe)
    u, t = _np(u), _np(t)
    s = _start_state(inst, _np(u0), t0, history, z0)
    rows = lambda a, i: None if a is None else a[i : i + block]
    out = [
        _drive_block(
            inst, probe, u[i : i + block], t[i : i + block], rows(drift_normals, i), rows(noise_normals, i), s
        )
        for i in range(0, len(t), block)
    ]
    return np.concatenate([o[0] for o in out]), np.concatenate([o[1] for o in out])


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
    vectorised=False,
    block=BLOCK,
):
    """:func:`drive_numpy` (or :func:`drive_numpy_vectorised` with ``vectorised``) over
    :func:`raster_drive`: the NumPy counterpart of ``raster_scan`` from
    ``afm.initial_state(u0, t0, history)`` with nominal volts.

    Returns ``trace``, ``retrace`` (lines, pixels) nm, ``path_trace``, ``path_retrace``
    (lines, pixels, 2) nm, and the whole drive's ``path`` (T, 2), ``recorded`` (T,)
    and ``t`` (T,). ``lines`` runs only the move and the first ``lines`` lines
    (a prefix of the same scan, e.g. for timing); ``probe`` as for the drive function used;
    ``block``: samples per block of :func:`drive_numpy_vectorised`.
    """
    u, t = raster_drive(afm, raster, u0, t0, move_time, move_samples)
    L, n = raster.lines if lines is None else lines, 2 * (raster.pixels + 2 * raster.margin)
    T = move_samples + L * n
    cut = lambda a: None if a is None else a[:T]
    args = (afm, height, u[:T], t[:T], cut(drift_normals), cut(noise_normals), u0, t0, history)
    if vectorised:
        path, rec = drive_numpy_vectorised(*args, probe=probe, block=block)
    else:
        path, rec = drive_numpy(*args, probe=probe)
    out = {"path": path, "recorded": rec, "t": t[:T]}
    P, m = raster.pixels, raster.margin
    for i, name in enumerate(("trace", "retrace")):
        for key, a in ((name, rec[move_samples:]), (f"path_{name}", path[move_samples:])):
            img = a.reshape((L, 2, n // 2) + a.shape[1:])[:, i, m : m + P]
            img = img[:, ::-1] if i == 1 else img
            out[key] = img[::-1] if raster.direction == "down" else img
    return out


def numerical_inverse_per_sample(model, wanted, t, state, u0, u_max):
    """The numerical inverse as jaxafm ran it before it ran over blocks (JAX, not NumPy): one
    ``lax.scan`` step per sample on both axes; each step solves the creep/rate lag's affine
    map for the hysteresis output by evaluating it at 0 and 1, inverts the hysteresis from the
    plays (``invert_step``) and steps the forward model. The baseline of
    ``jaxafm.identify.inverse.numerical_inverse``: same arguments, same results."""
    import jax.numpy as jnp
    from jax import lax

    from jaxafm.identify.inverse import axis_targets
    from jaxafm.model.scanner import AxisState

    def dynamics(axis, h, tn, s, t0):
        v, lag, creep, tt = jnp.reshape(h, (1,)), s.lag, s.creep, jnp.reshape(tn, (1,))
        if axis.rate_dependence is not None:
            v, lag = axis.rate_dependence.run(v, tt, lag, t0)
        if axis.creep is not None:
            v, creep = axis.creep.run(v, tt, creep, t0)
        return v[0], lag, creep

    def step_axis(axis, v, tn, s, t0, u_prev):
        f0, f1 = dynamics(axis, jnp.zeros(()), tn, s, t0)[0], dynamics(axis, jnp.ones(()), tn, s, t0)[0]
        u, saturated = axis.hysteresis.invert_step((v - f0) / (f1 - f0), s.plays, -u_max, u_max, u_prev)
        y, plays = axis.hysteresis.step(u, s.plays)
        _, lag, creep = dynamics(axis, y, tn, s, t0)
        return u, AxisState(plays, lag, creep), saturated

    def step(carry, inputs):
        sx, sy, t_prev, u_prev = carry
        vn, tn = inputs
        ux, sx, bad_x = step_axis(model.x, vn[0], tn, sx, t_prev, u_prev[0])
        uy, sy, bad_y = step_axis(model.y, vn[1], tn, sy, t_prev, u_prev[1])
        u = jnp.stack([ux, uy])
        return (sx, sy, tn, u), (u, jnp.stack([bad_x, bad_y]))

    v = axis_targets(model, wanted, t, state)
    _, (u, saturated) = lax.scan(step, (state.x, state.y, state.t, jnp.asarray(u0, dtype=float)), (v, t))
    return u, saturated
