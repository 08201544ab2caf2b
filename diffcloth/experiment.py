"""Run a fitting experiment from a config: targets -> fit -> result.json, plots, video, report.

The [fit], [fit.initial] and [truth] sections are parsed by `diffcloth.config.fit` (schema in
docs/config.md); `FitSettings`, `parse_fit` and `check_devices` are re-exported here.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from diffcloth import config as cfg
from diffcloth.config.fit import FitSettings, check_devices, parse_fit
from diffcloth.fit_targets import load_fit_targets, load_targets  # noqa: F401  (re-exported)

__all__ = ["FitSettings", "check_devices", "parse_fit", "run_fit_config", "video_strip"]

_METHOD_NAMES = {
    "lm": "Levenberg-Marquardt (optimistix, forward-mode Jacobians, coarse-to-fine stages)",
    "adam": "Adam (optax)",
    "staged": "staged Levenberg-Marquardt (free sets and scans stage by stage, then all)",
}


def smoke_config(config: cfg.Config) -> cfg.Config:
    """A much smaller version of a config for smoke runs (CI): few frames, tiny images."""
    sim = dataclasses.replace(config.sim, num_frames=min(config.sim.num_frames, 4))
    render = dataclasses.replace(config.render, width=24, height=24, level=2, frame_stride=1)
    return dataclasses.replace(config, sim=sim, render=render)


def video_strip(video: np.ndarray) -> np.ndarray:
    """(cameras, T, H, W, C) -> (T, H, cameras * W, C): the cameras side by side."""
    return np.concatenate(list(np.asarray(video)), axis=2)


@functools.lru_cache(maxsize=16)
def _optimizer(learning_rate: float, schedule: str, steps: int):
    """Adam with clipping (and the cosine schedule); cached, so equal settings in one process
    reuse the compiled fit step (a resumed fit, a rerun)."""
    import optax

    rate = learning_rate
    if schedule == "cosine":
        rate = optax.cosine_decay_schedule(rate, steps, alpha=0.1)
    return optax.chain(optax.clip_by_global_norm(1.0), optax.adam(rate))


def _check_values(sc, values: Mapping, where: str) -> None:
    """[truth]/[fit.initial] values against the scene: shapes and ranges (ConfigError)."""
    from diffcloth import pipeline

    try:
        pipeline.check_param_values(sc, dict(values))
    except ValueError as err:
        raise cfg.ConfigError(f"[{where}] {err}") from None


def _check_stable_values(sc, settings, stability: str) -> None:
    """The stability gate (`scene.check_run_stability`) at the [truth] and [fit.initial] values,
    which may be stiffer or lighter than the scene's own."""
    from diffcloth import pipeline, scene

    for where, values in (("truth", settings.truth), ("fit.initial", settings.initial)):
        if not any(pipeline.PARAMETERS[n][0] in ("material", "sim") for n in values):
            continue
        s = pipeline.apply_params(sc, dict(values))
        scene.check_run_stability(
            s.net,
            s.sim,
            s.material,
            stability=stability,
            label=f"[{where}] {_fmt_params(values)}: ",
        )


def _cloth_text(sc) -> str:
    """ "net 10x13" (grid) or "mesh cloth of 725 vertices (equilibrium)" for reports."""
    from diffcloth.scene import cloth_kind

    if cloth_kind(sc) == "mesh":
        return f"mesh cloth of {sc.net.num_vertices} vertices ({sc.sim.mode})"
    return f"net {sc.net.rows}x{sc.net.cols}"


def _fmt_params(params: Mapping) -> str:
    return ", ".join(f"{k} = {np.asarray(v).tolist()}" for k, v in params.items())


def _status_line(status: str) -> str:
    return {
        "converged": "converged: the loss reached its tolerance",
        "stalled": "stalled: no relative improvement for `patience` steps",
        "max_steps": "max_steps: ran all steps",
        "nonfinite": "nonfinite: stopped on a non-finite loss or gradient",
        "interrupted": "interrupted: stopped by a signal; resume with --resume",
        "stopped": "stopped by a callback",
    }.get(status, status)


