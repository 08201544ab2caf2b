"""The CLI's config pre-checks and its two main subcommands, `simulate` and `render` (`cli` holds
the parser, `fit`, `view`, `bench` and the error handling, and re-exports these names)."""

from __future__ import annotations

import os
import sys
import time


def check_config(
    path, command: str = "render", *, allow_unstable: bool = False, smoke: bool = False
):
    """The checks `diffcloth COMMAND CONFIG` runs before any work, without running it: the config
    (ConfigError, every value also in the run's dtype), the memory estimate (MemoryLimitError),
    the stability gate (physics.UnstableStepError unless `allow_unstable`) and, for render and
    fit, the Scene and the [truth]/[fit.initial] values against it; for fit also the target
    images ([fit] targets). `smoke`: the `fit --smoke` variant (tiny sizes). Returns the Scene
    (or the Config for simulate). `diffcloth warmup` runs it for every config before compiling.
    """
    from diffcloth import memory
    from diffcloth.config import ConfigError, load_config
    from diffcloth.scene import build_scene

    if command not in ("simulate", "render", "fit"):
        raise ValueError(f"command={command!r}; allowed: simulate, render, fit")
    config = load_config(path)
    if command == "fit" and config.fit is None:
        raise ConfigError(f"{path}: missing [fit] section")
    if smoke and command == "fit":
        from diffcloth.experiment import smoke_config

        config = smoke_config(config)
    multistart = config.fit.multistart if command == "fit" else 1
    if smoke and command == "fit":
        multistart = min(multistart, 2)
    memory.check_memory(
        memory.estimate_memory(
            memory.JobSizes.from_config(config), command, multistart=multistart
        ),  # fmt: skip
        f"{command} {path}",
    )
    stability = "warn" if allow_unstable else "error"
    if command == "simulate":
        from diffcloth.config import build_physics
        from diffcloth.scene import build_bodies, check_run_stability

        phys = build_physics(config)
        build_bodies(config)
        check_run_stability(phys.net, phys.sim, phys.material, stability=stability)
        return config
    scene = build_scene(config, stability=stability)
    if command == "fit":
        from diffcloth.experiment import _check_stable_values, _check_values

        _check_values(scene, config.fit.truth, "truth")
        _check_values(scene, config.fit.initial, "fit.initial")
        _check_stable_values(scene, config.fit, stability)
        if config.fit.targets is not None:
            from diffcloth.experiment import load_fit_targets

            load_fit_targets(config.fit, scene)
    return scene


def _config_x64(paths) -> bool:
    """True when a fit config asks for float64 ([fit] x64 = true), or a config is a mesh cloth
    (`_mesh_x64`): the CLI turns JAX's x64 on before any work, as --x64 does. A config that
    does not load is left to the real checks."""
    from diffcloth.config import load_config

    for path in paths:
        try:
            config = load_config(path)
        except (ValueError, OSError):
            continue
        if (config.fit is not None and config.fit.x64) or config.cloth.is_mesh:
            return True
    return False


def _mesh_x64(path) -> bool:
    """True for a mesh cloth config ([cloth] shape other than "grid"): the CLI runs it in float64,
    as --x64 does. Its Newton solves need it: in float32 the rounding of the membrane forces of a
    stiff fabric (hundreds of N/m) is a few percent of a vertex's weight, so an equilibrium
    stalls above any useful tolerance (the Cusick config: 5 % in float32, converged in float64)."""
    from diffcloth.config import load_config

    try:
        return load_config(path).cloth.is_mesh
    except (ValueError, OSError):
        return False


def shipped_configs_dir():
    """The folder of the example configs that ship with diffcloth, or None: the wheel's package
    data (diffcloth/configs_data, pyproject.toml's force-include of configs/), else the configs/
    of the source checkout this package runs from (an editable install)."""
    from pathlib import Path

    here = Path(__file__).resolve().parent
    if (here / "configs_data").is_dir():
        return here / "configs_data"
    if (here.parent / "pyproject.toml").is_file() and (here.parent / "configs").is_dir():
        return here.parent / "configs"
    return None


def resolve_config(path: str) -> str:
    """The config file a command reads: `path` itself when it exists; else the shipped copy it
    names (`configs/drape_fit.toml`, `configs/experiments/joint.toml` or `drape_fit.toml`, run
    outside the checkout), saying so in one line; else `path` unchanged, so that the command
    reports the missing file as before."""
    from pathlib import Path

    given = Path(path)
    if given.exists() or given.suffix != ".toml":
        return path
    parts = given.parts
    if "configs" in parts:
        rel = parts[len(parts) - parts[::-1].index("configs") :]
    elif len(parts) == 1:
        rel = parts
    else:
        return path
    root = shipped_configs_dir()
    if root is None or not rel or ".." in rel or not (root.joinpath(*rel)).is_file():
        return path
    found = str(root.joinpath(*rel))
    print(f"{path} is not here; using the copy shipped with diffcloth: {found}", flush=True)
    return found


