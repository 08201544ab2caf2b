"""Levenberg-Marquardt (trust-region Gauss-Newton) on a residual vector, driven step by step.

    result = fit_lm(residual_fn, {"bend": 1e-3, "drag_normal": 0.4}, loss_args=(targets,))

The solver is `optimistix.LevenbergMarquardt` (QR solves from lineax, a classical trust region);
this module does not implement the method itself. It drives the solver one jitted step at a time
(`solver.init` / `solver.step`) from Python, which gives what the Adam loop has: a progress bar,
a history, the best-so-far point, early stops, a non-finite stop, a per-step hook and Ctrl-C.

Variables are the raw (unconstrained) values of `diffcloth.fit.constraints`, as in the Adam loop;
`residual_fn(physical_params, *loss_args, *stage_args)` returns any-shaped residuals r and the loss
is sum(r ** 2). Jacobians are forward mode (`jax.linearize` inside the solver, `jax.jacfwd` for
the initial damping and the covariance at the end), so a step costs about (1 + n_params) forward
passes: meant for up to ~16 scalar parameters.

Stages: `stages` is a list of extra argument tuples of equal shapes (e.g. pyramid-level and frame
weights, see `diffcloth.fit.schedule`); each stage is an LM run warm-started from the previous
one's best point, and all stages share one compiled step.

Statuses (as the Adam loop): "converged" (a small accepted step with a small loss change, the
solver's own test, or loss <= loss_tol), "stalled" (no relative improvement > lm_ftol for
lm_patience steps), "max_steps", "nonfinite", "stopped" (callback), "interrupted" (Ctrl-C).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping, Sequence
from types import SimpleNamespace
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from diffcloth.fit.checkpoint import _as_checkpoint, save_checkpoint
from diffcloth.fit.constraints import make_constraints, to_physical, to_raw
from diffcloth.fit.lm_polish import polish
from diffcloth.fit.lm_solver import (  # noqa: F401 (public names re-exported here)
    _compiled,
    _probe,
    lm_jacobian,
    num_scalars,
)
from diffcloth.fit.results import (
    FitResult,
    History,
    MultiStartResult,
    _as_float,
    _check_init,
    _fmt,
    _stack_inits,
    best_of,
)
from diffcloth.fit.settings import FitSettings, resolve_settings
from diffcloth.fit.tracker import _progress_bar

__all__ = ["fit_lm", "fit_lm_multistart", "lm_jacobian", "num_scalars"]

log = logging.getLogger("diffcloth.fit")

#: consecutive rejected steps allowed = _REJECT_FACTOR * lm_patience (each shrinks the radius 4x)
_REJECT_FACTOR = 3


class _Interrupted(Exception):
    pass


def _run_lm(
    residual_fn,
    init_phys,
    constraints,
    *,
    batched: bool,
    n: int,
    settings: FitSettings,
    loss_args: tuple,
    stages: Sequence[tuple] | None,
    stage_names: Sequence[str] | None,
    hook: Callable[[int, dict], Any] | None,
    devices=None,
    stop=None,
    priors=None,
) -> tuple[list[FitResult], float]:
    s = settings
    names = list(init_phys)
    cons = make_constraints(names, constraints)
    cons_items = tuple(sorted(cons.items()))
    init_fn, step_fn = _compiled(residual_fn, cons_items, batched)
    raw = {k: _as_float(v) for k, v in to_raw(init_phys, cons).items()}
    stages = [tuple(a) for a in (stages or [()])]
    stage_names = list(stage_names or [f"stage {i + 1}" for i in range(len(stages))])
    if len(stage_names) != len(stages):
        raise ValueError(f"{len(stage_names)} stage names for {len(stages)} stages")
    loss_args = tuple(loss_args)
    if batched and devices is not None:
        from diffcloth.fit.loop import _spread

        raw, _, loss_args = _spread(devices, n, raw, {}, loss_args)

    def host(x):
        x = np.asarray(x)
        return x if batched else x[None]

    def phys_of(r):
        return {k: host(v) for k, v in to_physical(r, cons).items()}

    t0 = time.perf_counter()
    hist_loss: list[np.ndarray] = []
    hist_params: list[dict] = []
    hist_wall: list[float] = []
    hist_stage: list[int] = []
    best_loss = np.full(n, np.inf)
    best_raw: list[dict | None] = [None] * n
    status = ["max_steps"] * n
    message = [""] * n
    stop_len = np.full(n, -1)
    active = np.ones(n, bool)
    evaluations = 0  # residual evaluations with a Jacobian (per start)
    stage_log: list[dict] = []

    def record(loss, y, stage, force=False):
        hist_loss.append(loss)
        hist_params.append(phys_of(y))
        hist_wall.append(time.perf_counter() - t0)
        hist_stage.append(stage)
        if force:
            return
        yh = {k: host(v) for k, v in y.items()}
        for i in range(n):
            if active[i] and np.isfinite(loss[i]) and loss[i] < best_loss[i]:
                best_loss[i] = loss[i]
                best_raw[i] = {k: yh[k][i] for k in names}

    def save(step, st):
        if s.checkpoint_path is None:
            return
        i = int(np.argmin(np.where(np.isfinite(best_loss), best_loss, np.inf)))
        if best_raw[i] is None:
            return
        braw = {kk: np.asarray(v) for kk, v in best_raw[i].items()}
        bphys = {kk: np.asarray(v) for kk, v in to_physical(braw, cons).items()}
        arrays = {"step": np.asarray(step)}
        for group, d in (("raw", braw), ("params", bphys), ("best", bphys), ("last_finite", bphys)):
            arrays.update({f"{group}/{kk}": v for kk, v in d.items()})
        meta = {
            "method": "lm",
            "step": int(step),
            "status": st,
            "names": names,
            "loss": float(best_loss[i]) if np.isfinite(best_loss[i]) else None,
            "best": bphys,
        }
        save_checkpoint(s.checkpoint_path, arrays, meta)

    def stop_fit(i, st, msg):
        status[i], message[i] = st, msg
        active[i] = False
        stop_len[i] = len(hist_loss)

    k_global = 0
    interrupted = False
    try:
        for si, stage_args in enumerate(stages):
            last_stage = si == len(stages) - 1
            flat_start = (
                ravel_pytree(raw)[0] if not batched else jax.vmap(lambda r: ravel_pytree(r)[0])(raw)
            )
            zero_mu = jnp.zeros((n,) if batched else (), flat_start.dtype)
            prior0 = (flat_start, zero_mu)
            args = (loss_args, stage_args, prior0)
            # Restart each stage from each start's best point so far.
            if si > 0:
                for kname in names:
                    cur = host(raw[kname]).copy()
                    for i in range(n):
                        if best_raw[i] is not None:
                            cur[i] = best_raw[i][kname]
                    raw[kname] = jnp.asarray(cur if batched else cur[0], raw[kname].dtype)
                best_loss[:] = np.inf  # losses of different stages do not compare
            # Probe step at the start point: its loss and J (Marquardt's initial damping
            # lambda0 = tau * max diag(J^T J)); then restart the solver with that damping.
            _, loss0, diag, ok0, _ = _probe(init_fn, step_fn, raw, args, batched, n)
            evaluations += 1
            loss0, diag = host(loss0).astype(float), host(diag).astype(float)
            ok0 = host(ok0).astype(bool) & np.isfinite(loss0)
            if si == 0:
                record(np.where(active, loss0, np.nan), raw, si)
            for i in np.flatnonzero(active & ~ok0):
                stop_fit(
                    i,
                    "nonfinite",
                    f"non-finite residual or Jacobian at the start of "
                    f"{stage_names[si]} (loss {loss0[i]:.4g})",
                )
            if not active.any():
                break
            if not last_stage and s.lm_prior > 0 and (priors is None or priors[si]):
                # coarse stages: a prior pulling towards the stage's start point, of weight
                # lm_prior * max diag(J^T J), keeps parameters this stage cannot see in place
                mu = s.lm_prior * np.where(diag > 0, diag, 1.0)
                sqrt_mu = jnp.asarray(np.sqrt(mu) if batched else np.sqrt(mu[0]), flat_start.dtype)
                args = (loss_args, stage_args, (flat_start, sqrt_mu))
            last_diag = np.where(diag > 0, diag, 1.0)
            lam0 = s.lm_tau * last_diag
            size = 1.0 / lam0
            state = init_fn(raw, args, jnp.asarray(size if batched else np.float64(size[0])))
            budget = s.steps if last_stage else min(s.lm_stage_steps, s.steps)
            ref = loss0.copy()
            stall = np.zeros(n, int)
            rejected = np.zeros(n, int)
            prev_acc = np.zeros(n, int)
            prev_loss = loss0.copy()
            prev_y = {k: host(v).copy() for k, v in raw.items()}
            stage_active = active.copy()
            bar = _progress_bar(budget, s.progress, f"LM {stage_names[si]}")
            stage_status = ["max_steps"] * n
            try:
                for k in range(budget):
                    if batched:
                        out = step_fn(raw, state, args, jnp.asarray(stage_active))
                    else:
                        out = step_fn(raw, state, args)
                    raw, state, loss, done, acc, radius = out[:6]
                    evaluations += 1
                    k_global += 1
                    loss, done = host(loss).astype(float), host(done).astype(bool)
                    acc, radius = host(acc).astype(int), host(radius).astype(float)
                    record(np.where(stage_active, loss, np.nan), raw, si)
                    yh = {kk: host(v) for kk, v in raw.items()}
                    for i in np.flatnonzero(stage_active):
                        dy = max(float(np.max(np.abs(yh[kk][i] - prev_y[kk][i]))) for kk in names)
                        accepted = acc[i] > prev_acc[i]
                        rel = abs(prev_loss[i] - loss[i]) / max(abs(prev_loss[i]), 1e-300)
                        end = None
                        if not np.isfinite(loss[i]) or not all(
                            np.all(np.isfinite(yh[kk][i])) for kk in names
                        ):
                            end = (
                                "nonfinite",
                                f"non-finite loss at LM step {k} of "
                                f"{stage_names[si]} (loss {loss[i]:.4g})",
                            )
                        elif s.loss_tol is not None and loss[i] <= s.loss_tol:
                            end = ("converged", f"loss {loss[i]:.4g} <= loss_tol {s.loss_tol:g}")
                        elif done[i] or (accepted and k > 0 and dy < s.lm_xtol and rel < s.lm_ftol):
                            end = (
                                "converged",
                                f"step {dy:.2g} (raw) and relative loss change "
                                f"{rel:.2g} at LM step {k} of {stage_names[si]}",
                            )
                        else:
                            # A rejected step only shrinks the trust region (x 1/4 in
                            # optimistix); far from the optimum many in a row are normal, so
                            # they get a longer patience than accepted steps that stop helping.
                            if loss[i] < ref[i] * (1.0 - s.lm_ftol):
                                ref[i], stall[i], rejected[i] = loss[i], 0, 0
                            elif accepted:
                                stall[i] += 1
                            else:
                                rejected[i] += 1
                            if stall[i] >= s.lm_patience or rejected[i] >= _REJECT_FACTOR * (
                                s.lm_patience
                            ):
                                end = (
                                    "stalled",
                                    f"no relative improvement > {s.lm_ftol:g} for "
                                    f"{stall[i] + rejected[i]} LM steps ({rejected[i]} rejected; "
                                    f"trust radius {radius[i]:.2g}) in {stage_names[si]}",
                                )
                        prev_acc[i], prev_loss[i] = acc[i], loss[i]
                        for kk in names:
                            prev_y[kk][i] = yh[kk][i]
                        if end is not None:
                            stage_active[i] = False
                            stage_status[i] = end[0]
                            if end[0] == "nonfinite" or last_stage:
                                stop_fit(i, *end)
                    bar.update(1)
                    if not bar.disable:
                        i = int(np.nanargmin(np.where(np.isfinite(loss), loss, np.inf)))
                        bar.set_postfix_str(
                            f"loss={loss[i]:.4g} "
                            + " ".join(f"{kk}={_fmt(hist_params[-1][kk][i])}" for kk in names[:6]),
                            refresh=False,
                        )
                    info = {
                        "step": k_global,
                        "stage": si,
                        "stage_name": stage_names[si],
                        "loss": loss if batched else float(loss[0]),
                        "params": hist_params[-1]
                        if batched
                        else {kk: v[0] for kk, v in hist_params[-1].items()},
                        "raw": {kk: np.asarray(v) for kk, v in raw.items()},
                        "best_loss": best_loss.copy() if batched else float(best_loss[0]),
                        "best_raw": best_raw if batched else best_raw[0],
                        "status": "running",
                        "method": "lm",
                    }
                    if hook is not None:
                        hook(k_global, info)
                    if s.callback is not None and s.callback(k_global, info):
                        for i in np.flatnonzero(active):
                            stop_fit(i, "stopped", f"stopped by callback at LM step {k_global}")
                            stage_status[i] = "stopped"
                        stage_active[:] = False
                    if stop is not None and stop.is_set():
                        for i in np.flatnonzero(active):
                            stop_fit(i, "interrupted", f"interrupted after LM step {k_global}")
                            stage_status[i] = "interrupted"
                        stage_active[:] = False
                    if s.checkpoint_every and k_global % s.checkpoint_every == 0:
                        save(k_global, "running")
                    if not stage_active.any():
                        break
            finally:
                bar.close()
            save(k_global, "running")
            stage_log.append(
                {
                    "name": stage_names[si],
                    "steps": k + 1,
                    "loss": [float(x) for x in best_loss],
                    "status": list(stage_status),
                }
            )
            if not active.any():
                break
        polish_starts = [
            i for i, st in enumerate(status) if st in ("converged", "stalled", "max_steps")
        ]
        if s.lm_polish and polish_starts and best_raw[polish_starts[0]] is not None:
            ctx = SimpleNamespace(
                names=names, best_raw=best_raw, best_loss=best_loss, status=status,
                message=message, host=host, record=record, stage=len(stages) - 1,
            )  # fmt: skip
            k_global, evaluations = polish(
                s, polish_starts, (init_fn, step_fn, batched, n), (loss_args, stages[-1], prior0),
                ctx, k_global, evaluations, last_diag,
            )  # fmt: skip
    except KeyboardInterrupt:
        interrupted = True
        for i in np.flatnonzero(active):
            stop_fit(i, "interrupted", f"interrupted (Ctrl-C) at LM step {k_global}")
    wall = time.perf_counter() - t0
    save(k_global, "interrupted" if interrupted or "interrupted" in status else "done")
    if interrupted:
        log.warning("LM fit interrupted; returning the best point so far")
    results = []
    for i in range(n):
        m = int(stop_len[i]) if stop_len[i] >= 0 else len(hist_loss)
        hist = History(
            loss=np.array([float(l[i]) for l in hist_loss[:m]]),
            params={kk: np.stack([p[kk][i] for p in hist_params[:m]]) for kk in names},
            grad_norm={kk: np.full(m, np.nan) for kk in names},
            wall_s=np.asarray(hist_wall[:m], float),
        )
        init_i = {
            kk: (np.asarray(v)[i] if batched else np.asarray(v)) for kk, v in init_phys.items()
        }
        if best_raw[i] is None:
            braw = {kk: np.asarray(v) for kk, v in to_raw(init_i, cons).items()}
        else:
            braw = {kk: np.asarray(v) for kk, v in best_raw[i].items()}
        params = {kk: np.asarray(v) for kk, v in to_physical(braw, cons).items()}
        st = status[i]
        msg = message[i] or f"reached steps={s.steps} in {stage_names[-1]}"
        res = FitResult(
            params=params,
            raw=braw,
            loss=float(best_loss[i]),
            initial={kk: np.asarray(v) for kk, v in init_i.items()},
            history=hist,
            iterations=m - 1,
            wall_s=float(wall),
            status=st,
            message=msg,
            best_step=int(np.nanargmin(np.where(np.isfinite(hist.loss), hist.loss, np.inf)))
            if m
            else -1,
            last_finite=params,
        )
        res.method = "lm"
        res.evaluations = int(evaluations)
        res.stages = [
            {"name": d["name"], "steps": d["steps"], "loss": d["loss"][i], "status": d["status"][i]}
            for d in stage_log
        ]
        results.append(res)
    return results, wall


def _settings_and_hook(settings, kwargs):
    hook = kwargs.pop("hook", None)
    stop = kwargs.pop("stop", None)
    resume = kwargs.pop("resume", None)
    return resolve_settings(settings, kwargs), hook, stop, resume


def _resumed(init, resume):
    """Start from a checkpoint's best values (an LM fit restarts its stages from there)."""
    if resume is None:
        return init
    ck = _as_checkpoint(resume)
    best = ck.get("best") or {}
    missing = sorted(set(init) - set(best))
    if missing:
        raise ValueError(f"resume: the checkpoint has no values for {missing}")
    return {k: best[k] for k in init}


