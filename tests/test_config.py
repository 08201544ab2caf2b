"""TOML configs: the shipped scenes load; unknown keys and bad values name the key and range."""

import math
from pathlib import Path

import numpy as np
import pytest

from diffcloth.config import (
    Config,
    ConfigError,
    build_physics,
    check_keys,
    get_number,
    load_config,
    parse_config,
)

ROOT = Path(__file__).resolve().parents[1]


def test_shipped_configs_load_and_build():
    drape = load_config(ROOT / "configs" / "drape.toml")
    assert (drape.net.rows, drape.net.cols) == (10, 13)
    assert len(drape.spheres) == 1 and drape.spheres[0].radius == 0.3
    scene = build_physics(drape)
    assert scene.net.rest.shape == (10, 13, 3) and scene.colliders.num_spheres == 1
    assert scene.num_frames == drape.sim.num_frames
    hang = load_config(ROOT / "configs" / "hang.toml")
    net = build_physics(hang).net
    assert int(np.asarray(net.pinned).sum()) == 2 and bool(net.pinned[0, 12])
    assert isinstance(hang, Config) and hang == load_config(ROOT / "configs" / "hang.toml")


def test_later_sections_pass_through_unvalidated():
    cfg = parse_config(
        {
            "camera": {"eye": [0, 1, 3], "anything": "goes"},
            "bodies": [{"shape": "sphere"}],
            "fit": {"free": ["stretch"]},
            "output": {"video": True},
        }
    )
    assert cfg.sections["camera"]["anything"] == "goes"
    assert cfg.sections["bodies"][0]["shape"] == "sphere"
    with pytest.raises(TypeError):
        cfg.sections["new"] = 1


@pytest.mark.parametrize(
    "data, match",
    [
        ({"nett": {}}, r"unknown key 'nett'; allowed keys: .*net"),
        ({"net": {"row": 3}}, r"\[net\] unknown key 'row'; allowed keys: .*rows"),
        ({"net": {"rows": 1}}, r"\[net\] rows = 1 is out of range; allowed range \[2, inf\)"),
        ({"net": {"rows": 3.5}}, r"rows = 3.5 must be an integer"),
        ({"net": {"width": 0.0}}, r"width = 0.0 is out of range; allowed range \(0, inf\)"),
        ({"net": {"pinned": [[0, 13]]}}, r"pin \[0, 13\] lies outside the net"),
        ({"net": {"pinned": "corners"}}, r"allowed presets"),
        ({"net": {"plane": "yz"}}, r"plane = 'yz'; allowed values: xz, xy"),
        (
            {"material": {"density": 0.0}},
            r"\[material\] density = 0.0 is out of range; allowed range \(0, inf\)",
        ),
        ({"material": {"stretch": -5.0}}, r"stretch = -5.0 .*\(0, inf\) N/m"),
        ({"material": {"bend": math.nan}}, r"bend = nan is out of range"),
        ({"material": {"friction": -1.0}}, r"friction = -1.0 .*\[0, inf\)"),
        ({"material": {"stiffness": 1.0}}, r"unknown key 'stiffness'"),
        ({"sim": {"dt": 0.0}}, r"\[sim\] dt = 0.0 is out of range; allowed range \(0, inf\)"),
        ({"sim": {"dt": math.inf}}, r"dt = inf is out of range"),
        ({"sim": {"integrator": "rk4"}}, r"allowed values: symplectic, implicit"),
        ({"sim": {"num_substeps": 0}}, r"num_substeps = 0 is out of range"),
        (
            {"sim": {"gravity": [0, math.nan, 0]}},
            r"gravity = .* must be a list of 3 finite numbers",
        ),
        ({"spheres": [{"center": [0, 0, 0], "radius": -1.0}]}, r"\[spheres #0\] radius = -1.0"),
        ({"spheres": [{"center": [0, 0, 0]}]}, r"missing required key 'radius'"),
        ({"planes": [{"normal": [0, 0, 0]}]}, r"normal = .* must be non-zero"),
    ],
)
def test_bad_configs_name_the_key_and_range(data, match):
    with pytest.raises(ConfigError, match=match):
        parse_config(data)


def test_nan_in_a_toml_file_names_the_file_and_key(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text("[material]\ndensity = nan\n")
    with pytest.raises(ValueError, match=r"bad.toml: \[material\] density = nan"):
        load_config(p)
    p.write_text("[material\n")
    with pytest.raises(ConfigError, match="invalid TOML"):
        load_config(p)


def test_helpers_are_reusable_for_later_sections():
    with pytest.raises(
        ConfigError, match=r"\[camera\] unknown key 'fovy'; allowed keys: eye, fov_y"
    ):
        check_keys({"fovy": 1}, ("eye", "fov_y"), "camera")
    assert get_number({"fov_y": 45}, "fov_y", where="camera", lo=0, hi=180) == 45.0
    with pytest.raises(ConfigError, match=r"fov_y = 200 is out of range; allowed range \[0, 180\]"):
        get_number({"fov_y": 200}, "fov_y", where="camera", lo=0, hi=180)
