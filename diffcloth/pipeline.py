"""The whole pipeline as one differentiable function:

    physics.rollout (or coupled_rollout with rigid bodies) -> surface.tessellate
        -> surface.collide_surface -> render.render -> video

A mesh cloth (`scene.cloth_kind(scene) == "mesh"`) takes `physics.mesh.run.mesh_trajectory`
(dynamic rollout or static equilibrium) and `physics.mesh.cloth_surface` in place of the first
two; everything after the surface is the same.

`simulate_and_render(scene, params)` returns the video of every camera; `params` is a dict of named
values that override the scene's own (material, wind, appearance, rigid bodies), so any of them
can be fitted.
"""

# ruff: noqa: F401  (re-exports: names moved to sibling modules stay importable here)
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth import physics, render, surface
from diffcloth.parameters import (
    BODY_PARAMETERS,
    NUISANCE_PARAMETERS,
    NUISANCE_RANGES,
    PARAMETER_RANGES,
    PARAMETERS,
    ParamRange,
    _check_bodies,
    _parameter_ranges,
    apply_params,
    check_nuisance_ranges,
    check_param_names,
    check_param_values,
    param_range,
    param_value,
    scene_capture,
)
from diffcloth.render.shadow_quality import frame_maps
from diffcloth.scene import cloth_kind
from diffcloth.shapes import Plane, Sphere

__all__ = [
    "NUISANCE_PARAMETERS",
    "NUISANCE_RANGES",
    "PARAMETERS",
    "PARAMETER_RANGES",
    "ParamRange",
    "apply_params",
    "check_param_values",
    "diagnose",
    "first_bad_frame",
    "param_value",
    "params_in_range",
    "render_frames",
    "rendered_states",
    "simulate",
    "simulate_all",
    "simulate_and_render",
    "simulate_and_render_checked",
    "trajectory_status",
]


def split_colliders(colliders):
    """Static Colliders -> (planes or None, spheres or None), as `physics.coupled_rollout` takes
    them: the planes act on bodies and cloth, the spheres on the cloth only."""
    if colliders is None:
        return None, None
    planes = colliders.planes if colliders.planes.offset.shape[0] else None
    spheres = colliders.spheres if colliders.num_spheres else None
    return planes, spheres


def simulate_all(scene, params=None) -> tuple[physics.ClothState, tuple]:
    """Cloth and rigid-body trajectories: (ClothState with leaves (num_frames, rows, cols, 3),
    tuple of RigidBody with a leading num_frames axis; empty without bodies).

    Differentiated as `scene.sim.gradient` says ([sim] gradient; default "reverse"): "auto" computes the
    trajectory's derivative by forward sensitivities (`physics.sensitivity.mixed_mode`) when at
    most 2 scalars of the physics inputs are differentiated (e.g. a fit's material parameters)
    and the Jacobian fits 256 MB, else in reverse mode; "forward" / "reverse" force one of them.
    Values are the same either way."""
    scene = apply_params(scene, params)
    if _kind(scene) == "mesh":
        return mesh_simulate(scene)[0], ()
    run = physics.sensitivity.mixed_mode(
        _physics_fn(scene.num_frames, scene.two_way), scene.sim.gradient
    )
    return run(scene.net, scene.sim, scene.material, scene.state, scene.bodies, scene.colliders)


_kind = cloth_kind  # "grid" or "mesh" (diffcloth.scene.cloth_kind)


def mesh_simulate(scene, params=None):
    """A mesh cloth scene's run: (trajectory (T, n, 3) leaves, `physics.mesh.run.MeshStatus`).
    A frame whose solve did not converge is NaN (the status says why: `mesh_failure`)."""
    from diffcloth.physics.mesh.run import mesh_trajectory

    scene = apply_params(scene, params)
    return mesh_trajectory(scene.net, scene.sim, scene.material, scene.state, scene.colliders,
                           num_frames=scene.num_frames)  # fmt: skip


def cloth_render_surface(scene, x):
    """The surface to draw of one cloth state: `surface.tessellate` of a control net
    (rows, cols, 3), or `physics.mesh.cloth_surface` of a mesh cloth's vertices (n, 3) (with the
    scene's display subdivision)."""
    if _kind(scene) == "mesh":
        from diffcloth.physics.mesh.surface import cloth_surface

        return cloth_surface(scene.net, x, display=getattr(scene, "display", None))
    return surface.tessellate(x, scene.level, scene.basis, flip=scene.flip)


