"""Command line: `diffcloth simulate | fit CONFIG --out DIR` (also `python -m diffcloth`)."""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path


def check_config(path, command: str = "render"):
    """The checks `diffcloth COMMAND CONFIG` runs before any work, without running it: the config
    (ConfigError), the memory estimate (MemoryLimitError) and, for render and fit, the Scene and
    the [truth]/[fit.initial] values against it. Returns the Scene (or the Config for simulate).
    """
    from diffcloth import memory
    from diffcloth.config import ConfigError, load_config
    from diffcloth.scene import build_scene

    if command not in ("simulate", "render", "fit"):
        raise ValueError(f"command={command!r}; allowed: simulate, render, fit")
    config = load_config(path)
    if command == "fit" and config.fit is None:
        raise ConfigError(f"{path}: missing [fit] section")
    multistart = config.fit.multistart if command == "fit" else 1
    memory.check_memory(
        memory.estimate_memory(
            memory.JobSizes.from_config(config), command, multistart=multistart
        ),  # fmt: skip
        f"{command} {path}",
    )
    if command == "simulate":
        from diffcloth.config import build_physics
        from diffcloth.scene import build_bodies

        build_physics(config)
        build_bodies(config)
        return config
    scene = build_scene(config)
    if command == "fit":
        from diffcloth.experiment import _check_values

        _check_values(scene, config.fit.truth, "truth")
        _check_values(scene, config.fit.initial, "fit.initial")
    return scene


def _err(msg: str) -> None:
    print(f"error: {msg}", file=sys.stderr, flush=True)


def _check_positive(name: str, value, lo: int = 1) -> None:
    from diffcloth.outdir import UsageError

    if value is not None and value < lo:
        raise UsageError(f"{name} must be >= {lo}, got {value}")


def _simulate(args) -> int:
    import jax

    if args.x64:
        jax.config.update("jax_enable_x64", True)
    import numpy as np

    from diffcloth import memory, physics
    from diffcloth.config import build_physics, load_config
    from diffcloth.outdir import OutputDir
    from diffcloth.physics.rollout import ADVICE
    from diffcloth.pipeline import split_colliders
    from diffcloth.scene import build_bodies

    _check_positive("--frames", args.frames)
    _check_positive("--chunk", args.chunk)
    _check_positive("--level", args.level, 2)
    config = load_config(args.config)
    num_frames = config.sim.num_frames if args.frames is None else args.frames
    memory.check_memory(
        memory.estimate_memory(
            memory.JobSizes.from_config(config, num_frames=num_frames), "simulate",
            chunk=args.chunk,
        ),
        f"simulating {num_frames} frames of a {config.net.rows}x{config.net.cols} net",
        hint="lower num_frames (--frames) or the net size",
    )  # fmt: skip
    scene = build_physics(config)
    bodies, two_way = build_bodies(config)
    net, sim, material = scene.net, scene.sim, scene.material
    out = OutputDir(args.out, overwrite=args.overwrite)
    print(
        f"diffcloth simulate {args.config}: net {net.rows}x{net.cols}, {num_frames} frames, "
        f"{sim.num_substeps} substeps/frame, {sim.integrator}, {len(bodies)} rigid bodies",
        flush=True,
    )
    try:
        physics.check_stability(net, sim, material, error=not args.allow_unstable)
    except ValueError as err:
        out.discard()
        _err(str(err))
        return 1
    chunk = max(1, min(args.chunk, num_frames))
    jitted = {}

    planes, spheres = split_colliders(scene.colliders)

    def run(state, bods, n):
        if n not in jitted:
            if bodies:
                jitted[n] = jax.jit(
                    lambda s, b: physics.coupled_rollout(
                        net, sim, material, s, b, num_frames=n, planes=planes, colliders=spheres,
                        two_way=two_way,
                    )
                )  # fmt: skip
            else:
                jitted[n] = jax.jit(
                    lambda s, b: (
                        physics.rollout(
                            net, sim, material, s, num_frames=n, colliders=scene.colliders
                        ),
                        (),
                    )
                )
        return jitted[n](state, bods)

    last = lambda tree: jax.tree_util.tree_map(lambda a: a[-1], tree)
    state, bods, parts, body_parts = scene.state, bodies, [], []
    done, t0 = 0, time.perf_counter()
    while done < num_frames:
        n = min(chunk, num_frames - done)
        traj, body_traj = run(state, bods, n)
        ok = np.asarray(physics.frames_ok(net, traj, sim, scene.state, first_frame=done))
        for b in body_traj:
            ok = ok & np.isfinite(np.asarray(b.position)).reshape(n, -1).all(axis=1)
        if not ok.all():
            out.discard()
            _err(
                f"unstable: the cloth blew up (non-finite or exploded state) at frame "
                f"{done + int(np.argmin(ok))}; {ADVICE}"
            )
            return 1
        state, bods = last(traj), last(body_traj)
        parts.append(traj)
        body_parts.append(body_traj)
        done += n
        elapsed = time.perf_counter() - t0
        print(f"  frame {done:4d}/{num_frames}  {elapsed:6.1f} s", flush=True)
    x = np.concatenate([np.asarray(p.x) for p in parts])
    v = np.concatenate([np.asarray(p.v) for p in parts])
    extra = {}
    if bodies:  # (T, num_bodies, ...) body states
        for field in ("position", "orientation", "velocity", "angular_velocity"):
            extra[f"body_{field}"] = np.concatenate(
                [np.stack([np.asarray(getattr(b, field)) for b in bt], axis=1) for bt in body_parts]
            )
    np.savez(
        out.tmp / "trajectory.npz",
        x=x,
        v=v,
        rest=np.asarray(net.rest),
        pinned=np.asarray(net.pinned),
        dt=float(np.asarray(sim.dt)),
        **extra,
    )
    if args.obj:
        from diffcloth import surface
        from diffcloth.io import write_obj_sequence

        flip = net.rows >= 2 and config.net.plane == "xz"  # normals up for a horizontal net
        surfaces = jax.jit(jax.vmap(lambda xf: surface.tessellate(xf, args.level, flip=flip)))(x)
        paths = write_obj_sequence(out.tmp / "obj", surfaces)
    dest = out.commit()
    print(f"wrote {dest / 'trajectory.npz'}: x {x.shape} ({time.perf_counter() - t0:.1f} s)")
    if args.obj:
        print(f"wrote {len(paths)} OBJ files (level {args.level}) to {dest / 'obj'}")
    return 0


