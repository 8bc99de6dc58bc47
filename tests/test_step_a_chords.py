"""Step A's chord stage and height model against closed forms and images drawn here in NumPy."""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

from jaxafm.identify.chords import background_design
from jaxafm.identify.scan_model import ScanModel, transplant
from jaxafm.identify.stages import level_out
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
