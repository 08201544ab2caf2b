"""TOML scene configs -> validated frozen dataclasses (see docs/config.md for the schema).

Physics sections ([net], [material], [sim], [[spheres]], [[planes]]) are validated here. The later
sections ([camera], [cameras], [lights], [render], [fit], [truth], [[bodies]], [output]) are passed
through unvalidated in `Config.sections`, for the stages that own them; they can validate with the
helpers below (`check_keys`, `get_number`, `get_vec3`, `get_choice`), which raise `ConfigError`
naming the key, the bad value and the allowed range.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
import types
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from diffcloth.physics.material import MATERIAL_FIELDS, material_range
from diffcloth.physics.net import PIN_PRESETS
from diffcloth.physics.state import INTEGRATORS

PASSTHROUGH_SECTIONS = (
    "camera", "cameras", "lights", "render", "appearance", "fit", "truth", "bodies", "coupling",
    "output",
)
PHYSICS_SECTIONS = ("net", "material", "sim", "spheres", "planes")

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


# ----------------------------------------------------------------------------- physics sections


@dataclasses.dataclass(frozen=True)
class NetConfig:
    """[net]: a rows x cols grid of size (width, height) m, centred at `center`."""

    rows: int = 10
    cols: int = 13
    width: float = 1.2
    height: float = 0.9
    center: tuple[float, float, float] = (0.0, 1.0, 0.0)
    plane: str = "xz"
    pinned: str | tuple[tuple[int, int], ...] = "none"
    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclasses.dataclass(frozen=True)
class MaterialConfig:
    """[material]: per-unit material (see diffcloth.physics.Material)."""

    stretch: float = MATERIAL_FIELDS["stretch"][3]
    shear: float = MATERIAL_FIELDS["shear"][3]
    bend: float = MATERIAL_FIELDS["bend"][3]
    damping: float = MATERIAL_FIELDS["damping"][3]
    density: float = MATERIAL_FIELDS["density"][3]
    drag_normal: float = MATERIAL_FIELDS["drag_normal"][3]
    drag_tangent: float = MATERIAL_FIELDS["drag_tangent"][3]
    friction: float = MATERIAL_FIELDS["friction"][3]


@dataclasses.dataclass(frozen=True)
class SimConfig:
    """[sim]: time stepping."""

    dt: float = 1.0 / 30.0
    num_frames: int = 60
    num_substeps: int = 40
    integrator: str = "symplectic"
    gravity: tuple[float, float, float] = (0.0, -9.81, 0.0)
    wind: tuple[float, float, float] = (0.0, 0.0, 0.0)
    collision_margin: float = 0.0
    newton_iters: int = 3
    cg_iters: int = 200
    cg_tol: float = 1e-5


@dataclasses.dataclass(frozen=True)
class SphereConfig:
    center: tuple[float, float, float]
    radius: float


@dataclasses.dataclass(frozen=True)
class PlaneConfig:
    normal: tuple[float, float, float]
    offset: float = 0.0


@dataclasses.dataclass(frozen=True)
class Config:
    """A whole scene config. `sections` holds the later sections, unvalidated (read-only)."""

    net: NetConfig = NetConfig()
    material: MaterialConfig = MaterialConfig()
    sim: SimConfig = SimConfig()
    spheres: tuple[SphereConfig, ...] = ()
    planes: tuple[PlaneConfig, ...] = ()
    sections: Mapping[str, Any] = dataclasses.field(
        default_factory=lambda: types.MappingProxyType({}), compare=False, hash=False
    )
    path: str | None = None


def _fields(cls) -> tuple[str, ...]:
    return tuple(f.name for f in dataclasses.fields(cls))


def _parse_net(t: Mapping[str, Any]) -> NetConfig:
    w = "net"
    check_keys(t, _fields(NetConfig), w)
    d = NetConfig()
    rows = get_number(t, "rows", d.rows, where=w, lo=2, integer=True)
    cols = get_number(t, "cols", d.cols, where=w, lo=2, integer=True)
    pinned = t.get("pinned", d.pinned)
    if isinstance(pinned, str):
        if pinned not in PIN_PRESETS:
            raise ConfigError(
                f"[net] pinned = {pinned!r}; allowed presets: {', '.join(PIN_PRESETS)}"
            )
    elif isinstance(pinned, list):
        pins = []
        for p in pinned:
            if (
                not isinstance(p, list)
                or len(p) != 2
                or not all(isinstance(i, int) and not isinstance(i, bool) for i in p)
            ):
                raise ConfigError(f"[net] pinned: each pin must be [row, col] integers, got {p!r}")
            r, c = p
            if not (0 <= r < rows and 0 <= c < cols):
                raise ConfigError(
                    f"[net] pinned: pin [{r}, {c}] lies outside the net; row must be in "
                    f"[0, {rows - 1}] and col in [0, {cols - 1}]"
                )
            pins.append((r, c))
        pinned = tuple(pins)
    else:
        raise ConfigError(
            f"[net] pinned = {pinned!r} must be a preset name or a list of [row, col]"
        )
    return NetConfig(
        rows=rows,
        cols=cols,
        width=get_number(t, "width", d.width, where=w, lo=0, lo_inclusive=False),
        height=get_number(t, "height", d.height, where=w, lo=0, lo_inclusive=False),
        center=get_vec3(t, "center", d.center, where=w),
        plane=get_choice(t, "plane", d.plane, ("xz", "xy"), where=w),
        pinned=pinned,
        velocity=get_vec3(t, "velocity", d.velocity, where=w),
    )


def _parse_material(t: Mapping[str, Any]) -> MaterialConfig:
    check_keys(t, _fields(MaterialConfig), "material")
    values = {}
    for name, (lo, inclusive, unit, _default) in MATERIAL_FIELDS.items():
        if name in t:
            v = t[name]
            bad = isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v)
            if not bad:
                bad = not (v >= lo if inclusive else v > lo)
            if bad:
                raise ConfigError(
                    f"[material] {name} = {v!r} is out of range; allowed range "
                    f"{material_range(name)} {unit}"
                )
            values[name] = float(v)
    return MaterialConfig(**values)


def _parse_sim(t: Mapping[str, Any]) -> SimConfig:
    w = "sim"
    check_keys(t, _fields(SimConfig), w)
    d = SimConfig()
    return SimConfig(
        dt=get_number(t, "dt", d.dt, where=w, lo=0, lo_inclusive=False),
        num_frames=get_number(t, "num_frames", d.num_frames, where=w, lo=0, integer=True),
        num_substeps=get_number(t, "num_substeps", d.num_substeps, where=w, lo=1, integer=True),
        integrator=get_choice(t, "integrator", d.integrator, INTEGRATORS, where=w),
        gravity=get_vec3(t, "gravity", d.gravity, where=w),
        wind=get_vec3(t, "wind", d.wind, where=w),
        collision_margin=get_number(t, "collision_margin", d.collision_margin, where=w, lo=0),
        newton_iters=get_number(t, "newton_iters", d.newton_iters, where=w, lo=1, integer=True),
        cg_iters=get_number(t, "cg_iters", d.cg_iters, where=w, lo=1, integer=True),
        cg_tol=get_number(
            t, "cg_tol", d.cg_tol, where=w, lo=0, hi=1, lo_inclusive=False, hi_inclusive=False
        ),
    )


def _array_of_tables(data, key) -> list:
    items = data.get(key, [])
    if not isinstance(items, list) or not all(isinstance(i, Mapping) for i in items):
        raise ConfigError(f"[[{key}]] must be an array of tables")
    return items


def parse_config(data: Mapping[str, Any], path: str | None = None) -> Config:
    """Validate a TOML-like dict into a Config (ConfigError names any bad key or value)."""
    check_keys(data, PHYSICS_SECTIONS + PASSTHROUGH_SECTIONS, "top level")
    spheres = []
    for i, s in enumerate(_array_of_tables(data, "spheres")):
        w = f"spheres #{i}"
        check_keys(s, ("center", "radius"), w)
        spheres.append(
            SphereConfig(
                center=get_vec3(s, "center", where=w), radius=get_number(s, "radius", where=w, lo=0)
            )
        )
    planes = []
    for i, p in enumerate(_array_of_tables(data, "planes")):
        w = f"planes #{i}"
        check_keys(p, ("normal", "offset"), w)
        normal = get_vec3(p, "normal", where=w)
        if math.hypot(*normal) == 0:
            raise ConfigError(f"[{w}] normal = {list(normal)} must be non-zero")
        planes.append(PlaneConfig(normal=normal, offset=get_number(p, "offset", 0.0, where=w)))
    sections = {k: data[k] for k in PASSTHROUGH_SECTIONS if k in data}
    return Config(
        net=_parse_net(data.get("net", {})),
        material=_parse_material(data.get("material", {})),
        sim=_parse_sim(data.get("sim", {})),
        spheres=tuple(spheres),
        planes=tuple(planes),
        sections=types.MappingProxyType(sections),
        path=path,
    )


def load_config(path) -> Config:
    """Read and validate a TOML scene config. Raises ConfigError (a ValueError) on bad content."""
    path = Path(path)
    try:
        with path.open("rb") as fh:
            data = tomllib.load(fh)
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{path}: invalid TOML: {err}") from err
    try:
        return parse_config(data, str(path))
    except ConfigError as err:
        raise ConfigError(f"{path}: {err}") from None


# ----------------------------------------------------------------------------- builders


@dataclasses.dataclass(frozen=True)
class PhysicsScene:
    """Everything `physics.rollout` needs, built from a Config."""

    net: Any
    sim: Any
    material: Any
    state: Any
    colliders: Any
    num_frames: int


def build_physics(config: Config, dtype=None) -> PhysicsScene:
    """Net, SimSettings, Material, initial ClothState and Colliders of a Config."""
    from diffcloth import physics
    from diffcloth.shapes import make_plane, make_sphere

    n, s = config.net, config.sim
    pinned = n.pinned if isinstance(n.pinned, str) else [list(p) for p in n.pinned]
    net = physics.grid_net(
        n.rows,
        n.cols,
        (n.width, n.height),
        center=n.center,
        plane=n.plane,
        pinned=pinned or None,
        dtype=dtype,
    )
    sim = physics.make_sim(
        s.dt,
        gravity=s.gravity,
        wind=s.wind,
        num_substeps=s.num_substeps,
        integrator=s.integrator,
        collision_margin=s.collision_margin,
        newton_iters=s.newton_iters,
        cg_iters=s.cg_iters,
        cg_tol=s.cg_tol,
        dtype=dtype,
    )
    material = physics.make_material(dtype=dtype, **dataclasses.asdict(config.material))
    spheres = [make_sphere(sp.center, sp.radius, dtype=dtype) for sp in config.spheres]
    planes = [make_plane(pl.normal, pl.offset, dtype=dtype) for pl in config.planes]
    colliders = physics.make_colliders(spheres, planes, dtype=dtype) if spheres or planes else None
    state = physics.rest_state(net, velocity=n.velocity)
    return PhysicsScene(net, sim, material, state, colliders, s.num_frames)
