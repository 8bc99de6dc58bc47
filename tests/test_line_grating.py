"""1-D grating fit: pitch, fast-axis nonlinearity and skew from drawn gratings of known distortion, and the real file.

The gratings are drawn here with numpy from the equation in ``jaxafm.identify.line_grating``
(trapezoidal grooves, point-sampled), not with the code under test.
"""

from pathlib import Path

import numpy as np
import pytest
from numpy.polynomial import legendre

import jaxafm
from jaxafm.identify import features
from jaxafm.identify.line_grating import fit_line_grating
from jaxafm.instrument.images import read_image

REAL = Path(jaxafm.__file__).parent / "data" / "real" / "grating_1d_nanosurf.txt"
PX = (50.0, 60.0)  # nm


def draw(
    shape=(96, 160),
    pitch=1000.0,
    coeffs=(40.0, -25.0),
    skew=0.015,
    bow=0.0,
    drift=0.0,
    phase=300.0,
    groove=450.0,
    width_wander=0.0,
    depth=500.0,
    ramp=200.0,
    noise=0.0,
    seed=0,
):
    """Grooves of ``depth`` nm, ``groove`` nm wide at mid-depth, sides ``ramp`` nm wide, on a pitch of
    ``pitch`` nm, seen through x_true = x + sum c_k P_k(s) + skew y + bow P_2(t) + drift (x - x_mid) t / 2.
    Falling edges (into a groove) at x_true = phase + n pitch, rising ones ``groove`` later; ``width_wander``
    widens the grooves row by row about their centres."""
    rows, cols = shape
    x, y = np.meshgrid(np.arange(cols) * PX[0], np.arange(rows) * PX[1])
    s, t = 2 * x / x.max() - 1, 2 * y / y.max() - 1
    xt = (
        x
        + legendre.legval(s, [0.0, 0.0, *coeffs])
        + skew * y
        + bow * 0.5 * (3 * t**2 - 1)
        + drift * (x - x.max() / 2) * t / 2
    )
    g = groove + width_wander * np.sin(2 * np.pi * t)  # per row, about a fixed centre
    u = np.mod(xt - phase - groove / 2 + pitch / 2, pitch) - pitch / 2  # from the groove's centre
    inside = np.clip((g / 2 - np.abs(u)) / ramp + 0.5, 0.0, 1.0)
    return depth * (1 - inside) + noise * np.random.default_rng(seed).standard_normal(shape)


def test_edge_crossings_ignore_noise_on_the_slopes():
    c = np.arange(200.0)
    clean = np.clip(0.5 * (np.abs(np.mod(c - 23.3, 40) - 20) - 10), -4, 4)  # level 0 at 13.3 + 20 k
    row = clean + 0.5 * np.random.default_rng(4).standard_normal(c.size)
    pos, rising = features.edge_crossings(row)
    # slope 0.5 per px and noise 0.5: each edge within ~1 px (1 sigma), all ten within 3 px
    assert len(pos) == 10 and np.abs(pos - (13.3 + 20 * np.arange(10))).max() < 3.0
    assert np.all(rising[1:] != rising[:-1]) and rising[0]
    assert len(features.edge_crossings(row, band=0.0)[0]) > 10  # without the dead band the noise adds edges


def test_recovers_pitch_nonlinearity_and_skew():
    # 1 % height noise (5 nm) on sides of 2.5 nm/nm: ~1.6 nm jitter per edge, ~1100 edges, so
    # standard errors of 0.02 nm (pitch), 0.1 nm (c_k) and 2.5e-5 (skew); over 20 noise seeds the
    # errors / standard errors had unit spread. The tolerances are ~10 standard errors, far
    # below the distortion drawn (c_k 25-40 nm, skew 86 nm over the image).
    truth = dict(pitch=1000.0, coeffs=(40.0, -25.0), skew=0.015)
    f = fit_line_grating(draw(**truth, noise=5.0), PX, degree=3)
    assert abs(f.pitch_nm - 1000.0) < 0.3 and f.pitch_se_nm < 0.1
    assert np.allclose(f.coeffs_nm, truth["coeffs"], atol=1.5)
    assert abs(f.skew - 0.015) < 2e-4  # 1 nm over the 5700 nm of y
    assert abs(f.bow_nm) < 1.5 and abs(f.drift) < 3e-4  # none drawn
    assert np.isclose(np.mod(f.phase_fall_nm - 300.0 + 500, 1000), 500, atol=1.0)
    assert np.isclose(f.line_width_nm, 450.0, atol=1.0)
    assert f.residual_rms_nm < 3.0
    # the map inverts the drawing: nominal (x, y) -> true x
    x, y = np.array([100.0, 4000.0, 7900.0]), np.array([0.0, 3000.0, 5700.0])
    s = 2 * x / (159 * PX[0]) - 1
    assert np.allclose(f.corrected_x(x, y), x + legendre.legval(s, [0, 0, 40.0, -25.0]) + 0.015 * y, atol=2.0)


def test_degree_is_chosen_by_bic():
    assert fit_line_grating(draw(coeffs=(40.0, -25.0), noise=5.0), PX).degree == 3
    assert fit_line_grating(draw(coeffs=(40.0,), noise=5.0), PX).degree == 2


