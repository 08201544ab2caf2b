"""The drape onto a sphere is smooth in the material: no jumps for a local optimiser to stall on.

With the plain "coulomb" friction rule the friction acted one substep after a node's contact, so a
tiny parameter change that moved the moment of contact across a substep boundary moved the cloth by
h * friction * |v.n| (1.4-3 mm in the main job for 0.25 % changes of bend): the image loss jumped,
FD disagreed with AD and the LM trust region rejected every step. The "impact" rule (the symplectic
default) makes the trajectory continuous; the slow test checks the main job's loss itself.
"""

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth import physics
from diffcloth.shapes import Sphere

ROOT = Path(__file__).resolve().parents[1]
_SCANS = {}


def _final_positions(rule: str, rel: np.ndarray) -> np.ndarray:
    """Final control nets (len(rel), rows, cols, 3) of a small drape onto a sphere, bend scaled by
    (1 + rel); one jitted vmapped rollout per rule."""
    if rule not in _SCANS:
        net = physics.grid_net(6, 6, (0.6, 0.6), center=(0.0, 0.82, 0.0))
        sim = physics.make_sim(1 / 30, num_substeps=8, friction_rule=rule)
        mat = physics.make_material(stretch=40.0, shear=15.0, bend=2e-3, friction=0.3)
        sphere = physics.as_colliders([Sphere(jnp.array([0.05, 0.5, 0.02]), jnp.array(0.3))])
        state = physics.rest_state(net)

        def one(r):
            m = dataclasses.replace(mat, bend=mat.bend * (1 + r))
            return physics.rollout(net, sim, m, state, num_frames=6, colliders=sphere).x[-1]

        _SCANS[rule] = jax.jit(jax.vmap(one))
    return np.asarray(_SCANS[rule](jnp.asarray(rel, jnp.float32)))


def _steps(rule: str) -> np.ndarray:
    """Max node displacement between neighbouring points of a fine scan of bend (0.1 % apart)."""
    x = _final_positions(rule, np.linspace(-0.03, 0.03, 61))
    return np.abs(np.diff(x, axis=0)).max(axis=(1, 2, 3))


def test_impact_friction_rule_is_continuous_in_the_material():
    steps = _steps("impact")
    # continuous: no 0.1 % step moves the cloth much more than the typical one (a residue of
    # O(h^2) remains where a contact crosses a substep: 7.5x here, 63x with "coulomb")
    assert steps.max() < 10 * np.median(steps), (steps.max(), np.median(steps))


def test_coulomb_rule_jumps_where_contact_crosses_a_substep():
    """The detector above can fail: the old rule shows the jumps it rules out."""
    steps = _steps("coulomb")
    assert steps.max() > 30 * np.median(steps), (steps.max(), np.median(steps))


@pytest.mark.slow
def test_main_job_loss_is_smooth_near_the_truth():
    """configs/drape_fit.toml: central FD of the loss over bend at two step sizes (0.1 %, 0.3 %)
    agree with the AD derivative 1 % off the truth (float32, the fit's precision)."""
    from diffcloth import config as cfg
    from diffcloth import pipeline, scene
    from diffcloth.fit.scene_fit import video_loss

    config = cfg.load_config(ROOT / "configs" / "drape_fit.toml")
    sc = scene.build_scene(config)
    render = jax.jit(lambda p: pipeline.simulate_and_render(sc, p))
    truth = {k: jnp.float32(v) for k, v in config.fit.truth.items()}
    target = render(truth)

    def loss(s):  # s: bend relative to the truth
        p = dict(truth, bend=truth["bend"] * s)
        return video_loss(render(p), target, "pyramid")

    value_and_grad = jax.jit(jax.value_and_grad(loss))
    s0 = jnp.float32(1.01)
    _, ad = value_and_grad(s0)
    for h in (1e-3, 3e-3):
        fd = (value_and_grad(s0 + h)[0] - value_and_grad(s0 - h)[0]) / (2 * h)
        assert abs(float(fd) - float(ad)) < 0.1 * abs(float(ad)), (h, float(fd), float(ad))
