"""Rigid-body sections of the schema: [[bodies]] and [coupling] (docs/config.md)."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

from diffcloth.config._fields import ConfigError, check_keys, get_bool


@dataclasses.dataclass(frozen=True)
class BodiesConfig:
    """[[bodies]] entries (validated tables, built by `physics.rigid.bodies_from_config`) and
    [coupling] two_way (whether the cloth's contact impulses act back on the bodies)."""

    entries: tuple[Mapping[str, Any], ...] = ()
    two_way: bool = True


def parse_bodies_section(data: Mapping[str, Any]) -> BodiesConfig:
    """Validate [[bodies]] (every key and range, by building them once) and [coupling]."""
    from diffcloth.physics.rigid import bodies_from_config

    entries = data.get("bodies", [])
    if not isinstance(entries, list):
        raise ConfigError("[[bodies]] must be an array of tables ([[bodies]] per body)")
    try:
        bodies_from_config(entries)
    except (ValueError, TypeError) as err:
        raise ConfigError(f"[[bodies]] {err}") from None
    t = data.get("coupling", {})
    if not isinstance(t, Mapping):
        raise ConfigError("[coupling] must be a table")
    check_keys(t, ("two_way",), "coupling")
    return BodiesConfig(
        entries=tuple(dict(e) for e in entries),
        two_way=get_bool(t, "two_way", True, where="coupling"),
    )
