"""Every number of a validated Config, checked against the float dtype the run uses.

`parse_config` checks values as Python floats (float64); `check_config_dtype(config, dtype)` then
checks each of them in the run's dtype (`diffcloth.representable`): finite there, and 0 or of a
normal magnitude. `build_physics` (and so `build_scene`) runs it first, then checks the derived
physics quantities (node masses, rest lengths, spring weights, the substep) the same way, so a
ConfigError names the key (or the keys that make the quantity) before anything is compiled.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Mapping
from typing import Any

from diffcloth.config._fields import ConfigError
from diffcloth.representable import check_physics, check_representable, run_dtype

__all__ = ["check_config_dtype", "check_physics_dtype", "config_numbers"]

_SKIP = {"sections", "path"}


def _is_number(v, raw: bool) -> bool:
    if isinstance(v, bool):
        return False
    # typed settings: ints are counts and sizes (exact in Python); raw user tables: any number
    return isinstance(v, float) or (raw and isinstance(v, int))


def _walk(where: str, key: str, value, raw: bool) -> Iterator[tuple[str, str, Any]]:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        for f in dataclasses.fields(value):
            sub = getattr(value, f.name)
            if dataclasses.is_dataclass(sub) or (
                isinstance(sub, tuple) and sub and dataclasses.is_dataclass(sub[0])
            ):
                yield from _walk(f"{where}.{f.name}", f.name, sub, raw)
            else:
                yield from _walk(where, f.name, sub, raw)
    elif isinstance(value, Mapping):
        for k, v in value.items():
            yield from _walk(where, str(k), v, True)
    elif isinstance(value, (tuple, list)):
        if value and all(_is_number(v, True) for v in value):  # a vector: shown whole
            yield where, key, list(value)
        elif value and all(dataclasses.is_dataclass(v) or isinstance(v, Mapping) for v in value):
            for i, v in enumerate(value):
                yield from _walk(f"{where} #{i}", key, v, raw)
        else:
            for v in value:
                yield from _walk(where, key, v, raw)
    elif hasattr(value, "dtype") and hasattr(value, "shape"):  # [truth] / [fit.initial] arrays
        yield where, key, value
    elif _is_number(value, raw):
        yield where, key, value


def config_numbers(config) -> Iterator[tuple[str, str, Any]]:
    """(section, key, value) for every number of a Config (array-of-table entries as
    "spheres #0"; [fit.initial] and [truth] values as arrays)."""
    for f in dataclasses.fields(config):
        if f.name in _SKIP:
            continue
        value = getattr(config, f.name)
        if f.name == "fit" and value is not None:
            for g in dataclasses.fields(value):
                sub = getattr(value, g.name)
                section = {"initial": "fit.initial", "truth": "truth"}.get(g.name, "fit")
                if section == "fit":
                    yield from _walk("fit", g.name, sub, False)
                else:
                    for name, v in sub.items():
                        yield section, name, v
            continue
        if f.name == "bodies":
            for i, entry in enumerate(value.entries):
                yield from _walk(f"bodies #{i}", "", entry, True)
            continue
        yield from _walk(f.name, f.name, value, f.name == "appearance")


def _prefix(config) -> str:
    return f"{config.path}: " if getattr(config, "path", None) else ""


def check_config_dtype(config, dtype=None) -> None:
    """ConfigError naming [section] key, the value and the allowed magnitudes for any number of
    `config` that overflows, or underflows to 0 or a subnormal, in `dtype` (default: the run's,
    float64 when JAX's x64 is on, else float32)."""
    dtype = run_dtype(dtype)
    for where, key, value in config_numbers(config):
        try:
            check_representable(f"[{where}] {key}", value, dtype)
        except ValueError as err:
            raise ConfigError(f"{_prefix(config)}{err}") from None


def check_physics_dtype(config, net, sim, material) -> None:
    """The derived physics quantities of a built config (see `representable.check_physics`),
    ConfigError naming the keys that make them."""
    density = "[material] density" if config.material.model == "continuum" else (
        "[material] density (with mass_lumping)"
    )  # fmt: skip
    names = {
        "net": "[net] rows, cols, width, height, center",
        "mass": f"[net] width, height, rows, cols and {density}",
        "substep": "[sim] dt and num_substeps",
    }
    try:
        check_physics(net, sim, material, names=names)
    except ValueError as err:
        raise ConfigError(f"{_prefix(config)}{err}") from None
