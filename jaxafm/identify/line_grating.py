"""Pitch, fast-axis nonlinearity and skew from one image of a 1-D calibration grating.

The real-data half of step A: the grating's pitch need not be known. Every
row gives the sub-pixel positions of its rising and falling mid-level edges
(``features.edge_crossings``); each edge gets its line index ``n``, the same in
every row. The scanner maps the nominal position (``x``, ``y``) nm of an edge
to where the tip really was,

    x_true = x + sum_{k=2..degree} c_k P_k(s) + skew y + bow P_2(t) + drift (x - x_mid) t / 2,

with ``P_k`` the Legendre polynomials, ``s = 2 (x - x_0) / (x_1 - x_0) - 1`` and
``t = 2 (y - y_0) / (y_1 - y_0) - 1`` ([x_0, x_1] the first and last column
centre, [y_0, y_1] the first and last row centre). On a grating of pitch ``p``
the ``n``-th rising edge of row ``r`` lies at ``x_true = phase_rise + n p + w_r / 2``,
the ``n``-th falling one at ``phase_fall + n p - w_r / 2``. All of it is linear in
(c_k, skew, bow, drift, w_r, phase_rise, phase_fall, p): one least-squares solve.

Gauge: one image cannot tell an offset or a uniform x scale error from the
grating's phase and pitch, so the constant and linear terms of the
nonlinearity are left out (``P_k``, k >= 2, are orthogonal to both over the
scan). The pitch is in the instrument's nominal length calibration:
``pitch_nm / nominal pitch - 1`` is the x calibration error. ``skew`` (nm of x
per nm of y) shifts each scan line in proportion to its y: scanner
cross-coupling, a grating rotated on the stage and a steady x drift during the
frame look the same in one image.

Optional terms. ``slow=True``: ``bow`` (nm), an x shift quadratic in y (a tube
scanner's bow, or x drift that speeds up or slows down), and ``drift``, the
relative change of the x scale from the first row to the last (creep or
heating of the x piezo during the frame), centred so that ``pitch_nm`` is the
pitch at the middle row. ``widths=True``: ``w_r`` (mean zero over the rows), how
much wider the gap from a falling to the next rising edge is in row ``r``: the
apparent line width wanders with the tip and the feedback, and moves the two
kinds of edge in opposite directions, which is no scanner motion.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np
from numpy.polynomial import legendre

from .features import check_image, edge_crossings, pitch_spread
from .fit import bic
from .projection import project_out

MIN_ROWS = 8  # scan lines: enough to see the skew against the edge jitter
MIN_PERIODS = 3  # complete periods (same-type edge to same-type edge) in a typical row
DEGREES = (2, 3)  # the candidates when degree=None, chosen by BIC
TOL = 0.25  # an edge further than this fraction of a period off its line breaks the indexing


@dataclasses.dataclass(frozen=True)
class GratingEdges:
    """All edges of a 1-D grating image: ``row``, nominal ``x_nm`` and ``y_nm`` (pixel
    centres, pixel [0, 0] at 0), ``rising`` (height increases with x) and line ``index``
    (the same line has the same index in every row; 0 = leftmost line of its type)."""

    row: np.ndarray
    x_nm: np.ndarray
    y_nm: np.ndarray
    rising: np.ndarray
    index: np.ndarray
    shape: tuple
    pixel_size: tuple


@dataclasses.dataclass(frozen=True)
class LineGratingFit:
    """Fitted grating and scanner distortion (the equation is in the module docstring).

    ``coeffs_nm``: (c_2, ..., c_degree) nm. ``*_se``: standard errors from the residual
    variance, the edges taken as independent. ``bow_nm``, ``drift``: 0 (se NaN) unless
    fitted. ``row_width_nm``: per row, the line's width (the groove's where ``grooves``)
    minus its mean, NaN where the row has no edges or widths were not fitted.
    ``line_width_nm``: the mean width at mid-level. ``bic_by_degree``: each degree tried.
    """

    pitch_nm: float
    pitch_se_nm: float
    coeffs_nm: tuple
    coeffs_se_nm: tuple
    skew: float
    skew_se: float
    bow_nm: float
    bow_se_nm: float
    drift: float
    drift_se: float
    phase_rise_nm: float
    phase_fall_nm: float
    line_width_nm: float
    degree: int
    residual_rms_nm: float
    x_range_nm: tuple
    y_range_nm: tuple
    bic: float
    bic_by_degree: dict
    row_width_nm: np.ndarray = dataclasses.field(repr=False, compare=False)
    edges: GratingEdges = dataclasses.field(repr=False, compare=False)
    grooves: bool = True

    def nonlinearity_nm(self, x_nm) -> np.ndarray:
        """sum_k c_k P_k(s) (nm) at nominal x (nm): the fast axis beyond its linear calibration."""
        x0, x1 = self.x_range_nm
        s = 2 * (np.asarray(x_nm, dtype=float) - x0) / (x1 - x0) - 1
        return legendre.legval(s, np.concatenate([[0.0, 0.0], self.coeffs_nm]))

    def slow_axis_nm(self, x_nm, y_nm) -> np.ndarray:
        """bow P_2(t) + drift (x - x_mid) t / 2 (nm) at nominal (x, y) nm."""
        (x0, x1), (y0, y1) = self.x_range_nm, self.y_range_nm
        x = np.asarray(x_nm, dtype=float)
        t = 2 * (np.asarray(y_nm, dtype=float) - y0) / (y1 - y0) - 1
        return self.bow_nm * 0.5 * (3 * t**2 - 1) + self.drift * (x - 0.5 * (x0 + x1)) * t / 2

    def corrected_x(self, x_nm, y_nm) -> np.ndarray:
        """True x (nm) at nominal (x, y) nm: x + nonlinearity + skew y + bow and drift terms."""
        x, y = np.asarray(x_nm, dtype=float), np.asarray(y_nm, dtype=float)
        return x + self.nonlinearity_nm(x) + self.skew * y + self.slow_axis_nm(x, y)

    def ideal_x(self) -> np.ndarray:
        """Where each edge lies on the fitted grating (nm): phase + index * pitch +- w_r / 2."""
        e = self.edges
        half = 0.5 * np.nan_to_num(self.row_width_nm[e.row]) * (1 if self.grooves else -1)
        return (
            np.where(e.rising, self.phase_rise_nm + half, self.phase_fall_nm - half) + e.index * self.pitch_nm
        )

    def residuals_nm(self) -> np.ndarray:
        """Per edge: its corrected x minus its place on the fitted grating (nm)."""
        return self.corrected_x(self.edges.x_nm, self.edges.y_nm) - self.ideal_x()

    def local_pitch(self, corrected: bool = True) -> tuple:
        """(x, pitch, row): distances (nm) between consecutive same-type edges of each row, at
        the nominal pixel size or after ``corrected_x``, the nominal x (nm) halfway between
        them, and their row."""
        e = self.edges
        return local_pitch(e, self.corrected_x(e.x_nm, e.y_nm) if corrected else e.x_nm)

    def uniformity(self) -> dict:
        """``features.pitch_spread`` of the local pitch: ``{"raw": ..., "corrected": ...}``."""
        return {
            k: pitch_spread(self.local_pitch(corrected=c)[1])
            for k, c in (("raw", False), ("corrected", True))
        }


def local_pitch(edges: GratingEdges, x_nm: np.ndarray) -> tuple:
    """(x, pitch, row): distances (nm) between the same-type edges of a row whose line indices
    differ by 1, the edges placed at ``x_nm``; x (nm) is the nominal position halfway between."""
    key = 2 * edges.row + edges.rising
    order = np.lexsort((edges.index, key))
    k, i, x, xn = key[order], edges.index[order], np.asarray(x_nm)[order], edges.x_nm[order]
    pair = (k[1:] == k[:-1]) & (np.diff(i) == 1)
    return 0.5 * (xn[1:] + xn[:-1])[pair], np.diff(x)[pair], edges.row[order][1:][pair]


def _kind(rising: bool) -> str:
    return "rising" if rising else "falling"


def grating_edges(z: np.ndarray, pixel_size, name: str = "image") -> GratingEdges:
    """Sub-pixel rising and falling edges of every row of a 1-D grating image (lines along the
    slow axis y, rows), each with its line index, tracked from row to row."""
    z = np.asarray(z, dtype=float)
    if z.ndim == 2 and z.shape[0] < MIN_ROWS:
        raise ValueError(
            f"{name} has {z.shape[0]} scan line(s); fitting the skew needs at least {MIN_ROWS}: "
            "scan more lines"
        )
    z = check_image(z, name)
    dx, dy = (float(p) for p in np.broadcast_to(np.asarray(pixel_size, dtype=float), (2,)))
    if not (dx > 0 and dy > 0):
        raise ValueError(f"{name}: pixel size must be > 0 nm on both axes, got {pixel_size}")
    rows = [edge_crossings(r) for r in z]
    both = [r.any() and not r.all() for _, r in rows]  # rows with rising and falling edges
    if sum(both) < MIN_ROWS:
        raise ValueError(
            f"{name}: only {sum(both)} scan line(s) show both rising and falling edges; the fit needs "
            f"at least {MIN_ROWS}: check that the lines run along the slow axis (rows)"
        )
    periods = [max(np.sum(r) - 1, np.sum(~r) - 1, 0) for _, r in rows]
    if np.median(periods) < MIN_PERIODS:
        raise ValueError(
            f"{name}: a typical row shows {int(np.median(periods))} complete grating period(s) along x; "
            f"the fit needs at least {MIN_PERIODS}: scan a wider area or use a grating of finer pitch, "
            "with its lines along the slow axis (rows)"
        )
    p0 = float(np.median(np.concatenate([np.diff(c[r == t]) for c, r in rows for t in (True, False)])))

    found = []
    for rising in (True, False):
        ref = None  # x (px) of index 0 on the last row with edges of this type
        for j, (c, r) in enumerate(rows):
            if not both[j]:
                continue
            x = c[r == rising]
            steps = np.diff(x) / p0
            whole = np.round(steps)
            if np.any(whole < 1) or np.any(np.abs(steps - whole) > TOL):
                raise ValueError(
                    f"{name}: edge indexing is inconsistent: in row {j} the {_kind(rising)} edges at columns "
                    f"{np.round(x, 1).tolist()} are not whole periods ({p0:.1f} px) apart; a defect, dust or a "
                    "broken line interrupts the grating there: crop or fill it"
                )
            m = np.concatenate([[0], np.cumsum(whole)]).astype(int)
            phase = float(np.median(x - p0 * m))
            if ref is not None:
                shift = (phase - ref) / p0
                if abs(shift - round(shift)) > TOL:
                    raise ValueError(
                        f"{name}: edge indexing is inconsistent: the {_kind(rising)} edges move by {shift:+.2f} "
                        f"periods from the row before row {j} to row {j}, so which line is which is ambiguous; "
                        "the image jumps there (a tip change, a shock): crop the image at that row"
                    )
                m = m + int(round(shift))
            ref = float(np.median(x - p0 * m))
            found.append((np.full(x.size, j), x, np.full(x.size, rising), m))
    row, x, rising, index = (np.concatenate(a) for a in zip(*found))
    for t in (True, False):
        index[rising == t] -= index[rising == t].min()
    return GratingEdges(row, x * dx, row * dy, rising, index, z.shape, (dx, dy))


@dataclasses.dataclass(frozen=True)
class EdgeDesign:
    """The linear model of a grating's edges (:func:`edge_design`).

    Attributes:
        columns: (edges, m) the right side's columns.
        names: their names (``c2``.., ``skew``, [``bow``, ``drift``], the phases, ``pitch``).
        x_range_nm: the x range (nm) that ``s`` spans (first to last column centre).
        y_range_nm: the y range (nm) that ``t`` spans (first to last row centre).
    """

    columns: np.ndarray
    names: list
    x_range_nm: tuple
    y_range_nm: tuple


def edge_design(e: GratingEdges, degree: int, slow: bool, widths: bool) -> EdgeDesign:
    """The design of the module's model: the columns of
    ``x_nom = phase + n p - sum_{k=2..degree} c_k P_k(s) - skew y [- bow P_2(t) - drift (x - x_mid) t / 2]``
    (the slow terms with ``slow``). With ``widths`` one centre ``phase`` (the per-row widths are
    not columns: :func:`_solve` projects them out), else a ``phase_rise`` and a ``phase_fall``."""
    rows, cols = e.shape
    xr, yr = (0.0, (cols - 1) * e.pixel_size[0]), (0.0, (rows - 1) * e.pixel_size[1])
    s = 2 * (e.x_nm - xr[0]) / (xr[1] - xr[0]) - 1
    t = 2 * (e.y_nm - yr[0]) / (yr[1] - yr[0]) - 1
    columns = [-legendre.legval(s, np.eye(degree + 1)[k]) for k in range(2, degree + 1)]
    names = [f"c{k}" for k in range(2, degree + 1)]
    columns.append(-e.y_nm)
    names.append("skew")
    if slow:
        columns += [-0.5 * (3 * t**2 - 1), -(e.x_nm - 0.5 * sum(xr)) * t / 2]
        names += ["bow", "drift"]
    if widths:  # phase of the line centre; rise and fall +- W_r / 2 of it, W_r free per row
        columns.append(np.ones_like(e.x_nm))
        names.append("phase")
    else:
        columns += [e.rising.astype(float), (~e.rising).astype(float)]
        names += ["phase_rise", "phase_fall"]
    columns.append(e.index.astype(float))
    names.append("pitch")
    return EdgeDesign(np.stack(columns, -1), names, xr, yr)


def _solve(a: np.ndarray, b: np.ndarray, e: GratingEdges, widths: bool, name: str) -> tuple:
    """Least squares for x_nom = a @ theta (+ W_r sign / 2 per row where ``widths``).

    The W_r are projected out of ``a`` and ``b`` (Frisch-Waugh-Lovell,
    :func:`~jaxafm.identify.projection.project_out`: within a row, the sign-weighted mean is
    removed), which leaves theta, its covariance and the residuals as in the full problem.
    Returns parameters, standard errors, the residual sum of squares, the number of parameters
    and W_r (rows without edges: NaN).
    """
    n_rows = e.shape[0]
    sign = np.where(e.rising, 1.0, -1.0)
    count = np.bincount(e.row, minlength=n_rows)
    at, bt = (project_out(a, sign, e.row), project_out(b, sign, e.row)) if widths else (a, b)
    norm = np.linalg.norm(at, axis=0)
    norm[norm == 0] = 1.0
    sol, _, rank, _ = np.linalg.lstsq(at / norm, bt, rcond=None)
    p = a.shape[1] + (np.count_nonzero(count) if widths else 0)
    if rank < a.shape[1] or a.shape[0] <= p:
        raise ValueError(
            f"{name}: {a.shape[0]} edges at too few distinct places for {p} parameters: scan more "
            "periods or lines, lower the degree, or fit without slow=True or widths=True"
        )
    r = bt - (at / norm) @ sol
    rss = float(r @ r)
    cov = rss / (a.shape[0] - p) * np.linalg.inv((at / norm).T @ (at / norm))
    theta = sol / norm
    w = np.full(n_rows, np.nan)
    if widths:
        w[count > 0] = (2 * np.bincount(e.row, sign * (b - a @ theta), n_rows) / np.maximum(count, 1))[
            count > 0
        ]
    return theta, np.sqrt(np.diag(cov)) / norm, rss, p, w


def fit_line_grating(
    z: np.ndarray,
    pixel_size,
    degree: Optional[int] = None,
    grooves: bool = True,
    slow: bool = True,
    widths: bool = True,
    name: str = "image",
) -> LineGratingFit:
    """Fit pitch, fast-axis nonlinearity and skew (and the optional terms) to a 1-D grating image.

    ``z`` (rows, cols) heights nm, lines along the slow axis (y, rows); ``pixel_size`` (x, y)
    nm. ``degree``: the highest Legendre order of the nonlinearity (1: none); ``None`` picks
    2 or 3 by the Bayesian information criterion. ``grooves``: the lines are grooves (the
    widths reported are the grooves'), else raised lines. ``slow``: fit the bow and the
    x-scale drift; ``widths``: fit a line width per row. Model: the module docstring.
    """
    e = grating_edges(z, pixel_size, name)
    fits = {}
    for d in DEGREES if degree is None else (int(degree),):
        if d < 1:
            raise ValueError(f"degree must be >= 1 (1: no nonlinearity), got {d}")
        design = edge_design(e, d, slow, widths)
        theta, se, rss, p, w = _solve(design.columns, e.x_nm, e, widths, name)
        fits[d] = (
            bic(rss, len(e.x_nm), p),
            design,
            dict(zip(design.names, theta)),
            dict(zip(design.names, se)),
            rss,
            w,
        )
    best = min(fits, key=lambda d: fits[d][0])
    fit = _grating_fit(e, best, fits, widths, grooves)
    res = fit.residuals_nm()
    worst = int(np.argmax(np.abs(res)))
    pitch = fit.pitch_nm
    if abs(res[worst]) > TOL * pitch:
        raise ValueError(
            f"{name}: edge indexing is inconsistent: an edge in row {e.row[worst]} at x = {e.x_nm[worst]:.0f} nm "
            f"lies {res[worst]:+.0f} nm off its line (pitch {pitch:.0f} nm): a defect or a partial line there; "
            "crop it"
        )
    return fit


def _grating_fit(e: GratingEdges, best: int, fits: dict, widths: bool, grooves: bool) -> LineGratingFit:
    """The :class:`LineGratingFit` of degree ``best`` from :func:`fit_line_grating`'s solves
    ``fits`` (per degree: BIC, design, values and standard errors by name, RSS, row widths)."""
    best_bic, design, sol, se, rss, w = fits[best]
    pitch = sol["pitch"]
    if widths:  # W_r about its mean; the mean splits the centre phase into the two edges'
        mean = float(np.nanmean(w))
        w = (w - mean) * (1 if grooves else -1)
        sol["phase_rise"], sol["phase_fall"] = sol["phase"] + mean / 2, sol["phase"] - mean / 2
    groove_width = (sol["phase_rise"] - sol["phase_fall"]) % pitch
    return LineGratingFit(
        pitch_nm=float(pitch),
        pitch_se_nm=float(se["pitch"]),
        coeffs_nm=tuple(float(sol[f"c{k}"]) for k in range(2, best + 1)),
        coeffs_se_nm=tuple(float(se[f"c{k}"]) for k in range(2, best + 1)),
        skew=float(sol["skew"]),
        skew_se=float(se["skew"]),
        bow_nm=float(sol.get("bow", 0.0)),
        bow_se_nm=float(se.get("bow", np.nan)),
        drift=float(sol.get("drift", 0.0)),
        drift_se=float(se.get("drift", np.nan)),
        phase_rise_nm=float(sol["phase_rise"]),
        phase_fall_nm=float(sol["phase_fall"]),
        line_width_nm=float(groove_width if grooves else pitch - groove_width),
        degree=best,
        residual_rms_nm=float(np.sqrt(rss / len(e.x_nm))),
        x_range_nm=design.x_range_nm,
        y_range_nm=design.y_range_nm,
        bic=float(best_bic),
        bic_by_degree={d: float(f[0]) for d, f in fits.items()},
        row_width_nm=w,
        edges=e,
        grooves=grooves,
    )
