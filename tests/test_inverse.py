"""The numerical inverse over blocks of samples against the sample-by-sample one it replaced.

``reference.numerical_inverse_per_sample`` is the inverse as it stepped before: one scan step
per sample, the lags solved by evaluating them at 0 and 1, ``invert_step`` from the plays.
The new one must give the same drive: its forward output within 1e-9 nm of the old drive's
(the issue's bound; both are float64 round-off, about 1e-11 nm here). Drives are compared
at 1e-11 V: 1e-9 nm at 100 nm/V, the steepest slope of these models (the uniform Preisach
plane's at the end of a major branch; the PI operators' is under 75 nm/V).
The truth the inverse is held to is the forward model, which shares no code with it.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from reference import numerical_inverse_per_sample

from jaxafm.identify.inverse import inverse_and_state, invert_axis, numerical_inverse
from jaxafm.model.effects import Bow, Coupling, Creep, RateDependence
from jaxafm.model.hysteresis import Deadzone, GeneralizedPI, Linear, PrandtlIshlinskii, Preisach
from jaxafm.model.scanner import Axis, Scanner

NM, VOLT = 1e-9, 1e-11  # forward outputs (nm) and drives (V) of the two inverses agree to these
U_MAX = 10.0
T = 150
t = 0.05 + 1e-3 * jnp.arange(1, T + 1)  # after the state's last sample at 0.05 s


def pi():
    return PrandtlIshlinskii.with_loop_width(8, 2 * U_MAX, 1000.0, 0.15)


def hysteresis(kind: str):
    if kind == "pi":
        return pi()
    if kind == "gpi":
        dz = Deadzone(
            jnp.asarray(1.0), jnp.array([100.0, 300.0]), jnp.array([-0.1, -0.15]),
            jnp.array([-100.0, -300.0]), jnp.array([0.08, 0.1]),
        )  # fmt: skip
        return GeneralizedPI(pi(), dz)
    if kind == "preisach":
        return Preisach.uniform(8, -U_MAX, U_MAX, total=500.0)
    return Linear(jnp.asarray(50.0), jnp.asarray(3.0))


def scanner(x: str, y: str, hold: str = "zero") -> Scanner:
    """Two axes with rate dependence (a lag of 2 samples, its input held between samples as
    ``hold`` says) and creep, with coupling and bow."""
    axis = lambda kind: Axis(
        hysteresis(kind), RateDependence(jnp.asarray(2e-3), hold), Creep.logarithmic(0.02, 1e-3, 1.0, 2)
    )
    return Scanner(axis(x), axis(y), Coupling(jnp.asarray(0.02), jnp.asarray(-0.012)), Bow(2e-5, -1e-5))


def moved(model: Scanner):
    """A state away from rest, after an input history and 50 samples of drive: the state, the
    last drive (2,) V and where the model stands (2,) nm."""
    history = jnp.array([[-10.0, -10.0], [10.0, 9.0], [-4.0, -6.0], [6.0, 3.0]])
    state = model.initial_state(jnp.array([2.0, -1.0]), 0.0, history)
    s = 1e-3 * jnp.arange(1, 51)
    u = jnp.stack([2 + 3 * jnp.sin(60 * s), -1 + 4 * jnp.sin(45 * s)], -1)
    out, state = model.run(u, s, state)
    return state, u[-1], out[-1]


def path(here, scale: float = 1.0):
    """A wanted path (T, 2) nm from ``here``; at ``scale`` 3.5 it runs past the drive limits."""
    s = t - t[0] + 1e-3
    return here + scale * jnp.stack([-150 * jnp.sin(40 * s), 200 * jnp.sin(30 * s)], -1)


def both(model, wanted, state, u0):
    new = numerical_inverse(model, wanted, t, state, u0, U_MAX)
    old = numerical_inverse_per_sample(model, wanted, t, state, u0, U_MAX)
    return new, old


def assert_same(model, state, new, old):
    (u, sat), (u_ref, sat_ref) = new, old
    np.testing.assert_array_equal(sat, sat_ref)
    np.testing.assert_allclose(u, u_ref, rtol=0, atol=VOLT)
    out, out_ref = model.run(u, t, state)[0], model.run(u_ref, t, state)[0]
    np.testing.assert_allclose(out, out_ref, rtol=0, atol=NM)


@pytest.mark.parametrize("x, y", [("pi", "gpi"), ("preisach", "linear")])
@pytest.mark.parametrize("scale", [1.0, 3.5])
def test_blocked_inverse_equals_the_sample_by_sample_one(x, y, scale):
    # PI and generalised PI run the blocked path, Preisach steps (Newton) sample by sample;
    # at scale 3.5 the path leaves the drive limits and the blocked axes fall back to stepping
    model = scanner(x, y)
    state, u0, here = moved(model)
    new, old = both(model, path(here, scale), state, u0)
    assert bool(new[1].any()) == (scale > 1)
    assert_same(model, state, new, old)


@pytest.mark.parametrize("hold", ["zero", "linear"])
def test_the_forward_model_of_the_drive_follows_the_wanted_path(hold):
    # the truth: the model run on the inverse's drive, code the inverse does not use
    for x, y in [("pi", "gpi"), ("preisach", "linear")]:
        model = scanner(x, y, hold)
        state, u0, here = moved(model)
        u, saturated = numerical_inverse(model, path(here), t, state, u0, U_MAX)
        assert not saturated.any()
        np.testing.assert_allclose(model.run(u, t, state)[0], path(here), rtol=0, atol=NM)


def test_saturated_samples_stay_at_the_limits_and_the_rest_follows_the_path():
    model = scanner("pi", "gpi")
    state, u0, here = moved(model)
    u, saturated = numerical_inverse(model, path(here, 3.5), t, state, u0, U_MAX)
    assert saturated.any() and not saturated.all()
    np.testing.assert_array_equal(np.abs(np.asarray(u)[np.asarray(saturated)]), U_MAX)
    assert np.all(np.abs(np.asarray(u)) <= U_MAX)


def test_a_state_no_input_history_gives_is_inverted_sample_by_sample():
    # plays that break |p_k+1 - p_k| <= r_k+1 - r_k: the closed form does not hold, the axis steps
    model = scanner("pi", "gpi")
    state, u0, here = moved(model)
    odd = state.x.plays.at[3].add(0.5)
    state = type(state)(
        type(state.x)(odd, state.x.lag, state.x.creep), state.y, state.wander, state.t, state.origin
    )
    assert_same(model, state, *both(model, path(here), state, u0))


def test_the_state_after_the_drive_is_the_models():
    model = scanner("pi", "gpi")
    state, u0, here = moved(model)
    for scale in (1.0, 3.5):
        u, _, after = inverse_and_state(model, path(here, scale), t, state, u0, U_MAX)
        run = model.run(u, t, state)[1]
        for a, b in ((after.x, run.x), (after.y, run.y)):
            np.testing.assert_allclose(a.plays, b.plays, rtol=0, atol=VOLT)
            for la, lb in zip(
                jax.tree_util.tree_leaves((a.lag, a.creep)), jax.tree_util.tree_leaves((b.lag, b.creep))
            ):
                np.testing.assert_allclose(la, lb, rtol=0, atol=NM)
        assert float(after.t) == float(t[-1])


def test_under_vmap_a_saturating_trial_does_not_change_the_others():
    # the fallback is a while_loop: batched, it runs for the batch when one trial needs it
    model = scanner("pi", "gpi")
    state, u0, here = moved(model)
    wanted = jnp.stack([path(here, 1.0), path(here, 3.5), path(here, 0.5)])
    u, saturated = jax.vmap(lambda w: numerical_inverse(model, w, t, state, u0, U_MAX))(wanted)
    for k in range(3):
        one = numerical_inverse(model, wanted[k], t, state, u0, U_MAX)
        np.testing.assert_array_equal(saturated[k], one[1])
        np.testing.assert_allclose(u[k], one[0], rtol=0, atol=VOLT)


def test_invert_axis_is_the_inverse_of_one_axis():
    model = scanner("gpi", "preisach")
    state, u0, here = moved(model)
    plain = Scanner(model.x, model.y)
    for k, (axis, s) in enumerate(((model.x, state.x), (model.y, state.y))):
        u, saturated = invert_axis(axis, path(here)[:, k], t, s, state.t, u0[k], -U_MAX, U_MAX)
        u_ref, _ = numerical_inverse_per_sample(plain, path(here), t, state, u0, U_MAX)
        assert not saturated.any()
        np.testing.assert_allclose(u, u_ref[:, k], rtol=0, atol=VOLT)


@pytest.mark.parametrize("kind", ["pi", "gpi", "linear"])
def test_invert_run_inverts_run_from_a_state(kind):
    H = hysteresis(kind)
    plays = H.initial_state(0.0, jnp.array([-10.0, 10.0, -3.0, 5.0, 1.0]))
    u = 8 * jnp.sin(jnp.linspace(0, 9, 200)) * jnp.linspace(1, 0.3, 200)
    y, after = H.run(u, plays)
    u_back, exact = H.invert_run(y, plays)
    assert exact
    np.testing.assert_allclose(u_back, u, rtol=0, atol=VOLT)
    b = H.block_inverse(plays)
    np.testing.assert_allclose(b.state(b.plays), plays, rtol=0, atol=1e-13)  # inverse plays and back


def test_operators_without_a_block_inverse_say_so():
    assert not Preisach.uniform(4, -1.0, 1.0).has_block_inverse
    assert (
        pi().has_block_inverse
        and hysteresis("gpi").has_block_inverse
        and hysteresis("linear").has_block_inverse
    )
    with pytest.raises(TypeError, match="sample by sample"):
        Preisach.uniform(4, -1.0, 1.0).block_inverse(jnp.zeros(4))
