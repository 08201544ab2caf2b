"""Rollouts over frames (lax.scan, checkpointed frame body), stability checks and an eager wrapper."""

from __future__ import annotations

import math
import warnings

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import checkify

from diffcloth.physics.collide import Colliders, as_colliders
from diffcloth.physics.integrate import step
from diffcloth.physics.material import Material, validate_material
from diffcloth.physics.net import Net
from diffcloth.physics.state import ClothState, SimSettings, validate_state

#: positions further than this from the rest net (m) count as blown up.
BLOWUP_DISTANCE = 1e5

ADVICE = "lower dt, raise num_substeps, or use the implicit integrator"


class StabilityWarning(UserWarning):
    """The time step is above the explicit integrator's stability estimate."""


class UnstableStepError(ValueError):
    """The explicit substep is above the stability estimate: refused before any work
    (`check_stability(..., error=True)`; the CLI exits 1 with the advice)."""


class UnstableSimulationError(RuntimeError):
    """The trajectory became non-finite or blew up."""


def _frame_colliders(colliders: Colliders, dt, num_frames: int):
    """Per-frame Colliders (leading T axis, pose at the end of each frame) -> start poses + velocity.

    Leaves without a frame axis (e.g. fixed planes next to moving spheres) are broadcast over frames.
    """
    T = num_frames
    c = colliders.spheres.center
    c = c if c.ndim == 3 else jnp.broadcast_to(c[None], (T,) + c.shape)
    r = colliders.spheres.radius
    r = r if r.ndim == 2 else jnp.broadcast_to(r[None], (T,) + r.shape)
    pn, po = colliders.planes.normal, colliders.planes.offset
    pn = pn if pn.ndim == 3 else jnp.broadcast_to(pn[None], (T,) + pn.shape)
    po = po if po.ndim == 2 else jnp.broadcast_to(po[None], (T,) + po.shape)
    for name, a in (("sphere centres", c), ("sphere radii", r), ("plane normals", pn)):
        if a.shape[0] != T:
            raise ValueError(
                f"colliders: per-frame {name} have {a.shape[0]} frames, expected num_frames={T}"
            )
    prev = jnp.concatenate([c[:1], c[:-1]], axis=0)
    vel = (c - prev) / dt
    return Colliders(
        spheres=type(colliders.spheres)(prev, r),
        sphere_velocity=vel,
        planes=type(colliders.planes)(pn, po),
    )


def is_per_frame(colliders: Colliders | None) -> bool:
    """True when the collider arrays carry a leading frame axis.

    Shapes: collider leaves (k, 3) static or (T, k, 3) per frame -> bool.
    """
    return colliders is not None and (
        colliders.spheres.center.ndim == 3 or colliders.planes.normal.ndim == 3
    )