def drawn_planes(scene):
    """The plane colliders to draw ([render] draw_planes) as a Plane batch, or None."""
    if not getattr(scene, "draw_planes", False) or scene.colliders is None:
        return None
    if _kind(scene) == "mesh":
        c = scene.colliders
        return Plane(c.plane_normal, c.plane_offset) if c.plane_offset.shape[0] else None
    return split_colliders(scene.colliders)[0]


_PHYSICS_FNS = {}


def _physics_fn(num_frames: int, two_way: bool):
    """(net, sim, material, state, bodies, colliders) -> (trajectory, body trajectories): the
    physics of a scene as a function of its traced leaves only (nothing closed over, as
    `mixed_mode` needs). One function object per (num_frames, two_way)."""
    key = (num_frames, two_way)
    if key not in _PHYSICS_FNS:

        def run(net, sim, material, state, bodies, colliders):
            if not bodies:
                traj = physics.rollout(
                    net, sim, material, state, num_frames=num_frames, colliders=colliders
                )
                return traj, ()
            planes, spheres = split_colliders(colliders)
            return physics.coupled_rollout(
                net,
                sim,
                material,
                state,
                bodies,
                num_frames=num_frames,
                planes=planes,
                colliders=spheres,
                two_way=two_way,
            )

        _PHYSICS_FNS[key] = run
    return _PHYSICS_FNS[key]


def simulate(scene, params=None) -> physics.ClothState:
    """The cloth trajectory: ClothState with leaves (num_frames, rows, cols, 3) (differentiated
    as `simulate_all` says)."""
    return simulate_all(scene, params)[0]


#: vmap axis name of `render_frames`' frames (the rasterizer picks each static work budget for
#: the largest image of the batch over it: `raster.rasterize`'s batch_axes)
FRAME_AXIS = "frames"
#: the vmap axis name of the cameras of one frame (`_each_camera`)
CAMERA_AXIS = "cameras"


def render_frame(
    scene,
    x: jax.Array,
    spheres=None,
    *,
    with_mask: bool = False,
    boxes=None,
    time=None,
    batch_axes: tuple = (),
):
    """One control net (rows, cols, 3) -> images (num_cameras, H, W, 3) of the scene.

    spheres: this frame's spheres (default: the scene's static spheres).
    boxes: this frame's `render.boxes.BoxPoses` (box bodies, drawn with the cloth; they cast
    shadows) or None. time: this frame's time in s, for the scene's [[deform]] waves / ripples
    (None: no deformation).
    with_mask: also return the visible cloth coverage (num_cameras, H, W) (see `render.render`'s
    return_cloth_mask); returns (images, masks).
    With a `scene.capture`, each camera gets its pose error, background and exposure gain (the
    gain multiplies the whole image, background included; the mask is not scaled).
    batch_axes: names of the vmap axes this call runs under (`render_frames` passes FRAME_AXIS)."""
    spheres = scene.spheres if spheres is None else spheres
    surf = cloth_render_surface(scene, x)
    if getattr(scene, "deform", ()) and time is not None:
        from diffcloth.surface.deform import apply_deformations

        surf = apply_deformations(surf, scene.deform, time)
    if spheres is not None:
        surf = surface.collide_surface(surf, spheres, offset=scene.push_out_offset)
    capture = getattr(scene, "capture", None)
    planes = drawn_planes(scene)
    # shadow maps of this frame, shared by every camera (None when no light casts shadows)
    occluders = None
    if boxes is not None:
        box_verts, _, box_faces = render.boxes.box_mesh(boxes)
        occluders = (box_verts, box_faces)
    maps, sky = frame_maps(
        surf,
        scene.lights,
        getattr(scene, "ambient_occlusion", 0),
        quality=getattr(scene, "shadow_quality", "full"),
        shadow_map_size=getattr(scene, "shadow_map_size", 256),
        image_size=max(max(c.width, c.height) for c in scene.cameras),
        spheres=spheres,
        occluders=occluders,
        planes=planes,
    )

    def one(camera, i, axes):
        background = scene.background
        if capture is not None:
            camera = render.perturb_camera(camera, capture.rotation[i], capture.translation[i])
            background = capture.background[i]
        img, mask = render.render(
            surf,
            camera,
            scene.lights,
            scene.shading,
            scene.appearance,
            spheres=spheres,
            textures=scene.textures,
            background=background,
            return_cloth_mask=True,
            planes=planes,
            plane_color=getattr(scene, "plane_color", render.PLANE_COLOR),
            shadow_maps=maps,
            sky_maps=sky,
            boxes=boxes,
            cull=getattr(scene, "cull", False),
            batch_axes=batch_axes + axes,
        )
        img = img[..., :3]
        if capture is not None:
            img = img * capture.exposure[i]
        return img, mask

    images, masks = _each_camera(one, scene.cameras)
    return (images, masks) if with_mask else images


