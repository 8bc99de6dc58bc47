"""An independent generator of two-axis piezo actuator records (NumPy/SciPy only, no jaxafm).

Written from textbook definitions, not from jaxafm's simulator, so that jaxafm's diagnosis can
be checked on data its own model code did not make. Units: time s, input V, output nm.

Sampling. ``t[n] = n * dt``, ``dt = 1 / fs``. Between its samples the drive is the straight line
through them (an analogue ramp). The model runs at ``OVERSAMPLE = 10`` internal steps per sample
(``dt_f = dt / 10``) on that line and the record keeps every 10th internal sample. Every filter is
the exact zero-order-hold (ZOH) discretisation of its continuous system at ``dt_f``: its input
held constant over each internal step. (At ``dt`` itself the ZOH's staircase would lag the ramp
by half a sample, 0.5 ms, in every filtered effect: a delay none of the effects has; at ``dt_f``
it is 0.05 ms. The hysteresis is rate-independent, so its values at the record's samples are the
same either way.)

Hysteresis (one per axis, the truth's class):

- Prandtl-Ishlinskii (PI). The play (backlash) operator of radius ``r >= 0``::

      p_r[0] = u[0],   p_r[n] = max(u[n] - r, min(u[n] + r, p_r[n-1]))

  and the PI output ``y[n] = offset + sum_i w_i p_{r_i}[n]`` (weights ``w_i >= 0``). On a major
  loop between -A and A (all ``r_i <= A``) the ascending branch is ``sum w_i (u - r_i)`` and
  the descending one ``sum w_i (u + r_i)``: the loop is ``2 sum_i w_i r_i`` wide at every u
  where all plays move, and its output span is ``2 sum_i w_i (A - r_i)``.
- Preisach. Relays ``R_{alpha,beta}`` with thresholds ``alpha >= beta``::

      R[n] = +1 if u[n] >= alpha,  -1 if u[n] <= beta,  R[n-1] otherwise

  one relay per cell of an ``n x n`` grid over ``[u_lo, u_hi] = [-10, 10] V`` (n = 100, or
  ``make_case``'s ``relays``; lower triangle, diagonal cells included), placed at a fixed random
  point of its cell (a stratified sample of the plane, so that a row of relays does not switch
  at once and the output has no staircase of 30 nm steps; a diagonal cell's point is mirrored
  into alpha >= beta and weighs half a cell). Output
  ``y[n] = offset + scale * sum_k mu_k A_k R_k[n] / sum_k mu_k A_k`` (``A_k`` the cell's area),
  the density ``mu`` in centre ``c = (alpha + beta) / 2`` and half-width
  ``h = (alpha - beta) / 2``::

      mu = exp(-(c - c0)^2 / (2 sc^2) - (h - h0)^2 / (2 sh^2))

  With ``c0`` at the middle of the input range the density is symmetric,
  ``mu(alpha, beta) = mu(-beta, -alpha)`` about that middle (the relays' jitter breaks the mirror
  symmetry of the sample only at the scale of one cell, 0.2 V). Start state: AC-demagnetised about
  ``u[0]`` (the staircase limit): ``R = +1`` where ``c < u[0]``, ``-1`` where ``c > u[0]`` and 0 on
  the line ``c = u[0]`` itself (half up, half down), then the rule above at ``u[0]``. This is
  the state the PI's ``p_r[0] = u[0]`` corresponds to. On a major loop between -A and A the
  width at u = 0 is ``2 scale * sum_{|c| < h} mu / sum mu`` (the relays with beta < 0 < alpha).

Effects, each after the hysteresis ``h`` (nm, centred: no offset yet), in this order:

1. ``asymmetry`` (a, per axis): ``d -> d + a (d - c)^2 / H`` with ``c`` the middle of the axis's
   output range and ``H`` its half-range, so the ascending and descending branches differ in
   shape (asymmetric hysteresis); at the ends of the range it adds ``a H``.
2. ``rate_dependence`` (tau s): first-order lag ``tau y' + y = d``; ZOH:
   ``y[n+1] = q y[n] + (1 - q) d[n]``, ``q = exp(-dt / tau)``, started at rest at ``d[0]``.
3. ``creep`` (gamma per decade): ``y = d + (gamma / m) sum_k (L_k d - d[0])``, ``L_k`` first-order
   lags (ZOH as in 2., at rest at ``d[0]``) with ``tau_k = tau_min 10^(k / m)``, ``k = 0..K``,
   ``tau_min = 0.01 s``, ``tau_max = 1000 s``, ``m = 4`` per decade. A step ``d0`` at ``t = 0``
   gives ``y(t) = d0 (1 + (gamma / m) sum_k (1 - exp(-t / tau_k)))
   ~= d0 (1 + gamma (log10(t / tau_min) + 0.25 + 1 / (2 m)))`` for ``tau_min << t << tau_max``:
   gamma d0 per decade of time (the 0.25 is Euler's gamma / ln 10, the 1 / (2m) the sum's first term).
4. ``coupling`` (c): ``x -> x + c y``, ``y -> y - 0.6 c x`` (both from the values before).
5. ``bow`` (b, 1/nm): ``x -> x + b y^2``, ``y -> y - 0.5 b x^2`` (centred outputs, values before).
6. ``vibration`` (f0 Hz, zeta): a mechanical mode ``x'' + 2 zeta w0 x' + w0^2 x = w0^2 p``,
   ``w0 = 2 pi f0``, ZOH-discretised (``scipy.signal.cont2discrete``), at rest at ``p[0]``. Step
   response: overshoot ``exp(-pi zeta / sqrt(1 - zeta^2))``, ringing at ``w0 sqrt(1 - zeta^2)``.
7. offset (per axis), ``drift`` (v nm/s: ``x += v_x t``, ``y += v_y t``, ``v_y = -0.7 v_x``-ish,
   opposite signs) and ``noise`` (white, Gaussian, 2 nm std, every case). A drift may also
   wander (``wander``, :data:`WANDERS`), the same process on each axis, drawn independently,
   sampled exactly at ``t``, ``w[0] = 0``:

   - ``walk``, a random walk of ``sigma`` nm/sqrt(s): ``w[n+1] = w[n] + sigma sqrt(dt) xi``;
     its sd after ``t`` s is ``sigma sqrt(t)``;
   - ``ou``, an Ornstein-Uhlenbeck process of stationary sd ``sigma`` nm and time constant
     ``tau`` s: ``w[n+1] = a w[n] + sigma sqrt(1 - a^2) xi``, ``a = exp(-dt / tau)``; its sd
     after ``t`` s is ``sigma sqrt(1 - exp(-2 t / tau))``.

Per-seed truth: PI, 12 plays of radii 0 ... 7.2 V, weights decaying as ``exp(-r / s)``; the
linear (r = 0) weight sets the major loop's width to 10-25 % of its span; span 2 G 9 V with the
gain G = 100 nm/V +-20 %. Preisach: ``c0 = 0``, ``sc`` 0.5-0.9 x 9 V, ``sh / h0`` 0.3-0.6, ``h0``
set (bisection) so the major loop's width is 10-25 % of its span, ``scale`` so the span is
2 G 9 V. Offsets +-100 nm. Effect parameters: the level's magnitude x U(0.8, 1.2).

The drive (:data:`DRIVE`): two axes at 1 kHz for 6 s, each a piecewise-linear (triangle-like)
wave through turning points: x starts with two full +-9 V cycles, then reversals of varying
amplitude (minor loops, some nested) at 1.5-5 Hz; y the same at 1-3 Hz with its own points.
"""

