"""Sample topographies ``z = sample.height(xy)`` (nm) and the AFM tip that images them.

Every sample is an :class:`AbstractSample` with ``height(xy)`` for points ``xy`` of
shape ``(..., 2)`` nm, differentiable in the points and the sample's parameters:
calibration gratings (1-D lines, 2-D lattices of pits or pillars) with edges of
finite width, nanoparticles on a flat or tilted substrate, indents pressed by
the tip, and any measured height map, sampled by bilinear interpolation.

The tip (effect ``tip``): a sphere of radius ``R`` capped by a cone of half-angle
``theta``. What the AFM records is the dilation of the surface by the tip,
``I(p) = max_q [z(p + q) - tip(q)]`` (Villarrubia 1997), evaluated here over a
fixed polar stencil of offsets ``q`` so that it works at any point of a
distorted scan path (:meth:`AbstractSample.imaged`); particles and line gratings
override it with their closed forms (:meth:`Particles.imaged`, :meth:`Grating.imaged`).
A new kind of sample is one class: its ``height``, and ``imaged`` where a closed form
exists.
"""

from __future__ import annotations

import abc
from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .. import checks
from ..model.hysteresis import softplus_inverse

Array = jax.Array


def _ramp(distance_inside: Array, edge_width: Array) -> Array:
    """0 outside, 1 inside, linear across an edge ``edge_width`` nm wide centred on the boundary."""
    return jnp.clip(distance_inside / edge_width + 0.5, 0.0, 1.0)


def _rotate(xy: Array, angle: Array) -> Array:
    """Coordinates of ``xy`` in axes turned by ``angle`` (rad) anticlockwise."""
    c, s = jnp.cos(angle), jnp.sin(angle)
    x, y = xy[..., 0], xy[..., 1]
    return jnp.stack([c * x + s * y, -s * x + c * y], axis=-1)


def _nearest_offset(u: Array, pitch: Array, phase: Array) -> Array:
    """Offset of ``u`` from the nearest of the points ``phase + k pitch``."""
    return jnp.mod(u - phase + pitch / 2, pitch) - pitch / 2


class AbstractSample(eqx.Module):
    """A sample's topography, and how the tip images it."""

    @abc.abstractmethod
    def height(self, xy: Array) -> Array:
        """The surface height at points ``xy`` (..., 2) nm.

        Arguments:
            xy: lateral positions (..., 2) nm.

        Returns:
            Heights (...) nm.
        """

    def imaged(self, tip: Tip, xy: Array) -> Array:
        """What the tip records at ``xy`` (..., 2) nm: ``max_q [height(xy + q) - tip(|q|)]``.

        By default over the tip's stencil (:meth:`Tip.dilate`); samples with a closed form
        override it.

        Arguments:
            tip: the probe.
            xy: the apex's lateral positions (..., 2) nm.

        Returns:
            The dilated heights (...) nm.
        """
        return tip.dilate(self.height, xy)


class Plane(AbstractSample):
    """A flat substrate ``z = z0 + slope . xy`` (nm; slopes dimensionless)."""

    z0: Array = eqx.field(default_factory=lambda: jnp.zeros(()))
    slope: Array = eqx.field(default_factory=lambda: jnp.zeros(2))

    def height(self, xy: Array) -> Array:
        return self.z0 + xy @ self.slope


