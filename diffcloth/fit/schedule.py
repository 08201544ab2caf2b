"""Coarse-to-fine schedules for least-squares video fits: pyramid levels and a growing frame window.

A video loss turns rugged once contact and folds appear: a small parameter change moves a fold by
a pixel and the pixel loss jumps. The standard cure is to fit coarse first, in space (blurred,
downsampled images, whose loss is smooth over a wider range) and in time (the first frames, before
the cloth meets the collider), then warm-start finer stages from the result.

Here every stage uses the same residual vector layout: the Gaussian pyramid of (rendered - target)
for all levels and frames, each scaled by sqrt(level weight * frame weight / count). A stage only
changes the weights, which are jit arguments, so all stages share one compiled LM step (no
recompilation; frames outside the window are still simulated, they only stop counting).

    Schedule(stages=(Stage(min_level=2, frames=0.5), Stage(min_level=1, frames=1.0)))

The last stage is always the fit's own loss ("l2": the finest level only; "pyramid": every level
equally, as `pyramid_loss`) over all frames, so sum(residual ** 2) equals `video_loss` there.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Any

import jax.numpy as jnp
import numpy as np

from diffcloth.fit.losses import gaussian_pyramid

__all__ = [
    "DEFAULT_SCHEDULE",
    "Schedule",
    "Stage",
    "make_schedule",
    "num_pyramid_levels",
    "stage_weights",
    "video_residuals",
]


@dataclasses.dataclass(frozen=True)
class Stage:
    """One coarse stage: pyramid levels >= min_level (0 = full resolution), equally weighted, over
    the first `frames` fraction of the rendered frames (at least one frame).

    free: the parameters this stage fits (None: all of the fit's); the others are held at their
    current values (`diffcloth.fit.staged`): e.g. air damping alone on the free fall first.
    scan: (name, (factor, ...)): before the stage's LM, the loss is evaluated at the current
    value of `name` times each factor and the stage starts from the best (a global look along
    one parameter; `name` must be free in the stage)."""

    min_level: int = 0
    frames: float = 1.0
    free: tuple[str, ...] | None = None
    scan: tuple[str, tuple[float, ...]] | None = None

    def __post_init__(self):
        if (
            isinstance(self.min_level, bool)
            or not isinstance(self.min_level, int)
            or not (0 <= self.min_level <= 8)
        ):
            raise ValueError(f"Stage: min_level={self.min_level!r} must be an integer in [0, 8]")
        if not (isinstance(self.frames, int | float) and 0 < self.frames <= 1):
            raise ValueError(f"Stage: frames={self.frames!r} must be in (0, 1]")
        if self.free is not None:
            free = (self.free,) if isinstance(self.free, str) else tuple(self.free)
            if not free or not all(isinstance(n, str) for n in free):
                raise ValueError(f"Stage: free={self.free!r} must be a non-empty list of names")
            object.__setattr__(self, "free", free)
        if self.scan is not None:
            if isinstance(self.scan, Mapping):
                if len(self.scan) != 1:
                    raise ValueError(f"Stage: scan={dict(self.scan)!r} must name one parameter")
                scan = next(iter(self.scan.items()))
            else:
                scan = tuple(self.scan)
            name, factors = scan
            f = np.asarray(factors, float) if not isinstance(factors, str) else np.zeros(0)
            if f.ndim != 1 or f.size < 2 or not np.all(np.isfinite(f)) or np.any(f <= 0):
                raise ValueError(
                    f"Stage: scan {name!r} = {factors!r} must be a list of >= 2 positive factors"
                )
            if self.free is not None and name not in self.free:
                raise ValueError(f"Stage: scan {name!r} is not in the stage's free {self.free}")
            object.__setattr__(self, "scan", (str(name), tuple(float(x) for x in f)))

    @property
    def staged(self) -> bool:
        """Whether this stage changes the free set or scans (needs `diffcloth.fit.staged`)."""
        return self.free is not None or self.scan is not None


@dataclasses.dataclass(frozen=True)
class Schedule:
    """Coarse stages run before the final stage (the fit's own loss over all frames).

    num_levels: pyramid levels of the residual vector (4, as `pyramid_loss`)."""

    stages: tuple[Stage, ...] = ()
    num_levels: int = 4

    def __post_init__(self):
        object.__setattr__(self, "stages", tuple(self.stages))
        if not all(isinstance(s, Stage) for s in self.stages):
            raise ValueError("Schedule: stages must be Stage objects")
        if (
            isinstance(self.num_levels, bool)
            or not isinstance(self.num_levels, int)
            or not (1 <= self.num_levels <= 8)
        ):
            raise ValueError(f"Schedule: num_levels={self.num_levels!r} must be in [1, 8]")


DEFAULT_SCHEDULE = Schedule(stages=(Stage(min_level=2, frames=0.5), Stage(min_level=1, frames=1.0)))


#: keys of one stage table in the config ([[fit.stages]])
STAGE_KEYS = ("min_level", "frames", "free", "scan")


def make_schedule(spec: Any) -> Schedule:
    """A Schedule from None (the default), "none" (no coarse stages), a Schedule, or a list of
    {"min_level": int, "frames": float, "free": [names], "scan": {name: [factors]}} tables (the
    config form)."""
    if spec is None:
        return DEFAULT_SCHEDULE
    if isinstance(spec, Schedule):
        return spec
    if isinstance(spec, str):
        if spec.lower() == "none":
            return Schedule(stages=())
        if spec.lower() == "default":
            return DEFAULT_SCHEDULE
        raise ValueError(f"schedule {spec!r} is not 'default', 'none' or a list of stages")
    if isinstance(spec, Sequence):
        stages = []
        for i, item in enumerate(spec):
            if isinstance(item, Stage):
                stages.append(item)
                continue
            if not isinstance(item, Mapping) or set(item) - set(STAGE_KEYS):
                raise ValueError(
                    f"schedule[{i}] = {item!r} must be a table with keys {', '.join(STAGE_KEYS)}"
                )
            try:
                stages.append(
                    Stage(
                        int(item.get("min_level", 0)),
                        float(item.get("frames", 1.0)),
                        free=item.get("free"),
                        scan=item.get("scan"),
                    )
                )
            except (TypeError, ValueError) as err:
                raise ValueError(f"schedule[{i}]: {err}") from None
        return Schedule(stages=tuple(stages))
    raise ValueError(f"schedule {spec!r} is not 'default', 'none' or a list of stages")


def num_pyramid_levels(image_shape: Sequence[int], num_levels: int) -> int:
    """Levels `gaussian_pyramid` makes for (H, W) images (it stops below 4 x 4)."""
    h, w = int(image_shape[0]), int(image_shape[1])
    n = 1
    while n < num_levels and min(h, w) >= 4:
        h, w = math.ceil(h / 2), math.ceil(w / 2)
        n += 1
    return n


def stage_weights(
    loss: str, num_levels: int, num_frames: int, stage: Stage | None, dtype=np.float32
) -> tuple[np.ndarray, np.ndarray]:
    """(level weights (L,) summing to 1, frame weights (T,) summing to 1) of a stage; stage None is
    the final stage of loss "l2" (finest level only) or "pyramid" (every level)."""
    lw = np.zeros(num_levels)
    fw = np.zeros(num_frames)
    if stage is None:
        if loss == "pyramid":
            lw[:] = 1.0
        else:
            lw[0] = 1.0
        fw[:] = 1.0
    else:
        lw[min(stage.min_level, num_levels - 1) :] = 1.0
        fw[: max(1, math.ceil(stage.frames * num_frames - 1e-9))] = 1.0
    return (lw / lw.sum()).astype(dtype), (fw / fw.sum()).astype(dtype)


def video_residuals(video, targets, level_weights, frame_weights, num_levels: int):
    """Weighted pyramid residuals of a video, flattened.

    video, targets: (cameras, T, H, W, C). level_weights: (L,), frame_weights: (T,), each summing
    to 1. Returns a 1-D vector r with
    sum(r ** 2) = sum_l w_l sum_t f_t mean_{cams,pixels}(d_l ** 2):
    with equal level weights and all frames this is exactly `video_loss(video, targets,
    "pyramid")`, with the finest level only it is the "l2" loss.
    """
    d = video - jnp.asarray(targets, video.dtype)
    pyr = gaussian_pyramid(d, num_levels)
    cams = d.shape[0]
    out = []
    for lvl, dl in enumerate(pyr):
        count = cams * dl.shape[-3] * dl.shape[-2] * dl.shape[-1]
        w = jnp.sqrt(level_weights[lvl] * frame_weights / count).astype(dl.dtype)
        out.append((dl * w[None, :, None, None, None]).ravel())
    return jnp.concatenate(out)
