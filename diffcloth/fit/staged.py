"""Coarse to fine in the parameters: fit the parameters that act first on the frames they act in.

Footage of cloth falling onto a collider is a chain: air damping alone sets the free fall, the
stiffnesses only show once the cloth meets the sphere, and a contact or fold bifurcation makes the
loss over a stiffness cliff-like far from the truth. One Levenberg-Marquardt run over every
parameter and every frame then stalls on the first cliff. The cure is a sequence of stages, each
warm-started from the previous one:

    stages = [
        ParamStage(free=("air_damping",), stage_args=[(early_window,)]),
        ParamStage(free=("k_struct", "air_damping"), scan={"k_struct": 2.0 ** np.arange(-4, 5)},
                   stage_args=[(half_window,), (all_frames,)]),
    ]
    result = fit_staged(residual_fn, init, constraints, stages=stages, loss_args=(...,), ties=ties)

A stage fits only its `free` parameters (the others are held at their current values, passed to
the residual as jit arguments, so a stage's compiled step is reused whenever the same free set
comes back). `scan` first evaluates the loss (forward only) at the current value times each
factor of one parameter (its tied followers move with it) and starts the stage from the best
grid point: a global look along one direction before the local solver. `stage_args` are the
LM's own coarse-to-fine stages (e.g. frame-window and pyramid weights, as `fit_lm`), and
`loss_args` may be replaced per stage (e.g. a scene that simulates only the early frames).
"""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth.fit.ties import Ties, parse_ties

__all__ = ["ParamStage", "StagedResult", "fit_staged"]


@dataclasses.dataclass(frozen=True)
class ParamStage:
    """One stage of a staged fit.

    free: names fitted in this stage (a subset of the fit's free names).
    stage_args: LM sub-stages, a list of extra residual-argument tuples (None: one, no extras).
    scan: {name: factors}: before the LM, evaluate the loss at value * factor for each factor
      (name must be free here) and start from the best; factors must include 1 to keep the
      current value in the running.
    loss_args: replaces the fit's loss_args for this stage (None: keep them).
    steps: LM step budget of this stage (None: the settings' steps).
    name: for logs and the result.
    """

    free: tuple[str, ...]
    stage_args: Sequence[tuple] | None = None
    scan: Mapping[str, Sequence[float]] | None = None
    loss_args: tuple | None = None
    steps: int | None = None
    name: str = ""

    def __post_init__(self):
        object.__setattr__(self, "free", tuple(self.free))
        if not self.free:
            raise ValueError("ParamStage: free must name at least one parameter")
        if self.scan is not None:
            if len(self.scan) != 1:
                raise ValueError(f"ParamStage.scan: one parameter at a time, got {list(self.scan)}")
            ((name, factors),) = self.scan.items()
            if name not in self.free:
                raise ValueError(f"ParamStage.scan: {name!r} is not free in this stage {self.free}")
            f = np.asarray(factors, float)
            if f.ndim != 1 or f.size < 2 or not np.all(np.isfinite(f)) or np.any(f <= 0):
                raise ValueError(
                    f"ParamStage.scan[{name!r}]: factors must be >= 2 finite positive numbers"
                )
        if self.steps is not None and (not isinstance(self.steps, int) or self.steps < 1):
            raise ValueError(f"ParamStage.steps={self.steps!r} must be a positive integer")


@dataclasses.dataclass
class StagedResult:
    """params: physical values of every fitted parameter (tied ones included) after the last
    stage. stages: one dict per stage (name, free, scan profile, LM status, loss, evaluations,
    wall_s, params). results: the `FitResult` of each stage's LM run."""

    params: dict[str, np.ndarray]
    loss: float
    status: str
    stages: list[dict]
    results: list
    wall_s: float
    evaluations: int


@dataclasses.dataclass(frozen=True, eq=False)
class _HeldResidual:
    """residual_fn with the held parameters passed as the first loss argument (a dict of
    arrays): one compiled LM step per (residual_fn, free set), whatever the held values."""

    fn: Callable[..., jax.Array]
    ties: Ties

    def __call__(self, params, held, *args):
        return self.fn(self.ties.expand({**held, **params}), *args)


_HELD: dict[tuple, _HeldResidual] = {}


def _held_residual(fn, ties: Ties, free: tuple[str, ...]) -> _HeldResidual:
    key = (fn, ties, free)
    if key not in _HELD:
        _HELD[key] = _HeldResidual(fn, ties)
    return _HELD[key]


@functools.lru_cache(maxsize=16)
def _compiled_loss(residual):
    return jax.jit(lambda p, h, la, sa: jnp.sum(jnp.square(residual(p, h, *la, *sa))))


