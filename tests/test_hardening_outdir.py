"""Issue 35, class 1: an output folder never destroys an input and never races (diffcloth.outdir).

In-process CLI runs on the tiny scene of test_hardening.py: refusals happen before anything is
compiled. A fit that is accepted runs with its work replaced by a stub (`_stub_fit`): what is
tested here is the folder around it, not the fit. The two-process race is the one subprocess.
"""

import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_hardening import FIT, TINY, assert_usage_error, run, write

from diffcloth import experiment
from diffcloth.cli import main
from diffcloth.io import save_png
from diffcloth.outdir import OutputDir, UsageError, config_inputs

ROOT = Path(__file__).resolve().parents[1]


def _project(root: Path) -> Path:
    """root/proj/{scene.toml, notes.txt, targets/frame_*.png} and root/ck/checkpoint.npz(+json)."""
    proj = root / "proj"
    (proj / "targets").mkdir(parents=True)
    for i in range(3):
        save_png(proj / "targets" / f"frame_{i}.png", np.full((16, 16, 3), 0.3 + 0.1 * i))
    (proj / "scene.toml").write_text(TINY + FIT + 'targets = "targets"\n')
    (proj / "notes.txt").write_text("my notes")
    from diffcloth.fit import save_checkpoint

    save_checkpoint(root / "ck" / "checkpoint.npz", {"step": 2, "best/bend": 1.5e-3,
                    "params/bend": 1.5e-3}, {"step": 2, "names": ["bend"]})  # fmt: skip
    return proj


def _snapshot(root: Path, folders=("proj", "ck")) -> dict:
    """Every file under root/proj (the config, the targets, a file beside them) and root/ck."""
    return {
        p.relative_to(root): p.read_bytes()
        for f in folders
        for p in sorted((root / f).rglob("*"))
        if p.is_file()
    }


def _leftovers(root: Path) -> list[str]:
    return [str(p) for p in root.rglob(".*") if ".tmp-" in p.name or p.name.endswith(".lock")]


@pytest.fixture
def stub_fit(monkeypatch):
    """run_fit_config with every check and the output folder, but no fit (one file written)."""

    def fake(config_path, settings, sc, targets, out, ckpt, *a, **k):
        (out.tmp / "result.json").write_text("{}")
        return {"status": "max_steps", "params": {}, "loss": 0.0, "iterations": 0, "total_s": 0.0}

    monkeypatch.setattr(experiment, "_run_fit", fake)


# ----------------------------------------------------------------------------- inputs


@pytest.mark.parametrize("cmd", ["simulate", "render", "fit"])
@pytest.mark.parametrize(
    "out, needle",
    [("proj", "holds an input"), ("proj/targets", "is an input"),
     ("proj/targets/new", "inside an input folder"), ("proj/scene.toml", "is an input"),
     (".", "current folder")],
)  # fmt: skip
def test_out_holding_or_inside_an_input_is_refused_even_with_overwrite(
    tmp_path, capsys, monkeypatch, cmd, out, needle
):
    proj = _project(tmp_path)
    before = _snapshot(tmp_path)
    monkeypatch.chdir(tmp_path)
    code, _, err = run([cmd, "proj/scene.toml", "--out", out, "--overwrite"], capsys)
    assert_usage_error(code, err, "--out", needle)
    assert _snapshot(tmp_path) == before and not _leftovers(tmp_path)
    assert not (proj / "targets" / "new").exists()


def test_inputs_named_by_the_config_are_found(tmp_path):
    proj = _project(tmp_path)
    labels = dict((str(p.relative_to(tmp_path)), label) for label, p in
                  config_inputs(proj / "scene.toml"))  # fmt: skip
    assert labels == {"proj/scene.toml": "config", "proj/targets": "[fit] targets"}
    (proj / "dot.toml").write_text(TINY + FIT + 'target_cameras = ["."]\ntargets = "targets"\n')
    assert [lab for lab, _ in config_inputs(proj / "dot.toml")] == ["config", "[fit] targets"]
    (proj / "bad.toml").write_text("[net\n")  # unreadable: only the config itself
    assert [lab for lab, _ in config_inputs(proj / "bad.toml")] == ["config"]


def test_init_from_checkpoint_and_resumed_config_copy_are_inputs(tmp_path, capsys, stub_fit):
    proj = _project(tmp_path)
    cfg = str(proj / "scene.toml")
    ck = tmp_path / "ck"
    before = _snapshot(tmp_path)
    code, _, err = run(["fit", cfg, "--out", str(ck), "--overwrite", "--init-from", str(ck)],
                       capsys)  # fmt: skip
    assert_usage_error(code, err, "--init-from checkpoint")
    code, _, err = run(["fit", cfg, "--out", str(tmp_path), "--overwrite", "--init-from",
                        str(ck / "checkpoint.npz")], capsys)  # fmt: skip
    assert_usage_error(code, err, "holds an input")
    # a fit folder's config.toml given back as the config of its own --resume
    res = tmp_path / "res"
    res.mkdir()
    (res / "config.toml").write_bytes((proj / "scene.toml").read_bytes().replace(
        b'targets = "targets"', b'targets = "../proj/targets"'))  # fmt: skip
    copy = (res / "config.toml").read_bytes()
    code, _, err = run(["fit", str(res / "config.toml"), "--out", str(res), "--resume"], capsys)
    assert_usage_error(code, err, "holds an input", "config")
    assert _snapshot(tmp_path) == before and (res / "config.toml").read_bytes() == copy
    # a new folder beside the inputs is fine, and the fit starts from the checkpoint's values
    code, out, err = run(["fit", cfg, "--out", str(tmp_path / "new"), "--init-from", str(ck)],
                         capsys)  # fmt: skip
    assert code == 0, err
    assert (tmp_path / "new" / "result.json").exists() and not _leftovers(tmp_path)


