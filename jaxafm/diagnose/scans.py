"""Gap diagnosis on trace/retrace images of a 1-D grating at two or more scan speeds.

What an actuator record cannot show -- the z-feedback's lag and the tip's shape --
an image set can: both change the *shape* of every edge. For each edge of each
row, the sub-pixel positions where the profile crosses the levels ``LEVELS`` of
its step (fractions of the row's 10-90 % contrast) are the data (nm). They are
modelled as

    x_nom = X - D_d(x_nom) + o [retrace] + (k / g_d(x_nom)) S_l(theta; kind, d, dt) + [linear candidate terms],

``X = phase_kind + n p`` the edge's place on the grating (pitch ``p``, nominal nm),
``D_d = sum_{j=2,3} c_{j,d} P_j(s)`` the fast-axis nonlinearity of the trace or
retrace branch ``d`` and ``o`` the loop's offset between them (the nominal
scanner: rate-independent hysteresis, the same at every speed), ``k = p /
pitch_nm`` the calibration scale, ``g_d = 1 + D_d'`` the local gain, and
``S_l`` where the grating's known edge (a ramp ``edge_width_nm`` wide, depth
from the image) crosses level ``l`` once imaged: dilated by the tip
(candidate ``tip``: a sphere-capped cone of fitted apex radius and known half
angle), sampled at the pixel pitch, recorded through a first-order lag along
the scan direction (candidate ``feedback_lag``: time constant ``tau``, one way
in trace, the other in retrace, ``tau / dt`` samples at sample time ``dt``),
averaged over where the pixels fall on the edge. The nominal model has an
ideal tip and feedback. Linear candidates: ``rate_dependence`` (the scanner's
position lag, ``+- v tau_r``, ``v`` the nominal scan speed), ``coupling`` (skew
``x += s y``) and ``bow`` (``x += b P_2(t)``).

Training: the first ``train_fraction`` of every pair's rows; held out: the later
rows (a later time window; the speed dependence needs every speed in training).
Gap: the systematic misfit on the held-out rows, the rms over the cells (pair,
trace or retrace, rising or falling, level) of the cell's mean crossing residual
(nm), what is the same for every edge of a kind, with the white noise averaged
out; the per-crossing rms is reported beside it. Tip radius and lag are fitted
by a scalar search (log grid, then bounded refinement), the rest by linear least
squares; BIC, significance, ranking and verdict are the core's (:mod:`jaxafm.diagnose.core`).
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from numpy.polynomial import legendre
from scipy.optimize import minimize, minimize_scalar
from scipy.signal import lfilter

from ..config import ScanSample  # the grating and tip of a scan set: its config schema
from ..identify.features import check_image, edge_crossings
from ..identify.line_grating import MIN_ROWS, GratingEdges
from ..identify.projection import project_out
from ..instrument.samples import Tip
from ..model.effects import FeedbackAsymmetry
from .core import DataKind, Diagnosis, Findings, Fit, Rules, diagnose

LEVELS = (0.1, 0.3, 0.5, 0.7, 0.9)
CANDIDATES = ("rate_dependence", "feedback_lag", "feedback_asymmetry", "tip", "coupling", "bow")
ASYMMETRY_RATIOS = (0.01, 0.5)  # tau_rise / tau_fall searched: a parachute falls at least 2x slower
LATTICE_CHORD = 0.7  # lattice rows used: a feature chord >= this fraction of the longest (near centres)
LATTICE_DEPTH = 0.8  # ... and a contrast >= this fraction of the deepest rows'
BAND = 0.2  # an edge: the profile passes from below mid - BAND c to above mid + BAND c (c the contrast)
PHASES = 8  # where the pixels fall on an edge, averaged
FINE_NM = 0.25  # grid of the modelled edge profile
TIP_RADII_NM = (0.5, 500.0)  # the tip search's bounds
LAG_SAMPLES = (0.01, 200.0)  # the feedback-lag search's bounds, in samples of the fastest pair


@dataclasses.dataclass(frozen=True)
class ScanPair:
    """Trace and retrace (lines, pixels) nm of a 1-D grating, both left to right, row 0 first
    in time; ``pixel_size`` (dx, dy) nm; ``sample_time_s`` between two pixels of a line."""

    trace: np.ndarray
    retrace: np.ndarray
    pixel_size: tuple
    sample_time_s: float
    name: str = "scan"

    @property
    def speed_nm_s(self) -> float:
        return self.pixel_size[0] / self.sample_time_s


# ----------------------------------------------------------------------------- data


@dataclasses.dataclass(frozen=True)
class RowEdges:
    """The edges of one image (:func:`row_edges`): ``edges`` (a ``GratingEdges``: row, nominal
    x and y nm, rising, line index), per image row the levels ``lo``, ``hi`` (nm) the crossing
    levels are fractions of (NaN on rows not used), and the pitch (nominal nm) the indices count."""

    edges: GratingEdges
    lo: np.ndarray
    hi: np.ndarray
    pitch_nm: float


def row_edges(z, pixel_size, name: str = "image", kind: str = "lines", pitch_nm=None) -> RowEdges:
    """The rising and falling edges of every row of an image of a 1-D grating (``kind="lines"``,
    lines along the slow axis) or of a 2-D lattice of pits or pillars (``"lattice"``), each with
    an index that is the same for the same feature in every row.

    No full periods are needed: a row counts when it shows an edge of each kind. Each low
    region (a falling edge, then a rising one) has a centre; the centres of the image lie on a
    lattice of the pitch (the median spacing of neighbouring centres in a row; ``pitch_nm``
    nominal nm where no row has two), and each edge's index is its centre's place on it. Lines:
    every row is used, its levels the 10th and 90th percentiles (as ``features.edge_crossings``).
    Lattice: a row between the features' rows crosses none and a row grazing them sees shallow
    or stretched walls, so only the rows with a contrast (2nd to 98th percentile) of at least
    ``LATTICE_DEPTH`` of the deepest rows' and a mean low-region width of at least
    ``LATTICE_CHORD`` of the widest row's are used, their levels those percentiles.

    Raises:
        ValueError: for an image that is not 2-D and finite, a non-positive pixel size, or
            fewer than ``MIN_ROWS`` rows with edges of both kinds, with what to change.
    """
    z = check_image(np.asarray(z, dtype=float), name)
    dx, dy = (float(p) for p in np.broadcast_to(np.asarray(pixel_size, dtype=float), (2,)))
    if not (dx > 0 and dy > 0):
        raise ValueError(f"{name}: pixel size must be > 0 nm on both axes, got {pixel_size}")
    lattice = kind == "lattice"
    q = (2, 98) if lattice else (10, 90)
    lo, hi = np.percentile(z, q, axis=1)
    use = np.ones(len(z), bool)
    if lattice:
        contrast = hi - lo
        use = contrast >= LATTICE_DEPTH * np.percentile(contrast, 95)
    rows = [
        edge_crossings(z[r], BAND, (lo[r], hi[r])) if use[r] else (np.empty(0), np.empty(0, bool))
        for r in range(len(z))
    ]
    both = np.array([r.any() and not r.all() for _, r in rows])
    if lattice and both.any():  # rows near the features' centres: their low regions are widest
        width = np.full(len(z), np.nan)
        for j in np.flatnonzero(both):
            w = _low_regions(*rows[j])[1]
            width[j] = np.mean(w) if w.size else np.nan
        wide = width >= LATTICE_CHORD * np.nanpercentile(width, 95)
        both &= wide
    if both.sum() < MIN_ROWS:
        raise ValueError(
            f"{name}: only {int(both.sum())} scan line(s) show both rising and falling edges"
            + (" across the lattice's features" if lattice else "")
            + f"; the fit needs at least {MIN_ROWS}: "
            + (
                "scan more lines, or check the lattice's pitch and that the image shows its pits or pillars"
                if lattice
                else "check that the lines run along the slow axis (rows), or scan more lines"
            )
        )
    centres = {j: _centres(*rows[j]) for j in np.flatnonzero(both)}
    gaps = np.concatenate([np.diff(np.unique(c)) for c in centres.values()])
    if gaps.size:
        p0 = float(np.median(gaps))
    elif pitch_nm is not None:
        p0 = float(pitch_nm) / dx
    else:
        raise ValueError(
            f"{name}: no row shows two features, so the pitch cannot be measured: give the "
            "grating's pitch_nm, or scan a wider area"
        )
    allc = np.concatenate(list(centres.values()))
    phase = p0 / (2 * np.pi) * np.angle(np.mean(np.exp(2j * np.pi * allc / p0)))
    found = []
    for j, c in centres.items():
        x, r = rows[j]
        found.append((np.full(x.size, j), x, r, np.round((c - phase) / p0).astype(int)))
    row, x, rising, index = (np.concatenate(v) for v in zip(*found))
    for t in (True, False):
        index[rising == t] -= index[rising == t].min()
    lo[~both], hi[~both] = np.nan, np.nan
    e = GratingEdges(row, x * dx, row * dy, rising, index, z.shape, (dx, dy))
    return RowEdges(e, lo, hi, p0 * dx)


def _low_regions(x: np.ndarray, rising: np.ndarray) -> tuple:
    """(centres, widths) px of a row's low regions: a falling edge followed by a rising one."""
    k = np.flatnonzero(~rising[:-1] & rising[1:])
    return 0.5 * (x[k] + x[k + 1]), x[k + 1] - x[k]


