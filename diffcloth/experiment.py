"""Run a fitting experiment from a config: targets -> fit -> result.json, plots, video, report.

The [fit], [fit.initial] and [truth] sections are parsed by `diffcloth.config.fit` (schema in
docs/config.md); `FitSettings`, `parse_fit` and `check_devices` are re-exported here.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from diffcloth import config as cfg
from diffcloth.config.fit import FitSettings, check_devices, parse_fit

__all__ = ["FitSettings", "check_devices", "parse_fit", "run_fit_config", "video_strip"]


def smoke_config(config: cfg.Config) -> cfg.Config:
    """A much smaller version of a config for smoke runs (CI): few frames, tiny images."""
    sim = dataclasses.replace(config.sim, num_frames=min(config.sim.num_frames, 4))
    render = dataclasses.replace(config.render, width=24, height=24, level=2, frame_stride=1)
    return dataclasses.replace(config, sim=sim, render=render)


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
    if config.fit is None:
        raise cfg.ConfigError(
            f"{config_path}: missing [fit] section: name the free parameters, "
            'e.g. free = ["stretch"]'
        )
    settings = config.fit
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
    import optax

    rate = settings.learning_rate
    if settings.schedule == "cosine":
        rate = optax.cosine_decay_schedule(rate, settings.steps, alpha=0.1)
    optimizer = optax.chain(optax.clip_by_global_norm(1.0), optax.adam(rate))
    result = dcfit.fit(
        sc,
        targets,
        settings.free,
        settings.steps,
        optimizer,
        init=settings.initial,
        loss=settings.loss,
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
            sc, targets, result.params, noise_sigma=settings.noise_sigma
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
        target=video_strip(targets),  # linear; compare.gif is sRGB-encoded by the report
        fitted=video_strip(fitted_video),
        fps=10.0,
        gain=4.0,
        identifiability=ident,
        extra_sections=sections,
        title=title or f"Fit: {config_path.name}",
    )
    summary = report.fit_summary(result, truth, result.initial)
    summary["out_dir"] = str(out)
    summary["status"] = result.status
    if diagnosis is not None:
        summary["diagnosis"] = diagnosis
    summary["total_s"] = time.perf_counter() - t0
    return summary