from __future__ import annotations

import numpy as np
from scipy import signal, special

FS = 1000.0  # Hz
DURATION = 6.0  # s
U_MAX = 9.0  # V, the drive's amplitude
U_RANGE = (-10.0, 10.0)  # V, the Preisach plane
NOISE_NM = 2.0
GAIN = 100.0  # nm/V, +-20 % per axis and seed
CREEP_TAU = (0.01, 1000.0)  # s
CREEP_PER_DECADE = 4
EFFECTS = ("asymmetry", "rate_dependence", "creep", "drift", "coupling", "bow", "vibration")
LEVELS = ("low", "middle", "high")

#: low, middle, high per effect, fixed before any run; each case draws its parameter within
#: +-20 % of these. Units: asymmetry a (fraction of the half-range added at the ends),
#: rate_dependence tau s, creep gamma per decade, drift nm/s (x; y has -0.7x), coupling c,
#: bow b 1/nm, vibration f0 Hz (zeta 0.05; a lower f0 rings more).
MAGNITUDES = {
    "asymmetry": (0.01, 0.04, 0.12),
    "rate_dependence": (0.0003, 0.002, 0.008),
    "creep": (0.002, 0.01, 0.03),
    "drift": (0.5, 2.0, 6.0),
    "coupling": (0.002, 0.01, 0.03),
    "bow": (4e-6, 2e-5, 6e-5),
    "vibration": (350.0, 200.0, 80.0),
}
UNITS = {
    "asymmetry": "a: added a H at the ends of the range (fraction of the half-range H)",
    "rate_dependence": "tau s",
    "creep": "gamma per decade of time",
    "drift": "nm/s (x axis; y axis -0.7 x)",
    "coupling": "c (x += c y, y -= 0.6 c x)",
    "bow": "b 1/nm (x += b y^2, y -= 0.5 b x^2)",
    "vibration": "f0 Hz (zeta 0.05)",
}
VIBRATION_ZETA = 0.05
OVERSAMPLE = 10  # internal steps per sample
#: A drift's wander per level (``make_case(..., wander=...)``): ``walk`` sigma nm/sqrt(s), ``ou``
#: stationary sigma nm with ``OU_TAU_S``; over the 6 s record each spreads about as far as the
#: level's straight drift goes (3, 12 and 36 nm).
WANDERS = {"walk": (1.2, 5.0, 15.0), "ou": (4.5, 18.0, 54.0)}
OU_TAU_S = 20.0


