"""The control net: a regular grid of mass points joined by Provot-style springs.

Node (i, j) is row i, column j. Springs are implicit in the grid, so forces are evaluated as shifted
slices of the (rows, cols, 3) position array (no index lists, no scatter-adds):

    structural  (i, j)-(i, j+1) and (i, j)-(i+1, j)
    shear       (i, j)-(i+1, j+1) and (i, j+1)-(i+1, j)
    bend        (i, j-1)-(i, j)-(i, j+1) and (i-1, j)-(i, j)-(i+1, j)   (skip-one, Provot)

Every spring carries a geometric weight so that a `Material` given per unit (N/m, N m, kg/m^2) acts the
same, up to discretisation error, on a coarse and on a refined net: a structural spring stands for a
strip of cloth as wide as the spacing across it (half that on a boundary), a shear spring for half a
cell, a bend triplet for a strip of bending.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth.representable import check_quantities, net_quantities

PIN_PRESETS = ("none", "all", "top_row", "top_corners", "bottom_row", "left_column")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Net:
    """A grid control net. Arrays are leaves; `rows` and `cols` are static.

    Attributes:
      rest: (rows, cols, 3) rest positions in m.
      area: (rows, cols) lumped area per node in m^2; node mass = material.density * area.
      pinned: (rows, cols) bool, True where the node is pinned (fixed or prescribed).
      rest_h: (rows, cols-1) rest length of horizontal structural springs, m.
      rest_v: (rows-1, cols) rest length of vertical structural springs, m.
      rest_d1: (rows-1, cols-1) rest length of shear springs (i, j)-(i+1, j+1), m.
      rest_d2: (rows-1, cols-1) rest length of shear springs (i, j+1)-(i+1, j), m.
      weight_h, weight_v: structural weights (width / length, dimensionless); k = stretch * weight.
      weight_d: (rows-1, cols-1) shear weight; k = shear * weight_d (each of the two diagonals).
      weight_bh: (rows, cols-2) bend weight, 1/m^2; energy = bend * weight / 2 * |x_a - 2 x_b + x_c|^2.
      weight_bv: (rows-2, cols) bend weight along columns, 1/m^2.
    """

    rest: jax.Array
    area: jax.Array
    pinned: jax.Array
    rest_h: jax.Array
    rest_v: jax.Array
    rest_d1: jax.Array
    rest_d2: jax.Array
    weight_h: jax.Array
    weight_v: jax.Array
    weight_d: jax.Array
    weight_bh: jax.Array
    weight_bv: jax.Array
    rows: int = dataclasses.field(metadata={"static": True})
    cols: int = dataclasses.field(metadata={"static": True})

    @property
    def shape(self) -> tuple[int, int]:
        return (self.rows, self.cols)


def _pin_mask(pinned, rows: int, cols: int) -> np.ndarray:
    """Resolve a pin specification into a (rows, cols) bool mask, with clear errors."""
    if pinned is None:
        return np.zeros((rows, cols), bool)
    if isinstance(pinned, str):
        mask = np.zeros((rows, cols), bool)
        if pinned == "none":
            pass
        elif pinned == "all":
            mask[:] = True
        elif pinned == "top_row":
            mask[0, :] = True
        elif pinned == "bottom_row":
            mask[-1, :] = True
        elif pinned == "top_corners":
            mask[0, 0] = mask[0, -1] = True
        elif pinned == "left_column":
            mask[:, 0] = True
        else:
            raise ValueError(f"pinned: unknown preset {pinned!r}; allowed: {PIN_PRESETS}")
        return mask
    arr = np.asarray(pinned)
    if arr.dtype == bool:
        if arr.shape != (rows, cols):
            raise ValueError(f"pinned: bool mask must have shape ({rows}, {cols}), got {arr.shape}")
        return arr.copy()
    if arr.size == 0:
        return np.zeros((rows, cols), bool)
    if arr.ndim != 2 or arr.shape[1] != 2 or not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(
            "pinned: expected a preset name, a (rows, cols) bool mask or a list of integer "
            f"(row, col) pairs, got {pinned!r}"
        )
    mask = np.zeros((rows, cols), bool)
    for r, c in arr.tolist():
        if not (0 <= r < rows and 0 <= c < cols):
            raise ValueError(
                f"pinned: pin ({r}, {c}) lies outside the net; rows must be in [0, {rows - 1}] "
                f"and cols in [0, {cols - 1}]"
            )
        mask[r, c] = True
    return mask


def _lengths(d: np.ndarray, name: str) -> np.ndarray:
    length = np.linalg.norm(d, axis=-1)
    if np.any(length <= 0):
        idx = np.argwhere(length <= 0)[0].tolist()
        raise ValueError(
            f"rest: {name} spring at {idx} has zero rest length; rest positions of joined nodes "
            "must differ (allowed rest length range (0, inf))"
        )
    return length


def make_net(rest, *, pinned=None, dtype=None) -> Net:
    """Build a Net from arbitrary (rows, cols, 3) rest positions (rows, cols >= 2).

    Lumped areas and spring weights come from the local spacing of the rest grid (exact for a
    regular grid). Raises ValueError for too small a grid, non-finite positions, coincident joined
    nodes (zero rest length) or pins outside the net.

    Args:
      rest: (rows, cols, 3) rest positions in m.
      pinned: None, a preset name (see PIN_PRESETS), a (rows, cols) bool mask, or (row, col) pairs.
      dtype: float dtype of the arrays (default: JAX's default float).
    """
    rest = np.asarray(rest, dtype=np.float64)
    if rest.ndim != 3 or rest.shape[-1] != 3:
        raise ValueError(f"rest: expected shape (rows, cols, 3), got {rest.shape}")
    rows, cols = rest.shape[:2]
    if rows < 2 or cols < 2:
        raise ValueError(
            f"net: rows and cols must be >= 2 (allowed range [2, inf)), got {rows}x{cols}"
        )
    if not np.all(np.isfinite(rest)):
        raise ValueError("rest: positions must be finite, found NaN or inf")
    mask = _pin_mask(pinned, rows, cols)

    rest_h = _lengths(rest[:, 1:] - rest[:, :-1], "horizontal structural")
    rest_v = _lengths(rest[1:] - rest[:-1], "vertical structural")
    rest_d1 = _lengths(rest[1:, 1:] - rest[:-1, :-1], "shear")
    rest_d2 = _lengths(rest[1:, :-1] - rest[:-1, 1:], "shear")

    # Cell sides (rows-1, cols-1): mean widths along and across.
    cell_w = 0.5 * (rest_h[1:] + rest_h[:-1])  # along columns direction (x-like)
    cell_h = 0.5 * (rest_v[:, 1:] + rest_v[:, :-1])  # along rows direction
    cell_area = (
        np.linalg.norm(
            np.cross(rest[1:, 1:] - rest[:-1, :-1], rest[1:, :-1] - rest[:-1, 1:]), axis=-1
        )
        * 0.5
    )
    area = np.zeros((rows, cols))
    area[:-1, :-1] += cell_area / 4
    area[1:, :-1] += cell_area / 4
    area[:-1, 1:] += cell_area / 4
    area[1:, 1:] += cell_area / 4

    # Structural: strip width across the spring (half on boundaries).
    width_h = np.zeros((rows, cols - 1))
    width_h[:-1] += 0.5 * cell_h
    width_h[1:] += 0.5 * cell_h
    width_v = np.zeros((rows - 1, cols))
    width_v[:, :-1] += 0.5 * cell_w
    width_v[:, 1:] += 0.5 * cell_w
    weight_h = width_h / rest_h
    weight_v = width_v / rest_v
    # Shear: each diagonal carries half the cell, k = shear * area / d^2 (mean over diagonals).
    weight_d = cell_area / (rest_d1 * rest_d2)
    # Bend (quadratic, discrete curvature): energy density bend/2 kappa^2, kappa = |second diff| / h^2,
    # over a strip of area width * h  ->  weight = width / h^3.
    hb = 0.5 * (rest_h[:, 1:] + rest_h[:, :-1])
    width_bh = 0.5 * (width_h[:, 1:] + width_h[:, :-1])
    weight_bh = width_bh / hb**3
    vb = 0.5 * (rest_v[1:] + rest_v[:-1])
    width_bv = 0.5 * (width_v[1:] + width_v[:-1])
    weight_bv = width_bv / vb**3

    dtype = dtype or jnp.zeros(()).dtype
    arrays = dict(rest=rest, area=area, rest_h=rest_h, rest_v=rest_v, rest_d1=rest_d1,
                  rest_d2=rest_d2, weight_h=weight_h, weight_v=weight_v, weight_d=weight_d,
                  weight_bh=weight_bh, weight_bv=weight_bv)  # fmt: skip
    # in the run's dtype, before the cast: a net of 1e20 m overflows its areas in float32
    check_quantities("the net's rest positions (size, center)", net_quantities(arrays), dtype)
    a = lambda t: jnp.asarray(t, dtype)
    return Net(
        rest=a(rest),
        area=a(area),
        pinned=jnp.asarray(mask),
        rest_h=a(rest_h),
        rest_v=a(rest_v),
        rest_d1=a(rest_d1),
        rest_d2=a(rest_d2),
        weight_h=a(weight_h),
        weight_v=a(weight_v),
        weight_d=a(weight_d),
        weight_bh=a(weight_bh),
        weight_bv=a(weight_bv),
        rows=rows,
        cols=cols,
    )


def grid_net(
    rows: int,
    cols: int,
    size=(1.2, 0.9),
    *,
    center=(0.0, 0.0, 0.0),
    plane: str = "xz",
    pinned=None,
    dtype=None,
) -> Net:
    """A flat rectangular net of rows x cols nodes.

    Args:
      rows, cols: number of nodes (>= 2 each). The default scene is 10 rows x 13 cols.
      size: (width, height) in m: width along the columns, height along the rows.
      center: (3,) centre of the net in m.
      plane: "xz" (horizontal; columns along +x, rows along +z) or "xy" (vertical, hanging;
        columns along +x, rows downwards along -y, so row 0 is the top).
      pinned: see `make_net`.
      dtype: float dtype (default: JAX's default float).

    >>> net = grid_net(10, 13, (1.2, 0.9), pinned="top_corners")
    >>> net.rest.shape
    (10, 13, 3)
    """
    for name, val in (("rows", rows), ("cols", cols)):
        if isinstance(val, bool) or not isinstance(val, int | np.integer):
            raise TypeError(f"{name}: must be an int, got {val!r}")
        if val < 2:
            raise ValueError(f"{name}: must be >= 2 (allowed range [2, inf)), got {val}")
    width, height = (float(s) for s in size)
    for name, val in (("size[0] (width)", width), ("size[1] (height)", height)):
        if not np.isfinite(val) or val <= 0:
            raise ValueError(f"{name}: must be finite and > 0 (allowed range (0, inf)), got {val}")
    center = np.asarray(center, np.float64)
    if center.shape != (3,) or not np.all(np.isfinite(center)):
        raise ValueError(f"center: must be a finite 3-vector, got {center.tolist()}")
    u = np.linspace(-width / 2, width / 2, cols)
    w = np.linspace(-height / 2, height / 2, rows)
    uu, ww = np.meshgrid(u, w)  # (rows, cols)
    zeros = np.zeros_like(uu)
    if plane == "xz":
        rest = np.stack([uu, zeros, ww], axis=-1)
    elif plane == "xy":
        rest = np.stack([uu, -ww, zeros], axis=-1)
    else:
        raise ValueError(f"plane: must be 'xz' or 'xy', got {plane!r}")
    return make_net(rest + center, pinned=pinned, dtype=dtype)


def spring_list(net: Net) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Explicit spring lists (for reference implementations, exporters and benchmarks).

    Returns:
      pairs: (n, 2) int flat node indices (row * cols + col) of structural and shear springs.
      kind: (n,) int, 0 structural, 1 shear.
      rest_length: (n,) float rest lengths, m.
      weight: (n,) float weights (k = stiffness * weight).
    Bending (triplets) is not listed: see `bend_triplets`.
    """
    R, C = net.rows, net.cols
    idx = np.arange(R * C).reshape(R, C)
    parts = [
        (idx[:, :-1], idx[:, 1:], 0, net.rest_h, net.weight_h),
        (idx[:-1, :], idx[1:, :], 0, net.rest_v, net.weight_v),
        (idx[:-1, :-1], idx[1:, 1:], 1, net.rest_d1, net.weight_d),
        (idx[:-1, 1:], idx[1:, :-1], 1, net.rest_d2, net.weight_d),
    ]
    pairs = np.concatenate([np.stack([a.ravel(), b.ravel()], -1) for a, b, *_ in parts])
    kind = np.concatenate([np.full(a.size, k) for a, _, k, *_ in parts])
    rest = np.concatenate([np.asarray(r).ravel() for *_, r, _ in parts])
    weight = np.concatenate([np.asarray(w).ravel() for *_, w in parts])
    return pairs, kind, rest, weight


def bend_triplets(net: Net) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) flat node indices of bend triplets (a, b, c) and their (n,) weights (1/m^2)."""
    R, C = net.rows, net.cols
    idx = np.arange(R * C).reshape(R, C)
    th = np.stack([idx[:, :-2].ravel(), idx[:, 1:-1].ravel(), idx[:, 2:].ravel()], -1)
    tv = np.stack([idx[:-2].ravel(), idx[1:-1].ravel(), idx[2:].ravel()], -1)
    w = np.concatenate([np.asarray(net.weight_bh).ravel(), np.asarray(net.weight_bv).ravel()])
    return np.concatenate([th, tv]), w