class Grating(AbstractSample):
    """A 1-D calibration grating: raised lines of ``depth`` nm every ``pitch`` nm.

    Lines run perpendicular to the direction ``angle`` (rad; 0: lines along
    y, so x crosses them); a line's top is ``duty * pitch`` wide, and each edge
    rises over ``edge_width`` nm. A line is centred at ``phase`` nm.
    """

    pitch: Array
    depth: Array
    duty: Array = eqx.field(default_factory=lambda: jnp.asarray(0.5))
    edge_width: Array = eqx.field(default_factory=lambda: jnp.asarray(50.0))
    angle: Array = eqx.field(default_factory=lambda: jnp.zeros(()))
    phase: Array = eqx.field(default_factory=lambda: jnp.zeros(()))

    def __check_init__(self):
        checks.positive("Grating.pitch", self.pitch)
        checks.positive("Grating.edge_width", self.edge_width)
        checks.finite("Grating.depth", self.depth)
        v = np.asarray(self.duty) if checks.is_concrete(self.duty) else None
        if v is not None and not 0 < v < 1:
            raise ValueError(
                f"Grating.duty is the fraction of a pitch a line's top covers: 0 < duty < 1, got {v}"
            )

    def height(self, xy: Array) -> Array:
        d = jnp.abs(_nearest_offset(_rotate(xy, self.angle)[..., 0], self.pitch, self.phase))
        return self.depth * _ramp(self.duty * self.pitch / 2 - d, self.edge_width)

    def imaged(self, tip: Tip, xy: Array) -> Array:
        """The exact tip image at ``xy`` (..., 2) nm, ``max_q [h(xy + q) - tip(|q|)]``.

        The grating is the same along its lines and its profile across them is piecewise
        linear, so the maximum is attained on a top corner, ``H - tip(|s - t|)``, on a top
        plateau, ``H``, or inside a wall where the apex sphere touches it tangentially:
        for a wall of slope ``m <= cot(theta)`` the sphere touches ``r* = R m / sqrt(1 + m^2)``
        uphill and the image is the wall lifted by ``R (sqrt(1 + m^2) - 1)`` (steeper walls
        meet the tip only at their corners). ``s`` is the distance from a line's centre,
        ``t`` the top's half width, ``H`` its height; the nearest line and its two neighbours
        are taken. Grooves (``depth < 0``) are lines of ``|depth|`` between them, lowered.
        """
        neg = self.depth < 0
        depth, duty = jnp.abs(self.depth), jnp.where(neg, 1 - self.duty, self.duty)
        phase = jnp.where(neg, self.phase + self.pitch / 2, self.phase)
        p, w = self.pitch, self.edge_width
        half, top = duty * p / 2 + w / 2, jnp.maximum(duty * p / 2 - w / 2, 0.0)  # wall foot, top edge
        height = depth * jnp.clip(half / w, 0.0, 1.0)
        m = depth / w
        u = _rotate(xy, self.angle)[..., 0]
        k = jnp.round((u - phase) / p)[..., None] + jnp.array([-1.0, 0.0, 1.0])
        s = jnp.abs(u[..., None] - phase - k * p)  # (..., 3)
        corner = height - tip.profile(jnp.abs(s - top))
        plateau = jnp.where(s <= top, height, -jnp.inf)
        r_star = tip.radius * m / jnp.sqrt(1 + m**2)
        inside = (
            (s - r_star >= top)
            & (s - r_star <= jnp.minimum(half, p / 2))
            & (m * jnp.tan(tip.half_angle) <= 1)
        )
        wall = jnp.where(inside, depth * (half - s) / w + tip.radius * (jnp.sqrt(1 + m**2) - 1), -jnp.inf)
        best = jnp.max(jnp.maximum(jnp.maximum(corner, plateau), wall), axis=-1)
        return jnp.maximum(best, 0.0) + jnp.where(neg, self.depth, 0.0)


class Lattice(AbstractSample):
    """A 2-D calibration grating: round pits or pillars of ``radius`` on a square or
    rectangular lattice of ``pitch`` (2,) nm turned by ``angle`` (rad).

    ``depth > 0`` gives pillars that high, ``depth < 0`` pits that deep, on a
    base at 0 nm. Centre of one feature at ``phase`` (2,) nm.
    """

    pitch: Array
    radius: Array
    depth: Array
    edge_width: Array = eqx.field(default_factory=lambda: jnp.asarray(50.0))
    angle: Array = eqx.field(default_factory=lambda: jnp.zeros(()))
    phase: Array = eqx.field(default_factory=lambda: jnp.zeros(2))

    def __check_init__(self):
        checks.positive("Lattice.pitch", self.pitch)
        checks.positive("Lattice.radius", self.radius)
        checks.positive("Lattice.edge_width", self.edge_width)
        checks.finite("Lattice.depth", self.depth)

    def free_parameters(
        self, length_scale, depth_scale, edge_scale, angle_scale: Optional[float] = None
    ) -> tuple:
        """The lattice's unknowns at order one, and the map back (the pitch is known and stays):
        ``phase / length_scale``, ``softplus^-1(radius / length_scale)``, ``depth / depth_scale``,
        ``softplus^-1(edge_width / edge_scale)`` (radius and edge width kept > 0) and, with an
        ``angle_scale`` (rad), ``angle / angle_scale`` (without one the angle is known and stays).

        Returns:
            ``(raw, rebuild)``: a tuple of raw parameters in that order and ``rebuild(raw) -> Lattice``.
        """
        raw = (
            self.phase / length_scale,
            softplus_inverse(self.radius / length_scale),
            self.depth / depth_scale,
            softplus_inverse(self.edge_width / edge_scale),
        )
        if angle_scale is not None:
            raw += (self.angle / angle_scale,)

        def rebuild(p):
            values = (
                p[0] * length_scale,
                jax.nn.softplus(p[1]) * length_scale,
                p[2] * depth_scale,
                jax.nn.softplus(p[3]) * edge_scale,
            )
            fields = lambda lat: (lat.phase, lat.radius, lat.depth, lat.edge_width)
            if angle_scale is not None:
                values += (p[4] * angle_scale,)
                fields = lambda lat: (lat.phase, lat.radius, lat.depth, lat.edge_width, lat.angle)
            return eqx.tree_at(fields, self, values)

        return raw, rebuild

    def coordinates(self, xy: Array) -> Array:
        """Lattice coordinates (..., 2) of positions ``xy`` (..., 2) nm: in pitches along the
        lattice's axes from the feature at ``phase``; whole numbers at feature centres."""
        return _rotate(xy - self.phase, self.angle) / self.pitch

    def sites(self, ij: Array) -> Array:
        """Positions (..., 2) nm of the feature centres with lattice indices ``ij`` (..., 2): the
        inverse of :meth:`coordinates`."""
        return self.phase + _rotate(jnp.asarray(ij) * self.pitch, -self.angle)

    def height(self, xy: Array) -> Array:
        off = _nearest_offset(_rotate(xy, self.angle), self.pitch, _rotate(self.phase, self.angle))
        r = jnp.sqrt(jnp.sum(off**2, axis=-1) + 1e-12)
        return self.depth * _ramp(self.radius - r, self.edge_width)