def _force_host_devices(n: int) -> None:
    """Let JAX's CPU backend expose `n` devices (no effect on GPUs), unless XLA_FLAGS already sets it.

    Must run before JAX initialises a backend; the CLI calls it before any computation.
    """
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_force_host_platform_device_count" not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count={n}".strip()


def _render(args) -> int:
    import jax

    if args.x64:
        jax.config.update("jax_enable_x64", True)
    import numpy as np

    from diffcloth import memory, pipeline
    from diffcloth.config import load_config
    from diffcloth.experiment import video_strip
    from diffcloth.io import save_png, save_video
    from diffcloth.outdir import OutputDir
    from diffcloth.physics.rollout import ADVICE
    from diffcloth.scene import build_scene

    _check_positive("--size", args.size)
    _check_positive("--chunk", args.chunk)
    if not (args.fps > 0 and args.fps < 1000):
        from diffcloth.outdir import UsageError

        raise UsageError(f"--fps must be in (0, 1000), got {args.fps}")
    config = load_config(args.config)
    sizes = memory.JobSizes.from_config(config, size=args.size)
    memory.check_memory(
        memory.estimate_memory(sizes, "render", chunk=args.chunk),
        f"rendering {sizes.num_frames // sizes.frame_stride} frames from {sizes.cameras} "
        f"camera(s) at {sizes.width}x{sizes.height} (net {sizes.rows}x{sizes.cols})",
        hint="lower the image size (--size, [render] width/height), --chunk, num_frames or the "
        "net size",
    )
    overrides = {}
    if args.size is not None:
        overrides.update(width=args.size, height=args.size)
    scene = build_scene(config, overrides=overrides or None)
    T, k = scene.num_frames, scene.frame_stride
    h, w = scene.image_shape
    out = OutputDir(args.out, overwrite=args.overwrite)
    print(
        f"diffcloth render {args.config}: {T} frames (every {k}), {len(scene.cameras)} camera(s) "
        f"{w}x{h}, shading {scene.shading}, level {scene.level} (lod {config.render.lod}), "
        f"culling {'on' if scene.cull else 'off'}, {len(scene.deform)} deformations, "
        f"{len(scene.bodies)} rigid bodies",
        flush=True,
    )
    t0 = time.perf_counter()
    traj, bodies = jax.jit(pipeline.simulate_all)(scene)
    bad = pipeline.first_bad_frame(scene, traj, bodies)
    if bad is not None:
        out.discard()
        _err(f"unstable: the simulation blew up (non-finite or exploded state) at frame {bad}; "
             f"{ADVICE}")  # fmt: skip
        return 1
    print(f"  simulated in {time.perf_counter() - t0:.1f} s", flush=True)
    xs, spheres = pipeline.rendered_states(scene, traj, bodies)
    render_chunk = jax.jit(pipeline.render_frames)
    chunk = max(1, args.chunk)
    parts = []
    for a in range(0, xs.shape[0], chunk):
        sl = slice(a, min(a + chunk, xs.shape[0]))
        sp = None if spheres is None else type(spheres)(spheres.center[sl], spheres.radius)
        if xs[sl].shape[0] != chunk:  # pad the last chunk: one compiled shape
            pad = chunk - xs[sl].shape[0]
            x_part = np.concatenate([xs[sl], np.repeat(xs[sl][-1:], pad, 0)])
            if sp is not None:
                c = np.concatenate([sp.center, np.repeat(sp.center[-1:], pad, 0)])
                sp = type(spheres)(c, sp.radius)
            parts.append(np.asarray(render_chunk(scene, x_part, sp))[:, : chunk - pad])
        else:
            parts.append(np.asarray(render_chunk(scene, xs[sl], sp)))
        done = min(a + chunk, xs.shape[0])
        print(f"  rendered {done:4d}/{xs.shape[0]}  {time.perf_counter() - t0:6.1f} s", flush=True)
    video = np.concatenate(parts, axis=1)  # (cams, T, H, W, 3) linear RGB
    if not np.all(np.isfinite(video)):
        out.discard()
        _err("the rendered video is not finite (a degenerate control net?); nothing written")
        return 1
    strip = video_strip(video)  # linear; the files for people are sRGB-encoded
    path = save_video(out.tmp / f"video.{args.format}", strip, fps=args.fps, colorspace="srgb")
    save_png(out.tmp / "first.png", strip[0], colorspace="srgb")
    save_png(out.tmp / "last.png", strip[-1], colorspace="srgb")
    if args.npy:
        np.save(out.tmp / "video.npy", video.astype(np.float32))  # linear, for programs
    dest = out.commit()
    print(
        f"wrote {dest / path.name}, first.png, last.png (sRGB-encoded"
        f"{'; video.npy linear' if args.npy else ''}) ({time.perf_counter() - t0:.1f} s)"
    )
    return 0


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
    if args.x64:
        jax.config.update("jax_enable_x64", True)
    _check_positive("--steps", args.steps)
    from diffcloth.experiment import run_fit_config
    from diffcloth.fit.interrupt import catch_interrupts

    print(f"diffcloth fit {args.config} -> {args.out}", flush=True)
    with catch_interrupts(message=False) as stop:
        summary = run_fit_config(
            args.config,
            args.out,
            smoke=args.smoke,
            steps=args.steps,
            devices=args.devices,
            overwrite=args.overwrite,
            resume=args.resume,
            stop=stop,
        )
    status = summary.get("status")
    if status == "interrupted":
        print(
            f"interrupted after {summary['iterations']} steps: checkpoint and partial report in "
            f"{summary['out_dir']}; continue with: diffcloth fit {args.config} --out "
            f"{summary['out_dir']} --resume",
            file=sys.stderr,
        )
        return 130
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


