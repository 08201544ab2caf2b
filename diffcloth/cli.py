"""Command line: `diffcloth simulate | render | fit CONFIG --out DIR`, `diffcloth drape fit |
predict | suite` (also `python -m diffcloth`)."""

# ruff: noqa: F401  (re-exports: names moved to sibling modules stay importable here)
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from diffcloth.cli_commands import (
    _check_positive,
    _config_x64,
    _err,
    _force_host_devices,
    _render,
    _simulate,
    check_config,
    resolve_config,
)


def _fit(args) -> int:
    from diffcloth.outdir import UsageError

    if args.devices is not None:
        if args.devices < 1:
            raise UsageError(f"--devices must be >= 1, got {args.devices}")
        _force_host_devices(args.devices)
    import jax

    if args.devices is not None and args.devices > jax.device_count():
        raise UsageError(
            f"--devices {args.devices} but JAX sees {jax.device_count()} device(s) "
            f"({jax.devices()[0].platform}); on CPU set XLA_FLAGS="
            f"--xla_force_host_platform_device_count={args.devices} before JAX starts"
        )
    if args.x64 or _config_x64([args.config]):  # --x64 or [fit] x64 = true
        jax.config.update("jax_enable_x64", True)
    _check_positive("--steps", args.steps)
    from diffcloth.experiment import run_fit_config
    from diffcloth.fit.interrupt import catch_interrupts

    print(f"diffcloth fit {args.config} -> {args.out}", flush=True)
    with catch_interrupts() as stop:
        summary = run_fit_config(
            args.config,
            args.out,
            smoke=args.smoke,
            steps=args.steps,
            devices=args.devices,
            overwrite=args.overwrite,
            resume=args.resume,
            init_from=args.init_from,
            stop=stop,
            allow_unstable=args.allow_unstable,
        )
    status = summary.get("status")
    if status == "interrupted":
        print(
            f"interrupted after {summary['iterations']} steps: checkpoint and partial report in "
            f"{summary['out_dir']}; continue with: diffcloth fit {args.config} --out "
            f"{summary['out_dir']} --resume",
            file=sys.stderr,
        )
        return 128 + (getattr(stop, "signum", None) or 2)  # SIGINT 130, SIGTERM 143
    if summary.get("diagnosis"):
        print(f"  stopped on a non-finite loss; stage check: {summary['diagnosis']}")
    for name, row in summary["params"].items():
        err = row.get("relative_error")
        tail = f"  relative error {err:.2%}" if err is not None else ""
        print(f"  {name}: initial {row['initial']}  fitted {row['fitted']}{tail}")
    loss = summary["loss"]
    print(
        f"{status}: loss {'-' if loss is None else format(loss, '.4g')} after "
        f"{summary['iterations']} steps, {summary['total_s']:.1f} s in all; wrote "
        f"{summary['out_dir']}/report.md"
    )
    if status == "nonfinite":
        _err(f"the fit stopped on a non-finite loss or gradient ({summary['message']})")
        return 1
    return 0


def _warmup(args) -> int:
    from diffcloth.outdir import UsageError
    from diffcloth.runtime import cache_disabled, check_cache_dir

    if args.no_cache or (args.cache is None and cache_disabled()):
        raise UsageError(
            "warmup fills the compilation cache: drop --no-cache (and DIFFCLOTH_CACHE=off), "
            "or name a folder with --cache DIR"
        )
    try:  # JAX only logs when it cannot write an entry: an unusable cache would keep nothing
        check_cache_dir(args.cache)
    except OSError as err:
        raise UsageError(f"warmup: {err}") from None
    import jax

    if args.x64 or _config_x64(args.configs):  # warm up what `fit` will run
        jax.config.update("jax_enable_x64", True)
    from diffcloth.warmup import warmup

    print(f"diffcloth warmup -> {jax.config.jax_compilation_cache_dir}", flush=True)
    warmup(args.configs, smoke=args.smoke)
    print("done: a `diffcloth fit` of these configs with this cache now skips compilation")
    return 0