class Particles(AbstractSample):
    """Spheres of ``radii`` (K,) nm resting at ``centres`` (K, 2) nm on a ``substrate``.

    The surface is the higher of the substrate and the spheres' upper halves:
    a sphere touching the substrate at ``c`` has its top ``2R`` above it.
    """

    centres: Array
    radii: Array
    substrate: AbstractSample = eqx.field(default_factory=Plane)

    def __check_init__(self):
        checks.positive("Particles.radii", self.radii)
        checks.finite("Particles.centres", self.centres)
        if np.size(self.radii) == 0:
            raise ValueError("Particles needs at least one particle; use the substrate alone for none")
        if np.shape(self.centres) != np.shape(self.radii) + (2,):
            raise ValueError(
                f"Particles.centres must have shape (K, 2) for K radii, got "
                f"{np.shape(self.centres)} for {np.shape(self.radii)} radii"
            )

    def height(self, xy: Array) -> Array:
        base = self.substrate.height(xy)
        r2 = jnp.sum((xy[..., None, :] - self.centres) ** 2, axis=-1)  # (..., K)
        inside = r2 < self.radii**2
        cap = jnp.sqrt(jnp.where(inside, self.radii**2 - r2, 1.0))
        top = self.substrate.height(self.centres) + self.radii + cap
        return jnp.maximum(base, jnp.max(jnp.where(inside, top, -jnp.inf), axis=-1))

    def near(self, lo: Array, hi: Array) -> Optional[tuple]:
        """``(spheres, exact)``: the :data:`NEAR` spheres that come closest to reaching into the
        box ``lo``..``hi`` (2,) nm, and whether they are all that reach into it. A sphere
        raises the surface only within its radius of its centre, so where ``exact`` the
        surface in the box is the same; ``None`` when there are no more than ``NEAR`` spheres."""
        if self.radii.shape[0] <= NEAR:
            return None
        gap = jnp.linalg.norm(jnp.maximum(jnp.maximum(lo - self.centres, self.centres - hi), 0.0), axis=-1)
        _, keep = lax.top_k(self.radii - gap, NEAR)  # reaching in: radius - gap > 0
        spheres = Particles(self.centres[keep], self.radii[keep], self.substrate)
        return spheres, jnp.sum(gap < self.radii) <= NEAR

    def imaged(self, tip: Tip, xy: Array) -> Array:
        """The exact tip image at ``xy`` (..., 2) nm, for a level substrate.

        The tip is the ball of radius ``r`` swept by a cone of half-angle ``theta``,
        so it touches a sphere of radius ``R`` where a sharp cone touches the sphere
        of radius ``rho = R + r``. At lateral distance ``d`` the apex stands at
        ``R - r + sqrt(rho^2 - d^2)`` for ``d <= rho cos(theta)`` (contact on the
        apex ball), else ``R - r + rho / sin(theta) - d / tan(theta)`` (on the
        flank); the substrate holds it at ``z0``. A tilted substrate adds its height
        at ``xy`` (exact to first order in the slope).
        """
        base = self.substrate.height(xy)
        R, th = self.radii, tip.half_angle
        rho = R + tip.radius
        d = jnp.sqrt(jnp.sum((xy[..., None, :] - self.centres) ** 2, axis=-1) + 1e-12)  # (..., K)
        ball = jnp.sqrt(jnp.maximum(rho**2 - jnp.minimum(d, rho * jnp.cos(th)) ** 2, 0.0))
        flank = jnp.maximum(d - rho * jnp.cos(th), 0.0) / jnp.tan(th)
        apex = R - tip.radius + ball - flank
        return base + jnp.maximum(jnp.max(apex, axis=-1), 0.0)


