"""Gradient-safe elementwise math shared by every stage.

Each function uses the per-element "double where": the unsafe branch is fed a harmless value
where it would be singular, so neither the value nor the gradient is ever NaN or inf
(the pattern of jax-md's `space.distance`). All functions work in float32 and float64.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

EPS = {jnp.dtype("float32"): 1e-12, jnp.dtype("float64"): 1e-30}


def dtype_eps(x) -> float:
    """Default threshold below which the safe functions treat a value as zero, per dtype."""
    return EPS.get(jnp.result_type(x), 1e-12)


def safe_sqrt(x, eps: float | None = None):
    """sqrt(max(x, 0)) with a finite gradient at and below 0 (gradient 0 there)."""
    eps = dtype_eps(x) if eps is None else eps
    ok = x > eps
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, x, 1.0)), 0.0)


def safe_norm(x, axis: int = -1, keepdims: bool = False, eps: float | None = None):
    """Euclidean norm along `axis`; 0 with gradient 0 for a zero vector."""
    sq = jnp.sum(x * x, axis=axis, keepdims=keepdims)
    return safe_sqrt(sq, eps)


def safe_normalize(x, axis: int = -1, fallback=None, eps: float | None = None):
    """x / |x| along `axis`; where |x| is (near) zero return `fallback` (default +y for 3-vectors,
    else the first basis vector). Finite value and gradient everywhere."""
    eps = dtype_eps(x) if eps is None else eps
    sq = jnp.sum(x * x, axis=axis, keepdims=True)
    ok = sq > eps
    n = jnp.sqrt(jnp.where(ok, sq, 1.0))
    if fallback is None:
        size = x.shape[axis]
        shape = [1] * x.ndim
        shape[axis] = size
        fallback = jnp.zeros(size, x.dtype).at[1 if size == 3 else 0].set(1.0).reshape(shape)
    return jnp.where(ok, jnp.where(ok, x, 1.0) / n, jnp.asarray(fallback, x.dtype))


def safe_div(num, den, eps: float | None = None, fallback=0.0):
    """num / den, returning `fallback` (gradient 0) where |den| <= eps."""
    eps = dtype_eps(den) if eps is None else eps
    ok = jnp.abs(den) > eps
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), fallback)


def safe_pow(x, k, eps: float = 1e-6):
    """max(x, eps) ** k for x >= 0 inputs such as clamped cosines; finite for any real k."""
    return jnp.power(jnp.maximum(x, eps), k)


def safe_atan2(y, x, eps: float | None = None):
    """atan2(y, x) that returns 0 with gradient 0 at the origin."""
    eps = dtype_eps(x) if eps is None else eps
    ok = (x * x + y * y) > eps
    return jnp.where(ok, jnp.arctan2(jnp.where(ok, y, 0.0), jnp.where(ok, x, 1.0)), 0.0)


def static_zero(x) -> bool:
    """True when x is concrete (not traced) and every entry is zero: a term it scales can be left
    out of the program. A traced x (fitted, vmapped) is never static."""
    return not isinstance(x, jax.core.Tracer) and not np.any(np.asarray(x))


def _scatter_copy(x):
    """x scattered row by row into zeros: a buffer of its own (zero-fill, copy of the shared zero
    constant, then the scatter), and its transpose is a row gather."""
    n = x.shape[0]
    return jnp.zeros_like(x).at[jnp.arange(n)].set(x, unique_indices=True, indices_are_sorted=True)


def in_place(x):
    """x with its first row written back over itself: a dynamic update slice, done in place on
    the producer's buffer (no zero-fill, no copy), so x is computed once into that buffer."""
    if x.ndim == 0 or x.shape[0] == 0:
        return x
    return jax.lax.dynamic_update_slice_in_dim(x, x[:1], 0, axis=0)


def _in_place_with_tangent(tangent_rule):
    """`in_place` as a custom_jvp whose tangent is tangent_rule(t)."""
    fn = jax.custom_jvp(in_place)
    fn.defjvp(lambda primals, tangents: (in_place(primals[0]), tangent_rule(tangents[0])))
    return fn