def _each_camera(one, cameras):
    """(images, masks) of `one(camera, index, batch_axes)` stacked over the cameras. Cameras of
    one size and kind run as one batch (a `vmap` named CAMERA_AXIS: one copy of the renderer in
    the compiled program, about half the compile time of a two-camera fit with one copy per
    camera); others one after another. The batch replaced a `lax.map` over the cameras, whose
    stacked outputs and backward residuals cost copies of every per-camera buffer: 0.64x the
    render gradient of the main job (26.7 -> 17.2 ms) and of drape_material (51.6 -> 36.4 ms),
    same compile time (A/B of 2ff6f7e, 2026-11-25; `benchmarks/fit_step.py` for the whole step)."""
    leaves = [jax.tree_util.tree_flatten(c) for c in cameras]
    same = all(
        td == leaves[0][1]
        and all(jnp.shape(a) == jnp.shape(b) and jnp.result_type(a) == jnp.result_type(b)
                for a, b in zip(lv, leaves[0][0], strict=True))
        for lv, td in leaves
    )  # fmt: skip
    if len(cameras) > 1 and same:
        stacked = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *cameras)
        batch = lambda camera, i: one(camera, i, (CAMERA_AXIS,))
        return jax.vmap(batch, axis_name=CAMERA_AXIS)(stacked, jnp.arange(len(cameras)))
    outs = [one(camera, i, ()) for i, camera in enumerate(cameras)]
    return jnp.stack([o[0] for o in outs]), jnp.stack([o[1] for o in outs])


def frame_spheres(scene, body_traj: tuple):
    """Per-frame spheres to draw: the static ones plus the sphere bodies at each frame.

    Returns None (no spheres) or a Sphere with center (T, n, 3) and radius (n,). Box bodies are
    drawn as triangles (`rendered_boxes`).
    """
    balls = [b for b in body_traj if b.shape == "sphere"]
    if not balls:
        return None
    T = balls[0].position.shape[0]
    centers = [jnp.stack([b.position for b in balls], axis=1)]
    radii = [jnp.stack([b.radius[0] if b.radius.ndim else b.radius for b in balls])]
    if scene.spheres is not None:
        static = scene.spheres.batched()
        centers.insert(0, jnp.broadcast_to(static.center, (T,) + static.center.shape))
        radii.insert(0, static.radius)
    dtype = centers[-1].dtype
    return Sphere(
        jnp.concatenate([c.astype(dtype) for c in centers], axis=1),
        jnp.concatenate([r.astype(dtype) for r in radii]),
    )


#: videos with at most this many pixels (frames x cameras x H x W) are rendered as one vmapped
#: batch in `render_frames` (more memory, no recomputation in the gradient); 2^17 = 8 images of
#: 128^2.
VMAP_PIXELS = 1 << 17


