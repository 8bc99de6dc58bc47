"""The model refined while it positions (jaxafm.position.online.Tracker) and the push's gate,
against the simulator's true scanner: a gain error learnt away, a known drift tracked, a push
with low odds withheld; and the filter against the closed-form ridge regression."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxafm.instrument.afm import AFM, default_afm, run_cycle
from jaxafm.instrument.samples import Particles, Plane, Tip
from jaxafm.position import online, push_odds
from jaxafm.position.positioning import Positioner, Push, goto, push_and_check

CYCLE = np.array([[-10.0, -10.0], [10.0, 10.0]])
#: the scatter (nm) of one observed position: a local scan's find
FIND_NM = 1.0


def _stand(afm, model):
    """A positioner through ``model`` and where it stands after the same cycle on the instrument
    and on the model's twin."""
    state = run_cycle(afm, Plane(), afm.initial_state((0.0, 0.0), 0.0, CYCLE), CYCLE, jax.random.key(0))
    twin = AFM(model, Tip(), afm.sensitivity, None, dilate=False)
    tw = run_cycle(twin, Plane(), twin.initial_state((0.0, 0.0), 0.0, CYCLE), CYCLE, jax.random.key(0))
    pos = Positioner(afm, model)
    return pos, pos.start(state, tw.scanner)


def _x_gain(scanner, g):
    """``scanner`` with its x axis's hysteresis output scaled by ``g``: the PI's weights and offset
    and the dead zones' thresholds and centre (each dead zone is homogeneous,
    ``dz_{g d}(g y) = g dz_d(y)``)."""
    h = scanner.x.hysteresis
    parts = lambda h: (h.pi.weights, h.pi.offset, h.deadzone.upper, h.deadzone.lower, h.deadzone.centre)
    h = eqx.tree_at(parts, h, tuple(g * v for v in parts(h)))
    return eqx.tree_at(lambda s: s.x.hysteresis, scanner, h)


@eqx.filter_jit
def _go_each(pos, stand, wanted, keys):
    """The true tip (k, 2) nm after a move to each wanted position, all from ``stand``."""
    return jax.vmap(lambda w, k: goto(pos, Plane(), stand, w, k)[0])(wanted, keys)


def _gains(true_xy, wanted):
    """The 2 x 2 matrix of the affine least-squares map from wanted to true positions."""
    A = np.column_stack([np.ones(len(wanted)), wanted])
    return np.linalg.lstsq(A, true_xy, rcond=None)[0][1:].T


def test_split_updates_give_the_ridge_regression_and_its_posterior_covariance():
    # without drift the filter's posterior is the closed-form Bayesian linear regression:
    # mean (F^T F + s^2/p^2 I)^-1 F^T Y, covariance s^2 (F^T F + s^2/p^2 I)^-1, however the
    # observations are split into updates
    rng = np.random.default_rng(0)
    centre, half, prior, noise = np.array([200.0, -100.0]), 1500.0, 100.0, 2.0
    p = centre + rng.uniform(-half, half, (50, 2))
    y = rng.normal(0, 30, (50, 2))
    F = online.quadratic(p, centre, half)
    A = F.T @ F + (noise / prior) ** 2 * np.eye(6)
    tracker = online.Tracker.start(centre, half, prior, noise)
    for part in np.array_split(np.arange(50), [7, 8, 31]):
        tracker = tracker.observe(p[part], y[part])
    field = tracker.field()
    np.testing.assert_allclose(field.coef, np.linalg.solve(A, F.T @ y), atol=1e-8)
    np.testing.assert_allclose(field.cov, noise**2 * np.linalg.inv(A), rtol=1e-9)


def test_a_model_with_a_ten_percent_gain_error_is_refined_to_the_true_gain_within_one_percent():
    # the true scanner (default_afm without drift) driven through a model whose x output is 0.9 of
    # the truth's: the tip truly goes 1/0.9 as far along x as wanted. Thirty moves, each seen to
    # FIND_NM, refine the model (the tracker's field, its gain and coupling terms); thirty moves to
    # new places through it then go where they are wanted: the gain from wanted to true positions
    # within 1 % of the truth's, 1 (the true model's exact inverse)
    afm = default_afm()
    afm = eqx.tree_at(lambda a: a.scanner, afm, afm.scanner.without("drift"))
    model = _x_gain(afm.scanner.without("noise"), 0.9)
    pos, stand = _stand(afm, model)
    rng = np.random.default_rng(2)
    half = 1500.0
    wanted = rng.uniform(-half, half, (30, 2))
    truly = np.asarray(_go_each(pos, stand, jnp.asarray(wanted), jax.random.split(jax.random.key(1), 30)))
    before = _gains(truly, wanted)
    assert abs(before[0, 0] - 1 / 0.9) < 0.01  # the error the model starts with
    seen = truly + rng.normal(0, FIND_NM, truly.shape)
    field = online.Tracker.start(np.zeros(2), half, 100.0, FIND_NM).observe(seen, wanted - seen).field()
    new = rng.uniform(-half, half, (30, 2))
    keys = jax.random.split(jax.random.key(2), 30)
    after = _gains(np.asarray(_go_each(pos, stand, jnp.asarray(new + field(new)), keys)), new)
    np.testing.assert_allclose(np.diag(after), 1.0, atol=0.01)
    assert np.max(np.abs(after - np.eye(2))) < 0.01