# --------------------------------------------------------------------------- hysteresis
def play_operators(u, radii) -> np.ndarray:
    """Plays ``p_r`` (T, R) of input ``u`` (T,) for every radius; started at ``p = u[0]``."""
    u = np.asarray(u, float)
    radii = np.asarray(radii, float)
    out = np.empty((u.size, radii.size))
    p = np.full(radii.size, u[0])
    for n, un in enumerate(u):
        p = np.maximum(un - radii, np.minimum(un + radii, p))
        out[n] = p
    return out


def pi_operator(u, radii, weights, offset=0.0) -> np.ndarray:
    """Prandtl-Ishlinskii output ``offset + sum_i w_i p_{r_i}(u)`` (T,)."""
    return offset + play_operators(u, radii) @ np.asarray(weights, float)


def preisach_grid(n: int = 100, u_range=U_RANGE, seed: int = 0):
    """Relay thresholds ``alpha >= beta`` and cell areas: one relay per cell of an n x n grid
    over ``u_range`` (lower triangle, diagonal cells included), at a fixed random point of its
    cell (a stratified sample of the plane: relays of one row do not all switch at once, so the
    output has no staircase of whole rows); a diagonal cell's point is mirrored into alpha >= beta
    and weighs half a cell."""
    lo, hi = u_range
    step = (hi - lo) / n
    i, j = np.tril_indices(n)
    rng = np.random.default_rng(seed)
    a = lo + (i + rng.random(i.size)) * step
    b = lo + (j + rng.random(i.size)) * step
    alpha, beta = np.maximum(a, b), np.minimum(a, b)
    area = np.where(i == j, 0.5, 1.0) * step**2
    return alpha, beta, area


def preisach_density(alpha, beta, c0, sc, h0, sh) -> np.ndarray:
    """Gaussian density in centre ``(alpha + beta) / 2`` and half-width ``(alpha - beta) / 2``."""
    c, h = 0.5 * (alpha + beta), 0.5 * (alpha - beta)
    return np.exp(-((c - c0) ** 2) / (2 * sc**2) - (h - h0) ** 2 / (2 * sh**2))


def preisach_weights(c0, sc, h0, sh, n=100, u_range=U_RANGE):
    """Relays (alpha, beta) and their weights ``mu * area``, normalised to sum 1."""
    alpha, beta, area = preisach_grid(n, u_range)
    mu = preisach_density(alpha, beta, c0, sc, h0, sh) * area
    return alpha, beta, mu / mu.sum()


def preisach_operator(
    u, c0=0.0, sc=4.0, h0=1.5, sh=0.8, scale=1.0, offset=0.0, n=100, u_range=U_RANGE
) -> np.ndarray:
    """Preisach output (T,): relays on an n x n grid over ``u_range`` with the Gaussian density,
    ``offset + scale * sum mu R / sum mu``; start state demagnetised about ``u[0]``."""
    u = np.asarray(u, float)
    alpha, beta, mu = preisach_weights(c0, sc, h0, sh, n, u_range)
    c = 0.5 * (alpha + beta)
    state = np.sign(u[0] - c)  # +1 below u[0], -1 above, 0 on the line
    out = np.empty(u.size)
    for k, un in enumerate(u):
        state = np.where(un >= alpha, 1.0, np.where(un <= beta, -1.0, state))
        out[k] = state @ mu
    return offset + scale * out


