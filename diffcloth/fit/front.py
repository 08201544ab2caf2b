"""The front door: `fit(scene, targets, free=[...], method="auto")` for every engine and schedule.

    result = dc.fit.fit(scene, video, free=["k_struct", "air_damping"])
    print(result.summary())            # status, loss, values, and the knob to turn on a stall

method "auto" (the default) does what the footage recipe of docs/fit.md does, where a rule says
so (`diffcloth.fit.auto`): float64 when the scene has contact, a scan when the start is far,
coarse-to-fine Levenberg-Marquardt stages. "lm" is that LM alone (the scene's dtype, no scan),
"staged" the staged recipe (damping alone on the free fall, a scan of the stiffest parameter,
then everything), "adam" the optax loop. The engines are in `diffcloth.fit.engines`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["fit"]

#: LM settings of the staged recipe (benchmarks/cross_engine/protocol.py), unless given
RECIPE_LM = {"lm_tau": 1.0, "lm_xtol": 1e-3, "lm_ftol": 1e-5, "lm_polish": 0}


def fit(
    scene,
    targets,
    free: Sequence[str],
    steps: int | None = None,
    optimizer=None,
    *,
    method: str = "auto",
    stages=None,
    scan=None,
    x64: bool | None = None,
    init: Mapping[str, Any] | None = None,
    constraints: Mapping[str, Any] | None = None,
    loss: Any = "l2",
    ties: Mapping[str, Any] | None = None,
    settings=None,
    masks=None,
    **fit_kwargs,
):
    """Fit the named scene parameters to target videos: the one entry point for every engine.

    Args:
      scene: a `diffcloth.Scene`.
      targets: (cameras, T, H, W, C) video, or (T, H, W, C) for a single camera; float in [0, 1]
        or uint8 (divided by 255). Checked against `scene.video_shape` before any compilation.
      free: names of the parameters to fit (see `diffcloth.pipeline.PARAMETERS`).
      steps: maximum optimizer steps (default 100; LM: steps of the final stage).
      optimizer: an optax transformation (Adam only; giving one makes method "auto" pick Adam).
      method: "auto" (default): Levenberg-Marquardt for l2/pyramid losses and <= 16 scalar
        parameters (else Adam), in float64 when the scene has contact; a scan decides whether
        the start is far (`diffcloth.fit.auto`): far runs the "staged" recipe, near LM with
        the coarse-to-fine stages. "lm": that LM in
        the scene's dtype without a scan (what `diffcloth fit` runs). "staged": the staged
        recipe (air resistance alone on the first 35 % of the frames, a scan of the stiffest
        parameter, then all; LM started damped, lm_xtol 1e-3, lm_ftol 1e-5, no polish), or
        the given `stages`. "adam": the optax loop. Left at "auto", a `settings.method` wins.
      stages: coarse-to-fine stages (`diffcloth.fit.schedule.make_schedule`: None = the
        method's default, "none", or a list of {"min_level", "frames", "free", "scan"}); a
        stage with `free` or `scan` runs the staged engine.
      scan: None (the method's: "auto" scans up to 3 positive physical scalars and moves only
        when the start's loss is in the upper half of the scan's range), False, "auto", or
        {name: factors} (scan those, start from the best).
      x64: None (the method's: "auto" and "staged" use float64 when the scene has contact), True,
        False. JAX's x64 is on for this call only; the scene and targets are cast.
      init: initial physical values (default: the scene's own values).
      constraints: name -> constraint (default `default_constraint(name)`).
      loss: "l2", "l1" or "pyramid" (multi-scale, wider basin of convergence), or a
        `diffcloth.fit.footage.FootageLoss` (robust colour + silhouette, for footage diffcloth
        did not render; a sum of squares, so LM and the staged recipe fit it).
      ties: {name: "other" | "c * other"} tied parameters (`diffcloth.fit.ties`): not optimised,
        set from their source (which must be free) at every evaluation; reported in the result.
      settings: a `FitSettings`; the keyword arguments override its fields.
      masks: the target cloth masks (cameras, T, H, W) in [0, 1], for a `FootageLoss` with a
        mask term or a `color_margin`.
      fit_kwargs: any other `FitSettings` field (multistart, spread, seed, devices,
        learning_rate, tol, patience, progress, callback, checkpoint_path, lm_patience, ...),
        `hook` (LM per-step hook), `stop` (interrupt event) and `resume` (a checkpoint).
    Returns:
      FitResult (MultiStartResult when multistart > 1). `.method` says which engine ran,
      `.auto` what the rules decided (x64, scans), `.hints` the knobs to turn when the fit
      stalled (also in `.summary()`).
    Raises:
      ValueError: unknown parameter names, a bad loss kind, bad ties, or targets of the wrong shape.
    """
    from diffcloth import pipeline
    from diffcloth.fit.auto import cast_floats, has_contact
    from diffcloth.fit.constraints import Positive
    from diffcloth.fit.footage import FootageLoss
    from diffcloth.fit.lm import num_scalars
    from diffcloth.fit.losses import as_target_array, validate_targets
    from diffcloth.fit.scene_fit import LOSSES, choose_method, default_constraint
    from diffcloth.fit.settings import FitSettings, resolve_settings
    from diffcloth.fit.ties import parse_ties

    run = {k: fit_kwargs.pop(k, None) for k in ("hook", "stop", "resume")}
    overrides = dict(fit_kwargs)
    if steps is not None:
        overrides["steps"] = steps
    elif settings is None:
        overrides.setdefault("steps", 100)
    named = {"optimizer": optimizer, "ties": ties, "stages": stages, "scan": scan, "x64": x64}
    overrides.update({k: v for k, v in named.items() if v is not None})
    if method != "auto" or settings is None:
        overrides["method"] = method
    s = resolve_settings(settings, overrides)
    default = FitSettings()
    given = set(overrides) | {
        f.name
        for f in dataclasses.fields(FitSettings)
        if settings is not None and getattr(settings, f.name) != getattr(default, f.name)
    }
    devices, multistart = s.devices, s.multistart
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
    tie_set = parse_ties(s.ties, free)
    tied = [n for n in free if n in tie_set.targets]
    free = [n for n in free if n not in tie_set.targets]
    if not free:
        raise ValueError(f"every free parameter is tied ({tied}); leave at least one free")
    if "bump_strength" in free:  # warns when the bump map is filtered away at this resolution
        from diffcloth.render.detail import check_bump_detail

        check_bump_detail(scene, free)
    footage = loss if isinstance(loss, FootageLoss) else None
    if footage is not None:
        loss = "l2"  # a sum of squares at full resolution: what the engine choice reads
        if masks is not None:
            masks = as_target_array(masks, "masks")
    elif loss not in LOSSES:
        raise ValueError(f"loss must be one of {LOSSES} or a FootageLoss, got {loss!r}")
    elif masks is not None:
        raise ValueError("masks are for a footage loss (loss=FootageLoss(...))")
    targets = as_target_array(targets, "targets")
    if targets.ndim == 4 and len(scene.cameras) == 1:
        targets = targets[None]
    # rendered (linear) videos exceed 1 at highlights and noisy synthetic targets ([fit] noise)
    # dip below 0: only data that looks like 0..255 is refused here
    targets = validate_targets(targets, scene.video_shape, name="targets", value_range=(None, 2.0))
    dtype = np.dtype(scene.material.density.dtype)
    start = {
        n: np.asarray(init[n] if init and n in init else pipeline.param_value(scene, n))
        for n in free
    }
    cons = {n: (constraints or {}).get(n, default_constraint(n)) for n in free}
    engine = choose_method(s.method, loss, num_scalars(start), s.optimizer)
    contact = has_contact(scene)
    recipe = s.method in ("auto", "staged")
    use_x64 = bool(s.x64) if s.x64 is not None else (recipe and contact)
    if engine == "staged":
        s = s.replace(**{k: v for k, v in RECIPE_LM.items() if k not in given})
    inits = [start]
    if multistart > 1:
        rng = np.random.default_rng(s.seed)
        for _ in range(multistart - 1):
            guess = {}
            for n, v in start.items():
                if isinstance(cons[n], Positive):
                    guess[n] = v * np.exp(s.spread * rng.standard_normal(np.shape(v)))
                else:
                    guess[n] = v + s.spread * 0.1 * rng.standard_normal(np.shape(v))
            inits.append(guess)
    job = _Job(engine, loss, s, given, tie_set, cons, run, contact, footage)
    if use_x64 and dtype != np.float64:
        with jax.enable_x64(True):
            result = job(cast_floats(scene, jnp.float64), jnp.asarray(targets, jnp.float64),
                         [{k: np.asarray(v, np.float64) for k, v in d.items()} for d in inits],
                         masks)  # fmt: skip
        for r in getattr(result, "results", [result]):  # the caller's dtype, as numpy
            for attr in ("params", "initial", "last_finite"):
                d = getattr(r, attr)
                setattr(r, attr, {k: np.asarray(v, dtype) for k, v in d.items()})
    else:
        result = job(scene, jnp.asarray(targets, dtype), inits, masks)
    for r in getattr(result, "results", [result]):
        r.auto = {"engine": engine, **(r.auto or {}), "method": s.method, "x64": use_x64}
    return result


@dataclasses.dataclass(frozen=True)
class _Job:
    """One fit's fixed choices; called with the (possibly float64) scene, targets and starts."""

    engine: str
    loss: str
    s: Any
    given: set
    ties: Any
    cons: dict
    run: dict
    contact: bool
    footage: Any = None

    def __call__(self, scene, targets, inits, masks=None):
        from diffcloth.fit.auto import SCAN_RISE, hints, scan_candidates, scan_start
        from diffcloth.fit.lm import fit_lm, fit_lm_multistart
        from diffcloth.fit.loop import fit_multistart, fit_params
        from diffcloth.fit.scene_fit import (
            _add_tied,
            _fit_staged_schedule,
            _lm_stages,
            _loss_fn,
            _residual_fn,
            recipe_stages,
        )
        from diffcloth.fit.schedule import Stage, make_schedule, stage_weights

        s, cons, run, engine = self.s, self.cons, self.run, self.engine
        init, multistart = inits[0], len(inits)
        record = None
        chained = False  # stages with their own free set or scan: the result's history and
        # start are the last stage's, so `initial` is reset to the caller's below
        loss_fn, res_fn = None, None
        if self.footage is not None:
            from diffcloth.fit.footage import footage_loss_fn, footage_residual_fn, prepare_targets

            targets = prepare_targets(scene, targets, masks, self.footage, value_range=(None, 2.0))
            loss_fn = footage_loss_fn(self.footage, self.ties)
            res_fn = footage_residual_fn(self.footage, self.ties)
        if self.engine == "adam":
            kw = dict(
                settings=s, loss_args=(targets, scene), resume=run["resume"], stop=run["stop"]
            )
            loss_fn = loss_fn or _loss_fn(self.loss, self.ties)
            if multistart <= 1:
                result = fit_params(loss_fn, init, cons, **kw)
            else:
                devices = s.devices if s.devices and s.devices > 1 else None
                result = fit_multistart(loss_fn, inits, cons, devices=devices, **kw)
        else:
            spec = s.stages
            if self.engine == "staged" and spec is None:
                spec = recipe_stages(init, cons)
            stage_args, stage_names, levels, priors = _lm_stages(scene, self.loss, spec)
            res_fn = res_fn or _residual_fn(levels, self.ties)
            scan = s.scan if s.scan is not None else ("auto" if s.method == "auto" else False)
            if scan not in (False, "none") and multistart <= 1 and run["resume"] is None:
                rule = scan in ("auto", True)
                names = scan_candidates(init, cons) if rule else dict(scan)
                if names:  # on the full resolution over the first half of the frames
                    lw, fw = stage_weights(self.loss, levels, scene.video_shape[1], Stage(0, 0.5),
                                           np.dtype(scene.material.density.dtype))  # fmt: skip
                    init, record = scan_start(res_fn, init, names, (targets, scene),
                                              (jnp.asarray(lw), jnp.asarray(fw)),
                                              rise=SCAN_RISE if rule else None)  # fmt: skip
            if s.method == "auto" and record and record["far"] and s.stages is None:
                # far: the staged recipe from the start (a coordinate scan alone lands off the
                # truth when the free fall's damping is wrong: benchmarks/fit_defaults.py)
                engine, init, spec = "staged", inits[0], recipe_stages(inits[0], cons)
                s = s.replace(**{k: v for k, v in RECIPE_LM.items() if k not in self.given})
                stage_args, stage_names, levels, priors = _lm_stages(scene, self.loss, spec)
            sched = make_schedule(spec)
            if any(st.staged for st in sched.stages):
                chained = True
                if multistart > 1:
                    raise ValueError("stages with free or scan run one start: set multistart = 1")
                result = _fit_staged_schedule(res_fn, init, cons, sched, stage_args, stage_names,
                                              (targets, scene), s)  # fmt: skip
            else:
                common = dict(loss_args=(targets, scene), stages=stage_args,
                              stage_names=stage_names, stage_priors=priors, settings=s,
                              hook=run["hook"], stop=run["stop"], resume=run["resume"])  # fmt: skip
                if multistart <= 1:
                    result = fit_lm(res_fn, init, cons, **common)
                else:
                    result = fit_lm_multistart(res_fn, inits, cons, **common)
            if engine == "staged":
                result.method = "staged"
        ident = None if self.footage else self._identifiability(scene, targets, result)
        for r in getattr(result, "results", [result]):
            if multistart <= 1 and (record is not None or engine == "staged" or chained):
                r.initial = {k: np.asarray(v) for k, v in inits[0].items()}  # before the scan
            r.auto = {**(record or {}), "engine": engine}
            # a float32 fit the caller asked for (x64=False) gets no "use x64" hint
            x64 = np.dtype(scene.material.density.dtype) == np.float64 or "x64" in self.given
            r.hints = hints(r, cons=cons, auto=record, x64=x64, contact=self.contact, ident=ident,
                            loss=None if self.footage else self.loss)  # fmt: skip
            if self.ties:
                _add_tied(r, self.ties)
        return result

    def _identifiability(self, scene, targets, result):
        """Confounded pairs at a stalled single LM fit's values (None otherwise, or on error)."""
        from diffcloth.fit.scene_fit import scene_identifiability

        if self.engine == "adam" or not hasattr(result, "status") or len(result.params) < 2:
            return None
        if result.status not in ("stalled", "max_steps"):
            return None
        try:
            params = {k: v for k, v in result.params.items() if k not in self.ties.targets}
            return scene_identifiability(
                scene, targets, params, ties=self.ties, constraints=self.cons
            )
        except Exception:  # a hint is never worth failing the fit over
            return None
