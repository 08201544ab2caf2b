"""A generic optax fitting loop: any JAX scalar loss of named physical parameters.

    result = fit_params(loss_fn, {"stretch": 500.0}, {"stretch": Positive()}, steps=200)

The optimiser works on raw (unconstrained) values; `loss_fn` always receives physical values
(see `constraints.py`). One jitted step does value_and_grad in raw space and the optax update; the
Python loop around it keeps the history, draws the progress bar, stops early and stops cleanly when
the loss or a gradient becomes NaN/inf (the update is then not applied, so the parameters never
become NaN; this does not depend on `optax.apply_if_finite`).

`fit_multistart` fits several initial guesses at once with `jax.vmap`; each start has its own
finite flag, so one diverging start freezes by itself without poisoning the others.
"""

from __future__ import annotations

import functools
import logging
import math
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax

from diffcloth.fit.checkpoint import (  # noqa: F401 (re-exported: the public names stay here)
    CHECKPOINT_FORMAT,
    _as_checkpoint,
    _restore,
    load_checkpoint,
    pack_tree,
    save_checkpoint,
    unpack_tree,
)
from diffcloth.fit.constraints import make_constraints, to_physical, to_raw
from diffcloth.fit.results import (  # noqa: F401 (re-exported)
    STATUSES,
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
from diffcloth.fit.tracker import _check_stopping, _postfix, _progress_bar, _Tracker

__all__ = [
    "FitResult",
    "FitSettings",
    "History",
    "MultiStartResult",
    "default_optimizer",
    "fit_multistart",
    "fit_params",
    "load_checkpoint",
    "pack_tree",
    "save_checkpoint",
    "unpack_tree",
]

log = logging.getLogger("diffcloth.fit")


@functools.lru_cache(maxsize=32)
def default_optimizer(learning_rate: float = 0.05, clip_norm: float = 1.0):
    """adam(learning_rate) after clip_by_global_norm(clip_norm). Cached, so equal settings reuse
    the compiled fit step."""
    return optax.chain(optax.clip_by_global_norm(clip_norm), optax.adam(learning_rate))


def _step_impl(loss_fn, cons_items, optimizer, raw, opt_state, active, args):
    cons = dict(cons_items)

    def raw_loss(r):
        return loss_fn(to_physical(r, cons), *args)

    phys = to_physical(raw, cons)
    loss, grads = jax.value_and_grad(raw_loss)(raw)
    grad_norm = {k: jnp.sqrt(jnp.sum(jnp.square(g))) for k, g in grads.items()}
    updates, new_state = optimizer.update(grads, opt_state, raw)
    new_raw = optax.apply_updates(raw, updates)
    leaves_ok = [jnp.all(jnp.isfinite(g)) for g in jax.tree_util.tree_leaves(grads)]
    leaves_ok += [jnp.all(jnp.isfinite(x)) for x in jax.tree_util.tree_leaves(new_raw)]
    finite = jnp.isfinite(loss)
    for ok in leaves_ok:
        finite = finite & ok
    grad_finite = {k: jnp.all(jnp.isfinite(g)) for k, g in grads.items()}
    apply = finite & active

    def keep(new, old):
        return jnp.where(apply, new, old)

    new_raw = jax.tree_util.tree_map(keep, new_raw, raw)
    new_state = jax.tree_util.tree_map(keep, new_state, opt_state)
    return new_raw, new_state, loss, phys, grad_norm, finite, grad_finite


_step = jax.jit(_step_impl, static_argnums=(0, 1, 2))
_step_batched = jax.jit(
    lambda f, c, o, raw, st, act, args: jax.vmap(
        functools.partial(_step_impl, f, c, o), in_axes=(0, 0, 0, None)
    )(raw, st, act, args),
    static_argnums=(0, 1, 2),
)


def _resolve_optimizer(optimizer, learning_rate, clip_norm):
    if optimizer is None:
        lr = 0.05 if learning_rate is None else float(learning_rate)
        if not (math.isfinite(lr) and lr > 0):
            raise ValueError(f"learning_rate={learning_rate!r} must be finite and > 0")
        return default_optimizer(lr, float(clip_norm))
    if learning_rate is not None:
        raise ValueError("give either optimizer= or learning_rate=, not both")
    return optimizer


def _run(
    loss_fn,
    init_phys,
    constraints,
    *,
    batched,
    n,
    steps,
    optimizer,
    learning_rate,
    clip_norm,
    tol,
    patience,
    loss_tol,
    progress,
    callback,
    checkpoint_path,
    checkpoint_every,
    desc,
    loss_args,
    devices=None,
    resume=None,
    stop=None,
):
    _check_stopping(steps, tol, patience, loss_tol)
    names = list(init_phys)
    cons = make_constraints(names, constraints)
    cons_items = tuple(sorted(cons.items()))
    opt = _resolve_optimizer(optimizer, learning_rate, clip_norm)
    raw = {k: _as_float(v) for k, v in to_raw(init_phys, cons).items()}
    tr = _Tracker(n, names, tol, patience, loss_tol)
    if batched:
        opt_state = jax.vmap(opt.init)(raw)
        if resume is not None:
            raw, opt_state = _restore(resume, raw, opt_state, names, n, steps, tr)
        if devices is not None:
            raw, opt_state, loss_args = _spread(devices, n, raw, opt_state, loss_args)

        def step(r, s, a):
            return _step_batched(loss_fn, cons_items, opt, r, s, jnp.asarray(a), loss_args)
    else:
        opt_state = opt.init(raw)
        if resume is not None:
            raw, opt_state = _restore(resume, raw, opt_state, names, n, steps, tr)

        def step(r, s, a):
            return _step(loss_fn, cons_items, opt, r, s, jnp.asarray(a[0]), loss_args)

    def host(x):  # add the batch axis on the host for a single fit
        x = np.asarray(x)
        return x if batched else x[None]

    path_msg = (
        str(checkpoint_path)
        if checkpoint_path is not None
        else "FitResult.last_finite (pass checkpoint_path= to also write them to disk)"
    )
    k0 = len(tr.loss)
    t0 = time.perf_counter() - (tr.wall[-1] if tr.wall else 0.0)
    bar = _progress_bar(steps, progress, desc)
    bar.update(min(k0, steps))

    def save(r, s):
        if checkpoint_path is None:
            return
        i = int(np.argmin(np.where(np.isfinite(tr.best_loss), tr.best_loss, np.inf)))
        best = tr.best_raw[i] or {n: host(r[n])[i] for n in names}
        last = tr.last_finite_raw[i] or best
        arrays = {f"raw/{n}": host(r[n])[i] for n in names}
        arrays.update({f"params/{n}": np.asarray(v) for n, v in to_physical(
            {n: host(r[n])[i] for n in names}, cons).items()})  # fmt: skip
        arrays.update({f"best/{n}": np.asarray(v) for n, v in to_physical(best, cons).items()})
        arrays.update(
            {f"last_finite/{n}": np.asarray(v) for n, v in to_physical(last, cons).items()}
        )
        arrays.update({f"state/raw/{n}": np.asarray(r[n]) for n in names})
        arrays.update(pack_tree("opt_state", s))
        arrays.update(tr.to_arrays())
        arrays["step"] = np.asarray(len(tr.loss))
        loss_i = float(tr.best_loss[i])
        meta = {
            "format": CHECKPOINT_FORMAT,
            "step": len(tr.loss),
            "names": names,
            "starts": n,
            "loss": loss_i if math.isfinite(loss_i) else None,
            "status": tr.status[i],
            "best": {k: np.asarray(v) for k, v in to_physical(best, cons).items()},
            "last_finite": {k: np.asarray(v) for k, v in to_physical(last, cons).items()},
            "tracker_status": tr.status,
            "tracker_message": tr.message,
        }
        save_checkpoint(checkpoint_path, arrays, meta)

    interrupted = False
    try:
        for k in range(k0, steps + 1):
            if not tr.active.any():
                break
            final = k == steps
            act = tr.active & (not final)
            raw_before = raw
            raw, opt_state, loss, phys, gnorm, finite, gfin = step(raw, opt_state, act)
            loss, finite = host(loss).astype(float), host(finite).astype(bool)
            phys = {n: host(v) for n, v in phys.items()}
            gnorm = {n: host(v) for n, v in gnorm.items()}
            gfin = {n: host(v) for n, v in gfin.items()}
            raw_host = {n: host(v) for n, v in raw_before.items()}
            recording = tr.active.copy()
            tr.record(k, loss, phys, gnorm, finite, raw_host, time.perf_counter() - t0, recording)
            if final:
                for i in np.flatnonzero(tr.active & ~finite):
                    tr.status[i] = "nonfinite"
                    tr.message[i] = (
                        f"non-finite loss/grad at step {k} (loss={loss[i]:.4g}, after the last "
                        f"update); last finite params saved to {path_msg}"
                    )
                break
            tr.update_stopping(k, loss, finite, gfin, path_msg)
            bar.update(1)
            if not bar.disable:
                _postfix(bar, tr, phys, batched)
            if callback is not None:
                i = int(np.argmin(np.where(np.isfinite(loss), loss, np.inf)))
                info = {
                    "loss": float(loss[i]) if not batched else loss,
                    "params": {n: v[i] for n, v in phys.items()} if not batched else phys,
                    "grad_norm": {n: float(v[i]) for n, v in gnorm.items()}
                    if not batched
                    else gnorm,
                    "finite": bool(finite[i]) if not batched else finite,
                }
                if callback(k, info):
                    for i in np.flatnonzero(tr.active):
                        tr.status[i] = "stopped"
                        tr.message[i] = f"stopped by callback at step {k}"
                        tr.stop_step[i] = k + 1
                    tr.active[:] = False
            if checkpoint_every and (k + 1) % checkpoint_every == 0:
                save(raw, opt_state)
            if stop is not None and stop.is_set() and tr.active.any():
                save(raw, opt_state)  # before marking: a resumed fit carries on from here
                where = f"checkpoint {checkpoint_path}" if checkpoint_path else "no checkpoint"
                for i in np.flatnonzero(tr.active):
                    tr.status[i] = "interrupted"
                    tr.message[i] = f"interrupted after step {k} ({where})"
                    tr.stop_step[i] = k + 1
                tr.active[:] = False
                interrupted = True
                break
    finally:
        bar.close()
    wall = time.perf_counter() - t0
    if not interrupted:
        save(raw, opt_state)
    results = [
        tr.result(
            i,
            batched,
            {k: np.asarray(v) if not batched else np.asarray(v)[i] for k, v in init_phys.items()},
            cons,
            wall,
            None if checkpoint_path is None else str(checkpoint_path),
        )
        for i in range(n)
    ]
    for r in results:
        if r.status == "nonfinite":
            log.warning(r.message)
    return results, wall


def _spread(devices, n, raw, opt_state, loss_args):
    """Shard the starts (leading axis) over a device mesh; replicate the loss arguments."""
    from jax.sharding import Mesh, NamedSharding
    from jax.sharding import PartitionSpec as P

    from diffcloth.batch import make_mesh, shard_batch

    mesh = devices if isinstance(devices, Mesh) else make_mesh(int(devices))
    if n % mesh.devices.size:
        raise ValueError(
            f"the number of starts ({n}) must be a multiple of devices ({mesh.devices.size}): each "
            "device fits the same number of starts"
        )
    raw, opt_state = shard_batch((raw, opt_state), mesh)
    loss_args = jax.device_put(loss_args, NamedSharding(mesh, P()))
    return raw, opt_state, loss_args


def _adam_settings(settings, kwargs) -> FitSettings:
    """`resolve_settings`, with this loop's own checks of the stopping options."""
    s = resolve_settings(settings, kwargs)
    _check_stopping(s.steps, s.tol, s.patience, s.loss_tol)
    return s


def _run_settings(loss_fn, init_phys, constraints, s, *, batched, n, desc, loss_args, resume,
                  stop, devices=None):  # fmt: skip
    return _run(
        loss_fn, init_phys, constraints, batched=batched, n=n, steps=s.steps,
        optimizer=s.optimizer, learning_rate=s.learning_rate, clip_norm=s.clip_norm, tol=s.tol,
        patience=s.patience, loss_tol=s.loss_tol, progress=s.progress, callback=s.callback,
        checkpoint_path=s.checkpoint_path, checkpoint_every=s.checkpoint_every, desc=desc,
        loss_args=tuple(loss_args), devices=devices, resume=_as_checkpoint(resume), stop=stop,
    )  # fmt: skip


def fit_params(
    loss_fn: Callable[..., jax.Array],
    init: Mapping[str, Any],
    constraints: Mapping | None = None,
    *,
    settings: FitSettings | None = None,
    loss_args: tuple = (),
    resume: str | Path | Mapping | None = None,
    stop: Any = None,
    **options,
) -> FitResult:
    """Minimise `loss_fn(physical_params)` over the named parameters with optax.

    Args:
      loss_fn: a JAX function of a dict name -> physical value (scalar or array) returning a scalar.
        It is jitted once (cached on the function object, constraints and optimizer).
      init: initial physical values, name -> float or array; validated against the constraints.
      constraints: name -> Constraint or spec (see `constraints.make_constraint`); missing names
        are unconstrained.
      settings: a `FitSettings` (steps, optimizer, learning_rate, clip_norm, tol, patience,
        loss_tol, progress, callback, checkpoint_path, checkpoint_every; other fields are LM's and
        ignored here). Each of these may also be given as a keyword argument (`**options`), which
        overrides the settings' field; an unknown keyword raises TypeError.
        steps: maximum number of optimizer updates (default 200).
        optimizer: an optax GradientTransformation on raw values. Default:
          `chain(clip_by_global_norm(clip_norm), adam(learning_rate))`.
        learning_rate: for the default optimizer (default 0.05, i.e. about 5% relative steps for
          log-space parameters). Give optimizer= or learning_rate=, not both.
        clip_norm: gradient clipping of the default optimizer (1.0).
        tol, patience: stop ("stalled") after `patience` steps (50) without a relative
          improvement of the loss by more than `tol` (1e-7); patience=None disables.
        loss_tol: stop ("converged") once the loss is <= loss_tol.
        progress: tqdm bar (loss, current values, rate); quiet when stderr is not a terminal.
        callback: `callback(step, info)` with info = {"loss", "params", "grad_norm", "finite"}
          after each step; a truthy return value stops the fit ("stopped").
        checkpoint_path: .npz file (+ .json sidecar) written at the end, on a non-finite stop and
          every `checkpoint_every` steps: raw, physical, best and last finite params, optimizer
          state.
      loss_args: extra arguments, `loss_fn(params, *loss_args)`: pytrees of arrays such as the
        target video, passed to the jitted step as arguments (not baked in as constants, so a
        new target of the same shape does not recompile).
      resume: a checkpoint (path or `load_checkpoint` dict) written by a fit with the same
        parameters, optimizer and loss: the fit continues from its step with its optimizer state
        and history, and ends exactly as an uninterrupted fit of `steps` steps would.
      stop: an object with `is_set()` (e.g. `threading.Event`, see `diffcloth.fit.interrupt`),
        checked after every step: once set, the checkpoint is written and the fit returns with
        status "interrupted".
    Returns:
      FitResult. On a non-finite loss or gradient at step k the fit stops, status "nonfinite",
      message "non-finite loss/grad at step k (...); last finite params saved to ...", and
      the parameters are never updated with the non-finite values.
    """
    s = _adam_settings(settings, options)
    results, _ = _run_settings(
        loss_fn, _check_init(init), constraints, s, batched=False, n=1, desc="fit",
        loss_args=loss_args, resume=resume, stop=stop,
    )  # fmt: skip
    return results[0]


def fit_multistart(
    loss_fn: Callable[..., jax.Array],
    inits,
    constraints: Mapping | None = None,
    *,
    settings: FitSettings | None = None,
    loss_args: tuple = (),
    resume: str | Path | Mapping | None = None,
    stop: Any = None,
    devices: int | Any | None = None,
    **options,
) -> MultiStartResult:
    """Fit several initial guesses at once (`jax.vmap` over the raw parameters); keep the best.

    Args:
      inits: a list of dicts (same names and shapes) or a dict of arrays stacked on a leading axis.
      Everything else as in `fit_params` (`settings` and/or the same keywords); `loss_args` are
      shared by all starts; the callback receives per-start arrays. Each start has its own finite
      flag and stopping state: a start whose loss or gradient becomes non-finite is frozen at its
      last finite parameters (status "nonfinite") and the others carry on unchanged. The
      checkpoint holds the best start.
      devices: spread the starts over this many devices (or over a given 1-D
        `jax.sharding.Mesh` with axis "batch"): the raw parameters and optimizer states are
        sharded along the start axis (`diffcloth.batch.shard_batch`), `loss_args` replicated, and
        the one jitted step runs each device's starts there. The number of starts must be a
        multiple of the number of devices. None: settings.devices, else JAX's default placement.
    Returns:
      MultiStartResult: `.results` (one FitResult per start), `.best_index`, `.best`, `.params`.
    """
    s = _adam_settings(settings, options)
    stacked, n = _stack_inits(inits)
    results, wall = _run_settings(
        loss_fn, stacked, constraints, s, batched=True, n=n, desc=f"fit x{n}",
        loss_args=loss_args, resume=resume, stop=stop,
        devices=devices if devices is not None else s.devices,
    )  # fmt: skip
    return best_of(results, wall)
