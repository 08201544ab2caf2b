"""The compiled Levenberg-Marquardt step of `diffcloth.fit.lm` (optimistix), and Jacobians from it.

One jitted (init, step) pair per (residual function, constraints, batched), cached; Jacobians are
forward mode (one batched forward pass carrying n tangents)."""

from __future__ import annotations

import functools
from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from diffcloth.fit.constraints import make_constraints, to_physical, to_raw
from diffcloth.fit.results import _as_float, _check_init

__all__ = ["lm_jacobian", "num_scalars"]


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

    @eqx.filter_jit
    def residual_and_jac(y, loss_args, stage_args):
        """(r (m,), J (m, n)) at raw y (a dict; J's columns follow `ravel_pytree`): one forward
        pass carrying n tangents (the primal is computed once, unbatched). Jitted on its own:
        tracing the pipeline under vmap and jvp is most of tracing init and step, and so it is
        traced once per argument shapes, not in each of the solver's init (two shape
        evaluations) and step (jax.linearize)."""
        z, unravel = ravel_pytree(y)

        def g(v):
            return jnp.ravel(residual_fn(to_physical(unravel(v), cons), *loss_args, *stage_args))

        return jax.vmap(lambda t: jax.jvp(g, (z,), (t,)), out_axes=(None, 1))(
            jnp.eye(z.size, dtype=z.dtype)
        )

    def fn(y, args):
        loss_args, stage_args, (anchor, sqrt_mu) = args
        flat = ravel_pytree(y)[0]
        z = jax.lax.stop_gradient(flat)
        r, jac = residual_and_jac(jax.lax.stop_gradient(y), loss_args, stage_args)
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
