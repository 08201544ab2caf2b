"""Issue 35, class 3: SIGINT and SIGTERM in every command (diffcloth.signals): exit 130 / 143,
no crash after a compiled call, no traceback from a garbage-collector callback, and either a
complete result or nothing.

The handler's rules are tested in-process (`signals._exit` replaced, so that an abort raises
SystemExit instead of ending pytest); real signals go to a few real processes, run side by side
where they can (each imports JAX: about 5 s).
"""

import contextlib
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from test_hardening import TINY, run, write

from diffcloth import experiment, signals
from diffcloth.outdir import OutputDir

ENV = dict(os.environ, DIFFCLOTH_CACHE="off", PYTHONUNBUFFERED="1")


@pytest.fixture
def no_exit(monkeypatch):
    def fake_exit(code):
        raise SystemExit(code)

    monkeypatch.setattr(signals, "_exit", fake_exit)


def _leftovers(root: Path) -> list[str]:
    return [str(p) for p in root.rglob(".*") if ".tmp-" in p.name or p.name.endswith(".lock")]


# ----------------------------------------------------------------------------- the handler


def test_abort_discards_the_temporary_folder_and_exits_128_plus_signum(tmp_path, no_exit, capsys):
    before = signal.getsignal(signal.SIGTERM)
    with signals.handle_signals() as st:
        out = OutputDir(tmp_path / "res")
        (out.tmp / "half.npz").write_text("")
        with pytest.raises(SystemExit) as exc:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(1)  # the handler runs at the next bytecode
    assert exc.value.code == 143 and st.exit_code == 143
    assert not (tmp_path / "res").exists() and not _leftovers(tmp_path)
    assert "interrupted by SIGTERM (nothing written)" in capsys.readouterr().err
    assert signal.getsignal(signal.SIGTERM) is before  # put back


def test_cooperative_first_signal_sets_the_event_second_aborts(tmp_path, no_exit, capsys):
    before = signal.getsignal(signal.SIGINT)
    with signals.handle_signals() as st, st.cooperate() as stop:
        out = OutputDir(tmp_path / "res")
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.1)
        assert stop.is_set() and stop.signum == signal.SIGINT and out.tmp.exists()
        assert "stopping after the current step" in capsys.readouterr().err
        with pytest.raises(SystemExit) as exc:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(1)
    assert exc.value.code == 143 and not _leftovers(tmp_path)
    assert signal.getsignal(signal.SIGINT) is before


def test_a_signal_during_the_commit_waits_for_it(tmp_path, no_exit, capsys):
    with signals.handle_signals():
        out = OutputDir(tmp_path / "res")
        (out.tmp / "done.txt").write_text("complete")
        with pytest.raises(SystemExit) as exc, signals.deferred("the results are complete"):
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.1)  # handled here, acted on when the block ends
            out.commit()
    assert exc.value.code == 130 and (tmp_path / "res" / "done.txt").read_text() == "complete"
    assert "(the results are complete)" in capsys.readouterr().err and not _leftovers(tmp_path)


def test_catch_interrupts_outside_the_cli_keeps_its_own_handlers():
    from diffcloth.fit.interrupt import catch_interrupts

    before = signal.getsignal(signal.SIGINT)
    with catch_interrupts(message=False) as stop:
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.1)
        assert stop.is_set() and stop.signum == signal.SIGINT
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1)
    assert signal.getsignal(signal.SIGINT) is before