def preisach_continuous(
    u, c0=0.0, sc=4.0, h0=1.5, sh=0.8, scale=1.0, offset=0.0, u_range=U_RANGE, widths: int = 400
) -> np.ndarray:
    """The same Preisach output (T,) with the density continuous over the plane instead of
    sampled by one relay a cell: the limit of :func:`preisach_operator` as its grid refines.
    In centre ``c`` and half-width ``h`` (``d alpha d beta = 2 dc dh``; the plane ``|c| <= L(h)
    = u_hi - h`` for the symmetric range), the relays of half-width ``h`` are all set by one play
    of radius ``h`` (``R = sign(p_h - c)``, the play started at ``u[0]`` as the relays' start
    state), so their weighted sum is a closed form in the error function::

        N_h(p) = int_{-L}^{L} g(c) sign(p - c) dc = 2 E(clip(p, -L, L)) - E(-L) - E(L),

    ``g`` the Gaussian in ``c``, ``E`` its integral (``sc sqrt(pi / 2) erf((c - c0) / (sqrt(2) sc))``);
    ``h`` by the midpoint rule over ``widths`` half-widths. Output
    ``offset + scale * int G(h) N_h dh / int G(h) N_h(+inf) dh``, ``G`` the Gaussian in ``h``."""
    lo, hi = u_range
    if lo != -hi:
        raise ValueError(f"preisach_continuous takes a range symmetric about 0 V, got {u_range}")
    h = (np.arange(widths) + 0.5) * hi / widths
    half = hi - h  # the plane's half-extent in c at each half-width
    erf_int = lambda c: sc * np.sqrt(np.pi / 2) * special.erf((c - c0) / (np.sqrt(2) * sc))
    weight = np.exp(-((h - h0) ** 2) / (2 * sh**2))
    u = np.asarray(u, float)
    n, p = np.empty(u.size), np.full(widths, u[0])
    for k, uk in enumerate(u):  # the plays of play_operators, one sample at a time (no (T, widths) array)
        p = np.maximum(uk - h, np.minimum(uk + h, p))
        n[k] = 2 * erf_int(np.clip(p, -half, half)) @ weight
    n -= (erf_int(-half) + erf_int(half)) @ weight
    total = weight @ (erf_int(half) - erf_int(-half))
    return offset + scale * n / total


def preisach_major_fraction(c0, sc, h0, sh, a=U_MAX, n=100, u_range=U_RANGE):
    """(width at u = c0 over the span) of the major loop between c0 -+ a, and the span per scale."""
    alpha, beta, mu = preisach_weights(c0, sc, h0, sh, n, u_range)
    c, h = 0.5 * (alpha + beta) - c0, 0.5 * (alpha - beta)
    switched = mu[(alpha <= c0 + a) & (beta >= c0 - a)].sum()
    across = mu[np.abs(c) < h].sum()
    return across / switched, 2 * switched


# --------------------------------------------------------------------------- effects
def asymmetry(d, a, centre, half_range) -> np.ndarray:
    """``d + a (d - centre)^2 / half_range``."""
    return d + a * (d - centre) ** 2 / half_range


def first_order_lag(d, tau, dt) -> np.ndarray:
    """ZOH-exact ``tau y' + y = d`` along axis 0, at rest at ``d[0]``."""
    d = np.asarray(d, float)
    q = np.exp(-dt / tau)
    b, a = [0.0, 1.0 - q], [1.0, -q]
    zi = signal.lfilter_zi(b, a)
    zi = zi.reshape((1,) + (1,) * (d.ndim - 1)) * d[:1]
    return signal.lfilter(b, a, d, axis=0, zi=zi)[0]


def rate_dependence(d, tau, dt) -> np.ndarray:
    """A first-order lag of ``tau`` s after the hysteresis."""
    return first_order_lag(d, tau, dt)


def creep_taus(tau_range=CREEP_TAU, per_decade=CREEP_PER_DECADE) -> np.ndarray:
    decades = np.log10(tau_range[1] / tau_range[0])
    return tau_range[0] * 10.0 ** (np.arange(int(round(decades * per_decade)) + 1) / per_decade)


def creep(d, gamma, dt, tau_range=CREEP_TAU, per_decade=CREEP_PER_DECADE) -> np.ndarray:
    """Logarithmic creep: ``d + (gamma / m) sum_k (lag_k(d) - d[0])``, log-spaced lags."""
    d = np.asarray(d, float)
    extra = sum(first_order_lag(d, tau, dt) - d[:1] for tau in creep_taus(tau_range, per_decade))
    return d + gamma / per_decade * extra


def drift(d, t, velocities) -> np.ndarray:
    """``d[:, i] + v_i t``."""
    return d + np.asarray(t)[:, None] * np.asarray(velocities)[None, :]


def drift_wander(t, kind: str, sigma: float, tau: float, rng) -> np.ndarray:
    """A drift's wander (T,) nm at the times ``t`` (module docstring, 7.), ``w[0] = 0``."""
    dt = np.diff(t)
    xi = rng.standard_normal(dt.size)
    if kind == "walk":
        return np.r_[0.0, np.cumsum(sigma * np.sqrt(dt) * xi)]
    a = np.exp(-dt / tau)
    w = np.zeros(t.size)
    for n in range(dt.size):
        w[n + 1] = a[n] * w[n] + sigma * np.sqrt(1 - a[n] ** 2) * xi[n]
    return w