def rollout(
    net: Net,
    sim: SimSettings,
    material: Material,
    state: ClothState,
    *,
    num_frames: int,
    colliders=None,
    pin_path=None,
    debug: bool = False,
    collect: bool = True,
) -> ClothState:
    """Simulate `num_frames` frames; return the trajectory (frames, rows, cols, 3) for x and v.

    Frame k of the trajectory is the state after k + 1 steps (the initial state is not included).
    Checkpointing: the frames are `jax.checkpoint`-ed (a frame's substeps store their states while
    that frame is differentiated; symplectic rollouts of at most SMALL_ROLLOUT node-substeps are
    not: they keep every substep's residuals and skip the second forward pass), and rollouts
    longer than NESTED_FRAMES frames are scanned in
    blocks of ceil(sqrt(frames)) frames, each block checkpointed too. A gradient then keeps
    O(sqrt(frames) + substeps) states instead of
    one per substep (plus the returned trajectory itself; `advance` returns no trajectory, so its
    gradient memory grows sublinearly with the rollout length). See benchmarks/memory.py.

    Args:
      net, sim: fixed structure and settings (sim.integrator picks the integrator).
      material: differentiable Material.
      state: initial ClothState.
      num_frames: static number of frames (>= 0; 0 gives an empty trajectory).
      colliders: None, Sphere/Plane (or a list of them), or Colliders. Colliders whose sphere
        centres are (num_frames, n, 3) (and planes (num_frames, m, 3)/(num_frames, m)) move: entry k
        is the pose at the end of frame k; sphere velocities come from finite differences.
      pin_path: optional (num_frames, rows, cols, 3): where pinned points are at the end of each frame.
      debug: add `checkify` checks that every frame is finite; wrap the caller in
        `jax.experimental.checkify.checkify` to collect them (as `checked_rollout(debug=True)` does).
      collect: False returns only the final state (no trajectory; what `advance` uses).

    >>> net = grid_net(4, 4, (0.3, 0.3), pinned="top_row")     # doctest: +SKIP
    >>> traj = rollout(net, make_sim(), make_material(), rest_state(net), num_frames=10)  # doctest: +SKIP
    """
    if isinstance(num_frames, bool) or not isinstance(num_frames, int | np.integer):
        raise TypeError(f"num_frames: must be an int, got {num_frames!r}")
    if num_frames < 0:
        raise ValueError(f"num_frames: must be >= 0 (allowed range [0, inf)), got {num_frames}")
    colliders = as_colliders(colliders, dtype=state.x.dtype)
    moving = is_per_frame(colliders)
    if moving:
        colliders = _frame_colliders(colliders, sim.dt, num_frames)
    if pin_path is not None and tuple(pin_path.shape) != (num_frames, net.rows, net.cols, 3):
        raise ValueError(
            f"pin_path: expected shape ({num_frames}, {net.rows}, {net.cols}, 3), got {pin_path.shape}"
        )

    def body(carry, xs):
        frame_colliders, target = xs
        if not moving:
            frame_colliders = colliders
        new = step(net, sim, material, carry, frame_colliders, pin_target=target)
        if debug:
            checkify.check(
                jnp.all(jnp.isfinite(new.x)) & jnp.all(jnp.isfinite(new.v)),
                f"physics: non-finite cloth state ({ADVICE})",
            )
        return new, new

    xs = (colliders if moving else None, pin_path)
    work = net.rows * net.cols * sim.num_substeps * num_frames
    remat = sim.integrator != "symplectic" or work > SMALL_ROLLOUT or num_frames > NESTED_FRAMES
    final, traj = checkpointed_scan(body, state, xs, num_frames, collect=collect, remat=remat)
    return traj if collect else final


def advance(net, sim, material, state, *, num_frames: int, colliders=None) -> ClothState:
    """The state after `num_frames` frames (num_frames = 0 returns `state` unchanged).

    Unlike `rollout(...)[-1]` no trajectory is built, so the gradient memory grows sublinearly
    with num_frames (O(sqrt(num_frames)) frame states, see `checkpointed_scan`).

    Shapes: state x, v (rows, cols, 3) -> state (rows, cols, 3).
    """
    if num_frames == 0:
        return state
    return rollout(
        net, sim, material, state, num_frames=num_frames, colliders=colliders, collect=False
    )


#: rollouts longer than this many frames are checkpointed in two levels (sqrt blocks).
NESTED_FRAMES = 64

#: symplectic rollouts of at most this many node-substeps (nodes x substeps x frames) keep every
#: substep's residuals instead of checkpointing the frames: the backward pass then does not run
#: the forward a second time (small nets are launch-bound). Gradient temporaries: ~80 B per
#: node-substep (drape_material, 49,920: 3.9 MB vs 0.4 MB checkpointed). drape_fit: 31,200.
SMALL_ROLLOUT = 65536


def checkpointed_scan(body, carry, xs, length: int, *, collect: bool = True, remat: bool = True):
    """`lax.scan(jax.checkpoint(body), carry, xs, length)` with sublinear gradient memory.

    For length > NESTED_FRAMES the scan runs over blocks of B = ceil(sqrt(length)) steps, and each
    block is checkpointed as a whole: the backward pass keeps one carry per block and, while it
    differentiates one block, one carry per step of that block, i.e. O(sqrt(length)) carries
    instead of `length`, at the price of one more forward pass. Results are identical.

    Args:
      body: (carry, x) -> (carry, y).
      xs: pytree with leading axis `length`, or None.
      collect: return the stacked ys (like lax.scan); False returns None for them.
      remat: False runs a plain lax.scan (every step's residuals kept; for short, small loops).
    Returns:
      (final carry, ys or None).
    """
    step_fn = jax.checkpoint(body, prevent_cse=False) if remat else body

    def one(c, x):
        c, y = step_fn(c, x)
        return c, (y if collect else None)

    if length <= NESTED_FRAMES or not remat:
        return jax.lax.scan(one, carry, xs, length=length)
    size = math.isqrt(length - 1) + 1
    blocks, rest = divmod(length, size)
    tmap = jax.tree_util.tree_map
    head = tmap(lambda a: a[: blocks * size].reshape((blocks, size) + a.shape[1:]), xs)
    block = jax.checkpoint(lambda c, x: jax.lax.scan(one, c, x, length=size), prevent_cse=False)
    carry, ys = jax.lax.scan(block, carry, head, length=blocks)
    if collect:
        ys = tmap(lambda a: a.reshape((blocks * size,) + a.shape[2:]), ys)
    if rest:
        tail = tmap(lambda a: a[blocks * size :], xs)
        carry, ys_rest = jax.lax.scan(one, carry, tail, length=rest)
        if collect:
            ys = tmap(lambda a, b: jnp.concatenate([a, b]), ys, ys_rest)
    return carry, ys


