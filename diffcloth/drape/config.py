"""The drape-test config: one fabric's observations (silhouette images, optional 3D scans), the
tester's geometry, the weighed density and the fit's choices. A small TOML file:

    name = "gray-interlock"
    [geometry]                      # m (defaults: the Cusick tester, 0.15 / 0.09)
    specimen_radius = 0.15
    pedestal_radius = 0.09
    [fabric]
    density = 0.187                 # kg/m^2, weighed (required)
    preset = "wang2011-gray-interlock"   # optional: the other fields' values
    [images]                        # defaults for every observation
    mm_per_pixel = 1.17             # omit: the image width spans the specimen diameter
    warp_angle = 0.0                # deg, the warp direction in the image (omit: unknown)
    [[observations]]
    file = "A_face_1.jpg"           # relative to this file
    sample = "A"
    side = "face"                   # "face" or "back"
    [[scans]]                       # optional 3D surfaces of a drape, OBJ in metres
    file = "A_face_1.obj"
    [fit]
    params = ["bend"]               # or ["bend_warp", "bend_weft"]; add "stretch" / "shear"
    seeds = 3                       # simulated drapes per evaluation
    [predict]
    seeds = 8

Every key is checked; an error names the key and the allowed values.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from pathlib import Path

from diffcloth.drape.images import DrapeGeometry, check_geometry
from diffcloth.drape.model import DEFAULT_EDGE

__all__ = ["FIT_PARAMS", "DrapeConfig", "DrapeConfigError", "Observation", "load_drape_config"]

#: fabric fields a drape fit can estimate, with their allowed range (SI)
FIT_PARAMS = {
    "bend": (1e-8, 1e-2),  # N m, isotropic: warp = weft = bias
    "bend_warp": (1e-8, 1e-2),
    "bend_weft": (1e-8, 1e-2),
    "stretch": (1.0, 1e5),  # N/m, isotropic membrane
    "shear": (0.1, 1e4),  # N/m
}


class DrapeConfigError(ValueError):
    """A bad drape config: the message names the file and the key."""


@dataclasses.dataclass(frozen=True)
class Observation:
    """One drape image: path, sample and side labels, its scale (mm/px or None) and centre."""

    path: Path
    sample: str
    side: str
    mm_per_pixel: float | None
    center_px: tuple[float, float] | None
    warp_angle: float | None


@dataclasses.dataclass(frozen=True)
class DrapeConfig:
    """A validated drape config (see the module docstring)."""

    source: Path
    name: str
    geometry: DrapeGeometry
    density: float
    fabric: dict  # the other Fabric fields (preset and overrides), density included
    observations: tuple[Observation, ...]
    scans: tuple[Path, ...]
    params: tuple[str, ...]
    start: dict  # param -> start value
    seeds: int
    steps: int
    edge: float
    amplitude: float
    predict_seeds: int


_TOP = {"name", "geometry", "fabric", "images", "observations", "scans", "fit", "predict"}
_FIT = {"params", "start", "seeds", "steps", "edge", "amplitude"}


def _fail(src: Path, key: str, msg: str):
    raise DrapeConfigError(f"{src}: {key}: {msg}")


def _number(src, key, value, lo, hi, *, integer=False):
    ok = isinstance(value, int | float) and not isinstance(value, bool)
    if integer:
        ok = ok and isinstance(value, int)
    if not ok or not math.isfinite(float(value)) or not lo <= value <= hi:
        kind = "an integer" if integer else "a number"
        _fail(src, key, f"must be {kind} in [{lo}, {hi}], got {value!r}")
    return int(value) if integer else float(value)


def _unknown(src, where, table, allowed):
    extra = sorted(set(table) - set(allowed))
    if extra:
        _fail(src, where, f"unknown key(s) {', '.join(extra)}; known: {', '.join(sorted(allowed))}")


def _center(src, key, value):
    if value is None:
        return None
    if not (isinstance(value, list) and len(value) == 2):
        _fail(src, key, f"must be [column, row] pixels, got {value!r}")
    return tuple(_number(src, key, v, -1e6, 1e6) for v in value)


def load_drape_config(path) -> DrapeConfig:
    """Read and check a drape config. Raises DrapeConfigError (or OSError for a missing file)."""
    src = Path(path)
    with src.open("rb") as fh:
        try:
            data = tomllib.load(fh)
        except tomllib.TOMLDecodeError as err:
            raise DrapeConfigError(f"{src}: not valid TOML ({err})") from None
    _unknown(src, "top level", data, _TOP)
    base = src.parent
    name = str(data.get("name", src.stem))
    geo = data.get("geometry", {})
    _unknown(src, "[geometry]", geo, {"specimen_radius", "pedestal_radius"})
    try:
        geometry = check_geometry(DrapeGeometry(**{k: float(v) for k, v in geo.items()}))
    except (TypeError, ValueError) as err:
        raise DrapeConfigError(f"{src}: [geometry]: {err}") from None
    fab = dict(data.get("fabric", {}))
    if "density" not in fab:
        _fail(src, "[fabric] density", "required: the weighed areal density in kg/m^2")
    density = _number(src, "[fabric] density", fab["density"], 0.01, 2.0)
    fabric = _fabric_values(src, fab, base)
    fabric["density"] = density
    images = data.get("images", {})
    _unknown(src, "[images]", images, {"mm_per_pixel", "center_px", "warp_angle"})
    obs = []
    entries = data.get("observations", [])
    if not isinstance(entries, list) or not entries:
        _fail(src, "[[observations]]", "at least one image is needed (file = ...)")
    for i, o in enumerate(entries):
        where = f"[[observations]] {i}"
        _unknown(src, where, o, {"file", "sample", "side", "mm_per_pixel", "center_px",
                                 "warp_angle"})  # fmt: skip
        if "file" not in o:
            _fail(src, f"{where} file", "required")
        p = base / str(o["file"])
        if not p.is_file():
            _fail(src, f"{where} file", f"no such image {str(p)!r}")
        side = str(o.get("side", "face"))
        if side not in ("face", "back"):
            _fail(src, f"{where} side", f"must be 'face' or 'back', got {side!r}")
        mm = o.get("mm_per_pixel", images.get("mm_per_pixel"))
        warp = o.get("warp_angle", images.get("warp_angle"))
        obs.append(Observation(
            path=p,
            sample=str(o.get("sample", "A")),
            side=side,
            mm_per_pixel=None if mm is None else _number(src, f"{where} mm_per_pixel", mm, 1e-3, 1e3),
            center_px=_center(src, f"{where} center_px", o.get("center_px", images.get("center_px"))),
            warp_angle=None if warp is None else _number(src, f"{where} warp_angle", warp, -360, 360),
        ))  # fmt: skip
    scans = []
    for i, s in enumerate(data.get("scans", [])):
        _unknown(src, f"[[scans]] {i}", s, {"file"})
        p = base / str(s.get("file", ""))
        if not p.is_file():
            _fail(src, f"[[scans]] {i} file", f"no such OBJ {str(p)!r}")
        scans.append(p)
    fit = data.get("fit", {})
    _unknown(src, "[fit]", fit, _FIT)
    params = fit.get("params", ["bend"])
    if isinstance(params, str):
        params = [params]
    bad = [p for p in params if p not in FIT_PARAMS]
    if bad or not params or len(set(params)) != len(params):
        _fail(src, "[fit] params", f"must be distinct names from {', '.join(FIT_PARAMS)}, "
                                   f"got {params!r}")  # fmt: skip
    if "bend" in params and ({"bend_warp", "bend_weft"} & set(params)):
        _fail(src, "[fit] params", "'bend' (isotropic) or 'bend_warp'/'bend_weft', not both")
    start = {}
    for k, v in dict(fit.get("start", {})).items():
        if k not in params:
            _fail(src, f"[fit] start.{k}", f"not a fitted parameter ({', '.join(params)})")
        start[k] = _number(src, f"[fit] start.{k}", v, *FIT_PARAMS[k])
    pred = data.get("predict", {})
    _unknown(src, "[predict]", pred, {"seeds"})
    hang = geometry.specimen_radius - geometry.pedestal_radius
    return DrapeConfig(
        source=src,
        name=name,
        geometry=geometry,
        density=density,
        fabric=fabric,
        observations=tuple(obs),
        scans=tuple(scans),
        params=tuple(params),
        start=start,
        seeds=_number(src, "[fit] seeds", fit.get("seeds", 3), 1, 64, integer=True),
        steps=_number(src, "[fit] steps", fit.get("steps", 12), 1, 200, integer=True),
        edge=_number(src, "[fit] edge", fit.get("edge", DEFAULT_EDGE), 1e-3, hang / 4),
        amplitude=_number(src, "[fit] amplitude", fit.get("amplitude", 5e-3), 0.0, 0.02),
        predict_seeds=_number(src, "[predict] seeds", pred.get("seeds", 8), 1, 256, integer=True),
    )


def _fabric_values(src: Path, fab: dict, base: Path) -> dict:
    """The [fabric] table's preset (a name or a TOML path) and overrides, checked."""
    from diffcloth.physics.mesh.fabric import FABRIC_FIELDS, fabric_preset

    values = {}
    preset = fab.get("preset")
    if preset is not None:
        name = str(preset)
        if name.endswith(".toml"):
            name = str(base / name)
        try:
            values.update(fabric_preset(name))
        except ValueError as err:
            raise DrapeConfigError(f"{src}: [fabric] preset: {err}") from None
    for k, v in fab.items():
        if k in ("preset", "density"):
            continue
        if k not in FABRIC_FIELDS:
            _fail(src, f"[fabric] {k}", f"unknown field; known: {', '.join(FABRIC_FIELDS)}")
        values[k] = _number(src, f"[fabric] {k}", v, 0.0, 1e9)
    return values
