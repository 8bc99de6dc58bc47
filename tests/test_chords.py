"""Chords of lattice features against images drawn here in NumPy, where every edge is known."""

from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

import jaxafm.data
from jaxafm.identify.chords import background_design, find_chords, level
from jaxafm.identify.held_out import chord_centres
from jaxafm.instrument.images import read_image

REAL = Path(jaxafm.data.__file__).parent / "real"


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


@pytest.mark.parametrize("pits", [False, True])
def test_dust_taller_than_the_features_is_neither_their_height_nor_a_feature(pits):
    """Specks of 3 x 3 px three times the features' height, over 1 % of the image (more than
    the 0.5 % above the 99.5th percentile that sets the features' level), on the surface between
    the features, standing up out of it (dust) on pillars and, for the pits, sunk into it."""
    shape, radius = (104, 104), 9.0
    z = _discs(shape, CENTRES, radius, 200.0) + np.random.default_rng(0).normal(0, 1.0, shape)
    specks = [(r, c) for r in (4, 36, 68, 99) for c in (4, 36, 68, 99)]  # between the discs
    for r, c in specks:
        z[r - 1 : r + 2, c - 1 : c + 2] += 600.0
    assert len(specks) * 9 > 0.01 * z.size
    chords = find_chords(-z if pits else z, pits=pits)
    assert chords.image.height == pytest.approx(200.0, rel=0.01)
    assert len(chords.centres) == 9
    for ends, f in zip(chords.ends, chords.feature):
        centre = np.array(min(CENTRES, key=lambda c: np.hypot(*(np.asarray(c) - chords.centres[f]))))
        assert np.hypot(*(ends - centre).T) == pytest.approx(radius, abs=0.5)  # the noise: 1 nm of 200


@pytest.mark.parametrize("pits", [False, True])
def test_dust_on_a_features_wall_ends_no_chord(pits):
    """Specks three times the features' height on the walls of the discs, too few to take the
    features' level: a chord that crossed into a speck would end at its far side, up to its
    width off the drawn circle. Pixels more than half the features' height beyond both the
    surface and the features' level are outliers, and every chord kept lies on its circle."""
    shape, radius = (104, 104), 9.0
    z = _discs(shape, CENTRES, radius, 200.0) + np.random.default_rng(0).normal(0, 1.0, shape)
    for r, c in CENTRES:  # one speck on each disc's left wall, one on its top wall
        for i, j in ((round(r), round(c - radius)), (round(r + radius), round(c))):
            z[i - 1 : i + 2, j - 1 : j + 2] += 600.0
    chords = find_chords(-z if pits else z, pits=pits)
    assert len(chords.centres) == 9
    for ends, f in zip(chords.ends, chords.feature):
        centre = np.array(min(CENTRES, key=lambda c: np.hypot(*(np.asarray(c) - chords.centres[f]))))
        assert np.hypot(*(ends - centre).T) == pytest.approx(radius, abs=0.5)  # the noise: 1 nm of 200


def _squares(shape, centres, half, height, wall=3.0, tilt_deg=0.0):
    """Squares of side ``2 half`` px (at half height) at ``centres`` (row, col) px, turned by
    ``tilt_deg``, ``height`` nm, with a linear wall ``wall`` px wide centred on the side."""
    rows, cols = np.mgrid[: shape[0], : shape[1]].astype(float)
    c, s = np.cos(np.deg2rad(tilt_deg)), np.sin(np.deg2rad(tilt_deg))
    z = np.zeros(shape)
    for r0, c0 in centres:
        u, v = c * (cols - c0) + s * (rows - r0), -s * (cols - c0) + c * (rows - r0)
        z = np.maximum(z, height * np.clip(0.5 - (np.maximum(np.abs(u), np.abs(v)) - half) / wall, 0, 1))
    return z


def test_a_feature_whose_chords_fix_one_coordinate_keeps_none():
    """Scars along the top and bottom walls of one of nine squares (turned by 4 degrees) end
    every one of its column chords: its line chords alone would leave its row free (a centre
    from them is any point on a line). It keeps no chord; the other squares keep the chords
    they have without the scars."""
    shape, half = (104, 104), 9.5
    noise = np.random.default_rng(1).normal(0, 1.0, shape)
    clean = _squares(shape, CENTRES, half, 200.0, tilt_deg=4.0) + noise
    z = clean.copy()
    r0, c0 = CENTRES[4]
    for row in (round(r0 - half), round(r0 + half)):
        z[row - 1 : row + 1, round(c0) - 8 : round(c0) + 13] += 300.0
    chords, before = find_chords(z, pits=False), find_chords(clean, pits=False)
    assert len(chords.centres) == 9 and chords.image.scars.any()
    middle = np.argmin(np.hypot(*(chords.centres - np.array([r0, c0])).T))
    assert not (chords.feature == middle).any()
    assert (before.feature == middle).sum() > 30  # it had chords both ways
    # the other squares: the same chords, and the centres they give moved by no more than the
    # scars' change to the levelling moves them (0.5 nm of the features' 200 nm moves a crossing
    # of a 3 px wall by 0.0075 px)
    others = CENTRES[:4] + CENTRES[5:]
    a, b = _chord_centres(chords, others), _chord_centres(before, others)
    np.testing.assert_array_equal(a[:, :2], b[:, :2])
    np.testing.assert_allclose(a[:, 2:], b[:, 2:], atol=0.01)  # px