def render_frames(
    scene, xs: jax.Array, spheres=None, *, with_mask: bool = False, boxes=None, times=None
):
    """Control nets (T, rows, cols, 3) -> video (num_cameras, T, H, W, 3).

    spheres: optional per-frame spheres (center (T, n, 3), radius (n,)), e.g. `frame_spheres`.
    boxes: optional per-frame box poses (leaves (T, b, ...)), e.g. `rendered_boxes`.
    times: optional (T,) frame times in s for [[deform]] (e.g. `rendered_times`).
    with_mask: also return the cloth coverage video (num_cameras, T, H, W): (video, masks).
    Short, small videos (at most VMAP_PIXELS pixels over all frames and cameras, e.g. the main
    job's 5 frames x 2 cameras x 64^2) are rendered as one batch (`vmap`): the gradient keeps every
    frame's render residuals, and needs no second forward render (0.71-0.76x fit step, same
    process). Longer ones are rendered one after another (`lax.map`) with the frame body
    checkpointed, so the memory of a gradient through a long video is that of a few frames plus the
    trajectory.
    """
    radius = None if spheres is None else spheres.radius
    centers = None if spheres is None else spheres.center

    def one(a, axes=()):
        x, c, b, t = a
        sph = None if c is None else Sphere(c, radius)
        return render_frame(scene, x, sph, with_mask=with_mask, boxes=b, time=t, batch_axes=axes)

    frames_in = (xs, centers, boxes, times)
    pixels = xs.shape[0] * sum(int(c.width) * int(c.height) for c in scene.cameras)
    if pixels <= VMAP_PIXELS:
        frames = jax.vmap(lambda a: one(a, (FRAME_AXIS,)), axis_name=FRAME_AXIS)(frames_in)
    else:
        frames = jax.lax.map(jax.checkpoint(one), frames_in)
    return jax.tree_util.tree_map(lambda f: jnp.moveaxis(f, 0, 1), frames)


def params_in_range(scene) -> jax.Array:
    """() bool, traceable: every parameter of the scene lies in PARAMETER_RANGES and is finite
    (the traced twin of `check_param_values`: density 0 or stretch -40 passed inside jit)."""
    ok = jnp.asarray(True)
    for name in PARAMETER_RANGES:
        rng = param_range(scene, name)
        group = PARAMETERS[name][0]
        if group == "bodies" and not scene.bodies:
            continue
        try:
            v = param_value(scene, name)
        except ValueError:  # not a parameter of this scene (e.g. the other material model)
            continue
        good = jnp.isfinite(v)
        if rng.lo is not None:
            good &= v >= rng.lo if rng.lo_inclusive else v > rng.lo
        if rng.hi is not None:
            good &= v <= rng.hi if rng.hi_inclusive else v < rng.hi
        ok &= jnp.all(good)
    return ok


def trajectory_status(scene, traj, bodies=()) -> jax.Array:
    """() bool, traceable: the parameters are in range (`params_in_range`), the cloth trajectory
    is finite and not blown up (`physics.frames_ok`, which allows a long free fall), and every
    rigid body stays finite."""
    ok = physics.trajectory_ok(scene.net, traj, scene.sim, scene.state) & params_in_range(scene)
    for b in bodies:
        ok &= jnp.all(jnp.isfinite(b.position)) & jnp.all(jnp.isfinite(b.velocity))
    return ok


def rendered_states(scene, traj, bodies=()):
    """The states the video shows: (control nets (T_video, rows, cols, 3), per-frame spheres or
    None). With frame_stride k the video has T_video = num_frames // k images: simulated frames
    k, 2k, ... (first_frame = 1; frame j is the state after j frames, the trajectory's entry
    j - 1) or 0, k, 2k, ... (first_frame = 0, starting from the initial state)."""
    k = scene.frame_stride
    n = scene.num_frames // k
    if scene.first_frame == 1:
        xs = traj.x[k - 1 :: k][:n]
        spheres = frame_spheres(scene, bodies)
        if spheres is not None:
            spheres = Sphere(spheres.center[k - 1 :: k][:n], spheres.radius)
        return xs, spheres
    xs = jnp.concatenate([scene.state.x[None], traj.x[k - 1 :: k][: n - 1]])
    if bodies:
        bodies = tuple(
            jax.tree_util.tree_map(lambda a0, a: jnp.concatenate([a0[None], a]), b0, b)
            for b0, b in zip(scene.bodies, bodies, strict=True)
        )
    spheres = frame_spheres(scene, bodies)
    if spheres is not None:
        idx = np.arange(n) * k
        spheres = Sphere(spheres.center[idx], spheres.radius)
    return xs, spheres


def rendered_times(scene) -> jax.Array:
    """(T_video,) time in s of each image (as `rendered_states`: frames k, 2k, ... or 0, k, ...)."""
    k = scene.frame_stride
    n = scene.num_frames // k
    frames = jnp.arange(n) * k + (k if scene.first_frame == 1 else 0)
    return frames.astype(scene.sim.dt.dtype) * scene.sim.dt


