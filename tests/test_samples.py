"""Tests of the sample topographies and the AFM tip (jaxafm.instrument.samples).

Every expected value comes from outside the code under test: closed forms
(the sphere-capped cone written out by hand, the dilation of a sphere or a
plane by a spherical apex, bilinear functions that bilinear interpolation must
reproduce exactly), geometric properties (periods, symmetry, widths at half
height, a dilation never lowers the surface), analytic derivatives and
central finite differences.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

# importing jaxafm.instrument switches JAX to float64 (jaxafm._precision)
from jaxafm.instrument import samples
from jaxafm.instrument.afm import render
from jaxafm.instrument.samples import (
    NEAR,
    Grating,
    HeightMap,
    Indented,
    Lattice,
    Particles,
    Plane,
    Tip,
    surface,
)

RT, THETA = 10.0, np.deg2rad(20.0)  # Tip() defaults


def ref_profile(r, R=RT, th=THETA):
    """Sphere-capped cone written out from geometry: the apex sphere up to the tangent
    point r_t = R cos(th), then the cone, whose (virtual) apex lies R (1 - 1/sin th) above
    the tip's apex and whose flank rises 1/tan(th) per nm."""
    r = np.asarray(r, dtype=float)
    rt = R * np.cos(th)
    sphere = R - np.sqrt(np.maximum(R**2 - r**2, 0.0))
    cone = r / np.tan(th) + R * (1 - 1 / np.sin(th))
    return np.where(r <= rt, sphere, cone)


def pts(*xy):
    """One point (2,) or several (n, 2)."""
    a = np.array(xy, dtype=float)
    return jnp.asarray(a[0] if len(xy) == 1 else a)


# jitted once per sample type and shape: eager op-by-op dispatch is far slower to warm up
H = jax.jit(lambda sample, xy: sample.height(xy))
D = jax.jit(lambda tip, sample, xy: tip.dilate(sample.height, xy))
dH_dxy = jax.jit(jax.grad(lambda sample, xy: sample.height(xy), argnums=1))
dH_dsample = jax.jit(jax.grad(lambda sample, xy: sample.height(xy)))  # a sample-shaped tree of gradients
dD = jax.jit(jax.grad(lambda tip, sample, xy: tip.dilate(sample.height, xy), argnums=2))
P = jax.jit(lambda tip, r: tip.profile(r))
dP = jax.jit(jax.grad(lambda tip, r: tip.profile(r), argnums=(0, 1)))


def fd(f, x, h=1e-5):
    """Central finite-difference gradient of a scalar function of a 1-D array."""
    x = np.asarray(x, dtype=float)
    g = np.zeros_like(x)
    for i in range(x.size):
        e = np.zeros_like(x)
        e[i] = h
        g[i] = (float(f(jnp.asarray(x + e))) - float(f(jnp.asarray(x - e)))) / (2 * h)
    return g


# ----------------------------------------------------------------------------- Plane


def test_plane_is_affine():
    pl = Plane(jnp.asarray(2.5), jnp.array([0.1, -0.3]))
    xy = np.random.default_rng(0).uniform(-100, 100, (4, 3, 2))
    np.testing.assert_allclose(
        np.asarray(H(pl, jnp.asarray(xy))), 2.5 + 0.1 * xy[..., 0] - 0.3 * xy[..., 1], rtol=1e-13
    )


# ----------------------------------------------------------------------------- Grating

G_KW = dict(pitch=400.0, depth=30.0, duty=0.3, edge_width=20.0, angle=0.4, phase=37.0)


def grating(**kw):
    return Grating(**{k: jnp.asarray(v) for k, v in {**G_KW, **kw}.items()})


def across(u, v=0.0, angle=G_KW["angle"]):
    """Lab points at distance u across the lines (along the direction ``angle``) and v along them."""
    u, v = np.broadcast_arrays(np.asarray(u, float), np.asarray(v, float))
    c, s = np.cos(angle), np.sin(angle)
    return jnp.asarray(np.stack([c * u - s * v, s * u + c * v], axis=-1))


def test_grating_profile_closed_form():
    """Across the lines: top of ``depth`` on |u - phase| <= duty*pitch/2 - w/2, floor 0 beyond
    duty*pitch/2 + w/2, straight edges of slope depth/w between; half depth at a width of
    exactly duty*pitch."""
    g = grating()
    half_top = 0.3 * 400 / 2  # 60
    w = 20.0
    for side in (+1, -1):
        u = 37.0 + side * np.array([0.0, 30.0, half_top - w / 2, half_top, half_top + w / 2, 150.0, 199.0])
        z = np.asarray(H(g, across(u)))
        np.testing.assert_allclose(z, [30, 30, 30, 15, 0, 0, 0], atol=1e-10)
    # inside the edge the height is linear: depth * (half_top + w/2 - |du|) / w
    du = np.linspace(half_top - w / 2 + 0.5, half_top + w / 2 - 0.5, 17)
    np.testing.assert_allclose(
        np.asarray(H(g, across(37.0 + du))), 30 * (half_top + w / 2 - du) / w, atol=1e-10
    )
    # top width at half depth = duty * pitch, whatever the duty
    for duty in (0.2, 0.5, 0.8):
        gd = grating(duty=duty)
        hw = duty * 400 / 2
        np.testing.assert_allclose(np.asarray(H(gd, across(37.0 + np.array([-hw, hw])))), 15.0, atol=1e-10)


