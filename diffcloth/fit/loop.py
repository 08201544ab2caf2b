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

import dataclasses
import functools
import json
import logging
import math
import os
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax

from diffcloth.fit.constraints import make_constraints, to_physical, to_raw
from diffcloth.io.media import to_jsonable

__all__ = [
    "FitResult",
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

STATUSES = ("max_steps", "converged", "stalled", "stopped", "nonfinite", "interrupted")

#: version of the checkpoint layout written by `save_checkpoint`.
CHECKPOINT_FORMAT = 2


@dataclasses.dataclass
class History:
    """Per evaluation (entry i = parameters after i optimizer updates).

    loss: (n,); params: name -> (n, *shape) physical values; grad_norm: name -> (n,) norm of the
    loss gradient w.r.t. that parameter's raw (optimised) value; wall_s: (n,) seconds since start.
    """

    loss: np.ndarray
    params: dict[str, np.ndarray]
    grad_norm: dict[str, np.ndarray]
    wall_s: np.ndarray

    def __len__(self) -> int:
        return int(self.loss.shape[0])

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly lists."""
        return {
            "loss": self.loss.tolist(),
            "params": {k: v.tolist() for k, v in self.params.items()},
            "grad_norm": {k: v.tolist() for k, v in self.grad_norm.items()},
            "wall_s": self.wall_s.tolist(),
        }


@dataclasses.dataclass
class FitResult:
    """Outcome of a fit.

    params/raw/loss: the evaluated parameters with the lowest finite loss (physical, raw).
    initial: the physical starting values. iterations: optimizer updates applied.
    status: "max_steps", "converged" (loss <= loss_tol), "stalled" (no relative improvement > tol
    for `patience` steps), "stopped" (callback), "nonfinite" or "interrupted" (the `stop` event was
    set, e.g. by Ctrl-C; a checkpoint to resume from was written when checkpoint_path was given).
    message: a one-line explanation.
    last_finite: physical parameters of the last evaluation with a finite loss and gradient.
    method: "adam" or "lm" (`diffcloth.fit.lm`). evaluations: loss + derivative evaluations.
    """

    params: dict[str, np.ndarray]
    raw: dict[str, np.ndarray]
    loss: float
    initial: dict[str, np.ndarray]
    history: History
    iterations: int
    wall_s: float
    status: str
    message: str
    best_step: int
    last_finite: dict[str, np.ndarray]
    checkpoint_path: str | None = None
    method: str = "adam"
    evaluations: int | None = None  # loss(+derivative) evaluations; None: len(history)
    stages: list[dict] | None = None  # LM coarse-to-fine stages (name, steps, loss, status)

    @property
    def ok(self) -> bool:
        """False when the fit stopped on a non-finite loss or gradient."""
        return self.status != "nonfinite"

    def summary(self) -> str:
        vals = ", ".join(f"{k}={_fmt(v)}" for k, v in self.params.items())
        return (
            f"{self.status}: loss {self.loss:.4g} after {self.iterations} steps "
            f"in {self.wall_s:.1f} s; {vals}"
        )


@dataclasses.dataclass
class MultiStartResult:
    """Outcome of `fit_multistart`: one FitResult per start and the index of the best one."""

    results: list[FitResult]
    best_index: int
    wall_s: float

    @property
    def best(self) -> FitResult:
        return self.results[self.best_index]

    @property
    def params(self) -> dict[str, np.ndarray]:
        return self.best.params

    @property
    def losses(self) -> np.ndarray:
        return np.array([r.loss for r in self.results])

    @property
    def statuses(self) -> list[str]:
        return [r.status for r in self.results]


def _fmt(v) -> str:
    a = np.asarray(v)
    if a.size == 1:
        return f"{float(a):.4g}"
    return "[" + ", ".join(f"{x:.3g}" for x in a.ravel()[:4]) + (", ...]" if a.size > 4 else "]")


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


def _as_float(v) -> jax.Array:
    """A float array with a strong (not weak) dtype, so the first and later steps share a trace."""
    a = jnp.asarray(v)
    dtype = a.dtype if jnp.issubdtype(a.dtype, jnp.floating) else jnp.result_type(float)
    return jnp.array(a, dtype=dtype)


def _check_init(init: Mapping[str, Any], what: str = "init") -> dict[str, jax.Array]:
    if not isinstance(init, Mapping) or not init:
        raise ValueError(f"{what} must be a non-empty dict of name -> value, got {init!r}")
    out = {}
    for k, v in init.items():
        a = _as_float(v)
        if not bool(jnp.all(jnp.isfinite(a))):
            raise ValueError(f"{what}[{k!r}]={np.asarray(a).tolist()} must be finite")
        out[k] = a
    return out


def pack_tree(prefix: str, tree) -> dict[str, np.ndarray]:
    """A pytree's leaves as {prefix/0000: array, ...} (tree_leaves order), for `save_checkpoint`."""
    return {
        f"{prefix}/{i:04d}": np.asarray(leaf)
        for i, leaf in enumerate(jax.tree_util.tree_leaves(tree))
    }


def unpack_tree(leaves: Sequence[np.ndarray], like):
    """Rebuild a pytree shaped like `like` from its saved leaves (see `pack_tree`); checks that the
    number, shapes and dtypes of the leaves match (a checkpoint of another optimizer fails here)."""
    ref, treedef = jax.tree_util.tree_flatten(like)
    if len(ref) != len(leaves):
        raise ValueError(
            f"checkpoint: the saved solver state has {len(leaves)} leaves, this optimizer's has "
            f"{len(ref)} (was it written by another optimizer or parameter set?)"
        )
    out = []
    for i, (a, b) in enumerate(zip(ref, leaves, strict=True)):
        if np.shape(a) != np.shape(b):
            raise ValueError(
                f"checkpoint: solver state leaf {i} has shape {np.shape(b)}, expected {np.shape(a)}"
            )
        out.append(jnp.asarray(b, dtype=jnp.asarray(a).dtype))
    return jax.tree_util.tree_unflatten(treedef, out)


def save_checkpoint(path, arrays: Mapping[str, Any], meta: Mapping[str, Any]) -> str:
    """Write a fit checkpoint: `path` (.npz, the arrays) and a .json sidecar (`meta`).

    The layout any fit loop can use (keys are "group/name"): "step" (evaluations done),
    "raw/", "params/", "best/", "last_finite/" (name -> value of the best start), "state/raw/"
    (the current raw values, with the start axis for a multistart fit), "opt_state/" (the
    optimizer or solver state pytree, `pack_tree`), "history/" (loss, params/NAME, grad_norm/NAME,
    wall) and "tracker/" (the loop's stopping state). Written to a temporary file and renamed, so a
    checkpoint on disk is always complete.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        np.savez(fh, **{k: np.asarray(v) for k, v in arrays.items()})
    os.replace(tmp, path)
    side = path.with_suffix(".json")
    side_tmp = side.with_name(side.name + ".tmp")
    side_tmp.write_text(json.dumps(to_jsonable(dict(meta)), indent=2, allow_nan=False) + "\n")
    os.replace(side_tmp, side)
    return str(path)


def load_checkpoint(path) -> dict[str, Any]:
    """Read a fit checkpoint (.npz, and its .json sidecar when present).

    Returns {"step", "raw", "params", "best", "last_finite", "opt_state", "state", "history",
    "tracker", "meta"}: dict entries map names to arrays; opt_state is the list of optimizer-state
    leaves (tree_leaves order, rebuild with `unpack_tree`); "history" holds "loss", "wall" and
    the dicts "params" and "grad_norm"; "meta" the sidecar's JSON (statuses, messages, names).
    """
    path = Path(path)
    out: dict[str, Any] = {
        "raw": {}, "params": {}, "best": {}, "last_finite": {}, "opt_state": [], "state": {},
        "history": {"params": {}, "grad_norm": {}}, "tracker": {}, "meta": {},
    }  # fmt: skip
    try:
        z = np.load(path)
    except (OSError, ValueError) as err:
        raise ValueError(f"cannot read checkpoint {str(path)!r}: {err}") from None
    with z:
        for key in sorted(z.files):
            if key == "step":
                out["step"] = int(z[key])
                continue
            group, name = key.split("/", 1)
            if group == "opt_state":
                out["opt_state"].append(z[key])
            elif group in ("state", "tracker", "history") and "/" in name:
                sub, leaf = name.split("/", 1)
                out[group].setdefault(sub, {})[leaf] = z[key]
            elif group in ("state", "tracker", "history"):
                out[group][name] = z[key]
            else:
                out[group][name] = z[key]
    side = path.with_suffix(".json")
    if side.exists():
        out["meta"] = json.loads(side.read_text())
    return out


def _progress_bar(total: int, progress: bool, desc: str):
    from tqdm.auto import tqdm

    return tqdm(
        total=total,
        disable=None if progress else True,
        desc=desc,
        unit="step",
        dynamic_ncols=True,
        leave=True,
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


def _check_stopping(steps, tol, patience, loss_tol):
    if not isinstance(steps, (int, np.integer)) or isinstance(steps, bool) or steps < 0:
        raise ValueError(f"steps={steps!r} must be an integer >= 0")
    if tol < 0 or not math.isfinite(tol):
        raise ValueError(f"tol={tol!r} must be finite and >= 0")
    if patience is not None and (not isinstance(patience, (int, np.integer)) or patience < 1):
        raise ValueError(f"patience={patience!r} must be None or an integer >= 1")
    if loss_tol is not None and not math.isfinite(loss_tol):
        raise ValueError(f"loss_tol={loss_tol!r} must be finite or None")


class _Tracker:
    """Host-side bookkeeping for n starts (n = 1 for a plain fit)."""

    def __init__(self, n, names, tol, patience, loss_tol):
        self.n, self.names = n, names
        self.tol, self.patience, self.loss_tol = tol, patience, loss_tol
        self.loss: list[np.ndarray] = []
        self.params: list[dict] = []
        self.grad_norm: list[dict] = []
        self.wall: list[float] = []
        self.active = np.ones(n, bool)
        self.status = ["max_steps"] * n
        self.message = [""] * n
        self.stop_step = np.full(n, -1)  # number of history entries of each start
        self.best_loss = np.full(n, np.inf)
        self.best_step = np.full(n, -1)
        self.ref_loss = np.full(n, np.inf)  # best loss at the last significant improvement
        self.stall = np.zeros(n, int)
        self.updates = np.zeros(n, int)
        self.best_raw: list[dict | None] = [None] * n
        self.last_finite_raw: list[dict | None] = [None] * n
        self.last_finite_phys: list[dict | None] = [None] * n

    def record(self, k, loss, phys, gnorm, finite, raw, wall, recording):
        self.loss.append(np.where(recording, loss, np.nan))
        self.params.append(phys)
        self.grad_norm.append(gnorm)
        self.wall.append(wall)
        for i in np.flatnonzero(recording & finite):
            if loss[i] < self.best_loss[i]:
                self.best_loss[i] = loss[i]
                self.best_step[i] = k
                self.best_raw[i] = {n: raw[n][i] for n in self.names}
            self.last_finite_raw[i] = {n: raw[n][i] for n in self.names}
            self.last_finite_phys[i] = {n: phys[n][i] for n in self.names}

    _FIELDS = ("active", "stop_step", "best_loss", "best_step", "ref_loss", "stall", "updates")

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The whole state as "history/..." and "tracker/..." arrays (see `save_checkpoint`)."""
        out: dict[str, np.ndarray] = {f"tracker/{f}": np.asarray(getattr(self, f)) for f in
                                      self._FIELDS}  # fmt: skip
        out["history/loss"] = np.asarray(self.loss, float).reshape(len(self.loss), self.n)
        out["history/wall"] = np.asarray(self.wall, float)
        for n in self.names:
            if self.params:
                out[f"history/params/{n}"] = np.stack([np.asarray(p[n]) for p in self.params])
                out[f"history/grad_norm/{n}"] = np.stack([np.asarray(g[n]) for g in self.grad_norm])
            for key, rows in (("best_raw", self.best_raw), ("last_raw", self.last_finite_raw),
                              ("last_phys", self.last_finite_phys)):  # fmt: skip
                ref = next((r[n] for r in rows if r is not None), None)
                if ref is None:
                    continue
                out[f"tracker/{key}/{n}"] = np.stack(
                    [np.asarray(r[n]) if r is not None else np.zeros_like(ref) for r in rows]
                )
        for key, rows in (("best_raw", self.best_raw), ("last_raw", self.last_finite_raw)):
            out[f"tracker/has_{key}"] = np.array([r is not None for r in rows])
        return out

    def restore(self, ck: Mapping[str, Any]) -> None:
        """Load the state written by `to_arrays` (a `load_checkpoint` dict)."""
        t, h = ck["tracker"], ck["history"]
        for f in self._FIELDS:
            setattr(self, f, np.array(t[f]))
        meta = ck.get("meta", {})
        self.status = list(meta.get("tracker_status", self.status))
        self.message = list(meta.get("tracker_message", self.message))
        K = int(np.shape(h["loss"])[0])
        self.loss = [np.asarray(h["loss"][k]) for k in range(K)]
        self.wall = [float(w) for w in h["wall"]]
        self.params = [{n: h["params"][n][k] for n in self.names} for k in range(K)]
        self.grad_norm = [{n: h["grad_norm"][n][k] for n in self.names} for k in range(K)]

        def rows(key, has):
            flags = t.get(f"has_{has}", np.zeros(self.n, bool))
            return [
                {n: t[key][n][i] for n in self.names} if flags[i] else None for i in range(self.n)
            ]

        self.best_raw = rows("best_raw", "best_raw")
        self.last_finite_raw = rows("last_raw", "last_raw")
        self.last_finite_phys = rows("last_phys", "last_raw")

    def update_stopping(self, k, loss, finite, grad_finite, path_msg):
        """After evaluation k of the active starts (whose update was applied if finite)."""
        for i in np.flatnonzero(self.active):
            if not finite[i]:
                bad = [n for n in self.names if not grad_finite[n][i]]
                what = f"loss={loss[i]:.4g}" + (f", non-finite gradient of {bad}" if bad else "")
                self.status[i] = "nonfinite"
                self.message[i] = (
                    f"non-finite loss/grad at step {k} ({what}); "
                    f"last finite params saved to {path_msg}"
                )
                self.active[i] = False
                self.stop_step[i] = k + 1
                continue
            self.updates[i] += 1
            if self.loss_tol is not None and loss[i] <= self.loss_tol:
                self.status[i] = "converged"
                self.message[i] = f"loss {loss[i]:.4g} <= loss_tol {self.loss_tol:g} at step {k}"
                self.active[i] = False
                self.stop_step[i] = k + 1
                continue
            ref = self.ref_loss[i]
            if not np.isfinite(ref) or loss[i] < ref - self.tol * abs(ref):
                self.ref_loss[i] = loss[i]
                self.stall[i] = 0
            else:
                self.stall[i] += 1
                if self.patience is not None and self.stall[i] >= self.patience:
                    self.status[i] = "stalled"
                    self.message[i] = (
                        f"no relative improvement > {self.tol:g} for {self.patience} steps "
                        f"(step {k})"
                    )
                    self.active[i] = False
                    self.stop_step[i] = k + 1

    def result(self, i, batched, initial, cons, wall_s, checkpoint_path) -> FitResult:
        m = int(self.stop_step[i]) if self.stop_step[i] >= 0 else len(self.loss)
        sel = (lambda a: np.asarray(a)[i]) if batched else (lambda a: np.asarray(a)[0])
        hist = History(
            loss=np.array([float(sel(l)) for l in self.loss[:m]]),
            params={n: np.stack([sel(p[n]) for p in self.params[:m]]) for n in self.names},
            grad_norm={
                n: np.array([float(sel(g[n])) for g in self.grad_norm[:m]]) for n in self.names
            },
            wall_s=np.asarray(self.wall[:m], float),
        )
        if self.best_raw[i] is None:  # not even the first evaluation was finite
            best_raw = {n: np.asarray(initial[n]) for n in self.names}
            raw_dict = {n: np.asarray(v) for n, v in to_raw(best_raw, cons).items()}
            params = best_raw
            last = best_raw
        else:
            raw_dict = {n: np.asarray(v) for n, v in self.best_raw[i].items()}
            params = {n: np.asarray(v) for n, v in to_physical(raw_dict, cons).items()}
            last = {n: np.asarray(v) for n, v in self.last_finite_phys[i].items()}
        status = self.status[i]
        msg = self.message[i] or {
            "max_steps": f"reached steps={self.updates[i]}",
        }.get(status, status)
        return FitResult(
            params=params,
            raw=raw_dict,
            loss=float(self.best_loss[i]),
            initial={n: np.asarray(initial[n]) for n in self.names},
            history=hist,
            iterations=int(self.updates[i]),
            wall_s=float(wall_s),
            status=status,
            message=msg,
            best_step=int(self.best_step[i]),
            last_finite=last,
            checkpoint_path=checkpoint_path,
        )


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


def _as_checkpoint(resume):
    if resume is None or isinstance(resume, Mapping):
        return resume
    return load_checkpoint(resume)


def _restore(ck, raw, opt_state, names, n, steps, tr):
    """Raw values, optimizer state and tracker from a `load_checkpoint` dict (for resume=)."""
    meta = ck.get("meta", {})
    saved = meta.get("names")
    if saved is not None and list(saved) != list(names):
        raise ValueError(f"resume: the checkpoint fits {saved}, this fit {names}")
    if meta.get("starts", n) != n:
        raise ValueError(f"resume: the checkpoint has {meta.get('starts')} starts, this fit {n}")
    if "raw" not in ck.get("state", {}) or not ck.get("tracker"):
        raise ValueError("resume: the checkpoint has no loop state (written by an older version?)")
    done = int(ck["step"])
    if done > steps + 1:
        raise ValueError(
            f"resume: the checkpoint is at step {done - 1}, beyond steps={steps}; raise steps"
        )
    new_raw = {}
    for k in names:
        a = np.asarray(ck["state"]["raw"][k])
        if a.shape != tuple(raw[k].shape):
            raise ValueError(
                f"resume: checkpoint value of {k!r} has shape {a.shape}, expected {raw[k].shape}"
            )
        new_raw[k] = jnp.asarray(a, raw[k].dtype)
    opt_state = unpack_tree(ck["opt_state"], opt_state)
    tr.restore(ck)
    return new_raw, opt_state


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


def _postfix(bar, tr, phys, batched):
    if batched:
        i = int(np.argmin(np.where(np.isfinite(tr.best_loss), tr.best_loss, np.inf)))
        bar.set_postfix_str(
            f"best loss={tr.best_loss[i]:.4g} active={int(tr.active.sum())}/{tr.n} "
            f"diverged={tr.status.count('nonfinite')}",
            refresh=False,
        )
        return
    loss = tr.loss[-1][0]
    vals = " ".join(f"{n}={_fmt(phys[n][0])}" for n in tr.names[:6])
    bar.set_postfix_str(f"loss={loss:.4g} {vals}", refresh=False)


def fit_params(
    loss_fn: Callable[..., jax.Array],
    init: Mapping[str, Any],
    constraints: Mapping | None = None,
    *,
    steps: int = 200,
    optimizer: optax.GradientTransformation | None = None,
    learning_rate: float | None = None,
    clip_norm: float = 1.0,
    tol: float = 1e-7,
    patience: int | None = 50,
    loss_tol: float | None = None,
    progress: bool = True,
    callback: Callable[[int, dict], Any] | None = None,
    checkpoint_path: str | Path | None = None,
    checkpoint_every: int | None = None,
    loss_args: tuple = (),
    resume: str | Path | Mapping | None = None,
    stop: Any = None,
) -> FitResult:
    """Minimise `loss_fn(physical_params)` over the named parameters with optax.

    Args:
      loss_fn: a JAX function of a dict name -> physical value (scalar or array) returning a scalar.
        It is jitted once (cached on the function object, constraints and optimizer).
      init: initial physical values, name -> float or array; validated against the constraints.
      constraints: name -> Constraint or spec (see `constraints.make_constraint`); missing names
        are unconstrained.
      steps: maximum number of optimizer updates.
      optimizer: an optax GradientTransformation on raw values. Default:
        `chain(clip_by_global_norm(clip_norm), adam(learning_rate))`.
      learning_rate: for the default optimizer (default 0.05, i.e. about 5% relative steps for
        log-space parameters). Give optimizer= or learning_rate=, not both.
      clip_norm: gradient clipping of the default optimizer.
      tol, patience: stop ("stalled") after `patience` steps without a relative improvement of the
        loss by more than `tol`; patience=None disables.
      loss_tol: stop ("converged") once the loss is <= loss_tol.
      progress: tqdm bar (loss, current values, rate); quiet when stderr is not a terminal.
      callback: `callback(step, info)` with info = {"loss", "params", "grad_norm", "finite"} after
        each step; a truthy return value stops the fit ("stopped").
      checkpoint_path: .npz file (+ .json sidecar) written at the end, on a non-finite stop and
        every `checkpoint_every` steps: raw, physical, best and last finite params, optimizer state.
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
    init_phys = _check_init(init)
    results, _ = _run(
        loss_fn,
        init_phys,
        constraints,
        batched=False,
        n=1,
        steps=steps,
        optimizer=optimizer,
        learning_rate=learning_rate,
        clip_norm=clip_norm,
        tol=tol,
        patience=patience,
        loss_tol=loss_tol,
        progress=progress,
        callback=callback,
        checkpoint_path=checkpoint_path,
        checkpoint_every=checkpoint_every,
        loss_args=tuple(loss_args),
        desc="fit",
        resume=_as_checkpoint(resume),
        stop=stop,
    )
    return results[0]


def _stack_inits(inits) -> tuple[dict[str, jax.Array], int]:
    if isinstance(inits, Mapping):
        stacked = _check_init(inits, "inits")
        sizes = {k: (v.shape[0] if v.ndim else None) for k, v in stacked.items()}
        if any(s is None for s in sizes.values()) or len(set(sizes.values())) != 1:
            raise ValueError(
                "a dict of inits must hold stacked values with one common leading (batch) axis; "
                f"got leading sizes {sizes}"
            )
        return stacked, next(iter(sizes.values()))
    if isinstance(inits, Sequence) and not isinstance(inits, (str, bytes)) and len(inits) > 0:
        dicts = [_check_init(d, f"inits[{i}]") for i, d in enumerate(inits)]
        keys = list(dicts[0])
        for i, d in enumerate(dicts):
            if set(d) != set(keys):
                raise ValueError(f"inits[{i}] has names {sorted(d)}, inits[0] has {sorted(keys)}")
            for k in keys:
                if d[k].shape != dicts[0][k].shape:
                    raise ValueError(
                        f"inits[{i}][{k!r}] has shape {d[k].shape}, inits[0] has "
                        f"{dicts[0][k].shape}"
                    )
        return {k: jnp.stack([d[k] for d in dicts]) for k in keys}, len(dicts)
    raise ValueError(
        f"inits must be a non-empty list of dicts or a dict of stacked arrays, got {inits!r}"
    )


def fit_multistart(
    loss_fn: Callable[..., jax.Array],
    inits,
    constraints: Mapping | None = None,
    *,
    steps: int = 200,
    optimizer: optax.GradientTransformation | None = None,
    learning_rate: float | None = None,
    clip_norm: float = 1.0,
    tol: float = 1e-7,
    patience: int | None = 50,
    loss_tol: float | None = None,
    progress: bool = True,
    callback: Callable[[int, dict], Any] | None = None,
    checkpoint_path: str | Path | None = None,
    checkpoint_every: int | None = None,
    loss_args: tuple = (),
    resume: str | Path | Mapping | None = None,
    stop: Any = None,
    devices: int | Any | None = None,
) -> MultiStartResult:
    """Fit several initial guesses at once (`jax.vmap` over the raw parameters); keep the best.

    Args:
      inits: a list of dicts (same names and shapes) or a dict of arrays stacked on a leading axis.
      Everything else as in `fit_params`; `loss_args` are shared by all starts; the callback
      receives per-start arrays. Each start has its own finite flag and stopping state: a start
      whose loss or gradient becomes non-finite is frozen at its last finite parameters (status
      "nonfinite") and the others carry on unchanged. The checkpoint holds the best start.
      devices: spread the starts over this many devices (or over a given 1-D
        `jax.sharding.Mesh` with axis "batch"): the raw parameters and optimizer states are
        sharded along the start axis (`diffcloth.batch.shard_batch`), `loss_args` replicated, and
        the one jitted step runs each device's starts there. The number of starts must be a
        multiple of the number of devices. None: JAX's default placement (one device).
    Returns:
      MultiStartResult: `.results` (one FitResult per start), `.best_index`, `.best`, `.params`.
    """
    stacked, n = _stack_inits(inits)
    results, wall = _run(
        loss_fn,
        stacked,
        constraints,
        batched=True,
        n=n,
        steps=steps,
        optimizer=optimizer,
        learning_rate=learning_rate,
        clip_norm=clip_norm,
        tol=tol,
        patience=patience,
        loss_tol=loss_tol,
        progress=progress,
        callback=callback,
        checkpoint_path=checkpoint_path,
        checkpoint_every=checkpoint_every,
        loss_args=tuple(loss_args),
        desc=f"fit x{n}",
        devices=devices,
        resume=_as_checkpoint(resume),
        stop=stop,
    )
    losses = np.array([r.loss if np.isfinite(r.loss) else np.inf for r in results])
    return MultiStartResult(results=results, best_index=int(np.argmin(losses)), wall_s=wall)