def test_the_drift_state_tracks_a_known_drift():
    # the true scanner drifts at (1.0, -0.6) nm/s plus a wander of 0.3 nm/sqrt(s); the model is
    # the truth without drift. Forty moves 5.1 s apart, each to where the tracker predicts the
    # target needs, each seen to FIND_NM and fed back: the drift moves the tip over 200 nm, the
    # tracked moves stay within a few nm (the find's scatter, the wander between moves: the
    # predicted sd is about 1.5 nm), and the drift's velocity comes out as the truth's to within
    # what the wander allows over the run (0.3 nm/sqrt(s) over 200 s: about 0.03 nm/s)
    velocity, wander = np.array([1.0, -0.6]), 0.3
    afm = default_afm(drift_nm_per_min=tuple(60 * velocity), drift_sigma=wander)
    pos, stand = _stand(afm, afm.scanner.without("drift", "noise"))
    step = eqx.filter_jit(lambda pos, stand, w, key: goto(pos, Plane(), stand, w, key, dwell=5.0))
    t0 = float(stand.afm.scanner.t)
    kw = dict(centre=np.zeros(2), half=1500.0, prior_nm=100.0, noise_nm=FIND_NM, time=t0)
    tracking = online.Tracker.start(velocity_prior=2.0, walk=wander**2, **kw)
    static = online.Tracker.start(**kw)
    rng = np.random.default_rng(1)
    misses, z, static_misses = [], [], []
    for k in range(40):
        target = rng.uniform(-1500, 1500, 2)
        offset, sd = tracking.predict(target[None], float(stand.afm.scanner.t) + 5.1)
        xy, _, stand = step(pos, stand, jnp.asarray(target + offset[0]), jax.random.key(k))
        miss = np.asarray(xy) - target
        misses.append(np.linalg.norm(miss))
        z.append(miss / np.hypot(sd[0], 0.2))  # 0.2 nm: the truth's own position noise
        static_misses.append(np.linalg.norm(miss + offset[0] - static.predict(target[None])[0][0]))
        seen = np.asarray(xy) + rng.normal(0, FIND_NM, 2)
        t = float(stand.afm.scanner.t)
        tracking = tracking.observe(seen[None], (target + offset[0] - seen)[None], [t])
        static = static.observe(seen[None], (target + offset[0] - seen)[None])
    assert t - t0 > 200 and static_misses[-1] > 100  # a static field is left behind by the drift
    assert max(misses[10:]) < 5.0, misses
    assert 0.6 < np.sqrt(np.mean(np.square(z[10:]))) < 1.5  # the predicted sd is the miss's
    np.testing.assert_allclose(-tracking.mean[online.VELOCITY], velocity, atol=0.1)


def test_a_push_whose_predicted_success_is_low_is_withheld():
    # two particles of R = 20 nm, each pushed 300 nm. The odds of each push come from eight pushes
    # of 200-400 nm checked before it (push_odds): one history misses by 0.3 nm or so, the other falls 12 nm
    # short every time, beyond the 5 nm tolerance. With min_odds 0.99 the first push is made and
    # moves its particle to the goal; the second is withheld and its particle stays where it was
    afm = default_afm(drift_nm_per_min=(0.0, 0.0))
    pos, stand = _stand(afm, afm.scanner.without("drift", "noise"))
    rng = np.random.default_rng(3)
    distance = np.append(rng.uniform(200.0, 400.0, 8), 300.0)
    tolerance = 0.25 * 20.0
    odds = []
    for short in (0.0, -12.0):
        along = np.append(short + rng.normal(0, 0.3, 8), np.nan)
        across = np.append(rng.normal(0, 0.3, 8), np.nan)
        push = distance[:, None] * [1.0, 0.0]
        miss = push_odds.online_misses(push, np.stack([along, across], -1), np.arange(9) < 8)
        odds.append(float(push_odds.success_probability(miss, tolerance)[-1]))
    assert odds[0] > 0.99 > 0.01 > odds[1]
    spec = Push(corrections=0, min_odds=0.99)
    centres = jnp.array([[300.0, -200.0], [-250.0, 400.0]])
    direction = jnp.array([1.0, 0.0])

    @eqx.filter_jit
    def push_each(pos, stand, odds):
        def one(c, chance, key):
            sample = Particles(c[None], jnp.array([20.0]))
            return push_and_check(pos, sample, stand, c, c, 20.0, direction, 300.0, key, spec, odds=chance)[0]

        return jax.vmap(one)(centres, odds, jax.random.split(jax.random.key(4), 2))

    checked = push_each(pos, stand, jnp.asarray(odds))
    np.testing.assert_array_equal(np.asarray(checked.withheld), [False, True])
    goal = np.asarray(centres[0] + 300.0 * direction)
    assert bool(checked.first.contact[0]) and np.linalg.norm(np.asarray(checked.final[0]) - goal) < tolerance
    np.testing.assert_array_equal(np.asarray(checked.final[1]), np.asarray(centres[1]))