def test_recovers_bow_drift_and_wandering_width():
    truth = dict(coeffs=(-30.0,), skew=-0.01, bow=20.0, drift=0.01, width_wander=30.0)
    f = fit_line_grating(draw(**truth), PX, degree=2)
    assert abs(f.pitch_nm - 1000.0) < 0.3 and abs(f.coeffs_nm[0] + 30.0) < 1.0
    assert abs(f.skew + 0.01) < 1e-4 and abs(f.bow_nm - 20.0) < 1.0 and abs(f.drift - 0.01) < 2e-4
    t = np.linspace(-1, 1, 96)
    assert np.allclose(f.row_width_nm, 30.0 * np.sin(2 * np.pi * t), atol=2.0)
    # without the width term the wander (rising and falling edges moved apart) stays in the residual
    assert fit_line_grating(draw(**truth), PX, degree=2, widths=False).residual_rms_nm > 5 * f.residual_rms_nm


def test_correction_makes_the_local_pitch_uniform():
    f = fit_line_grating(draw(coeffs=(60.0, -40.0), noise=5.0), PX)
    u = f.uniformity()
    # the drawn nonlinearity's slope runs from -10.6 % to +2.2 %: raw local pitch 979-1081 nm
    assert u["raw"]["pitch_std_pct"] > 1.0
    assert u["corrected"]["pitch_std_pct"] < 0.3 * u["raw"]["pitch_std_pct"]
    assert abs(u["corrected"]["pitch_mean_nm"] - 1000.0) < 2.0


@pytest.mark.parametrize(
    "bad, message",
    [
        (lambda z: np.where(z < 100, np.nan, z), "NaN"),
        (lambda z: np.zeros_like(z), "flat"),
        (lambda z: z[:, :50], "complete grating period"),  # 2.5 periods
        (lambda z: z[:5], "scan line"),
        (
            lambda z: np.concatenate([z[:48], np.roll(z[48:], 10, axis=1)]),
            "edge indexing is inconsistent",
        ),  # half
        (
            lambda z: np.where((np.arange(96)[:, None] == 40) & (np.abs(np.arange(160) - 80) < 2), 0.0, z),
            "edge indexing is inconsistent",
        ),  # a pit between two grooves in one row
    ],
)
def test_bad_images_raise_errors_naming_the_problem(bad, message):
    with pytest.raises(ValueError, match=message):
        fit_line_grating(bad(draw()), PX)


def shift_difference_pitch(z: np.ndarray, lo: int, hi: int) -> int:
    """The lag k (px) in [lo, hi) that minimises D(k) = mean (z[:, x + k] - z[:, x])^2 over the
    rows and the overlap: numpy alone, no edges. Near a multiple m p of the period (an
    image periodic along x up to noise and slight distortion), z(x + k) - z(x) ~ (k - m p) z'(x),
    so D(k) ~ (k - m p)^2 mean z'^2 + floor is even about m p and grows with |k - m p|: its
    smallest value on the integer lags is at the lag nearest m p, within 0.5 px of it."""
    cols = z.shape[1]
    d = [np.mean((z[:, k:] - z[:, : cols - k]) ** 2) for k in range(lo, hi)]
    return lo + int(np.argmin(d))


def test_real_grating_pitch_and_uniformity():
    image = read_image(REAL)
    f = fit_line_grating(image.z, image.pixel_size)
    dx = image.pixel_size[0]  # 78.1 nm
    # an independent estimate: the lag of the third period (near 3 x 2.9 um / 78 nm = 111 px,
    # searched over 3 x 30-40 px), read to the nearest pixel: the pitch within 0.5 px / 3 = 13 nm
    # (quantisation); over those 3 periods the fitted nonlinearity (sum c_k P_k, ~12 nm peak to
    # peak over the row) moves the lag by at most its peak-to-peak value / 3
    lag = shift_difference_pitch(image.z, 90, 120)
    x = np.arange(image.z.shape[1]) * dx
    bound = 0.5 * dx / 3 + np.ptp(f.nonlinearity_nm(x)) / 3 + 3 * f.pitch_se_nm
    assert abs(f.pitch_nm - lag * dx / 3) < bound  # 2885.5 against 111 px / 3 = 2890.6 nm
    # the fit's own uncertainty against the edge statistics: with a line of its own a row and
    # kind, the pitch's se would be sigma / sqrt(sum (n - mean n)^2) (sigma: the residual rms,
    # 2.8 nm; 896 edges, 3-4 of a kind a row: 0.09 nm); the other terms' correlation with the
    # line index changes it by a factor near 1, and it stays far below the quantisation bound
    e = f.edges
    key = 2 * e.row + e.rising
    spread = sum(np.sum((e.index[key == k] - e.index[key == k].mean()) ** 2) for k in np.unique(key))
    alone = f.residual_rms_nm / np.sqrt(spread)
    assert 0.5 * alone < f.pitch_se_nm < 2 * alone and 3 * f.pitch_se_nm < 0.1 * 0.5 * dx / 3
    u = f.uniformity()
    assert u["corrected"]["pitch_std_nm"] < u["raw"]["pitch_std_nm"]
