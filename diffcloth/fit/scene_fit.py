"""Scene-level fitting: named scene parameters -> rendered video -> image loss -> optax.

    result = dc.fit.fit(scene, targets, free=["stretch", "bend"], steps=100)

Where the stages meet: this module calls `diffcloth.pipeline`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth.fit.constraints import Bounded, Identity, Positive
from diffcloth.fit.identifiability import identifiability
from diffcloth.fit.loop import fit_multistart, fit_params
from diffcloth.fit.losses import image_loss, pyramid_loss, validate_targets

__all__ = [
    "LOSSES",
    "default_constraint",
    "fit",
    "make_targets",
    "scene_identifiability",
    "video_loss",
]

LOSSES = ("l2", "l1", "pyramid")

_UNIT_INTERVAL = ("sphere_reflectivity", "refraction_blend")
_COLOURS = ("ambient", "diffuse", "specular", "reflectance", "sphere_color")


def default_constraint(name: str):
    """Log space for positive physical quantities, (0, 1) for colours and blends, none for wind."""
    if name in ("wind", "body_velocity", "body_position"):
        return Identity()
    if name == "body_restitution":
        return Bounded(0.0, 1.0)
    if name in _COLOURS or name in _UNIT_INTERVAL:
        return Bounded(0.0, 1.0)
    if name == "bump_strength":
        return Bounded(0.0, 10.0)
    if name in ("light_direction", "point_light_position"):
        return Identity()
    if name in ("camera_rotation", "camera_translation", "background"):
        from diffcloth.pipeline import NUISANCE_RANGES

        return Bounded(*NUISANCE_RANGES[name])
    return Positive()


def video_loss(video: jax.Array, targets: jax.Array, kind: str = "l2", mask=None) -> jax.Array:
    """Mean image loss over cameras and frames. video, targets: (cams, T, H, W, C)."""
    if kind not in LOSSES:
        raise ValueError(f"loss must be one of {LOSSES}, got {kind!r}")
    flat_v = video.reshape((-1,) + video.shape[-3:])
    flat_t = targets.reshape((-1,) + targets.shape[-3:])
    if kind == "pyramid":
        per_image = jax.vmap(lambda a, b: pyramid_loss(a, b, mask=mask))(flat_v, flat_t)
    else:
        per_image = jax.vmap(lambda a, b: image_loss(a, b, kind=kind, mask=mask))(flat_v, flat_t)
    return jnp.mean(per_image)


def make_targets(scene, truth: Mapping[str, Any], *, noise: float = 0.0, seed: int = 0):
    """Synthetic target video of `scene` with the `truth` parameters, plus Gaussian image noise of
    standard deviation `noise` (fraction of full scale)."""
    from diffcloth import pipeline

    pipeline.check_param_names(truth)
    video = jax.jit(pipeline.simulate_and_render)(scene, dict(truth))
    if noise > 0:
        key = jax.random.PRNGKey(seed)
        video = video + noise * jax.random.normal(key, video.shape, video.dtype)
    return video


def _loss_fn(kind: str):
    from diffcloth import pipeline

    return _LOSS_FNS.setdefault(
        kind,
        lambda params, targets, scene: video_loss(
            pipeline.simulate_and_render(scene, params), targets, kind
        ),
    )


_LOSS_FNS: dict[str, Any] = {}


def fit(
    scene,
    targets,
    free: Sequence[str],
    steps: int = 100,
    optimizer=None,
    *,
    init: Mapping[str, Any] | None = None,
    constraints: Mapping[str, Any] | None = None,
    loss: str = "l2",
    learning_rate: float | None = None,
    multistart: int = 1,
    spread: float = 0.5,
    seed: int = 0,
    devices: int | None = None,
    **fit_kwargs,
):
    """Fit the named scene parameters to target videos.

    Args:
      scene: a `diffcloth.Scene`.
      targets: (cameras, T, H, W, C) video, or (T, H, W, C) for a single camera; float in [0, 1]
        or uint8 (divided by 255). Checked against `scene.video_shape` before any compilation.
      free: names of the parameters to fit (see `diffcloth.pipeline.PARAMETERS`).
      steps: maximum optimizer steps.  optimizer: an optax transformation (default Adam + clipping).
      init: initial physical values (default: the scene's own values).
      constraints: name -> constraint (default `default_constraint(name)`).
      loss: "l2", "l1" or "pyramid" (multi-scale, wider basin of convergence).
      multistart: number of initial guesses fitted at once with `vmap`; guesses beyond the first are
        the initial values times exp(spread * N(0, 1)) for positive parameters; the best is kept.
      devices: spread the multistart guesses over this many devices (`jax.sharding`); multistart
        must be a multiple of it. None or 1: one device.
      fit_kwargs: passed to `diffcloth.fit.fit_params` (tol, patience, progress, callback,
        checkpoint_path, ...).
    Returns:
      FitResult (or MultiStartResult when multistart > 1).
    Raises:
      ValueError: unknown parameter names, a bad loss kind, or targets of the wrong shape.
    """
    from diffcloth import pipeline

    if devices is not None and (
        isinstance(devices, bool) or not isinstance(devices, int) or devices < 1
    ):
        raise ValueError(f"devices must be an integer >= 1, got {devices!r}")
    if devices is not None and devices > 1 and multistart % devices:
        raise ValueError(
            f"devices = {devices} spreads the multistart guesses over devices, so multistart must "
            f"be a multiple of it (got multistart = {multistart}); a single fit runs on one device"
        )
    free = list(free)
    if not free:
        raise ValueError("free must name at least one parameter to fit")
    pipeline.check_param_names(free)
    if "bump_strength" in free:  # warns when the bump map is filtered away at this resolution
        from diffcloth.render.detail import check_bump_detail

        check_bump_detail(scene, free)
    if loss not in LOSSES:
        raise ValueError(f"loss must be one of {LOSSES}, got {loss!r}")
    targets = np.asarray(targets)
    if targets.ndim == 4 and len(scene.cameras) == 1:
        targets = targets[None]
    targets = validate_targets(targets, scene.video_shape, name="targets")
    targets = jnp.asarray(targets, scene.material.density.dtype)
    init = {
        n: np.asarray(init[n] if init and n in init else pipeline.param_value(scene, n))
        for n in free
    }
    cons = {n: (constraints or {}).get(n, default_constraint(n)) for n in free}
    loss_fn = _loss_fn(loss)
    common = dict(
        steps=steps,
        optimizer=optimizer,
        learning_rate=learning_rate,
        loss_args=(targets, scene),
        **fit_kwargs,
    )
    if multistart <= 1:
        return fit_params(loss_fn, init, cons, **common)
    rng = np.random.default_rng(seed)
    inits = [init]
    for _ in range(multistart - 1):
        guess = {}
        for n, v in init.items():
            if isinstance(cons[n], Positive):
                guess[n] = v * np.exp(spread * rng.standard_normal(np.shape(v)))
            else:
                guess[n] = v + spread * 0.1 * rng.standard_normal(np.shape(v))
        inits.append(guess)
    return fit_multistart(
        loss_fn, inits, cons, devices=devices if devices and devices > 1 else None, **common
    )


def scene_identifiability(
    scene, targets, params: Mapping[str, Any], *, noise_sigma: float = 0.01, **kwargs
):
    """Gauss-Newton identifiability of `params` (name -> fitted value) from the image residuals
    (rendered - target), with pixel noise `noise_sigma`. See `diffcloth.fit.identifiability`."""
    from diffcloth import pipeline

    targets = jnp.asarray(targets)

    def residual(p):
        return (pipeline.simulate_and_render(scene, p) - targets).ravel()

    return identifiability(residual, dict(params), noise_sigma=noise_sigma, **kwargs)
