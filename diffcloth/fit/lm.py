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

import functools
import logging
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from diffcloth.fit.constraints import make_constraints, to_physical, to_raw
from diffcloth.fit.loop import (
    FitResult,
    History,
    MultiStartResult,
    _as_float,
    _check_init,
    _fmt,
    _stack_inits,
)
from diffcloth.fit.settings import FitSettings, resolve_settings

__all__ = ["fit_lm", "fit_lm_multistart", "lm_jacobian", "num_scalars"]

log = logging.getLogger("diffcloth.fit")

#: consecutive rejected steps allowed = _REJECT_FACTOR * lm_patience (each shrinks the radius 4x)
_REJECT_FACTOR = 3


def num_scalars(params: Mapping[str, Any]) -> int:
    """Total number of scalars in a dict of parameters."""
    return int(sum(np.size(v) for v in params.values()))


@functools.lru_cache(maxsize=32)
def _compiled(residual_fn, cons_items, batched: bool):
    """(init, step) jitted for one residual function and constraints; cached.

    The function handed to the solver computes the residuals r and their Jacobian J (jacfwd:
    one batched forward pass with n tangents) at the current point and returns
    r + J (y - stop_gradient(y)): its value is r and its linearisation is exactly J, so the
    solver's `jax.linearize` keeps only J (not the whole simulation) and its linear solves are
    small matrix products. J is also returned as the solver's aux (initial damping, covariance).
    """
    import equinox as eqx
    import optimistix as optx

    cons = dict(cons_items)
    # Tolerances of the solver's own (elementwise Cauchy) test; the host loop adds its own tests.
    solver = optx.LevenbergMarquardt(rtol=1e-7, atol=1e-12)

    def fn(y, args):
        loss_args, stage_args, (anchor, sqrt_mu) = args
        flat, unravel = ravel_pytree(y)
        z = jax.lax.stop_gradient(flat)

        def g(v):
            return jnp.ravel(residual_fn(to_physical(unravel(v), cons), *loss_args, *stage_args))

        # one forward pass carrying n tangents (the primal is computed once, unbatched)
        r, jac = jax.vmap(lambda t: jax.jvp(g, (z,), (t,)), out_axes=(None, 1))(
            jnp.eye(z.size, dtype=z.dtype)
        )
        # prior rows sqrt(mu) (y - anchor): hold parameters the stage cannot determine (mu = 0 in
        # the final stage)
        prior = sqrt_mu.astype(flat.dtype) * (flat - anchor.astype(flat.dtype))
        return jnp.concatenate([r + jac @ (flat - z), prior]), jac

    def init(y, args, step_size):
        f_struct, aux_struct = jax.eval_shape(lambda: fn(y, args))
        state = solver.init(fn, y, args, {}, f_struct, aux_struct, frozenset())
        size = jnp.asarray(step_size, state.search_state.step_size.dtype)
        return eqx.tree_at(lambda s: s.search_state.step_size, state, size)

    def step(y, state, args):
        y_new, state_new, _ = solver.step(fn, y, args, {}, state, frozenset())
        loss = jnp.sum(jnp.square(state_new.f_info.residual))
        done, result = solver.terminate(fn, y_new, args, {}, state_new, frozenset())
        jac = state_new.aux  # J at the accepted point y_new
        return (
            y_new,
            state_new,
            loss,
            done & (result == optx.RESULTS.successful),
            state_new.num_accepted_steps,
            state_new.search_state.step_size,
            jnp.max(jnp.sum(jnp.square(jac), axis=0)),
            jnp.all(jnp.isfinite(jac)),
        )

    if not batched:
        return _forward_mode(eqx.filter_jit(init)), _forward_mode(eqx.filter_jit(step))

    def masked_step(y, state, args, active):
        ax = eqx.if_array(0)
        out = eqx.filter_vmap(step, in_axes=(ax, ax, (None, None, 0)))(y, state, args)
        y_new, state_new = out[0], out[1]

        def keep(new, old):
            if not eqx.is_array(new):
                return new
            mask = active.reshape((-1,) + (1,) * (new.ndim - 1))
            return jnp.where(mask, new, old)

        y_new = jax.tree_util.tree_map(keep, y_new, y)
        state_new = jax.tree_util.tree_map(keep, state_new, state)
        return (y_new, state_new) + out[2:]

    return (
        _forward_mode(
            eqx.filter_jit(eqx.filter_vmap(init, in_axes=(eqx.if_array(0), (None, None, 0), 0)))
        ),
        _forward_mode(eqx.filter_jit(masked_step)),
    )


