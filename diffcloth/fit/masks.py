"""Silhouette (cloth-mask) losses: soft IoU and a distance-transform loss, each with a residual
form for least-squares solvers.

Masks are coverage images (..., H, W) in [0, 1]: the rendered one comes from
`render.render(..., return_cloth_mask=True)` (antialiased, so differentiable at the silhouette),
the target one from footage (segmentation, a colour key) and may be binary.

  soft_iou(p, t)        = sum(p t) / sum(p + t - p t)       (equals the IoU on binary masks)
  iou_loss(p, t)        = 1 - soft_iou(p, t)
  distance_transform_loss(p, t, d_out, d_in)
                        = mean(p^2 d_out + (1 - p)^2 d_in)
      d_out: distance (px) from each pixel to the target mask (0 inside it),
      d_in:  distance (px) from each pixel to the target's outside (0 outside it);
      both from `target_distances(t)` (no gradient through them). Cloth drawn far from the
      target costs more than cloth just off its edge, so the gradient reaches a silhouette that
      is several pixels off, where the IoU's gradient is confined to overlapping pixels.

Residual forms (sum of squares = the loss): `iou_residuals` (one residual per mask,
sqrt(1 - IoU), with a zero Jacobian rather than a NaN at a perfect match) and
`distance_transform_residuals` (two per pixel).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth._math import safe_div

__all__ = [
    "MASK_LOSSES",
    "distance_transform_loss",
    "distance_transform_residuals",
    "iou_loss",
    "iou_residuals",
    "mask_loss",
    "mask_residuals",
    "soft_iou",
    "target_distances",
]

MASK_LOSSES = ("iou", "distance", "l2")


def _check_pair(pred, target):
    if pred.shape != target.shape:
        raise ValueError(f"mask shapes differ: pred {pred.shape} != target {target.shape}")
    if pred.ndim < 2:
        raise ValueError(f"masks must be (..., H, W); got shape {pred.shape}")


def soft_iou(pred, target):
    """Soft intersection over union per mask: sum(p t) / sum(p + t - p t) over (H, W).

    Args:
      pred, target: (..., H, W) coverage in [0, 1]; pred differentiable.
    Returns:
      (...) IoU in [0, 1]; 1 where both masks are empty (nothing to disagree on).
    """
    pred = jnp.asarray(pred)
    target = jnp.asarray(target, pred.dtype)
    _check_pair(pred, target)
    inter = jnp.sum(pred * target, axis=(-2, -1))
    union = jnp.sum(pred + target - pred * target, axis=(-2, -1))
    return jnp.where(union > 0, safe_div(inter, union), 1.0)


def iou_loss(pred, target):
    """1 - soft_iou(pred, target), per mask (...)."""
    return 1.0 - soft_iou(pred, target)


@jax.custom_jvp
def _safe_sqrt(x):
    return jnp.sqrt(jnp.maximum(x, 0.0))


@_safe_sqrt.defjvp
def _safe_sqrt_jvp(primals, tangents):
    (x,), (dx,) = primals, tangents
    y = _safe_sqrt(x)
    return y, jnp.where(y > 0, dx / (2.0 * jnp.where(y > 0, y, 1.0)), 0.0)


def iou_residuals(pred, target):
    """(..., 1) residuals sqrt(1 - soft IoU): their squares sum to `iou_loss`. At a perfect match
    the Jacobian is 0 (not NaN); Gauss-Newton then sees a flat residual there, which is where it
    should stop anyway."""
    return _safe_sqrt(iou_loss(pred, target))[..., None]


def target_distances(target, threshold: float = 0.5):
    """Euclidean distance transforms of a target mask, in pixels (numpy, no gradient).

    Args:
      target: (..., H, W) mask; pixels > threshold are inside.
    Returns:
      (d_out, d_in), each (..., H, W) float64: d_out = distance to the nearest inside pixel (0
      inside), d_in = distance to the nearest outside pixel (0 outside). An empty (full) mask gives
      d_out (d_in) = 0 everywhere, so that term is switched off.
    """
    from scipy import ndimage

    t = np.asarray(target) > threshold
    if t.ndim < 2:
        raise ValueError(f"target mask must be (..., H, W); got shape {t.shape}")
    flat = t.reshape((-1,) + t.shape[-2:])
    d_out = np.zeros(flat.shape)
    d_in = np.zeros(flat.shape)
    for i, m in enumerate(flat):  # numpy preprocessing of concrete targets, once per fit
        if m.any():
            d_out[i] = ndimage.distance_transform_edt(~m)
        if (~m).any():
            d_in[i] = ndimage.distance_transform_edt(m)
    return d_out.reshape(t.shape), d_in.reshape(t.shape)


def distance_transform_residuals(pred, d_out, d_in):
    """(..., 2 H W) residuals [p sqrt(d_out), (1 - p) sqrt(d_in)] / sqrt(H W): their squares sum to
    `distance_transform_loss`."""
    pred = jnp.asarray(pred)
    d_out = jnp.asarray(d_out, pred.dtype)
    d_in = jnp.asarray(d_in, pred.dtype)
    _check_pair(pred, d_out)
    _check_pair(pred, d_in)
    n = pred.shape[-2] * pred.shape[-1]
    a = pred * jnp.sqrt(d_out) / np.sqrt(n)
    b = (1.0 - pred) * jnp.sqrt(d_in) / np.sqrt(n)
    flat = pred.shape[:-2] + (n,)
    return jnp.concatenate([a.reshape(flat), b.reshape(flat)], axis=-1)


def distance_transform_loss(pred, d_out, d_in):
    """mean(p^2 d_out + (1 - p)^2 d_in) over (H, W), per mask (...); units: pixels.

    Zero exactly when pred equals the binary target (p = 1 inside, 0 outside)."""
    return jnp.sum(distance_transform_residuals(pred, d_out, d_in) ** 2, axis=-1)


def mask_residuals(pred, target, kind: str = "iou", distances=None):
    """Residuals of a mask loss, (..., R): their squares summed over R give `mask_loss`.

    kind: "iou" (1 residual), "distance" (2 H W; `distances` = target_distances(target), computed
    here when None) or "l2" (H W: (p - t) / sqrt(H W), a per-pixel mean squared error).
    """
    pred = jnp.asarray(pred)
    if kind not in MASK_LOSSES:
        raise ValueError(f"mask loss kind={kind!r} is not one of {MASK_LOSSES}")
    if kind == "iou":
        return iou_residuals(pred, target)
    if kind == "distance":
        d_out, d_in = target_distances(target) if distances is None else distances
        return distance_transform_residuals(pred, d_out, d_in)
    target = jnp.asarray(target, pred.dtype)
    _check_pair(pred, target)
    n = pred.shape[-2] * pred.shape[-1]
    return ((pred - target) / np.sqrt(n)).reshape(pred.shape[:-2] + (n,))


def mask_loss(pred, target, kind: str = "iou", distances=None):
    """Mask loss per mask (...): "iou" (1 - soft IoU), "distance" (distance-transform loss, px) or
    "l2" (mean squared coverage difference)."""
    if kind == "iou":  # the direct form (its sqrt residual is only for least squares)
        return iou_loss(pred, target)
    return jnp.sum(mask_residuals(pred, target, kind, distances) ** 2, axis=-1)
