"""`diffcloth simulate CONFIG --out DIR` and `python -m diffcloth`."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from diffcloth.cli import main

ROOT = Path(__file__).resolve().parents[1]

SMALL = """
[net]
rows = 4
cols = 5
width = 0.4
height = 0.3
center = [0.0, 0.5, 0.0]
pinned = [[0, 0], [0, 4]]
plane = "xy"

[material]
stretch = 20.0
shear = 5.0

[sim]
num_frames = 6
num_substeps = 20

[[spheres]]
center = [0.0, 0.1, 0.2]
radius = 0.1

[camera]
eye = [0, 1, 3]
"""


def test_simulate_writes_trajectory_and_prints_progress(tmp_path, capsys):
    cfg = tmp_path / "small.toml"
    cfg.write_text(SMALL)
    out = tmp_path / "out"
    assert main(["simulate", str(cfg), "--out", str(out), "--chunk", "3"]) == 0
    printed = capsys.readouterr().out
    assert "frame    3/6" in printed and "frame    6/6" in printed
    data = np.load(tmp_path / "out" / "trajectory.npz")
    assert data["x"].shape == (6, 4, 5, 3) and np.all(np.isfinite(data["x"]))
    np.testing.assert_allclose(data["x"][:, 0, 0], np.broadcast_to(data["rest"][0, 0], (6, 3)))
    assert data["x"][-1, -1, 2, 1] < data["rest"][-1, 2, 1]  # it falls


def test_bad_config_and_unstable_step_exit_nonzero(tmp_path, capsys):
    cfg = tmp_path / "bad.toml"
    cfg.write_text("[material]\ndensity = -1.0\n")
    assert main(["simulate", str(cfg), "--out", str(tmp_path / "o")]) == 2
    assert "density = -1.0" in capsys.readouterr().err
    cfg.write_text(SMALL.replace("num_substeps = 20", "num_substeps = 1"))
    assert main(["simulate", str(cfg), "--out", str(tmp_path / "o")]) == 1
    assert "implicit integrator" in capsys.readouterr().err


def test_python_dash_m_entry_point():
    out = subprocess.run(
        [sys.executable, "-m", "diffcloth", "--help"], capture_output=True, text=True, cwd=ROOT
    )
    assert out.returncode == 0 and "simulate" in out.stdout


def test_simulate_obj_files_hold_the_tessellated_frames(tmp_path):
    from diffcloth.io import read_obj

    cfg = tmp_path / "small.toml"
    cfg.write_text(SMALL)
    assert main(["simulate", str(cfg), "--out", str(tmp_path / "o"), "--obj", "--level", "2"]) == 0
    files = sorted((tmp_path / "o" / "obj").glob("*.obj"))
    assert len(files) == 6
    mesh = read_obj(files[-1])
    verts = mesh["positions"]
    assert np.asarray(verts).shape == ((4 - 3) * 2 * (5 - 3) * 2, 3)


def test_fit_devices_errors(tmp_path, capsys, monkeypatch):
    import jax

    jax.device_count()  # start the backend first: the CLI's XLA_FLAGS must not reach this process
    monkeypatch.setenv("XLA_FLAGS", "")  # the CLI may add the host device count; restore after
    cfg = str(Path(__file__).parents[1] / "configs" / "drape_fit.toml")
    assert main(["fit", cfg, "--out", str(tmp_path), "--devices", "0"]) == 2
    assert "--devices must be >= 1" in capsys.readouterr().err
    # JAX started long ago in this process with one CPU device: a clear error, not a crash
    assert main(["fit", cfg, "--out", str(tmp_path), "--devices", "64"]) == 2
    err = capsys.readouterr().err
    assert "JAX sees 1 device" in err and "xla_force_host_platform_device_count=64" in err


def test_fit_config_devices_must_divide_multistart():
    from diffcloth.config import ConfigError
    from diffcloth.experiment import parse_fit

    base = {"free": ["bend"], "multistart": 4}
    assert parse_fit({"fit": {**base, "devices": 2}, "truth": {"bend": 1e-3}}).devices == 2
    with pytest.raises(
        ConfigError, match=r"\[fit\] devices = 3 .* multiple of it \(got multistart = 4\)"
    ):
        parse_fit({"fit": {**base, "devices": 3}, "truth": {"bend": 1e-3}})
    with pytest.raises(ConfigError, match="devices"):
        parse_fit({"fit": {**base, "devices": 0}, "truth": {"bend": 1e-3}})


BALL = SMALL.replace(
    "[camera]",
    """
[[planes]]
normal = [0.0, 1.0, 0.0]
offset = -0.2

[[bodies]]
shape = "sphere"
radius = 0.08
mass = 0.1
position = [0.0, 0.3, 0.4]
velocity = [0.0, 0.0, -3.0]

[camera]""",
)


@pytest.mark.slow  # keeps the default suite under 10 min; runs with -m slow
def test_render_and_simulate_with_a_rigid_body(tmp_path, capsys):
    import imageio.v3 as iio

    path = tmp_path / "ball.toml"
    path.write_text(BALL)
    out = tmp_path / "render"
    assert main(["render", str(path), "--out", str(out), "--size", "16", "--format", "gif",
                 "--chunk", "4"]) == 0  # fmt: skip
    video = iio.imread(out / "video.gif")
    assert video.shape[:3] == (6, 16, 16)  # 6 frames (the last chunk padded, then cut)
    assert (out / "first.png").exists() and (out / "last.png").exists()
    assert "1 rigid bodies" in capsys.readouterr().out
    assert main(["simulate", str(path), "--out", str(tmp_path / "sim"), "--chunk", "4"]) == 0
    traj = np.load(tmp_path / "sim" / "trajectory.npz")
    assert traj["body_position"].shape == (6, 1, 3)
    assert traj["body_position"][-1, 0, 2] < 0.4 - 0.1  # thrown towards -z
    bad = tmp_path / "bad.toml"
    bad.write_text(BALL.replace("mass = 0.1", "mass = 0.0"))
    assert main(["render", str(bad), "--out", str(tmp_path / "bad")]) == 2
    assert "mass" in capsys.readouterr().err


def test_bench_runs_a_stage_benchmark_and_rejects_unknown_ones(tmp_path, capsys):
    assert main(["bench", "nope"]) == 2
    assert "unknown benchmark(s) ['nope']" in capsys.readouterr().err
    args = ["bench", "surface", "--out", str(tmp_path), "--args", "--levels 2 --repeats 2"]
    assert main(args) == 0
    lines = (tmp_path / "surface.jsonl").read_text().strip().splitlines()
    import json

    rows = [json.loads(line) for line in lines]
    assert rows and all("bench" in r for r in rows)


def test_compilation_cache_is_written_and_reported(tmp_path):
    script = (
        "import jax, jax.numpy as jnp, json\n"
        "from diffcloth import runtime\n"
        f"runtime.enable_compilation_cache({str(tmp_path / 'cache')!r}, min_compile_seconds=0)\n"
        "jax.jit(lambda x: jnp.sin(x) * 2)(jnp.ones(3)).block_until_ready()\n"
        "print(json.dumps(runtime.environment()))\n"
    )
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr[-2000:]
    import json

    env = json.loads(res.stdout.strip().splitlines()[-1])
    assert env["compilation_cache"] == str(tmp_path / "cache")
    assert any((tmp_path / "cache").iterdir())  # the compiled program was stored