def _check_view_args(args) -> None:
    """Everything `diffcloth view` can check before it simulates (UsageError, exit 2): the port
    and host to serve on, the image size and level, and that --export can be written."""
    import os
    import socket

    from diffcloth.outdir import UsageError

    if not 0 <= args.port <= 65535:
        raise UsageError(f"--port {args.port} is out of range; allowed 0-65535 (0: any free port)")
    if args.export is None:
        try:
            socket.getaddrinfo(args.host, args.port, type=socket.SOCK_STREAM)
        except (OSError, UnicodeError) as err:
            raise UsageError(
                f"--host {args.host!r} is not an address to serve on ({err})"
            ) from None
    if not 1 <= args.size <= 8192:
        raise UsageError(f"--size {args.size} is out of range; allowed 1-8192 (pixels)")
    if args.level is not None and not 2 <= args.level <= 64:
        raise UsageError(f"--level {args.level} is out of range; allowed 2-64")
    if args.overlay and args.export is None:
        raise UsageError("--overlay applies to --export (a recording); add --export FILE.html")
    if args.export is not None:
        from diffcloth.outdir import config_inputs
        from diffcloth.runtime import unwritable_folder

        path = Path(args.export)
        if path.is_dir():
            raise UsageError(f"--export {str(path)!r} is a folder; give a file, e.g. view.html")
        src = Path(args.path)
        inputs = config_inputs(src) if src.is_file() else [("the result folder", src)]
        for label, inp in inputs:  # never write over an input of the run
            try:
                full = path.resolve()
                same = path.exists() and (full == inp.resolve() or inp.resolve() in full.parents)
            except OSError:
                same = False
            if same:
                raise UsageError(
                    f"--export {str(path)!r} is an input of this run ({label}); choose another file"
                )
        parent = path.parent
        while not parent.exists() and parent != parent.parent:
            parent = parent.parent  # the folder export_html would create the file under
        if not parent.is_dir():
            raise UsageError(f"--export {str(path)!r}: {str(parent)!r} is not a folder")
        why = unwritable_folder(parent)
        if why is None and path.exists() and not os.access(path, os.W_OK):
            why = "the file is not writable"
        if why:
            raise UsageError(f"--export {str(path)!r}: {str(parent)!r}: {why}")


def _view(args) -> int:
    _check_view_args(args)
    try:
        from diffcloth.view.cli import run
    except ImportError as err:
        if (err.name or "").split(".")[0] != "viser":
            raise
        print(
            "error: `diffcloth view` needs the viewer extra (viser): pip install 'diffcloth[view]'",
            file=sys.stderr,
        )
        return 2
    return run(args)


UNSTABLE_HELP = (
    "only warn (instead of refusing before any work) when dt/num_substeps exceeds the explicit "
    "stability estimate"
)

BENCHMARKS = ("physics", "surface", "render", "shading", "rigid", "memory")


def _bench(args) -> int:
    """Run the stage benchmarks of a source checkout (benchmarks/*.py); each prints JSON lines."""
    import shlex

    root = Path(__file__).resolve().parents[1] / "benchmarks"
    if not root.is_dir():
        print(
            f"error: no benchmarks/ folder next to the package ({root}); the benchmarks ship with "
            "the source checkout (git clone, then pip install -e .)",
            file=sys.stderr,
        )
        return 2
    stages = args.stages or list(BENCHMARKS)
    unknown = [st for st in stages if st not in BENCHMARKS]
    if unknown:
        print(
            f"error: unknown benchmark(s) {unknown}; allowed: {', '.join(BENCHMARKS)}",
            file=sys.stderr,
        )
        return 2
    out = None
    if args.out is not None:  # checked, locked and written as a whole, like every --out
        from diffcloth.outdir import OutputDir

        scripts = [("benchmark script", root / f"{st}.py") for st in stages]
        out = OutputDir(args.out, overwrite=args.overwrite, inputs=scripts)
    for stage in stages:
        cmd = [sys.executable, str(root / f"{stage}.py")]
        if args.quick and "--quick" in (root / f"{stage}.py").read_text():
            cmd.append("--quick")
        cmd += shlex.split(args.args or "")
        print(f"# {' '.join(cmd)}", flush=True)
        code, stdout = _child(cmd, capture=out is not None)
        if out is not None:
            (out.tmp / f"{stage}.jsonl").write_text(stdout)
            print(stdout, end="", flush=True)
        if code:
            kept = "; nothing written to --out (an older result there is unchanged)" if out else ""
            if out is not None:
                out.discard()
            print(f"error: benchmark {stage} failed (exit {code}){kept}", file=sys.stderr)
            return 1
    if out is not None:
        out.commit()
    return 0