def _forward_mode(fn):
    """Call (and so trace) `fn` with the physics' plain autodiff forces: the hand-written VJP of
    the symplectic step is reverse-mode only (`diffcloth.physics.forces.autodiff_forces`)."""
    from diffcloth.physics.forces import autodiff_forces

    @functools.wraps(fn)
    def call(*args, **kwargs):
        with autodiff_forces():
            return fn(*args, **kwargs)

    return call


def _probe(init_fn, step_fn, raw, args, batched, n):
    """One solver step at `raw` (always accepted): (state, loss (n,), max diag J^T J (n,),
    finite (n,), J). Costs one evaluation; compiles nothing beyond the step."""
    size = jnp.asarray(np.ones(n) if batched else np.float64(1.0))  # as the real init: strong
    state = init_fn(raw, args, size)
    if batched:
        out = step_fn(raw, state, args, jnp.ones((n,), bool))
    else:
        out = step_fn(raw, state, args)
    state = out[1]
    return state, out[2], out[6], out[7], state.aux


def lm_jacobian(residual_fn, params, constraints=None, *, loss_args=(), stage_args=()):
    """(residuals (m,), raw-space Jacobian (m, n)) at physical `params`, with the engine's compiled
    step (same residual_fn, constraints and argument shapes: no new compilation). Columns follow
    `ravel_pytree` of the raw dict (sorted names)."""
    names = list(params)
    cons = make_constraints(names, constraints)
    init_fn, step_fn = _compiled(residual_fn, tuple(sorted(cons.items())), False)
    raw = {k: _as_float(v) for k, v in to_raw(_check_init(params, "params"), cons).items()}
    flat = ravel_pytree(raw)[0]
    prior = (jnp.zeros_like(flat), jnp.zeros((), flat.dtype))
    state, _, _, _, jac = _probe(
        init_fn, step_fn, raw, (tuple(loss_args), tuple(stage_args), prior), False, 1
    )
    return np.asarray(state.f_info.residual)[: jac.shape[0]], np.asarray(jac)


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
    from diffcloth.fit.loop import _progress_bar

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
        from diffcloth.fit.loop import save_checkpoint

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
        polish = [i for i in range(n) if status[i] in ("converged", "stalled", "max_steps")]
        if s.lm_polish and polish and best_raw[polish[0]] is not None:
            k_global, evaluations = _polish(
                s,
                polish,
                init_fn,
                step_fn,
                (loss_args, stages[-1], prior0),
                batched,
                n,
                names,
                best_raw,
                best_loss,
                status,
                message,
                host,
                record,
                len(stages) - 1,
                k_global,
                evaluations,
                last_diag,
            )
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


