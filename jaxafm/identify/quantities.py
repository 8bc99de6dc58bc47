"""A fitted scanner's physical quantities (:func:`quantities`): each axis's gain and loop, its creep
and lag, the coupling, bow and drift, the edge delay, the lattice's angle, as functions of a
model. What the scans determine of them (:mod:`~jaxafm.identify.identifiability`) and what a user
states of them beforehand (:func:`known_misfits`, step A's prior on them,
:data:`~jaxafm.config.names.KNOWABLE`) speak of the same numbers."""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from .calibration_scan import drive_range
from .scan_model import ScanModel


class Definition(NamedTuple):
    """One physical quantity: its ``key`` (its name in ``metrics.json``, units included), its
    ``name`` in words, its ``unit``, and its value ``of(m) -> ()`` for a model ``m``."""

    key: str
    name: str
    unit: str
    of: Callable


def quantities(model: ScanModel, scans: tuple, drive: np.ndarray) -> list:
    """The physical quantities of models of ``model``'s structure, a :class:`Definition` each
    (its value of any model of that structure). ``drive`` (2, 2) V is the drive range [min,
    max] per axis that the scans covered: an axis's gain is its branches' mean slope, and its
    loop their separation (descending less ascending branch), at the middle of that range,
    after a sweep over it. (One function of about 70 lines: one small closure per quantity,
    each a line or two, which read best side by side.)"""
    travel = np.ptp(drive, axis=1) * np.asarray(scans[0].sensitivity)
    out = []

    def add(key, name, unit, fn):
        out.append(Definition(key, name, unit, fn))

    for k, a in enumerate("xy"):
        lo, hi = drive[k]
        mid = 0.5 * (lo + hi)
        u = jnp.concatenate([jnp.linspace(lo, hi, 101), jnp.linspace(hi, lo, 101)])
        branch = lambda m, a=a, u=u, lo=lo, hi=hi: getattr(m.scanner, a).hysteresis(u, jnp.asarray([hi, lo]))
        grid = jnp.linspace(lo, hi, 101)
        loop = lambda y, mid=mid, grid=grid: (
            jnp.interp(mid, grid, y[101:][::-1]) - jnp.interp(mid, grid, y[:101])
        )
        add(
            f"{a}_gain_nm_per_v",
            f"{a} gain",
            "nm/V",
            lambda m, b=branch, span=hi - lo: (b(m)[100] - b(m)[0]) / span,
        )
        add(
            f"{a}_loop_pct_of_travel",
            f"{a} loop at mid-drive",
            "% of travel",
            lambda m, b=branch, t=travel[k]: 100 * loop(b(m)) / t,
        )
        axis = getattr(model.scanner, a)
        if axis.creep is not None:
            add(
                f"{a}_creep_per_decade",
                f"{a} creep",
                "per decade",
                lambda m, a=a: getattr(m.scanner, a).creep.per_decade,
            )
            if axis.creep.onset is not None:
                add(
                    f"{a}_creep_onset_s",
                    f"{a} creep onset",
                    "s",
                    lambda m, a=a: getattr(m.scanner, a).creep.onset,
                )
        if axis.rate_dependence is not None:
            add(
                f"{a}_rate_lag_s",
                f"{a} rate-dependence lag",
                "s",
                lambda m, a=a: getattr(m.scanner, a).rate_dependence.tau,
            )
    for k, scan in enumerate(scans):
        add(f"loop_scan{k}_nm", f"loop in {scan.name}", "nm", lambda m, scan=scan: _scan_loop(m, scan))
    s = model.scanner
    if s.coupling is not None:
        add("coupling_xy", "coupling x from y", "", lambda m: m.scanner.coupling.xy)
        if not model.rotation_free:
            add("coupling_yx", "coupling y from x", "", lambda m: m.scanner.coupling.yx)
    if s.bow is not None:
        add("bow_x_per_nm", "bow x from y^2", "1/nm", lambda m: m.scanner.bow.bx)
        add("bow_y_per_nm", "bow y from x^2", "1/nm", lambda m: m.scanner.bow.by)
    if s.drift is not None:
        add("drift_x_nm_per_s", "drift x", "nm/s", lambda m: m.scanner.drift.velocity[0])
        add("drift_y_nm_per_s", "drift y", "nm/s", lambda m: m.scanner.drift.velocity[1])
    if model.feedback is not None:
        add("edge_delay_s", "edge delay (z signal)", "s", lambda m: m.edge_delay)
    if model.rotation_free:
        add("lattice_angle_deg", "lattice angle", "deg", lambda m: jnp.rad2deg(m.lattice.angle))
    return out


def _scan_loop(model: ScanModel, scan) -> jnp.ndarray:
    """How far (nm) the model's retrace lies behind its trace along the scan's fast axis in the
    middle column, on average over the lines: the loop (and the lag) the scan itself shows."""
    trace, retrace = model.paths(scan)
    mid = scan.raster.pixels // 2
    fast = jnp.asarray(scan.raster.rotation[:, 0])
    return jnp.mean((retrace[:, mid] - trace[:, mid]) @ fast)


def known_misfits(model: ScanModel, scans: tuple) -> jnp.ndarray:
    """How far (in stated sds) each quantity ``model.known`` states lies from its stated value,
    ``(q(model) - known_value) / known_sd`` (k,): the rows of step A's Gaussian prior on what the user knows
    of the scanner (:func:`~jaxafm.identify.stages.prior_rows`). A stated quantity the model
    does not have (creep in a rung without creep) adds no row. Empty when nothing is stated."""
    if not model.known:
        return jnp.zeros(0)
    defined = {d.key: d for d in quantities(model, scans, drive_range(scans))}
    with warnings.catch_warnings():  # an axis's loop over the whole drive may extrapolate
        warnings.filterwarnings("ignore", message="a drive far beyond the model's range")
        rows = [
            (defined[k].of(model) - model.known_value[i]) / model.known_sd[i]
            for i, k in enumerate(model.known)
            if k in defined
        ]
    return jnp.stack(rows) if rows else jnp.zeros(0)