def _child(cmd, *, capture: bool) -> tuple[int, str]:
    """Run a child process; a signal that aborts this command stops it too."""
    import subprocess

    from diffcloth import signals

    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE if capture else None, text=True)
    hook = signals.at_abort(proc.kill)
    try:
        stdout, _ = proc.communicate()
    finally:
        signals.forget(hook)
    return proc.returncode, stdout or ""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="diffcloth", description=__doc__)
    from diffcloth import __version__

    parser.add_argument("--version", action="version", version=f"diffcloth {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    cache = argparse.ArgumentParser(add_help=False)
    cache.add_argument(
        "--cache",
        default=None,
        metavar="DIR",
        help="JAX persistent compilation cache folder (default $DIFFCLOTH_CACHE or "
        "~/.cache/diffcloth/jax): a second run of the same config skips compilation",
    )
    cache.add_argument("--no-cache", action="store_true", help="do not use the compilation cache")
    cache.add_argument(
        "--debug", action="store_true", help="show Python tracebacks instead of one-line errors"
    )
    cache.add_argument(
        "--overwrite",
        action="store_true",
        help="replace a non-empty --out folder (as a whole: no file of the old run survives)",
    )
    p = sub.add_parser(
        "simulate", parents=[cache], help="simulate a config; write DIR/trajectory.npz"
    )
    p.add_argument("config", help="scene TOML (see docs/config.md)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--frames", type=int, default=None, help="override [sim] num_frames")
    p.add_argument("--chunk", type=int, default=10, help="frames per progress line")
    p.add_argument("--x64", action="store_true", help="simulate in float64")
    p.add_argument("--obj", action="store_true", help="also write DIR/obj/frame_*.obj surfaces")
    p.add_argument("--level", type=int, default=4, help="tessellation level for --obj")
    p.add_argument("--allow-unstable", action="store_true", help=UNSTABLE_HELP)
    p.set_defaults(func=_simulate)
    r = sub.add_parser(
        "render",
        parents=[cache],
        help="simulate and render a config; write DIR/video.mp4 (or .gif) and PNGs",
    )
    r.add_argument(
        "config", help="scene TOML (e.g. configs/drape.toml, configs/ball_into_cloth.toml)"
    )
    r.add_argument("--out", required=True, help="output folder")
    r.add_argument("--size", type=int, default=None, help="override [render] width and height")
    r.add_argument("--frames", type=int, default=None, help="override [sim] num_frames")
    r.add_argument("--format", choices=("mp4", "gif"), default="mp4", help="video format")
    r.add_argument("--fps", type=float, default=30.0)
    r.add_argument("--chunk", type=int, default=10, help="frames rendered per compiled call")
    r.add_argument("--npy", action="store_true", help="also write the linear video as video.npy")
    r.add_argument("--x64", action="store_true", help="run in float64")
    r.add_argument("--allow-unstable", action="store_true", help=UNSTABLE_HELP)
    r.set_defaults(func=_render)
    b = sub.add_parser("bench", help="run the stage benchmarks (JSON lines); needs the checkout")
    b.add_argument("stages", nargs="*", help=f"some of {', '.join(BENCHMARKS)} (default: all)")
    b.add_argument("--quick", action="store_true", help="small sizes, fewer repeats")
    b.add_argument("--out", default=None, help="also write DIR/<stage>.jsonl")
    b.add_argument(
        "--overwrite", action="store_true", help="replace a non-empty --out folder (as a whole)"
    )
    b.add_argument(
        "--args", default=None, help='extra arguments for the script(s), e.g. "--repeats 3"'
    )
    b.set_defaults(func=_bench)
    f = sub.add_parser(
        "fit", parents=[cache], help="fit scene parameters to target images; write DIR/report.md"
    )
    f.add_argument("config", help="scene + [fit] TOML (e.g. configs/drape_fit.toml)")
    f.add_argument("--out", required=True, help="output folder")
    f.add_argument("--steps", type=int, default=None, help="override [fit] steps")
    f.add_argument("--smoke", action="store_true", help="tiny sizes, 2 steps (CI)")
    f.add_argument(
        "--resume",
        action="store_true",
        help="continue from --out/checkpoint.npz (written every 10 steps and on Ctrl-C/SIGTERM); "
        "ends where an uninterrupted fit with the same steps ends",
    )
    f.add_argument(
        "--init-from",
        metavar="CHECKPOINT",
        default=None,
        help="start a new fit from the best parameters of an earlier fit's checkpoint.npz (or "
        "its folder), e.g. after its config or targets changed, where --resume refuses",
    )
    f.add_argument("--x64", action="store_true", help="fit in float64")
    f.add_argument("--allow-unstable", action="store_true", help=UNSTABLE_HELP)
    f.add_argument(
        "--devices",
        type=int,
        default=None,
        help="spread the [fit] multistart guesses over N devices (GPUs, or N CPU devices); "
        "overrides [fit] devices",
    )
    f.set_defaults(func=_fit)
    w = sub.add_parser(
        "warmup",
        parents=[cache],
        help="compile fit configs into the compilation cache, so that their first fit is warm",
    )
    w.add_argument("configs", nargs="+", help="fit TOML(s), e.g. configs/drape_fit.toml")
    w.add_argument("--smoke", action="store_true", help="warm up `fit --smoke` instead")
    w.add_argument("--x64", action="store_true", help="warm up `fit --x64` instead")
    w.set_defaults(func=_warmup)
    v = sub.add_parser("view", parents=[cache], help="open a scene or fit result in the browser")
    v.add_argument("path", help="scene TOML or fit result folder (see docs/viewer.md)")
    v.add_argument("--host", default="127.0.0.1", help="address to serve on (default: local only)")
    v.add_argument("--port", type=int, default=8080)
    v.add_argument("--export", metavar="HTML", help="write a self-contained recording instead")
    v.add_argument("--overlay", action="store_true", help="--export: a fit's target over the fit")
    v.add_argument("--level", type=int, default=None, help="tessellation level of the 3D cloth")
    v.add_argument("--size", type=int, default=256, help="image size of the render panel")
    v.add_argument("--paused", action="store_true", help="start paused at the last frame")
    v.set_defaults(func=_view)
    from diffcloth.drape.cli import add_drape_parser

    add_drape_parser(sub, [cache])
    return parser


def main(argv=None) -> int:
    """Run the CLI; returns the exit code: 0 done, 1 failed (blow-up, non-finite fit, internal
    error), 2 bad usage or config (a one-line message naming the key/file/option), 130 / 143
    interrupted by SIGINT / SIGTERM (`diffcloth.signals`). `--debug` shows the traceback instead."""
    args = build_parser().parse_args(argv)
    _resolve_configs(args)
    from diffcloth.signals import handle_signals, signal_name

    with handle_signals() as sig:  # SIGINT / SIGTERM for every command (diffcloth.signals)
        code = _run(args)
    if sig.signum is not None and code == 0:  # the signal came as the command finished
        print(f"\n{signal_name(sig.signum)} received as the run finished; its results are "
              "complete", file=sys.stderr)  # fmt: skip
        code = sig.exit_code
    if sig.signum is not None and argv is None:  # our own process: skip the teardown, where
        sys.stdout.flush()  # XLA's threads can crash a process interrupted mid-call
        sys.stderr.flush()
        os._exit(code)
    return code


def _resolve_configs(args) -> None:
    """A config path that is not on disk but names a shipped config (`configs/drape_fit.toml` run
    outside the checkout) reads the shipped copy (`cli_commands.resolve_config`)."""
    if args.command in ("simulate", "render", "fit"):
        args.config = resolve_config(args.config)
    elif args.command == "warmup":
        args.configs = [resolve_config(c) for c in args.configs]
    elif args.command == "view" and args.path.endswith(".toml"):
        args.path = resolve_config(args.path)


def _run(args) -> int:
    debug = getattr(args, "debug", False)
    import warnings

    shown = warnings.showwarning
    if not debug:  # warnings as one line each, like the errors

        def one_line(message, category, filename, lineno, file=None, line=None):
            print(f"warning: {message}", file=sys.stderr, flush=True)

        warnings.showwarning = one_line
    try:
        from diffcloth.runtime import cache_disabled, enable_compilation_cache

        explicit = getattr(args, "cache", None) is not None
        if not getattr(args, "no_cache", True) and (explicit or not cache_disabled()):
            try:
                enable_compilation_cache(args.cache)
            except OSError as err:  # a read-only home, say: run without the cache
                if args.command != "warmup":  # warmup needs it: _warmup refuses (exit 2)
                    print(f"warning: compilation cache disabled ({err})", file=sys.stderr)
        return args.func(args)
    except KeyboardInterrupt:
        _discard()
        if debug:
            raise
        print("\ninterrupted (nothing written)", file=sys.stderr)
        return 130
    except Exception as err:  # noqa: BLE001  (one line for the user; --debug for the trace)
        _discard()
        if debug:
            raise
        return _report_error(err)
    finally:
        warnings.showwarning = shown


def _discard() -> None:
    from diffcloth.outdir import discard_all

    discard_all()


def _report_error(err: Exception) -> int:
    from diffcloth.physics.rollout import UnstableSimulationError, UnstableStepError

    if isinstance(err, (UnstableSimulationError, UnstableStepError)):
        _err(str(err))
        return 1
    if isinstance(err, (ValueError, TypeError, OSError, MemoryError)):
        # ConfigError, UsageError and MemoryLimitError are ValueErrors; OSError: missing or
        # unreadable files; TypeError/ValueError from the library name the bad argument
        msg = str(err) or type(err).__name__
        if isinstance(err, OSError) and err.filename:
            msg = f"{err.strerror or err}: {err.filename}"
        if isinstance(err, MemoryError):
            msg = "out of memory; lower the image size, num_frames or the net size"
        _err(msg.splitlines()[0] if len(msg) > 2000 else msg)
        return 2
    _err(f"internal error ({type(err).__name__}: {err}); rerun with --debug for the traceback")
    return 1


if __name__ == "__main__":
    raise SystemExit(main())