def _entry(residual_fn, inits, constraints, batched, loss_args, stages, stage_names, priors,
           settings, kwargs):  # fmt: skip
    """Shared body of `fit_lm` (one init dict) and `fit_lm_multistart`: (results, wall)."""
    s, hook, stop, resume = _settings_and_hook(settings, dict(kwargs))
    if not batched:
        init_phys, n = _check_init(_resumed(inits, resume)), 1
    else:
        if resume is not None:
            if not isinstance(inits, Sequence) or not inits:
                raise ValueError("resume needs inits as a list of dicts")
            inits = [_resumed(inits[0], resume)] + list(inits[1:])
        init_phys, n = _stack_inits(inits)
    return _run_lm(
        residual_fn, init_phys, constraints, batched=batched, n=n, settings=s,
        loss_args=tuple(loss_args), stages=stages, stage_names=stage_names, hook=hook,
        devices=s.devices if batched and s.devices and s.devices > 1 else None, stop=stop,
        priors=priors,
    )  # fmt: skip


def fit_lm(
    residual_fn: Callable[..., jax.Array],
    init: Mapping[str, Any],
    constraints: Mapping | None = None,
    *,
    loss_args: tuple = (),
    stages: Sequence[tuple] | None = None,
    stage_names: Sequence[str] | None = None,
    stage_priors: Sequence[bool] | None = None,
    settings: FitSettings | None = None,
    **kwargs,
) -> FitResult:
    """Least squares: minimise sum(residual_fn(params, *loss_args, *stage_args) ** 2).

    Args:
      residual_fn: JAX function of a dict name -> physical value (+ loss_args, stage args)
        returning residuals of any shape. Cached compilation per (residual_fn, constraints).
      init: initial physical values. constraints: as in `fit_params`.
      loss_args: jit arguments shared by all stages (e.g. the target video).
      stages: list of argument tuples, one per coarse-to-fine stage (same shapes); None: one stage.
      stage_priors: per stage, whether the coarse-stage prior (settings.lm_prior) applies
        (default: every stage but the last).
      settings: FitSettings (steps, lm_patience, lm_xtol, lm_ftol, lm_stage_steps, lm_tau,
        loss_tol, progress, callback); keyword arguments naming its fields override it.
      hook (keyword): `hook(step, info)` after every LM step (info: step, stage, loss, params, raw,
        best_loss, best_raw, status, method); its return value is ignored.
      stop (keyword): an object with `is_set()` (`diffcloth.fit.interrupt`): checked after each
        step; when set the fit ends with status "interrupted" (best point kept, checkpoint saved).
      resume (keyword): a checkpoint (path or `load_checkpoint` dict): start from its best values.
      checkpoint_path / checkpoint_every (settings): `loop.save_checkpoint` layout (raw, params,
        best, last_finite of the best start) after every stage, every k steps and at the end.
    Returns:
      FitResult with method "lm", `evaluations` (residual + Jacobian evaluations) and `stages`.
      history.grad_norm is NaN (LM does not form the gradient).
    """
    results, _ = _entry(
        residual_fn, init, constraints, False, loss_args, stages, stage_names, stage_priors,
        settings, kwargs,
    )  # fmt: skip
    return results[0]


def fit_lm_multistart(
    residual_fn: Callable[..., jax.Array],
    inits,
    constraints: Mapping | None = None,
    *,
    loss_args: tuple = (),
    stages: Sequence[tuple] | None = None,
    stage_names: Sequence[str] | None = None,
    stage_priors: Sequence[bool] | None = None,
    settings: FitSettings | None = None,
    **kwargs,
) -> MultiStartResult:
    """`fit_lm` for several starts at once (vmap; each start has its own trust region and stops
    on its own); `devices` (settings) shards the starts as `fit_multistart` does. The best final
    loss wins."""
    return best_of(
        *_entry(
            residual_fn, inits, constraints, True, loss_args, stages, stage_names, stage_priors,
            settings, kwargs,
        )
    )  # fmt: skip
