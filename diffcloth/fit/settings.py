"""One frozen settings object for every fitting loop (Adam, Levenberg-Marquardt, multistart).

    settings = FitSettings(method="lm", steps=40)
    result = fit_params(loss_fn, init, settings=settings)          # or keyword arguments
    result = fit_params(loss_fn, init, steps=40)                   # the same, still accepted

`fit_params`, `fit_multistart`, `fit_lm` and the scene-level `fit` take `settings=` and/or the
same names as keyword arguments (keywords override the settings' fields), so a new option is added
here once. The config's [fit] section is parsed into the same fields (docs/config.md).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

__all__ = ["METHODS", "FitSettings", "LM_MAX_PARAMS", "resolve_settings"]

METHODS = ("auto", "lm", "adam", "staged")
LM_MAX_PARAMS = 16  # method "auto" picks Levenberg-Marquardt up to this many scalar parameters


@dataclasses.dataclass(frozen=True)
class FitSettings:
    """Options of the fitting loops. Fields not used by a method are ignored by it.

    Shared:
      method: "auto" (LM for <= 16 scalar parameters and a least-squares loss, else Adam; with
        float64 under contact and a scan when the start is far: `diffcloth.fit.auto`), "lm",
        "adam", "staged" (the staged LM recipe). Only the scene-level `fit` and `run_fit_config`
        choose; `engines.adam` is Adam and `engines.lm` is LM.
      scan: None (the method's own: "auto" scans by the far-start rule, "staged" scans the
        stiffest scalar, "lm"/"adam" none), False (none), "auto" (the rule with any LM method)
        or {name: factors} (scan these and start from the best). Scene-level `fit` only.
      x64: None (the method's own: "auto"/"staged" fit in float64 when the scene has contact),
        True or False. Scene-level `fit` only.
      steps: maximum optimizer steps (Adam updates; LM iterations of the last stage).
      tol, patience: "stalled" after `patience` steps without a relative loss improvement > tol.
      loss_tol: "converged" once the loss is <= loss_tol.
      progress: progress bar / lines. callback: `callback(step, info)`; truthy return stops.
      checkpoint_path, checkpoint_every: see `fit_params`.
    Adam:
      optimizer (optax, default clip + adam), learning_rate (0.05), clip_norm (1.0).
    Levenberg-Marquardt (`diffcloth.fit.lm`):
      lm_patience: stall patience of LM (each LM step is worth many Adam steps).
      lm_xtol: "converged" when an accepted step moves every raw (log-space) value by less than
        this and the loss changed by less than lm_ftol (relative).
      lm_stage_steps: step budget of each coarse stage of the schedule.
      lm_tau: initial damping lambda0 = tau * max diag(J^T J) (Marquardt's rule).
      lm_prior: coarse stages add residuals sqrt(mu) (raw - raw at the stage start), mu =
        lm_prior * max diag(J^T J): a parameter the stage barely sees (e.g. bending before the
        cloth meets the sphere) stays put instead of wandering along a flat direction. The final
        stage has no prior. 0 disables.
      lm_polish: at most this many undamped Gauss-Newton steps after the last stage (each
        clipped to lm_polish_step in raw units); the fixed point replaces the trust-region result
        when the steps settle and its loss is at most twice the trust-region best (a rugged
        loss biases the fixed point: with the old "coulomb" contact rule the main job's lay 8 %
        off in bend at 3.7x the loss and was refused; with the continuous "impact" rule it takes
        the main job and drape_material to the truth). 0 disables.
      stages: coarse-to-fine stages (`diffcloth.fit.schedule.make_schedule` spec: None = the
        default, "none", a Schedule or a list of {min_level, frames} tables).
    Multistart:
      multistart (number of starts), spread (log-normal spread of the extra guesses), seed,
      devices (shard the starts over this many devices).
    Ties: name -> expression, e.g. {"shear": "stretch", "bend": "1e-4 * stretch"}
      (`diffcloth.fit.ties`).
    """

    method: str = "auto"
    scan: Any = None
    x64: bool | None = None
    steps: int = 200
    tol: float = 1e-7
    patience: int | None = 50
    loss_tol: float | None = None
    progress: bool = True
    callback: Callable[[int, dict], Any] | None = None
    checkpoint_path: str | Path | None = None
    checkpoint_every: int | None = None
    # Adam
    optimizer: Any = None
    learning_rate: float | None = None
    clip_norm: float = 1.0
    # Levenberg-Marquardt
    lm_patience: int = 6
    lm_xtol: float = 1e-5
    lm_ftol: float = 1e-6
    lm_stage_steps: int = 20
    lm_tau: float = 1e-3
    lm_prior: float = 1e-2
    lm_polish: int = 10
    lm_polish_step: float = 0.05
    stages: Any = None
    # multistart
    multistart: int = 1
    spread: float = 0.5
    seed: int = 0
    devices: int | None = None
    # ties
    ties: Mapping[str, Any] | None = None

    def __post_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"method={self.method!r} is not one of {METHODS}")
        for name in ("steps", "lm_patience", "lm_stage_steps", "multistart", "lm_polish"):
            v = getattr(self, name)
            low = 0 if name in ("steps", "lm_polish") else 1
            if isinstance(v, bool) or not isinstance(v, int) or v < low:
                raise ValueError(f"{name}={v!r} must be an integer >= {low}")
        for name in ("lm_xtol", "lm_ftol", "lm_tau", "lm_prior", "lm_polish_step", "spread", "tol"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v >= 0):
                raise ValueError(f"{name}={v!r} must be a finite number >= 0")
        if self.lm_tau <= 0:
            raise ValueError(f"lm_tau={self.lm_tau!r} must be > 0")

    def replace(self, **changes) -> FitSettings:
        return dataclasses.replace(self, **changes)


_FIELDS = {f.name for f in dataclasses.fields(FitSettings)}


def resolve_settings(settings: FitSettings | None, kwargs: Mapping[str, Any]) -> FitSettings:
    """`settings` (default FitSettings()) with the keyword arguments that name its fields applied.

    Raises TypeError for a keyword that is not a field (the message lists the fields)."""
    base = settings if settings is not None else FitSettings()
    if not isinstance(base, FitSettings):
        raise TypeError(f"settings must be a FitSettings, got {type(base).__name__}")
    unknown = sorted(set(kwargs) - _FIELDS)
    if unknown:
        raise TypeError(f"unknown fit option(s) {unknown}; FitSettings fields: {sorted(_FIELDS)}")
    return dataclasses.replace(base, **kwargs) if kwargs else base
