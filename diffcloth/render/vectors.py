"""Per-pixel vector helpers of the shading modes: short sums written out, normalisation, powers
through exp / log, view vectors, reflection and refraction (`shade` re-exports every name)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from diffcloth._math import EPS, safe_sqrt

# Per-pixel vectors are (H, W, ..., 3). XLA's CPU backend lowers a reduce over such a short minor
# axis to a slow generic loop (a (256, 256, 1, 3) dot product took 4.4 ms, the written-out sum
# 0.15 ms) and jnp.power to a scalar libm call (4.5x slower than exp(k log x)), so the helpers
# below spell short sums out and take powers of positive bases through exp / log.


def _sum_axis(x, axis: int):
    """Sum over a short axis (written out up to 8 entries)."""
    n = x.shape[axis]
    if n > 8 or n == 0:
        return jnp.sum(x, axis=axis)
    take = [jax.lax.index_in_dim(x, i, axis, keepdims=False) for i in range(n)]
    out = take[0]
    for t in take[1:]:
        out = out + t
    return out


def _dot(a, b):
    return _sum_axis(a * b, -1)


def _normalize(x):
    """`diffcloth._math.safe_normalize` over the last axis (fallback +y for 3-vectors, else the
    first basis vector) with the squared length summed by `_sum_axis`."""
    eps = EPS.get(jnp.result_type(x), 1e-12)
    sq = _sum_axis(x * x, -1)[..., None]
    ok = sq > eps
    n = jnp.sqrt(jnp.where(ok, sq, 1.0))
    size = x.shape[-1]
    fallback = jnp.zeros(size, x.dtype).at[1 if size == 3 else 0].set(1.0)
    return jnp.where(ok, jnp.where(ok, x, 1.0) / n, fallback.reshape((1,) * (x.ndim - 1) + (size,)))


def _pow(x, k, eps: float = 1e-6):
    """`diffcloth._math.safe_pow`: max(x, eps) ** k, as exp(k log max(x, eps))."""
    return jnp.exp(k * jnp.log(jnp.maximum(x, eps)))


def _bc(x, like):
    """Reshape a parameter (e.g. a (3,) colour) to the rank of `like` (explicit broadcasting)."""
    x = jnp.asarray(x)
    return jnp.reshape(x, (1,) * (jnp.ndim(like) - x.ndim) + x.shape)


def view_vectors(eye, positions):
    """Unit vectors E from each position toward the eye.

    Args:
      eye: (3,) eye position (m), or (4,) homogeneous (x, y, z, w): w = 1 a point, w = 0 a direction
        toward the viewer (orthographic / parallel projection), or an array shaped like
        `positions` (e.g. (H, W, 3)): per-pixel vectors toward the viewer (minus the pixel rays;
        right for every projection, oblique included).
      positions: (..., 3) world positions.
    Returns:
      (..., 3) unit vectors (a zero vector falls back to +y).
    """
    eye = jnp.asarray(eye)
    if eye.ndim > 1 and eye.shape == positions.shape:
        return _normalize(eye)
    if eye.shape == (3,):
        return _normalize(_bc(eye, positions) - positions)
    if eye.shape == (4,):
        return _normalize(_bc(eye[:3], positions) - eye[3] * positions)
    raise ValueError(f"eye must have shape (3,) or (4,), got {eye.shape}")


def reflect(e, n):
    """The seed's reflected eye vector R = -(E - 2 (E.N) N) (E toward the eye, N unit)."""
    return 2.0 * _dot(e, n)[..., None] * n - e


def refract_shortened(e, n, s):
    """The seed's refraction approximation with a shortened normal N' = s N:
    R' = -(E - 2 (E.N') N') = -(E - 2 s^2 (E.N) N), normalised (zero falls back to +y).

    Shapes: e, n (..., 3), s () -> (..., 3).
    """
    return _normalize(-(e - 2.0 * (s * s) * _dot(e, n)[..., None] * n))


def refract(incident, n, eta):
    """Snell refraction of a unit `incident` direction (pointing at the surface) through unit normal
    `n` with relative index eta = n_from / n_to. Where the square-root argument is negative (total
    internal reflection) it returns the mirror reflection instead; finite value and gradient.

    Shapes: incident, n (..., 3), eta () or (...) -> (..., 3).
    """
    cos_i = -_dot(incident, n)
    k = 1.0 - eta * eta * (1.0 - cos_i * cos_i)
    t = eta * incident + (eta * cos_i - safe_sqrt(k))[..., None] * n
    mirror = incident + 2.0 * cos_i[..., None] * n
    return _normalize(jnp.where((k > 0)[..., None], t, mirror))