def stable_substep(net: Net, sim: SimSettings, material, *, method: str = "modes") -> float:
    """Largest substep (s) the explicit integrator tolerates, estimated eagerly at rest.

    method "modes" (default): from the stiffest and the most damped mode of the linearised forces
    at rest (Lanczos, see `stability.modal_substep`); "gershgorin": the per-node bound
    `stability.node_substeps` (each node's mass against the springs actually attached to it plus
    its damping; never above the modal value, up to ~2x below it). inf if no node is free.
    """
    from diffcloth.physics import stability

    if not (~np.asarray(net.pinned)).any():
        return math.inf
    if method == "modes":
        return stability.modal_substep(net, sim, material)
    if method == "gershgorin":
        return float(np.min(stability.node_substeps(net, material)))
    raise ValueError(f"method: must be 'modes' or 'gershgorin', got {method!r}")


def check_stability(net: Net, sim: SimSettings, material, *, error: bool = False) -> float:
    """Warn (or raise UnstableStepError, a ValueError, when `error`) if the explicit substep exceeds
    the stability limit.

    Two stages: the cheap per-node Gershgorin bound (`method="gershgorin"`) clears most runs; only
    a substep above it is checked against the tight modal estimate (`method="modes"`, which costs
    a compilation and a few dozen force evaluations). Returns the estimate that decided (s).
    Nothing is checked for the implicit integrator.
    """
    h_max = stable_substep(net, sim, material, method="gershgorin")
    if sim.integrator != "symplectic":
        return h_max
    h = float(np.asarray(sim.dt)) / sim.num_substeps
    if h > h_max:
        h_max = stable_substep(net, sim, material, method="modes")
    if h > h_max:
        ratio = float(np.asarray(sim.dt)) / h_max if h_max > 0 else math.inf
        need = f"num_substeps >= {math.ceil(ratio)}" if math.isfinite(ratio) else (
            "raise the masses or lower the stiffnesses: no substep count is enough"
        )  # fmt: skip
        msg = (
            f"unstable time step: substep dt/num_substeps = {h:.3g} s exceeds the explicit "
            f"stability estimate {h_max:.3g} s (stiffest mode of the linearised forces); {ADVICE} "
            f"(e.g. {need})"
        )
        if error:
            raise UnstableStepError(msg)
        warnings.warn(msg, StabilityWarning, stacklevel=2)
    return h_max


def blowup_bound(sim: SimSettings, state: ClothState, num_frames: int, first_frame: int = 0):
    """(num_frames,) m: how far from the rest net frame k may legitimately be.

    BLOWUP_DISTANCE plus what a free fall could cover by the end of frame k (t = (k + 1) dt):
    (max initial speed + wind speed) t + |g| t^2, twice the free-fall distance |g| t^2 / 2 as a
    margin for spring and drag forces. A cloth falling freely for minutes is not "blown up"; an
    exploding explicit integrator exceeds this within a few frames. `state` is the initial state
    of the whole run and `first_frame` the index of the first frame checked (for a run in chunks).
    """
    t = (jnp.arange(num_frames) + 1.0 + first_frame) * sim.dt
    v0 = jnp.max(jnp.sqrt(jnp.sum(jnp.where(jnp.isfinite(state.v), state.v, 0.0) ** 2, -1)))
    wind = jnp.sqrt(jnp.sum(sim.wind**2))
    g = jnp.sqrt(jnp.sum(sim.gravity**2))
    return BLOWUP_DISTANCE + (v0 + wind) * t + g * t * t


