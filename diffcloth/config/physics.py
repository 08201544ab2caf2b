"""Physics sections of the schema: [net], [material], [sim], [[spheres]], [[planes]]
(docs/config.md), and `build_physics`, which turns them into the physics stage's pytrees."""

from __future__ import annotations

import dataclasses
import math
import types
from collections.abc import Mapping
from typing import Any

from diffcloth.config._fields import (
    ConfigError,
    array_of_tables,
    check_keys,
    dataclass_keys,
    get_choice,
    get_number,
    get_vec3,
)
from diffcloth.physics.massspring import LUMPINGS, MASS_SPRING_FIELDS, mass_spring_range
from diffcloth.physics.material import MATERIAL_FIELDS, material_range
from diffcloth.physics.net import PIN_PRESETS
from diffcloth.physics.state import FRICTION_RULES, GRADIENT_MODES, INTEGRATORS

#: [material] model -> its numeric fields (name -> (lo, inclusive, unit, default)) and range text
MATERIAL_MODELS = {
    "continuum": (MATERIAL_FIELDS, material_range),
    "provot": (MASS_SPRING_FIELDS, mass_spring_range),
}

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
    """[material]: `model` "continuum" (per-unit material, diffcloth.physics.Material; the
    default) or "provot" (per-spring mass-spring, diffcloth.physics.MassSpring). Each model reads
    only its own keys (density and friction are shared); keys of the other model are an error."""

    model: str = "continuum"
    mass_lumping: str = "auto"
    stretch: float = MATERIAL_FIELDS["stretch"][3]
    shear: float = MATERIAL_FIELDS["shear"][3]
    bend: float = MATERIAL_FIELDS["bend"][3]
    damping: float = MATERIAL_FIELDS["damping"][3]
    density: float = MATERIAL_FIELDS["density"][3]
    drag_normal: float = MATERIAL_FIELDS["drag_normal"][3]
    drag_tangent: float = MATERIAL_FIELDS["drag_tangent"][3]
    friction: float = MATERIAL_FIELDS["friction"][3]
    k_struct: float = MASS_SPRING_FIELDS["k_struct"][3]
    k_shear: float = MASS_SPRING_FIELDS["k_shear"][3]
    k_flex: float = MASS_SPRING_FIELDS["k_flex"][3]
    d_struct: float = MASS_SPRING_FIELDS["d_struct"][3]
    d_shear: float = MASS_SPRING_FIELDS["d_shear"][3]
    d_flex: float = MASS_SPRING_FIELDS["d_flex"][3]
    air_damping: float = MASS_SPRING_FIELDS["air_damping"][3]

    def fields(self) -> dict[str, float]:
        """The numeric fields of the chosen model (what its constructor takes)."""
        return {name: getattr(self, name) for name in MATERIAL_MODELS[self.model][0]}

    @property
    def lumping(self) -> str:
        """The mass lumping actually used ("auto": area for continuum, uniform for provot)."""
        if self.mass_lumping != "auto":
            return self.mass_lumping
        return "area" if self.model == "continuum" else "uniform"


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
    contact_thickness: float | None = None
    friction_rule: str = "auto"
    newton_iters: int = 3
    cg_iters: int = 200
    cg_tol: float = 1e-5
    gradient: str = "reverse"
    # mesh cloth only ([cloth] shape other than "grid")
    mode: str = "dynamic"
    perturb: Mapping[str, Any] | None = None
    solver_iters: int | None = None
    solver_tol: float | None = None
    # both cloth kinds (the grid net: physics.grid_contact; None: 8 for a mesh, 16 for a grid)
    self_contact: bool = False
    self_contact_thickness: float = 2e-3
    self_contact_capacity: int | None = None


@dataclasses.dataclass(frozen=True)
class SphereConfig:
    center: tuple[float, float, float]
    radius: float


@dataclasses.dataclass(frozen=True)
class PlaneConfig:
    normal: tuple[float, float, float]
    offset: float = 0.0


def parse_net(t: Mapping[str, Any]) -> NetConfig:
    w = "net"
    check_keys(t, dataclass_keys(NetConfig), w)
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


