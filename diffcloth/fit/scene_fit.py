"""Scene-level fitting helpers: the losses and residuals of a scene's video, the engine choice,
the staged schedule, identifiability. The front door `fit` is `diffcloth.fit.front`.

Where the stages meet: this module calls `diffcloth.pipeline`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth.fit.constraints import Bounded, Identity, Positive
from diffcloth.fit.losses import image_loss, pyramid_loss

__all__ = [
    "LOSSES",
    "default_constraint",
    "recipe_stages",
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
    return add_noise(jax.jit(pipeline.simulate_and_render)(scene, dict(truth)), noise, seed)


def add_noise(video, noise: float, seed: int):
    """`video` plus Gaussian noise of standard deviation `noise` (key `PRNGKey(seed)`)."""
    video = jnp.asarray(video)
    if noise > 0:
        key = jax.random.PRNGKey(seed)
        video = video + noise * jax.random.normal(key, video.shape, video.dtype)
    return video


def _loss_fn(kind: str, ties=None):
    from diffcloth import pipeline
    from diffcloth.fit.ties import Ties

    ties = ties or Ties()

    def loss(params, targets, scene):
        return video_loss(pipeline.simulate_and_render(scene, ties.expand(params)), targets, kind)

    return _LOSS_FNS.setdefault((kind, ties), loss)


def _residual_fn(num_levels: int, ties=None):
    """residual(params, targets, scene, level_weights, frame_weights): weighted pyramid residuals
    of the rendered video (`diffcloth.fit.schedule.video_residuals`); cached per (levels, ties)."""
    from diffcloth import pipeline
    from diffcloth.fit.schedule import video_residuals
    from diffcloth.fit.ties import Ties

    ties = ties or Ties()

    def residual(params, targets, scene, level_w, frame_w):
        video = pipeline.simulate_and_render(scene, ties.expand(params))
        return video_residuals(video, targets, level_w, frame_w, num_levels)

    return _RESIDUAL_FNS.setdefault((num_levels, ties), residual)


_LOSS_FNS: dict[Any, Any] = {}
_RESIDUAL_FNS: dict[Any, Any] = {}
LM_LOSSES = ("l2", "pyramid")  # losses that are a sum of squares (what LM can fit)


def choose_method(method: str, loss: str, num_scalars: int, optimizer=None) -> str:
    """The engine: "lm" or "adam" for method "auto" (LM for a least-squares loss, <= 16 scalar
    parameters and no custom optax optimizer; otherwise Adam), "staged" for "staged". Explicit
    "lm" or "staged" with a loss LM cannot fit raises."""
    from diffcloth.fit.settings import LM_MAX_PARAMS, METHODS

    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if method in ("lm", "staged"):
        if loss not in LM_LOSSES:
            raise ValueError(
                f"method {method!r} fits least-squares losses {LM_LOSSES}; loss {loss!r} needs "
                "'adam'"
            )
        return method
    if method == "adam":
        return "adam"
    if loss in LM_LOSSES and num_scalars <= LM_MAX_PARAMS and optimizer is None:
        return "lm"
    return "adam"


def _lm_stages(scene, loss: str, schedule):
    """(stage argument tuples, names, num_levels) of a schedule for this scene's video."""
    from diffcloth.fit.schedule import make_schedule, num_pyramid_levels, stage_weights

    sched = make_schedule(schedule)
    levels = num_pyramid_levels(scene.image_shape, sched.num_levels)
    frames = scene.video_shape[1]
    dtype = np.dtype(scene.material.density.dtype)
    args, names, priors = [], [], []
    for st in list(sched.stages) + [None]:
        priors.append(st is not None and st.frames < 1.0)  # a frame window hides parameters
        lw, fw = stage_weights(loss, levels, frames, st, dtype)
        args.append((jnp.asarray(lw), jnp.asarray(fw)))
        if st is None:
            names.append(f"final ({loss}, all {frames} frames)")
        else:
            nf = int(np.count_nonzero(fw))
            names.append(f"levels>={st.min_level}, frames 1-{nf}")
    return args, names, levels, priors


def recipe_stages(init: Mapping[str, Any], cons: Mapping[str, Any]) -> list[dict]:
    """The staged recipe's stages for these free values (method "staged" without `stages`):
    air resistance alone on the first 35 % of the frames (when there is something else to fit),
    then a scan of the stiffest positive scalar over 1/16..16x and LM over everything on the
    first half; the final stage (all frames) follows."""
    from diffcloth.fit.auto import _FIRST, SCAN_FACTORS, scan_candidates

    dampers = [n for n in init if n in _FIRST]
    stiff = [n for n in scan_candidates(init, cons) if n not in _FIRST]
    stages: list[dict] = []
    if dampers and len(dampers) < len(init):
        stages.append({"frames": 0.35, "free": dampers})
    stage: dict[str, Any] = {"frames": 0.5}
    if stiff:
        stage["scan"] = {stiff[0]: list(SCAN_FACTORS)}
    stages.append(stage)
    return stages