# ----------------------------------------------------------------------------- symlinks


def test_symlinked_out_is_written_through_and_kept(tmp_path, capsys, stub_fit):
    proj = _project(tmp_path)
    cfg = str(proj / "scene.toml")
    real = tmp_path / "disk" / "results"
    real.mkdir(parents=True)
    link = tmp_path / "link"
    link.symlink_to(real, target_is_directory=True)
    assert run(["fit", cfg, "--out", str(link)], capsys)[0] == 0
    assert link.is_symlink() and (real / "result.json").exists()
    (real / "stale.txt").write_text("old run")
    code, _, err = run(["fit", cfg, "--out", str(link)], capsys)
    assert_usage_error(code, err, "not empty")
    assert run(["fit", cfg, "--out", str(link), "--overwrite"], capsys)[0] == 0
    assert link.is_symlink() and sorted(p.name for p in real.iterdir()) == ["result.json"]
    dangling = tmp_path / "dangling"
    dangling.symlink_to(tmp_path / "disk" / "later")
    assert run(["fit", cfg, "--out", str(dangling)], capsys)[0] == 0
    assert dangling.is_symlink() and (tmp_path / "disk" / "later" / "result.json").exists()
    to_proj = tmp_path / "to_proj"
    to_proj.symlink_to(proj, target_is_directory=True)
    code, _, err = run(["fit", cfg, "--out", str(to_proj), "--overwrite"], capsys)
    assert_usage_error(code, err, "holds an input")
    loop = tmp_path / "loop"
    loop.symlink_to(loop)
    code, _, err = run(["fit", cfg, "--out", str(loop)], capsys)
    assert code == 2 and "--out" in err, err
    assert (proj / "notes.txt").read_text() == "my notes" and not _leftovers(tmp_path)


# ----------------------------------------------------------------------------- lock and commit


def test_a_second_writer_is_refused_at_once_and_the_lock_goes_with_the_first(tmp_path):
    out = tmp_path / "a" / "b" / "res"
    first = OutputDir(out)
    assert (out.parent / ".res.lock").read_text().strip() == str(os.getpid())
    with pytest.raises(UsageError, match=rf"being written by another diffcloth run \(process "
                       rf"{os.getpid()}\)"):  # fmt: skip
        OutputDir(out, overwrite=True)
    (first.tmp / "x.txt").write_text("1")
    first.commit()
    assert (out / "x.txt").read_text() == "1" and not _leftovers(tmp_path)
    assert oct(out.stat().st_mode & 0o777) != oct(0o700)  # a results folder, not a private one
    with pytest.raises(UsageError, match="not empty"):
        OutputDir(out)
    second = OutputDir(out, overwrite=True)
    second.discard()  # nothing written: the older result stays
    assert (out / "x.txt").read_text() == "1" and not _leftovers(tmp_path)
    third = OutputDir(tmp_path / "new" / "deeper" / "res")
    third.discard()  # the parents it made go too
    assert not (tmp_path / "new").exists()


def test_commit_refuses_a_folder_filled_meanwhile_and_stale_temporaries_go(tmp_path):
    out = tmp_path / "res"
    d = OutputDir(out)
    (d.tmp / "mine.txt").write_text("this run")
    out.mkdir()
    (out / "theirs.txt").write_text("another program")
    with pytest.raises(UsageError, match="filled by another program"):
        d.commit()
    assert sorted(p.name for p in out.iterdir()) == ["theirs.txt"] and not _leftovers(tmp_path)
    stale = tmp_path / ".res.tmp-killed"  # a run killed with SIGKILL left it behind
    stale.mkdir()
    (stale / "half.npz").write_text("")
    OutputDir(out, overwrite=True).discard()
    assert not stale.exists()
    empty = tmp_path / "empty"
    empty.mkdir()
    e = OutputDir(empty)  # an empty folder is replaced in one rename
    (e.tmp / "r").write_text("ok")
    e.commit()
    assert (empty / "r").read_text() == "ok"