def frames_ok(
    net: Net, traj: ClothState, sim: SimSettings | None = None, state=None, first_frame: int = 0
):
    """(frames,) bool, usable under jit and vmap: frame k is finite (positions and velocities) and
    within `blowup_bound` of the rest net (BLOWUP_DISTANCE when `sim`/`state` are not given)."""
    T = traj.x.shape[0]
    axes = tuple(range(1, traj.x.ndim))
    finite = jnp.all(jnp.isfinite(traj.x), axis=axes) & jnp.all(jnp.isfinite(traj.v), axis=axes)
    dist = jnp.max(
        jnp.abs(jnp.where(jnp.isfinite(traj.x), traj.x, 0.0) - net.rest[None]), axis=axes
    )
    if sim is None or state is None:
        bound = BLOWUP_DISTANCE
    else:
        bound = blowup_bound(sim, state, T, first_frame)
    return finite & (dist < bound)


def trajectory_ok(net: Net, traj: ClothState, sim: SimSettings | None = None, state=None):
    """Per-trajectory status flag (a bool array, usable under jit and vmap): every frame finite and
    not blown up (see `frames_ok`; pass `sim` and the initial `state` so a long free fall is not
    mistaken for a blow-up)."""
    return jnp.all(frames_ok(net, traj, sim, state))


def first_bad_frame(net: Net, traj: ClothState, sim=None, state=None) -> int | None:
    """Eager: index of the first non-finite or blown-up frame, or None.

    Shapes: traj x, v (T, rows, cols, 3) -> Python int or None.
    """
    ok = np.asarray(frames_ok(net, traj, sim, state))
    return None if ok.all() else int(np.argmin(ok))


_JITTED = {}


def _jitted_rollout(num_frames: int, debug: bool):
    key = (num_frames, debug)
    if key not in _JITTED:
        fn = jax.jit(
            lambda net, sim, material, state, colliders, pin_path: rollout(
                net,
                sim,
                material,
                state,
                num_frames=num_frames,
                colliders=colliders,
                pin_path=pin_path,
                debug=debug,
            )
        )
        _JITTED[key] = checkify.checkify(fn) if debug else fn
    return _JITTED[key]


def checked_rollout(
    net: Net,
    sim: SimSettings,
    material: Material,
    state: ClothState,
    *,
    num_frames: int,
    colliders=None,
    pin_path=None,
    debug: bool = False,
) -> ClothState:
    """Eager, checked `rollout`: validates inputs, warns on a too-large step, raises on blow-up.

    Raises:
      ValueError: non-finite initial state, bad material values.
      UnstableSimulationError: the trajectory became non-finite or blew up (`frames_ok`); the message
        says "unstable: lower dt, raise num_substeps, or use the implicit integrator".

    Shapes: state x, v (rows, cols, 3) -> trajectory (num_frames, rows, cols, 3).
    """
    validate_state(net, state)
    if hasattr(material, "total_forces_planar"):
        from diffcloth.physics.massspring import validate_mass_spring

        validate_mass_spring(material)
    else:
        validate_material(material)
    check_stability(net, sim, material)
    colliders = as_colliders(colliders, dtype=state.x.dtype)
    fn = _jitted_rollout(int(num_frames), debug)
    if debug:
        err, traj = fn(net, sim, material, state, colliders, pin_path)
        err.throw()
    else:
        traj = fn(net, sim, material, state, colliders, pin_path)
    first = first_bad_frame(net, traj, sim, state)
    if first is not None:
        from diffcloth.physics.grid_contact import failure_note

        last = state if first == 0 else ClothState(x=traj.x[first - 1], v=traj.v[first - 1])
        note = failure_note(net, sim, last.x, last.v)
        raise UnstableSimulationError(
            f"unstable: the cloth state became non-finite or blew up at frame {first}; {ADVICE} "
            f"(substep {float(np.asarray(sim.dt)) / sim.num_substeps:.3g} s, explicit estimate "
            f"{stable_substep(net, sim, material, method='gershgorin'):.3g} s){note}"
        )
    return traj


def simulate(*args, **kwargs) -> ClothState:
    """Deprecated name of `checked_rollout` (it clashed with the scene-level `diffcloth.simulate`,
    which does something else); will be removed in 0.3."""
    warnings.warn(
        "diffcloth.physics.simulate is renamed checked_rollout (diffcloth.simulate is the "
        "scene-level trajectory); the old name goes in 0.3",
        DeprecationWarning,
        stacklevel=2,
    )
    return checked_rollout(*args, **kwargs)
