"""The JAX raster scan against the NumPy sample-by-sample reference (tests/reference.py).

The reference is a plain loop over samples written from the model's equations;
it is fed the same standard-normal draws as the JAX scanner (drift kicks and
noise), so the whole instrument (hysteresis with dead zones, rate dependence,
creep, coupling, bow, drift, noise, tip dilation, feedback lag) must agree to rounding.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from reference import (
    numpy_grating_image,
    numpy_height,
    raster_normals,
    raster_scan_numpy,
)

from jaxafm import RateDependence
from jaxafm.instrument.afm import Raster, default_afm, raster_scan
from jaxafm.instrument.samples import Grating

RASTER = Raster(size=(8000.0, 8000.0), pixels=16, lines=4, line_rate=2.0, centre=(100.0, -200.0))
SAMPLE = Grating(
    jnp.asarray(3000.0), jnp.asarray(550.0), edge_width=jnp.asarray(400.0), angle=jnp.asarray(0.3)
)
HISTORY = [[-10.0, -10.0], [10.0, 10.0]]  # the initialisation cycle, then rest at U0
U0, T0 = (1.5, -2.0), 1.25


def with_rate_dependence(afm):
    for ax, tau in (("x", 2e-3), ("y", 5e-3)):
        afm = eqx.tree_at(
            lambda a: getattr(a.scanner, ax).rate_dependence,
            afm,
            RateDependence(jnp.asarray(tau)),
            is_leaf=lambda v: v is None,
        )
    return afm


def test_raster_scan_matches_numpy_reference():
    # every effect on, with a strong wander so that a mismatched draw would show
    afm = with_rate_dependence(default_afm(drift_sigma=5.0))
    assert afm.effects >= {
        "hysteresis",
        "asymmetry",
        "rate_dependence",
        "creep",
        "coupling",
        "bow",
        "drift",
        "noise",
        "tip",
        "feedback_lag",
    }
    key = jax.random.key(7)
    state = afm.initial_state(U0, t0=T0, history=HISTORY)
    out = eqx.filter_jit(raster_scan)(afm, SAMPLE, state, RASTER, key=key)
    drift, noise = raster_normals(key, RASTER)
    probe = numpy_grating_image(SAMPLE, afm.tip)
    ref = raster_scan_numpy(afm, numpy_height(SAMPLE), RASTER, drift, noise, U0, T0, HISTORY, probe=probe)

    for name in ("trace", "retrace", "path_trace", "path_retrace"):
        got, want = np.asarray(getattr(out, name)), ref[name]
        assert got.shape == want.shape, name
        scale = np.max(np.abs(want))
        assert np.max(np.abs(got - want)) <= 1e-9 * scale, (name, np.max(np.abs(got - want)), scale)
    np.testing.assert_allclose(
        np.asarray(out.t_trace), ref["t"][32:].reshape(4, 2, -1)[:, 0, 2:18], rtol=1e-15
    )
    np.testing.assert_allclose(np.asarray(out.state.z), ref["recorded"][-1:], rtol=1e-9)
    # not vacuous: the scan crosses the grating's lines, and the random draws move the tip
    assert np.ptp(ref["trace"]) > 100.0
    still = raster_scan_numpy(
        afm.without("drift", "noise"), numpy_height(SAMPLE), RASTER, None, None, U0, T0, HISTORY, probe=probe
    )
    assert np.max(np.abs(still["path_trace"] - ref["path_trace"])) > 1.0
