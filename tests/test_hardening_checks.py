"""Issue 35, class 6: "checks everything before any work" holds for every command.

- warmup runs every config's checks (`cli_commands.check_config(..., "fit")`: the config in the
  run's dtype, memory, stability, [truth]/[fit.initial], target images) before compiling the first,
  and refuses a compilation cache folder it cannot write into (exit 2), instead of compiling
  everything, keeping nothing and reporting success;
- view checks --port (0-65535), --host, --size, --level and that --export can be written before it
  simulates;
- a config path that is not a regular file (a FIFO would block the read forever, a device, a
  folder) is refused by `load_config` for every command.
Work is replaced by a recorder (monkeypatch) where the test must prove it never started.
"""

import os
import subprocess
import sys
from pathlib import Path

import pytest
from test_hardening import FIT, TINY, TRUTH, assert_usage_error, run, write

from diffcloth.config import ConfigError, check_config_path

ROOT = Path(__file__).resolve().parents[1]


class Recorder:
    """Stands in for the work (compiling, simulating): records calls, does nothing."""

    def __init__(self):
        self.calls = []

    def __call__(self, *args, **kwargs):
        self.calls.append((args, kwargs))
        return {"status": "max_steps"}


@pytest.fixture
def no_fit(monkeypatch):
    rec = Recorder()
    monkeypatch.setattr("diffcloth.experiment.run_fit_config", rec)
    return rec


# ----------------------------------------------------------------------------- warmup


def _gap_targets(tmp_path):
    import numpy as np

    from diffcloth.io import save_png

    for i in (0, 1, 3):
        save_png(tmp_path / "t" / f"frame_{i}.png", np.full((16, 16, 3), 0.4), colorspace="srgb")
    return 'targets = "t"\n'


@pytest.mark.parametrize(
    "second, needles",
    [
        (lambda p: TINY + FIT + TRUTH.replace("2e-3", "-1.0"), ["[truth]", "bend"]),
        (lambda p: TINY, ["missing [fit] section"]),
        (lambda p: TINY.replace("num_substeps = 20", "num_substeps = 1").replace(
            "stretch = 20.0", "stretch = 4000.0") + FIT + TRUTH, ["unstable time step"]),
        (lambda p: TINY + FIT + _gap_targets(p), ["frame_2.png"]),
        (lambda p: TINY.replace("width = 16", "width = 8192").replace(
            "height = 16", "height = 8192") + FIT + TRUTH, ["memory"]),
        (lambda p: TINY.replace("bend = 1e-3", "bendd = 1e-3") + FIT + TRUTH, ["bendd"]),
    ],
    ids=["truth", "no_fit", "unstable", "target_gap", "memory", "unknown_key"],
)  # fmt: skip
def test_warmup_checks_every_config_before_compiling_the_first(tmp_path, capsys, no_fit, second,
                                                               needles):  # fmt: skip
    good = write(tmp_path, TINY + FIT + TRUTH, "good.toml")
    bad = write(tmp_path, second(tmp_path), "bad.toml")
    code, out, err = run(["warmup", good, bad, "--cache", str(tmp_path / "cache")], capsys)
    if "unstable time step" in needles:  # the stability gate's exit code, as in fit
        assert code == 1 and err.startswith("error: unstable time step"), err
    elif "memory" in needles:  # the estimate's own words
        assert code == 2 and "error: " in err, err
    else:
        assert_usage_error(code, err, *needles)
    assert no_fit.calls == [], "the first config was compiled before the second was checked"


def test_warmup_smoke_checks_the_smoke_variant(tmp_path, capsys, no_fit):
    """--smoke shrinks the sizes before the memory check, as `fit --smoke` does."""
    big = TINY.replace("width = 16", "width = 8192").replace("height = 16", "height = 8192")
    cfg = write(tmp_path, big + FIT + TRUTH)
    code, out, err = run(["warmup", cfg, "--smoke", "--cache", str(tmp_path / "c")], capsys)
    assert code == 0, err
    assert len(no_fit.calls) == 1 and no_fit.calls[0][1]["smoke"] is True


def _a_file(tmp_path, *below):
    """tmp_path/afile (a regular file), joined with `below`."""
    (tmp_path / "afile").write_text("x")
    return Path(tmp_path / "afile", *below)


def _read_only_folder(tmp_path):
    d = tmp_path / "ro"
    d.mkdir()
    d.chmod(0o555)
    return d


@pytest.mark.parametrize(
    "cache, needle",
    [
        (lambda p: _a_file(p), "is not a folder"),
        (lambda p: _a_file(p, "sub"), "cannot be made"),
        (_read_only_folder, "read-only"),
        (lambda p: Path("/proc/diffcloth-cache"), "cannot be made"),
    ],
    ids=["file", "under_a_file", "read_only", "proc"],
)
def test_warmup_refuses_an_unusable_cache_folder(tmp_path, capsys, no_fit, cache, needle):
    cfg = write(tmp_path, TINY + FIT + TRUTH)
    folder = cache(tmp_path)
    try:
        code, out, err = run(["warmup", cfg, "--cache", str(folder)], capsys)
    finally:
        if folder.is_dir() and folder.name == "ro":
            folder.chmod(0o755)
    assert_usage_error(code, err, "compilation cache", needle, "--cache DIR")
    assert "done" not in out and no_fit.calls == []


# ----------------------------------------------------------------------------- view


@pytest.fixture
def no_view(monkeypatch):
    pytest.importorskip("viser")
    rec = Recorder()
    monkeypatch.setattr("diffcloth.view.model.load_view", rec)
    return rec


