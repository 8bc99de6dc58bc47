"""Chords of lattice features against images drawn here in NumPy, where every edge is known."""

import numpy as np
import pytest

from jaxafm.identify.chords import background_design, find_chords, level


def _discs(shape, centres, radius, height, wall=1.5):
    """Discs of ``radius`` px at ``centres`` (row, col) px, ``height`` nm, with a linear wall
    ``wall`` px wide centred on the radius: exactly half height at the radius."""
    rows, cols = np.mgrid[: shape[0], : shape[1]].astype(float)
    z = np.zeros(shape)
    for r0, c0 in centres:
        d = np.hypot(rows - r0, cols - c0) - radius
        z = np.maximum(z, height * np.clip(0.5 - d / wall, 0, 1))
    return z


CENTRES = [(r, c) for r in (20.3, 52.6, 84.1) for c in (19.7, 51.2, 83.9)]


@pytest.mark.parametrize("scale", [1.0, 20.0])
def test_chord_ends_lie_on_the_drawn_circles_through_a_tilt_a_bow_and_line_offsets(scale):
    """A background 1.5 and 30 times the features' height (a tilt, a bow, line offsets): the
    polynomial is fitted exactly, so the chords do not move with it."""
    shape, radius = (104, 104), 9.0
    z = _discs(shape, CENTRES, radius, 200.0)
    rng = np.random.default_rng(0)
    rows, cols = np.mgrid[: shape[0], : shape[1]] / 100.0
    background = (
        scale * (300 * cols - 120 * rows + 150 * (cols - 0.5) ** 2) + rng.normal(0, 5, shape[0])[:, None]
    )
    chords = find_chords(z + background, pits=False)
    assert len(chords.centres) == 9
    fitted = chords.image.background
    assert np.std((fitted - background) - np.mean(fitted - background)) < 1.0  # nm, of 300 scale nm
    for ends, f in zip(chords.ends, chords.feature):
        centre = np.array(min(CENTRES, key=lambda c: np.hypot(*(np.asarray(c) - chords.centres[f]))))
        # linear interpolation of a linear wall is exact away from the wall's kinks
        assert np.hypot(*(ends - centre).T) == pytest.approx(radius, abs=0.05)
    along = chords.along_lines
    assert 0 < along.sum() < len(along)  # chords along the lines and along the pixel columns


def test_pits_spikes_and_clipped_pixels():
    shape = (104, 104)
    z = -_discs(shape, CENTRES, 9.0, 150.0)
    z[30, 60] += 400.0  # a spike on the surface
    z[52, 51] = z.min() - 1  # clipped pixels in a pit floor: several at the image's lowest value
    z[53, 51] = z[52, 51]
    chords = find_chords(z, pits=True)
    assert len(chords.centres) == 9
    assert chords.image.outliers[30, 60] and chords.image.outliers[52, 51] and chords.image.outliers[53, 51]
    assert chords.image.outliers.sum() == 3
    assert chords.image.height == pytest.approx(150.0, rel=0.01)


def test_features_cut_by_the_edge_and_spikes_are_not_features():
    shape = (104, 104)
    z = _discs(shape, CENTRES + [(50.0, 1.0)], 9.0, 100.0)  # a disc cut by the left edge
    z[70, 70] = 100.0  # a one-pixel spike, as high as the features
    chords = find_chords(z, pits=False)
    assert len(chords.centres) == 9


def test_an_image_without_features_is_refused_by_name():
    flat = np.random.default_rng(1).normal(0, 1, (64, 64))
    with pytest.raises(ValueError, match="scan.png: no feature level stands out"):
        level(flat, pits=False, name="scan.png")


def test_background_design_is_the_legendre_products_up_to_the_order():
    a = background_design((5, 7), order=2)
    assert a.shape == (35, 6)
    assert np.linalg.matrix_rank(a) == 6
