"""Issue 35, class 4: values are checked in the dtype the run uses, and the stability refusal is
the same in simulate, render and fit.

A value that is fine as a Python float (float64) may overflow to inf or underflow to 0 / a
subnormal in float32. Every config value, every `apply_params` value and the physics quantities
derived from them (node masses, rest lengths, spring weights, the substep) are checked in the run's
dtype by one mechanism (`diffcloth.representable`, `diffcloth.config.dtype`); the refusal names the
key and the allowed magnitudes, before anything is compiled. CLI cases run in-process on the tiny
scene of test_hardening.py.
"""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_hardening import FIT, TINY, TRUTH, assert_usage_error, run, write

import diffcloth as dc
from diffcloth import physics
from diffcloth.config import ConfigError, parse_config
from diffcloth.config.dtype import check_config_dtype, config_numbers
from diffcloth.representable import check_representable, range_text, unrepresentable

PROVOT = TINY.replace(
    "[material]\nstretch = 20.0\nshear = 5.0\nbend = 1e-3",
    '[material]\nmodel = "provot"\nk_struct = 40.0',
)


def _set(text: str, section: str, key: str, value: str) -> str:
    """`text` with `key = value` in `[section]` (replacing the key when present)."""
    head = f"[{section}]\n"
    if head not in text:
        return text + f"\n{head}{key} = {value}\n"
    start = text.index(head) + len(head)
    end = text.find("\n[", start)
    end = len(text) if end < 0 else end
    body = text[start:end]
    line = re.compile(rf"^{re.escape(key)} = .*$", re.M)
    body = line.sub(f"{key} = {value}", body) if line.search(body) else f"{key} = {value}\n" + body
    return text[:start] + body + text[end:]


@pytest.fixture(autouse=True)
def float32_run():
    """The CLI's default run: float32 (conftest turns x64 on for the rest of the suite)."""
    jax.config.update("jax_enable_x64", False)
    try:
        yield
    finally:
        jax.config.update("jax_enable_x64", True)


# (section, key, value, what the message must name): the direct overflows / underflows ...
DIRECT = [
    ("net", "width", "1e39", "[net] width"),
    ("net", "height", "5e38", "[net] height"),
    ("net", "center", "[0.0, 1e39, 0.0]", "[net] center"),
    ("net", "velocity", "[0.0, -2e-39, 0.0]", "[net] velocity"),
    ("material", "density", "1e-46", "[material] density"),
    ("material", "density", "1e-40", "[material] density"),  # subnormal, not 0
    ("material", "stretch", "1e39", "[material] stretch"),
    ("material", "bend", "1e-45", "[material] bend"),
    ("material", "damping", "3e-39", "[material] damping"),
    ("sim", "dt", "1e-46", "[sim] dt"),
    ("sim", "dt", "1e-39", "[sim] dt"),
    ("sim", "gravity", "[0.0, -1e39, 0.0]", "[sim] gravity"),
    ("sim", "wind", "[1e-40, 0.0, 0.0]", "[sim] wind"),
    ("sim", "collision_margin", "1e-42", "[sim] collision_margin"),
    ("render", "background", "[1e-39, 0.1, 0.1]", "[render] background"),
    ("camera", "eye", "[0.0, 1e39, 1.5]", "[cameras #0] eye"),
    ("appearance", "diffuse", "[1e-40, 0.5, 0.5]", "[appearance] diffuse"),
    ("lights", "ambient", "[2e-39, 0.1, 0.1]", "[lights] ambient"),
]
# ... and quantities the physics derives from values that are each representable
DERIVED = [
    ("net", "width", "1e20", "[net] width, height"),  # spring weights 1/m^2 underflow
    ("net", "width", "1e-20", "[net] width, height"),  # bend weights overflow
    ("material", "density", "1e-37", "[material] density"),  # node masses subnormal
    ("sim", "dt", "1e-36", "[sim] dt and num_substeps"),  # substep dt / 400 subnormal
]