def _scan(residual, name, factors, current, held, loss_args, stage_args, dtype):
    """Loss (sum of squares, forward only) along `name` times each factor; returns
    [(value, loss)] with non-finite losses as inf."""
    loss = _compiled_loss(residual)
    out = []
    for f in factors:
        p = {k: jnp.asarray(v, dtype) for k, v in current.items()}
        p[name] = jnp.asarray(current[name] * f, dtype)
        value = float(loss(p, held, tuple(loss_args), tuple(stage_args)))
        out.append((float(current[name] * f), value if np.isfinite(value) else np.inf))
    return out


def fit_staged(
    residual_fn: Callable[..., jax.Array],
    init: Mapping[str, Any],
    constraints: Mapping | None = None,
    *,
    stages: Sequence[ParamStage],
    loss_args: tuple = (),
    ties: Mapping[str, Any] | Ties | None = None,
    settings=None,
    log: Callable[[dict], Any] | None = None,
) -> StagedResult:
    """Fit `init`'s parameters stage by stage (see the module docstring).

    Args:
      residual_fn: `residual_fn(params, *loss_args, *stage_args)` -> residuals; `params` holds
        every parameter of `init` and every tied one (physical values).
      init: starting physical values of every free (untied) parameter.
      constraints: as in `fit_lm` (name -> constraint); only the free names of a stage are used.
      stages: the `ParamStage`s, run in order.
      ties: tied parameters (`diffcloth.fit.ties`): their sources must be in `init`.
      settings: `diffcloth.fit.settings.FitSettings` of each stage's LM (steps, tolerances).
      log: called with one dict per stage when it ends.
    Returns:
      StagedResult.
    """
    from diffcloth.fit.lm import fit_lm
    from diffcloth.fit.settings import FitSettings

    if not stages:
        raise ValueError("fit_staged: give at least one ParamStage")
    ties = parse_ties(ties, list(init)) if not isinstance(ties, Ties) else ties
    unknown = sorted({n for st in stages for n in st.free} - set(init))
    if unknown:
        raise ValueError(f"fit_staged: stage parameters {unknown} are not in init {sorted(init)}")
    settings = settings or FitSettings(method="lm", progress=False)
    constraints = dict(constraints or {})
    current = {k: np.asarray(v) for k, v in init.items()}
    dtype = jnp.result_type(*[jnp.asarray(v) for v in current.values()])
    t0 = time.perf_counter()
    logs, results, evaluations = [], [], 0
    status, loss = "max_steps", float("nan")
    for i, st in enumerate(stages):
        t = time.perf_counter()
        residual = _held_residual(residual_fn, ties, st.free)
        held = {k: jnp.asarray(v, dtype) for k, v in current.items() if k not in st.free}
        largs = tuple(loss_args if st.loss_args is None else st.loss_args)
        sargs = [tuple(a) for a in (st.stage_args or [()])]
        row: dict[str, Any] = {"stage": i, "name": st.name or f"stage {i + 1}", "free": st.free}
        if st.scan:
            ((name, factors),) = st.scan.items()
            profile = _scan(residual, name, factors, {k: current[k] for k in st.free}, held,
                            largs, sargs[0], dtype)  # fmt: skip
            best = min(profile, key=lambda vl: vl[1])
            current[name] = np.asarray(best[0], current[name].dtype)
            row["scan"] = {"name": name, "profile": profile, "best": best[0]}
            evaluations += len(profile)
        stage_settings = settings
        if st.steps is not None:
            stage_settings = dataclasses.replace(
                settings, steps=st.steps, lm_stage_steps=min(settings.lm_stage_steps, st.steps)
            )
        result = fit_lm(
            residual,
            {k: current[k] for k in st.free},
            {k: constraints[k] for k in st.free if k in constraints},
            loss_args=(held, *largs),
            stages=sargs,
            settings=stage_settings,
        )
        current.update({k: np.asarray(v) for k, v in result.params.items()})
        results.append(result)
        evaluations += int(result.evaluations or 0)
        status, loss = result.status, float(result.loss)
        row.update(status=status, loss=loss, evaluations=result.evaluations,
                   wall_s=round(time.perf_counter() - t, 2),
                   params={k: float(np.asarray(v)) for k, v in current.items()})  # fmt: skip
        logs.append(row)
        if log is not None:
            log(row)
        if status == "nonfinite":
            break
    return StagedResult(
        params=ties.expand(current),
        loss=loss,
        status=status,
        stages=logs,
        results=results,
        wall_s=time.perf_counter() - t0,
        evaluations=evaluations,
    )