def _chord_centres(chords, centres) -> np.ndarray:
    """Per drawn centre, the nearest feature's chords along the lines and the columns and where
    their midpoints put it: ``(lines, columns, mean column, mean row)``."""
    out = []
    for centre in centres:
        mine = chords.feature == np.argmin(np.hypot(*(chords.centres - np.asarray(centre)).T))
        lines, columns = chords.ends[mine & chords.along_lines], chords.ends[mine & ~chords.along_lines]
        out.append((len(lines), len(columns), lines[..., 1].mean(), columns[..., 0].mean()))
    return np.array(out)


@pytest.mark.parametrize("lattice, pits", [("square_pits", True), ("round_pillars", False)])
def test_scars_and_dust_on_a_real_lattice_move_no_features_centre_by_a_pixel(lattice, pits):
    """Two shipped Nanosurf lattices, trace and retrace, with 12 scars (1-3 lines tall, 40-120 px
    long, 300-800 nm up or down) and 1 % of 3 x 3 px specks 1.5 um tall (holes on the pits) drawn
    on each image: every feature that keeps chords is put by them (their midpoints, least
    squares) within a pixel of where the clean image's put it (a feature's chords left along
    one wall put it several pixels off), and most features keep chords."""
    rng = np.random.default_rng(0)
    for direction in ("trace", "retrace"):
        z = read_image(REAL / f"lattice_{lattice}_nanosurf.nid", direction=direction).z
        dirty = z.copy()
        for _ in range(12):
            tall, long = rng.integers(1, 4), rng.integers(40, 121)
            i, j = rng.integers(0, z.shape[0] - tall), rng.integers(0, z.shape[1] - long)
            dirty[i : i + tall, j : j + long] += rng.choice([-1, 1]) * rng.uniform(300, 800)
        for _ in range(int(0.01 * z.size / 9)):
            i, j = rng.integers(1, z.shape[0] - 1), rng.integers(1, z.shape[1] - 1)
            dirty[i - 1 : i + 2, j - 1 : j + 2] += -1500.0 if pits else 1500.0
        (_, before), (_, after) = (
            chord_centres(c.ends, c.feature[:, None], c.along_lines, np.zeros(2))
            for c in (find_chords(z, pits), find_chords(dirty, pits))
        )
        offset = np.min(np.hypot(*(after[:, None] - before[None]).T), axis=0)
        assert len(after) > len(before) / 2
        assert offset.max() < 1.0  # px


def test_scars_are_outliers_and_neither_features_nor_gaps_in_them():
    """Scars, one and three lines tall, up and down, across features and on the surface
    between them, taller than half the features: the nine discs stay nine, every scar pixel is
    an outlier, and every chord kept lies on its drawn circle as on the clean image. Square
    features with walls along the lines (a column's heights monotone across a wall) have no
    scar."""
    shape, radius = (104, 104), 9.0
    z = _discs(shape, CENTRES, radius, 200.0)
    scars = np.zeros(shape, bool)
    for row, lines, start, length, step in [
        (20, 1, 5, 40, 150.0),
        (50, 3, 30, 50, -150.0),
        (36, 1, 40, 30, 300.0),
    ]:
        scars[row : row + lines, start : start + length] = True
        z[row : row + lines, start : start + length] += step
    chords = find_chords(z, pits=False)
    assert len(chords.centres) == 9
    found = chords.image.scars
    assert found[scars].all() and chords.image.outliers[scars].all()
    # beyond a scar's ends, where it meets a wall, a pixel or two may go with it; nothing elsewhere
    near = ndimage.binary_dilation(scars, structure=np.ones((1, 5), bool))
    assert not (found & ~near).any()
    for ends, f in zip(chords.ends, chords.feature):
        centre = np.array(min(CENTRES, key=lambda c: np.hypot(*(np.asarray(c) - chords.centres[f]))))
        assert np.hypot(*(ends - centre).T) == pytest.approx(radius, abs=0.05)
    rows, cols = np.mgrid[: shape[0], : shape[1]].astype(float)
    squares = sum(  # walls 3 px wide; less than half of each line on a wall, so its offset is the surface's
        200.0 * np.clip((11.0 - np.maximum(np.abs(rows - r0), np.abs(cols - c0))) / 3, 0, 1)
        for r0, c0 in [(r, c) for r in (30.3, 72.6) for c in (30.7, 73.9)]
    )
    plain = find_chords(squares, pits=False)
    assert len(plain.centres) == 4 and not plain.image.scars.any()


def test_features_cut_by_the_edge_and_spikes_are_not_features():
    shape = (104, 104)
    z = _discs(shape, CENTRES + [(50.0, 1.0)], 9.0, 100.0)  # a disc cut by the left edge
    z[70, 70] = 100.0  # a one-pixel spike, as high as the features
    chords = find_chords(z, pits=False)
    assert len(chords.centres) == 9