def test_grating_period_orientation_and_phase():
    g = grating()
    rng = np.random.default_rng(1)
    u, v = rng.uniform(-1000, 1000, (2, 50))
    z = np.asarray(H(g, across(u, v)))
    assert z.min() == pytest.approx(0.0) and z.max() == pytest.approx(30.0)  # the points hit floor and tops
    # periodic across the lines, invariant along them
    for k in (1, -3, 7):
        np.testing.assert_allclose(np.asarray(H(g, across(u + k * 400, v))), z, atol=1e-9)
    np.testing.assert_allclose(np.asarray(H(g, across(u, v + 123.4))), z, atol=1e-9)
    # ... and not invariant along the unrotated y axis: the angle is really used
    shifted = np.asarray(H(g, across(u, v) + jnp.array([0.0, 123.4])))
    assert np.abs(shifted - z).max() > 5
    # phase shifts the pattern across the lines
    g0 = grating(phase=0.0)
    np.testing.assert_allclose(
        np.asarray(H(g, across(u + 37.0, v))), np.asarray(H(g0, across(u, v))), atol=1e-9
    )
    # angle 0: lines along y, x crosses them
    ga = grating(angle=0.0, phase=0.0)
    np.testing.assert_allclose(
        np.asarray(H(ga, pts([0.0, 0.0], [0.0, 500.0], [200.0, 0.0], [200.0, 77.0]))),
        [30, 30, 0, 0],
        atol=1e-10,
    )


def test_grating_gradients():
    """On an edge the height falls at depth/w per nm away from the line centre: gradient
    wrt the point is -depth/w along +u (right edge), wrt phase +depth/w; matches FD too."""
    g = grating()
    ang = G_KW["angle"]
    p = np.asarray(across(37.0 + 63.0, 11.0))  # right edge, 3 nm past half depth
    gx = np.asarray(dH_dxy(g, jnp.asarray(p)))
    np.testing.assert_allclose(gx, -30 / 20 * np.array([np.cos(ang), np.sin(ang)]), rtol=1e-10)
    np.testing.assert_allclose(gx, fd(lambda x: H(g, x), p), rtol=1e-6)
    gs = dH_dsample(g, jnp.asarray(p))
    assert float(gs.phase) == pytest.approx(30 / 20, rel=1e-10)
    # left edge: signs flip
    q = jnp.asarray(across(37.0 - 63.0))
    assert float(dH_dsample(g, q).phase) == pytest.approx(-30 / 20, rel=1e-10)
    # depth and edge_width enter as closed forms: z = depth * (h + w/2 - du) / w
    assert float(gs.depth) == pytest.approx((60 + 10 - 63) / 20, rel=1e-10)
    assert float(gs.edge_width) == pytest.approx(30 * (0.5 * 20 - (60 + 10 - 63)) / 20**2, rel=1e-10)


# ----------------------------------------------------------------------------- Lattice

L_PITCH, L_ANGLE, L_PHASE = np.array([300.0, 450.0]), 0.3, np.array([40.0, -25.0])


def lattice(depth=20.0):
    return Lattice(
        jnp.asarray(L_PITCH),
        jnp.asarray(80.0),
        jnp.asarray(depth),
        edge_width=jnp.asarray(10.0),
        angle=jnp.asarray(L_ANGLE),
        phase=jnp.asarray(L_PHASE),
    )


def lab(a, b):
    """Lab offset of a and b nm along the lattice's first and second (rotated) axes."""
    c, s = np.cos(L_ANGLE), np.sin(L_ANGLE)
    return np.array([c * a - s * b, s * a + c * b])


@pytest.mark.parametrize("depth", [20.0, -20.0])
def test_lattice_features(depth):
    """A pillar (depth > 0) or a pit (depth < 0) of ``|depth|`` centred at ``phase`` and at
    every lattice point, radius at half height exactly ``radius``, base 0 between."""
    lt = lattice(depth)
    centres = [L_PHASE + lab(i * 300, j * 450) for i, j in [(0, 0), (1, 0), (0, 1), (-2, 3)]]
    np.testing.assert_allclose(np.asarray(H(lt, jnp.asarray(np.array(centres)))), depth, atol=1e-9)
    phis = np.linspace(0, 2 * np.pi, 13)
    ring = lambda r: jnp.asarray(np.array([L_PHASE + lab(r * np.cos(f), r * np.sin(f)) for f in phis]))
    np.testing.assert_allclose(np.asarray(H(lt, ring(80.0))), depth / 2, atol=1e-9)
    np.testing.assert_allclose(np.asarray(H(lt, ring(74.0))), depth, atol=1e-9)  # inside radius - w/2
    np.testing.assert_allclose(np.asarray(H(lt, ring(86.0))), 0.0, atol=1e-9)  # beyond radius + w/2
    np.testing.assert_allclose(np.asarray(H(lt, ring(83.0))), depth * 0.2, atol=1e-9)  # linear edge
    # middle of a cell, between four features: base
    assert float(H(lt, jnp.asarray(L_PHASE + lab(150, 225)))) == pytest.approx(0.0, abs=1e-12)


def test_lattice_periodic_along_rotated_axes():
    lt = lattice()
    xy = np.random.default_rng(2).uniform(-700, 700, (400, 2))
    z = np.asarray(H(lt, jnp.asarray(xy)))
    assert (z > 19).any() and (z < 1).any() and ((z > 1) & (z < 19)).any()
    for a, b in [(300, 0), (0, 450), (-600, 900)]:
        np.testing.assert_allclose(np.asarray(H(lt, jnp.asarray(xy + lab(a, b)))), z, atol=1e-9)
    # not periodic along the unrotated x axis
    assert np.abs(np.asarray(H(lt, jnp.asarray(xy + [300.0, 0.0]))) - z).max() > 5


def test_lattice_gradients():
    """On the edge, z = depth * (radius + w/2 - r) / w: gradient wrt the point is
    -depth/w times the unit vector from the centre, wrt phase the opposite."""
    lt = lattice()
    u = np.array([np.cos(1.0), np.sin(1.0)])
    p = L_PHASE + lab(300, 0) + 82.0 * u
    g = np.asarray(dH_dxy(lt, jnp.asarray(p)))
    np.testing.assert_allclose(g, -20 / 10 * u, rtol=1e-8)
    np.testing.assert_allclose(g, fd(lambda x: H(lt, x), p), rtol=1e-6)
    gph = np.asarray(dH_dsample(lt, jnp.asarray(p)).phase)
    np.testing.assert_allclose(gph, 20 / 10 * u, rtol=1e-8)