def _err(msg: str) -> None:
    print(f"error: {msg}", file=sys.stderr, flush=True)


def _stability(args) -> str:
    """The stability gate's mode of a command (`scene.check_run_stability`): the same in
    simulate, render and fit: refuse, or only warn with --allow-unstable."""
    return "warn" if getattr(args, "allow_unstable", False) else "error"


def _check_positive(name: str, value, lo: int = 1) -> None:
    from diffcloth.outdir import UsageError

    if value is not None and value < lo:
        raise UsageError(f"{name} must be >= {lo}, got {value}")


def _simulate(args) -> int:
    import jax

    if args.x64 or _mesh_x64(args.config):
        jax.config.update("jax_enable_x64", True)
    import numpy as np

    from diffcloth import memory, physics
    from diffcloth.config import build_physics, load_config
    from diffcloth.outdir import OutputDir, config_inputs
    from diffcloth.physics.grid_contact import failure_note
    from diffcloth.physics.rollout import ADVICE
    from diffcloth.pipeline import split_colliders
    from diffcloth.scene import build_bodies, check_run_stability

    _check_positive("--frames", args.frames)
    _check_positive("--chunk", args.chunk)
    _check_positive("--level", args.level, 2)
    config = load_config(args.config)
    if config.cloth.is_mesh:
        return _simulate_mesh(args, config)
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
    check_run_stability(net, sim, material, stability=_stability(args))  # before any work
    out = OutputDir(args.out, overwrite=args.overwrite, inputs=config_inputs(args.config))
    print(
        f"diffcloth simulate {args.config}: net {net.rows}x{net.cols}, {num_frames} frames, "
        f"{sim.num_substeps} substeps/frame, {sim.integrator}, {len(bodies)} rigid bodies",
        flush=True,
    )
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
            bad = int(np.argmin(ok))
            ok_x, ok_v = (state.x, state.v) if bad == 0 else (traj.x[bad - 1], traj.v[bad - 1])
            _err(
                f"unstable: the cloth blew up (non-finite or exploded state) at frame "
                f"{done + bad}; {ADVICE}{failure_note(net, sim, ok_x, ok_v)}"
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


def _simulate_mesh(args, config) -> int:
    """`diffcloth simulate` of a mesh cloth ([cloth] shape): the dynamic rollout (--frames
    overrides num_frames) or the equilibrium (one frame); trajectory.npz holds x, v (T, n, 3),
    rest, pinned, faces, uv and dt; --obj writes the drawn mesh of every frame."""
    import jax
    import numpy as np

    from diffcloth import pipeline
    from diffcloth.outdir import OutputDir, config_inputs
    from diffcloth.physics.mesh.run import status_message
    from diffcloth.scene import build_scene

    if args.frames is not None and config.sim.mode == "dynamic":
        import dataclasses

        config = dataclasses.replace(
            config, sim=dataclasses.replace(config.sim, num_frames=args.frames)
        )
    scene = build_scene(config, stability=_stability(args))
    net, sim = scene.net, scene.sim
    out = OutputDir(args.out, overwrite=args.overwrite, inputs=config_inputs(args.config))
    print(
        f"diffcloth simulate {args.config}: mesh cloth ({config.cloth.shape}) of "
        f"{net.num_vertices} vertices, {net.num_faces} faces, {sim.mode}"
        + (f", {scene.num_frames} frames, {sim.num_substeps} substeps/frame, {sim.integrator}"
           if sim.mode == "dynamic" else ""),
        flush=True,
    )  # fmt: skip
    t0 = time.perf_counter()
    traj, status = jax.jit(pipeline.mesh_simulate)(scene)
    why = status_message(sim, status)
    if why is None and pipeline.first_bad_frame(scene, traj) is not None:
        why = f"the cloth blew up at frame {pipeline.first_bad_frame(scene, traj)}"
    if why is not None:
        out.discard()
        _err(f"{'not converged' if sim.mode == 'equilibrium' else 'unstable'}: {why}; "
             "nothing written")  # fmt: skip
        return 1
    x, v = np.asarray(traj.x), np.asarray(traj.v)
    print(f"  solved in {time.perf_counter() - t0:.1f} s", flush=True)
    np.savez(
        out.tmp / "trajectory.npz",
        x=x,
        v=v,
        rest=np.asarray(net.rest),
        pinned=np.asarray(net.pinned),
        faces=np.asarray(net.faces),
        uv=np.asarray(net.uv),
        dt=float(np.asarray(sim.dt)),
        iterations=np.asarray(status.iterations),
    )
    if args.obj:
        from diffcloth.io import write_obj_sequence

        surfaces = jax.jit(jax.vmap(lambda xf: pipeline.cloth_render_surface(scene, xf)))(x)
        paths = write_obj_sequence(out.tmp / "obj", surfaces)
    dest = out.commit()
    print(f"wrote {dest / 'trajectory.npz'}: x {x.shape} ({time.perf_counter() - t0:.1f} s)")
    if args.obj:
        print(f"wrote {len(paths)} OBJ files to {dest / 'obj'}")
    return 0


def _force_host_devices(n: int) -> None:
    """Let JAX's CPU backend expose `n` devices (no effect on GPUs), unless XLA_FLAGS already sets it.

    Must run before JAX initialises a backend; the CLI calls it before any computation.
    """
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_force_host_platform_device_count" not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count={n}".strip()


def _pad_frames(tree, sl, pad: int):
    """Frames `sl` of (control nets, spheres, box poses, times) (None entries stay None; the
    spheres' radius has no frame axis), the last frame repeated `pad` times."""
    import jax
    import numpy as np

    def cut(a):
        a = np.asarray(a)[sl]
        return np.concatenate([a, np.repeat(a[-1:], pad, 0)]) if pad else a

    xs, spheres, boxes, times = tree
    sp = None if spheres is None else type(spheres)(cut(spheres.center), spheres.radius)
    bx = None if boxes is None else jax.tree_util.tree_map(cut, boxes)
    return cut(xs), sp, bx, None if times is None else cut(times)


def _render(args) -> int:
    import jax

    if args.x64 or _mesh_x64(args.config):
        jax.config.update("jax_enable_x64", True)
    import numpy as np

    from diffcloth import memory, pipeline
    from diffcloth.config import load_config
    from diffcloth.experiment import video_strip
    from diffcloth.io import save_png, save_video
    from diffcloth.outdir import OutputDir, config_inputs
    from diffcloth.physics.rollout import ADVICE
    from diffcloth.scene import build_scene

    _check_positive("--size", args.size)
    _check_positive("--chunk", args.chunk)
    _check_positive("--frames", args.frames)
    from diffcloth.outdir import UsageError

    if not (args.fps > 0 and args.fps < 1000):
        raise UsageError(f"--fps must be in (0, 1000), got {args.fps}")
    config = load_config(args.config)
    if args.frames is not None:  # override [sim] num_frames, as simulate --frames does
        stride = config.render.frame_stride
        if args.frames < stride:
            raise UsageError(
                f"--frames {args.frames} is below [render] frame_stride = {stride}, so no frame "
                f"would be rendered; allowed >= {stride}"
            )
        import dataclasses

        config = dataclasses.replace(
            config, sim=dataclasses.replace(config.sim, num_frames=args.frames)
        )
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
    scene = build_scene(config, overrides=overrides or None, stability=_stability(args))
    T, k = scene.num_frames, scene.frame_stride
    h, w = scene.image_shape
    out = OutputDir(args.out, overwrite=args.overwrite, inputs=config_inputs(args.config))
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
        if pipeline.cloth_kind(scene) == "mesh":  # the solver's own reason
            why = pipeline.mesh_failure(scene) or f"non-finite state at frame {bad}"
            _err(f"the mesh cloth gives no shape: {why}; nothing written")
            return 1
        from diffcloth.physics.grid_contact import failure_note

        last = scene.state if bad == 0 else jax.tree_util.tree_map(lambda a: a[bad - 1], traj)
        _err(f"unstable: the simulation blew up (non-finite or exploded state) at frame {bad}; "
             f"{ADVICE}{failure_note(scene.net, scene.sim, last.x, last.v)}")  # fmt: skip
        return 1
    print(f"  simulated in {time.perf_counter() - t0:.1f} s", flush=True)
    xs, spheres = pipeline.rendered_states(scene, traj, bodies)
    # per-image box poses and [[deform]] times, as simulate_and_render draws them
    boxes = pipeline.rendered_boxes(scene, bodies)
    times = pipeline.rendered_times(scene) if scene.deform else None
    render_chunk = jax.jit(pipeline.render_frames)
    chunk = max(1, args.chunk)
    parts = []
    for a in range(0, xs.shape[0], chunk):
        sl = slice(a, min(a + chunk, xs.shape[0]))
        pad = chunk - xs[sl].shape[0]  # pad the last chunk: one compiled shape
        x_part, sp, bx, t = _pad_frames((xs, spheres, boxes, times), sl, pad)
        video_part = render_chunk(scene, x_part, sp, boxes=bx, times=t)
        parts.append(np.asarray(video_part)[:, : chunk - pad])
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
