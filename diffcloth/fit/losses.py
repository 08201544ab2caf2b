"""Image losses and target validation.

Images are float (..., H, W, C) in [0, 1]; a video is (T, H, W, C). Elementwise errors
(`squared_error`, `absolute_error`, `charbonnier_error`) return the input shape; `image_loss` and
`pyramid_loss` reduce over (H, W, C) and return one value per image (shape `...`): reduce over
frames and views where you fit.

Every loss is exactly 0 with gradient exactly 0 where rendered == target (no sqrt/abs kink at 0).

Example:
    >>> import jax.numpy as jnp
    >>> a = jnp.zeros((2, 8, 8, 3)); b = jnp.full((2, 8, 8, 3), 0.5)
    >>> image_loss(a, b, kind="l2").tolist()
    [0.25, 0.25]
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np

from diffcloth._math import safe_div

__all__ = [
    "LOSS_KINDS",
    "absolute_error",
    "blur",
    "charbonnier_error",
    "downsample",
    "gaussian_pyramid",
    "image_loss",
    "pyramid_loss",
    "squared_error",
    "validate_targets",
]


def squared_error(pred, target):
    """(pred - target)^2, elementwise."""
    d = pred - target
    return d * d


def absolute_error(pred, target):
    """|pred - target|, elementwise, with gradient 0 (not +-1) where pred == target."""
    d = pred - target
    return jnp.where(d == 0, jnp.zeros_like(d), jnp.abs(d))


def charbonnier_error(pred, target, eps: float = 1e-3):
    """sqrt((pred - target)^2 + eps^2) - eps: a smooth L1; 0 with gradient 0 at equality."""
    d = pred - target
    return jnp.sqrt(d * d + eps * eps) - eps


LOSS_KINDS = {"l2": squared_error, "l1": absolute_error, "charbonnier": charbonnier_error}


def _error_fn(kind: str):
    if kind not in LOSS_KINDS:
        raise ValueError(f"kind={kind!r} is not one of {sorted(LOSS_KINDS)}")
    return LOSS_KINDS[kind]


def _expand_mask(mask, image):
    """Mask (..., H, W), (..., H, W, 1) or image-shaped -> broadcast to the image shape."""
    mask = jnp.asarray(mask, dtype=image.dtype)
    if mask.ndim < image.ndim and mask.shape[-2:] == image.shape[-3:-1]:
        mask = mask[..., None]  # (..., H, W) -> (..., H, W, 1)
    while mask.ndim < image.ndim:
        mask = mask[None]
    try:
        return jnp.broadcast_to(mask, image.shape)
    except ValueError as e:
        raise ValueError(
            f"mask shape {mask.shape} does not broadcast to the image shape {image.shape}"
        ) from e


_INT_SCALE = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}


def _target_as(target, dtype):
    """Target images in the rendered float dtype, with the rule of `validate_targets`: uint8 / 255,
    uint16 / 65535, bool 0/1 (also under jit: the rule depends on the dtype only). Other integer
    dtypes raise instead of being compared as 0..255 values."""
    target = jnp.asarray(target)
    if target.dtype in _INT_SCALE:
        return target.astype(dtype) / _INT_SCALE[target.dtype]
    if not (target.dtype == jnp.bool_ or jnp.issubdtype(target.dtype, jnp.floating)):
        raise ValueError(
            f"target dtype {target.dtype} is not supported; expected float in [0, 1], uint8 "
            "(divided by 255) or uint16 (divided by 65535)"
        )
    return target.astype(dtype)


def image_loss(pred, target, *, kind: str = "l2", mask=None):
    """Mean error per image over (H, W, C); with a mask, the mask-weighted mean.

    Args:
      pred: rendered images (..., H, W, C); differentiable.
      target: target images, same shape; float, or uint8/uint16 (divided by 255/65535).
      kind: "l2" (squared error), "l1" (absolute) or "charbonnier" (smooth L1).
      mask: optional weights (..., H, W), (..., H, W, 1) or image-shaped, >= 0. An all-zero mask
        gives loss 0 (not NaN).
    Returns:
      Loss per image, shape `...` (a scalar for one image).
    """
    pred = jnp.asarray(pred)
    target = _target_as(target, pred.dtype)
    if pred.shape != target.shape:
        raise ValueError(f"pred shape {pred.shape} != target shape {target.shape}")
    if pred.ndim < 3:
        raise ValueError(f"images must be (..., H, W, C); got shape {pred.shape}")
    err = _error_fn(kind)(pred, target)
    axes = (-3, -2, -1)
    if mask is None:
        return jnp.mean(err, axis=axes)
    m = _expand_mask(mask, err)
    return safe_div(jnp.sum(m * err, axis=axes), jnp.sum(m, axis=axes))


_BINOMIAL = np.array([1.0, 4.0, 6.0, 4.0, 1.0]) / 16.0


@functools.lru_cache(maxsize=64)
def _blur_matrix(n: int, stride: int) -> np.ndarray:
    """(ceil(n / stride), n) matrix: 5-tap binomial blur with replicated edges, then decimation."""
    m = np.zeros((n, n))
    for i in range(n):
        for t, w in enumerate(_BINOMIAL):
            m[i, min(max(i + t - 2, 0), n - 1)] += w
    return m[::stride]


def _blur_impl(images, stride: int):
    """Separable blur of (..., H, W, C) as two small matrix products (cheap to compile)."""
    x = jnp.asarray(images)
    h, w = x.shape[-3], x.shape[-2]
    mh = jnp.asarray(_blur_matrix(h, stride), dtype=x.dtype)
    mw = jnp.asarray(_blur_matrix(w, stride), dtype=x.dtype)
    return jnp.einsum("ih,...hwc,jw->...ijc", mh, x, mw)


def blur(images):
    """5 x 5 binomial blur (sigma about 1 px) over H and W of (..., H, W, C); edges replicated."""
    return _blur_impl(images, 1)


def downsample(images):
    """Blur, then keep every second row and column: (..., H, W, C) -> (..., ceil(H/2),
    ceil(W/2), C)."""
    return _blur_impl(images, 2)


def gaussian_pyramid(images, num_levels: int) -> list:
    """[images, downsample(images), ...], `num_levels` entries (stops early below 2 x 2 pixels)."""
    levels = [jnp.asarray(images)]
    while len(levels) < num_levels and min(levels[-1].shape[-3:-1]) >= 4:
        levels.append(downsample(levels[-1]))
    return levels


def pyramid_loss(
    pred,
    target,
    *,
    num_levels: int = 4,
    kind: str = "l2",
    mask=None,
    weights: Sequence[float] | None = None,
):
    """Multi-scale loss: weighted mean of `image_loss` over a Gaussian pyramid of both images.

    Coarse levels compare blurred, downsampled images, so a silhouette that is off by several
    pixels still gets a useful gradient (a wider basin of convergence than the plain pixel loss);
    the finest level keeps the optimum exact.

    Args:
      pred, target: (..., H, W, C) images; pred differentiable.
      num_levels: pyramid levels including the full-resolution one (>= 1).
      kind: per-pixel error, see `image_loss`.
      mask: optional weights as in `image_loss`; it is pyramided with the images.
      weights: per-level weights (default equal); normalised to sum to 1.
    Returns:
      Loss per image, shape `...`.
    """
    if num_levels < 1:
        raise ValueError(f"num_levels={num_levels} must be >= 1")
    pred = jnp.asarray(pred)
    target = _target_as(target, pred.dtype)
    if pred.shape != target.shape:
        raise ValueError(f"pred shape {pred.shape} != target shape {target.shape}")
    # The blur is linear, so the pyramid of the difference equals the difference of the pyramids,
    # and it is exactly 0 where pred == target (however XLA orders the arithmetic).
    pp = gaussian_pyramid(pred - target, num_levels)
    if mask is not None:
        mp = gaussian_pyramid(_expand_mask(mask, pred), num_levels)
    else:
        mp = [None] * len(pp)
    n = len(pp)
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=float)[:n]
    if w.shape != (n,) or not np.all(np.isfinite(w)) or np.any(w < 0) or w.sum() <= 0:
        raise ValueError(f"weights={weights!r} must be {n} finite non-negative numbers, not all 0")
    w = w / w.sum()
    total = 0.0
    for wi, d, m in zip(w, pp, mp, strict=True):
        total = total + float(wi) * image_loss(d, jnp.zeros_like(d), kind=kind, mask=m)
    return total


def _shape_of(x) -> tuple:
    """The shape of a (possibly ragged) nested list, as far as it is regular."""
    if isinstance(x, (list, tuple)):
        return (len(x),)
    return tuple(np.shape(x))


def as_target_array(targets, name: str = "targets") -> np.ndarray:
    """`np.asarray(targets)`, with a ValueError naming `name` and the odd entries when `targets`
    is a ragged list (frames or cameras of different shapes), instead of NumPy's own message."""
    if isinstance(targets, (list, tuple)):

        def ragged(x, where):
            if not isinstance(x, (list, tuple)) or not x:
                return None
            shapes = [np.shape(e) if not isinstance(e, (list, tuple)) else None for e in x]
            if all(s is None for s in shapes):  # nested lists: look one level down
                inner = [_shape_of(e) for e in x]
                if len(set(inner)) > 1:
                    return where, inner
                for i, e in enumerate(x):
                    got = ragged(e, f"{where}[{i}]")
                    if got:
                        return got
                return None
            try:
                shapes = [np.shape(e) for e in x]
            except ValueError:
                shapes = [_shape_of(e) for e in x]
            return (where, shapes) if len(set(shapes)) > 1 else None

        got = ragged(list(targets), name)
        if got:
            where, shapes = got
            common = max(set(shapes), key=shapes.count)
            odd = [f"{where}[{i}] has shape {s}" for i, s in enumerate(shapes) if s != common]
            raise ValueError(
                f"{name} is a ragged list: the entries of {where} differ in shape (most are "
                f"{common}; " + ", ".join(odd[:6]) + (" ..." if len(odd) > 6 else "") + "); "
                "give frames of one size, e.g. a (T, H, W, C) array per camera"
            )
    try:
        arr = np.asarray(targets)
    except ValueError as err:  # ragged in a way the walk above did not name
        raise ValueError(f"{name} cannot be made an array (ragged frames?): {err}") from None
    if arr.dtype == object:
        raise ValueError(f"{name} is a ragged list or holds non-numbers (dtype object)")
    return arr