class HeightMap(AbstractSample):
    """A measured topography ``z`` (rows = y, columns = x) nm, pixel ``pixel_size`` (2,) nm
    (x, y), pixel ``[0, 0]`` centred at ``origin`` (2,) nm; bilinear between pixels,
    the edge value beyond them."""

    z: Array = eqx.field(converter=lambda z: jnp.asarray(z, dtype=float))
    pixel_size: Array
    origin: Array = eqx.field(default_factory=lambda: jnp.zeros(2))

    def __check_init__(self):
        checks.finite("HeightMap.z", self.z)
        checks.positive("HeightMap.pixel_size", self.pixel_size)
        if np.ndim(self.z) != 2:
            raise ValueError(f"HeightMap.z must be a 2-D image, got shape {np.shape(self.z)}")

    def height(self, xy: Array) -> Array:
        ij = (xy - self.origin) / self.pixel_size  # (..., 2) as (col, row)
        coords = [jnp.ravel(ij[..., 1]), jnp.ravel(ij[..., 0])]
        z = jax.scipy.ndimage.map_coordinates(self.z, coords, order=1, mode="nearest")
        return z.reshape(ij.shape[:-1])


class Tip(eqx.Module):
    """A sphere-capped cone: apex radius ``radius`` nm, cone half-angle ``half_angle`` rad.

    ``profile(r)``, the tip's surface above its apex at lateral distance ``r``:
    ``R - sqrt(R^2 - r^2)`` up to where the sphere meets the cone tangentially,
    ``r_t = R cos(theta)``, then ``z_t + (r - r_t) / tan(theta)``.

    ``dilate(height, xy)`` images a surface with the tip over a stencil of
    ``rings`` rings of ``per_ring`` offsets each (plus the centre), out to
    ``reach`` nm, the rings denser near the apex. The reach needs to cover how
    far the flank can touch: about ``r_t + h tan(theta)`` for features ``h`` nm high.
    """

    radius: Array = eqx.field(default_factory=lambda: jnp.asarray(10.0))
    half_angle: Array = eqx.field(default_factory=lambda: jnp.asarray(np.deg2rad(20.0)))
    reach: float = eqx.field(static=True, default=100.0)
    rings: int = eqx.field(static=True, default=8)
    per_ring: int = eqx.field(static=True, default=16)

    def __check_init__(self):
        checks.positive("Tip.radius", self.radius)
        a = np.asarray(self.half_angle) if checks.is_concrete(self.half_angle) else None
        if a is not None and not 0 < a < np.pi / 2:
            raise ValueError(f"Tip.half_angle is in radians, 0 < half_angle < pi/2, got {a}")
        if not self.reach > 0 or self.rings < 1 or self.per_ring < 4:
            raise ValueError(
                f"Tip stencil needs reach > 0 nm, rings >= 1 and per_ring >= 4, got "
                f"reach={self.reach}, rings={self.rings}, per_ring={self.per_ring}"
            )

    def profile(self, r: Array) -> Array:
        R, th = self.radius, self.half_angle
        rt = R * jnp.cos(th)
        sphere = R - jnp.sqrt(jnp.maximum(R**2 - jnp.minimum(r, rt) ** 2, 1e-12))
        return sphere + jnp.maximum(r - rt, 0.0) / jnp.tan(th)

    def stencil(self) -> tuple:
        """Offsets (S, 2) nm and the tip's height at each (S,)."""
        radii = self.reach * (np.arange(1, self.rings + 1) / self.rings) ** 2
        angles = 2 * np.pi * np.arange(self.per_ring) / self.per_ring
        q = np.concatenate(
            [
                np.zeros((1, 2)),
                (radii[:, None, None] * np.stack([np.cos(angles), np.sin(angles)], axis=-1)).reshape(-1, 2),
            ]
        )
        return jnp.asarray(q), self.profile(jnp.asarray(np.hypot(q[:, 0], q[:, 1])))

    def dilate(self, height, xy: Array) -> Array:
        """``max_q [height(xy + q) - profile(|q|)]`` for ``height`` a function of points (..., 2)."""
        q, lift = self.stencil()
        return jnp.max(height(xy[..., None, :] + q) - lift, axis=-1)