def _method_section(result, settings) -> str:
    """report.md: which method ran, its stages and evaluation count."""
    text = f"{_METHOD_NAMES[result.method]}"
    text += ' (chosen by method = "auto")' if settings.method == "auto" else ""
    text += f"; {result.evaluations} loss/Jacobian evaluations." if result.evaluations else "."
    if result.stages:
        text += "\n\n| stage | LM steps | final loss of the stage | status |\n|---|---|---|---|\n"
        text += "\n".join(
            f"| {st['name']} | {st['steps']} | {st['loss']:.4g} | {st['status']} |"
            for st in result.stages
        )
        text += (
            "\n\nStages are coarse to fine (pyramid levels from the coarsest, then a frame window "
            "growing to all frames), each warm-started from the previous one; the losses of "
            "different stages weight the pixels differently and do not compare."
        )
    if getattr(result, "ties", None):
        text += f"\n\nTied parameters (not optimised): {result.ties.describe()}."
    return text


#: the [fit] LM keys' config defaults: only keys set to something else reach the fit, so that
#: method "staged" keeps the recipe's own values (`diffcloth.fit.front.RECIPE_LM`) otherwise
_LM_DEFAULTS = {"lm_xtol": 1e-5, "lm_ftol": 1e-6, "lm_tau": 1e-3, "lm_polish": 10}


def _lm_tolerances(settings) -> dict:
    """The LM tolerances, damping and polish a [fit] section sets (those off their defaults)."""
    return {k: getattr(settings, k) for k, d in _LM_DEFAULTS.items() if getattr(settings, k) != d}


def _footage_section(settings, target_masks, fitted_masks) -> str:
    """report.md: the footage loss's settings and the fitted silhouettes' IoU."""
    spec = settings.footage
    text = (
        f"colour {spec.color} (scale {spec.color_scale:g}, weight {spec.color_weight:g}"
        + (
            f", on the target's cloth pixels grown by {spec.color_margin} px"
            if spec.color_region == "cloth"
            else ", every pixel"
        )
        + f"); silhouette {spec.mask} (weight {spec.mask_weight:g})"
    )
    if target_masks is None:
        return text + "."
    from_file = spec.masks != "color" and Path(settings.targets).suffix == ".npz"
    source = "the target file's masks" if from_file else "a colour key"
    a, b = fitted_masks > 0.5, np.asarray(target_masks) > 0.5
    union = np.logical_or(a, b).sum(axis=(-2, -1))
    iou = np.where(union > 0, np.logical_and(a, b).sum(axis=(-2, -1)) / np.maximum(union, 1), 1.0)
    return (
        text + f"; target masks from {source}. Silhouette IoU of the fit against the target "
        f"(masks > 1/2, every camera and frame): mean {iou.mean():.3f}, min {iou.min():.3f}."
    )


