"""Simulated data with one effect the nominal model lacks: the test bench of ``jaxafm diagnose``.

Actuator records (:func:`simulate_record`) come from the default scanner reduced to symmetric
PI hysteresis and white noise; scan sets (:func:`simulate_scans`) are trace/retrace images of a
1-D grating (or a 2-D pit lattice) by the simulated AFM with that scanner, an ideal tip and an
ideal z-feedback. One
``withheld`` effect is switched on at a ``magnitude`` (units: :data:`RECORD_UNITS`,
:data:`SCAN_UNITS`); none makes a control.
"""

from __future__ import annotations

from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..config import ScanSample
from ..instrument.afm import AFM, Raster, raster_scan
from ..instrument.records import Record
from ..instrument.samples import Grating, Lattice, Tip
from ..model.effects import Bow, Coupling, Creep, Drift, FeedbackAsymmetry, FeedbackLag, RateDependence
from ..model.scanner import Scanner, default_scanner
from .scans import ScanPair

#: Unit of the ``magnitude`` of a withheld effect in :func:`simulate_record`.
RECORD_UNITS = {
    "asymmetry": "x default dead zones",
    "rate_dependence": "s",
    "creep": "per decade",
    "drift": "nm/s",
    "coupling": "dimensionless",
    "bow": "1/nm",
}


def simulated_scanner(withheld: Optional[str], magnitude: float, noise_nm: float) -> Scanner:
    """:func:`default_scanner` with symmetric PI hysteresis and white noise only, plus ``withheld``
    at ``magnitude`` (unit: :data:`RECORD_UNITS`)."""
    full = default_scanner(noise_std=noise_nm, creep_gamma=0.0)
    base = full.without("asymmetry", "creep", "coupling", "bow", "drift")
    if withheld is None:
        return base
    if withheld not in RECORD_UNITS:
        raise ValueError(
            f"simulate.withheld: {withheld!r} cannot be simulated in an actuator record; "
            f"one of {', '.join(RECORD_UNITS)}"
        )
    m = jnp.asarray(float(magnitude))
    if withheld == "asymmetry":
        scaled = full.without("creep", "coupling", "bow", "drift")
        for ax in ("x", "y"):
            for side in ("upper_weights", "lower_weights"):
                get = lambda s, ax=ax, side=side: getattr(getattr(s, ax).hysteresis.deadzone, side)
                scaled = eqx.tree_at(get, scaled, m * get(scaled))
        return scaled
    if withheld in ("rate_dependence", "creep"):
        stage = RateDependence(m) if withheld == "rate_dependence" else Creep.logarithmic(float(magnitude))
        return eqx.tree_at(
            lambda s: (getattr(s.x, withheld), getattr(s.y, withheld)),
            base,
            (stage, stage),
            is_leaf=lambda v: v is None,
        )
    module = {
        "coupling": lambda: Coupling(m, -0.6 * m),
        "bow": lambda: Bow(m, -0.5 * m),
        "drift": lambda: Drift(jnp.stack([m, -0.6 * m]), jnp.full(2, 0.05), jnp.asarray(1e-3)),
    }[withheld]()
    return eqx.tree_at(lambda s: getattr(s, withheld), base, module, is_leaf=lambda v: v is None)


def simulate_record(
    withheld: Optional[str] = None,
    magnitude: float = 0.0,
    seed: int = 0,
    duration_s: float = 20.0,
    sample_rate_hz: float = 100.0,
    noise_nm: float = 2.0,
    amplitude_v: float = 9.0,
) -> Record:
    """A two-axis record of :func:`simulated_scanner`, each axis driven by
    ``u = A e(t) sin(phi(t))``, ``e(t) = 0.55 + 0.45 cos(2 pi t / 10 s)``, at a frequency
    ``phi'/2 pi`` swept between 0.2 and 1.8 Hz (x) and 0.3 and 1.3 Hz (y), so that
    loops of many sizes and speeds appear."""
    t = np.arange(int(round(duration_s * sample_rate_hz))) / sample_rate_hz
    env = lambda s: 0.55 + 0.45 * np.cos(2 * np.pi * s / 10.0)
    phase = lambda f0, df, period: (
        2 * np.pi * (f0 * t + df * period / (2 * np.pi) * (1 - np.cos(2 * np.pi * t / period)))
    )
    u = amplitude_v * np.stack(
        [env(t) * np.sin(phase(1.0, 0.8, 7.0)), env(t + 5.0) * np.sin(phase(0.8, 0.5, 9.0))], -1
    )
    truth = simulated_scanner(withheld, magnitude, noise_nm)
    d = np.asarray(truth(jnp.asarray(u), jnp.asarray(t), key=jax.random.key(seed)))
    unit = RECORD_UNITS.get(withheld, "")
    meta = {
        "source": f"simulated: PI scanner + noise {noise_nm} nm"
        + (f" + {withheld} {magnitude:g} {unit}" if withheld else ""),
        "samples": len(t),
    }
    return Record(t, u, d, meta)