def rendered_boxes(scene, bodies=()):
    """Poses of the box bodies at the frames the video shows (as `rendered_states`):
    `render.boxes.BoxPoses` with leaves (T_video, b, ...), or None without boxes."""
    if _kind(scene) == "mesh":
        return _static_boxes(scene)
    if not any(b.shape == "box" for b in bodies):
        return None
    k = scene.frame_stride
    n = scene.num_frames // k
    poses = render.boxes.box_poses(bodies)
    if scene.first_frame == 1:
        return jax.tree_util.tree_map(lambda a: a[k - 1 :: k][:n], poses)
    first = render.boxes.box_poses(scene.bodies)
    idx = np.arange(n) * k
    return jax.tree_util.tree_map(lambda a0, a: jnp.concatenate([a0[None], a])[idx], first, poses)


def _static_boxes(scene):
    """A mesh cloth's box colliders as drawn boxes (`render.boxes.BoxPoses`, leaves
    (T_video, b, ...)), or None."""
    c = scene.colliders
    if c is None or c.box_center.shape[0] == 0:
        return None
    n = scene.num_frames // scene.frame_stride
    # the config's boxes are axis-aligned: identity orientation (w, x, y, z)
    quat = jnp.zeros((c.box_center.shape[0], 4), c.box_center.dtype).at[:, 0].set(1.0)
    poses = render.boxes.BoxPoses(position=c.box_center, orientation=quat, half_extents=c.box_half)
    return jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (n,) + a.shape), poses)


def first_bad_frame(scene, traj, bodies=()) -> int | None:
    """Eager: the first frame whose cloth (or body) state is non-finite or blown up, or None."""
    ok = np.asarray(physics.frames_ok(scene.net, traj, scene.sim, scene.state))
    for b in bodies:
        ok = ok & np.isfinite(np.asarray(b.position)).reshape(ok.shape[0], -1).all(axis=1)
        ok = ok & np.isfinite(np.asarray(b.velocity)).reshape(ok.shape[0], -1).all(axis=1)
    return None if ok.all() else int(np.argmin(ok))


def _simulate_and_render(scene, params, with_mask=False):
    scene = apply_params(scene, params)
    traj, bodies = simulate_all(scene)
    xs, spheres = rendered_states(scene, traj, bodies)
    out = render_frames(
        scene,
        xs,
        spheres,
        with_mask=with_mask,
        boxes=rendered_boxes(scene, bodies),
        times=rendered_times(scene) if getattr(scene, "deform", ()) else None,
    )
    return out, trajectory_status(scene, traj, bodies)


def _nan_unless(ok, out):
    return jax.tree_util.tree_map(lambda a: jnp.where(ok, a, jnp.nan), out)


def simulate_and_render(scene, params=None, *, with_mask: bool = False):
    """Parameters -> physics -> surface -> collision -> render, for every camera.

    Args:
      scene: a `diffcloth.Scene` (see `diffcloth.scene`).
      params: optional dict name -> value overriding the scene's own (see `PARAMETERS`);
        differentiable. Concrete values are checked against PARAMETER_RANGES (ValueError).
      with_mask: also return the visible cloth coverage (num_cameras, T, H, W) in [0, 1], soft at
        silhouettes (for the mask losses of `diffcloth.fit.masks`).
    Returns:
      video (num_cameras, T, H, W, 3), linear RGB, T = num_frames // frame_stride: simulated
      frames k, 2k, ... for frame_stride k (the initial state is not drawn), or 0, k, 2k, ...
      with scene.first_frame = 0 (see `rendered_states`). When a parameter is out of range
      (checked eagerly for concrete values, by `params_in_range` for traced ones) or the
      simulation becomes non-finite or blows up, the whole video is NaN, so a loss on it is NaN
      and a fit stops with status "nonfinite"; a blow-up never comes out as a finite picture. Use
      `simulate_and_render_checked` for an explicit flag. With with_mask: (video, masks).
    """
    out, ok = _simulate_and_render(scene, params, with_mask)
    return _nan_unless(ok, out)


def simulate_and_render_checked(scene, params=None, *, with_mask: bool = False):
    """(video, finite): `simulate_and_render` plus a () bool flag, usable under jit and vmap,
    that is False when the cloth (or a body) became non-finite or blew up; the video is then NaN.
    With with_mask: ((video, masks), finite).
    """
    out, ok = _simulate_and_render(scene, params, with_mask)
    return _nan_unless(ok, out), ok


# stage-by-stage checks live in diffcloth.diagnose (imported last: it uses the names above)
from diffcloth.diagnose import diagnose, mesh_failure  # noqa: E402