def run_fit_config(
    config_path,
    out_dir,
    *,
    smoke: bool = False,
    steps: int | None = None,
    devices: int | None = None,
    progress: bool = True,
    title: str | None = None,
    extra_sections: Mapping[str, str] | None = None,
    overwrite: bool = False,
    resume: bool = False,
    init_from=None,
    stop=None,
    checkpoint_every: int = 10,
    allow_unstable: bool = False,
) -> dict:
    """Load a fit config, make or load the targets, fit, and write the results folder.

    Every check (config, sizes and memory, targets, the output folder) runs before any work. The
    results are written to a temporary folder next to `out_dir` and moved into place when
    complete (`diffcloth.outdir.OutputDir`): result.json (with "status": converged / stalled /
    max_steps / nonfinite / interrupted), metrics.jsonl, loss.png, params.png, compare.gif (target
    | fit | difference, cameras side by side, sRGB-encoded), report.md, identifiability.json
    (when enabled), config.toml (a copy), checkpoint.npz (+ .json: to resume from).

    Args:
      overwrite: replace a non-empty `out_dir` (as a whole: no stale file survives).
      resume: continue the fit from `out_dir`/checkpoint.npz (written by an earlier run of the
        same config, interrupted or not); the result equals that of an uninterrupted run. A
        checkpoint of another problem (the config's values or the targets changed; see
        `diffcloth.fit.problem`), or a damaged one, is refused, naming the file and what changed.
      init_from: a checkpoint.npz (or its folder) whose best parameters start a new fit.
      stop: an event (`is_set()`) that interrupts the fit after the current step (see
        `diffcloth.fit.interrupt.catch_interrupts`): the checkpoint and a partial report marked
        "interrupted" are written, and the summary's status is "interrupted".
      checkpoint_every: also write the checkpoint every this many steps.
      allow_unstable: only warn when an explicit substep exceeds the stability estimate, for the
        config's own values, [truth] or [fit.initial] (`scene.check_run_stability`); by default
        that is refused (physics.UnstableStepError) before any work, as in simulate and render.
    Returns:
      The summary dict written to result.json (plus "out_dir", "total_s").
    Raises:
      ConfigError, UsageError, MemoryLimitError (a ValueError each) for bad input, before any work.
    """
    from diffcloth import memory, scene
    from diffcloth.fit.problem import (
        check_same_problem,
        fit_inputs,
        initial_from_checkpoint,
        problem_record,
        read_checkpoint,
        stamp_checkpoint,
    )
    from diffcloth.outdir import OutputDir, UsageError

    config_path = Path(config_path)
    config = cfg.load_config(config_path)
    if config.fit is None:
        raise cfg.ConfigError(
            f"{config_path}: missing [fit] section: name the free parameters, "
            'e.g. free = ["stretch"]'
        )
    settings = config.fit
    if settings.x64:
        import jax

        if not jax.config.jax_enable_x64:
            raise cfg.ConfigError(
                f"{config_path}: [fit] x64 = true needs JAX's float64 mode: turn it on before "
                "building anything (jax.config.update('jax_enable_x64', True)); `diffcloth fit` "
                "does that itself"
            )
    if smoke:
        config = smoke_config(config)
        settings = dataclasses.replace(settings, steps=2, multistart=min(settings.multistart, 2))
        settings = dataclasses.replace(settings, devices=min(settings.devices, settings.multistart))
    if steps is not None:
        if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
            raise UsageError(f"--steps must be an integer >= 1, got {steps!r}")
        settings = dataclasses.replace(settings, steps=steps)
    if devices is not None:
        check_devices(devices, settings.multistart, "--devices")
        settings = dataclasses.replace(settings, devices=devices)
    sizes = memory.JobSizes.from_config(config)
    memory.check_memory(
        memory.estimate_memory(sizes, "fit", multistart=settings.multistart),
        f"fitting {config_path.name} ({sizes.num_frames} frames, {sizes.cameras} camera(s) "
        f"{sizes.width}x{sizes.height}, net {sizes.rows}x{sizes.cols}, "
        f"multistart {settings.multistart})",
        hint="lower [render] width/height, [sim] num_frames, the net size or multistart",
    )
    stability = "warn" if allow_unstable else "error"
    sc = scene.build_scene(config, stability=stability)
    if init_from is not None:  # a new fit from an earlier fit's parameters (--init-from)
        if resume:
            raise UsageError("--init-from starts a new fit and --resume continues one: give one")
        try:
            init_from, initial, note = initial_from_checkpoint(init_from, settings, sc)
        except ValueError as err:
            raise UsageError(str(err)) from None
        settings = dataclasses.replace(settings, initial=initial)
        extra_sections = {**(extra_sections or {}), "Initial values": note}
    _check_values(sc, settings.truth, "truth")
    _check_values(sc, settings.initial, "fit.initial")
    _check_stable_values(sc, settings, stability)
    targets = masks = None
    if settings.targets is not None:
        targets, masks = load_fit_targets(settings, sc)
    problem = problem_record(config_path, targets, smoke=smoke)
    out = OutputDir(
        out_dir, overwrite=overwrite, resume=resume, inputs=fit_inputs(config_path, init_from)
    )
    ckpt = None
    if resume:
        path = out.path / "checkpoint.npz"
        if not path.is_file():
            out.discard()
            raise UsageError(
                f"--resume: no checkpoint {str(path)!r}; run without --resume to start afresh"
            )
        try:
            ckpt = read_checkpoint(path)
            check_same_problem(ckpt, path, problem, config_path)
        except ValueError as err:
            out.discard()
            raise UsageError(f"--resume: {err}") from None
    try:
        summary = _run_fit(
            config_path, settings, sc, (targets, masks), out, ckpt, stop, progress, title,
            extra_sections, checkpoint_every,
        )  # fmt: skip
    except BaseException:
        out.discard()
        raise
    stamp_checkpoint(out.tmp / "checkpoint.npz", problem)  # what a --resume must match
    out.commit()
    summary["out_dir"] = str(out.path)
    return summary


