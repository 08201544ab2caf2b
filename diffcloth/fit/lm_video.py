"""A scene's video from the Levenberg-Marquardt engine's compiled step, instead of compiling
`simulate_and_render` on its own.

An LM fit compiles one large program, the step (residuals and their Jacobian). A synthetic
target video and the fitted video of the report need the rendered video at given parameters,
which `jax.jit(pipeline.simulate_and_render)` gives at the price of a second large compilation
(about a fifth of the main job's cold run). The step's residuals with the weights of the finest
pyramid level only, every frame at weight 1 and zero targets are the video itself times
sqrt(1 / (cameras x pixels x channels)): `lm_video` evaluates them with the step (no new
compilation when the fit uses the same scene, free names and schedule) and undoes the scale.
The values equal `simulate_and_render`'s up to float rounding (the parameters pass through the
raw space and back, and the scale is undone in float64).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import jax.numpy as jnp
import numpy as np

__all__ = ["lm_video", "lm_video_ok"]


def lm_video_ok(settings, method: str, free: list[str]) -> bool:
    """True when `lm_video` reuses the fit's own step: a single-start LM fit without ties or
    staged free sets (those compile other step programs), of the given free names."""
    from diffcloth.fit.schedule import make_schedule

    if method != "lm" or settings.multistart > 1 or settings.ties:
        return False
    if any(st.staged for st in make_schedule(settings.stages).stages):
        return False
    return len(free) > 0


def lm_video(scene, params: Mapping[str, Any], *, loss: str, stages=None) -> np.ndarray:
    """(cameras, T, H, W, C) linear video of `scene` at the physical `params` (the free names of
    an LM fit with this loss and `stages` schedule, default constraints) from the LM step."""
    from diffcloth.fit.lm_solver import lm_jacobian
    from diffcloth.fit.scene_fit import _lm_stages, _residual_fn, default_constraint
    from diffcloth.fit.ties import Ties

    args, _, levels, _ = _lm_stages(scene, loss, stages)
    lw_fit, fw_fit = args[-1]
    lw = np.zeros(lw_fit.shape, lw_fit.dtype)
    lw[0] = 1.0
    fw = np.ones(fw_fit.shape, fw_fit.dtype)
    shape = scene.video_shape
    dtype = np.dtype(scene.material.density.dtype)
    cons = {n: default_constraint(n) for n in params}
    r, _ = lm_jacobian(
        _residual_fn(levels, Ties()),
        {k: np.asarray(v, dtype) for k, v in params.items()},
        cons,
        loss_args=(jnp.zeros(shape, dtype), scene),
        stage_args=(jnp.asarray(lw), jnp.asarray(fw)),
    )
    count = int(np.prod(shape)) // shape[1]  # cameras x pixels x channels of one frame
    video = np.asarray(r[: int(np.prod(shape))], np.float64) * np.sqrt(count)
    return video.reshape(shape).astype(dtype)
