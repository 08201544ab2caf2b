"""Shared parsing helpers of the config schema: `ConfigError` and typed getters that name the
section, the key, the bad value and the allowed range."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

_MISSING = object()


class ConfigError(ValueError):
    """A config value or key is not allowed; the message names the key and the allowed range."""


# ----------------------------------------------------------------------------- reusable helpers


def check_keys(table: Mapping[str, Any], allowed: Iterable[str], where: str) -> None:
    """Raise ConfigError for any key of `table` not in `allowed` (names the key and the allowed)."""
    allowed = tuple(allowed)
    if not isinstance(table, Mapping):
        raise ConfigError(f"[{where}] must be a table, got {type(table).__name__}")
    for key in table:
        if key not in allowed:
            raise ConfigError(
                f"[{where}] unknown key {key!r}; allowed keys: {', '.join(sorted(allowed))}"
            )


def _range_text(lo, hi, lo_inclusive, hi_inclusive) -> str:
    left = "[" if lo_inclusive and lo is not None else "("
    right = "]" if hi_inclusive and hi is not None else ")"
    return f"{left}{'-inf' if lo is None else lo}, {'inf' if hi is None else hi}{right}"


def get_number(
    table: Mapping[str, Any],
    key: str,
    default=_MISSING,
    *,
    where: str,
    lo: float | None = None,
    hi: float | None = None,
    lo_inclusive: bool = True,
    hi_inclusive: bool = True,
    integer: bool = False,
):
    """table[key] (or default) as a finite float/int within the range; ConfigError otherwise."""
    if key not in table:
        if default is _MISSING:
            raise ConfigError(f"[{where}] missing required key {key!r}")
        return default
    value = table[key]
    rng = _range_text(lo, hi, lo_inclusive, hi_inclusive)
    kind = "an integer" if integer else "a number"
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ConfigError(f"[{where}] {key} = {value!r} must be {kind} in {rng}")
    if integer and not isinstance(value, int):
        raise ConfigError(f"[{where}] {key} = {value!r} must be an integer in {rng}")
    ok = math.isfinite(value)
    if ok and lo is not None:
        ok = value >= lo if lo_inclusive else value > lo
    if ok and hi is not None:
        ok = value <= hi if hi_inclusive else value < hi
    if not ok:
        raise ConfigError(f"[{where}] {key} = {value!r} is out of range; allowed range {rng}")
    return int(value) if integer else float(value)


def get_vec3(table: Mapping[str, Any], key: str, default=_MISSING, *, where: str):
    """table[key] as a tuple of 3 finite floats."""
    if key not in table:
        if default is _MISSING:
            raise ConfigError(f"[{where}] missing required key {key!r}")
        return tuple(float(v) for v in default)
    value = table[key]
    if (
        not isinstance(value, list | tuple)
        or len(value) != 3
        or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
        or not all(math.isfinite(v) for v in value)
    ):
        raise ConfigError(f"[{where}] {key} = {value!r} must be a list of 3 finite numbers")
    return tuple(float(v) for v in value)


def get_choice(table: Mapping[str, Any], key: str, default, choices: Iterable[str], *, where: str):
    """table[key] (or default), which must be one of `choices`."""
    choices = tuple(choices)
    value = table.get(key, default)
    if value not in choices:
        raise ConfigError(f"[{where}] {key} = {value!r}; allowed values: {', '.join(choices)}")
    return value


def get_bool(table: Mapping[str, Any], key: str, default: bool, *, where: str) -> bool:
    """table[key] (or default), which must be true or false."""
    value = table.get(key, default)
    if not isinstance(value, bool):
        raise ConfigError(f"[{where}] {key} = {value!r} must be true or false")
    return value


def get_table(table: Mapping[str, Any], key: str, *, where: str) -> Mapping[str, Any]:
    """table[key] as a table ({} when absent)."""
    value = table.get(key, {})
    if not isinstance(value, Mapping):
        raise ConfigError(f"[{where}] {key} must be a table, got {value!r}")
    return value


def array_of_tables(data: Mapping[str, Any], key: str) -> list:
    """data[key] as a list of tables ([] when absent)."""
    items = data.get(key, [])
    if not isinstance(items, list) or not all(isinstance(i, Mapping) for i in items):
        raise ConfigError(f"[[{key}]] must be an array of tables ([[{key}]] per entry)")
    return items


def dataclass_keys(cls) -> tuple[str, ...]:
    """The field names of a settings dataclass: the keys its section allows."""
    import dataclasses

    return tuple(f.name for f in dataclasses.fields(cls))
