"""Cubic spline bases for control nets: uniform B-spline, Bezier and clamped B-spline.

Everything here is plain numpy, evaluated once per (net size, level, basis) and cached; the JAX
side (`tessellate`) only multiplies the cached matrices with the control points.

All three bases are written as cubic B-splines over one knot vector, so one Cox-de Boor routine
evaluates them (with derivatives) and one parameterisation serves all:

* ``"bspline"``: uniform cubic B-spline, knots ``-3, -2, ..., n``. A net of ``n`` points gives
  ``n - 3`` patches that do not interpolate the net; C2 across patch seams.
* ``"bezier"``: bicubic Bezier, ``n = 3m + 1`` points, every interior knot of multiplicity 3, so
  ``m`` patches that pass through every third point; C0 across seams.
* ``"clamped"``: open uniform cubic B-spline (end knots of multiplicity 4): ``n - 3`` patches, C2
  inside, reaching the first and last control points.

The global parameter ``t`` runs over ``[0, num_patches]``; patch ``k`` covers ``[k, k + 1]``.
Derivatives are with respect to ``t``.
"""

from __future__ import annotations

import functools

import numpy as np

BASES = ("bspline", "bezier", "clamped")
ORDER = 4  # cubic: 4 control points per patch and direction


def check_basis(basis: str) -> None:
    """Raise ValueError unless `basis` is one of BASES.

    Shapes: none (a basis name is checked).
    """
    if basis not in BASES:
        raise ValueError(f"basis must be one of {BASES}, got {basis!r}")


def check_num_points(num_points: int, basis: str, name: str = "num_points") -> None:
    """Raise ValueError unless `num_points` control points make at least one patch of `basis`.

    Shapes: none (integer counts are checked).
    """
    check_basis(basis)
    if num_points < ORDER:
        raise ValueError(
            f"{name} = {num_points} is smaller than the spline order: a cubic {basis} patch needs "
            f"at least {ORDER} control points per direction (required minimum {ORDER})"
        )
    if basis == "bezier" and (num_points - 1) % 3 != 0:
        raise ValueError(
            f"{name} = {num_points}: a bicubic Bezier net needs 3*m + 1 control points per "
            f"direction (4, 7, 10, 13, ...)"
        )


def num_patches(num_points: int, basis: str) -> int:
    """Number of patches along one direction of a net with `num_points` control points.

    Shapes: none (integers).
    """
    check_num_points(num_points, basis)
    return (num_points - 1) // 3 if basis == "bezier" else num_points - 3


def knots(num_points: int, basis: str) -> np.ndarray:
    """Knot vector (num_points + 4,) whose valid parameter range is [0, num_patches]."""
    check_num_points(num_points, basis)
    n = num_points
    if basis == "bspline":
        return np.arange(-3, n + 1, dtype=np.float64)
    if basis == "clamped":
        inner = np.arange(1, n - 3, dtype=np.float64)
        return np.concatenate([np.zeros(4), inner, np.full(4, float(n - 3))])
    m = (n - 1) // 3
    inner = np.repeat(np.arange(1, m, dtype=np.float64), 3)
    return np.concatenate([np.zeros(4), inner, np.full(4, float(m))])


def _span_index(basis: str, patch: np.ndarray) -> np.ndarray:
    """Index s of the knot interval [knots[s], knots[s+1]) that holds patch `patch`."""
    return 3 + 3 * patch if basis == "bezier" else 3 + patch


def _cox_de_boor(kv: np.ndarray, degree: int, t: np.ndarray, span: np.ndarray, deriv: int):
    """Values (or `deriv`-th derivatives) of all B-splines of `degree` over knots `kv` at `t`.

    The degree-0 function of the forced `span` is 1, so a parameter on a knot is evaluated as the
    limit from inside that span (this is how seams get their one-sided limits). Returns
    (len(t), len(kv) - degree - 1).
    """
    count0 = len(kv) - 1
    n = np.zeros((len(t), count0))
    n[np.arange(len(t)), span] = 1.0
    for p in range(1, degree + 1):
        count = len(kv) - p - 1
        i = np.arange(count)
        left = kv[i + p] - kv[i]
        right = kv[i + p + 1] - kv[i + 1]
        inv_l = np.divide(1.0, left, out=np.zeros_like(left), where=left > 0)
        inv_r = np.divide(1.0, right, out=np.zeros_like(right), where=right > 0)
        lo, hi = n[:, :count], n[:, 1 : count + 1]
        if p > degree - deriv:  # differentiate this degree step
            n = p * (lo * inv_l - hi * inv_r)
        else:
            n = (t[:, None] - kv[i]) * inv_l * lo + (kv[i + p + 1] - t[:, None]) * inv_r * hi
    return n


def patch_weights(num_points: int, patch, s, basis: str = "bspline", deriv: int = 0) -> np.ndarray:
    """Weights of every control point at local parameter `s` in [0, 1] of patch `patch`.

    Args:
      num_points: control points along this direction.
      patch: int or (k,) ints, patch index in [0, num_patches).
      s: (k,) local parameters in [0, 1] (s = 1 is the limit from inside the patch).
      basis: "bspline", "bezier" or "clamped".
      deriv: 0 for values, 1, 2, 3 for derivatives with respect to the global parameter t.
    Returns:
      (k, num_points) float64 weights; a point is ``weights @ control_points``.
    """
    s = np.atleast_1d(np.asarray(s, dtype=np.float64))
    patch = np.broadcast_to(np.asarray(patch, dtype=np.int64), s.shape)
    npatch = num_patches(num_points, basis)
    if np.any(patch < 0) or np.any(patch >= npatch):
        raise ValueError(f"patch must be in [0, {npatch}), got {patch.tolist()}")
    kv = knots(num_points, basis)
    return _cox_de_boor(kv, 3, patch + s, _span_index(basis, patch), deriv)


def basis_matrix(num_points: int, t, basis: str = "bspline", deriv: int = 0) -> np.ndarray:
    """Weights (len(t), num_points) at global parameters t in [0, num_patches].

    Shapes: t (k,) -> (k, num_points) numpy.
    """
    t = np.atleast_1d(np.asarray(t, dtype=np.float64))
    npatch = num_patches(num_points, basis)
    patch = np.clip(np.floor(t).astype(np.int64), 0, npatch - 1)
    return patch_weights(num_points, patch, t - patch, basis, deriv)


def sample_parameters(num_points: int, level: int, basis: str = "bspline") -> np.ndarray:
    """The tessellation's parameter samples: num_patches * level values spread uniformly over
    [0, num_patches], both ends included. One connected grid: no duplicated seam vertices.

    Shapes: -> (num_patches * level + 1,) numpy.
    """
    npatch = num_patches(num_points, basis)
    return np.linspace(0.0, float(npatch), npatch * level)


@functools.lru_cache(maxsize=64)
def sampled_basis(num_points: int, level: int, basis: str = "bspline"):
    """Cached (values, first derivatives) at `sample_parameters`, each (patches*level, num_points).

    Derivatives are with respect to the normalised coordinate u = t / num_patches in [0, 1]
    (the surface's uv). Arrays are read-only float64.
    """
    t = sample_parameters(num_points, level, basis)
    npatch = num_patches(num_points, basis)
    b = basis_matrix(num_points, t, basis, 0)
    db = basis_matrix(num_points, t, basis, 1) * npatch
    for a in (b, db):
        a.setflags(write=False)
    return b, db