def test_fit_stopped_by_sigterm_exits_143(tmp_path, capsys, monkeypatch):
    """The fit's cooperative stop keeps the signal's exit code (the fit itself is a stub here;
    test_hardening.py case 2 runs the real one)."""
    from test_hardening import FIT, TRUTH

    from diffcloth.fit import interrupt

    @contextlib.contextmanager
    def fake(*a, **k):
        ev = threading.Event()
        ev.signum = signal.SIGTERM
        ev.set()
        yield ev

    def stub(config_path, settings, sc, targets, out, ckpt, stop, *a, **k):
        assert stop.is_set()
        (out.tmp / "checkpoint.npz").write_text("")
        return {"status": "interrupted", "iterations": 1, "params": {}, "loss": 1.0}

    monkeypatch.setattr(interrupt, "catch_interrupts", fake)
    monkeypatch.setattr(experiment, "_run_fit", stub)
    cfg = write(tmp_path, TINY + FIT + TRUTH)
    code, _, err = run(["fit", cfg, "--out", str(tmp_path / "o")], capsys)
    assert code == 143 and "--resume" in err, err
    assert (tmp_path / "o" / "checkpoint.npz").exists()


# ----------------------------------------------------------------------------- real processes


def _start(argv, cwd, **kw):
    return subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=ENV, cwd=cwd, **kw)  # fmt: skip


def _wait_line(proc, text, timeout=120):
    t = time.time()
    while time.time() - t < timeout:
        line = proc.stdout.readline()
        if text in line:
            return line
        if not line and proc.poll() is not None:
            break
    raise AssertionError(f"no line with {text!r} (exit {proc.poll()})")


def _finish(proc, timeout=120):
    out, err = proc.communicate(timeout=timeout)
    return proc.returncode, out, err


LONG = (TINY.replace("rows = 4", "rows = 40").replace("cols = 4", "cols = 40")
        .replace("pinned = [[0, 0], [0, 3]]", "pinned = [[0, 0], [0, 39]]")
        .replace("num_frames = 3", "num_frames = 800")
        .replace("num_substeps = 20", "num_substeps = 100"))  # fmt: skip


def test_simulate_sigint_in_a_long_compiled_call_and_sigterm_keep_old_results(tmp_path):
    """Two processes side by side: SIGINT during one long compiled call exits 130 (not 139) and
    leaves nothing; SIGTERM of a run into an older result (--overwrite) exits 143 and leaves the
    older result byte-identical. Neither leaves a hidden temporary folder or a lock."""
    cfg = write(tmp_path, LONG)
    old = tmp_path / "old"
    old.mkdir()
    (old / "trajectory.npz").write_bytes(b"an older result")
    sim = [sys.executable, "-m", "diffcloth", "simulate", cfg, "--chunk", "800"]
    a = _start([*sim, "--out", str(tmp_path / "new")], tmp_path)
    b = _start([*sim, "--out", str(old), "--overwrite", "--chunk", "100"], tmp_path)
    for proc in (a, b):
        _wait_line(proc, "diffcloth simulate")
    time.sleep(2.0)  # compiling or inside the compiled rollout
    a.send_signal(signal.SIGINT)
    b.send_signal(signal.SIGTERM)
    (ca, _, ea), (cb, _, eb) = _finish(a), _finish(b)
    assert ca == 130 and "interrupted by SIGINT" in ea and "Traceback" not in ea, (ca, ea)
    assert cb == 143 and "interrupted by SIGTERM" in eb and "Traceback" not in eb, (cb, eb)
    assert not (tmp_path / "new").exists()
    assert (old / "trajectory.npz").read_bytes() == b"an older result"
    assert sorted(p.name for p in old.iterdir()) == ["trajectory.npz"] and not _leftovers(tmp_path)


GC_SCRIPT = """
import gc, os, signal, sys
from diffcloth import signals
from diffcloth.outdir import OutputDir

with signals.handle_signals() as st, st.cooperate(message=False) as stop:
    out = OutputDir(sys.argv[1])
    def callback(phase, info):
        if phase == "start":
            os.kill(os.getpid(), signal.SIGINT)
            for _ in range(1000):  # a few bytecodes: the handler runs inside this callback
                pass
    gc.callbacks.append(callback)
    gc.collect()
    assert stop.is_set(), "the first signal only sets the event"
    gc.collect()
    print("still running after the second signal")
"""


