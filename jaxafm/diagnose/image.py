"""Diagnosis on one image of a 1-D grating or a 2-D lattice: edge positions against the scanner's distortion.

The edges of every row (:func:`jaxafm.diagnose.scans.row_edges`: no full periods needed) are
fitted by linear least squares,
``x_nom = phase + n p - sum_k c_k P_k(s) - [candidate terms]`` (``line_grating``'s model):
the nominal, hysteresis-only scanner has the fast-axis nonlinearity ``c_2, c_3`` (one branch
of the loop) and the grating's pitch ``p`` and two edge phases. Candidates add one column
each: ``coupling`` the skew ``x += s y``, ``bow`` ``x += b P_2(y)``, ``creep`` an x scale
that changes over the frame. Training rows: the first ``train_fraction`` in scan order;
held out: the later rows. Gap: rms edge residual (nm) on the held-out rows; BIC,
significance, ranking and verdict are the core's (:mod:`jaxafm.diagnose.core`).

A 2-D lattice of pits or pillars: only the rows across the features are used, and each chord
through a feature (its two edges in one row) has its own width, projected out: what is fitted is
the chord's midpoint (a row grazing a pit sees a shorter chord, and on a turned lattice the
chords of one row differ); the edge phases become one centre phase. Pillars are read as the pits
of ``-z``, so that a chord is one feature's. A lattice turned by ``a`` on the stage shows a
feature centred at height ``y_c`` ``tan(a) y_c`` to the left of where the unturned one would
be, a shear as the scanner's coupling makes (``skew = tan a``), and one image cannot tell the two
apart; the gauge is step A's (``calibration.parameters``): the tilt of the lattice's rows,
measured from the centres of its complete pits or pillars (:func:`lattice_vectors`), is taken as
the lattice's turn and removed from every chord before any fit (with its feature's ``y_c``, the
nearest lattice site's), so that ``coupling`` is only the shear beyond it. Where a chord's
midpoint lies within its feature depends on the feature's shape (a round one's is its centre's x,
a turned square's moves along it by ``tan(a) (y - y_c)``): the nominal model has a slope
``shape`` of the midpoints in ``y - y_c``, the same for every feature.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..identify.features import feature_centres, index_lattice
from ..identify.line_grating import GratingEdges, edge_design
from ..identify.projection import project_out
from .core import DataKind, Diagnosis, Findings, Fit, Rules, diagnose
from .report import autocorrelation, binned_rms, rms
from .scans import LATTICE_CHORD, row_edges

NOMINAL = ("c2", "c3", "phase_rise", "phase_fall", "pitch")
NOMINAL_LATTICE = ("c2", "c3", "phase", "pitch")
COLUMN = {"coupling": "skew", "bow": "bow", "creep": "drift"}


@dataclasses.dataclass(frozen=True, eq=False)
class ImageFit(Fit):
    """A :class:`~jaxafm.diagnose.core.Fit` of an image's edges; ``residual`` (edges,) nm.

    Attributes:
        fitted: every fitted coefficient by its column's name (nm; ``skew`` nm/nm).
    """

    fitted: dict

    def shown(self) -> dict:
        return {"fitted": self.fitted}

    def summary(self) -> dict:
        return super().summary() | {"fitted": self.fitted}


@dataclasses.dataclass(frozen=True, eq=False)
class GratingImage(DataKind):
    """One image of a 1-D grating as a diagnosis's data.

    Attributes:
        image: the image (an ``AFMImage``), rows in scan order.
        edges: its edges.
        train: (edges,) True on the edges of the training rows.
        first_heldout_row: the first held-out row.
        design: the columns (edges, m) of the linear model.
        columns: their names.
    """

    image: object
    edges: GratingEdges
    train: np.ndarray
    first_heldout_row: int
    design: np.ndarray
    columns: list
    lattice: bool = False
    row_tilt: float | None = None
    chord: np.ndarray | None = None

    name = "image"
    gap_label = "held-out gap (rms edge residual) [nm]"
    model = "hysteresis-only scanner: fast-axis nonlinearity c2, c3 + grating pitch and phases"
    label = "hysteresis-only scanner"
    tries = tuple(COLUMN)

    @classmethod
    def split_off(cls, image, train_fraction: float, kind: str = "lines", pitch_nm=None) -> GratingImage:
        """``image`` with its first ``train_fraction`` of the rows (with edges) to train on;
        ``kind``: ``lines`` (a 1-D grating) or ``lattice``, whose ``pitch_nm`` (x) indexes rows
        with one feature.

        Raises:
            ValueError: with fewer than 8 rows with edges or 20 edges in either part.
        """
        name = str(image.meta.get("source", "image"))
        lattice = kind == "lattice"
        z = image.z
        if lattice and np.median(z) < np.mean(np.percentile(z, (2, 98))):  # pillars: a minority high
            z = -z
        e = row_edges(z, image.pixel_size, name, kind, pitch_nm).edges
        chord = None
        if lattice:
            e, chord = _chords(e)
        rows = np.unique(e.row)
        cut = rows[int(round(train_fraction * len(rows)))] if len(rows) > 1 else 0
        train = e.row < cut
        if train.sum() < 20 or (~train).sum() < 20 or len(rows) < 8:
            raise ValueError(
                f"{name}: {len(rows)} rows with edges ({int(train.sum())} training and "
                f"{int((~train).sum())} held-out edges at train_fraction={train_fraction}): too few to "
                "split; scan more lines or change train_fraction in the config"
            )
        frame = lattice_vectors(image, pitch_nm) if lattice else None
        tilt = None
        if frame is not None:  # the lattice's turn: a feature centred at y_c is seen tan(a) y_c to the left
            tilt, y_c = frame[1][1] / frame[1][0], _feature_y(e, chord, frame)
            e = dataclasses.replace(e, x_nm=e.x_nm + tilt * y_c)
        design = edge_design(e, 3, True, lattice)
        a, names = design.columns, design.names
        if frame is not None:  # a chord's midpoint moves along its feature as the feature's shape has it
            a, names = np.column_stack([a, e.y_nm - y_c]), [*names, "shape"]
        return cls(image, e, train, int(cut), a, names, lattice, tilt, chord)

    def _within(self, v: np.ndarray) -> np.ndarray:
        """Lattice: ``v`` (edges, ...) less its projection on a width per chord (rising edge
        +1/2, falling -1/2; Frisch-Waugh-Lovell, :func:`~jaxafm.identify.projection.project_out`): both edges of a
        chord become its midpoint; else ``v``."""
        if not self.lattice:
            return v
        return project_out(v, np.where(self.edges.rising, 0.5, -0.5), self.chord)

    def _fit(self, cols: list) -> ImageFit:
        """Least squares on the training edges (a lattice: chord midpoints, each counted once);
        residual (all edges) nm, gap and BIC."""
        x = self._within(self.design[:, [self.columns.index(c) for c in cols]])
        b, train = self._within(self.edges.x_nm), self.train
        theta = np.linalg.lstsq(x[train], b[train], rcond=None)[0]
        r = b - x @ theta
        rss, n = float(r[train] @ r[train]), int(train.sum())
        if self.lattice:  # the data are the midpoints: two equal residuals per chord
            rss, n = rss / 2, n // 2
        return ImageFit(
            residual=r,
            heldout_gap_nm=float(np.sqrt(np.mean(r[~train] ** 2))),
            fitted=dict(zip(cols, theta.tolist())),
            **Fit.scores(rss, n, len(cols)),
        )

    @property
    def nominal_columns(self) -> list:
        return list(NOMINAL_LATTICE if self.lattice else NOMINAL) + (
            ["shape"] if "shape" in self.columns else []
        )

    def fit_nominal(self) -> ImageFit:
        return self._fit(self.nominal_columns)

    def fit_candidate(self, effect: str, nominal: ImageFit) -> ImageFit:
        return self._fit(self.nominal_columns + [COLUMN[effect]])

    def describe(self) -> dict:
        per = 2 if self.lattice else 1  # a lattice's data: chords, two edges each
        return {
            "source": str(self.image.meta.get("source", "image")),
            "kind": "2-D lattice image" if self.lattice else "1-D grating image",
            "pixels": list(self.image.shape),
            "pixel_size_nm": list(self.image.pixel_size),
            "train_samples": int(self.train.sum()) // per,
            "heldout_samples": int((~self.train).sum()) // per,
            "heldout_from_row": self.first_heldout_row,
            "counts": "chords (their midpoints)" if self.lattice else "edges",
            "units": "nm (edge positions, gaps)",
        } | ({"lattice_row_tilt": self.row_tilt} if self.lattice else {})

    def findings(self, diagnosis: Diagnosis) -> Findings:
        """The nominal residual by place in the field, by row, by edge kind; whiteness down the frame."""
        dec, test = self.decompose(diagnosis.nominal.residual), self.row_tests(diagnosis.nominal.residual)
        m = test["metrics"]
        metrics = {"train_edges": int(self.train.sum()), "heldout_edges": int((~self.train).sum())}
        metrics |= m | {
            "residual_rms_nm": dec["overall_rms_nm"],
            "residual_rising_nm": dec["rms_nm"]["rising"],
            "residual_falling_nm": dec["rms_nm"]["falling"],
        }
        notes = [
            f"- Whiteness down the frame: lag-1 autocorrelation of the per-row mean residual "
            f"{m['row_mean_residual_acf_lag1']:.2f}, {m['row_mean_residual_acf_outside_band_pct']:.0f} % "
            f"of lags outside the 95 % band (+-{m['correlation_band_95']:.2f}).",
            "- One image shows one branch at one speed: what it cannot show is listed as 'not tried' above.",
        ]
        if self.lattice:
            notes.append(
                "- The lattice's rows were not measured (too few complete pits or pillars): a turned "
                "lattice, if it is one, is in the coupling candidate's skew."
                if self.row_tilt is None
                else f"- The lattice's rows tilt by dy/dx = {self.row_tilt:.4f} (a turn of "
                f"{np.degrees(np.arctan(self.row_tilt)):.2f} degrees), taken as the lattice's turn on the "
                "stage and removed from the edges (one image cannot tell it from the scanner's coupling); "
                "the coupling candidate's skew is the shear beyond it."
            )
        return Findings(metrics, self.where(dec), notes, dec, {"test": test, "dec": dec})

    def decompose(self, r: np.ndarray) -> dict:
        """rms edge residual ``r`` (nm) by position in the scan field (x), by row, rising vs falling."""
        e = self.edges
        xe = np.linspace(e.x_nm.min(), e.x_nm.max(), 9)
        ye = np.linspace(e.row.min(), e.row.max() + 1, 11)
        return {
            "edges": {"x_nm": xe.tolist(), "row": ye.tolist()},
            "rms_nm": {
                "x_nm": binned_rms(e.x_nm, r, xe),
                "row": binned_rms(e.row, r, ye),
                "rising": rms(r[e.rising]),
                "falling": rms(r[~e.rising]),
            },
            "overall_rms_nm": rms(r),
        }

    def where(self, dec: dict) -> list:
        """Sentences that say where the residual of :meth:`decompose` is concentrated."""
        tab, overall = dec["rms_nm"], dec["overall_rms_nm"]
        x = np.array(tab["x_nm"])
        b = int(np.nanargmax(x))
        rows = np.array(tab["row"])
        return [
            f"Across the scan field (x) the rms edge residual is largest between {dec['edges']['x_nm'][b]:.0f} and "
            f"{dec['edges']['x_nm'][b + 1]:.0f} nm: {x[b]:.3g} nm against {overall:.3g} nm overall.",
            f"Down the frame (rows, in scan order) it goes from {rows[0]:.3g} nm (first tenth) to {rows[-1]:.3g} nm "
            f"(last tenth); the held-out rows start at row {self.first_heldout_row}.",
        ] + (
            []
            if self.lattice  # a chord's two edges share its midpoint's residual
            else [
                f"Rising edges {tab['rising']:.3g} nm, falling edges {tab['falling']:.3g} nm rms "
                "(a lag or a tip would move the two kinds apart)."
            ]
        )

    def row_tests(self, r: np.ndarray) -> dict:
        """Whiteness of the per-row mean of the edge residual ``r`` down the frame (a slow-axis
        miss correlates rows): its autocorrelation, the 95 % band and the flat metrics."""
        e = self.edges
        rows = np.unique(e.row)
        mean = np.array([r[e.row == k].mean() for k in rows])
        acf = autocorrelation(mean, min(20, len(rows) // 3))
        band = 1.96 / np.sqrt(len(rows))
        return {
            "acf": acf,
            "band": band,
            "metrics": {
                "row_mean_residual_acf_lag1": float(acf[0]),
                "row_mean_residual_acf_outside_band_pct": float(100 * np.mean(np.abs(acf) > band)),
                "correlation_band_95": float(band),
            },
        }

    def panels(self, axes: list, diagnosis: Diagnosis, findings: Findings) -> None:
        """The nominal residual in the scan field, its per-row mean down the frame (with the
        verdict's), and that mean's autocorrelation."""
        e, r, top = self.edges, diagnosis.nominal.residual, diagnosis.top
        test, dec = findings.plots["test"], findings.plots["dec"]
        fig, a = axes[0].figure, axes[0]
        sc = a.scatter(
            e.x_nm / 1e3,
            e.row,
            c=r,
            s=6,
            cmap="coolwarm",
            vmin=-3 * dec["overall_rms_nm"],
            vmax=3 * dec["overall_rms_nm"],
        )
        a.axhline(self.first_heldout_row - 0.5, color="k", ls="--", lw=1)
        fig.colorbar(sc, ax=a, label="edge residual [nm]")
        a.set(
            xlabel="x [µm]",
            ylabel="row (scan order)",
            title="nominal residual in the scan field (--: held out above)",
        )
        a = axes[1]
        rows = np.unique(e.row)
        kinds = (
            (((True, False), "chord midpoints"),)
            if self.lattice
            else (((True,), "rising edges"), ((False,), "falling edges"))
        )
        for k, m in kinds:
            a.plot(
                rows,
                [r[(e.row == j) & np.isin(e.rising, k)].mean() for j in rows],
                ".-",
                lw=0.8,
                label=m,
            )
        if top is not None:
            best = top.fit.residual
            a.plot(rows, [best[e.row == j].mean() for j in rows], "k-", lw=1, label=f"with {top.effect}")
        a.set(xlabel="row (scan order)", ylabel="mean residual per row [nm]", title="down the frame")
        a.legend(fontsize=8)
        a = axes[2]
        a.plot(np.arange(1, test["acf"].size + 1), test["acf"], "o-")
        a.axhspan(-test["band"], test["band"], color="0.85", label="95 % band (white)")
        a.set(xlabel="lag [rows]", ylabel="autocorrelation", title="whiteness of the per-row mean residual")
        a.legend(fontsize=8)


def lattice_vectors(image, pitch_nm) -> tuple | None:
    """``(origin, a1, a2)`` nm of a lattice image (a site at ``origin + i a1 + j a2``; ``a1``
    along its rows, ``a1[1] / a1[0]`` their tilt dy/dx), fitted by least squares to the centres
    of its complete pillars, or pits, whichever are more
    (:func:`~jaxafm.identify.features.feature_centres`), indexed at the pitch ``pitch_nm`` (one
    number or (x, y)) as step A's calibration indexes them
    (:func:`~jaxafm.identify.features.index_lattice`); ``None`` with fewer than 6 of them.

    Raises:
        ValueError: the image shows complete features, but they do not repeat at ``pitch_nm``
            (the message says how far apart they lie).
    """
    pixel = np.asarray(image.pixel_size, dtype=float)
    pitch = np.broadcast_to(np.asarray(pitch_nm, dtype=float), (2,))
    name = str(image.meta.get("source", "image"))
    found, off_pitch = [], None
    for z in (image.z, -image.z):
        try:
            xy = feature_centres(z, name)[:, ::-1] * pixel
        except ValueError:  # no complete features of this sign
            continue
        try:
            found.append((xy, index_lattice(xy, pitch, name, "nm")[0]))
        except ValueError as e:  # features, but not at the stated pitch
            off_pitch = off_pitch or e
    if not found and off_pitch is not None:
        raise ValueError(f"pitch_nm = {' x '.join(f'{p:g}' for p in pitch)} nm: {off_pitch}") from None
    xy, ij = max(found, key=lambda f: len(f[0]), default=(np.zeros((0, 2)), None))
    if len(xy) < 6:
        return None
    return tuple(np.linalg.lstsq(np.column_stack([np.ones(len(xy)), ij]), xy, rcond=None)[0])


def _chords(e: GratingEdges) -> tuple:
    """The edges that bound a pit in a row (a falling edge, then the rising one after it), in
    pairs, and each one's chord number. Dropped: edges of pits cut by the image's border, and
    chords shorter than ``LATTICE_CHORD`` of the median one (a row grazing a pit, or a pit split
    by a spike: their midpoints miss the pit's centre)."""
    order = np.lexsort((e.x_nm, e.row))
    row, rising, x = e.row[order], e.rising[order], e.x_nm[order]
    k = np.flatnonzero(~rising[:-1] & rising[1:] & (row[:-1] == row[1:]))
    width = x[k + 1] - x[k]
    k = k[width >= LATTICE_CHORD * np.median(width)]
    keep = order[np.stack([k, k + 1], -1).ravel()]
    fields = ("row", "x_nm", "y_nm", "rising", "index")
    return dataclasses.replace(e, **{f: getattr(e, f)[keep] for f in fields}), np.repeat(np.arange(k.size), 2)


def _feature_y(e: GratingEdges, chord: np.ndarray, frame: tuple) -> np.ndarray:
    """Per edge, the y (nm) of the centre of its feature: the lattice site (``frame``, from
    :func:`lattice_vectors`) nearest to its chord's midpoint."""
    origin, a1, a2 = frame
    m = np.stack([a1, a2], -1)
    mid = np.stack([np.bincount(chord, e.x_nm)[chord] / 2, e.y_nm], -1)
    ij = np.round(np.linalg.solve(m, (mid - origin).T)).T
    return (origin + ij @ m.T)[:, 1]


def diagnose_image(
    image,
    candidates,
    train_fraction: float,
    rules: Rules = Rules(),
    log=None,
    kind: str = "lines",
    pitch_nm=None,
) -> Diagnosis:
    """Nominal and nominal + candidate fits to the edges of ``image`` (an ``AFMImage``).

    Arguments:
        image: one image of a 1-D grating, lines along the slow axis, or of a 2-D lattice
            (``kind="lattice"``, ``pitch_nm`` its pitch along x), rows in scan order.
        candidates: effect names to try (those one image cannot show are skipped with the reason).
        train_fraction: the first part of the rows the fits train on.
        rules: when a candidate is significant.
        log: called with a line per fit (``None``: quiet).
        kind: ``lines`` or ``lattice``.
        pitch_nm: the lattice's pitch along x (nm), for rows that show one feature.

    Returns:
        The :class:`~jaxafm.diagnose.core.Diagnosis`; its ``data`` is a :class:`GratingImage`,
        its fits are :class:`ImageFit` s.
    """
    return diagnose(GratingImage.split_off(image, train_fraction, kind, pitch_nm), candidates, rules, log)