def _centres(x: np.ndarray, rising: np.ndarray) -> np.ndarray:
    """Per edge of a row, the centre (px) of its low region; an edge with no partner in the row
    (at either end) is put half the row's median low-region width beyond it."""
    c, w = _low_regions(x, rising)
    half = 0.5 * (np.median(w) if w.size else 0.0)
    out = np.where(rising, x - half, x + half)
    k = np.flatnonzero(~rising[:-1] & rising[1:])
    out[k], out[k + 1] = c, c
    return out


@dataclasses.dataclass(frozen=True)
class Crossings:
    """Level crossings of edges, flat arrays (one entry per edge and level).

    Attributes:
        x: where the profile crosses the level (nominal nm).
        level: the level, a fraction of the row's contrast (:data:`LEVELS`).
        pair: the pair's number (``pairs`` slowest first).
        retrace: True in the retrace image.
        row: the image row.
        y: the row's nominal y (nm).
        index: the edge's line index (the same line in every image).
        rising: True on a rising edge.
    """

    x: np.ndarray
    level: np.ndarray
    pair: np.ndarray
    retrace: np.ndarray
    row: np.ndarray
    y: np.ndarray
    index: np.ndarray
    rising: np.ndarray


def crossings(pairs, levels=LEVELS, kind: str = "lines", pitch_nm=None) -> Crossings:
    """Level crossings of every edge of every image of ``pairs`` (:class:`Crossings`).

    A line keeps its index across the images: each image's indices are shifted by the whole
    periods that bring its edges nearest to the reference image's -- the trace of the same pair
    for a retrace, the same direction of the pair before (``pairs`` slowest first) otherwise.
    An image shifted by more than half a period against its reference is misindexed.
    ``kind``, ``pitch_nm``: :func:`row_edges`.
    """
    edges = {}
    for p, pair in enumerate(pairs):
        for retrace, z in ((False, pair.trace), (True, pair.retrace)):
            e = row_edges(
                z, pair.pixel_size, f"{pair.name} ({'retrace' if retrace else 'trace'})", kind, pitch_nm
            )
            ref = edges.get((p - 1, retrace) if p else (0, False))
            edges[p, retrace] = e if ref is None else _align(e, ref)
    cols = {k: [] for k in ("x", "level", "pair", "retrace", "row", "y", "index", "rising")}
    for (p, retrace), re in edges.items():
        e = re.edges
        z = pairs[p].retrace if retrace else pairs[p].trace
        x = edge_levels(np.asarray(z, float), re, levels, kind) * e.pixel_size[0]
        ok = np.isfinite(x)
        for k, v in (("row", e.row), ("y", e.y_nm), ("index", e.index), ("rising", e.rising)):
            cols[k].append(np.repeat(v, len(levels))[ok.ravel()])
        cols["x"].append(x[ok])
        cols["level"].append(np.tile(levels, len(e.row))[ok.ravel()])
        cols["pair"].append(np.full(ok.sum(), p))
        cols["retrace"].append(np.full(ok.sum(), retrace))
    return Crossings(**{k: np.concatenate(v) for k, v in cols.items()})