def test_second_sigint_in_a_gc_callback_and_fit_double_sigint(tmp_path):
    """A second Ctrl-C that lands in a garbage-collector callback still stops the process (no
    "Exception ignored" traceback); a fit stopped by two Ctrl-C writes nothing."""
    script = write(tmp_path, GC_SCRIPT, "gc_signal.py")
    g = _start([sys.executable, script, str(tmp_path / "gc_out")], tmp_path)
    cfg = write(tmp_path, TINY + '[fit]\nfree = ["bend"]\nsteps = 50\n[truth]\nbend = 2e-3\n')
    f = _start([sys.executable, "-m", "diffcloth", "fit", cfg, "--out", str(tmp_path / "fit")],
               tmp_path)  # fmt: skip
    _wait_line(f, "diffcloth fit")
    time.sleep(1.0)
    f.send_signal(signal.SIGINT)
    time.sleep(0.5)
    f.send_signal(signal.SIGINT)
    cg, og, eg = _finish(g)
    assert cg == 130 and "still running" not in og, (cg, og, eg)
    assert "Exception ignored" not in eg and "Traceback" not in eg, eg
    cf, of, ef = _finish(f)
    assert cf == 130 and "stopping after the current step" in ef, (cf, ef)
    assert "interrupted by SIGINT (nothing written)" in ef and "Traceback" not in ef, ef
    assert not (tmp_path / "fit").exists() and not (tmp_path / "gc_out").exists()
    assert not _leftovers(tmp_path)


def test_bench_sigterm_stops_its_benchmark_too(tmp_path):
    b = _start([sys.executable, "-m", "diffcloth", "bench", "physics", "--out",
                str(tmp_path / "b")], tmp_path)  # fmt: skip
    _wait_line(b, "# ")
    time.sleep(1.0)
    children = Path(f"/proc/{b.pid}/task/{b.pid}/children").read_text().split()
    assert children, "the benchmark runs in a child process"
    b.send_signal(signal.SIGTERM)
    code, _, err = _finish(b)
    assert code == 143 and "interrupted by SIGTERM" in err, (code, err)
    time.sleep(0.5)
    for pid in children:
        stat = Path(f"/proc/{pid}/stat")
        assert not stat.exists() or stat.read_text().split(") ")[1][0] == "Z", pid
    assert not (tmp_path / "b").exists() and not _leftovers(tmp_path)


@pytest.mark.slow  # a real fit to its first step (about 25 s)
def test_fit_sigterm_writes_checkpoint_and_exits_143(tmp_path):
    fit = '[fit]\nfree = ["bend"]\nmethod = "adam"\nsteps = 200\npatience = 1000\n'
    cfg = write(tmp_path, TINY + fit + "identifiability = false\n[truth]\nbend = 2e-3\n")
    f = _start([sys.executable, "-m", "diffcloth", "fit", cfg, "--out", str(tmp_path / "fit")],
               tmp_path)  # fmt: skip
    _wait_line(f, "method:")
    time.sleep(1.0)
    f.send_signal(signal.SIGTERM)
    code, out, err = _finish(f, timeout=300)
    assert code == 143 and "--resume" in err and "Traceback" not in err, (code, err)
    assert (tmp_path / "fit" / "checkpoint.npz").exists() and not _leftovers(tmp_path)
    assert "interrupted" in (tmp_path / "fit" / "report.md").read_text().splitlines()[0]


def test_warmup_abort_removes_its_temporary_folder(tmp_path, no_exit, monkeypatch, capsys):
    from test_hardening import FIT, TRUTH

    from diffcloth.warmup import warmup

    seen = []

    def stub(path, out_dir, **k):
        seen.append(Path(out_dir).parent)
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(1)

    monkeypatch.setattr(experiment, "run_fit_config", stub)
    cfg = write(tmp_path, TINY + FIT + TRUTH)
    with signals.handle_signals(), pytest.raises(SystemExit) as exc:
        warmup([cfg])
    assert exc.value.code == 143 and seen and not seen[0].exists()