def coupling(d, c) -> np.ndarray:
    """``x + c y``, ``y - 0.6 c x``."""
    x, y = d[:, 0], d[:, 1]
    return np.stack([x + c * y, y - 0.6 * c * x], axis=1)


def bow(d, b) -> np.ndarray:
    """``x + b y^2``, ``y - 0.5 b x^2`` (b 1/nm)."""
    x, y = d[:, 0], d[:, 1]
    return np.stack([x + b * y**2, y - 0.5 * b * x**2], axis=1)


def vibration(p, f0, zeta, dt) -> np.ndarray:
    """A second-order mode ``x'' + 2 zeta w0 x' + w0^2 x = w0^2 p`` (ZOH), at rest at ``p[0]``."""
    p = np.asarray(p, float)
    w0 = 2 * np.pi * f0
    num, den, _ = signal.cont2discrete(([w0**2], [1.0, 2 * zeta * w0, w0**2]), dt, method="zoh")
    b, a = np.ravel(num), np.ravel(den)
    zi = signal.lfilter_zi(b, a)
    zi = zi.reshape((-1,) + (1,) * (p.ndim - 1)) * p[:1]
    return signal.lfilter(b, a, p, axis=0, zi=zi)[0]


def noise(shape, rng, std=NOISE_NM) -> np.ndarray:
    """White Gaussian noise of ``std`` nm."""
    return rng.normal(0.0, std, shape)


# --------------------------------------------------------------------------- drive
def _wave(duration, fs, first, f_range, period_s, seed) -> np.ndarray:
    """Piecewise-linear wave through turning points: the fixed ``first`` ones, then random
    reversals (alternating direction, varying amplitude) whose half-period follows a frequency
    sweeping ``f_range`` with a period of ``period_s``."""
    rng = np.random.default_rng(seed)
    times, values = [0.0], [0.0]
    k = 0
    while times[-1] < duration:
        f = f_range[0] + (f_range[1] - f_range[0]) * 0.5 * (1 - np.cos(2 * np.pi * times[-1] / period_s))
        if k < len(first):
            v = first[k]
        else:
            last = values[-1]
            up = last < values[-2]  # reverse the last move
            big = rng.random() < 0.3
            if up:
                v = U_MAX if big else rng.uniform(max(last + 2.0, -U_MAX + 3), U_MAX)
            else:
                v = -U_MAX if big else rng.uniform(-U_MAX, min(last - 2.0, U_MAX - 3))
        times.append(times[-1] + 1.0 / (2 * f))
        values.append(v)
        k += 1
    t = np.arange(int(round(duration * fs))) / fs
    return np.interp(t, times, values)


def make_drive(duration: float = DURATION, fs: float = FS):
    """(t (T,) s, u (T, 2) V): x 1.5-5 Hz, y 1-3 Hz, both +-9 V with minor loops."""
    x = _wave(duration, fs, [U_MAX, -U_MAX, U_MAX, -U_MAX], (1.5, 5.0), 2.5, 11)
    y = _wave(duration, fs, [-U_MAX, U_MAX, -U_MAX], (1.0, 3.0), 3.7, 23)
    t = np.arange(x.size) / fs
    return t, np.stack([x, y], axis=1)


DRIVE = make_drive()


# --------------------------------------------------------------------------- cases
def _pi_truth(rng):
    """PI per axis: 12 plays up to 0.8 U_MAX, decaying weights, loop width 10-25 % of range."""
    radii = np.linspace(0.0, 0.8 * U_MAX, 12)
    w = np.exp(-radii / (U_MAX * rng.uniform(0.2, 0.6))) * rng.uniform(0.7, 1.3, radii.size)
    w[0] = 0.0
    frac = rng.uniform(0.10, 0.25)  # width / span on the +-U_MAX major loop
    # frac = sum w r / (w0 A + sum w (A - r))  ->  w0
    w[0] = max((np.sum(w * radii) / frac - np.sum(w * (U_MAX - radii))) / U_MAX, 0.0)
    gain = GAIN * rng.uniform(0.8, 1.2)
    w *= gain * U_MAX / np.sum(w * (U_MAX - radii))  # span 2 gain U_MAX
    return {"radii": radii, "weights": w, "width_fraction": frac, "gain_nm_per_v": gain}