def _align(re: RowEdges, ref: RowEdges) -> RowEdges:
    """``re`` with each kind's line indices shifted to match ``ref``'s (see :func:`crossings`)."""
    e, r = re.edges, ref.edges
    index = e.index.copy()
    pitch = ref.pitch_nm
    for rising in (True, False):
        a, b = e.rising == rising, r.rising == rising
        phase = lambda g, s: np.median(g.x_nm[s] - g.index[s] * pitch)
        index[a] += int(np.round((phase(e, a) - phase(r, b)) / pitch))
    return dataclasses.replace(re, edges=dataclasses.replace(e, index=index))


def edge_levels(z: np.ndarray, re: RowEdges, levels, kind: str = "lines") -> np.ndarray:
    """(edges, levels) px: per edge, the mean crossing of each level of its row's ``lo`` to
    ``hi`` within a quarter period (lines), or within half the way to its neighbouring edges in
    the row (lattice: a pit's or pillar's walls may be closer than a quarter period)."""
    e = re.edges
    out = np.full((len(e.row), len(levels)), np.nan)
    centre = e.x_nm / e.pixel_size[0]
    quarter = 0.25 * re.pitch_nm / e.pixel_size[0]
    for r in np.unique(e.row):
        row = z[r]
        lo, hi = re.lo[r], re.hi[r]
        mine = np.flatnonzero(e.row == r)
        order = mine[np.argsort(centre[mine])]
        c = centre[order]
        if kind == "lattice":
            left = np.concatenate([[0.0], 0.5 * (c[1:] + c[:-1])])
            right = np.concatenate([0.5 * (c[1:] + c[:-1]), [len(row) - 1.0]])
        else:
            left, right = c - quarter, c + quarter
        for i, a0, b0, ci in zip(order, left, right, c):
            a, b = _passage(row, a0, b0, ci, e.rising[i])
            seg = row[a : b + 1]
            for j, lv in enumerate(levels):
                s = seg - (lo + lv * (hi - lo))
                k = np.flatnonzero((s[:-1] > 0) != (s[1:] > 0))
                if k.size:
                    out[i, j] = np.mean(a + k + s[k] / (s[k] - s[k + 1]))
    return out


def _passage(row: np.ndarray, a0: float, b0: float, centre: float, rising: bool) -> tuple:
    """Sample indices (a, b) of an edge's own passage within the window [a0, b0] px around its
    centre: from the window's lowest (rising; highest: falling) sample before the centre to its
    highest (lowest) after it, so that the tail of a neighbouring edge that has not settled
    (a slow fall before a rise) is not counted as a crossing of this one."""
    a, b = int(max(np.floor(a0), 0)), int(min(np.ceil(b0), len(row) - 1))
    m = int(min(max(round(centre), a), b))
    low, high = (np.argmin, np.argmax) if rising else (np.argmax, np.argmin)
    return a + int(low(row[a : m + 1])), m + int(high(row[m : b + 1]))


# ----------------------------------------------------------------------------- edge shape


