"""The paper's baseline for step A (section III-A): a polynomial per branch of the hysteresis
loop, fitted to the feature points of one trace/retrace pair (:func:`fit_polynomials`). Its
inverse, a network per branch, is :func:`~jaxafm.identify.step_a.paper_inverse`."""

from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np

from .calibration_scan import CalibrationScan


@dataclasses.dataclass(frozen=True)
class BranchPolynomials:
    """Position (nm) against drive (V) per branch, fitted to feature points (paper, section III-A):
    ``x_up`` (trace, rising drive), ``x_down`` (retrace), ``y`` (slow axis; one branch).
    Coefficients highest power first (``numpy.polyval``); ``u_range`` (2, 2) V is the
    drive each axis was fitted over."""

    x_up: np.ndarray
    x_down: np.ndarray
    y: np.ndarray
    u_range: np.ndarray

    def branch(self, name: str, u: np.ndarray) -> np.ndarray:
        """Position (nm) on branch ``name`` (``x_up``, ``x_down``, ``y``) at drive ``u`` (V).
        Outside the fitted drive range the polynomial continues along its end tangent:
        a polynomial of degree 5 extrapolated further runs off within a volt."""
        coef = getattr(self, name)
        lo, hi = self.u_range[0 if name.startswith("x") else 1]
        u = np.asarray(u, dtype=float)
        end = np.clip(u, lo, hi)
        return np.polyval(coef, end) + np.polyval(np.polyder(coef), end) * (u - end)

    def position(self, u: np.ndarray, rising: np.ndarray) -> np.ndarray:
        u = np.asarray(u, dtype=float)
        x = np.where(rising, self.branch("x_up", u[..., 0]), self.branch("x_down", u[..., 0]))
        return np.stack([x, self.branch("y", u[..., 1])], axis=-1)


def fit_polynomials(
    scan: CalibrationScan, features: Optional[tuple] = None, degree: int = 5
) -> BranchPolynomials:
    """Least-squares polynomials of ``degree`` from the feature points of trace and retrace.

    True positions are ``index * pitch`` plus one offset shared by both branches,
    chosen so that the features' mean true position equals their mean nominal one.
    """
    ft, fr = scan.features() if features is None else features
    pitch = np.asarray(scan.pitch)
    ut, ur = scan.volts(ft.rc), scan.volts(fr.rc)
    nominal = np.concatenate([ut, ur]) * np.asarray(scan.sensitivity)
    sites = np.concatenate([ft.ij, fr.ij]) * pitch
    offset = nominal.mean(axis=0) - sites.mean(axis=0)
    xt, xr = ft.ij * pitch + offset, fr.ij * pitch + offset
    for name, n in (
        ("trace x", len(np.unique(ft.ij[:, 0]))),
        ("retrace x", len(np.unique(fr.ij[:, 0]))),
        ("y", len(np.unique(ft.ij[:, 1]))),
    ):
        if n <= degree:
            raise ValueError(
                f"a degree-{degree} polynomial needs more than {degree} distinct {name} feature "
                f"lines, found {n}: lower the degree or use a finer grating"
            )
    u_all = np.concatenate([ut, ur])
    return BranchPolynomials(
        np.polyfit(ut[:, 0], xt[:, 0], degree),
        np.polyfit(ur[:, 0], xr[:, 0], degree),
        np.polyfit(
            np.concatenate([ut[:, 1], ur[:, 1]]), np.concatenate([xt[:, 1], xr[:, 1]]), min(degree, 3)
        ),
        np.stack([u_all.min(axis=0), u_all.max(axis=0)], axis=-1),
    )