def test_an_image_without_features_is_refused_by_name():
    flat = np.random.default_rng(1).normal(0, 1, (64, 64))
    i, j = np.mgrid[:64, :64]
    plane = 3.0 * i + 2.0 * j  # a tilt without noise: no feature (not its round-off)
    for z in (flat, plane):
        for pits in (False, True):
            with pytest.raises(ValueError, match="scan.png: no feature level stands out"):
                level(z, pits=pits, name="scan.png")
    for z, but in (
        (np.full((64, 64), -7.0), ""),
        (np.where(i + j < 3, 100.0, -7.0), " but 6 at its extreme value"),
    ):
        with pytest.raises(
            ValueError, match=f"scan.png: every pixel{but} has the height -7 nm: the image holds no"
        ):
            level(z, pits=False, name="scan.png")


def test_background_design_is_the_legendre_products_up_to_the_order():
    a = background_design((5, 7), order=2)
    assert a.shape == (35, 6)
    assert np.linalg.matrix_rank(a) == 6


def _turned_squares(shape, centres, half, turn_deg, height, wall=1.5):
    """Squares of half side ``half`` px turned ``turn_deg`` off the lines at ``centres`` (row,
    col) px, ``height`` nm, with a linear wall ``wall`` px wide centred on the sides."""
    rows, cols = np.mgrid[: shape[0], : shape[1]].astype(float)
    c, s = np.cos(np.radians(turn_deg)), np.sin(np.radians(turn_deg))
    z = np.zeros(shape)
    for r0, c0 in centres:
        u, v = c * (cols - c0) + s * (rows - r0), -s * (cols - c0) + c * (rows - r0)
        d = np.maximum(np.abs(u), np.abs(v)) - half
        z = np.maximum(z, height * np.clip(0.5 - d / wall, 0, 1))
    return z


def _cut(line, centre, half, turn_deg):
    """How far (px) the scan line ``line`` runs into the top or bottom side of the turned
    square about ``centre`` (row, col), at its nearer end: 0 for a chord from the left side to
    the right one, which is the interval where |u| <= half inside the one where |v| <= half."""
    c, s = np.cos(np.radians(turn_deg)), np.sin(np.radians(turn_deg))
    dy = line - centre[0]
    u = sorted([(-half - s * dy) / c, (half - s * dy) / c])  # x - x0 where |u| <= half
    v = sorted([(c * dy - half) / s, (c * dy + half) / s])  # x - x0 where |v| <= half
    return max(v[0] - u[0], u[1] - v[1], 0.0)


@pytest.mark.parametrize("turn_deg", [3.0, 6.0])
def test_a_chord_that_meets_a_turned_squares_top_or_bottom_is_off_its_features_line(turn_deg):
    """Squares turned a few degrees off the lines: a scan line near a square's top or bottom
    crosses that side by its corner, and its chord, cut short there, has its midpoint off the
    line the others' lie on by half the cut. Kept by default; with ``off_line_sd`` every chord
    cut by a pixel or more is dropped, every chord a pixel or more from a cut line (the wall is
    1.5 px wide) is kept, and the midpoints left lie on their features' lines to the edges'
    interpolation (a tenth of a pixel) and half of what a side cuts off a chord near it."""
    shape, half = (104, 104), 9.0
    centres = np.array([(r, c) for r in (20.3, 52.6, 84.1) for c in (19.7, 51.2, 83.9)])
    z = _turned_squares(shape, centres, half, turn_deg, 200.0)
    z += np.random.default_rng(1).normal(0, 1.0, shape)

    def along_lines(found):
        """The chords along the lines: their ends, their squares' centres, each one's cut and
        the largest cut of the lines within a pixel of it."""
        ends = found.ends[found.along_lines]
        found_centres = found.centres[found.feature[found.along_lines]]
        centre = centres[np.argmin(np.hypot(*(found_centres[:, None] - centres[None]).T), axis=0)]
        cut = np.array([_cut(e[0, 0], c, half, turn_deg) for e, c in zip(ends, centre)])
        near = np.array(
            [max(_cut(e[0, 0] + d, c, half, turn_deg) for d in (-1, 1)) for e, c in zip(ends, centre)]
        )
        return ends, centre, cut, np.maximum(cut, near)

    ends, centre, cut, near = along_lines(find_chords(z, pits=False))
    assert (cut >= 1.0).sum() >= 9  # the default keeps chords cut by a pixel or more
    kept, kept_centre, _, kept_near = along_lines(find_chords(z, pits=False, off_line_sd=5.0))
    kept_lines = {(*c, e[0, 0]) for e, c in zip(kept, kept_centre)}
    for e, c, k, n in zip(ends, centre, cut, near):
        assert ((*c, e[0, 0]) in kept_lines) == (k < 1.0) or 0.0 < n and k < 1.0
    mid = kept.mean(axis=1)
    for c in centres:
        on = np.all(kept_centre == c, axis=1)
        slope, offset = np.polyfit(mid[on, 0], mid[on, 1], 1)
        assert np.all(np.abs(mid[on, 1] - slope * mid[on, 0] - offset) < kept_near[on] / 2 + 0.1)  # px