class Indented(AbstractSample):
    """A ``base`` sample with up to ``capacity`` indents pressed into it by a ``tip``.

    An indent pressed at ``xy`` to ``depth`` nm leaves the tip's shape in the
    surface: ``z = min(surface, bottom + profile(|p - xy|))``, ``bottom`` the
    surface height there (earlier indents included) less the depth (plastic
    indentation, no pile-up).
    Slots are fixed so that ``press`` works under ``jit``; ``count`` are used.
    The capacity is checked on concrete values only: under ``jit`` an indent
    beyond it is dropped.
    """

    base: AbstractSample
    tip: Tip
    centres: Array  # (capacity, 2) nm
    bottoms: Array  # (capacity,) nm
    count: Array  # () int

    @classmethod
    def empty(cls, base, tip: Tip, capacity: int = 32) -> Indented:
        return cls(base, tip, jnp.zeros((capacity, 2)), jnp.zeros(capacity), jnp.zeros((), dtype=int))

    @property
    def capacity(self) -> int:
        return self.bottoms.shape[0]

    def press(self, xy: Array, depth) -> Indented:
        """The sample with one more indent at ``xy`` (2,) nm, ``depth`` nm deep."""
        if checks.is_concrete(self.count) and int(self.count) >= self.capacity:
            raise ValueError(
                f"all {self.capacity} indent slots are used; make the sample with "
                "Indented.empty(base, tip, capacity=...) larger"
            )
        bottom = self.height(xy) - depth
        return eqx.tree_at(
            lambda s: (s.centres, s.bottoms, s.count),
            self,
            (self.centres.at[self.count].set(xy), self.bottoms.at[self.count].set(bottom), self.count + 1),
        )

    def height(self, xy: Array) -> Array:
        r = jnp.sqrt(jnp.sum((xy[..., None, :] - self.centres) ** 2, axis=-1) + 1e-12)
        used = jnp.arange(self.capacity) < self.count
        pits = jnp.where(used, self.bottoms + self.tip.profile(r), jnp.inf)
        return jnp.minimum(self.base.height(xy), jnp.min(pits, axis=-1))

    def imaged(self, tip: Tip, xy: Array) -> Array:
        """The stencil's image (:meth:`Tip.dilate`) at ``xy`` (..., 2) nm, on a base of
        :class:`Particles` with only the spheres that reach the points' box widened by the
        stencil's reach (:meth:`Particles.near`), when those are all that reach it: the same
        image, at a fraction of the cost on a long path imaged in chunks
        (:func:`~jaxafm.instrument.afm.render`)."""
        near = self.base.near(*_box(xy, tip.reach)) if isinstance(self.base, Particles) else None
        if near is None:
            return tip.dilate(self.height, xy)
        culled = eqx.tree_at(lambda s: s.base, self, near[0])
        return lax.cond(near[1], lambda: tip.dilate(culled.height, xy), lambda: tip.dilate(self.height, xy))


#: how many spheres :meth:`Particles.near` keeps
NEAR = 16


def _box(xy: Array, margin: float) -> tuple:
    """The corners (2,) nm of the box around the points ``xy`` (..., 2), widened by ``margin`` nm."""
    flat = jnp.reshape(xy, (-1, 2))
    return jnp.min(flat, axis=0) - margin, jnp.max(flat, axis=0) + margin


def surface(sample: AbstractSample, tip: Optional[Tip]):
    """The height the AFM's probe follows, as a function of points (..., 2) nm.

    Arguments:
        sample: the sample.
        tip: the probe, or ``None`` for no tip effect.

    Returns:
        ``sample.imaged(tip, .)`` (:meth:`AbstractSample.imaged`), or ``sample.height``
        without a tip.
    """
    if tip is None:
        return sample.height
    return lambda xy: sample.imaged(tip, xy)