def _polish(
    s,
    which,
    init_fn,
    step_fn,
    args,
    batched,
    n,
    names,
    best_raw,
    best_loss,
    status,
    message,
    host,
    record,
    stage,
    k_global,
    evaluations,
    diag,
):
    """Gauss-Newton polish after the last stage: undamped GN steps (the solver's first step with
    a huge trust radius, lambda = 1e-9 max diag J^T J; no new compilation), each clipped to
    lm_polish_step in raw units, until the step is below lm_xtol * 10. A contact- or visibility-
    rugged loss makes the trust region reject every step long before the smooth model's minimum
    (J^T r = 0); the GN fixed point is that minimum. Used only when the steps settle and its loss
    is at most twice the trust-region best; otherwise the best trust-region point stays."""
    y = {
        k: np.stack(
            [best_raw[i][k] if best_raw[i] is not None else best_raw[which[0]][k] for i in range(n)]
        )
        for k in names
    }
    todo = np.zeros(n, bool)
    todo[which] = True
    done = np.zeros(n, bool)
    size = 1e9 / diag
    loss_at = np.full(n, np.nan)
    y_at = None
    iters = 0
    for _ in range(s.lm_polish):
        iters += 1
        yj = {k: jnp.asarray(v if batched else v[0]) for k, v in y.items()}
        state = init_fn(yj, args, jnp.asarray(size if batched else np.float64(size[0])))
        if batched:
            out = step_fn(yj, state, args, jnp.asarray(todo & ~done))
        else:
            out = step_fn(yj, state, args)
        evaluations += 1
        k_global += 1
        loss_at = host(out[2]).astype(float)
        y_at = {k: v.copy() for k, v in y.items()}
        step = {k: host(v) - y[k] for k, v in out[1].y_eval.items()}
        moves = np.array([max(float(np.max(np.abs(step[k][i]))) for k in names) for i in range(n)])
        for k in names:
            y[k] = y[k] + np.clip(step[k], -s.lm_polish_step, s.lm_polish_step)
        newly = todo & ~done & (moves < 10 * s.lm_xtol)
        done |= newly
        if np.all(done[todo]):
            break
    for i in np.flatnonzero(todo):
        if done[i] and np.isfinite(loss_at[i]) and loss_at[i] <= 2.0 * best_loss[i]:
            record_loss = np.full(n, np.nan)
            record_loss[i] = loss_at[i]
            best_raw[i] = {k: y_at[k][i] for k in names}
            best_loss[i] = loss_at[i]
            status[i] = "converged"
            message[i] = (message[i] + "; " if message[i] else "") + (
                f"then a Gauss-Newton polish reached the smooth model's minimum (J^T r = 0) in "
                f"{iters} steps (loss {loss_at[i]:.4g} there)"
            )
        elif done[i]:
            message[i] = (message[i] + "; " if message[i] else "") + (
                f"a Gauss-Newton polish settled at loss {loss_at[i]:.4g}, more than twice the "
                f"trust-region best {best_loss[i]:.4g} (a rugged loss biases the smooth model): "
                "kept the trust-region point"
            )
        else:
            message[i] = (message[i] + "; " if message[i] else "") + (
                f"a Gauss-Newton polish did not settle in {s.lm_polish} steps: kept the best "
                "trust-region point"
            )
    if np.any(done & todo):
        rec = np.where(done & todo, loss_at, np.nan)
        record(
            rec,
            {k: jnp.asarray(v if batched else v[0]) for k, v in y_at.items()},
            stage,
            force=True,
        )
    return k_global, evaluations


def _settings_and_hook(settings, kwargs):
    hook = kwargs.pop("hook", None)
    stop = kwargs.pop("stop", None)
    resume = kwargs.pop("resume", None)
    return resolve_settings(settings, kwargs), hook, stop, resume


def _resumed(init, resume):
    """Start from a checkpoint's best values (an LM fit restarts its stages from there)."""
    if resume is None:
        return init
    from diffcloth.fit.loop import _as_checkpoint

    ck = _as_checkpoint(resume)
    best = ck.get("best") or {}
    missing = sorted(set(init) - set(best))
    if missing:
        raise ValueError(f"resume: the checkpoint has no values for {missing}")
    return {k: best[k] for k in init}


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
    s, hook, stop, resume = _settings_and_hook(settings, dict(kwargs))
    init_phys = _check_init(_resumed(init, resume))
    results, _ = _run_lm(
        residual_fn,
        init_phys,
        constraints,
        batched=False,
        n=1,
        settings=s,
        loss_args=tuple(loss_args),
        stages=stages,
        stage_names=stage_names,
        hook=hook,
        stop=stop,
        priors=stage_priors,
    )
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
    s, hook, stop, resume = _settings_and_hook(settings, dict(kwargs))
    if resume is not None:
        if not isinstance(inits, Sequence) or not inits:
            raise ValueError("resume needs inits as a list of dicts")
        inits = [_resumed(inits[0], resume)] + list(inits[1:])
    stacked, n = _stack_inits(inits)
    results, wall = _run_lm(
        residual_fn,
        stacked,
        constraints,
        batched=True,
        n=n,
        settings=s,
        loss_args=tuple(loss_args),
        stages=stages,
        stage_names=stage_names,
        hook=hook,
        devices=s.devices if s.devices and s.devices > 1 else None,
        stop=stop,
        priors=stage_priors,
    )
    losses = np.array([r.loss if np.isfinite(r.loss) else np.inf for r in results])
    return MultiStartResult(results=results, best_index=int(np.argmin(losses)), wall_s=wall)