def parse_material(t: Mapping[str, Any]) -> MaterialConfig:
    w = "material"
    check_keys(t, dataclass_keys(MaterialConfig), w)
    model = get_choice(t, "model", "continuum", tuple(MATERIAL_MODELS), where=w)
    lumping = get_choice(t, "mass_lumping", "auto", ("auto",) + LUMPINGS, where=w)
    if model == "continuum" and lumping == "uniform":
        raise ConfigError(
            "[material] mass_lumping = 'uniform' needs model = 'provot'; the continuum model "
            "lumps by area (allowed: auto, area)"
        )
    fields, range_text = MATERIAL_MODELS[model]
    other = sorted(
        k
        for m, (f, _) in MATERIAL_MODELS.items()
        if m != model
        for k in f
        if k in t and k not in fields
    )
    if other:
        raise ConfigError(
            f"[material] {', '.join(other)} belong(s) to another model; with model = {model!r} "
            f"the keys are: {', '.join(fields)}"
        )
    values = {}
    for name, (lo, inclusive, unit, _default) in fields.items():
        if name in t:
            v = t[name]
            bad = isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v)
            if not bad:
                bad = not (v >= lo if inclusive else v > lo)
            if bad:
                raise ConfigError(
                    f"[material] {name} = {v!r} is out of range; allowed range "
                    f"{range_text(name)} {unit}"
                )
            values[name] = float(v)
    return MaterialConfig(model=model, mass_lumping=lumping, **values)


def parse_sim(t: Mapping[str, Any]) -> SimConfig:
    w = "sim"
    check_keys(t, dataclass_keys(SimConfig), w)
    if "contact_thickness" in t and "collision_margin" in t:
        raise ConfigError(
            "[sim] contact_thickness and collision_margin name the same thing; give one of them"
        )
    d = SimConfig()
    return SimConfig(
        dt=get_number(t, "dt", d.dt, where=w, lo=0, lo_inclusive=False),
        num_frames=get_number(
            t, "num_frames", d.num_frames, where=w, lo=1, hi=10_000_000, integer=True
        ),
        num_substeps=get_number(t, "num_substeps", d.num_substeps, where=w, lo=1, integer=True),
        integrator=get_choice(t, "integrator", d.integrator, INTEGRATORS, where=w),
        gravity=get_vec3(t, "gravity", d.gravity, where=w),
        wind=get_vec3(t, "wind", d.wind, where=w),
        collision_margin=get_number(t, "collision_margin", d.collision_margin, where=w, lo=0),
        contact_thickness=get_number(t, "contact_thickness", None, where=w, lo=0),
        friction_rule=get_choice(t, "friction_rule", d.friction_rule, FRICTION_RULES, where=w),
        newton_iters=get_number(t, "newton_iters", d.newton_iters, where=w, lo=1, integer=True),
        cg_iters=get_number(t, "cg_iters", d.cg_iters, where=w, lo=1, integer=True),
        cg_tol=get_number(
            t, "cg_tol", d.cg_tol, where=w, lo=0, hi=1, lo_inclusive=False, hi_inclusive=False
        ),
        gradient=get_choice(t, "gradient", d.gradient, GRADIENT_MODES, where=w),
        mode=get_choice(t, "mode", d.mode, ("dynamic", "equilibrium"), where=w),
        perturb=_parse_perturb(t.get("perturb")),
        solver_iters=get_number(t, "solver_iters", None, where=w, lo=1, integer=True),
        solver_tol=get_number(
            t, "solver_tol", None, where=w, lo=0, hi=1, lo_inclusive=False, hi_inclusive=False
        ),
        self_contact=_get_bool(t, "self_contact", d.self_contact, w),
        self_contact_thickness=get_number(
            t, "self_contact_thickness", d.self_contact_thickness, where=w, lo=0, lo_inclusive=False
        ),  # fmt: skip
        self_contact_capacity=get_number(
            t, "self_contact_capacity", d.self_contact_capacity, where=w, lo=1, integer=True
        ),  # fmt: skip
    )


def _get_bool(t, key, default, where):
    value = t.get(key, default)
    if not isinstance(value, bool):
        raise ConfigError(f"{where}.{key}: must be true or false, got {value!r}")
    return value


def _parse_perturb(p) -> Mapping[str, Any] | None:
    """[sim] perturb = {mode = k, amplitude = m, seed = s}: a fold-seeding bump of the mesh
    cloth's start state (`physics.mesh.run.perturbed_start`)."""
    if p is None:
        return None
    w = "sim.perturb"
    if not isinstance(p, Mapping):
        raise ConfigError(f"[sim] perturb = {p!r} must be a table {{mode, amplitude, seed}}")
    check_keys(p, ("mode", "amplitude", "seed"), w)
    return types.MappingProxyType(
        {
            "mode": get_number(p, "mode", where=w, lo=1, hi=64, integer=True),
            "amplitude": get_number(p, "amplitude", where=w, lo=0, hi=1),
            "seed": get_number(p, "seed", 0, where=w, lo=0, integer=True),
        }
    )