def validate_targets(
    targets,
    expected_shape: Sequence[int | None],
    *,
    name: str = "targets",
    dtype=None,
    check_range: bool = True,
    value_range: tuple[float | None, float | None] = (0.0, 1.0),
) -> np.ndarray:
    """Check target images against the rendered shape and convert them to float.

    Conversion rule: uint8 -> value / 255; uint16 -> value / 65535; bool -> 0/1; floats are kept
    (cast to `dtype` if given, else float32 unless already float64). Other integer types raise.

    Args:
      targets: array-like of images or video frames (a ragged list is a ValueError naming `name`).
      expected_shape: the shape the renderer produces, e.g. (T, H, W, C); None matches any size.
      name: the argument name used in messages.
      dtype: optional float dtype of the result.
      check_range: check float data against `value_range` (False: any finite value).
      value_range: (low, high) allowed for float data (None: unbounded); default [0, 1], what an
        image holds. `diffcloth.fit.fit` passes (None, 2): a rendered (linear) video exceeds 1 at
        highlights and noisy synthetic targets dip below 0; only 0..255-looking data is refused.
    Returns:
      A float numpy array of the expected shape.
    Raises:
      ValueError: a ragged list; wrong number of axes, frames, size or channels; NaN or inf
        pixels; float data outside `value_range` (data above 2 is named as looking like 0..255).
    """
    arr = as_target_array(targets, name)
    given_float = np.issubdtype(arr.dtype, np.floating)  # integer images are in range by design
    expected = tuple(expected_shape)
    if arr.dtype == np.uint8:
        arr = arr.astype(np.float32) / 255.0
    elif arr.dtype == np.uint16:
        arr = arr.astype(np.float32) / 65535.0
    elif arr.dtype == np.bool_:
        arr = arr.astype(np.float32)
    elif np.issubdtype(arr.dtype, np.floating):
        if arr.dtype not in (np.float32, np.float64):
            arr = arr.astype(np.float32)
    else:
        raise ValueError(
            f"{name} has dtype {arr.dtype}; expected float in [0, 1], uint8 (divided by 255) "
            "or uint16 (divided by 65535)"
        )
    if dtype is not None:
        arr = arr.astype(dtype)

    def shape_str(s):
        return "(" + ", ".join("*" if d is None else str(d) for d in s) + ")"

    given, want = tuple(arr.shape), shape_str(expected)
    if arr.ndim != len(expected):
        raise ValueError(
            f"{name} has shape {given} ({arr.ndim} axes) but the expected shape is {want} "
            f"({len(expected)} axes)"
        )
    bad = [
        i for i, (g, e) in enumerate(zip(given, expected, strict=True)) if e is not None and g != e
    ]
    if bad:
        parts = []
        for i in bad:
            if i == arr.ndim - 1 and arr.ndim >= 3:
                parts.append(f"{given[i]} channels instead of {expected[i]}")
            elif i == 0 and arr.ndim == 4:
                parts.append(f"{given[i]} frames instead of {expected[i]}")
            else:
                parts.append(f"axis {i} has size {given[i]} instead of {expected[i]}")
        raise ValueError(
            f"{name} has shape {given} but the expected shape is {want}: " + "; ".join(parts)
        )
    finite = np.isfinite(arr)
    if not finite.all():
        first = tuple(int(i) for i in np.argwhere(~finite)[0])
        raise ValueError(
            f"{name} (shape {given}) contains {int((~finite).sum())} NaN or inf values "
            f"(first at index {first}); the expected shape is {want} with finite values in [0, 1]"
        )
    lo_ok, hi_ok = value_range if check_range else (None, None)
    if arr.size and given_float:
        lo, hi = float(arr.min()), float(arr.max())
        if hi_ok is not None and hi > 2.0 and hi > hi_ok:
            raise ValueError(
                f"{name} has float values up to {hi:g}; images must be in [0, 1] "
                "(divide 0..255 data by 255, or pass uint8 arrays)"
            )
        if (lo_ok is not None and lo < lo_ok) or (hi_ok is not None and hi > hi_ok):
            bad = (arr < lo_ok) if lo_ok is not None else np.zeros(arr.shape, bool)
            if hi_ok is not None:
                bad |= arr > hi_ok
            first = tuple(int(i) for i in np.argwhere(bad)[0])
            lo_t = "-inf" if lo_ok is None else format(lo_ok, "g")
            allowed = f"[{lo_t}, {'inf' if hi_ok is None else format(hi_ok, 'g')}]"
            raise ValueError(
                f"{name} has float values in [{lo:g}, {hi:g}], {int(bad.sum())} of them outside "
                f"the allowed {allowed} (first at index {first}); clip them (np.clip(x, 0, 1)) "
                "or convert them to linear RGB in [0, 1] first"
            )
    return arr