@pytest.mark.parametrize(
    "extra, needles",
    [
        (["--port", "70000"], ["--port 70000", "0-65535"]),
        (["--port", "-1"], ["--port -1", "0-65535"]),
        (["--port", "65536"], ["0-65535"]),
        (["--size", "0"], ["--size 0", "1-8192"]),
        (["--level", "1"], ["--level 1", "2-64"]),
        (["--host", "no such host name!"], ["--host"]),
        (["--overlay"], ["--overlay", "--export"]),
    ],
    ids=["port_high", "port_negative", "port_edge", "size", "level", "host", "overlay"],
)
def test_view_refuses_bad_options_at_once(tmp_path, capsys, no_view, extra, needles):
    cfg = write(tmp_path, TINY)
    code, out, err = run(["view", cfg, "--no-cache", *extra], capsys)
    assert_usage_error(code, err, *needles)
    assert no_view.calls == [] and "simulating" not in out


@pytest.mark.parametrize(
    "target, needle",
    [
        (lambda p: _read_only_folder(p) / "v.html", "read-only"),
        (lambda p: _read_only_folder(p) / "new" / "deeper" / "v.html", "read-only"),
        (lambda p: p, "is a folder"),
        (lambda p: _a_file(p, "v.html"), "is not a folder"),
        (lambda p: Path("/proc/diffcloth-view.html"), "'/proc'"),
    ],
    ids=["read_only", "read_only_parent", "folder", "under_a_file", "proc"],
)
def test_view_export_that_cannot_be_written_is_refused_before_simulating(
    tmp_path, capsys, no_view, target, needle
):
    cfg = write(tmp_path, TINY)
    path = target(tmp_path)
    try:
        code, out, err = run(["view", cfg, "--no-cache", "--export", str(path)], capsys)
    finally:
        ro = tmp_path / "ro"
        if ro.is_dir():
            ro.chmod(0o755)
    assert_usage_error(code, err, "--export", needle)
    assert no_view.calls == [] and "simulating" not in out


@pytest.mark.parametrize("which", ["config", "symlink_to_config", "target_image"])
def test_view_export_onto_an_input_of_the_run_is_refused(tmp_path, capsys, no_view, which):
    """--export never writes over the config or a file the config names (it would be lost)."""
    cfg = write(tmp_path, TINY)
    before = Path(cfg).read_bytes()
    if which == "config":
        path = Path(cfg)
    elif which == "symlink_to_config":
        path = tmp_path / "link.html"
        path.symlink_to(cfg)
    else:
        img = tmp_path / "target.png"
        img.write_bytes(b"not really a png")
        text = Path(cfg).read_text() + '\n[textures]\nimage = "target.png"\n'
        Path(cfg).write_text(text)
        before = Path(cfg).read_bytes()
        path = img
    code, out, err = run(["view", cfg, "--no-cache", "--export", str(path)], capsys)
    assert code == 2 and "input of this run" in err, err
    assert no_view.calls == [] and "simulating" not in out
    assert Path(cfg).read_bytes() == before


def test_view_port_zero_means_any_free_port(tmp_path, capsys, no_view):
    """0 passes the check (viser then picks a free port); the recorder stands in for the rest."""
    from diffcloth.cli import _check_view_args, build_parser

    args = build_parser().parse_args(["view", write(tmp_path, TINY), "--port", "0"])
    _check_view_args(args)  # no error


# ----------------------------------------------------------------------------- config paths


@pytest.fixture
def fifo(tmp_path):
    path = tmp_path / "scene.toml"
    os.mkfifo(path)
    return path


def test_a_fifo_config_is_refused_not_read(fifo):
    with pytest.raises(ConfigError, match="FIFO"):
        check_config_path(fifo)  # returns at once: the FIFO is never opened


@pytest.mark.parametrize(
    "argv",
    [
        ["simulate", "{cfg}", "--out", "{tmp}/o"],
        ["render", "{cfg}", "--out", "{tmp}/o"],
        ["fit", "{cfg}", "--out", "{tmp}/o"],
        ["warmup", "{cfg}", "--cache", "{tmp}/c"],
        ["view", "{cfg}", "--no-cache", "--export", "{tmp}/v.html"],
    ],
    ids=["simulate", "render", "fit", "warmup", "view"],
)
def test_every_command_refuses_a_fifo_config(tmp_path, capsys, fifo, argv):
    if argv[0] == "view":
        pytest.importorskip("viser")
    check_config_path  # noqa: B018  (the guard above: a hang here would be a regression)
    args = [a.format(cfg=fifo, tmp=tmp_path) for a in argv]
    code, out, err = run(args, capsys)
    assert_usage_error(code, err, "FIFO", "not a config file")
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    "path, needle",
    [(lambda p: Path("/dev/null"), "a device"), (lambda p: p, "a folder"),
     (lambda p: p / "missing.toml", "no such config file")],
    ids=["device", "folder", "missing"],
)  # fmt: skip
def test_other_non_regular_config_paths(tmp_path, capsys, path, needle):
    code, out, err = run(["simulate", str(path(tmp_path)), "--out", str(tmp_path / "o")], capsys)
    assert_usage_error(code, err, needle)


def test_a_symlink_to_a_config_is_fine(tmp_path):
    real = Path(write(tmp_path, TINY))
    link = tmp_path / "link.toml"
    link.symlink_to(real)
    assert check_config_path(link) == link


def test_fifo_config_in_a_fresh_process_exits_2_quickly(tmp_path, fifo):
    res = subprocess.run(
        [sys.executable, "-m", "diffcloth", "simulate", str(fifo), "--out", str(tmp_path / "o")],
        capture_output=True, text=True, cwd=ROOT, timeout=120,
    )  # fmt: skip
    assert res.returncode == 2 and "FIFO" in res.stderr, res.stderr[-2000:]
