"""Step A's chord stage and height model against closed forms and images drawn here in NumPy."""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

from jaxafm.identify.chords import background_design
from jaxafm.identify.scan_model import ScanModel, transplant
from jaxafm.identify.stages import WIDTH_NODES, level_out, width_misfits
from jaxafm.instrument.samples import Lattice
from jaxafm.model.hysteresis import PrandtlIshlinskii
from jaxafm.model.scanner import Axis, Scanner


def test_level_out_removes_a_plane_and_a_bow_and_keeps_the_rest():
    """Closed form: a background of the model's own columns (plane, bow) goes exactly, with or
    without weights; a pattern orthogonal to it stays as it is."""
    shape = (24, 32)
    rng = np.random.default_rng(0)
    background = (background_design(shape) @ rng.normal(0, 50, 6)).reshape(shape)
    rows, cols = np.mgrid[: shape[0], : shape[1]]
    pattern = np.where((rows // 4 + cols // 4) % 2 == 0, 1.0, -1.0)  # a checkerboard: no polynomial in it
    pattern -= (
        background_design(shape) @ np.linalg.lstsq(background_design(shape), pattern.ravel(), rcond=None)[0]
    ).reshape(shape)
    weights = (rng.uniform(size=shape) > 0.3).astype(float)
    np.testing.assert_allclose(level_out(jnp.asarray(background), jnp.ones(shape)), 0.0, atol=1e-8)
    np.testing.assert_allclose(
        np.asarray(level_out(jnp.asarray(background), jnp.asarray(weights))) * weights, 0.0, atol=1e-8
    )
    np.testing.assert_allclose(
        level_out(jnp.asarray(background + pattern), jnp.ones(shape)), pattern, atol=1e-8
    )


def _scan_model(hysteresis) -> ScanModel:
    axis = Axis(hysteresis)
    lattice = Lattice(jnp.full(2, 1000.0), jnp.asarray(250.0), jnp.asarray(100.0))
    return ScanModel(Scanner(axis, axis), None, lattice)


def test_doubled_plays_start_where_the_fewer_plays_ended():
    """A PI operator transplanted onto twice the plays (the ladder's next rung) gives the same
    output on any drive, up to the new plays' small start weights, which are set to zero here."""
    fewer = PrandtlIshlinskii.uniform(4, 10.0, 300.0, others=0.0)
    fewer = eqx.tree_at(lambda p: p.weights, fewer, jnp.asarray([300.0, 40.0, 25.0, 10.0]))
    more = PrandtlIshlinskii.uniform(8, 10.0, 300.0, others=0.0)
    grown = transplant(_scan_model(fewer), _scan_model(more)).scanner.x.hysteresis
    assert grown.weights.shape == (8,)
    u = jnp.asarray(np.concatenate([np.linspace(0, 9, 50), np.linspace(9, -7, 80), np.linspace(-7, 5, 60)]))
    np.testing.assert_allclose(np.asarray(grown(u)), np.asarray(fewer(u)), atol=1e-8)


def test_chord_offsets_vanish_for_chords_of_circles_at_their_sites():
    """Chords of round features placed exactly: every midpoint lies on the line across the chords
    through its feature's site, whatever the chord's direction."""
    model = _scan_model(PrandtlIshlinskii.uniform(1, 10.0, 300.0))
    rng = np.random.default_rng(1)
    ij = rng.integers(-3, 4, (50, 2)).astype(float)
    sites = np.asarray(model.lattice.sites(jnp.asarray(ij)))
    angle = rng.uniform(0, np.pi, 50)
    offset = rng.uniform(-200, 200, 50)  # along the perpendicular: where the chord cuts the circle
    d = np.stack([np.cos(angle), np.sin(angle)], -1)
    p = np.stack([-d[:, 1], d[:, 0]], -1)
    half = np.sqrt(250.0**2 - offset**2)[:, None]
    tips = np.stack([sites + offset[:, None] * p - half * d, sites + offset[:, None] * p + half * d], axis=1)
    along = angle < np.pi / 2
    assert (
        np.abs(np.asarray(model.chord_offsets(jnp.asarray(tips), jnp.asarray(ij), jnp.asarray(along)))).max()
        < 1e-9
    )
    moved = tips + np.array([30.0, 0.0])  # the features 30 nm off their sites: the offset is d . (30, 0)
    out = np.asarray(model.chord_offsets(jnp.asarray(moved), jnp.asarray(ij), jnp.asarray(along)))
    np.testing.assert_allclose(out, 30.0 * d[:, 0], atol=1e-8)


@pytest.mark.parametrize("slope", [0.1, -0.05])
def test_chord_offsets_of_a_turned_square_follow_its_sides(slope):
    """A square turned by atan(slope): the midpoints of chords along x lie on the line along its
    near-vertical sides through the centre, which the model's chord slope describes."""
    model = eqx.tree_at(
        lambda m: m.chord_slope,
        _scan_model(PrandtlIshlinskii.uniform(1, 10.0, 300.0)),
        jnp.asarray([slope, 0.0]),
    )
    y = np.linspace(-150, 150, 7)
    left, right = -200 + slope * y, 200 + slope * y  # x of the sides at height y (sites at 0)
    tips = np.stack([np.stack([left, y], -1), np.stack([right, y], -1)], axis=1)
    ij = np.zeros((7, 2))
    out = np.asarray(model.chord_offsets(jnp.asarray(tips), jnp.asarray(ij), jnp.ones(7, bool)))
    np.testing.assert_allclose(out, 0.0, atol=1e-8)


def _circle_chords(model, rng, n: int, radius: float, offsets: float, sites: int = 0):
    """``n`` chords of round features of ``radius`` nm at random directions and distances (below
    ``offsets`` nm) from their centres, at random sites, or (``sites`` > 0) the same ``n`` at
    each of that many sites: tip positions at their ends (m, 2, 2), the sites' indices (m, 2),
    the chords' directions (m,) and their distances (m,)."""
    angle = rng.uniform(0, np.pi, n)
    offset = rng.uniform(-offsets, offsets, n)
    ij = rng.integers(-3, 4, (n, 2)).astype(float)
    if sites:
        ij = np.repeat(np.stack([np.arange(sites), np.zeros(sites)], -1), n, axis=0)
        angle, offset = np.tile(angle, sites), np.tile(offset, sites)
    centres = np.asarray(model.lattice.sites(jnp.asarray(ij)))
    d = np.stack([np.cos(angle), np.sin(angle)], -1)
    p = np.stack([-d[:, 1], d[:, 0]], -1)
    half = np.sqrt(radius**2 - offset**2)[:, None]
    middle = centres + offset[:, None] * p
    return np.stack([middle - half * d, middle + half * d], axis=1), ij, angle < np.pi / 2, offset


def test_chord_spans_are_a_chords_length_and_distance_from_its_site():
    """Closed form: a chord of a circle of radius R at distance o from its centre is
    2 sqrt(R^2 - o^2) long, whichever way it runs and wherever the site."""
    model = _scan_model(PrandtlIshlinskii.uniform(1, 10.0, 300.0))
    tips, ij, _, offset = _circle_chords(model, np.random.default_rng(2), 40, 250.0, 200.0)
    length, distance = model.chord_spans(jnp.asarray(tips), jnp.asarray(ij))
    np.testing.assert_allclose(length, 2 * np.sqrt(250.0**2 - offset**2), rtol=1e-12)
    np.testing.assert_allclose(distance, np.abs(offset), atol=1e-9)


def test_width_misfits_hold_one_shape_and_find_a_feature_crossed_too_fast():
    """Chords of features of one shape (circles, radius R = 0.25 pitch) fit one length profile
    to within its interpolation error (linear between nodes h = 0.5 / (WIDTH_NODES - 1) pitch
    apart: h^2 / 8 max |f''|, f = 2 sqrt(R^2 - o^2), |f''| <= 2 R^2 / (R^2 - o^2)^(3/2), at most
    three times that for a least-squares fit), halved as the misfits weigh lengths. A path that
    runs 10 % fast across one of seven features (its chords 10 % long, the same chords at each)
    shifts that feature's misfits by 0.5 * 0.1 * L * 6/7 (the profile takes up a seventh of the
    excess) and the others' by -0.5 * 0.1 * L / 7, to within the profile's error on the excess
    (0.1 / 7 of the bound)."""
    model = _scan_model(PrandtlIshlinskii.uniform(1, 10.0, 300.0))
    pitch, radius, reach = 1000.0, 250.0, 150.0
    rng = np.random.default_rng(3)
    tips, ij, along, _ = _circle_chords(model, rng, 100, radius, reach, sites=7)
    length, distance = (np.asarray(v) for v in model.chord_spans(jnp.asarray(tips), jnp.asarray(ij)))
    misfits = lambda lengths: np.asarray(
        width_misfits(
            jnp.asarray(lengths), jnp.asarray(distance), jnp.asarray(along), jnp.ones(len(ij)), pitch
        )
    )
    h = 0.5 / (WIDTH_NODES - 1)
    bound = 3 * h**2 / 8 * 2 * (radius / pitch) ** 2 / ((radius**2 - reach**2) / pitch**2) ** 1.5
    same = misfits(length)
    assert np.abs(same).max() <= 0.5 * bound
    fast = ij[:, 0] == 0
    shift = misfits(np.where(fast, 1.1, 1.0) * length) - same
    expected = 0.5 * 0.1 * length / pitch * np.where(fast, 6 / 7, -1 / 7)
    np.testing.assert_allclose(shift, expected, atol=0.5 * 0.1 / 7 * bound)