@pytest.mark.parametrize("section, key, value, needle", DIRECT + DERIVED, ids=lambda v: str(v)[:14])
def test_simulate_refuses_values_that_leave_float32_naming_the_key(
    tmp_path, capsys, section, key, value, needle
):
    text = _set(TINY, section, key, value)
    if value == "1e-36":
        text = _set(text, "sim", "num_substeps", "400")
    cfg = write(tmp_path, text)
    code, out, err = run(["simulate", cfg, "--out", str(tmp_path / "o")], capsys)
    assert_usage_error(code, err, needle, "float32", "1.175e-38")
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("command", ["render", "fit"])
@pytest.mark.parametrize(
    "section, key, value, needle",
    [DIRECT[0], DIRECT[4], DIRECT[9], DERIVED[2]],
    ids=["width", "density", "dt", "mass"],
)
def test_render_and_fit_refuse_the_same_values(tmp_path, capsys, command, section, key, value,
                                               needle):  # fmt: skip
    cfg = write(tmp_path, _set(TINY + FIT + TRUTH, section, key, value))
    code, out, err = run([command, cfg, "--out", str(tmp_path / "o")], capsys)
    assert_usage_error(code, err, needle, "float32")
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    "key, value", [("k_struct", "1e39"), ("air_damping", "1e-44"), ("density", "1e-46")]
)
def test_provot_values_are_checked_in_the_run_dtype(tmp_path, capsys, key, value):
    cfg = write(tmp_path, _set(PROVOT, "material", key, value))
    code, out, err = run(["simulate", cfg, "--out", str(tmp_path / "o")], capsys)
    assert_usage_error(code, err, f"[material] {key}", "float32")


@pytest.mark.parametrize(
    "section, key, value, needle",
    [
        ("truth", "bend", "1e-46", "[truth] bend"),
        ("fit.initial", "bend", "1e-40", "[fit.initial] bend"),
        ("fit", "learning_rate", "1e-45", "[fit] learning_rate"),
    ],
)
def test_fit_values_are_checked_too(tmp_path, capsys, section, key, value, needle):
    text = TINY + FIT + TRUTH
    text = text + f"\n[{section}]\n{key} = {value}\n" if section == "fit.initial" else (
        _set(text, section, key, value)
    )  # fmt: skip
    cfg = write(tmp_path, text)
    code, out, err = run(["fit", cfg, "--out", str(tmp_path / "o")], capsys)
    assert_usage_error(code, err, needle, "float32")


def test_x64_run_accepts_what_float32_refuses(tmp_path, capsys):
    cfg = write(tmp_path, _set(TINY, "material", "density", "1e-40"))
    code, out, err = run(["simulate", cfg, "--out", str(tmp_path / "o")], capsys)
    assert_usage_error(code, err, "[material] density", "float32", "--x64")
    # in float64 the value is normal: the run gets past the value check, to the next one (a
    # 1e-40 kg/m^2 cloth on 20 N/m springs needs substeps of 1e-21 s: the stability gate)
    code, out, err = run(["simulate", cfg, "--out", str(tmp_path / "o"), "--x64"], capsys)
    assert code == 1 and "unstable time step" in err and "float32" not in err, err


def test_the_same_values_pass_in_float64():
    """The check knows the dtype: a float32 refusal is no refusal in float64 (the --x64 run)."""
    import tomllib

    data = tomllib.loads(_set(TINY, "material", "density", "1e-40"))
    config = parse_config(data)
    with pytest.raises(ConfigError, match=r"\[material\] density = 1e-40 .*float32"):
        check_config_dtype(config, np.float32)
    check_config_dtype(config, np.float64)  # a normal float64
    data = tomllib.loads(_set(TINY, "net", "width", "1e39"))
    check_config_dtype(parse_config(data), np.float64)


def test_every_number_of_a_config_is_walked():
    import tomllib

    config = parse_config(tomllib.loads(TINY + FIT + TRUTH))
    seen = {(where, key) for where, key, _ in config_numbers(config)}
    for item in [("net", "width"), ("net", "center"), ("material", "density"), ("sim", "dt"),
                 ("sim", "gravity"), ("spheres #0", "radius"), ("cameras #0", "eye"),
                 ("cameras #0", "fov_y"), ("render", "background"), ("lights", "ambient"),
                 ("lights.directional #0", "intensity"), ("truth", "bend"),
                 ("fit", "learning_rate")]:  # fmt: skip
        assert item in seen, item


def test_unrepresentable_rule():
    f32 = np.float32
    assert unrepresentable(0.0, f32) is None  # zero is exact
    assert unrepresentable([0.0, 1.2e-38, -3.4e38], f32) is None
    assert "overflows" in unrepresentable(3.5e38, f32)
    assert "overflows" in unrepresentable(-1e39, f32)
    assert "underflows" in unrepresentable(-1e-39, f32)
    assert "not finite" in unrepresentable(np.nan, np.float64)
    assert unrepresentable(1e-300, np.float64) is None
    assert "underflows" in unrepresentable(1e-310, np.float64)  # subnormal float64
    assert "float32" in range_text(f32) and "1.175e-38" in range_text(f32)
    with pytest.raises(ValueError, match=r"speed = 1e\+39 overflows to inf in float32"):
        check_representable("speed", 1e39, f32)


