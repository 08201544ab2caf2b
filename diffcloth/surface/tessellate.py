"""Tessellate a control net into a smooth triangle mesh with analytic frames.

The map from control points to vertices is linear: per direction a basis matrix (samples x
control points) and its derivative matrix are computed once in numpy (cached per net size, level
and basis) and applied with einsum, so tessellation is a few small matrix products and
differentiable in the control points.

Sampling: along each direction the whole parameter range is sampled uniformly with
``num_patches * level`` samples, both ends included, giving one connected vertex grid (no
duplicated seam vertices, no cracks). The seed's 13 x 10 net (10 rows x 13 cols) at level 13 gives
130 x 91 = 11,830 vertices. Samples are therefore ``level`` per patch on average, not aligned to
the patch seams.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth._math import dtype_eps
from diffcloth.surface import basis as _basis

__all__ = [
    "Surface",
    "tessellate",
    "frames_from_derivatives",
    "orthonormal_tangent",
    "grid_frames",
    "grid_faces",
    "grid_uv",
    "vertex_grid_shape",
]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Surface:
    """A tessellated surface: a (vrows, vcols) vertex grid flattened row-major.

    Attributes:
      positions: (n, 3) vertex positions in m, n = vrows * vcols; vertex (i, j) is row i (along v),
        column j (along u), index i * vcols + j.
      normals: (n, 3) unit normals, normalize(dP/du x dP/dv).
      tangents: (n, 3) unit tangents along +u (dP/du, made orthogonal to the normal).
      bitangents: (n, 3) unit bitangents, normal x tangent (so tangent, bitangent, normal is a
        right-handed orthonormal frame; the bitangent points along +v up to shear).
      uv: (n, 2) texture coordinates in [0, 1] over the whole surface: u along columns, v along
        rows.
      faces: (m, 3) int32 triangle vertex indices, m = 2 (vrows - 1)(vcols - 1), counter-clockwise
        seen from the side the normals point to.
      grid_shape: static (vrows, vcols).
      flipped: static; True if the normals were reversed (normal along dP/dv x dP/du) by
        `tessellate(..., flip=True)`; frames recomputed later (`grid_frames`) keep this side.
    """

    positions: jax.Array
    normals: jax.Array
    tangents: jax.Array
    bitangents: jax.Array
    uv: jax.Array
    faces: jax.Array
    grid_shape: tuple[int, int] = dataclasses.field(metadata={"static": True})
    flipped: bool = dataclasses.field(default=False, metadata={"static": True})


def _check_level(level) -> int:
    if isinstance(level, bool) or not isinstance(level, (int, np.integer)):
        raise ValueError(f"level must be an int >= 2 (samples per patch edge), got {level!r}")
    if level < 2:
        raise ValueError(
            f"level = {level} is too small: the tessellation level (samples per patch edge) must "
            f"be >= 2 (required minimum 2)"
        )
    return int(level)


def vertex_grid_shape(net_shape, level: int, basis: str = "bspline") -> tuple[int, int]:
    """(vrows, vcols) of the vertex grid for a (rows, cols[, 3]) net: (patches * level) each way."""
    level = _check_level(level)
    rows, cols = int(net_shape[0]), int(net_shape[1])
    _basis.check_num_points(rows, basis, "control_points rows")
    _basis.check_num_points(cols, basis, "control_points cols")
    return _basis.num_patches(rows, basis) * level, _basis.num_patches(cols, basis) * level


@functools.lru_cache(maxsize=64)
def grid_faces_np(vrows: int, vcols: int) -> np.ndarray:
    """(2 (vrows - 1) (vcols - 1), 3) int triangle faces of a vrows x vcols vertex grid (numpy)."""
    i, j = np.meshgrid(np.arange(vrows - 1), np.arange(vcols - 1), indexing="ij")
    a = (i * vcols + j).ravel()
    b, c, d = a + 1, a + vcols + 1, a + vcols  # b: +u, c: +u+v, d: +v
    # (a, b, c) and (a, c, d): cross(b - a, c - a) ~ Pu x (Pu + Pv) = Pu x Pv, along the normal.
    f = np.stack([np.stack([a, b, c], -1), np.stack([a, c, d], -1)], 1).reshape(-1, 3)
    f = f.astype(np.int32)
    f.setflags(write=False)
    return f


def grid_faces(grid_shape) -> jax.Array:
    """Triangles (2 (vrows-1)(vcols-1), 3) int32 of a row-major vertex grid, wound so that
    cross(p1 - p0, p2 - p0) points along dP/du x dP/dv."""
    return jnp.asarray(grid_faces_np(int(grid_shape[0]), int(grid_shape[1])))


@functools.lru_cache(maxsize=64)
def _uv_np(vrows: int, vcols: int) -> np.ndarray:
    v, u = np.meshgrid(np.linspace(0, 1, vrows), np.linspace(0, 1, vcols), indexing="ij")
    uv = np.stack([u.ravel(), v.ravel()], -1)
    uv.setflags(write=False)
    return uv


def grid_uv(grid_shape, dtype=None) -> jax.Array:
    """(vrows * vcols, 2) uv in [0, 1]: u along columns, v along rows."""
    uv = _uv_np(int(grid_shape[0]), int(grid_shape[1]))
    return jnp.asarray(uv, dtype=dtype or jnp.zeros(()).dtype)


def _cross(a, b):
    ax, ay, az = a
    bx, by, bz = b
    return (ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx)


def _normalize(v, fallback):
    """Component-wise safe normalisation (per-element double where, as in _math.safe_normalize)."""
    x, y, z = v
    sq = x * x + y * y + z * z
    ok = sq > dtype_eps(sq)
    inv = jax.lax.rsqrt(jnp.where(ok, sq, 1.0))
    return tuple(jnp.where(ok, c * inv, f) for c, f in zip(v, fallback, strict=True))


def _tangent(t_raw, n):
    d = t_raw[0] * n[0] + t_raw[1] * n[1] + t_raw[2] * n[2]
    t_raw = tuple(c - d * nc for c, nc in zip(t_raw, n, strict=True))
    nx, ny, nz = n
    zero = jnp.zeros_like(nx)
    use_x = jnp.abs(nx) < 0.9
    # n x (x or z axis, whichever is less aligned with n): unit-able, orthogonal to n
    axis_cross = (
        jnp.where(use_x, zero, ny),
        jnp.where(use_x, nz, -nx),
        jnp.where(use_x, -ny, zero),
    )
    one, nil = jnp.ones_like(nx), jnp.zeros_like(nx)
    fallback = _normalize(axis_cross, (one, nil, nil))
    return _normalize(t_raw, fallback)


def _frames(du, dv):
    """Frames from component tuples; returns (n, t, b) as component tuples."""
    one, nil = jnp.ones_like(du[0]), jnp.zeros_like(du[0])
    n = _normalize(_cross(du, dv), (nil, one, nil))
    t = _tangent(du, n)
    return n, t, _cross(n, t)


def _split(a):
    return a[..., 0], a[..., 1], a[..., 2]


def _join(c):
    return jnp.stack(c, axis=-1)


def orthonormal_tangent(t_raw: jax.Array, n: jax.Array) -> jax.Array:
    """Unit vector along `t_raw` (..., 3) with its component along the unit normal `n` removed.

    Where that is (near) zero, falls back to n x (x or z axis, whichever is less aligned with n),
    which is unit, orthogonal to n and finite in value and gradient.
    """
    return _join(_tangent(_split(t_raw), _split(n)))


def frames_from_derivatives(du: jax.Array, dv: jax.Array):
    """Orthonormal frames from surface derivatives.

    Args:
      du, dv: (..., 3) dP/du and dP/dv (any positive scale).
    Returns:
      (normals, tangents, bitangents), each (..., 3) unit length. Degenerate input (a zero
      derivative, e.g. coincident or collinear control points) falls back to finite values: the
      normal to +y, the tangent to a fixed axis orthogonal to the normal; gradients stay finite.
    """
    n, t, b = _frames(_split(du), _split(dv))
    return _join(n), _join(t), _join(b)


def _grid_derivatives(grid: jax.Array):
    """Central differences (one-sided at the border) along u (axis 1) and v (axis 0)."""

    def diff(x, axis):
        x = jnp.moveaxis(x, axis, 0)
        if x.shape[0] < 2:
            return jnp.moveaxis(jnp.zeros_like(x), 0, axis)
        d = jnp.concatenate([x[1:2] - x[0:1], x[2:] - x[:-2], x[-1:] - x[-2:-1]], 0)
        return jnp.moveaxis(d, 0, axis)

    return diff(grid, 1), diff(grid, 0)


def grid_frames(positions: jax.Array, grid_shape, *, flip: bool = False):
    """Frames recomputed from the vertex grid itself (for deformed or collided vertices).

    Args:
      positions: (vrows * vcols, 3) in m, row-major grid.
      grid_shape: (vrows, vcols).
      flip: reverse the normals (pass `surface.flipped`).
    Returns:
      (normals, tangents, bitangents), each (n, 3), from central differences of the grid, oriented
      like the analytic frames (normal along dP/du x dP/dv, or the reverse if `flip`).
    """
    vrows, vcols = int(grid_shape[0]), int(grid_shape[1])
    grid = positions.reshape(vrows, vcols, 3)
    du, dv = _grid_derivatives(grid)
    if flip:
        dv = -dv
    n, t, b = frames_from_derivatives(du, dv)
    return n.reshape(-1, 3), t.reshape(-1, 3), b.reshape(-1, 3)


def tessellate(control_points, level: int = 13, basis: str = "bspline", *, flip: bool = False):
    """Evaluate the spline surface of a control net on a uniform vertex grid.

    Args:
      control_points: (rows, cols, 3) control net in m (rows along v, cols along u); differentiable.
        Float dtype is kept (float32 in, float32 out).
      level: samples per patch edge (>= 2); the grid has (patches * level) samples per direction.
      basis: "bspline" (uniform cubic, (rows-3) x (cols-3) patches, does not interpolate the net),
        "bezier" ((3m+1) x (3n+1) net, m x n patches through every third point) or "clamped"
        (open uniform cubic B-spline that reaches the net's border).
      flip: if True, reverse the normals and the triangle winding (tangents stay along +u,
        bitangents stay normal x tangent, so they then point along -v).
    Returns:
      Surface with analytic unit normals, tangents and bitangents from the patch derivatives.
    Raises:
      ValueError: level < 2, a net smaller than the spline order (4 per direction), a Bezier net
        that is not 3m+1, or a wrong shape.

    Example:
      >>> import jax.numpy as jnp
      >>> x, z = jnp.meshgrid(jnp.linspace(0, 1, 13), jnp.linspace(0, 1, 10))
      >>> net = jnp.stack([x, jnp.zeros_like(x), z], -1)          # (10, 13, 3)
      >>> tessellate(net, 13).positions.shape
      (11830, 3)
    """
    _basis.check_basis(basis)
    shape = tuple(np.shape(control_points))
    if len(shape) != 3 or shape[2] != 3:
        raise ValueError(f"control_points must have shape (rows, cols, 3), got {shape}")
    vrows, vcols = vertex_grid_shape(shape, level, basis)
    p = jnp.asarray(control_points)
    if not jnp.issubdtype(p.dtype, jnp.floating):
        p = p.astype(jnp.zeros(()).dtype)
    dtype = p.dtype
    bu, dbu = _basis.sampled_basis(shape[1], int(level), basis)
    bv, dbv = _basis.sampled_basis(shape[0], int(level), basis)
    wu = jnp.asarray(np.stack([bu, dbu]), dtype)  # (2, vcols, cols)
    bv, dbv = jnp.asarray(bv, dtype), jnp.asarray(dbv, dtype)
    # Component-major layout (3, vrows, vcols) so the frame arithmetic vectorises; the outputs
    # are interleaved to (n, 3) once at the end.
    q = jnp.einsum("kjc,rcx->kxrj", wu, p)  # (2, 3, rows, vcols): [P(u), dP/du] per net row
    pos = jnp.einsum("ir,xrj->xij", bv, q[0])
    du = jnp.einsum("ir,xrj->xij", bv, q[1])
    dv = jnp.einsum("ir,xrj->xij", dbv, q[0])
    if flip:
        dv = -dv
    n, t, b = _frames(tuple(du), tuple(dv))
    faces = grid_faces_np(vrows, vcols)
    if flip:
        faces = faces[:, ::-1]
    return Surface(
        positions=_join(tuple(pos)).reshape(-1, 3),
        normals=_join(n).reshape(-1, 3),
        tangents=_join(t).reshape(-1, 3),
        bitangents=_join(b).reshape(-1, 3),
        uv=grid_uv((vrows, vcols), dtype),
        faces=jnp.asarray(np.ascontiguousarray(faces)),
        grid_shape=(vrows, vcols),
        flipped=bool(flip),
    )