# ----------------------------------------------------------------------------- Particles


def test_particle_on_flat_substrate():
    R, z0 = 7.0, 3.0
    p = Particles(jnp.array([[10.0, -4.0]]), jnp.array([R]), Plane(jnp.asarray(z0), jnp.zeros(2)))
    r = np.array([0.0, 2.0, 5.0, 6.9, 7.1, 20.0])
    xy = np.stack([10.0 + r * np.cos(0.7), -4.0 + r * np.sin(0.7)], -1)
    want = np.where(r < R, z0 + R + np.sqrt(np.maximum(R**2 - r**2, 0)), z0)
    np.testing.assert_allclose(np.asarray(H(p, jnp.asarray(xy))), want, rtol=1e-12)
    assert float(H(p, pts([10.0, -4.0]))) == pytest.approx(z0 + 2 * R)
    # any batch shape
    assert H(p, jnp.zeros((4, 5, 2))).shape == (4, 5)


def test_particles_on_tilted_substrate_and_several():
    sub = Plane(jnp.asarray(2.0), jnp.array([0.1, -0.05]))
    c = np.array([[0.0, 0.0], [40.0, 10.0], [46.0, 10.0]])  # the last two overlap
    R = np.array([5.0, 4.0, 3.0])
    p = Particles(jnp.asarray(c), jnp.asarray(R), sub)
    s = lambda xy: 2.0 + 0.1 * xy[..., 0] - 0.05 * xy[..., 1]
    # each top is 2R above the substrate under its centre
    np.testing.assert_allclose(np.asarray(H(p, jnp.asarray(c[:2]))), s(c[:2]) + 2 * R[:2], rtol=1e-12)
    xy = np.random.default_rng(3).uniform([-10, -10], [55, 20], (400, 2))
    caps = []
    for ck, Rk in zip(c, R):
        r2 = ((xy - ck) ** 2).sum(-1)
        caps.append(np.where(r2 < Rk**2, s(ck) + Rk + np.sqrt(np.abs(Rk**2 - r2)), -np.inf))
    want = np.maximum(s(xy), np.max(caps, axis=0))
    assert (np.isfinite(np.max(caps, axis=0))).sum() > 20  # the points hit particles
    np.testing.assert_allclose(np.asarray(H(p, jnp.asarray(xy))), want, rtol=1e-12)
    # far from the particles: the substrate
    np.testing.assert_allclose(np.asarray(H(p, pts([100.0, -50.0]))), s(np.array([100.0, -50.0])))


def test_particles_none():
    """No particles is refused when made, naming Particles."""
    sub = Plane(jnp.asarray(2.0), jnp.array([0.1, 0.0]))
    with pytest.raises(ValueError, match="Particles needs at least one particle"):
        Particles(jnp.zeros((0, 2)), jnp.zeros(0), sub)


def test_particles_gradients():
    """z = sub(c) + R + sqrt(R^2 - |p - c|^2): dz/dp = -(p - c)/sqrt(..) + sub slope,
    dz/dc = (p - c)/sqrt(..) + sub slope, dz/dR = 1 + R/sqrt(..)."""
    slope = np.array([0.1, -0.05])
    c, R = np.array([[3.0, -2.0]]), np.array([6.0])
    p = Particles(jnp.asarray(c), jnp.asarray(R), Plane(jnp.asarray(1.0), jnp.asarray(slope)))
    xy = np.array([5.0, 1.0])
    d = xy - c[0]
    root = np.sqrt(R[0] ** 2 - d @ d)
    np.testing.assert_allclose(np.asarray(dH_dxy(p, jnp.asarray(xy))), -d / root, rtol=1e-10)
    gs = dH_dsample(p, jnp.asarray(xy))
    gc = gs.centres
    np.testing.assert_allclose(np.asarray(gc)[0], d / root + slope, rtol=1e-10)
    np.testing.assert_allclose(
        np.asarray(gc).ravel(),
        fd(lambda cc: H(eqx.tree_at(lambda s: s.centres, p, cc.reshape(1, 2)), jnp.asarray(xy)), c.ravel()),
        rtol=1e-6,
    )
    np.testing.assert_allclose(np.asarray(gs.radii), [1 + R[0] / root], rtol=1e-10)
    # off the particle: only the substrate, no NaN from the masked square root
    g_off = np.asarray(dH_dxy(p, pts([30.0, 30.0])))
    np.testing.assert_allclose(g_off, slope, rtol=1e-12)


# ----------------------------------------------------------------------------- HeightMap


def bilinear(x, y):
    return 1.5 + 0.2 * x - 0.7 * y + 0.03 * x * y


