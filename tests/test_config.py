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


def test_every_section_is_validated_up_front():
    """Render, body and fit sections are parsed into typed settings by load_config, not later."""
    cfg = parse_config(
        {
            "camera": {"eye": [0, 1, 3]},
            "bodies": [{"shape": "sphere", "radius": 0.1, "mass": 0.2}],
            "fit": {"free": ["stretch"]},
            "truth": {"stretch": 50.0},
        }
    )
    assert cfg.cameras[0].eye == (0.0, 1.0, 3.0) and cfg.render.width == 64
    assert cfg.bodies.entries[0]["shape"] == "sphere" and cfg.bodies.two_way
    assert cfg.fit.free == ("stretch",) and float(cfg.fit.truth["stretch"]) == 50.0
    with pytest.raises(TypeError):
        cfg.sections["new"] = 1
    bad = [
        ({"camera": {"eye": [0, 1, 3], "anything": "goes"}}, r"\[cameras #0\] unknown key"),
        ({"camera": {"eye": [0, 1, 0], "target": [0, 1, 0]}}, r"eye .* must differ from target"),
        ({"bodies": [{"shape": "sphere"}]}, r"\[\[bodies\]\] .*'mass' is required"),
        ({"output": {"video": True}}, r"unknown key 'output'"),
        ({"render": {"width": 0}}, r"\[render\] width = 0 is out of range"),
        ({"render": {"flip": 1}}, r"\[render\] flip = 1 must be true or false"),
        ({"lights": {"directional": [{"direction": [0, 0, 0]}]}}, r"direction .* must be non-zero"),
        ({"appearance": {"difuse": [1, 0, 0]}}, r"\[appearance\] unknown key 'difuse'"),
        ({"appearance": {"diffuse": "red"}}, r"\[appearance\] diffuse = 'red' must be a number"),
        ({"truth": {"stretch": 1.0}}, r"\[truth\] needs a \[fit\] section"),
        ({"fit": {"free": ["strech"]}, "truth": {"stretch": 1.0}}, r"\[fit\] free"),
        ({"coupling": {"two_way": "yes"}}, r"\[coupling\] two_way = 'yes' must be true or false"),
    ]
    for data, match in bad:
        with pytest.raises(ConfigError, match=match):
            parse_config(data)


def test_docs_config_md_lists_every_key_of_the_schema():
    """docs/config.md documents every section and key of `diffcloth.config.schema()`."""
    from diffcloth.config import schema

    text = (ROOT / "docs" / "config.md").read_text()
    headings = [line for line in text.splitlines() if line.startswith("## ")]
    for section, keys in schema().items():
        top = section.split(".")[0]
        heading = next((h for h in headings if f"[{top}]" in h or f"[[{top}]]" in h), None)
        assert heading is not None, f"docs/config.md has no heading for [{section}]"
        start = text.index(heading)
        nxt = [text.index(h) for h in headings if text.index(h) > start]
        part = text[start : min(nxt) if nxt else len(text)]
        missing = [k for k in keys if f"| {k} " not in part and f"| {section}.{k} " not in part]
        assert not missing, (
            f"docs/config.md section {heading!r} lacks keys {missing} of [{section}]"
        )


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
