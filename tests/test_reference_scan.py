"""The JAX raster scan against the NumPy references (tests/reference.py).

The references are written from the model's equations: a plain loop over samples, and a
vectorised one that loops only over the sequential stages (plays, lags, the drift's wander).
They are fed the same standard-normal draws as the JAX scanner (drift kicks and
noise), so the whole instrument (hysteresis with dead zones, rate dependence,
creep, coupling, bow, drift, noise, tip dilation, feedback lag) must agree to rounding.
"""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from reference import (
    numpy_grating_image,
    numpy_grating_images,
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
KEY = jax.random.key(7)
IMAGES = ("trace", "retrace", "path_trace", "path_retrace")


def with_rate_dependence(afm):
    for ax, tau in (("x", 2e-3), ("y", 5e-3)):
        afm = eqx.tree_at(
            lambda a: getattr(a.scanner, ax).rate_dependence,
            afm,
            RateDependence(jnp.asarray(tau)),
            is_leaf=lambda v: v is None,
        )
    return afm


@functools.cache
def jax_scan():
    """Every effect on, with a strong wander so that a mismatched draw would show: the AFM and
    its JAX raster scan from U0, T0 after HISTORY, computed once for the tests below."""
    afm = with_rate_dependence(default_afm(drift_sigma=5.0))
    state = afm.initial_state(U0, t0=T0, history=HISTORY)
    return afm, eqx.filter_jit(raster_scan)(afm, SAMPLE, state, RASTER, key=KEY)


def numpy_scan(afm, vectorised=False, probe="exact", key=KEY):
    """``raster_scan_numpy`` of the tests' scan; ``probe``: the exact grating image (``exact``)
    or the default, ``max`` over the tip's stencil (``stencil``). The vectorised scan runs in
    blocks of 7 samples, so that the state it carries from block to block is checked."""
    drift, noise = (None, None) if key is None else raster_normals(key, RASTER)
    image = numpy_grating_images if vectorised else numpy_grating_image
    probe = image(SAMPLE, afm.tip) if probe == "exact" else None
    return raster_scan_numpy(
        afm,
        numpy_height(SAMPLE),
        RASTER,
        drift,
        noise,
        U0,
        T0,
        HISTORY,
        probe=probe,
        vectorised=vectorised,
        block=7,
    )


def roundoff_bound(afm, ref):
    """Round-off bound on the difference of two implementations of the scan (nm).

    Each stage is memoryless (a fixed handful of roundings per sample) or a contracting linear
    recurrence (the plays, lags and the wander: |a| <= 1), whose per-step roundings add up at
    most over the T samples without growing. So |difference| <= c T eps |path|, with c = 8
    roundings per sample on each side; the probe turns a path error into a height error at most
    the steepest tip or wall slope (>= 1) times larger.
    """
    slope = max(1.0, 1.0 / np.tan(float(afm.tip.half_angle)), float(SAMPLE.depth / SAMPLE.edge_width))
    return 8 * ref["t"].size * np.finfo(float).eps * np.max(np.abs(ref["path"])) * slope


def assert_close(got, ref, bound):
    for name in IMAGES:
        g, want = np.asarray(got[name]), ref[name]
        assert g.shape == want.shape, name
        assert np.max(np.abs(g - want)) <= bound, (name, np.max(np.abs(g - want)), bound)


def test_raster_scan_matches_numpy_reference():
    afm, out = jax_scan()
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
    ref = numpy_scan(afm)

    for name in IMAGES:
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
    still = numpy_scan(afm.without("drift", "noise"), key=None)
    assert np.max(np.abs(still["path_trace"] - ref["path_trace"])) > 1.0


def test_vectorised_numpy_scan_matches_jax_and_loop():
    """The vectorised baseline of experiments/bench_scan.py against the JAX scan and the loop."""
    afm, out = jax_scan()
    vec, loop = numpy_scan(afm, vectorised=True), numpy_scan(afm)
    bound = roundoff_bound(afm, loop)
    assert_close({n: getattr(out, n) for n in IMAGES}, vec, bound)
    assert_close(loop, vec, bound)
    np.testing.assert_allclose(vec["recorded"][-1:], np.asarray(out.state.z), rtol=0, atol=bound)
    assert np.ptp(vec["trace"]) > 100.0 and np.ptp(vec["path_trace"][..., 0]) > 1000.0


@pytest.mark.parametrize("off", [(), ("tip",), ("drift", "noise", "feedback_lag", "creep")])
def test_vectorised_numpy_scan_matches_loop(off):
    """The vectorised scan's other branches against the loop: the probe as the maximum over the
    tip's stencil, the bare height without the tip, and a scanner without lags or random draws."""
    afm = jax_scan()[0].without(*off)
    key = None if "drift" in off else KEY
    loop = numpy_scan(afm, probe="stencil", key=key)
    assert_close(loop, numpy_scan(afm, vectorised=True, probe="stencil", key=key), roundoff_bound(afm, loop))