def _preisach_truth(rng):
    """Preisach per axis: Gaussian density, half-width tuned so the loop is 10-25 % of range."""
    frac = rng.uniform(0.10, 0.25)
    sc = U_MAX * rng.uniform(0.5, 0.9)
    rel = rng.uniform(0.3, 0.6)  # sh / h0
    lo, hi = 0.05, 6.0
    for _ in range(60):  # bisection: the width grows with h0
        h0 = 0.5 * (lo + hi)
        f, _ = preisach_major_fraction(0.0, sc, h0, rel * h0)
        lo, hi = (h0, hi) if f < frac else (lo, h0)
    span_per_scale = preisach_major_fraction(0.0, sc, h0, rel * h0)[1]
    gain = GAIN * rng.uniform(0.8, 1.2)
    return {
        "c0": 0.0,
        "sc": sc,
        "h0": h0,
        "sh": rel * h0,
        "scale": 2 * gain * U_MAX / span_per_scale,
        "width_fraction": frac,
        "gain_nm_per_v": gain,
    }


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


def fine_drive(u, oversample: int) -> np.ndarray:
    """The drive between its samples: linear interpolation, ``oversample`` steps per sample."""
    n = u.shape[0]
    tf = np.arange((n - 1) * oversample + 1) / oversample
    return np.stack([np.interp(tf, np.arange(n), u[:, i]) for i in range(u.shape[1])], axis=1)


def wander_parameters(wander, level) -> dict:
    """A drift's wander as ``{"kind", "sigma", "tau_s"}``: ``wander`` a kind of :data:`WANDERS`
    (its size at ``level``, :data:`OU_TAU_S`) or a dict that sets any of them."""
    w = wander if isinstance(wander, dict) else {"kind": wander}
    sigma = w.get("sigma", WANDERS[w["kind"]][LEVELS.index(level)] if level in LEVELS else None)
    return {"kind": w["kind"], "sigma": sigma, "tau_s": w.get("tau_s", OU_TAU_S)}


def case_wanders(t, wander: dict, seed: int) -> np.ndarray:
    """The two axes' wanders (T, 2) nm of a drift case of ``seed`` (``wander``: ``kind``,
    ``sigma``, ``tau_s``), drawn in turn from the seed's stream 3."""
    rng = np.random.default_rng([seed, 3])
    return np.stack(
        [drift_wander(t, wander["kind"], wander["sigma"], wander["tau_s"], rng) for _ in range(2)], 1
    )


def case_noise(shape, seed: int) -> np.ndarray:
    """A case's white noise (``NOISE_NM`` rms), drawn from the seed's stream 2."""
    return noise(shape, np.random.default_rng([seed, 2]))


def make_case(
    effect,
    level,
    seed: int,
    hysteresis: str = "pi",
    drive=None,
    magnitude=None,
    oversample=OVERSAMPLE,
    wander=None,
    relays=100,
) -> dict:
    """One record: ``t`` (T,) s, ``u`` (T, 2) V, ``d`` (T, 2) nm and ``truth`` (every parameter).

    ``effect`` None: a control. ``level`` in :data:`LEVELS` picks the magnitude (or pass
    ``magnitude``). ``hysteresis``: "pi" or "preisach" (asymmetry always uses "pi").
    ``drive``: ``(t, u)``, default :data:`DRIVE`. ``wander`` (a drift only): ``None``, a kind of
    :data:`WANDERS` at the level's size, or ``{"kind": ..., "sigma": ..., "tau_s": ...}``.
    ``relays``: a Preisach truth's grid, ``relays x relays`` cells over ``U_RANGE``, or ``None``
    for its density continuous over the plane (:func:`preisach_continuous`): the same scanner
    with less switching roughness, or none, the noise and every other draw the same.
    """
    if effect is not None and effect not in EFFECTS:
        raise ValueError(f"unknown effect {effect!r}; known: {EFFECTS}")
    if hysteresis not in ("pi", "preisach"):
        raise ValueError(f"hysteresis must be 'pi' or 'preisach', got {hysteresis!r}")
    if effect == "asymmetry":
        hysteresis = "pi"
    t, u = DRIVE if drive is None else drive
    dt = float(t[1] - t[0]) / oversample
    uf = fine_drive(u, oversample)
    if effect is not None and magnitude is None:
        magnitude = MAGNITUDES[effect][LEVELS.index(level)]
    r_hyst, r_eff = (np.random.default_rng([seed, k]) for k in range(2))
    axes = []
    h = np.empty(uf.shape)
    for i in range(2):
        if hysteresis == "pi":
            p = _pi_truth(r_hyst)
            h[:, i] = pi_operator(uf[:, i], p["radii"], p["weights"])
        else:
            p = _preisach_truth(r_hyst)
            args = (uf[:, i], p["c0"], p["sc"], p["h0"], p["sh"], p["scale"])
            h[:, i] = preisach_continuous(*args) if relays is None else preisach_operator(*args, n=relays)
        axes.append(p)
    half_range = np.array([p["gain_nm_per_v"] * U_MAX for p in axes])
    offsets = r_hyst.uniform(-100, 100, 2)
    jitter = lambda: r_eff.uniform(0.8, 1.2)
    params = {}
    d = h
    if effect == "asymmetry":
        params["a"] = [magnitude * jitter(), magnitude * jitter()]
        d = np.stack([asymmetry(d[:, i], params["a"][i], 0.0, half_range[i]) for i in range(2)], 1)
    elif effect == "rate_dependence":
        params["tau_s"] = magnitude * jitter()
        d = rate_dependence(d, params["tau_s"], dt)
    elif effect == "creep":
        params["gamma_per_decade"] = magnitude * jitter()
        d = creep(d, params["gamma_per_decade"], dt)
    elif effect == "coupling":
        params["c"] = magnitude * jitter()
        d = coupling(d, params["c"])
    elif effect == "bow":
        params["b_per_nm"] = magnitude * jitter()
        d = bow(d, params["b_per_nm"])
    elif effect == "vibration":
        params["f0_hz"], params["zeta"] = magnitude * jitter(), VIBRATION_ZETA * jitter()
        d = vibration(d, params["f0_hz"], params["zeta"], dt)
    d = d[::oversample] + offsets  # the samples at t
    if effect == "drift":
        params["v_nm_per_s"] = [magnitude * jitter(), -0.7 * magnitude * jitter()]
        d = drift(d, t, params["v_nm_per_s"])
        if wander is not None:
            params["wander"] = wander_parameters(wander, level)
            d = d + case_wanders(t, params["wander"], seed)
    d = d + case_noise(d.shape, seed)
    truth = {
        "effect": effect,
        "level": level,
        "magnitude": magnitude,
        "seed": seed,
        "hysteresis": hysteresis,
        "axes": axes,
        "offsets_nm": offsets,
        "effect_parameters": params,
        "noise_nm": NOISE_NM,
        "fs_hz": 1.0 / (dt * oversample),
        "oversample": oversample,
        "order": "hysteresis, asymmetry, rate lag, creep, coupling, bow, vibration, offset, drift, noise",
    }
    return {"t": t, "u": u, "d": d, "truth": _jsonable(truth)}