def test_heightmap_exact_for_bilinear_function():
    """Pixels (rows = y, columns = x) at origin + index * pixel_size; bilinear interpolation
    reproduces a function bilinear in x and y exactly anywhere inside the image, and its
    gradient too, and clamps to the edge pixels beyond."""
    ox, oy, px, py = -3.0, 5.0, 2.0, 0.5
    ny, nx = 7, 11  # not square: catches a transposed image
    X, Y = ox + px * np.arange(nx), oy + py * np.arange(ny)
    z = bilinear(X[None, :], Y[:, None])
    hm = HeightMap(jnp.asarray(z), jnp.array([px, py]), jnp.array([ox, oy]))
    rng = np.random.default_rng(4)
    xy = rng.uniform([X[0], Y[0]], [X[-1], Y[-1]], (200, 2))
    np.testing.assert_allclose(
        np.asarray(H(hm, jnp.asarray(xy))), bilinear(xy[:, 0], xy[:, 1]), rtol=1e-12, atol=1e-12
    )
    np.testing.assert_allclose(
        np.asarray(H(hm, jnp.asarray(xy.reshape(10, 20, 2)))),
        bilinear(xy[:, 0], xy[:, 1]).reshape(10, 20),
        rtol=1e-12,
        atol=1e-12,
    )
    # pixel centres give the pixels exactly
    np.testing.assert_allclose(
        np.asarray(H(hm, pts([X[3], Y[2]], [X[0], Y[0]], [X[-1], Y[-1]]))),
        [z[2, 3], z[0, 0], z[-1, -1]],
        rtol=1e-13,
    )
    # gradient: dz/dx = 0.2 + 0.03 y, dz/dy = -0.7 + 0.03 x (off the pixel grid lines)
    p = np.array([X[4] + 0.3, Y[3] + 0.1])
    np.testing.assert_allclose(
        np.asarray(dH_dxy(hm, jnp.asarray(p))), [0.2 + 0.03 * p[1], -0.7 + 0.03 * p[0]], rtol=1e-10
    )
    # beyond the image: the nearest edge value
    out = pts(
        [X[0] - 50, Y[3] + 0.2],
        [X[-1] + 9, Y[3] + 0.2],
        [X[5] + 0.5, Y[0] - 4],
        [X[5] + 0.5, Y[-1] + 40],
        [X[0] - 1, Y[0] - 1],
        [X[-1] + 1, Y[-1] + 1],
    )
    np.testing.assert_allclose(
        np.asarray(H(hm, out)),
        [
            bilinear(X[0], Y[3] + 0.2),
            bilinear(X[-1], Y[3] + 0.2),
            bilinear(X[5] + 0.5, Y[0]),
            bilinear(X[5] + 0.5, Y[-1]),
            z[0, 0],
            z[-1, -1],
        ],
        rtol=1e-12,
    )


def test_heightmap_gradient_wrt_pixels():
    """Bilinear weights: at fractional position (fx, fy) inside a pixel cell the height is
    sum of the four corners weighted (1-fx)(1-fy), fx(1-fy), (1-fx)fy, fx fy."""
    z = np.random.default_rng(5).normal(size=(4, 5))
    hm = HeightMap(jnp.asarray(z), jnp.array([1.0, 2.0]))
    fx, fy = 0.25, 0.6
    p = jnp.array([2 + fx, 2 * (1 + fy)])
    g = np.asarray(dH_dsample(hm, p).z)
    want = np.zeros_like(z)
    want[1, 2], want[1, 3], want[2, 2], want[2, 3] = (
        (1 - fx) * (1 - fy),
        fx * (1 - fy),
        (1 - fx) * fy,
        fx * fy,
    )
    np.testing.assert_allclose(g, want, atol=1e-12)


def test_heightmap_integer_image_interpolates():
    """An image of whole nanometres is still a topography: between pixels the height is the
    bilinear blend, not rounded to a whole number."""
    hm = HeightMap(np.arange(12, dtype=np.int16).reshape(3, 4), np.ones(2))
    z = np.asarray(hm.height(jnp.array([[0.5, 0.0], [0.25, 0.0], [1.5, 1.5]])))
    np.testing.assert_allclose(z, [0.5, 0.25, 7.5], rtol=1e-12)


# ----------------------------------------------------------------------------- Tip


@pytest.mark.parametrize("R,deg", [(10.0, 20.0), (3.0, 45.0), (25.0, 8.0)])
def test_tip_profile_closed_form(R, deg):
    th = np.deg2rad(deg)
    tip = Tip(jnp.asarray(R), jnp.asarray(th))
    rt = R * np.cos(th)
    r = np.concatenate([np.linspace(0, rt, 50), np.linspace(rt, 10 * R, 50)])
    np.testing.assert_allclose(
        np.asarray(P(tip, jnp.asarray(r))), ref_profile(r, R, th), rtol=1e-9, atol=1e-9
    )
    assert float(P(tip, jnp.asarray(0.0))) == pytest.approx(0.0, abs=1e-9)
    assert float(P(tip, jnp.asarray(rt))) == pytest.approx(R * (1 - np.sin(th)), rel=1e-9)
    # C1 at the tangent point: slope 1/tan(theta) from both sides; the cone beyond
    dprof = lambda r: dP(tip, r)[1]
    for rr in (rt - 1e-7 * R, rt + 1e-7 * R, 2 * rt, 5 * R):
        assert float(dprof(jnp.asarray(rr))) == pytest.approx(1 / np.tan(th), rel=1e-5)
    inside = 0.5 * rt
    assert float(dprof(jnp.asarray(inside))) == pytest.approx(inside / np.sqrt(R**2 - inside**2), rel=1e-8)
    # derivative wrt the apex radius: sphere 1 - R/sqrt(R^2 - r^2), cone 1 - 1/sin(theta)
    dR = lambda r: dP(tip, r)[0].radius
    assert float(dR(jnp.asarray(inside))) == pytest.approx(1 - R / np.sqrt(R**2 - inside**2), rel=1e-8)
    assert float(dR(jnp.asarray(3 * R))) == pytest.approx(1 - 1 / np.sin(th), rel=1e-8)


def test_tip_stencil():
    for kw in (dict(), dict(reach=40.0, rings=5, per_ring=6)):
        tip = Tip(**kw)
        q, lift = (np.asarray(a) for a in jax.jit(Tip.stencil)(tip))
        reach, rings, per_ring = kw.get("reach", 100.0), kw.get("rings", 8), kw.get("per_ring", 16)
        assert q.shape == (1 + rings * per_ring, 2) and lift.shape == (1 + rings * per_ring,)
        r = np.hypot(q[:, 0], q[:, 1])
        assert r[0] == 0 and lift[0] == pytest.approx(0.0, abs=1e-9)
        assert r.max() == pytest.approx(reach)
        np.testing.assert_allclose(lift, ref_profile(r), rtol=1e-9, atol=1e-9)
        radii = np.unique(np.round(r, 9))[1:]
        assert len(radii) == rings and np.all(np.diff(np.diff(radii)) > 0)  # denser near the apex


# ----------------------------------------------------------------------------- Tip.dilate


