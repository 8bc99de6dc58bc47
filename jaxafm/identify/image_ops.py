"""Operations on images and on arrays laid out like them (lines, pixels, ...): values at
fractional pixels by bilinear interpolation, and a separable Gaussian blur renormalised at the
borders. Step A samples the tip's path at feature centres with the first and compares blurred
images with the second."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

Array = jax.Array


def interpolate(a: Array, rc: Array, xp=jnp) -> Array:
    """Bilinear interpolation of ``a`` (L, P, ...) at fractional pixels ``rc`` (n, 2), with the
    array module ``xp`` (``jax.numpy`` inside the fits, ``numpy`` for a look at a result).

    ``a(r, c) = sum over the four neighbours (r0 + i, c0 + j), i, j in {0, 1}, of
    (1 - |r - r0 - i|) (1 - |c - c0 - j|) a[r0 + i, c0 + j]``, ``r0 = floor(r)``, ``c0 = floor(c)``
    clipped so that the neighbours lie inside (beyond the last row or column the edge's slope
    continues).
    """
    r0 = xp.clip(xp.floor(rc[:, 0]).astype(int), 0, a.shape[0] - 2)
    c0 = xp.clip(xp.floor(rc[:, 1]).astype(int), 0, a.shape[1] - 2)
    fr, fc = (rc[:, 0] - r0)[:, None], (rc[:, 1] - c0)[:, None]
    return (
        (1 - fr) * (1 - fc) * a[r0, c0]
        + (1 - fr) * fc * a[r0, c0 + 1]
        + fr * (1 - fc) * a[r0 + 1, c0]
        + fr * fc * a[r0 + 1, c0 + 1]
    )


def sample_at(a, rc) -> np.ndarray:
    """:func:`interpolate` in NumPy (nothing to compile): ``a`` (L, P, ...), e.g. a tip path
    (nm), at fractional pixels ``rc`` (n, 2) (row, col)."""
    return interpolate(np.asarray(a), np.asarray(rc, dtype=float), np)


def gaussian_kernel(sigma_px: float, radius: int) -> np.ndarray:
    """Taps ``-radius..radius`` of a Gaussian ``exp(-k^2 / (2 sigma_px^2))`` (unnormalised: the
    blur renormalises); a unit impulse for ``sigma_px = 0``."""
    k = np.arange(-radius, radius + 1)
    return (k == 0).astype(float) if sigma_px <= 0 else np.exp(-0.5 * (k / sigma_px) ** 2)


def blur(z: Array, kernel: Array) -> Array:
    """Separable blur of an image along both axes, renormalised at the borders:
    ``(K * z) / (K * 1)``, ``K`` the kernel along rows then columns, zero beyond the image."""
    r = (kernel.shape[0] - 1) // 2

    def along(a, axis):
        padded = jnp.pad(a, [(r, r) if ax == axis else (0, 0) for ax in range(a.ndim)])
        return sum(
            kernel[i] * jax.lax.slice_in_dim(padded, i, i + a.shape[axis], axis=axis)
            for i in range(kernel.shape[0])
        )

    return along(along(z, 0), 1) / along(along(jnp.ones_like(z), 0), 1)