def cases(seeds: int = 5, controls: int = 20) -> list:
    """Case descriptors, seed-round by seed-round (a partial run stays balanced).

    Every effect x level x seed, plus ``controls``. Asymmetry cases: truth and nominal "pi"
    (same class). In the others the nominal class differs from the truth's in as many cases as
    make the total half different (Bresenham over the list); different: truth preisach with
    nominal pi or truth pi with nominal preisach, alternately; same: pi/pi and preisach/preisach
    alternately.
    """
    rounds = max(seeds, -(-controls // 4))
    raw = []
    for s in range(rounds):
        raw += [(None, "control", 0.0, 10_000 + c) for c in range(4 * s, min(4 * s + 4, controls))]
        if s < seeds:
            raw += [
                (e, lv, MAGNITUDES[e][j], 1000 * i + 10 * j + s)
                for i, e in enumerate(EFFECTS)
                for j, lv in enumerate(LEVELS)
            ]
    free = [c for c in raw if c[0] != "asymmetry"]
    n_diff = min(len(raw) // 2, len(free))
    out, k, n_d, n_s = [], 0, 0, 0
    for effect, level, m, seed in raw:
        if effect == "asymmetry":
            truth, nominal = "pi", "pi"
        else:
            different = (k + 1) * n_diff // len(free) > k * n_diff // len(free)
            k += 1
            if different:
                truth, nominal = ("preisach", "pi") if n_d % 2 == 0 else ("pi", "preisach")
                n_d += 1
            else:
                truth = "pi" if n_s % 2 == 0 else "preisach"
                nominal = truth
                n_s += 1
        out.append(
            {
                "effect": effect,
                "level": level,
                "magnitude": m,
                "seed": seed,
                "truth_hysteresis": truth,
                "nominal_kind": nominal,
            }
        )
    return out


#: Four records described from another generator, each of which a diagnosis from a symmetric PI
#: nominal got wrong ("no significant unmodelled effect"): a drift of 0.70 nm/s with an
#: Ornstein-Uhlenbeck wander (sigma 31.5 nm, tau 20 s) under a PI and under a Preisach truth, and
#: creep of 2.1 % per decade under two Preisach truths. Their drive is not described; they run
#: here on this generator's drive over :data:`REPORTED_DRIVE` (60 s at 100 Hz), over which the
#: wander spreads about as far as it did there (held-out gaps of 45-60 nm on a later split).
REPORTED_CASES = {
    "drift with an OU wander, PI truth": {
        "effect": "drift",
        "level": "middle",
        "seed": 47_001,
        "hysteresis": "pi",
        "magnitude": 0.7,
        "wander": {"kind": "ou", "sigma": 31.5, "tau_s": 20.0},
    },
    "drift with an OU wander, Preisach truth": {
        "effect": "drift",
        "level": "middle",
        "seed": 47_002,
        "hysteresis": "preisach",
        "magnitude": 0.7,
        "wander": {"kind": "ou", "sigma": 31.5, "tau_s": 20.0},
    },
    "creep 2.1 %/decade, Preisach truth": {
        "effect": "creep",
        "level": "middle",
        "seed": 47_003,
        "hysteresis": "preisach",
        "magnitude": 0.021,
    },
    "creep 2.1 %/decade, another Preisach truth": {
        "effect": "creep",
        "level": "middle",
        "seed": 47_004,
        "hysteresis": "preisach",
        "magnitude": 0.021,
    },
}
REPORTED_DRIVE = (60.0, 100.0)  # s, Hz


def wandering_cases(seeds: int = 12, controls: int = 20) -> list:
    """Case descriptors of effects that wander or creep, seed-round by seed-round: a drift with a
    random-walk wander, a drift with an Ornstein-Uhlenbeck wander (``wander``: :data:`WANDERS`),
    and creep, at every level, plus ``controls`` (four a round). Half of the cases have a Preisach
    truth, half a PI one; the nominal is the symmetric PI (the diagnosis's default) on every
    case, so half the cases carry the other hysteresis class."""
    kinds = (("drift", "walk"), ("drift", "ou"), ("creep", None))
    out, k = [], 0
    for s in range(max(seeds, -(-controls // 4))):
        round_ = [(None, None, "control", 0.0, 20_000 + c) for c in range(4 * s, min(4 * s + 4, controls))]
        if s < seeds:
            round_ += [
                (e, w, lv, MAGNITUDES[e][j], 30_000 + 1000 * i + 100 * j + s)
                for i, (e, w) in enumerate(kinds)
                for j, lv in enumerate(LEVELS)
            ]
        for effect, wander, level, m, seed in round_:
            truth = ("pi", "preisach")[k % 2]
            k += 1
            out.append(
                {
                    "effect": effect,
                    "wander": wander,
                    "level": level,
                    "magnitude": m,
                    "seed": seed,
                    "truth_hysteresis": truth,
                    "nominal_kind": "pi",
                }
            )
    return out


def equal_weight_pi_control(seed: int, plays: int = 16, duration: float = 20.0, fs: float = 100.0) -> dict:
    """A control (no effect) whose PI truth has ``plays`` equal-weight plays above a linear one, at
    radii ``r_k = k 20 V / (2 plays)`` over a +-10 V range: a loop 15 % of its 10 um travel wide
    (the equal weights ``b = 0.15 T / sum_k min(2 r_k, 20 - 2 r_k)`` above ``w_0 = (T - b sum_k
    (20 - 2 r_k)) / 20`` with ``T = 10 um``), each weight x U(0.9, 1.1), plus 2 nm white noise.
    Its kinks lie where a nominal PI's evenly spread plays do not. The drive: per axis
    ``9 V e(t) sin(phi(t))``, envelope ``e = 0.55 + 0.45 cos(2 pi t / 10 s)`` (y: half a period
    later), frequency ``phi' / 2 pi`` swept 0.2-1.8 Hz (x) and 0.3-1.3 Hz (y): loops of every size.
    """
    t = np.arange(int(round(duration * fs))) / fs
    env = lambda s: 0.55 + 0.45 * np.cos(2 * np.pi * s / 10.0)
    phase = lambda f0, df, period: (
        2 * np.pi * (f0 * t + df * period / (2 * np.pi) * (1 - np.cos(2 * np.pi * t / period)))
    )
    u = U_MAX * np.stack(
        [env(t) * np.sin(phase(1.0, 0.8, 7.0)), env(t + 5.0) * np.sin(phase(0.8, 0.5, 9.0))], -1
    )
    radii = np.arange(plays) * 20.0 / (2 * plays)
    r, travel = radii[1:], 10_000.0
    b = 0.15 * travel / np.minimum(2 * r, 20.0 - 2 * r).sum()
    w = np.r_[(travel - b * (20.0 - 2 * r).sum()) / 20.0, np.full(plays - 1, b)]
    rng = np.random.default_rng(seed)
    d = np.stack([pi_operator(u[:, k], radii, w * rng.uniform(0.9, 1.1, plays)) for k in range(2)], -1)
    return {"t": t, "u": u, "d": d + noise(d.shape, rng)}