def test_dilate_flat_and_tilted_plane():
    """A flat plane is imaged flat at its own height. A tilted plane z = s . p is imaged as the
    same plane lifted by max_q [s . q - profile(|q|)] = R (sqrt(1 + |s|^2) - 1) when the
    contact is on the apex sphere (|s| < 1/tan theta); the stencil's max lies below that,
    and the same lift at every point (the stencil does not depend on the point)."""
    xy = jnp.asarray(np.random.default_rng(6).uniform(-300, 300, (30, 2)))
    flat = Plane(jnp.asarray(-4.0), jnp.zeros(2))
    np.testing.assert_allclose(np.asarray(D(Tip(), flat, xy)), -4.0, atol=1e-12)
    s = 0.5
    slope = np.array([0.6 * s, 0.8 * s])
    tilted = Plane(jnp.asarray(2.0), jnp.asarray(slope))
    exact = RT * (np.sqrt(1 + s**2) - 1)
    errs, bounds = [], []
    for kw in (dict(), dict(rings=32, per_ring=64)):
        tip = Tip(**kw)
        lift = np.asarray(D(tip, tilted, xy) - H(tilted, xy))
        np.testing.assert_allclose(lift, lift[0], atol=1e-10)
        assert 0 <= lift[0] <= exact + 1e-12
        # the stencil's max by its definition, in NumPy: max over its offsets of s . q - profile(|q|)
        q = np.asarray(jax.jit(Tip.stencil)(tip)[0])
        np.testing.assert_allclose(lift[0], np.max(q @ slope - ref_profile(np.hypot(*q.T))), atol=1e-9)
        # Taylor: f(q) = s . q - profile(|q|) peaks at q* = R s / sqrt(1 + s^2) (grad f = 0), so the
        # stencil offset nearest q*, h away, lies below the peak by at most kappa h^2 / 2, kappa the
        # apex sphere's largest curvature R^2 / (R^2 - r^2)^(3/2) over r <= |q*| + h
        q_star = RT * slope / np.sqrt(1 + s**2)
        h = np.min(np.hypot(*(q - q_star).T))
        kappa = RT**2 / (RT**2 - (np.hypot(*q_star) + h) ** 2) ** 1.5
        errs.append(exact - lift[0])
        bounds.append(0.5 * kappa * h**2)  # 0.41 nm (h = 1.9 nm) and 0.010 nm (h = 0.37 nm)
    assert errs[0] <= bounds[0] and errs[1] <= bounds[1] and errs[1] < errs[0] / 10
    assert errs[0] < 0.3  # the default stencil's accuracy on a 0.5 slope (0.281 nm; tighter than its bound)


def test_dilate_sphere_closed_form():
    """A sphere of radius Rp on a flat substrate, imaged where the contact is on the tip's
    spherical apex (r < (Rp + Rt) cos theta): the image is a sphere of radius Rp + Rt about
    the particle's centre, z = Rp + sqrt((Rp + Rt)^2 - r^2) - Rt. The stencil's max is
    below the true max (a subset of offsets), exact at the top (offset 0), and converges
    as the stencil is refined."""
    Rp = 20.0
    part = Particles(jnp.array([[5.0, -3.0]]), jnp.array([Rp]))
    r = np.linspace(0, 0.9 * (Rp + RT) * np.cos(THETA), 121)
    errs = []
    for kw in (dict(), dict(rings=32, per_ring=64)):
        tip = Tip(**kw)
        q = np.asarray(jax.jit(Tip.stencil)(tip)[0])
        worst = 0.0
        for ang in (0.0, 0.3, 2.0):
            xy = np.stack([5.0 + r * np.cos(ang), -3.0 + r * np.sin(ang)], -1)
            img = np.asarray(D(tip, part, jnp.asarray(xy)))
            # the stencil's max by its definition, in NumPy: max_q [z(p + q) - profile(|q|)]
            d2 = np.sum((xy[:, None] + q - [5.0, -3.0]) ** 2, -1)
            z = np.where(d2 < Rp**2, Rp + np.sqrt(np.clip(Rp**2 - d2, 0, None)), 0.0)
            np.testing.assert_allclose(img, np.max(z - ref_profile(np.hypot(*q.T)), -1), atol=1e-9)
            err = (Rp + np.sqrt((Rp + RT) ** 2 - r**2) - RT) - img
            assert err.min() > -1e-9  # never above the exact dilation
            assert err[0] == pytest.approx(0.0, abs=1e-9)  # apex on the top
            worst = max(worst, err.max())
        errs.append(worst)
    # measured: default (8 rings x 16) 2.46 nm, 32 rings x 64: 0.154 nm; the stencils' own values
    # (checked above against their definition), kept as the accuracy each stencil promises
    assert errs[0] < 3.0
    assert errs[1] < 0.2
    assert errs[1] < errs[0] / 10


