"""Losses for footage that diffcloth did not render: robust colour + cloth silhouette, as one
residual vector (for Levenberg-Marquardt) or one scalar (for Adam).

    spec = FootageLoss(color="huber", color_scale=0.05, mask="iou", mask_weight=1.0)
    prep = prepare_targets(scene, targets, target_masks, spec)
    r = scene_residuals(params, scene, prep, spec)      # sum(r ** 2) == scene_loss(...)

Colour term: mean over cameras, frames, pixels and channels of rho(rendered - target) (see
`robust.py`; "l2" is the plain mean squared error), times `color_weight`; `color = "none"` fits
the silhouette alone. Mask term: mean over cameras and frames of the mask loss (`masks.py`: "iou",
"distance" or "l2") between the rendered cloth coverage and the target mask, times
`mask_weight`. Optional per-frame weights (T,) (a coarse-to-fine frame window: 1 inside, 0
outside) multiply both terms frame by frame. `color_margin = k` compares colour only on the
target's cloth pixels (mask > 1/2) grown by k px: footage shows what the scene may not model
(a floor, other objects), and those pixels then do not count.

`footage_residual_fn(spec)` is the residual in the front door's layout, so
`dc.fit.fit(scene, video, free, loss=FootageLoss(...), masks=target_masks)` fits it with any
engine, stages, scans and ties (docs/fit.md, "Fitting footage from the command line").

Nuisance parameters of a real capture (exposure, camera pose error, background, lights) are
ordinary named parameters (`diffcloth.pipeline.NUISANCE_PARAMETERS`); fit them next to the
material by naming them in `free`.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth.fit.masks import MASK_LOSSES, distance_transform_residuals, iou_residuals
from diffcloth.fit.robust import ROBUST_KINDS, robust_residuals

__all__ = [
    "COLOR_LOSSES",
    "FootageLoss",
    "FootageTargets",
    "cloth_mask_by_color",
    "color_region",
    "footage_loss_fn",
    "footage_residual_fn",
    "footage_residuals",
    "prepare_targets",
    "scene_loss",
    "scene_residuals",
]

COLOR_LOSSES = ROBUST_KINDS + ("none",)


@dataclasses.dataclass(frozen=True)
class FootageLoss:
    """What to compare (static settings of the loss).

    color: "l2", "huber", "charbonnier", "cauchy" or "none".  color_scale: the robust loss's
    scale s (> 0, fraction of full scale).  color_weight: >= 0.
    mask: None, "iou", "distance" or "l2".  mask_weight: >= 0.
    color_margin: None (colour over every pixel) or k >= 0: colour only where the target mask
      is > 1/2, grown by k px (needs target masks).
    """

    color: str = "l2"
    color_scale: float = 0.05
    color_weight: float = 1.0
    mask: str | None = None
    mask_weight: float = 1.0
    color_margin: int | None = None

    def __post_init__(self):
        if self.color not in COLOR_LOSSES:
            raise ValueError(f"FootageLoss.color={self.color!r} is not one of {COLOR_LOSSES}")
        if self.mask is not None and self.mask not in MASK_LOSSES:
            raise ValueError(f"FootageLoss.mask={self.mask!r} is not None or one of {MASK_LOSSES}")
        for name in ("color_scale", "color_weight", "mask_weight"):
            v = getattr(self, name)
            ok = isinstance(v, int | float) and np.isfinite(v) and v >= 0
            if not ok or (name == "color_scale" and v <= 0):
                rng = "(0, inf)" if name == "color_scale" else "[0, inf)"
                raise ValueError(f"FootageLoss.{name}={v!r} must be a finite number in {rng}")
        if self.color == "none" and self.mask is None:
            raise ValueError("FootageLoss: color='none' needs a mask loss (mask=...)")
        m = self.color_margin
        if m is not None and (isinstance(m, bool) or not isinstance(m, int) or not 0 <= m <= 64):
            raise ValueError(
                f"FootageLoss.color_margin={m!r} must be None or an integer in [0, 64]"
            )


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class FootageTargets:
    """Targets ready for the loss (a pytree: pass it as a jit argument).

    video: (cams, T, H, W, 3) float; mask: (cams, T, H, W) in [0, 1] or None;
    d_out, d_in: (cams, T, H, W) distance transforms of the mask in px (mask = "distance") or None.
    color_w: (cams, T, H, W, 1) 0/1 weights of the colour term (spec.color_margin) or None.
    """

    video: Any
    mask: Any = None
    d_out: Any = None
    d_in: Any = None
    color_w: Any = None


def cloth_mask_by_color(images, color, tolerance: float = 0.1):
    """Binary cloth mask of footage by a colour test (numpy): pixels whose chromaticity
    (rgb / sum) lies within `tolerance` of the cloth colour's, and that are not black.

    images: (..., H, W, 3) linear RGB; color: (3,) the cloth's albedo or a sampled cloth colour.
    Returns (..., H, W) float 0/1. Works under shading changes (shadows scale all channels)."""
    img = np.asarray(images, np.float64)
    c = np.asarray(color, np.float64)
    s = img.sum(axis=-1, keepdims=True)
    chroma = img / np.maximum(s, 1e-12)
    ref = c / max(c.sum(), 1e-12)
    close = np.max(np.abs(chroma - ref), axis=-1) < tolerance
    return (close & (s[..., 0] > 1e-3)).astype(np.float64)


def color_region(masks, margin: int) -> np.ndarray:
    """(..., H, W) 0/1: the target's cloth pixels (mask > 1/2) grown by `margin` px (a square
    neighbourhood, not wrapping at the image border), where the colour term compares."""
    m = np.asarray(masks) > 0.5
    if margin <= 0:
        return m.astype(np.float64)
    h, w = m.shape[-2:]
    pad = [(0, 0)] * (m.ndim - 2) + [(margin, margin), (margin, margin)]
    padded = np.pad(m, pad)
    out = np.zeros_like(m)
    for dy in range(2 * margin + 1):
        for dx in range(2 * margin + 1):
            out |= padded[..., dy : dy + h, dx : dx + w]
    return out.astype(np.float64)


def prepare_targets(
    scene,
    targets,
    target_masks=None,
    spec: FootageLoss = FootageLoss(),
    *,
    dtype=None,
    value_range=(0.0, 1.0),
) -> FootageTargets:
    """Check the target video (cams, T, H, W, 3) against the scene and precompute what the mask
    loss needs (distance transforms, numpy, once). `value_range`: the allowed pixel values
    (`validate_targets`; the front door passes its own, which lets a rendered video's
    highlights above 1 through)."""
    from diffcloth.fit.losses import as_target_array, validate_targets
    from diffcloth.fit.masks import target_distances

    dtype = dtype or scene.material.density.dtype
    video = as_target_array(targets, "targets")
    if video.ndim == 4 and len(scene.cameras) == 1:
        video = video[None]
    video = validate_targets(video, scene.video_shape, name="targets", value_range=value_range)
    mask = d_out = d_in = color_w = None
    if spec.mask is not None or spec.color_margin is not None:
        if target_masks is None:
            what = f"mask={spec.mask!r}" if spec.mask else f"color_margin={spec.color_margin!r}"
            raise ValueError(f"FootageLoss.{what} needs target_masks")
        m = np.asarray(target_masks, np.float64)
        if m.ndim == 3 and len(scene.cameras) == 1:
            m = m[None]
        if m.shape != scene.video_shape[:4]:
            raise ValueError(
                f"target_masks has shape {m.shape}; expected {scene.video_shape[:4]} "
                "(cameras, frames, H, W)"
            )
        if not np.all(np.isfinite(m)) or m.min() < 0 or m.max() > 1:
            raise ValueError("target_masks must be finite values in [0, 1]")
        if spec.mask is not None:
            mask = jnp.asarray(m, dtype)
        if spec.mask == "distance":
            a, b = target_distances(m)
            d_out, d_in = jnp.asarray(a, dtype), jnp.asarray(b, dtype)
        if spec.color_margin is not None:
            color_w = jnp.asarray(color_region(m, spec.color_margin)[..., None], dtype)
    return FootageTargets(jnp.asarray(video, dtype), mask, d_out, d_in, color_w)


def footage_residuals(video, masks, targets: FootageTargets, spec: FootageLoss, frame_weights=None):
    """One residual vector from a rendered video (cams, T, H, W, 3) and cloth masks
    (cams, T, H, W) (None when spec.mask is None): sum of squares = the footage loss."""
    cams, T = video.shape[:2]
    fw = jnp.ones((T,), video.dtype) if frame_weights is None else jnp.asarray(frame_weights)
    parts = []
    if spec.color != "none":
        n = video[0, 0].size * cams * T
        d = video - targets.video
        if targets.color_w is not None:  # colour only on the target's (grown) cloth pixels
            d = d * targets.color_w
        psi = robust_residuals(d, spec.color, spec.color_scale)
        scale = jnp.sqrt(spec.color_weight * fw / n)[None, :, None, None, None]
        parts.append((psi * scale).ravel())
    if spec.mask is not None:
        w = jnp.sqrt(spec.mask_weight * fw / (cams * T))[None, :, None]
        if spec.mask == "iou":
            r = iou_residuals(masks, targets.mask)
        elif spec.mask == "distance":
            r = distance_transform_residuals(masks, targets.d_out, targets.d_in)
        else:
            hw = masks.shape[-1] * masks.shape[-2]
            r = ((masks - targets.mask) / np.sqrt(hw)).reshape(masks.shape[:2] + (hw,))
        parts.append((r * w).ravel())
    return jnp.concatenate(parts)


def scene_residuals(params, scene, targets: FootageTargets, spec: FootageLoss, frame_weights=None):
    """Residuals of the scene rendered with `params` (name -> value) against footage targets;
    a `residual_fn` for least squares (sum of squares = `scene_loss`)."""
    from diffcloth import pipeline

    if spec.mask is None:
        video, masks = pipeline.simulate_and_render(scene, params), None
    else:
        video, masks = pipeline.simulate_and_render(scene, params, with_mask=True)
    return footage_residuals(video, masks, targets, spec, frame_weights)


def scene_loss(params, scene, targets: FootageTargets, spec: FootageLoss, frame_weights=None):
    """sum(scene_residuals(...) ** 2): the scalar footage loss, for Adam (`engines.adam`)."""
    r = scene_residuals(params, scene, targets, spec, frame_weights)
    return jnp.sum(r * r)


_RESIDUAL_FNS: dict[Any, Any] = {}


def footage_residual_fn(spec: FootageLoss, ties=None):
    """residual(params, targets, scene, level_w, frame_w) of the footage loss, in the layout of
    the front door's image residuals (`targets` a `FootageTargets`; `level_w` unused; `frame_w`
    the stage's frame weights summing to 1, scaled here so that all frames give exactly
    `scene_loss`). Cached per (spec, ties): one compiled LM step per free set."""
    from diffcloth import pipeline
    from diffcloth.fit.ties import Ties

    ties = ties or Ties()

    def residual(params, targets, scene, level_w, frame_w):
        p = ties.expand(params)
        if spec.mask is None:
            video, masks = pipeline.simulate_and_render(scene, p), None
        else:
            video, masks = pipeline.simulate_and_render(scene, p, with_mask=True)
        return footage_residuals(video, masks, targets, spec, frame_w * frame_w.shape[0])

    return _RESIDUAL_FNS.setdefault((spec, ties), residual)


def footage_loss_fn(spec: FootageLoss, ties=None):
    """loss(params, targets, scene): the scalar footage loss (`scene_loss`) with ties expanded,
    for Adam; cached per (spec, ties)."""
    from diffcloth.fit.ties import Ties

    ties = ties or Ties()

    def loss(params, targets, scene):
        return scene_loss(ties.expand(params), scene, targets, spec)

    return _LOSS_FNS.setdefault((spec, ties), loss)


_LOSS_FNS: dict[Any, Any] = {}
