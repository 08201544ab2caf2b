"""Mixed-mode gradients of the pipeline (physics.sensitivity, [sim] gradient): forward
sensitivities equal reverse mode and central finite differences (float64) on the trajectory,
jacfwd works through them, "auto" picks forward for a few scalars and reverse for a whole state."""

import dataclasses
import tomllib

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from tiny_scenes import TINY_SCENE

from diffcloth import config as cfg
from diffcloth import pipeline, scene
from diffcloth.physics import sensitivity

#: the tiny scene, 2 frames of 8 substeps, 12 x 12 px, the cloth starting on the sphere (so the
#: bending stiffness matters)
SMALL = (
    TINY_SCENE.replace("num_frames = 3", "num_frames = 2")
    .replace("num_substeps = 16", "num_substeps = 8")
    .replace("width = 16\nheight = 16", "width = 12\nheight = 12")
    .replace("center = [0.0, 0.8, 0.0]", "center = [0.0, 0.69, 0.0]")
)
P0 = {"bend": 1e-3, "drag_normal": 0.5}


@pytest.fixture(scope="module")
def base():
    return scene.build_scene(cfg.parse_config(tomllib.loads(SMALL)), dtype=jnp.float64)


def _with(base, mode):
    return dataclasses.replace(base, sim=dataclasses.replace(base.sim, gradient=mode))


def _traj_loss(base, mode):
    sc = _with(base, mode)
    w = jax.random.normal(jax.random.PRNGKey(1), (base.num_frames,) + base.state.x.shape)
    return lambda p: jnp.sum(pipeline.simulate(sc, p).x * w)


@pytest.mark.slow  # 18 s; the default test below checks forward == reverse on a small scan
@pytest.mark.gate  # the gating slow tier (.ci/run)
def test_forward_sensitivities_equal_reverse_and_central_fd_on_the_trajectory(base):
    p0 = {k: jnp.float64(v) for k, v in P0.items()}
    g_fwd = jax.jit(jax.grad(_traj_loss(base, "forward")))(p0)
    g_rev = jax.jit(jax.grad(_traj_loss(base, "reverse")))(p0)
    f = jax.jit(_traj_loss(base, "reverse"))
    for name in p0:
        assert abs(float(g_rev[name])) > 1e-4, name
        np.testing.assert_allclose(g_fwd[name], g_rev[name], rtol=1e-9, atol=0, err_msg=name)
        h = 1e-5 * float(p0[name])
        fd = (f({**p0, name: p0[name] + h}) - f({**p0, name: p0[name] - h})) / (2 * h)
        np.testing.assert_allclose(g_fwd[name], fd, rtol=1e-5, err_msg=name)


def test_mixed_mode_rule_forward_reverse_and_fallback_agree():
    """A small scan (cheap to compile): the same derivatives in every mode and direction, "auto"
    takes the forward sensitivities for 2 scalars and falls back to jax.jvp for 40."""

    def fn(a, x0, n):  # a (2,) rates, x0 (40,) state, n: int leaf (no tangent)
        def body(x, _):
            x = x + 0.1 * (jnp.sin(a[0] * x) - a[1] * x**3) + n.astype(x.dtype)
            return x, x[:3]

        return jax.lax.scan(body, x0, None, length=6)

    a = jnp.array([0.7, 0.3])
    x0 = jnp.linspace(-1.0, 1.0, 40)
    n = jnp.int32(0)
    loss = lambda f: lambda a, x0: jnp.sum(f(a, x0, n)[0] ** 2) + jnp.sum(f(a, x0, n)[1])
    ref_a, ref_x = jax.jit(jax.grad(loss(fn), argnums=(0, 1)))(a, x0)
    for mode in sensitivity.GRADIENT_MODES:
        ga, gx = jax.jit(jax.grad(loss(sensitivity.mixed_mode(fn, mode)), argnums=(0, 1)))(a, x0)
        np.testing.assert_allclose(ga, ref_a, rtol=1e-12, err_msg=mode)
        np.testing.assert_allclose(gx, ref_x, rtol=1e-12, err_msg=mode)
        wrapped = sensitivity.mixed_mode(fn, mode)
        ja = jax.jit(jax.jacfwd(lambda a, w=wrapped: w(a, x0, n)[0]))(a)
        np.testing.assert_allclose(ja, jax.jacrev(lambda a: fn(a, x0, n)[0])(a), rtol=1e-12)
    assert sensitivity.use_forward("auto", 2, 100, 8)
    assert not sensitivity.use_forward("auto", 4, 100, 8)
    assert not sensitivity.use_forward("auto", 40, 100, 8)
    assert not sensitivity.use_forward("auto", 2, 1 << 30, 8)  # Jacobian over 256 MB
    assert sensitivity.use_forward("forward", 40, 100, 8)


@pytest.mark.slow  # ~45 s loaded: three gradient compilations of the rollout
def test_auto_picks_forward_for_few_scalars_and_reverse_for_a_state(base, monkeypatch):
    picked = []
    real = sensitivity.use_forward

    def spy(mode, num_params, out_size, itemsize):
        picked.append((num_params, real(mode, num_params, out_size, itemsize)))
        return picked[-1][1]

    monkeypatch.setattr(sensitivity, "use_forward", spy)
    sc = _with(base, "auto")
    w = jax.random.normal(jax.random.PRNGKey(2), base.state.x.shape)

    def on_params(p):
        return jnp.sum(pipeline.simulate(sc, p).x[-1] * w)

    def on_state(x0):  # (rows, cols, 3) initial positions: 60 scalars
        s = dataclasses.replace(sc, state=dataclasses.replace(sc.state, x=x0))
        return jnp.sum(pipeline.simulate(s).x[-1] * w)

    jax.jit(jax.grad(on_params))({k: jnp.float64(v) for k, v in P0.items()})
    assert picked == [(2, True)]
    picked.clear()
    g_auto = jax.jit(jax.grad(on_state))(base.state.x)
    assert picked == [(base.state.x.size, False)]
    # the reverse fallback inside the wrapper equals the unwrapped reverse mode
    sc = _with(base, "reverse")
    g_rev = jax.jit(jax.grad(on_state))(base.state.x)
    np.testing.assert_allclose(g_auto, g_rev, rtol=1e-12, atol=1e-15)
    assert np.abs(np.asarray(g_rev)).max() > 0


def test_gradient_setting_is_read_and_checked():
    raw = tomllib.loads(SMALL)
    raw["sim"]["gradient"] = "forward"
    sc = scene.build_scene(cfg.parse_config(raw))
    assert sc.sim.gradient == "forward"
    assert scene.build_scene(cfg.parse_config(tomllib.loads(SMALL))).sim.gradient == "reverse"
    raw["sim"]["gradient"] = "sideways"
    with pytest.raises(cfg.ConfigError, match=r"\[sim\] gradient.*auto.*forward.*reverse"):
        cfg.parse_config(raw)
    with pytest.raises(ValueError, match="gradient"):
        sensitivity.mixed_mode(lambda x: x, "sideways")