def test_particles_imaged_closed_form_against_brute_force():
    """Particles.imaged (closed form, ball and flank contact) against the dilation's
    definition max_q [z(p + q) - tip(q)] evaluated by brute force over a dense (0.25 nm)
    grid of offsets q in NumPy: the brute force lies below the exact value by at most the
    grid's reach, and the closed form is never below it. Profiles through two touching
    particles, out to where the image meets the substrate.

    Of the grid, the offsets in a box around each particle are evaluated, and q = 0: off the
    particles z = 0 and tip(q) >= tip(0) = 0, so no other offset beats q = 0 (z(p) >= 0). The
    maximum is the one over the whole grid, value for value (identical at all 78 points)."""
    tip = Tip()
    centres, radii = np.array([[0.0, 0.0], [70.0, 10.0]]), np.array([20.0, 8.0])
    parts = Particles(jnp.asarray(centres), jnp.asarray(radii))
    g = np.arange(-120.0, 120.01, 0.25)
    q = np.stack(np.meshgrid(g, g), -1)  # q[i, j] = (g[j], g[i])
    lift = np.asarray(tip.profile(jnp.asarray(np.hypot(q[..., 0], q[..., 1]))))
    zero = np.flatnonzero(g == 0.0)[0]
    assert lift[zero, zero] == 0.0 and lift.min() == 0.0

    def height(p):  # spheres on z = 0, in NumPy
        d2 = np.sum((p[:, None] - centres) ** 2, -1)
        top = np.where(d2 < radii**2, radii + np.sqrt(np.clip(radii**2 - d2, 0, None)), -np.inf)
        return np.maximum(0.0, top.max(-1))

    def brute_force(p):
        best = height(p[None])[0] - lift[zero, zero]  # q = 0
        for c, R in zip(centres, radii):  # the offsets in the box around each particle
            lo, hi = np.searchsorted(g, c - p - R, "left"), np.searchsorted(g, c - p + R, "right")
            box = (slice(lo[1], hi[1]), slice(lo[0], hi[0]))
            if q[box].size:
                best = max(best, np.max(height(p + q[box].reshape(-1, 2)) - lift[box].ravel()))
        return best

    xs = np.linspace(-80.0, 110.0, 39)
    for y in (0.0, 6.0):
        pts = np.stack([xs, np.full_like(xs, y)], -1)
        brute = np.array([brute_force(p) for p in pts])
        exact = np.asarray(jax.jit(lambda t, p: parts.imaged(t, p))(tip, jnp.asarray(pts)))
        assert np.all(exact >= brute - 1e-9)
        assert np.max(exact - brute) < 0.05  # measured 0.0042 and 0.0052 nm
        assert exact.min() == 0.0  # out on the substrate
    assert np.max(exact) < 2 * radii[0] and exact.max() > 2 * radii[1]  # y = 6 nm passes below the top


def test_dilate_sharp_step_cone_flank():
    """A 50 nm step with a 1e-3 nm edge: beside it the exact image is the tip's profile hung
    from the top corner, depth - profile(d) at distance d (the cone flank, slope
    1/tan theta, beyond r_t). The stencil reaches the corner only from its rings, so the
    image is a staircase: exact at d = ring radius, and between rings it lies between
    the exact value at d and the one at the next ring out (a lateral error of at most the
    ring gap)."""
    depth, w = 50.0, 1e-3
    g = Grating(jnp.asarray(1000.0), jnp.asarray(depth), edge_width=jnp.asarray(w))
    corner = 250.0 - w / 2  # top corner of the line's right edge (line centred at 0)
    exact = lambda d: np.maximum(depth - ref_profile(d), 0.0)
    lateral, vertical, gaps, steps = [], [], [], []
    for kw in (dict(), dict(rings=32, per_ring=64)):
        tip = Tip(**kw)
        q = np.asarray(jax.jit(Tip.stencil)(tip)[0])
        rings = np.unique(np.round(np.hypot(q[:, 0], q[:, 1]), 9))[1:]
        on = rings[(rings > 2 * w) & (rings < 25.5)]  # ring radii where the image is not yet 0
        d = np.concatenate([np.linspace(w + 1e-6, 27.0, 541), on])
        img_all = np.asarray(D(tip, g, jnp.asarray(np.stack([corner + d, 0 * d], -1))))
        img, img_on, d = img_all[:541], img_all[541:], d[:541]
        nxt = rings[np.searchsorted(rings, d)]  # the first ring that reaches the top from d
        assert np.all(img <= exact(d) + 1e-9)
        assert np.all(img >= exact(nxt) - 1e-9)
        # exact where d is a ring radius (the ring's offset along -x reaches the corner)
        np.testing.assert_allclose(img_on, exact(on), atol=1e-6)
        # from ring to ring on the flank (beyond r_t), the image falls at the cone's slope
        flank = on > RT * np.cos(THETA)
        assert flank.sum() >= 2
        np.testing.assert_allclose(np.diff(img_on[flank]) / np.diff(on[flank]), -1 / np.tan(THETA), rtol=1e-6)
        # lateral error: how much further out the exact image has the value the stencil gives
        m = (img > 0.5) & (d > RT * np.cos(THETA))
        dd = np.linspace(0, 30, 30001)
        lateral.append(np.max(np.interp(-img[m], -exact(dd), dd) - d[m]))
        vertical.append(np.max(exact(d) - img))
        # the staircase's bounds: laterally, the way from d to the next ring out (the default's
        # rings at 14.06 and 25 nm on the flank: 10.90 nm from the first point past 14.06 nm; 3.00
        # nm for 32 rings), to the 0.001 nm grid of dd; vertically, the exact image's fall from d
        # to that ring (29.9 and 8.2 nm)
        gaps.append(np.max(nxt[m] - d[m]) + 1e-3)
        steps.append(np.max(exact(d) - exact(nxt)) + 1e-9)
    assert lateral[0] <= gaps[0] < 11.0 and lateral[1] <= gaps[1] < 3.2
    assert vertical[0] <= steps[0] < 30.0 and vertical[1] <= steps[1] and vertical[1] < vertical[0] / 3


def test_dilate_never_lowers_and_keeps_flat_regions():
    tip = Tip()
    rng = np.random.default_rng(7)
    xy = jnp.asarray(rng.uniform(-600, 600, (300, 2)))
    for depth in (20.0, -20.0):
        lt = lattice(depth)
        z, img = np.asarray(H(lt, xy)), np.asarray(D(tip, lt, xy))
        assert np.all(img >= z - 1e-12)
        if depth < 0:  # the flat base is the highest level: imaged unchanged everywhere on it
            np.testing.assert_array_equal(img[z == 0], 0.0)
            assert (z == 0).sum() > 100
        else:  # pillar tops (the highest level) unchanged; base far from pillars unchanged
            np.testing.assert_allclose(img[z == depth], depth, atol=1e-12)
            far = np.asarray(L_PHASE + lab(150, 225))  # cell middle: 270 nm from any centre > 80 + 5 + reach
            assert float(D(tip, lt, jnp.asarray(far))) == pytest.approx(0.0, abs=1e-12)
            assert (img > z + 1).any()  # and the pillars do widen