def _run_fit(config_path, settings, sc, targets, out, ckpt, stop, progress, title, extra_sections,
             checkpoint_every) -> dict:  # fmt: skip
    import jax

    from diffcloth import fit as dcfit
    from diffcloth import pipeline, report
    from diffcloth.fit.lm import num_scalars
    from diffcloth.fit.lm_video import lm_video, lm_video_ok
    from diffcloth.fit.scene_fit import add_noise, choose_method

    tmp = out.tmp
    (tmp / "config.toml").write_bytes(config_path.read_bytes())
    t0 = time.perf_counter()
    targets, masks = targets
    footage = settings.footage.loss() if settings.footage is not None else None
    loss_kind = "l2" if footage is not None else settings.loss
    free_init = {
        n: settings.initial.get(n, pipeline.param_value(sc, n))
        for n in settings.free
        if n not in (settings.ties or {})
    }
    method = choose_method(settings.method, loss_kind, num_scalars(free_init))
    # a single-start LM fit renders its target and fitted videos with its own compiled step
    # (`diffcloth.fit.lm_video`): one large program to compile instead of two
    reuse = footage is None and lm_video_ok(settings, method, list(free_init))
    if targets is None:
        if reuse and set(settings.truth) == set(free_init):
            video = lm_video(sc, settings.truth, loss=settings.loss, stages=settings.stages)
            targets = np.asarray(add_noise(video, settings.noise, settings.seed))
        else:
            targets = np.asarray(
                dcfit.make_targets(sc, settings.truth, noise=settings.noise, seed=settings.seed)
            )
        if not np.all(np.isfinite(targets)):
            where = pipeline.diagnose(sc, dict(settings.truth)) or "non-finite target video"
            raise cfg.ConfigError(
                f"[truth] {_fmt_params(settings.truth)}: the simulation of the true values is not "
                f"usable ({where}); choose values the scene can simulate, or lower [sim] dt"
            )
    optimizer = None
    if method == "adam":
        optimizer = _optimizer(settings.learning_rate, settings.schedule, settings.steps)
    if progress:
        print(
            f"  method: {_METHOD_NAMES[method]}" + (" (auto)" if settings.method == "auto" else ""),
            flush=True,
        )
    result = dcfit.fit(
        sc,
        targets,
        settings.free,
        settings.steps,
        optimizer,
        init=settings.initial,
        loss=footage or settings.loss,
        masks=masks,
        method=method,
        ties=settings.ties,
        stages=settings.stages,
        multistart=settings.multistart,
        devices=settings.devices,
        seed=settings.seed,
        patience=settings.patience,
        lm_patience=settings.lm_patience,
        lm_stage_steps=settings.lm_stage_steps,
        **_lm_tolerances(settings),
        progress=progress,
        checkpoint_path=tmp / "checkpoint.npz",
        checkpoint_every=checkpoint_every,
        resume=ckpt,
        stop=stop,
    )
    multi = None
    if settings.multistart > 1:
        multi, result = result, result.best
        if "interrupted" in multi.statuses and result.status != "interrupted":
            result = dataclasses.replace(
                result, status="interrupted", message=next(
                    r.message for r in multi.results if r.status == "interrupted")
            )  # fmt: skip
    # the checkpoint ends up in out_dir, not in the temporary folder the messages name
    result = dataclasses.replace(
        result, message=result.message.replace(str(tmp), str(out.path)),
        checkpoint_path=str(out.path / "checkpoint.npz"),
    )  # fmt: skip
    interrupted = result.status == "interrupted"
    diagnosis = None
    if result.status == "nonfinite":  # name the stage where the values stopped being finite
        bad = {k: v[-1] for k, v in result.history.params.items()}
        diagnosis = pipeline.diagnose(sc, bad)
        lr = f"[fit] learning_rate (now {settings.learning_rate:g})"
        if diagnosis is None:
            diagnosis = (
                "every stage is finite at the last parameters: the loss or its gradient "
                f"overflowed; lower {lr}"
            )
        elif pipeline.diagnose(sc, result.initial) is None:
            diagnosis = (
                f"the optimizer stepped to {_fmt_params(bad)}, where the pipeline fails "
                f"({diagnosis.split(' (')[0]}), while the starting values work: lower {lr} or "
                "start closer; lower [sim] dt only if such values are physical"
            )
    fitted_video = None
    ident = None
    if not interrupted:  # a partial report skips the slow parts
        fitted = {k: np.asarray(v) for k, v in result.params.items()}
        if footage is not None:
            fitted_video, fitted_masks = jax.jit(
                functools.partial(pipeline.simulate_and_render, with_mask=True)
            )(sc, fitted)
            fitted_video = np.asarray(fitted_video)
            extra_sections = {
                **(extra_sections or {}),
                "Footage loss": _footage_section(settings, masks, np.asarray(fitted_masks)),
            }
        elif reuse and set(fitted) == set(free_init):
            fitted_video = lm_video(sc, fitted, loss=settings.loss, stages=settings.stages)
        else:
            fitted_video = np.asarray(jax.jit(pipeline.simulate_and_render)(sc, fitted))
        if settings.identifiability and result.status != "nonfinite" and footage is None:
            ident = dcfit.scene_identifiability(
                sc, targets, result.params, noise_sigma=settings.noise_sigma, ties=settings.ties
            )
    truth = {k: v for k, v in settings.truth.items() if k in settings.free} or None
    sections = {}
    if interrupted:
        sections["Interrupted"] = (
            f"This is a partial report: {result.message}. The parameters are the best found so "
            f"far. Continue with `diffcloth fit {config_path} --out {out.path} --resume`; the "
            "resumed fit ends where an uninterrupted one would."
        )
    sections.update(extra_sections or {})
    if multi is not None:
        sections["Multi-start"] = (
            f"{settings.multistart} starts fitted at once with vmap"
            + (f", spread over {settings.devices} devices" if settings.devices > 1 else "")
            + "; final losses "
            + ", ".join(f"{l:.3g}" for l in multi.losses)
            + f"; best start #{multi.best_index}."
        )
    if diagnosis is not None:
        sections["Non-finite stop"] = f"{result.message}. Stage check: {diagnosis}."
    sections["Method"] = _method_section(result, settings)
    sections["Scene"] = (
        f"{_cloth_text(sc)}, {sc.num_frames} frames "
        f"({sc.sim.num_substeps} substeps, {sc.sim.integrator}), {len(sc.cameras)} camera(s) "
        f"{sc.image_shape[1]}x{sc.image_shape[0]}, tessellation level {sc.level}, "
        f"shading {sc.shading}, loss {settings.loss}, target noise {settings.noise}; "
        f"total time including compilation {time.perf_counter() - t0:.1f} s."
    )
    report.write_fit_report(
        tmp,
        result,
        truth=truth,
        initial=result.initial,
        target=None if fitted_video is None else video_strip(targets),  # linear
        fitted=None if fitted_video is None else video_strip(fitted_video),
        fps=10.0,
        gain=4.0,
        identifiability=ident,
        extra_sections=sections,
        title=(title or f"Fit: {config_path.name}") + (" (interrupted)" if interrupted else ""),
        plots=not interrupted or len(result.history) > 1,
    )
    summary = report.fit_summary(result, truth, result.initial)
    summary["method"] = result.method
    summary["evaluations"] = result.evaluations
    if result.stages is not None:
        summary["stages"] = result.stages
    if settings.ties:
        summary["ties"] = {k: str(v) for k, v in settings.ties.items()}
    if diagnosis is not None:
        summary["diagnosis"] = diagnosis
    summary["total_s"] = time.perf_counter() - t0
    from diffcloth.io import save_json

    save_json(tmp / "result.json", summary)
    return summary