def parse_spheres(data: Mapping[str, Any]) -> tuple[SphereConfig, ...]:
    """[[spheres]]: static sphere colliders (also drawn)."""
    spheres = []
    for i, s in enumerate(array_of_tables(data, "spheres")):
        w = f"spheres #{i}"
        check_keys(s, ("center", "radius"), w)
        spheres.append(
            SphereConfig(
                center=get_vec3(s, "center", where=w), radius=get_number(s, "radius", where=w, lo=0)
            )
        )
    return tuple(spheres)


def parse_planes(data: Mapping[str, Any]) -> tuple[PlaneConfig, ...]:
    """[[planes]]: static half-space colliders."""
    planes = []
    for i, p in enumerate(array_of_tables(data, "planes")):
        w = f"planes #{i}"
        check_keys(p, ("normal", "offset"), w)
        normal = get_vec3(p, "normal", where=w)
        if math.hypot(*normal) == 0:
            raise ConfigError(f"[{w}] normal = {list(normal)} must be non-zero")
        planes.append(PlaneConfig(normal=normal, offset=get_number(p, "offset", 0.0, where=w)))
    return tuple(planes)


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


def build_physics(config, dtype=None) -> PhysicsScene:
    """Net, SimSettings, Material, initial ClothState and Colliders of a Config.

    Every value of the config, and the node masses, rest lengths, spring weights and substep
    derived from them, are first checked in the run's dtype (`dtype`, default JAX's float:
    float32 unless x64 is on): ConfigError names the key when one overflows or underflows there
    (`diffcloth.config.dtype`)."""
    from diffcloth import physics
    from diffcloth.config.dtype import check_config_dtype, check_physics_dtype
    from diffcloth.shapes import make_plane, make_sphere

    if config.cloth.is_mesh:  # triangle-mesh cloth ([cloth] shape)
        from diffcloth.config.cloth import build_mesh_physics

        return build_mesh_physics(config, dtype)

    check_config_dtype(config, dtype)  # every value in the run's dtype, naming the key
    n, s = config.net, config.sim
    pinned = n.pinned if isinstance(n.pinned, str) else [list(p) for p in n.pinned]
    try:
        net = physics.grid_net(
            n.rows,
            n.cols,
            (n.width, n.height),
            center=n.center,
            plane=n.plane,
            pinned=pinned or None,
            dtype=dtype,
        )
    except ValueError as err:  # the net's derived sizes in the run's dtype
        where = f"{config.path}: " if config.path else ""
        raise ConfigError(f"{where}[net] width, height, rows, cols, center: {err}") from None
    sim = physics.make_sim(
        s.dt,
        gravity=s.gravity,
        wind=s.wind,
        num_substeps=s.num_substeps,
        integrator=s.integrator,
        collision_margin=(
            s.collision_margin if s.contact_thickness is None else s.contact_thickness
        ),
        friction_rule=s.friction_rule,
        newton_iters=s.newton_iters,
        cg_iters=s.cg_iters,
        cg_tol=s.cg_tol,
        gradient=s.gradient,
        dtype=dtype,
    )
    m = config.material
    if m.model == "provot":
        if s.integrator != "symplectic":
            raise ConfigError(
                "[sim] integrator = 'implicit' supports [material] model = 'continuum' only; "
                "the provot model runs with integrator = 'symplectic'"
            )
        material = physics.make_mass_spring(dtype=dtype, lumping=m.lumping, **m.fields())
    else:
        material = physics.make_material(dtype=dtype, **m.fields())
    check_physics_dtype(config, net, sim, material)  # masses, lengths, weights, substep
    if s.self_contact:  # off: sim.self_contact stays None (the step's program is unchanged)
        from diffcloth.physics.grid_contact import make_grid_self_contact

        try:
            contact = make_grid_self_contact(s.self_contact_thickness, net=net,
                                             capacity=s.self_contact_capacity or 16,
                                             dtype=net.rest.dtype)  # fmt: skip
        except ValueError as err:
            where = f"{config.path}: " if config.path else ""
            raise ConfigError(f"{where}[sim] {err} (self_contact_thickness)") from None
        sim = dataclasses.replace(sim, self_contact=contact)
    spheres = [make_sphere(sp.center, sp.radius, dtype=dtype) for sp in config.spheres]
    planes = [make_plane(pl.normal, pl.offset, dtype=dtype) for pl in config.planes]
    colliders = physics.make_colliders(spheres, planes, dtype=dtype) if spheres or planes else None
    state = physics.rest_state(net, velocity=n.velocity)
    return PhysicsScene(net, sim, material, state, colliders, s.num_frames)
