"""Results of the fitting loops: `History`, `FitResult`, `MultiStartResult`, and the checks of
initial values shared by the Adam loop (`diffcloth.fit.loop`) and LM (`diffcloth.fit.lm`)."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["STATUSES", "FitResult", "History", "MultiStartResult", "best_of"]

STATUSES = ("max_steps", "converged", "stalled", "stopped", "nonfinite", "interrupted")


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
    method: "adam", "lm" (`diffcloth.fit.lm`) or "staged". evaluations: loss + derivative
    evaluations. auto: what the front door's rules decided (`diffcloth.fit.auto`: x64, the scans
    and whether the start was far). hints: the knobs to turn when the fit stalled (one line each,
    also in `summary()`).
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
    auto: dict | None = None
    hints: list[str] = dataclasses.field(default_factory=list)

    @property
    def ok(self) -> bool:
        """False when the fit stopped on a non-finite loss or gradient."""
        return self.status != "nonfinite"

    def summary(self) -> str:
        vals = ", ".join(f"{k}={_fmt(v)}" for k, v in self.params.items())
        text = (
            f"{self.status}: loss {self.loss:.4g} after {self.iterations} steps "
            f"in {self.wall_s:.1f} s; {vals}"
        )
        return "".join([text] + [f"\n  hint: {h}" for h in self.hints])


@dataclasses.dataclass
class MultiStartResult:
    """Outcome of `engines.adam_multistart` / `engines.lm_multistart`: one FitResult per start
    and the index of the best one."""

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


def best_of(results: list[FitResult], wall_s: float) -> MultiStartResult:
    """The MultiStartResult of per-start results: the lowest finite final loss wins."""
    losses = np.array([r.loss if np.isfinite(r.loss) else np.inf for r in results])
    return MultiStartResult(results=results, best_index=int(np.argmin(losses)), wall_s=wall_s)


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
