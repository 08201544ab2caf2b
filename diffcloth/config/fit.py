"""Fit sections of the schema: [fit], [fit.initial] and [truth] (docs/config.md).

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
    initial: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    truth: Mapping[str, Any] = dataclasses.field(default_factory=dict)


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
                    f"[truth] {name} = {value!r} is out of range; "
                    f"allowed {material_range(name)} {unit}"
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