def test_dilate_gradient_and_surface():
    part = Particles(jnp.array([[0.0, 0.0]]), jnp.array([20.0]))
    tip = Tip()
    f = lambda p: D(tip, part, p)
    for p in ([7.3, 2.1], [-12.0, 9.5]):
        p = np.array(p)
        g = np.asarray(dD(tip, part, jnp.asarray(p)))
        np.testing.assert_allclose(g, fd(f, p, h=1e-6), rtol=1e-5)
        assert g @ p < 0  # downhill away from the particle's top
    # surface(): the bare sample without a tip; with one, particles in closed form (above the
    # stencil's value, which takes the max over fewer offsets), anything else over the stencil
    assert surface(part, None) == part.height
    p = jnp.array([7.3, 2.1])
    assert float(jax.jit(surface(part, tip))(p)) == pytest.approx(float(part.imaged(tip, p)), rel=1e-13)
    assert float(part.imaged(tip, p)) > float(f(p))
    plane = Plane(jnp.asarray(1.0), jnp.array([0.1, 0.0]))
    assert float(jax.jit(surface(plane, tip))(p)) == pytest.approx(float(D(tip, plane, p)), rel=1e-13)


# ----------------------------------------------------------------------------- Indented


PRESS = jax.jit(lambda sample, xy, depth: sample.press(xy, depth))


def test_a_long_path_over_an_indented_field_is_imaged_as_over_every_sphere():
    """``render`` images a long path in chunks, and each chunk's stencil sees only the spheres
    that reach its box widened by the tip's reach (a sphere raises the surface only within its
    radius): the image is the stencil over every sphere, point by point. On a sparse field
    (64 spheres over 3 um) every chunk leaves spheres out; on a dense one (40 over 300 nm) more
    than ``NEAR`` reach a chunk and all are kept there."""
    tip = Tip()
    rng = np.random.default_rng(11)
    for n, size, culled in ((64, 3000.0, True), (40, 300.0, False)):
        spheres = Particles(jnp.asarray(rng.uniform(0, size, (n, 2))), jnp.asarray(rng.uniform(5, 50, n)))
        s = Indented.empty(spheres, tip, capacity=6)
        for c in rng.uniform(0, size, (6, 2)):
            s = PRESS(s, jnp.asarray(c), 30.0)
        x, y = np.meshgrid(np.linspace(0, size, 160), np.linspace(0, size, 48))
        path = jnp.asarray(np.stack([x, y], -1).reshape(-1, 2))  # 48 lines of 160 points
        got = np.asarray(jax.jit(lambda p: render(s, tip, p, batch=160))(path))  # a line a chunk
        want = np.asarray(jax.jit(jax.vmap(lambda p: tip.dilate(s.height, p)))(path))
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
        assert np.ptp(want) > 40  # the field shows: spheres and indents under the path
        boxes = [(c.min(0) - tip.reach, c.max(0) + tip.reach) for c in np.asarray(path).reshape(-1, 160, 2)]
        exact = [bool(spheres.near(jnp.asarray(lo), jnp.asarray(hi))[1]) for lo, hi in boxes]
        assert all(exact) if culled else not all(exact)  # dense: some chunks keep every sphere
    assert NEAR < 40


def test_a_sphere_the_tip_touches_from_beside_a_chunk_is_counted_as_reaching_it(monkeypatch):
    """Two spheres of radius 30 nm on a line and a third, of 40 nm, 60 nm beside it: its flank
    rises where the tip passes (about 11 nm in closed form at x = 550 nm). Kept to two
    spheres a chunk, the second chunk of the line must count all three (its box is widened by
    the tip's reach), so it keeps them all; counting only spheres that overlap the line would
    leave the third out."""
    monkeypatch.setattr(samples, "NEAR", 2)
    tip = Tip()
    spheres = Particles(jnp.array([[350.0, 0.0], [450.0, 0.0], [550.0, 60.0]]), jnp.array([30.0, 30.0, 40.0]))
    s = Indented.empty(spheres, tip, capacity=1)
    path = jnp.stack([jnp.linspace(0.0, 600.0, 600, endpoint=False), jnp.zeros(600)], -1)
    got = np.asarray(render(s, tip, path, batch=300))
    want = np.asarray(jax.vmap(lambda p: tip.dilate(s.height, p))(path))
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
    assert want[550] > 5 and float(spheres.imaged(tip, path[550])) > 5


def test_indent_shape_and_depth():
    """An indent at c, depth D in a flat base z0: z = min(z0, z0 - D + profile(|p - c|))."""
    z0 = 5.0
    s = Indented.empty(Plane(jnp.asarray(z0), jnp.zeros(2)), Tip(), capacity=4)
    assert s.capacity == 4 and int(s.count) == 0
    # unused slots (centred at 0 with bottom 0) do not show
    assert float(H(s, pts([0.0, 0.0]))) == pytest.approx(z0)
    c = np.array([30.0, -20.0])
    s = PRESS(s, jnp.asarray(c), 8.0)
    assert int(s.count) == 1
    r = np.linspace(0, 40, 81)
    xy = np.stack([c[0] + r * np.cos(0.4), c[1] + r * np.sin(0.4)], -1)
    np.testing.assert_allclose(
        np.asarray(H(s, jnp.asarray(xy))), np.minimum(z0, z0 - 8.0 + ref_profile(r)), atol=1e-6
    )
    assert float(H(s, jnp.asarray(c))) == pytest.approx(z0 - 8.0, abs=1e-6)
    assert float(H(s, pts([0.0, 0.0]))) == pytest.approx(z0)