@pytest.mark.parametrize(
    "build, needle",
    [
        (lambda: physics.make_sim(1e-46, dtype=jnp.float32), "dt = 1e-46"),
        (lambda: physics.make_sim(0.01, gravity=(0, -1e39, 0), dtype=jnp.float32), "gravity"),
        (lambda: physics.make_material(density=1e-46, dtype=jnp.float32), "material.density"),
        (lambda: physics.make_material(stretch=1e39, dtype=jnp.float32), "material.stretch"),
        (lambda: physics.make_mass_spring(jnp.float32, k_flex=1e39), "material.k_flex"),
        (lambda: physics.grid_net(4, 4, (1e20, 1.0), dtype=jnp.float32), "spring weights"),
        (lambda: physics.grid_net(4, 4, (1e-20, 1e-20), dtype=jnp.float32), "do not fit float32"),
    ],
    ids=["sim_dt", "sim_gravity", "density", "stretch", "k_flex", "net_big", "net_small"],
)
def test_constructors_check_their_dtype(build, needle):
    with pytest.raises(ValueError, match=re.escape(needle)):
        build()


@pytest.fixture(scope="module")
def tiny32(tmp_path_factory):
    return dc.load_scene(write(tmp_path_factory.mktemp("v"), TINY), dtype=jnp.float32)


@pytest.mark.parametrize(
    "params, needle",
    [
        ({"density": 1e-46}, "parameter density = 1e-46 underflows"),
        ({"stretch": 1e39}, "parameter stretch = 1e+39 overflows"),
        ({"bend": 2e-39}, "parameter bend"),
        ({"wind": [0.0, 0.0, 1e39]}, "parameter wind"),
        ({"diffuse": [1e-40, 0.5, 0.5]}, "parameter diffuse"),
        ({"density": 1e-37}, "node masses"),  # each value fine, the masses subnormal
    ],
    ids=["density", "stretch", "bend", "wind", "diffuse", "mass"],
)
def test_apply_params_checks_the_scene_dtype(tiny32, params, needle):
    with pytest.raises(ValueError, match=re.escape(needle)) as info:
        dc.apply_params(tiny32, params)
    assert "float32" in str(info.value)


def test_apply_params_in_float64_and_traced_values_are_not_refused(tiny32):
    ok = dc.apply_params(tiny32, {"density": 0.3, "damping": 0.0})
    assert float(ok.material.density) == pytest.approx(0.3)
    # traced values cannot be checked eagerly (simulate_and_render_checked flags those)
    jax.jit(lambda d: dc.apply_params(tiny32, {"density": d}).material.density)(1e-46)


# ----------------------------------------------------------------------------- stability gate

UNSTABLE = TINY.replace("num_substeps = 20", "num_substeps = 1").replace(
    "stretch = 20.0", "stretch = 4000.0"
)


@pytest.mark.parametrize("command", ["simulate", "render", "fit"])
def test_stability_refusal_is_the_same_in_every_command(tmp_path, capsys, command):
    cfg = write(tmp_path, UNSTABLE + FIT + TRUTH)
    code, out, err = run([command, cfg, "--out", str(tmp_path / "o")], capsys)
    assert code == 1, err
    assert "unstable time step" in err and "num_substeps >=" in err, err
    assert "Traceback" not in err and not (tmp_path / "o").exists()
    assert not list(tmp_path.glob(".o*"))  # refused before the output folder is made


def test_fit_refuses_a_truth_or_start_the_scene_cannot_step(tmp_path, capsys):
    fit = FIT.replace('["bend"]', '["stretch"]')
    cfg = write(tmp_path, TINY + fit + "[truth]\nstretch = 1e7\n")
    code, out, err = run(["fit", cfg, "--out", str(tmp_path / "o")], capsys)
    assert code == 1 and "[truth] stretch = 10000000.0" in err and "unstable" in err, err
    cfg = write(tmp_path, TINY + fit + "[fit.initial]\nstretch = 1e7\n[truth]\nstretch = 30.0\n")
    code, out, err = run(["fit", cfg, "--out", str(tmp_path / "o")], capsys)
    assert code == 1 and "[fit.initial] stretch" in err and "unstable" in err, err


def test_check_run_stability_modes():
    import tomllib

    from diffcloth.config import build_physics
    from diffcloth.scene import check_run_stability

    phys = build_physics(parse_config(tomllib.loads(UNSTABLE)))
    with pytest.raises(physics.UnstableStepError, match="unstable time step"):
        check_run_stability(phys.net, phys.sim, phys.material)
    with pytest.warns(physics.StabilityWarning):
        check_run_stability(phys.net, phys.sim, phys.material, stability="warn")
    with pytest.raises(ValueError, match="stability='maybe'"):
        check_run_stability(phys.net, phys.sim, phys.material, stability="maybe")