def edge_shape(
    grating: ScanSample,
    depth: float,
    dx: float,
    levels,
    radius: Optional[float] = None,
    lag_samples: float = 0.0,
    asymmetry_samples: Optional[tuple] = None,
) -> np.ndarray:
    """Crossings (2 kinds, 2 directions, levels) nm of the imaged ramp edge relative to its centre.

    Kinds: rising, falling; directions: trace (samples taken with x rising), retrace. The ramp
    is dilated by the tip (``radius`` nm, or none), sampled every ``dx`` nm, passed through
    ``z_n = a z_{n-1} + (1 - a) h_n`` (``a = exp(-1 / lag_samples)``, as ``effects.lowpass``)
    in the scan direction, or through ``effects.FeedbackAsymmetry`` (the simulator's module)
    with ``asymmetry_samples = (tau_rise, tau_fall)`` in samples, and its linear-interpolation
    crossings averaged over :data:`PHASES`.
    """
    w = grating.edge_width_nm
    reach = (
        0.0
        if radius is None
        else min(3 * radius + depth * np.tan(np.deg2rad(grating.tip_half_angle_deg)), 400.0)
    )
    slowest = lag_samples if asymmetry_samples is None else max(lag_samples, *asymmetry_samples)
    span = w / 2 + reach + 12 * slowest * dx + 4 * dx + 20
    xi = FINE_NM * np.arange(-int(span / FINE_NM), int(span / FINE_NM) + 1)  # 0 on the grid
    out = np.empty((2, 2, len(levels)))
    for kind, sign in ((0, 1.0), (1, -1.0)):
        h = depth * np.clip(sign * xi / w + 0.5, 0.0, 1.0)
        if radius is not None:
            h = _dilate(h, radius, np.deg2rad(grating.tip_half_angle_deg), reach)
        for d in (0, 1):
            if asymmetry_samples is not None:
                out[kind, d] = _asymmetric_crossings(xi, h, depth, dx, asymmetry_samples, d, levels)
                continue
            out[kind, d] = np.mean(
                [
                    _crossings(xi, h, depth, dx, (m + 0.5) / PHASES * dx, lag_samples, d, levels)
                    for m in range(PHASES)
                ],
                axis=0,
            )
    return out


@eqx.filter_jit
def _follow(feedback: FeedbackAsymmetry, v: jax.Array) -> jax.Array:
    """The heights ``feedback`` records of the profiles ``v`` (N, L), sampled at t = 0, 1, ..."""
    t = jnp.arange(v.shape[1], dtype=float)
    return jax.vmap(lambda row: feedback.run(row, t, feedback.initial_state(row[0]), t[0])[0])(v)


def _asymmetric_crossings(xi, h, depth, dx, taus, retrace, levels) -> np.ndarray:
    """As :func:`_crossings` averaged over the phases, the profiles recorded through
    ``FeedbackAsymmetry(*taus)`` (samples) in the scan direction, all phases in one call."""
    seqs = [np.interp(np.arange(xi[0] + (m + 0.5) / PHASES * dx, xi[-1], dx), xi, h) for m in range(PHASES)]
    n = max(len(q) for q in seqs)
    size = 1 << int(np.ceil(np.log2(n)))  # few shapes, few compilations
    v = np.empty((PHASES, size))
    for m, q in enumerate(seqs):  # in time order; padded after the end with the last height
        q = q[::-1] if retrace else q
        v[m] = np.concatenate([q, np.full(size - len(q), q[-1])])
    z = np.asarray(_follow(FeedbackAsymmetry(jnp.asarray(taus[0]), jnp.asarray(taus[1])), jnp.asarray(v)))
    out = np.empty((PHASES, len(levels)))
    for m, q in enumerate(seqs):
        zm = z[m, : len(q)]
        zm = zm[::-1] if retrace else zm
        xs = xi[0] + (m + 0.5) / PHASES * dx + dx * np.arange(len(q))
        out[m] = _level_crossings(xs, zm, depth, dx, levels)
    return out.mean(axis=0)


def _level_crossings(xs, v, depth, dx, levels) -> np.ndarray:
    out = np.empty(len(levels))
    for j, lv in enumerate(levels):
        s = v - lv * depth
        k = np.flatnonzero((s[:-1] > 0) != (s[1:] > 0))
        out[j] = np.mean(xs[k] + dx * s[k] / (s[k] - s[k + 1])) if k.size else np.nan
    return out