def _view(args) -> int:
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


BENCHMARKS = ("physics", "surface", "render", "shading", "rigid", "memory")


def _bench(args) -> int:
    """Run the stage benchmarks of a source checkout (benchmarks/*.py); each prints JSON lines."""
    import shlex
    import subprocess

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
    out = None if args.out is None else Path(args.out)
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
    for stage in stages:
        cmd = [sys.executable, str(root / f"{stage}.py")]
        if args.quick and "--quick" in (root / f"{stage}.py").read_text():
            cmd.append("--quick")
        cmd += shlex.split(args.args or "")
        print(f"# {' '.join(cmd)}", flush=True)
        res = subprocess.run(cmd, capture_output=out is not None, text=True)
        if out is not None:
            (out / f"{stage}.jsonl").write_text(res.stdout)
            print(res.stdout, end="", flush=True)
        if res.returncode:
            print(f"error: benchmark {stage} failed (exit {res.returncode})", file=sys.stderr)
            return 1
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="diffcloth", description=__doc__)
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
    p.add_argument(
        "--allow-unstable",
        action="store_true",
        help="only warn when dt/num_substeps exceeds the explicit stability estimate",
    )
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
    r.add_argument("--format", choices=("mp4", "gif"), default="mp4", help="video format")
    r.add_argument("--fps", type=float, default=30.0)
    r.add_argument("--chunk", type=int, default=10, help="frames rendered per compiled call")
    r.add_argument("--npy", action="store_true", help="also write the linear video as video.npy")
    r.add_argument("--x64", action="store_true", help="run in float64")
    r.set_defaults(func=_render)
    b = sub.add_parser("bench", help="run the stage benchmarks (JSON lines); needs the checkout")
    b.add_argument("stages", nargs="*", help=f"some of {', '.join(BENCHMARKS)} (default: all)")
    b.add_argument("--quick", action="store_true", help="small sizes, fewer repeats")
    b.add_argument("--out", default=None, help="also write DIR/<stage>.jsonl")
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
    f.add_argument("--x64", action="store_true", help="fit in float64")
    f.add_argument(
        "--devices",
        type=int,
        default=None,
        help="spread the [fit] multistart guesses over N devices (GPUs, or N CPU devices); "
        "overrides [fit] devices",
    )
    f.set_defaults(func=_fit)
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
    return parser


def main(argv=None) -> int:
    """Run the CLI; returns the exit code: 0 done, 1 failed (blow-up, non-finite fit, internal
    error), 2 bad usage or config (a one-line message naming the key/file/option), 130
    interrupted. `--debug` shows the traceback instead."""
    args = build_parser().parse_args(argv)
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
    from diffcloth.physics.rollout import UnstableSimulationError

    if isinstance(err, UnstableSimulationError):
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