_materialize_float = _in_place_with_tangent(_scatter_copy)


def materialize(x):
    """x itself, computed once into a buffer. XLA's CPU fusion otherwise inlines producers that
    look cheap (per-triangle tables, texture lookups, shaded pixels) into every consumer that reads
    them, e.g. per pixel, per channel or per shifted neighbour, and recomputes them there
    (optimization_barrier is removed before fusion); an in-place update's operand is always
    materialized. The value goes through `in_place` (no zero-fill or copy); the tangent of a
    float x through `_scatter_copy`, so derivatives (forward and backward) are those of the row
    scatter. Differentiable in both modes."""
    if jnp.issubdtype(jnp.result_type(x), jnp.inexact):
        return _materialize_float(x)
    return in_place(x)


_value_only = _in_place_with_tangent(lambda t: t)


def materialize_value(x):
    """x itself, its value computed once into a buffer (as `materialize`), its tangent and
    cotangent passed through untouched: the derivative programs are those of x itself."""
    if jnp.issubdtype(jnp.result_type(x), jnp.inexact):
        return _value_only(x)
    return in_place(x)


def _reread(x):
    """x itself, read back through a row gather: the transpose (in a backward pass) is a
    scatter-add, whose result XLA always materializes."""
    n = x.shape[0]
    return x.at[jnp.arange(n)].get(unique_indices=True, indices_are_sorted=True)


@jax.custom_jvp
def materialize_grad(x):
    """x itself; its tangent is computed once into a buffer (`materialize`), and so, transposed,
    is its cotangent in the backward pass (the tangent is re-read through a row gather, whose
    transpose is a materializing scatter-add: the transpose of `materialize` alone is a gather,
    which XLA fuses into the consumers and so recomputes): XLA's CPU fusion otherwise recomputes
    a cheap-looking backward chain inside every consumer of the cotangent (e.g. per channel of a
    stacked per-pixel array). A custom JVP (not a custom VJP), so forward mode (jacfwd: the LM
    engine, the identifiability analysis) works through it."""
    return x


@materialize_grad.defjvp
def _materialize_grad_jvp(primals, tangents):
    (x,), (t,) = primals, tangents
    return x, _reread(_scatter_copy(t))


#: odd polynomial of atan on [0, 1] in a^2 (|error| < 3e-7 rad; a least-squares fit on Chebyshev
#: nodes), constrained to sum to pi/4 so that the octant reflections of `fast_atan2` meet exactly
ATAN_POLY = (
    0.99999646824181809,
    -0.3331770257354103,
    0.19807482972860063,
    -0.13224887697156121,
    0.079385794980053714,
    -0.033347844419200065,
    0.0067148175731474025,
)


def fast_atan2(y, x):
    """atan2(y, x) from a polynomial, |error| < 3e-7 rad. XLA's CPU atan2 and acos are scalar
    library calls (about 35 and 70 ns an element against under 1 ns for a multiply-add), so
    per-pixel code uses this. Continuous, with a continuous derivative, wherever atan2 is (the
    octants meet exactly); 0 with gradient 0 at the origin.

    Shapes: y (...), x (...) -> (...) elementwise, radians.
    """
    ax, ay = jnp.abs(x), jnp.abs(y)
    hi, lo = jnp.maximum(ax, ay), jnp.minimum(ax, ay)
    ok = hi > 0
    a = jnp.where(ok, lo, 0.0) / jnp.where(ok, hi, 1.0)
    s = a * a
    p = jnp.asarray(ATAN_POLY[-1], s.dtype)
    for c in ATAN_POLY[-2::-1]:
        p = p * s + c
    r = a * p
    r = jnp.where(ay > ax, 0.5 * np.pi - r, r)
    r = jnp.where(x < 0, np.pi - r, r)
    return jnp.where(y < 0, -r, r)


def fast_acos(c):
    """arccos(c) for c in [-1, 1] (clipped) via `fast_atan2`; gradient finite at +-1.

    Shapes: c (...) -> (...) elementwise, radians.
    """
    c = jnp.clip(c, -1.0, 1.0)
    return fast_atan2(safe_sqrt(1.0 - c * c), c)