def test_two_processes_into_one_new_out_exactly_one_succeeds(tmp_path):
    cfg = write(tmp_path, TINY.replace("num_frames = 3", "num_frames = 30"))
    out = tmp_path / "same"
    env = dict(os.environ, DIFFCLOTH_CACHE="off")
    cmd = [sys.executable, "-m", "diffcloth", "simulate", cfg, "--out", str(out), "--chunk", "1"]
    procs = [subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                              env=env, cwd=tmp_path) for _ in range(2)]  # fmt: skip
    outs = [p.communicate(timeout=120) for p in procs]
    results = [(p.returncode, o, e) for p, (o, e) in zip(procs, outs, strict=True)]
    codes = sorted(r[0] for r in results)
    assert codes == [0, 2], results
    loser = next(r for r in results if r[0] == 2)
    assert loser[2].startswith("error: --out") and "Traceback" not in loser[2], loser
    assert "being written by another diffcloth run" in loser[2] or "not empty" in loser[2], loser
    assert np.load(out / "trajectory.npz")["x"].shape[0] == 30 and not _leftovers(tmp_path)


# ----------------------------------------------------------------------------- bench


def test_bench_out_is_an_output_folder(tmp_path, capsys):
    code, _, err = run(["bench", "surface", "--out", str(ROOT / "benchmarks")], capsys)
    assert_usage_error(code, err, "holds an input", "benchmark script")
    old = tmp_path / "bench"
    old.mkdir()
    (old / "surface.jsonl").write_text('{"bench": "earlier"}\n')
    code, _, err = run(["bench", "surface", "--out", str(old)], capsys)
    assert_usage_error(code, err, "not empty", "--overwrite")
    code, _, err = run(["bench", "surface", "--out", str(old), "--overwrite",
                        "--args=--no-such-option"], capsys)  # fmt: skip
    assert code == 1 and "failed" in err and "unchanged" in err, err
    assert (old / "surface.jsonl").read_text() == '{"bench": "earlier"}\n'
    assert not _leftovers(tmp_path)


# ----------------------------------------------------------------------------- fuzz

LAYOUTS = [
    "proj", "proj/targets", "proj/targets/sub", "proj/scene.toml", "proj/notes.txt", "ck",
    "ck/checkpoint.npz", ".", "out/new", "out/existing", "out/empty", "out/file.txt",
    "link_proj", "link_targets", "link_out", "link_dangling", "out/new/../../proj",
]  # fmt: skip


def _fuzz_root(root: Path) -> None:
    _project(root)
    (root / "out" / "existing").mkdir(parents=True)
    (root / "out" / "existing" / "old.txt").write_text("an older result")
    (root / "out" / "empty").mkdir()
    (root / "out" / "file.txt").write_text("a file")
    for name, target in (
        ("link_proj", "proj"),
        ("link_targets", "proj/targets"),
        ("link_out", "out/existing"),
        ("link_dangling", "out/later"),
    ):
        (root / name).symlink_to(root / target)  # fmt: skip


def _is_protected(root: Path, out: str, init_from: bool) -> bool:
    real = (root / out).resolve()
    inputs = [root / "proj" / "scene.toml", root / "proj" / "targets"]
    inputs += [root / "ck" / "checkpoint.npz"] if init_from else []
    return real == root.resolve() or any(
        real == i.resolve() or real in i.resolve().parents or (i.is_dir() and i.resolve() in
        real.parents) for i in inputs)  # fmt: skip


@settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck))
@given(
    cmd=st.sampled_from(["fit", "fit-init", "simulate-refused"]),
    out=st.sampled_from(LAYOUTS),
    overwrite=st.booleans(),
    resume=st.booleans(),
)
def test_fuzz_output_layouts_never_change_an_input(cmd, out, overwrite, resume):
    """Every layout of --out against the inputs: after the run, every input is byte-identical,
    no temporary folder or lock is left, and a refused --out names the reason."""
    with tempfile.TemporaryDirectory() as tmp, pytest.MonkeyPatch.context() as mp:
        root = Path(tmp)
        _fuzz_root(root)
        mp.chdir(root)
        mp.setattr(experiment, "_run_fit", _fake_run_fit)
        init = cmd == "fit-init"
        before = _snapshot(root, ("proj", "ck") if init else ("proj",))
        argv = ["fit" if cmd != "simulate-refused" else "simulate", "proj/scene.toml", "--out", out]
        argv += ["--overwrite"] * overwrite + ["--init-from", "ck"] * init
        argv += ["--resume"] * (resume and cmd == "fit")
        if cmd == "simulate-refused" and not _is_protected(root, out, False):
            argv += ["--frames", "0"]  # refused by its option check: nothing is compiled
        code = _quiet_main(argv)
        assert _snapshot(root, ("proj", "ck") if init else ("proj",)) == before, (argv, code)
        assert not _leftovers(root), argv
        assert code in (0, 2), (argv, code)
        if _is_protected(root, out, init):
            assert code == 2, argv
        real = (root / out).resolve()
        if code == 0:
            assert (real / "result.json").exists(), argv
        elif real.is_dir() and (root / out).name == "existing":
            assert (real / "old.txt").read_text() == "an older result"


def _fake_run_fit(config_path, settings, sc, targets, out, ckpt, *a, **k):
    (out.tmp / "result.json").write_text("{}")
    return {"status": "max_steps", "params": {}, "loss": 0.0, "iterations": 0, "total_s": 0.0}


def _quiet_main(argv) -> int:
    import contextlib
    import io

    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        return main(argv)
