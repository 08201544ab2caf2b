"""Parameter transforms: the optimiser works on unconstrained "raw" values, physics on physical.

A constraint maps raw (any real) -> physical (the valid range) with `forward` and back with
`inverse`. `to_physical` / `to_raw` apply them to dicts of named parameters.

    Positive()                 physical = exp(raw)     (log space; the default for stiffness)
    Positive(kind="softplus")  physical = scale * softplus(raw / scale)
    Bounded(lo, hi)            physical = lo + (hi - lo) * sigmoid(raw)
    Identity()                 physical = raw

Overflow guard: raw values far outside the useful range (|raw| > about 80 in float32, 700 in
float64) are smoothly saturated before the exp/softplus/sigmoid, so `to_physical` stays finite
and strictly positive (Positive) for any finite raw value, e.g. raw in [-1e3, 1e3], never NaN.

Example:
    >>> cons = {"stretch": Positive(), "damping": Bounded(0.0, 1.0)}
    >>> raw = to_raw({"stretch": 100.0, "damping": 0.5}, cons)
    >>> round(float(to_physical(raw, cons)["stretch"]), 6)
    100.0
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "Bounded",
    "Constraint",
    "Identity",
    "Positive",
    "make_constraint",
    "make_constraints",
    "to_physical",
    "to_raw",
]


def _float(x) -> jax.Array:
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    return x


def _limits(dtype) -> tuple[float, float]:
    """(start of saturation, saturation level) of the raw value for a float dtype."""
    if jnp.finfo(dtype).bits >= 64:
        return 600.0, 700.0  # exp(+-700) is finite and non-zero in float64
    if jnp.finfo(dtype).bits >= 32:
        return 60.0, 80.0  # exp(+-80) is finite and a normal number in float32
    return 8.0, 10.0  # float16 / bfloat16


def _saturate(raw: jax.Array) -> jax.Array:
    """Identity on [-a, a], smooth (C1) tanh saturation towards +-b outside. Finite grads."""
    a, b = _limits(raw.dtype)
    excess = jnp.abs(raw) - a
    outside = excess > 0
    soft = a + (b - a) * jnp.tanh(jnp.where(outside, excess, 0.0) / (b - a))
    return jnp.where(outside, jnp.sign(raw) * soft, raw)


def _unsaturate(raw: jax.Array) -> jax.Array:
    """Inverse of `_saturate` on (-b, b)."""
    a, b = _limits(raw.dtype)
    excess = jnp.abs(raw) - a
    outside = excess > 0
    y = jnp.clip(jnp.where(outside, excess, 0.0) / (b - a), 0.0, 1.0 - 1e-7)
    return jnp.where(outside, jnp.sign(raw) * (a + (b - a) * jnp.arctanh(y)), raw)


def _concrete(x) -> np.ndarray | None:
    """x as numpy when it is a concrete value (not traced), else None."""
    if isinstance(x, jax.core.Tracer):
        return None
    return np.asarray(x)


class Constraint:
    """Base class: `forward(raw) -> physical`, `inverse(physical) -> raw`, both elementwise."""

    def forward(self, raw):  # pragma: no cover - interface
        raise NotImplementedError

    def inverse(self, physical, name: str = "parameter"):  # pragma: no cover - interface
        raise NotImplementedError


@dataclasses.dataclass(frozen=True)
class Identity(Constraint):
    """No constraint: physical = raw."""

    def forward(self, raw):
        return _float(raw)

    def inverse(self, physical, name: str = "parameter"):
        return _float(physical)


@dataclasses.dataclass(frozen=True)
class Positive(Constraint):
    """physical > lower: kind "log" gives lower + exp(raw), kind "softplus" gives
    lower + scale * softplus(raw / scale).

    Log space suits stiffness-like parameters spanning decades (an Adam step of size lr is a
    relative change of about lr); softplus behaves linearly for large values.
    """

    kind: str = "log"
    scale: float = 1.0
    lower: float = 0.0

    def __post_init__(self):
        if self.kind not in ("log", "softplus"):
            raise ValueError(f"Positive: kind={self.kind!r} is not one of 'log', 'softplus'")
        if not (np.isfinite(self.scale) and self.scale > 0):
            raise ValueError(f"Positive: scale={self.scale!r} must be finite and > 0")
        if not np.isfinite(self.lower):
            raise ValueError(f"Positive: lower={self.lower!r} must be finite")

    def forward(self, raw):
        r = _saturate(_float(raw))
        if self.kind == "log":
            return self.lower + jnp.exp(r)
        # softplus(r) >= exp(r) / 2 for r < 0, so it stays > 0 wherever exp(r) does.
        return self.lower + self.scale * jax.nn.softplus(r)

    def inverse(self, physical, name: str = "parameter"):
        p = _float(physical)
        c = _concrete(p)
        if c is not None and not np.all(np.isfinite(c) & (c > self.lower)):
            raise ValueError(
                f"{name}={c.tolist()} is outside the allowed range ({self.lower}, inf) "
                "of its Positive constraint"
            )
        d = (p - self.lower) / (1.0 if self.kind == "log" else self.scale)
        if self.kind == "log":
            r = jnp.log(d)
        else:  # inverse softplus, stable for large d: d + log(-expm1(-d))
            r = d + jnp.log(-jnp.expm1(-d))
        return _unsaturate(r)


@dataclasses.dataclass(frozen=True)
class Bounded(Constraint):
    """lo < physical < hi through a sigmoid: physical = lo + (hi - lo) * sigmoid(raw)."""

    lo: float
    hi: float

    def __post_init__(self):
        if not (np.isfinite(self.lo) and np.isfinite(self.hi) and self.lo < self.hi):
            raise ValueError(f"Bounded: need finite lo < hi, got lo={self.lo!r}, hi={self.hi!r}")

    def forward(self, raw):
        r = _saturate(_float(raw))
        return self.lo + (self.hi - self.lo) * jax.nn.sigmoid(r)

    def inverse(self, physical, name: str = "parameter"):
        p = _float(physical)
        c = _concrete(p)
        if c is not None and not np.all(np.isfinite(c) & (c > self.lo) & (c < self.hi)):
            raise ValueError(
                f"{name}={c.tolist()} is outside the allowed open range ({self.lo}, {self.hi}) "
                "of its Bounded constraint"
            )
        u = (p - self.lo) / (self.hi - self.lo)
        return _unsaturate(jnp.log(u) - jnp.log1p(-u))


def make_constraint(spec: Any) -> Constraint:
    """A Constraint from a config-friendly spec.

    Accepted: a Constraint; None / "none" / "identity"; "positive" / "log"; "softplus";
    a 2-sequence (lo, hi) or {"lo": .., "hi": ..} for Bounded; {"kind": "softplus", "scale": ..}.
    """
    if isinstance(spec, Constraint):
        return spec
    if spec is None:
        return Identity()
    if isinstance(spec, str):
        key = spec.lower()
        table = {
            "none": Identity(),
            "identity": Identity(),
            "positive": Positive(),
            "log": Positive(),
            "softplus": Positive(kind="softplus"),
        }
        if key not in table:
            raise ValueError(f"constraint {spec!r} is not one of {sorted(table)} or (lo, hi)")
        return table[key]
    if isinstance(spec, Mapping):
        if "lo" in spec or "hi" in spec:
            return Bounded(float(spec["lo"]), float(spec["hi"]))
        kind = spec.get("kind", "log")
        if kind in ("log", "softplus", "positive"):
            return Positive(
                kind="log" if kind == "positive" else kind,
                scale=float(spec.get("scale", 1.0)),
                lower=float(spec.get("lower", 0.0)),
            )
        raise ValueError(f"constraint {dict(spec)!r}: unknown kind {kind!r}")
    if isinstance(spec, (tuple, list)) and len(spec) == 2:
        return Bounded(float(spec[0]), float(spec[1]))
    raise ValueError(f"constraint {spec!r} is not a Constraint, a name, or a (lo, hi) pair")


def make_constraints(names, constraints: Mapping | None) -> dict[str, Constraint]:
    """One Constraint per name (Identity where none is given); unknown names raise ValueError."""
    constraints = dict(constraints or {})
    unknown = sorted(set(constraints) - set(names))
    if unknown:
        raise ValueError(
            f"constraints name unknown parameters {unknown}; the parameters are {sorted(names)}"
        )
    return {n: make_constraint(constraints.get(n)) for n in names}


def to_raw(params: Mapping[str, Any], constraints: Mapping | None = None) -> dict[str, jax.Array]:
    """Physical -> raw for a dict of named parameters. Out-of-range values raise ValueError."""
    cons = make_constraints(list(params), constraints)
    return {n: cons[n].inverse(v, name=n) for n, v in params.items()}


def to_physical(raw: Mapping[str, Any], constraints: Mapping | None = None) -> dict[str, jax.Array]:
    """Raw -> physical for a dict of named parameters. Differentiable; finite for any finite raw."""
    cons = make_constraints(list(raw), constraints)
    return {n: cons[n].forward(v) for n, v in raw.items()}