def _fit_staged_schedule(res_fn, init, cons, sched, stage_args, stage_names, loss_args, s):
    """A schedule whose stages change the free set or scan (`diffcloth.fit.staged`): one
    `ParamStage` per schedule stage, then the final stage over every free parameter. Returns the
    final stage's FitResult, with `stages` listing every stage (free set, scan, LM status)."""
    from diffcloth.fit.staged import ParamStage, fit_staged

    free = tuple(init)
    stages = []
    for st, args, name in zip(sched.stages, stage_args, stage_names, strict=False):
        sub = st.free or free
        unknown = [n for n in sub if n not in free]
        if unknown:
            raise ValueError(
                f"stages: free {unknown} of stage '{name}' are not fitted (free, untied: {free})"
            )
        scan = {st.scan[0]: st.scan[1]} if st.scan else None
        largs = None
        if set(sub) < set(free) and st.frames < 1:  # its own step program anyway: a short scene
            args, largs = window_scene(args, loss_args)
        stages.append(ParamStage(sub, stage_args=[args], scan=scan, loss_args=largs, name=name))
    stages.append(ParamStage(free, stage_args=[stage_args[-1]], name=stage_names[-1]))
    out = fit_staged(res_fn, init, cons, stages=stages, loss_args=loss_args, settings=s)
    result = out.results[-1]
    result.evaluations = out.evaluations
    result.wall_s = out.wall_s
    result.stages = [
        {
            "name": row["name"] + ("" if set(row["free"]) == set(free) else
                                   f" (free: {', '.join(row['free'])})")
            + (f", scan {row['scan']['name']} -> {row['scan']['best']:.4g}" if "scan" in row
               else ""),
            "steps": int(r.iterations),
            "loss": row["loss"],
            "status": row["status"],
        }
        for row, r in zip(out.stages, out.results, strict=True)
    ]  # fmt: skip
    return result


def window_scene(stage_args, loss_args):
    """A stage's (level weights, frame weights) and (targets, scene) cut to its frame window:
    the scene simulates only the window's frames (the simulation is causal, so the residuals
    inside the window are the same and nothing outside is simulated). A staged stage whose free
    set is a strict subset (e.g. air damping alone on the free fall) compiles a step of its own
    anyway, so the shorter scene costs no extra compilation.

    Shapes: stage_args (L,), (T,) -> (L,), (n,); targets (cams, T, ...) (an array or a pytree
    of them) -> (cams, n, ...), with n the window's rendered frames."""
    import dataclasses

    lw, fw = stage_args
    n = int(np.count_nonzero(np.asarray(fw)))
    targets, scene = loss_args
    if n >= np.shape(fw)[0]:
        return stage_args, None
    short = dataclasses.replace(scene, num_frames=n * scene.frame_stride)
    cut = jax.tree_util.tree_map(lambda a: a[:, :n], targets)
    return (lw, fw[:n]), (cut, short)


def _add_tied(result, ties) -> None:
    """Put the tied parameters' values into a FitResult (params, initial, history, last_finite)."""
    result.ties = ties
    for attr in ("params", "initial", "last_finite"):
        d = getattr(result, attr)
        setattr(result, attr, {k: np.asarray(v) for k, v in ties.expand(d).items()})
    result.history.params = ties.expand(result.history.params)
    result.history.grad_norm = {
        **result.history.grad_norm,
        **{t: np.full_like(result.history.loss, np.nan) for t in ties.targets},
    }


def scene_identifiability(
    scene,
    targets,
    params: Mapping[str, Any],
    *,
    noise_sigma: float = 0.01,
    ties=None,
    constraints: Mapping[str, Any] | None = None,
    **kwargs,
):
    """Gauss-Newton identifiability of `params` (name -> fitted value) from the image residuals
    (rendered - target, every pixel of every frame and camera), with pixel noise `noise_sigma`.

    The Jacobian comes from the LM engine's compiled forward-mode function (after an LM fit of
    the same scene this compiles nothing new). Tied parameters (in `ties`) are left out: the
    analysis is over the free ones. See `diffcloth.fit.identifiability`.
    """
    from diffcloth.fit.identifiability import identifiability_from_jacobian
    from diffcloth.fit.lm import lm_jacobian
    from diffcloth.fit.schedule import num_pyramid_levels
    from diffcloth.fit.ties import parse_ties

    tie_set = parse_ties(ties)
    free = {k: np.asarray(v) for k, v in params.items() if k not in tie_set.targets}
    cons = {n: (constraints or {}).get(n, default_constraint(n)) for n in free}
    targets = np.asarray(targets)
    if targets.ndim == 4 and len(scene.cameras) == 1:
        targets = targets[None]
    targets = jnp.asarray(targets, scene.material.density.dtype)
    video_shape = targets.shape
    dtype = np.dtype(scene.material.density.dtype)
    # Residual layout of the engine (4 pyramid levels when the image allows): reuse its compiled
    # Jacobian with weights selecting the full-resolution level over every frame.
    levels = num_pyramid_levels(scene.image_shape, 4)
    lw = np.zeros(levels, dtype)
    lw[0] = 1.0
    fw = np.full(video_shape[1], 1.0 / video_shape[1], dtype)
    _, jac_raw = lm_jacobian(
        _residual_fn(levels, tie_set),
        free,
        cons,
        loss_args=(targets, scene),
        stage_args=(jnp.asarray(lw), jnp.asarray(fw)),
    )
    # r = d / sqrt(cams * pixels * T): undo the scale, then chain rule raw -> physical.
    count = video_shape[0] * video_shape[1] * int(np.prod(video_shape[2:]))
    jac_raw = jac_raw[:count] * np.sqrt(count)
    from diffcloth.fit.constraints import to_raw

    raw = to_raw(free, cons)
    dphys = []
    for k in sorted(free):
        g = jax.vmap(jax.grad(lambda z, c=cons[k]: c.forward(z)))(jnp.ravel(raw[k]))
        dphys.append(np.asarray(g, float))
    jac_phys = jac_raw / np.concatenate(dphys)[None, :]
    return identifiability_from_jacobian(jac_phys, free, noise_sigma=noise_sigma, **kwargs)
