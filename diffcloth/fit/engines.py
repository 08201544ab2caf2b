"""The fitting engines under the front door `diffcloth.fit.fit`, for functions that are not a scene.

`diffcloth.fit.fit(scene, targets, free=..., method=...)` is the one entry point for a scene: it
builds the residuals or the loss from the scene and the targets, picks the engine and its
schedule, and runs it. Reach for an engine directly when the model is not a diffcloth scene, or
the loss is your own (the footage loss of `diffcloth.fit.footage`, a loss over several scenes):
each takes a JAX function of a dict name -> physical value and the initial values.

    from diffcloth.fit import engines
    result = engines.lm(residual_fn, {"k": 1.0}, {"k": "positive"}, loss_args=(data,))

- `lm(residual_fn, init, constraints, *, loss_args, stages, settings, ...)`: Levenberg-Marquardt
  on a residual vector (optimistix; forward-mode Jacobians in the raw space), for a handful of
  parameters. The front door's method "lm".
- `lm_multistart(residual_fn, inits, ...)`: several starts at once (vmap), the best kept.
- `adam(loss_fn, init, constraints, *, loss_args, settings, ...)`: the optax loop on a scalar
  loss, for many parameters or a loss that is not a sum of squares. The front door's "adam".
- `adam_multistart(loss_fn, inits, ...)`: several starts at once, sharded over devices.
- `staged(residual_fn, init, constraints, *, stages=[ParamStage(...)], ...)`: LM stage after
  stage, each with its own free set, scan and arguments. The front door's "staged".

They were `fit_lm`, `fit_lm_multistart`, `fit_params`, `fit_multistart` and `fit_staged` in
`diffcloth.fit`; those names still work there, with a DeprecationWarning naming these.
"""

from __future__ import annotations

from diffcloth.fit.lm import fit_lm as lm
from diffcloth.fit.lm import fit_lm_multistart as lm_multistart
from diffcloth.fit.loop import fit_multistart as adam_multistart
from diffcloth.fit.loop import fit_params as adam
from diffcloth.fit.staged import ParamStage, StagedResult
from diffcloth.fit.staged import fit_staged as staged

__all__ = [
    "ParamStage",
    "StagedResult",
    "adam",
    "adam_multistart",
    "lm",
    "lm_multistart",
    "staged",
]

#: the names `diffcloth.fit` used to export -> their engine here
RENAMED = {
    "fit_lm": "lm",
    "fit_lm_multistart": "lm_multistart",
    "fit_params": "adam",
    "fit_multistart": "adam_multistart",
    "fit_staged": "staged",
}
