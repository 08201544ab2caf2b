"""Fit sections of the schema: [fit], [fit.initial] and [truth] (docs/config.md).

[fit]   free = ["stretch", "bend"]   parameters to fit (diffcloth.pipeline.PARAMETERS)
        steps = 60, learning_rate = 0.05, loss = "l2" | "l1" | "pyramid" | "footage" (the
        footage loss of [fit.footage]: diffcloth.config.footage), patience = 30,
        schedule = "cosine" (Adam's rate decays to 10% over the steps, damping the
        oscillation around the optimum) | "constant",
        noise = 0.0 (std of Gaussian noise added to synthetic targets), seed = 0,
        multistart = 1, devices = 1 (spread the multistart guesses over this many devices;
        multistart must be a multiple; `diffcloth fit --devices N` overrides),
        identifiability = true, noise_sigma = 0.01,
        method = "auto" | "lm" | "adam" | "staged" (auto: Levenberg-Marquardt for l2/pyramid and
        <= 16 scalar parameters, as "lm" from the command line; staged: the footage recipe of
        `dc.fit.fit(method="staged")`), stages = "default" | "none" | [{min_level = 2, frames = 0.5}, ...]
        (a stage may also set free = [subset] and scan = {name = [factors]}: diffcloth.fit.staged)
        (LM coarse-to-fine), lm_patience = 6, lm_xtol = 1e-5, lm_ftol = 1e-6, lm_tau = 1e-3,
        lm_polish = 10 (LM tolerances, initial damping, Gauss-Newton polish steps),
        x64 = false (fit in float64: `diffcloth fit` turns JAX's x64 on, as --x64 does),
        ties = { shear = "stretch", bend = "1e-4 * stretch" }   (tied parameters, not fitted)
        targets = "folder"   (instead of [truth]: PNGs, one subfolder cam0, cam1, ... per camera
                              or the PNGs directly for a single camera; or an .npz file with
                              images (cams, F, H, W, 3) and masks (cams, F, H, W))
        targets_make = "command"   (named in the error when the targets are missing)
        target_downsample = 1      (box-average k x k pixel blocks of the targets)
        target_glob = "*.png", target_cameras = ["cam0", ...], target_frames = [first, stop],
        target_stride = 1, colorspace = "auto" | "srgb" | "linear"   (target layout, see
                              diffcloth.experiment.load_targets)
[fit.initial]  name = value   starting values (default: the scene's own)
[truth]        name = value   true values, used to render synthetic targets
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from diffcloth.config import _fields as cfg


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
    target_glob: str = "*.png"
    target_cameras: tuple[str, ...] | None = None
    target_frames: tuple[int, int] | None = None
    target_stride: int = 1
    colorspace: str = "auto"
    initial: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    truth: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    method: str = "auto"
    ties: Mapping[str, Any] | None = None
    stages: Any = None
    lm_patience: int = 6
    lm_stage_steps: int = 20
    lm_xtol: float = 1e-5
    lm_ftol: float = 1e-6
    lm_tau: float = 1e-3
    lm_polish: int = 10
    x64: bool = False
    footage: Any = None
    target_downsample: int = 1
    targets_make: str | None = None

    def engine(self, **runtime):
        """The loop settings (`diffcloth.fit.settings.FitSettings`) of this [fit] section: the
        fields both share are copied, `runtime` (progress, callback, checkpoint_path, ...) added."""
        from diffcloth.fit.settings import FitSettings as LoopSettings

        shared = {f.name for f in dataclasses.fields(LoopSettings)} & {
            f.name for f in dataclasses.fields(self)
        }
        shared -= {"devices", "x64"}  # devices: 1 here means "one device" (None in the loop)
        values = {k: getattr(self, k) for k in shared}
        values["devices"] = self.devices if self.devices > 1 else None
        values.update(runtime)
        return LoopSettings(**values)


def _parse_engine(t: Mapping[str, Any], free) -> dict:
    """[fit] method, ties, stages, lm_patience (the LM engine's keys)."""
    from diffcloth.fit.schedule import make_schedule
    from diffcloth.fit.settings import METHODS
    from diffcloth.fit.ties import parse_ties

    w = "fit"
    out = {"method": cfg.get_choice(t, "method", "auto", METHODS, where=w)}
    ties = t.get("ties")
    if ties is not None:
        if not isinstance(ties, Mapping) or not ties:
            raise cfg.ConfigError(
                f"[fit] ties = {ties!r} must be a table, e.g. "
                'ties = { shear = "stretch", bend = "1e-4 * stretch" }'
            )
        try:
            parse_ties(ties, free)
        except ValueError as err:
            raise cfg.ConfigError(f"[fit] {err}") from None
        out["ties"] = dict(ties)
    stages = t.get("stages")
    if stages is not None:
        try:
            make_schedule(stages)
        except (ValueError, TypeError) as err:
            raise cfg.ConfigError(
                f'[fit] stages = {stages!r}: {err}; allowed: "default", "none" or a list of '
                "{ min_level = 0..8, frames = (0, 1], free = [names], scan = {name = [factors]} } "
                "tables"
            ) from None
        for i, st in enumerate(make_schedule(stages).stages):
            named = list(st.free or ()) + ([st.scan[0]] if st.scan else [])
            bad = [n for n in named if n not in free]
            if bad:
                raise cfg.ConfigError(
                    f"[fit] stages[{i}]: {bad} not in [fit] free {list(free)} (a stage fits a "
                    "subset of the free parameters)"
                )
        out["stages"] = stages
    out["lm_patience"] = cfg.get_number(t, "lm_patience", 6, where=w, lo=1, hi=1000, integer=True)
    out["lm_stage_steps"] = cfg.get_number(
        t, "lm_stage_steps", 20, where=w, lo=1, hi=1000, integer=True
    )
    # LM tolerances and damping (diffcloth.fit.settings.FitSettings; the cross-engine recipe
    # sets lm_xtol = 1e-3, lm_ftol = 1e-5, lm_tau = 1, lm_polish = 0)
    out["lm_xtol"] = cfg.get_number(t, "lm_xtol", 1e-5, where=w, lo=0, hi=1, lo_inclusive=False)
    out["lm_ftol"] = cfg.get_number(t, "lm_ftol", 1e-6, where=w, lo=0, hi=1, lo_inclusive=False)
    out["lm_tau"] = cfg.get_number(t, "lm_tau", 1e-3, where=w, lo=0, hi=1e6, lo_inclusive=False)
    out["lm_polish"] = cfg.get_number(t, "lm_polish", 10, where=w, lo=0, hi=1000, integer=True)
    out["x64"] = cfg.get_bool(t, "x64", False, where=w)
    return out


def _param_value(name: str, value, where: str):
    if isinstance(value, bool) or not isinstance(value, int | float | list):
        raise cfg.ConfigError(f"[{where}] {name} = {value!r} must be a number or a list of numbers")
    if isinstance(value, list) and not all(
        isinstance(v, int | float) and not isinstance(v, bool) for v in value
    ):
        raise cfg.ConfigError(f"[{where}] {name} = {value!r} must be a number or a list of numbers")
    arr = np.asarray(value, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        raise cfg.ConfigError(f"[{where}] {name} = {value!r} must be finite")
    return arr


def _check_range(name: str, arr, value, where: str) -> None:
    """The parameter's allowed range (diffcloth.pipeline.PARAMETER_RANGES, as `apply_params`)."""
    from diffcloth.pipeline import PARAMETER_RANGES, ParamRange

    rng = PARAMETER_RANGES.get(name, ParamRange())
    if not rng.contains(arr):
        raise cfg.ConfigError(f"[{where}] {name} = {value!r} is out of range; allowed {rng.text()}")


def _check_fittable(name: str, arr, value) -> None:
    """A starting value must lie strictly inside the fitted parameter's constraint (the optimizer
    works on an unconstrained transform of it: log for positive values, logit for (0, 1))."""
    from diffcloth.fit.constraints import Bounded, Positive
    from diffcloth.fit.scene_fit import default_constraint

    con = default_constraint(name)
    if isinstance(con, Positive) and not np.all(arr > 0):
        raise cfg.ConfigError(
            f"[fit.initial] {name} = {value!r} is outside the fitted range (0, inf): {name} is "
            "fitted in log space, so its starting value must be > 0"
        )
    if isinstance(con, Bounded) and not np.all((arr > con.lo) & (arr < con.hi)):
        raise cfg.ConfigError(
            f"[fit.initial] {name} = {value!r} is outside the fitted range ({con.lo:g}, "
            f"{con.hi:g}): {name} is fitted through a logistic transform, so its starting value "
            "must lie strictly inside"
        )


def parse_fit(sections: Mapping[str, Any], base_dir: Path | None = None) -> FitSettings:
    """Validate [fit], [fit.initial] and [truth] (ConfigError names the bad key and range)."""
    from diffcloth import pipeline
    from diffcloth.config.footage import parse_footage
    from diffcloth.fit.scene_fit import LOSSES

    if "truth" in sections and "fit" not in sections:
        raise cfg.ConfigError("[truth] needs a [fit] section naming the free parameters")

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
    init_table = t.get("initial", {})
    if not isinstance(init_table, Mapping):
        raise cfg.ConfigError(
            f"[fit] initial = {init_table!r} must be a table of starting values, e.g. "
            f"[fit.initial] {free[0]} = ..."
        )
    for name, value in init_table.items():
        if name not in free:
            raise cfg.ConfigError(f"[fit.initial] {name} is not a free parameter; free: {free}")
        arr = _param_value(name, value, "fit.initial")
        _check_range(name, arr, value, "fit.initial")
        _check_fittable(name, arr, value)
        initial[name] = arr
    truth = {}
    truth_table = sections.get("truth", {})
    if not isinstance(truth_table, Mapping):
        raise cfg.ConfigError(f"[truth] must be a table of name = value, got {truth_table!r}")
    for name, value in truth_table.items():
        try:
            pipeline.check_param_names([name])
        except ValueError as err:
            raise cfg.ConfigError(f"[truth] {err}") from None
        arr = _param_value(name, value, "truth")
        _check_range(name, arr, value, "truth")
        truth[name] = arr
    targets = t.get("targets")
    if targets is None and not truth:
        raise cfg.ConfigError('give target images ([fit] targets = "folder") or a [truth] table')
    if targets is not None:
        if not isinstance(targets, str) or not targets.strip():
            raise cfg.ConfigError(
                "[fit] targets must be a folder of images or an .npz file (a path string)"
            )
        targets = str((base_dir or Path(".")) / targets)
    make = t.get("targets_make")
    if make is not None and (not isinstance(make, str) or not make.strip()):
        raise cfg.ConfigError(
            f"[fit] targets_make = {make!r} must be the command that makes the targets (a string)"
        )
    multistart = cfg.get_number(t, "multistart", 1, where=w, lo=1, hi=64, integer=True)
    devices = cfg.get_number(t, "devices", 1, where=w, lo=1, hi=4096, integer=True)
    check_devices(devices, multistart, "[fit] devices")
    glob = t.get("target_glob", "*.png")
    if not isinstance(glob, str) or not glob.strip() or glob.startswith("/") or ".." in glob:
        raise cfg.ConfigError(
            f"[fit] target_glob = {glob!r} must be a file pattern relative to each camera folder, "
            'e.g. "*.png" or "rgb/frame_*.png"'
        )
    cams = t.get("target_cameras")
    if cams is not None:
        if (
            not isinstance(cams, list)
            or not cams
            or not all(isinstance(c, str) and c.strip() and ".." not in c for c in cams)
        ):
            raise cfg.ConfigError(
                f"[fit] target_cameras = {cams!r} must be a list of folder names (or globs "
                'matching one folder each) inside targets, one per camera, e.g. ["left", "right"]'
            )  # fmt: skip
        cams = tuple(cams)
    frames = t.get("target_frames")
    if frames is not None:
        if (
            not isinstance(frames, list)
            or len(frames) != 2
            or not all(isinstance(f, int) and not isinstance(f, bool) for f in frames)
            or not 0 <= frames[0] < frames[1]
        ):
            raise cfg.ConfigError(
                f"[fit] target_frames = {frames!r} must be [first, stop]: 0 <= first < stop, "
                "image indices after sorting (stop excluded)"
            )  # fmt: skip
        frames = (int(frames[0]), int(frames[1]))
    if targets is None:
        for key in ("target_glob", "target_cameras", "target_frames", "target_stride",
                    "colorspace", "target_downsample", "targets_make"):  # fmt: skip
            if key in t:
                raise cfg.ConfigError(f"[fit] {key} needs [fit] targets (a folder of images)")
    ident = t.get("identifiability", True)
    if not isinstance(ident, bool):
        raise cfg.ConfigError("[fit] identifiability must be true or false")
    loss = cfg.get_choice(t, "loss", "l2", LOSSES + ("footage",), where=w)
    footage = parse_footage(t, loss)
    if footage is not None and targets is None:
        raise cfg.ConfigError(
            '[fit] loss = "footage" compares with footage: give [fit] targets (a folder of '
            "images or an .npz file); synthetic [truth] targets have no footage masks"
        )
    return FitSettings(
        free=tuple(free),
        steps=cfg.get_number(t, "steps", 60, where=w, lo=1, integer=True),
        learning_rate=cfg.get_number(t, "learning_rate", 0.05, where=w, lo=0, lo_inclusive=False),
        loss=loss,
        footage=footage,
        patience=cfg.get_number(t, "patience", 30, where=w, lo=1, integer=True),
        schedule=cfg.get_choice(t, "schedule", "cosine", ("cosine", "constant"), where=w),
        noise=cfg.get_number(t, "noise", 0.0, where=w, lo=0, hi=1),
        seed=cfg.get_number(t, "seed", 0, where=w, integer=True),
        multistart=multistart,
        devices=devices,
        identifiability=ident,
        noise_sigma=cfg.get_number(t, "noise_sigma", 0.01, where=w, lo=0, lo_inclusive=False),
        targets=targets,
        target_glob=glob,
        target_cameras=cams,
        target_frames=frames,
        target_stride=cfg.get_number(t, "target_stride", 1, where=w, lo=1, integer=True),
        target_downsample=cfg.get_number(
            t, "target_downsample", 1, where=w, lo=1, hi=64, integer=True
        ),
        targets_make=make,
        colorspace=cfg.get_choice(t, "colorspace", "auto", ("auto", "srgb", "linear"), where=w),
        initial=initial,
        truth=truth,
        **_parse_engine(t, free),
    )


def check_devices(devices: int, multistart: int, where: str = "devices") -> None:
    """ConfigError unless the multistart guesses split evenly over the devices."""
    if devices > 1 and multistart % devices:
        raise cfg.ConfigError(
            f"{where} = {devices} spreads the multistart guesses over devices, so [fit] multistart "
            f"must be a multiple of it (got multistart = {multistart})"
        )