#: Unit of the ``magnitude`` of a withheld effect in :func:`simulate_scans`.
SCAN_UNITS = {
    "feedback_lag": "s",
    "feedback_asymmetry": "s (tau_fall; tau_rise = 0.1 tau_fall)",
    "tip": "nm (apex radius)",
    "rate_dependence": "s",
}
#: tau_rise / tau_fall of a simulated ``feedback_asymmetry``.
RISE_RATIO = 0.1
#: The simulated calibration grating: 400 nm pitch, 30 nm deep, 60-degree walls (17.3 nm ramps).
SIM_GRATING = ScanSample(pitch_nm=400.0, edge_width_nm=30.0 / np.tan(np.deg2rad(60.0)))
SIM_DEPTH_NM = 30.0
#: The simulated 2-D lattice: round pits 150 nm in radius, 30 nm deep, with the grating's walls,
#: on a square lattice of 400 nm.
SIM_LATTICE = ScanSample(kind="lattice", pitch_nm=[400.0, 400.0], edge_width_nm=SIM_GRATING.edge_width_nm)
SIM_PIT_RADIUS_NM = 150.0
SETTLE_LINES = 2  # the first lines run while the scanner's loop settles: dropped


def simulate_scans(
    withheld: Optional[str] = None,
    magnitude: float = 0.0,
    seed: int = 0,
    line_rates_hz=(1.0, 4.0),
    lines: int = 24,
    pixels: int = 512,
    size_nm: float = 2000.0,
    noise_nm: float = 0.5,
    sample: str = "lines",
) -> list:
    """Trace/retrace images of :data:`SIM_GRATING` (``sample="lines"``) or :data:`SIM_LATTICE`
    (``"lattice"``) by the simulated AFM at each line rate (slowest first, one scan after the
    other): the symmetric-PI scanner of :func:`simulated_scanner` (``noise_nm`` lateral noise),
    an ideal tip and feedback, plus ``withheld`` at ``magnitude`` (:data:`SCAN_UNITS`). Returns
    :class:`ScanPair` s."""
    if withheld is not None and withheld not in SCAN_UNITS:
        raise ValueError(
            f"simulate.withheld: {withheld!r} cannot be simulated in a scan set; "
            f"one of {', '.join(SCAN_UNITS)}"
        )
    scanner = simulated_scanner(
        "rate_dependence" if withheld == "rate_dependence" else None, magnitude, noise_nm
    )
    radius = float(magnitude) if withheld == "tip" else 10.0
    tip = Tip(jnp.asarray(radius), jnp.asarray(np.deg2rad(SIM_GRATING.tip_half_angle_deg)))
    m = jnp.asarray(float(magnitude))
    feedback = {
        "feedback_lag": lambda: FeedbackLag(m),
        "feedback_asymmetry": lambda: FeedbackAsymmetry(RISE_RATIO * m, m),
    }.get(withheld, lambda: None)()
    afm = AFM(scanner, tip, jnp.full(2, 500.0), feedback, u_max=10.0, dilate=withheld == "tip")
    if sample not in ("lines", "lattice"):
        raise ValueError(f"simulate.sample: {sample!r} is no simulated sample; one of lines, lattice")
    if sample == "lattice":
        sample = Lattice(
            jnp.asarray(SIM_LATTICE.pitch_nm),
            jnp.asarray(SIM_PIT_RADIUS_NM),
            jnp.asarray(-SIM_DEPTH_NM),
            edge_width=jnp.asarray(SIM_LATTICE.edge_width_nm),
            phase=jnp.asarray([37.0, 20.0]),
        )
    else:
        sample = Grating(
            jnp.asarray(SIM_GRATING.pitch_nm),
            jnp.asarray(SIM_DEPTH_NM),
            edge_width=jnp.asarray(SIM_GRATING.edge_width_nm),
            phase=jnp.asarray(37.0),
        )
    state = afm.initial_state()
    out = []
    for i, rate in enumerate(line_rates_hz):
        raster = Raster((size_nm, size_nm / 2), pixels, lines + SETTLE_LINES, line_rate=float(rate))
        img = raster_scan(afm, sample, state, raster, key=jax.random.fold_in(jax.random.key(seed), i))
        state = img.state
        pick = lambda z: np.asarray(z)[SETTLE_LINES:]
        out.append(
            ScanPair(
                pick(img.trace),
                pick(img.retrace),
                raster.pixel_size,
                raster.sample_time,
                f"{rate:g} Hz",
            )
        )
    return out