def _dilate(h: np.ndarray, radius: float, half_angle: float, reach: float) -> np.ndarray:
    """``max_q [h(xi + q) - tip(|q|)]`` on the fine grid (a grating is the same along y)."""
    q = np.arange(-int(reach / FINE_NM), int(reach / FINE_NM) + 1)
    lift = np.asarray(
        Tip(jnp.asarray(radius), jnp.asarray(half_angle)).profile(jnp.asarray(np.abs(q) * FINE_NM))
    )
    pad = np.pad(h, len(q) // 2, mode="edge")
    out = np.full_like(h, -np.inf)
    for j, lj in zip(q, lift):
        np.maximum(out, pad[len(q) // 2 + j : len(q) // 2 + j + len(h)] - lj, out=out)
    return out


def _crossings(xi, h, depth, dx, phase, lag_samples, retrace, levels) -> np.ndarray:
    xs = np.arange(xi[0] + phase, xi[-1], dx)
    v = np.interp(xs, xi, h)
    if lag_samples > 0:
        a = np.exp(-1.0 / lag_samples)
        seq = v[::-1] if retrace else v
        z = lfilter([1 - a], [1, -a], seq, zi=[a * seq[0]])[0]
        v = z[::-1] if retrace else z
    return _level_crossings(xs, v, depth, dx, levels)


# ----------------------------------------------------------------------------- fits


NOMINAL = (
    "phase_rise",
    "phase_fall",
    "pitch",
    "c2_trace",
    "c3_trace",
    "c2_retrace",
    "c3_retrace",
    "offset_retrace",
)


@dataclasses.dataclass(frozen=True, eq=False)
class ScanFit(Fit):
    """A :class:`~jaxafm.diagnose.core.Fit` of a scan set's crossings; ``residual`` (crossings,)
    nm; ``heldout_gap_nm`` the systematic held-out misfit (module docstring).

    Attributes:
        theta: the linear coefficients by column name (nm; ``rate_dependence`` s).
        fitted: the candidate's own parameter (``tau_s``, ``tip_radius_nm``, ``coupling``,
            ``bow``; none for the nominal model).
        rss: the training residual sum of squares (nm^2).
        heldout_rms_nm: the rms held-out crossing residual, noise included (nm).
    """

    theta: dict
    fitted: dict
    rss: float
    heldout_rms_nm: float

    def shown(self) -> dict:
        return {"fitted": self.fitted}

    def summary(self) -> dict:
        return {
            "train_rms_nm": self.train_rms_nm,
            "heldout_gap_nm": self.heldout_gap_nm,
            "heldout_rms_nm": self.heldout_rms_nm,
            "parameters": self.parameters,
            "fitted": self.theta,
        }


@dataclasses.dataclass(frozen=True, eq=False)
class ScanSet(DataKind):
    """Trace/retrace pairs at two or more scan speeds as a diagnosis's data: the crossings and
    what the model needs of them, flat over edges and levels.

    Attributes:
        crossings: the edges' level crossings (:func:`crossings`).
        pairs: the :class:`ScanPair` s, slowest first.
        grating: what is known of the grating and the tip.
        depth: the edges' depth (nm), the median 10-90 % contrast of the rows.
        train: (crossings,) True on the crossings of the training rows.
        scale: the calibration scale ``k = p / pitch_nm`` of the nominal fit without edge shape.
        groups: lattice: (crossings,) the scan row of each crossing, the same number for the
            same row in every image where all images have the same rows; each row's feature
            width and wall slope are its own (:func:`_within`). ``None`` for a 1-D grating.
    """

    crossings: Crossings
    pairs: list
    grating: ScanSample
    depth: float
    train: np.ndarray
    scale: float = 1.0
    groups: Optional[np.ndarray] = None

    name = "scans"
    gap_label = "held-out systematic gap [nm]"
    model = (
        "hysteresis-only scanner (a nonlinearity per branch and the loop offset), ideal tip "
        "and feedback, the grating's known edge"
    )
    label = "hysteresis only, ideal tip and feedback"
    tries = CANDIDATES

    @classmethod
    def split_off(cls, pairs, grating: ScanSample, train_fraction: float) -> ScanSet:
        """The crossings of ``pairs`` (:class:`ScanPair`), the first ``train_fraction`` of every
        pair's rows to train on, and the calibration scale.

        Raises:
            ValueError: with fewer than two pairs or two scan speeds, or fewer than 50 crossings
                in either part.
        """
        if len(pairs) < 2:
            raise ValueError(
                f"a scan-set diagnosis needs trace/retrace pairs at two or more scan speeds, got "
                f"{len(pairs)}: add a pair scanned at another line rate"
            )
        pairs = sorted(pairs, key=lambda p: p.speed_nm_s)
        speeds = [p.speed_nm_s for p in pairs]
        if len(set(np.round(speeds, 6))) < 2:
            raise ValueError(
                f"all pairs have the scan speed {speeds[0]:.4g} nm/s; telling a lag from hysteresis needs "
                "two speeds: give a pair scanned at another line rate"
            )
        f = crossings(pairs, kind=grating.kind, pitch_nm=grating.pitch_x_nm)
        rows = np.array([p.trace.shape[0] for p in pairs])[f.pair]
        train = f.row < np.round(train_fraction * rows)
        if train.sum() < 50 or (~train).sum() < 50:
            raise ValueError(
                f"{int(train.sum())} training and {int((~train).sum())} held-out crossings at "
                f"train_fraction={train_fraction}: too few to split; scan more lines or change train_fraction"
            )
        q = (2, 98) if grating.kind == "lattice" else (10, 90)
        contrast = np.concatenate([np.subtract(*np.percentile(p.trace, q[::-1], axis=1)) for p in pairs])
        if grating.kind == "lattice":  # the rows across the features (those between show none)
            contrast = contrast[contrast >= LATTICE_DEPTH * np.percentile(contrast, 95)]
        data = cls(
            f, list(pairs), grating, float(np.median(contrast)), train, groups=_groups(f, pairs, grating)
        )
        scale = _solve(data, list(NOMINAL), np.zeros(len(f.x)), 1.0).theta["pitch"] / grating.pitch_x_nm
        return dataclasses.replace(data, scale=scale)

    @property
    def sign(self) -> np.ndarray:  # +1 trace, -1 retrace
        return np.where(self.crossings.retrace, -1.0, 1.0)

    def field(self) -> tuple:
        """Legendre coordinate ``s`` in [-1, 1] of each crossing across its pair's field, and ds/dx."""
        width = np.array([(p.trace.shape[1] - 1) * p.pixel_size[0] for p in self.pairs])[self.crossings.pair]
        return 2 * self.crossings.x / width - 1, 2 / width

    def linear_columns(self) -> dict:
        """Nominal and linear-candidate columns (the model's right side, without the edge shape)."""
        s, _ = self.field()
        f, re = self.crossings, self.crossings.retrace.astype(float)
        p2, p3 = (legendre.legval(s, np.eye(4)[j]) for j in (2, 3))
        rows = np.array([p.trace.shape[0] - 1 for p in self.pairs])[f.pair]
        t = 2 * f.row / np.maximum(rows, 1) - 1
        speed = np.array([p.speed_nm_s for p in self.pairs])[f.pair]
        return {
            "phase_rise": f.rising.astype(float),
            "phase_fall": (~f.rising).astype(float),
            "pitch": f.index.astype(float),
            "c2_trace": -p2 * (1 - re),
            "c3_trace": -p3 * (1 - re),
            "c2_retrace": -p2 * re,
            "c3_retrace": -p3 * re,
            "offset_retrace": re,
            "rate_dependence": self.sign * speed,
            "coupling": -f.y,
            "bow": -0.5 * (3 * t**2 - 1),
        }

    def fit_nominal(self) -> ScanFit:
        return _solve(self, list(NOMINAL), _shape(self, self.scale), self.scale)

    def fit_candidate(self, effect: str, nominal: ScanFit) -> ScanFit:
        """Nominal + ``effect``: tip radius and feedback lag by a scalar search (:func:`_search`),
        the linear candidates by least squares; ``fitted`` holds the candidate's parameter."""
        cols, scale = list(NOMINAL), self.scale
        if effect == "tip":
            radius, fit = _search(
                lambda r: _solve(self, cols, _shape(self, scale, radius=r), scale, 1), *TIP_RADII_NM
            )
            return dataclasses.replace(fit, fitted={"tip_radius_nm": radius})
        if effect == "feedback_asymmetry":
            dt = min(p.sample_time_s for p in self.pairs)
            (rise, fall), fit = _search_asymmetry(
                lambda r, f: _solve(self, cols, _shape(self, scale, asymmetry_s=(r, f)), scale, 2),
                LAG_SAMPLES[0] * dt,
                LAG_SAMPLES[1] * dt,
            )
            return dataclasses.replace(fit, fitted={"tau_rise_s": rise, "tau_fall_s": fall})
        if effect == "feedback_lag":
            dt = min(p.sample_time_s for p in self.pairs)
            tau, fit = _search(
                lambda v: _solve(self, cols, _shape(self, scale, tau_s=v), scale, 1),
                LAG_SAMPLES[0] * dt,
                LAG_SAMPLES[1] * dt,
            )
            return dataclasses.replace(fit, fitted={"tau_s": tau})
        fit = _solve(self, cols + [effect], _shape(self, scale), scale)
        key = "tau_s" if effect == "rate_dependence" else effect
        return dataclasses.replace(fit, fitted={key: fit.theta[effect]})

    def describe(self) -> dict:
        pairs = [
            {
                "name": p.name,
                "pixels": list(p.trace.shape),
                "pixel_size_nm": list(p.pixel_size),
                "sample_time_s": p.sample_time_s,
                "speed_nm_s": p.speed_nm_s,
            }
            for p in self.pairs
        ]
        what = "a 2-D lattice" if self.groups is not None else "a 1-D grating"
        return {
            "source": f"{len(pairs)} trace/retrace pairs of {what}",
            "kind": "scan set",
            "pairs": pairs,
            "grating": self.grating.model_dump(),
            "levels": list(LEVELS),
            "train_samples": int(self.train.sum()),
            "heldout_samples": int((~self.train).sum()),
            "counts": "edge-level crossings",
            "units": "nm (crossings, gaps), s",
        }

    def findings(self, diagnosis: Diagnosis) -> Findings:
        """Which levels, directions and speeds the nominal model misses."""
        nominal = diagnosis.nominal
        metrics = {
            "nominal_heldout_rms_nm": nominal.heldout_rms_nm,
            "train_crossings": int(self.train.sum()),
            "heldout_crossings": int((~self.train).sum()),
            "calibration_scale": self.scale,
            "edge_depth_nm": self.depth,
        }
        notes = [
            "- The gap is systematic: per (pair, direction, edge kind, level) the mean held-out residual, then their "
            f"rms; the nominal's per-crossing rms is {nominal.heldout_rms_nm:.3g} nm.",
        ]
        return Findings(metrics, self.where(nominal.residual), notes)

    def where(self, r: np.ndarray) -> list:
        """Sentences: which levels, directions and speeds the residual ``r`` (nm) misses."""
        cells = _cell_means(self, r, ~self.train)
        speeds = [p.speed_nm_s for p in self.pairs]
        by_level = np.sqrt(np.nanmean(cells**2, axis=(0, 1, 2)))
        by_pair = np.sqrt(np.nanmean(cells**2, axis=(1, 2, 3)))
        # trace minus retrace, rising edges at mid level: a lag moves the two apart in proportion to the speed
        split = cells[:, 0, 0, LEVELS.index(0.5)] - cells[:, 1, 0, LEVELS.index(0.5)]
        spread = np.moveaxis(
            (cells[..., -1] - cells[..., 0]) * [1, -1], -1, 0
        )  # (kind, pair, direction); > 0: wider
        return [
            f"By level, the systematic misfit is {', '.join(f'{v:.2g}' for v in by_level)} nm at "
            f"{', '.join(f'{100 * lv:.0f} %' for lv in LEVELS)} of the step (an edge shape the model lacks "
            "shows at some levels more than others).",
            f"By scan speed ({', '.join(f'{v / 1e3:.3g}' for v in speeds)} um/s): "
            f"{', '.join(f'{v:.2g}' for v in by_pair)} nm"
            f"; trace minus retrace at mid level (rising edges): {', '.join(f'{v:+.2g}' for v in split)} nm "
            "(a lag grows it with the speed, hysteresis does not).",
            f"Edges wider than modelled (10 % to 90 % crossing), rising / falling, trace: "
            f"{', '.join(f'{v:+.2g}/{w:+.2g}' for v, w in zip(spread[0, :, 0], spread[1, :, 0]))} nm; retrace: "
            f"{', '.join(f'{v:+.2g}/{w:+.2g}' for v, w in zip(spread[0, :, 1], spread[1, :, 1]))} nm per speed "
            "(a tip widens every edge alike; a feedback lag widens them more at higher speed).",
        ]

    def panels(self, axes: list, diagnosis: Diagnosis, findings: Findings) -> None:
        """The mean held-out crossing residual per level, speed, direction and edge kind, of the
        nominal model and with the verdict; the nominal residual at mid level across the field."""
        nominal, top = diagnosis.nominal, diagnosis.top
        shown = [("nominal", nominal.residual)] + ([(f"with {top.effect}", top.fit.residual)] if top else [])
        for a, (label, r) in zip(axes[:2], shown):
            cells = _cell_means(self, r, ~self.train)
            for p, pair in enumerate(self.pairs):
                for d, ls in ((0, "-"), (1, "--")):
                    for k, marker in ((0, "^"), (1, "v")):
                        a.plot(
                            100 * np.array(LEVELS),
                            cells[p, d, k],
                            ls,
                            marker=marker,
                            color=f"C{p}",
                            lw=1,
                            label=f"{pair.speed_nm_s / 1e3:.3g} um/s" if d == k == 0 else None,
                        )
            a.axhline(0, color="k", lw=0.5)
            a.set(
                xlabel="level [% of the step]",
                ylabel="mean held-out crossing residual [nm]",
                title=f"{label}\n- trace, -- retrace; ^ rising, v falling edges",
            )
            a.legend(fontsize=8)
        if top is None:
            axes[1].axis("off")
        a = axes[2]
        f, r = self.crossings, nominal.residual
        for d, name in ((False, "trace"), (True, "retrace")):
            sel = ~self.train & (f.retrace == d) & (f.level == 0.5)
            a.plot(f.x[sel] / 1e3, r[sel], ".", ms=2, alpha=0.4, label=name)
        a.set(
            xlabel="x (nominal) [um]",
            ylabel="residual at mid level [nm]",
            title="nominal, held-out rows, across the field",
        )
        a.legend(fontsize=8, markerscale=4)


def _shape(data: ScanSet, scale: float, radius=None, tau_s: float = 0.0, asymmetry_s=None) -> np.ndarray:
    """The edge-shape term ``S_l`` (true nm) of every crossing; ``asymmetry_s``: (tau_rise,
    tau_fall) s of a ``FeedbackAsymmetry``."""
    f, out = data.crossings, np.empty(len(data.crossings.x))
    li = np.searchsorted(LEVELS, f.level)
    for p, pair in enumerate(data.pairs):
        dt = pair.sample_time_s
        table = edge_shape(
            data.grating,
            data.depth,
            pair.pixel_size[0] / scale,
            LEVELS,
            radius,
            tau_s / dt,
            None if asymmetry_s is None else (asymmetry_s[0] / dt, asymmetry_s[1] / dt),
        )
        sel = f.pair == p
        out[sel] = table[(~f.rising[sel]).astype(int), f.retrace[sel].astype(int), li[sel]]
    return out


def _solve(data: ScanSet, cols: list, shape: np.ndarray, scale: float, searched: int = 0) -> ScanFit:
    """Linear least squares on the training crossings with the shape term moved to the left,
    converted to nominal nm by ``k / g`` (two passes: the gain comes from the first);
    ``searched``: parameters of ``shape`` found by a search, counted in the BIC."""
    table = data.linear_columns()
    a = _within(data, np.stack([table[c] for c in cols], -1))
    s, ds = data.field()
    gain = np.ones_like(s)
    for _ in range(2):
        b = _within(data, data.crossings.x - shape * scale / gain)
        theta = np.linalg.lstsq(a[data.train], b[data.train], rcond=None)[0]
        th = dict(zip(cols, theta))
        for d, sel in (("trace", ~data.crossings.retrace), ("retrace", data.crossings.retrace)):
            c = np.array([0, 0, th[f"c2_{d}"], th[f"c3_{d}"]])
            gain[sel] = 1 + legendre.legval(s[sel], legendre.legder(c)) * ds[sel]
    r = b - a @ theta
    rss = float(r[data.train] @ r[data.train])
    return ScanFit(
        residual=r,
        heldout_gap_nm=_systematic(data, r),
        theta=th,
        fitted={},
        rss=rss,
        heldout_rms_nm=float(np.sqrt(np.mean(r[~data.train] ** 2))),
        **Fit.scores(rss, int(data.train.sum()), len(cols) + searched + _nuisance(data)),
    )


def _groups(f: Crossings, pairs, grating: ScanSample) -> Optional[np.ndarray]:
    """For a lattice, each crossing's row group (:attr:`ScanSet.groups`); ``None`` for lines."""
    if grating.kind != "lattice":
        return None
    same = len({(p.trace.shape[0], round(p.pixel_size[1], 9)) for p in pairs}) == 1
    return f.row if same else f.pair * (1 + f.row.max()) + f.row


def _nuisance_columns(data: ScanSet) -> np.ndarray:
    """(crossings, 2): a row's feature width (+-1/2 on rising and falling edges) and its walls'
    slope along the row (the same times the level's offset from mid-level)."""
    sign = np.where(data.crossings.rising, 0.5, -0.5)
    return np.stack([sign, sign * (data.crossings.level - 0.5)], -1)


def _within(data: ScanSet, v: np.ndarray) -> np.ndarray:
    """``v`` (crossings, ...) less its projection, row group by row group, on the lattice's
    per-row columns (:func:`_nuisance_columns`; Frisch-Waugh-Lovell,
    :func:`~jaxafm.identify.projection.project_out`: the fit is then the full
    one with a width and a wall slope per row, the held-out rows' own from their own edges).
    A lattice row grazes or crosses its features where it happens to lie, so each row's feature
    chord and apparent wall are its own; what moves with the scan direction or speed is not.
    Unchanged for a 1-D grating."""
    if data.groups is None:
        return v
    return project_out(v, _nuisance_columns(data), data.groups)


def _nuisance(data: ScanSet) -> int:
    """The per-row parameters of a lattice's training rows (2 per row group), for the BIC."""
    return 0 if data.groups is None else 2 * len(np.unique(data.groups[data.train]))


def _systematic(data: ScanSet, r: np.ndarray) -> float:
    """rms over the cells (pair, direction, edge kind, level) of the cell's mean held-out residual."""
    return float(np.sqrt(np.nanmean(_cell_means(data, r, ~data.train) ** 2)))


def _cell_means(data: ScanSet, r: np.ndarray, sel: np.ndarray) -> np.ndarray:
    """Mean residual (pairs, direction [trace, retrace], kind [rising, falling], levels) nm over
    the crossings ``sel``; NaN where a cell has none."""
    f, shape = data.crossings, (len(data.pairs), 2, 2, len(LEVELS))
    cell = np.ravel_multi_index(
        (
            f.pair,
            f.retrace.astype(int),
            (~f.rising).astype(int),
            np.searchsorted(LEVELS, f.level),
        ),
        shape,
    )
    sums = np.bincount(cell[sel], r[sel], minlength=np.prod(shape))
    counts = np.bincount(cell[sel], minlength=np.prod(shape))
    with np.errstate(invalid="ignore", divide="ignore"):
        return (sums / counts).reshape(shape)


def _search(fit_at, lo: float, hi: float) -> tuple:
    """Minimise ``fit_at(v).rss`` over ``v`` in [lo, hi]: a log grid, then bounded refinement."""
    grid = np.geomspace(lo, hi, 17)
    rss = [fit_at(v).rss for v in grid]
    i = int(np.argmin(rss))
    a, b = np.log(grid[max(i - 1, 0)]), np.log(grid[min(i + 1, len(grid) - 1)])
    best = minimize_scalar(
        lambda lv: fit_at(np.exp(lv)).rss, bounds=(a, b), method="bounded", options={"xatol": 0.01}
    )
    v = float(np.exp(best.x)) if best.fun <= rss[i] else float(grid[i])
    return v, fit_at(v)


def _search_asymmetry(fit_at, lo: float, hi: float) -> tuple:
    """Minimise ``fit_at(tau_rise, tau_fall).rss`` over ``tau_fall`` in [lo, hi] and
    ``tau_rise / tau_fall`` in :data:`ASYMMETRY_RATIOS`: a log grid, then Nelder-Mead in logs."""
    r0, r1 = np.log(ASYMMETRY_RATIOS)
    f0, f1 = np.log(lo), np.log(hi)
    at = lambda p: fit_at(np.exp(p[0] + p[1]), np.exp(p[0]))
    cost = lambda p: at(np.clip(p, [f0, r0], [f1, r1])).rss
    grid = [(f, r) for f in np.linspace(f0, f1, 11) for r in np.linspace(r0, r1, 3)]
    rss = [cost(np.array(p)) for p in grid]
    start = np.array(grid[int(np.argmin(rss))])
    step = np.array([(f1 - f0) / 10, (r1 - r0) / 2])
    best = minimize(
        cost,
        start,
        method="Nelder-Mead",
        options={
            "initial_simplex": [start, start + [step[0], 0], start + [0, step[1]]],
            "xatol": 0.01,
            "fatol": 1e-3,
            "maxfev": 50,
        },
    )
    p = np.clip(best.x, [f0, r0], [f1, r1]) if best.fun <= min(rss) else start
    return (float(np.exp(p[0] + p[1])), float(np.exp(p[0]))), at(p)


def diagnose_scans(
    pairs, grating: ScanSample, candidates, train_fraction: float, rules: Rules = Rules(), log=None
) -> Diagnosis:
    """Nominal and nominal + candidate fits to the edge-level crossings of ``pairs``.

    Arguments:
        pairs: :class:`ScanPair` s at two or more scan speeds.
        grating: what is known of the grating and the tip.
        candidates: effect names to try (those a scan set cannot show are skipped with the reason).
        train_fraction: the first part of every pair's rows the fits train on; its later rows
            are held out.
        rules: when a candidate is significant.
        log: called with a line per fit (``None``: quiet).

    Returns:
        The :class:`~jaxafm.diagnose.core.Diagnosis`; its ``data`` is a :class:`ScanSet`, its
        fits are :class:`ScanFit` s.
    """
    return diagnose(ScanSet.split_off(pairs, grating, train_fraction), candidates, rules, log)