def test_indents_sequential_and_relative_to_current_surface():
    """Indents fill the slots in order; each bottom is the surface there (pits already
    pressed included) less the depth; a full sample refuses another press."""
    slope = np.array([0.05, 0.02])
    base = Plane(jnp.asarray(1.0), jnp.asarray(slope))
    bz = lambda p: 1.0 + np.asarray(p) @ slope
    s = Indented.empty(base, Tip(), capacity=3)
    a, b = np.array([0.0, 0.0]), np.array([100.0, 50.0])
    s = PRESS(s, jnp.asarray(a), 4.0)
    s = PRESS(s, jnp.asarray(b), 6.0)
    assert int(s.count) == 2
    np.testing.assert_allclose(np.asarray(s.centres)[:2], [a, b])
    np.testing.assert_allclose(
        np.asarray(H(s, jnp.asarray(np.stack([a, b])))), [bz(a) - 4, bz(b) - 6], atol=1e-6
    )
    # pressing again at a: 3 nm deeper than the pit's bottom, not than the base
    s = PRESS(s, jnp.asarray(a), 3.0)
    assert int(s.count) == 3
    assert float(H(s, jnp.asarray(a))) == pytest.approx(bz(a) - 7, abs=1e-6)
    np.testing.assert_allclose(np.asarray(s.bottoms), [bz(a) - 4, bz(b) - 6, bz(a) - 7], atol=1e-6)
    # pressing on the wall of pit b: relative to the wall, not to the base
    wall = b + np.array([3.0, 0.0])
    z_wall = bz(b) - 6 + ref_profile(3.0)
    assert float(H(s, jnp.asarray(wall))) == pytest.approx(z_wall, abs=1e-6)
    s4 = PRESS(
        Indented(
            s.base,
            s.tip,
            jnp.zeros((4, 2)).at[:3].set(s.centres),
            jnp.zeros(4).at[:3].set(s.bottoms),
            s.count,
        ),
        jnp.asarray(wall),
        2.0,
    )
    assert float(s4.bottoms[3]) == pytest.approx(z_wall - 2, abs=1e-6)
    with pytest.raises(ValueError, match=r"all 3 indent slots are used.*capacity"):
        s.press(jnp.asarray(b), 1.0)


def test_indent_under_jit_and_grad():
    base = Plane(jnp.asarray(0.0), jnp.zeros(2))
    s0 = Indented.empty(base, Tip(), capacity=8)

    # a row of indents pressed in a loop under jit
    def row(s):
        return jax.lax.fori_loop(0, 5, lambda i, s: s.press(jnp.stack([60.0 * i, 100.0]), 1.0 + i), s)

    s5 = jax.jit(row)(s0)
    assert int(s5.count) == 5
    centres = np.stack([60.0 * np.arange(5), np.full(5, 100.0)], -1)
    np.testing.assert_allclose(np.asarray(s5.centres)[:5], centres)
    np.testing.assert_allclose(np.asarray(s5.bottoms), np.r_[-(1.0 + np.arange(5)), np.zeros(3)], atol=1e-6)
    np.testing.assert_allclose(np.asarray(H(s5, jnp.asarray(centres))), -(1.0 + np.arange(5)), atol=1e-6)
    # d height(p) / d depth = -1 and, at p on the pit's spherical wall (r = 3 < r_t, with
    # z = -depth + R - sqrt(R^2 - r^2)), d/d(press x) = -r / sqrt(R^2 - r^2)
    grad = jax.jit(jax.grad(lambda d, xy, s, p: s.press(xy, d).height(p), argnums=(0, 1)))
    gd, gxy = grad(jnp.asarray(5.0), jnp.array([0.0, 0.0]), s0, jnp.array([3.0, 0.0]))
    assert float(gd) == pytest.approx(-1.0, abs=1e-9)
    np.testing.assert_allclose(np.asarray(gxy), [-3.0 / np.sqrt(RT**2 - 9.0), 0.0], rtol=1e-6, atol=1e-9)


# ----------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    "make,match",
    [
        (lambda: grating(duty=0.0), "Grating.duty"),
        (lambda: grating(duty=1.0), "Grating.duty"),
        (lambda: grating(duty=1.5), "Grating.duty"),
        (lambda: grating(pitch=-400.0), "Grating.pitch"),
        (lambda: grating(pitch=0.0), "Grating.pitch"),
        (lambda: grating(edge_width=0.0), "Grating.edge_width"),
        (lambda: grating(depth=np.nan), "Grating.depth"),
        (lambda: Lattice(jnp.array([300.0, 0.0]), jnp.asarray(80.0), jnp.asarray(20.0)), "Lattice.pitch"),
        (lambda: Lattice(jnp.array([300.0, 300.0]), jnp.asarray(-1.0), jnp.asarray(20.0)), "Lattice.radius"),
        (lambda: Tip(half_angle=jnp.asarray(0.0)), "half_angle"),
        (lambda: Tip(half_angle=jnp.asarray(np.pi / 2)), "half_angle"),
        (lambda: Tip(half_angle=jnp.asarray(20.0)), "half_angle"),  # degrees by mistake
        (lambda: Tip(radius=jnp.asarray(0.0)), "Tip.radius"),
        (lambda: Tip(reach=0.0), "reach"),
        (lambda: Tip(per_ring=3), "per_ring"),
        (lambda: HeightMap(jnp.array([[1.0, np.nan], [0.0, 0.0]]), jnp.ones(2)), "HeightMap.z"),
        (lambda: HeightMap(jnp.arange(5.0), jnp.ones(2)), "HeightMap.z"),
        (lambda: HeightMap(jnp.zeros((3, 3)), jnp.array([1.0, 0.0])), "HeightMap.pixel_size"),
        (lambda: Particles(jnp.zeros(3), jnp.ones(3)), "Particles.centres"),
        (lambda: Particles(jnp.zeros((2, 2)), jnp.ones(3)), "Particles.centres"),
        (lambda: Particles(jnp.zeros((2, 2)), jnp.array([1.0, -1.0])), "Particles.radii"),
        (lambda: Particles(jnp.array([[0.0, np.inf]]), jnp.ones(1)), "Particles.centres"),
    ],
)
def test_bad_input_names_the_field(make, match):
    with pytest.raises(ValueError, match=match.replace(".", r"\.")):
        make()
