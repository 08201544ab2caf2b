"""The Gauss-Newton polish after the last Levenberg-Marquardt stage (`diffcloth.fit.lm`)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

__all__ = ["polish"]


def polish(s, which, solver, args, ctx, k_global, evaluations, diag):
    """Gauss-Newton polish after the last stage: undamped GN steps (the solver's first step with
    a huge trust radius, lambda = 1e-9 max diag J^T J; no new compilation), each clipped to
    lm_polish_step in raw units, until the step is below lm_xtol * 10. A contact- or visibility-
    rugged loss makes the trust region reject every step long before the smooth model's minimum
    (J^T r = 0); the GN fixed point is that minimum. Used only when the steps settle and its loss
    is at most twice the trust-region best; otherwise the best trust-region point stays.

    s: FitSettings; which: indices of the starts to polish; solver: (init_fn, step_fn, batched,
    n) of `lm_solver._compiled`; args: the last stage's solver arguments; ctx: the run's state
    (names, best_raw, best_loss, status, message: updated in place; host, record; stage);
    diag: (n,) max diag J^T J. Returns (k_global, evaluations) advanced by the steps taken."""
    init_fn, step_fn, batched, n = solver
    names, best_raw, best_loss = ctx.names, ctx.best_raw, ctx.best_loss
    status, message, host, record, stage = ctx.status, ctx.message, ctx.host, ctx.record, ctx.stage
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
