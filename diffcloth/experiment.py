"""Run a fitting experiment from a config: targets -> fit -> result.json, plots, video, report.

Config sections read here (the scene sections are in docs/config.md and diffcloth/scene.py):

    [fit]   free = ["stretch", "bend"]   parameters to fit (diffcloth.pipeline.PARAMETERS)
            steps = 60, learning_rate = 0.05, loss = "l2" | "l1" | "pyramid", patience = 30,
            schedule = "cosine" (Adam's rate decays to 10% over the steps, damping the
            oscillation around the optimum) | "constant",
            noise = 0.0 (std of Gaussian noise added to synthetic targets), seed = 0,
            multistart = 1, devices = 1 (spread the multistart guesses over this many devices;
            multistart must be a multiple; `diffcloth fit --devices N` overrides),
            identifiability = true, noise_sigma = 0.01,
            targets = "folder"   (instead of [truth]: PNGs, one subfolder cam0, cam1, ... per camera
                                  or the PNGs directly for a single camera)
    [fit.initial]  name = value   starting values (default: the scene's own)
    [truth]        name = value   true values, used to render synthetic targets
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from diffcloth import config as cfg

__all__ = ["FitSettings", "parse_fit", "run_fit_config", "video_strip"]

_METHOD_NAMES = {
    "lm": "Levenberg-Marquardt (optimistix, forward-mode Jacobians, coarse-to-fine stages)",
    "adam": "Adam (optax)",
}


@dataclasses.dataclass(frozen=True)
class FitSettings:
    free: tuple[str, ...]
    steps: int = 60
    learning_rate: float = 0.05
    loss: str = "l2"
    patience: int = 30
    schedule: str = "cosine"
    noise: float = 0.0
    seed: int = 0
    multistart: int = 1
    devices: int = 1
    identifiability: bool = True
    noise_sigma: float = 0.01
    targets: str | None = None
    initial: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    truth: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    method: str = "auto"
    ties: Mapping[str, Any] | None = None
    lm_schedule: Any = None


_BODY_RANGES = {  # name -> (lo, hi, allowed range as text); mass excludes 0
    "body_mass": (0.0, np.inf, "(0, inf) kg"),
    "body_restitution": (0.0, 1.0, "[0, 1]"),
    "body_friction": (0.0, np.inf, "[0, inf)"),
}


def _param_value(name: str, value, where: str):
    if isinstance(value, bool) or not isinstance(value, int | float | list):
        raise cfg.ConfigError(f"[{where}] {name} = {value!r} must be a number or a list of numbers")
    arr = np.asarray(value, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        raise cfg.ConfigError(f"[{where}] {name} = {value!r} must be finite")
    return arr


def parse_fit(sections: Mapping[str, Any], base_dir: Path | None = None) -> FitSettings:
    """Validate [fit], [fit.initial] and [truth] (ConfigError names the bad key and range)."""
    from diffcloth import pipeline
    from diffcloth.fit.scene_fit import LOSSES
    from diffcloth.physics.material import MATERIAL_FIELDS, material_range

    t = sections.get("fit")
    if t is None:
        raise cfg.ConfigError(
            'missing [fit] section: name the free parameters, e.g. free = ["stretch"]'
        )
    w = "fit"
    keys = [f.name for f in dataclasses.fields(FitSettings) if f.name != "truth"]
    cfg.check_keys(t, keys, w)
    free = t.get("free")
    if not isinstance(free, list) or not free or not all(isinstance(n, str) for n in free):
        raise cfg.ConfigError("[fit] free must be a non-empty list of parameter names")
    try:
        pipeline.check_param_names(free)
    except ValueError as err:
        raise cfg.ConfigError(f"[fit] free: {err}") from None
    initial = {}
    for name, value in t.get("initial", {}).items():
        if name not in free:
            raise cfg.ConfigError(f"[fit.initial] {name} is not a free parameter; free: {free}")
        initial[name] = _param_value(name, value, "fit.initial")
    truth = {}
    for name, value in sections.get("truth", {}).items():
        try:
            pipeline.check_param_names([name])
        except ValueError as err:
            raise cfg.ConfigError(f"[truth] {err}") from None
        arr = _param_value(name, value, "truth")
        if name in MATERIAL_FIELDS:
            lo, inclusive, unit, _ = MATERIAL_FIELDS[name]
            if not np.all(arr >= lo if inclusive else arr > lo):
                raise cfg.ConfigError(
                    f"[truth] {name} = {value!r} is out of range; allowed {material_range(name)} {unit}"
                )
        if name in _BODY_RANGES:
            lo, hi, text = _BODY_RANGES[name]
            if not np.all((arr > lo if name == "body_mass" else arr >= lo) & (arr <= hi)):
                raise cfg.ConfigError(f"[truth] {name} = {value!r} is out of range; allowed {text}")
        truth[name] = arr
    targets = t.get("targets")
    if targets is None and not truth:
        raise cfg.ConfigError('give target images ([fit] targets = "folder") or a [truth] table')
    if targets is not None:
        if not isinstance(targets, str):
            raise cfg.ConfigError("[fit] targets must be a folder path (string)")
        targets = str((base_dir or Path(".")) / targets)
    multistart = cfg.get_number(t, "multistart", 1, where=w, lo=1, hi=64, integer=True)
    devices = cfg.get_number(t, "devices", 1, where=w, lo=1, hi=4096, integer=True)
    check_devices(devices, multistart, "[fit] devices")
    ident = t.get("identifiability", True)
    if not isinstance(ident, bool):
        raise cfg.ConfigError("[fit] identifiability must be true or false")
    return FitSettings(
        free=tuple(free),
        steps=cfg.get_number(t, "steps", 60, where=w, lo=1, integer=True),
        learning_rate=cfg.get_number(t, "learning_rate", 0.05, where=w, lo=0, lo_inclusive=False),
        loss=cfg.get_choice(t, "loss", "l2", LOSSES, where=w),
        patience=cfg.get_number(t, "patience", 30, where=w, lo=1, integer=True),
        schedule=cfg.get_choice(t, "schedule", "cosine", ("cosine", "constant"), where=w),
        noise=cfg.get_number(t, "noise", 0.0, where=w, lo=0, hi=1),
        seed=cfg.get_number(t, "seed", 0, where=w, integer=True),
        multistart=multistart,
        devices=devices,
        identifiability=ident,
        noise_sigma=cfg.get_number(t, "noise_sigma", 0.01, where=w, lo=0, lo_inclusive=False),
        targets=targets,
        initial=initial,
        truth=truth,
    )


def check_devices(devices: int, multistart: int, where: str = "devices") -> None:
    """ConfigError unless the multistart guesses split evenly over the devices."""
    if devices > 1 and multistart % devices:
        raise cfg.ConfigError(
            f"{where} = {devices} spreads the multistart guesses over devices, so [fit] multistart "
            f"must be a multiple of it (got multistart = {multistart})"
        )


def smoke_config(config: cfg.Config) -> cfg.Config:
    """A much smaller version of a config for smoke runs (CI): few frames, tiny images."""
    sim = dataclasses.replace(config.sim, num_frames=min(config.sim.num_frames, 4))
    sections = dict(config.sections)
    render = dict(sections.get("render", {}))
    render.update(width=24, height=24, level=2, frame_stride=1)
    sections["render"] = render
    return dataclasses.replace(config, sim=sim, sections=sections)


def load_targets(folder: str, num_cameras: int) -> np.ndarray:
    """(cameras, T, H, W, C) from a folder of PNGs (subfolders cam0, cam1, ... for several)."""
    from diffcloth.io import load_image_sequence

    root = Path(folder)
    if not root.is_dir():
        raise cfg.ConfigError(f"[fit] targets = {folder!r} is not a folder")
    if num_cameras == 1 and not (root / "cam0").is_dir():
        return load_image_sequence(root)[None]
    return np.stack([load_image_sequence(root / f"cam{i}") for i in range(num_cameras)])


def video_strip(video: np.ndarray) -> np.ndarray:
    """(cameras, T, H, W, C) -> (T, H, cameras * W, C): the cameras side by side."""
    return np.concatenate(list(np.asarray(video)), axis=2)


def _display(video) -> np.ndarray:
    """Linear RGB -> display (gamma 2.2), clipped to [0, 1]."""
    return np.clip(np.asarray(video), 0.0, 1.0) ** (1.0 / 2.2)


def _method_section(result, settings) -> str:
    """report.md: which method ran, its stages and evaluation count."""
    text = f"{_METHOD_NAMES[result.method]}"
    text += " (chosen by method = \"auto\")" if settings.method == "auto" else ""
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
) -> dict:
    """Load a fit config, make or load the targets, fit, and write the results folder.

    Writes to out_dir: result.json, loss.png, params.png, compare.gif (target | fit | difference,
    cameras side by side), report.md, identifiability.json (when enabled), config.toml (a copy).
    Returns the summary dict written to result.json (plus "out_dir").
    """
    import jax

    from diffcloth import fit as dcfit
    from diffcloth import pipeline, report, scene

    config_path = Path(config_path)
    config = cfg.load_config(config_path)
    settings = parse_fit(config.sections, config_path.parent)
    if smoke:
        config = smoke_config(config)
        settings = dataclasses.replace(settings, steps=2, multistart=min(settings.multistart, 2))
        settings = dataclasses.replace(settings, devices=min(settings.devices, settings.multistart))
    if steps is not None:
        settings = dataclasses.replace(settings, steps=steps)
    if devices is not None:
        check_devices(devices, settings.multistart, "--devices")
        settings = dataclasses.replace(settings, devices=devices)
    sc = scene.build_scene(config)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.toml").write_bytes(config_path.read_bytes())

    t0 = time.perf_counter()
    if settings.targets is not None:
        targets = load_targets(settings.targets, len(sc.cameras))
    else:
        targets = np.asarray(
            dcfit.make_targets(sc, settings.truth, noise=settings.noise, seed=settings.seed)
        )
    from diffcloth.fit.lm import num_scalars
    from diffcloth.fit.scene_fit import choose_method

    free_init = {
        n: settings.initial.get(n, pipeline.param_value(sc, n))
        for n in settings.free
        if n not in (settings.ties or {})
    }
    method = choose_method(settings.method, settings.loss, num_scalars(free_init))
    optimizer = None
    if method == "adam":
        import optax

        rate = settings.learning_rate
        if settings.schedule == "cosine":
            rate = optax.cosine_decay_schedule(rate, settings.steps, alpha=0.1)
        optimizer = optax.chain(optax.clip_by_global_norm(1.0), optax.adam(rate))
    if progress:
        print(
            f"  method: {_METHOD_NAMES[method]}"
            + (" (auto)" if settings.method == "auto" else ""),
            flush=True,
        )
    result = dcfit.fit(
        sc,
        targets,
        settings.free,
        settings.steps,
        optimizer,
        init=settings.initial,
        loss=settings.loss,
        method=method,
        ties=settings.ties,
        schedule=settings.lm_schedule,
        multistart=settings.multistart,
        devices=settings.devices,
        seed=settings.seed,
        patience=settings.patience,
        progress=progress,
    )
    multi = None
    if settings.multistart > 1:
        multi, result = result, result.best
    diagnosis = None
    if result.status == "nonfinite":  # name the stage where the values stopped being finite
        bad = {k: v[-1] for k, v in result.history.params.items()}
        diagnosis = pipeline.diagnose(sc, bad) or (
            "every stage is finite at the last parameters: the loss or its gradient overflowed "
            "(lower the learning rate?)"
        )
    render_fn = jax.jit(pipeline.simulate_and_render)
    fitted_video = np.asarray(render_fn(sc, {k: np.asarray(v) for k, v in result.params.items()}))
    ident = None
    if settings.identifiability:
        ident = dcfit.scene_identifiability(
            sc, targets, result.params, noise_sigma=settings.noise_sigma, ties=settings.ties
        )
    truth = {k: v for k, v in settings.truth.items() if k in settings.free} or None
    sections = dict(extra_sections or {})
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
        f"net {sc.net.rows}x{sc.net.cols}, {sc.num_frames} frames "
        f"({sc.sim.num_substeps} substeps, {sc.sim.integrator}), {len(sc.cameras)} camera(s) "
        f"{sc.image_shape[1]}x{sc.image_shape[0]}, tessellation level {sc.level}, "
        f"shading {sc.shading}, loss {settings.loss}, target noise {settings.noise}; "
        f"total time including compilation {time.perf_counter() - t0:.1f} s."
    )
    report.write_fit_report(
        out,
        result,
        truth=truth,
        initial=result.initial,
        target=_display(video_strip(targets)),
        fitted=_display(video_strip(fitted_video)),
        fps=10.0,
        gain=4.0,
        identifiability=ident,
        extra_sections=sections,
        title=title or f"Fit: {config_path.name}",
    )
    summary = report.fit_summary(result, truth, result.initial)
    summary["out_dir"] = str(out)
    summary["status"] = result.status
    summary["method"] = result.method
    summary["evaluations"] = result.evaluations
    if result.stages is not None:
        summary["stages"] = result.stages
    if settings.ties:
        summary["ties"] = {k: str(v) for k, v in settings.ties.items()}
    if diagnosis is not None:
        summary["diagnosis"] = diagnosis
    summary["total_s"] = time.perf_counter() - t0
    return summary
