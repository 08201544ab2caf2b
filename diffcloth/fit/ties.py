"""Tied parameters: some parameters follow others with a fixed ratio.

    ties = parse_ties({"shear": "stretch", "bend": "1e-4 * stretch"})
    ties.expand({"stretch": 40.0})   # {"stretch": 40.0, "shear": 40.0, "bend": 0.004}

Expressions are parsed with a small grammar, never evaluated as code:

    expr := NAME | NUMBER "*" NAME | NAME "*" NUMBER | NAME "/" NUMBER

or a table {of = "stretch", scale = 1e-4}. The tied parameters are not optimised: the fit sees only
the free ones (one free scale for a whole family), and every evaluation fills in the tied values
before the physics runs. A tied parameter may not be the source of another tie.
"""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Mapping, Sequence
from typing import Any

__all__ = ["Tie", "Ties", "parse_tie", "parse_ties"]

_NAME = r"[A-Za-z_][A-Za-z0-9_]*"
_NUM = r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?"
_FORMS = (
    (re.compile(rf"^\s*({_NAME})\s*$"), lambda m: (m.group(1), 1.0)),
    (re.compile(rf"^\s*({_NUM})\s*\*\s*({_NAME})\s*$"), lambda m: (m.group(2), float(m.group(1)))),
    (re.compile(rf"^\s*({_NAME})\s*\*\s*({_NUM})\s*$"), lambda m: (m.group(1), float(m.group(2)))),
    (
        re.compile(rf"^\s*({_NAME})\s*/\s*({_NUM})\s*$"),
        lambda m: (m.group(1), 1.0 / float(m.group(2))) if float(m.group(2)) != 0 else None,
    ),
)


@dataclasses.dataclass(frozen=True)
class Tie:
    """target = scale * source."""

    target: str
    source: str
    scale: float = 1.0

    def __str__(self) -> str:
        return self.source if self.scale == 1.0 else f"{self.scale:g} * {self.source}"


@dataclasses.dataclass(frozen=True)
class Ties:
    """A set of ties (hashable, so it can key compiled functions)."""

    ties: tuple[Tie, ...] = ()

    @property
    def targets(self) -> tuple[str, ...]:
        return tuple(t.target for t in self.ties)

    @property
    def sources(self) -> tuple[str, ...]:
        return tuple(sorted({t.source for t in self.ties}))

    def __bool__(self) -> bool:
        return bool(self.ties)

    def expand(self, params: Mapping[str, Any]) -> dict[str, Any]:
        """params (free values) plus every tied value (scale * source); differentiable."""
        out = dict(params)
        for t in self.ties:
            out[t.target] = t.scale * params[t.source]
        return out

    def describe(self) -> str:
        return ", ".join(f"{t.target} = {t}" for t in self.ties)


def parse_tie(target: str, spec: Any) -> Tie:
    """One tie from an expression string or a {"of": name, "scale": number} table."""
    where = f"ties.{target}"
    if isinstance(spec, Mapping):
        if set(spec) - {"of", "scale"} or "of" not in spec:
            raise ValueError(f"{where} = {dict(spec)!r}: a table needs 'of' (and optional 'scale')")
        source, scale = spec["of"], spec.get("scale", 1.0)
        if not isinstance(source, str) or not re.fullmatch(_NAME, source):
            raise ValueError(f"{where}: of = {source!r} must be a parameter name")
        if isinstance(scale, bool) or not isinstance(scale, int | float):
            raise ValueError(f"{where}: scale = {scale!r} must be a number")
        return _checked(Tie(target, source, float(scale)), where)
    if not isinstance(spec, str):
        raise ValueError(
            f'{where} = {spec!r} must be an expression such as "stretch" or "1e-4 * stretch", '
            'or a table {of = "stretch", scale = 1e-4}'
        )
    for pattern, build in _FORMS:
        m = pattern.match(spec)
        if m:
            got = build(m)
            if got is None:
                break
            return _checked(Tie(target, got[0], got[1]), where)
    raise ValueError(
        f"{where} = {spec!r} is not of the form NAME, NUMBER * NAME, NAME * NUMBER or NAME / NUMBER"
    )


def _checked(tie: Tie, where: str) -> Tie:
    if not (math.isfinite(tie.scale) and tie.scale != 0):
        raise ValueError(f"{where}: the scale {tie.scale!r} must be finite and non-zero")
    if tie.source == tie.target:
        raise ValueError(f"{where}: a parameter cannot be tied to itself")
    return tie


def parse_ties(spec: Mapping[str, Any] | Ties | None, free: Sequence[str] | None = None) -> Ties:
    """Ties from {target: expression}; checks names against `diffcloth.pipeline.PARAMETERS`.

    With `free` (the names the user asked to fit), every source must be free and no target may be
    the source of another tie. Tied targets listed in `free` are simply not optimised.
    """
    if spec is None:
        return Ties()
    if isinstance(spec, Ties):
        ties = spec
    else:
        if not isinstance(spec, Mapping):
            raise ValueError(f"ties must be a table name -> expression, got {spec!r}")
        ties = Ties(tuple(parse_tie(str(k), v) for k, v in spec.items()))
    from diffcloth import pipeline

    pipeline.check_param_names(list(ties.targets) + list(ties.sources))
    chained = sorted(set(ties.targets) & set(ties.sources))
    if chained:
        raise ValueError(f"ties: {chained} are tied and also the source of another tie")
    if free is not None:
        missing = [s for s in ties.sources if s not in free]
        if missing:
            raise ValueError(
                f"ties: the source parameter(s) {missing} must be free (listed in free = "
                f"{list(free)})"
            )
    return ties
