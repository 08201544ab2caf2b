"""What method "auto" of the front door (`diffcloth.fit.fit`) decides, and the hints of a stall.

The recipe that fits footage with contact (docs/fit.md, benchmarks/cross_engine) has three parts
that a plain local Levenberg-Marquardt run lacks; "auto" does each when a measurable rule says so:

1. float64 when the scene has contact (a sphere, a plane, a rigid body): contact and folding
   amplify float32 round-off until the loss jumps at the scale LM probes (the cross-engine
   drape's loss moves 1 % for a 1e-6 relative change of the stiffness). JAX's x64 is switched on
   for the fit only (`jax.enable_x64` context) and the scene, targets and values are cast.
2. A scan before the local method when the start is far: the loss (forward only, on the full
   resolution over the first half of the frames, as the recipe scans) at the start value times
   2^-4 .. 2^4 of up to `MAX_SCANNED` positive physical scalars, one after another (air
   resistance first: it alone sets the free fall; then the stiffnesses). The fit moves to the
   best grid point when the current loss lies in the upper half of the scan's range (above
   low + `SCAN_RISE` (high - low): "far"); otherwise the start stays ("near"). A far start
   runs the staged recipe from the start (`scene_fit.recipe_stages`, damped LM), or, with the
   caller's own `stages`, LM from the best grid point.
3. The coarse-to-fine stages of the schedule (pyramid levels, a growing frame window).

`hints` reads a finished fit and names the knob to turn when it stalled.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "LARGE_RESIDUAL",
    "MAX_SCANNED",
    "SCAN_FACTORS",
    "SCAN_RISE",
    "cast_floats",
    "has_contact",
    "hints",
    "scan_candidates",
    "scan_start",
]

SCAN_FACTORS = tuple(float(f) for f in 2.0 ** np.arange(-4, 5))  # x 1/16 .. 16, 9 points
SCAN_RISE = 0.5  # "far": the start's loss is in the upper half of the scan's range
MAX_SCANNED = 3
LARGE_RESIDUAL = 0.05  # RMS (l2, pyramid) or mean (l1) pixel error, fraction of full scale
#: scan order: air resistance (sets the free fall alone), then stiffnesses, then the rest
_FIRST = ("air_damping", "drag_normal", "drag", "drag_tangent")
_STIFF = ("k_struct", "stretch", "stretch_warp", "stretch_weft", "k_shear", "shear", "bend",
          "bend_warp", "bend_weft", "k_flex")  # fmt: skip


def has_contact(scene) -> bool:
    """Whether the cloth can touch something: a sphere or plane collider or a rigid body."""
    col = scene.colliders
    n = 0
    for attr in ("num_spheres", "num_planes"):
        try:
            n += int(getattr(col, attr))
        except (AttributeError, TypeError):
            pass
    return n > 0 or scene.spheres is not None or bool(scene.bodies)


def cast_floats(tree, dtype):
    """`tree` with every floating array leaf cast to `dtype` (integers and statics unchanged)."""

    def cast(a):
        if hasattr(a, "dtype") and jnp.issubdtype(a.dtype, jnp.floating):
            return jnp.asarray(a, dtype)
        return a

    return jax.tree_util.tree_map(cast, tree)


def scan_candidates(init: Mapping[str, Any], constraints: Mapping[str, Any]) -> list[str]:
    """The free names method "auto" scans: positive (log-space) physical scalars, air resistance
    first, then stiffnesses, then the rest; at most MAX_SCANNED."""
    from diffcloth import pipeline
    from diffcloth.fit.constraints import Positive

    ok = [
        n
        for n in init
        if np.size(init[n]) == 1
        and isinstance(constraints.get(n), Positive)
        and pipeline.PARAMETERS.get(n, ("",))[0] in ("material", "sim", "bodies")
    ]
    rank = {n: i for i, n in enumerate(_FIRST + _STIFF)}
    return sorted(ok, key=lambda n: rank.get(n, len(rank)))[:MAX_SCANNED]


@functools.lru_cache(maxsize=16)
def _loss(residual_fn):
    return jax.jit(lambda p, la, sa: jnp.sum(jnp.square(residual_fn(p, *la, *sa))))


def scan_start(
    residual_fn,
    init: Mapping[str, Any],
    names: Sequence[str] | Mapping[str, Sequence[float]],
    loss_args: tuple,
    stage_args: tuple,
    *,
    rise: float | None = SCAN_RISE,
) -> tuple[dict[str, np.ndarray], dict]:
    """Scan each name in turn (value x factor, the others at the best so far) and return the
    start and a record {"initial_loss", "loss", "far", "scans": [{name, profile, best, moved}]}.

    names: a list (factors SCAN_FACTORS) or {name: factors}. rise: move to the best grid point
    only when the current loss lies above low + rise * (high - low) of the scan's finite losses
    (the upper half for 0.5): a rule blind to a constant offset of the loss, such as footage
    pixels the scene does not model (None: always move to a lower grid point)."""
    loss = _loss(residual_fn)
    spec = dict(names) if isinstance(names, Mapping) else {n: SCAN_FACTORS for n in names}
    current = {k: np.asarray(v) for k, v in init.items()}

    def at(p):
        v = float(loss({k: jnp.asarray(x) for k, x in p.items()}, loss_args, stage_args))
        return v if np.isfinite(v) else np.inf

    start_loss = best_loss = at(current)
    scans = []
    for name, factors in spec.items():
        profile = []
        for f in factors:
            value = current[name] * float(f)
            profile.append((float(value), at({**current, name: value})))
        value, low = min(profile, key=lambda vl: vl[1])
        high = max([v for _, v in profile if np.isfinite(v)] + [best_loss])
        moved = low < best_loss and (rise is None or best_loss - low > rise * (high - low))
        if moved:
            current[name] = np.asarray(value, current[name].dtype)
            best_loss = low
        edge = value in (profile[0][0], profile[-1][0])
        scans.append(dict(name=name, profile=profile, best=value, moved=bool(moved), edge=edge))
    far = any(s["moved"] for s in scans)
    return current, dict(initial_loss=start_loss, loss=best_loss, far=far, scans=scans)


def hints(
    result, *, cons, auto: Mapping | None, x64: bool, contact: bool, ident=None, loss=None
) -> list[str]:
    """Knobs to turn, one line each, for a fit that did not converge cleanly.

    auto: the front door's record (scan, x64); ident: an `Identifiability` at the fitted values,
    or None; loss: the fit's loss kind ("l2", "pyramid", "l1"; None: no residual check). Empty
    when the fit converged away from every bound with a residual below LARGE_RESIDUAL."""
    from diffcloth.fit.constraints import Bounded, Positive

    out = []
    stalled = result.status in ("stalled", "max_steps")
    scans = (auto or {}).get("scans") or []
    for name, c in cons.items():
        v = np.asarray(result.params.get(name, np.nan), float)
        v0 = np.asarray(result.initial.get(name, np.nan), float)
        if isinstance(c, Bounded):
            span = float(c.hi) - float(c.lo)
            t = (v - float(c.lo)) / span
            if np.any(t < 1e-3) or np.any(t > 1 - 1e-3):
                out.append(
                    f"parameter at a bound: {name} = {np.round(v, 6).tolist()} at its range "
                    f"[{float(c.lo):g}, {float(c.hi):g}]: widen constraints={{{name!r}: (lo, hi)}} "
                    "or fix it"
                )
        elif isinstance(c, Positive) and np.all(v0 > 0) and np.all(v > 0):
            ratio = float(np.max(np.abs(np.log(v / v0))))
            if ratio > np.log(100.0):
                out.append(
                    f"parameter ran off: {name} moved {np.exp(ratio):.0f}x from its start: the "
                    "loss is flat in it; fix it, tie it (ties=) or start closer (init=)"
                )
    for s in scans if stalled else []:  # the LM may well go on past the grid's end
        if s["moved"] and s["edge"]:
            out.append(
                f"scan edge: {s['name']}'s best grid point {s['best']:.4g} is the end of the scan:"
                f" widen it, scan={{{s['name']!r}: [...]}}, or start closer (init=)"
            )
    if loss in ("l2", "pyramid", "l1") and np.isfinite(result.loss):
        rms = float(np.sqrt(result.loss)) if loss != "l1" else float(result.loss)
        if rms > LARGE_RESIDUAL:
            out.append(
                f"large residual: pixel error {rms:.2f} of full scale at the fitted values: the "
                "scene does not explain the images (a floor, shadows, lights, background or "
                "camera it lacks: add them, or fit light_*, background, exposure), or the fit "
                "is in a wrong basin (scan=, method='staged')"
            )
    if ident is not None:
        for a, b, r in ident.confounded[:2]:
            out.append(f"confounded pair: {a} and {b} (correlation {r:+.2f}): tie or fix one")
    if stalled:
        if not x64 and contact:
            out.append("float32 noise: the scene has contact; use x64=True (float64)")
        moved_little = _moved_little(result)
        if not scans and moved_little:
            out.append(
                "start far: the fit barely moved from its start; set scan='auto' (or "
                "scan={name: factors}), method='staged', or start closer (init=)"
            )
        elif scans and moved_little:
            out.append(
                "start far: the scan found no basin; widen scan= factors, scan another parameter, "
                "or fit in stages (method='staged', stages=[...])"
            )
        if result.status == "max_steps":
            out.append(f"not converged: ran all {result.iterations} steps; raise steps=")
        elif not out:
            out.append("stalled: raise lm_patience= / patience=, or loosen lm_xtol= / tol=")
    return out


def _moved_little(result) -> bool:
    """True when every fitted value is within 5 % of its start (log space)."""
    for k, v0 in result.initial.items():
        v = np.asarray(result.params.get(k, v0), float)
        v0 = np.asarray(v0, float)
        if np.any(v0 <= 0) or np.any(v <= 0):
            if np.any(np.abs(v - v0) > 0.05 * (np.abs(v0) + 1e-12)):
                return False
        elif np.any(np.abs(np.log(v / v0)) > np.log(1.05)):
            return False
    return True
