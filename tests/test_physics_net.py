"""Net construction, Material validation, SimSettings validation, parameter maps (rows 2-5, 8)."""

import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth import physics
from diffcloth.physics.net import bend_triplets, spring_list


def test_grid_net_shapes_areas_and_dtype():
    net = physics.grid_net(10, 13, (1.2, 0.9), pinned="top_corners")
    assert net.rest.shape == (10, 13, 3) and net.area.shape == (10, 13)
    assert net.rows == 10 and net.cols == 13
    np.testing.assert_allclose(float(net.area.sum()), 1.2 * 0.9, rtol=1e-12)
    np.testing.assert_allclose(net.rest[0, -1] - net.rest[0, 0], [1.2, 0, 0], atol=1e-12)
    assert int(net.pinned.sum()) == 2 and bool(net.pinned[0, 0]) and bool(net.pinned[0, 12])
    # structural springs of a square grid weigh 1 inside, 1/2 on the boundary; shear 1/2
    net2 = physics.grid_net(4, 4, (0.3, 0.3))
    np.testing.assert_allclose(net2.weight_h[1], 1.0)
    np.testing.assert_allclose(net2.weight_h[0], 0.5)
    np.testing.assert_allclose(net2.weight_d, 0.5)
    assert physics.grid_net(3, 3, (1, 1), dtype=jnp.float32).rest.dtype == jnp.float32
    pairs, kind, rest, weight = spring_list(net2)
    assert pairs.shape == (2 * 4 * 3 + 2 * 3 * 3, 2) and (kind == 1).sum() == 18
    trip, bw = bend_triplets(net2)
    assert trip.shape == (2 * 4 * 2, 3) and bw.shape == (16,)


def test_hanging_plane_has_row_zero_on_top():
    net = physics.grid_net(5, 4, (0.3, 0.4), center=(0, 1, 0), plane="xy")
    assert float(net.rest[0, 0, 1]) > float(net.rest[-1, 0, 1])
    np.testing.assert_allclose(net.rest[..., 2], 0.0)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(rows=1, cols=5), "rows"),
        (dict(rows=5, cols=1), "cols"),
        (dict(rows=4, cols=4, size=(0.0, 1.0)), "width"),
        (dict(rows=4, cols=4, size=(1.0, -1.0)), "height"),
        (dict(rows=4, cols=4, pinned=[(0, 4)]), r"pin \(0, 4\) lies outside"),
        (dict(rows=4, cols=4, pinned=[(-1, 0)]), "outside the net"),
        (dict(rows=4, cols=4, pinned="corners"), "unknown preset"),
        (dict(rows=4, cols=4, pinned=np.zeros((3, 3), bool)), "bool mask"),
        (dict(rows=4, cols=4, plane="yz"), "plane"),
    ],
)
def test_grid_net_bad_input(kwargs, match):
    with pytest.raises(ValueError, match=match):
        physics.grid_net(**kwargs)


def test_grid_net_type_errors():
    with pytest.raises(TypeError, match="rows"):
        physics.grid_net(4.0, 4)


def test_zero_rest_length_spring_is_an_error():
    rest = np.asarray(physics.grid_net(3, 3, (1, 1)).rest).copy()
    rest[1, 1] = rest[1, 0]
    with pytest.raises(ValueError, match="zero rest length"):
        physics.make_net(rest)
    bad = rest.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="finite"):
        physics.make_net(bad)


def test_material_defaults_and_dtype():
    m = physics.make_material(stretch=500.0)
    assert float(m.stretch) == 500.0 and float(m.density) > 0
    assert physics.make_material(dtype=jnp.float32).bend.dtype == jnp.float32


@pytest.mark.parametrize(
    "field, value",
    [
        ("density", 0.0),
        ("density", -1.0),
        ("density", float("nan")),
        ("stretch", 0.0),
        ("shear", -5.0),
        ("bend", 0.0),
        ("stretch", float("inf")),
        ("damping", -1e-3),
        ("friction", -0.1),
        ("drag_normal", float("nan")),
    ],
)
def test_material_bad_values_name_field_and_range(field, value):
    with pytest.raises(ValueError, match=rf"material\.{field} = .* allowed range [\[(]0, inf\)"):
        physics.make_material(**{field: value})


def test_material_unknown_field_and_validate():
    with pytest.raises(ValueError, match="unknown field"):
        physics.make_material(stiffness=1.0)
    m = physics.make_material()
    import dataclasses

    with pytest.raises(ValueError, match="material.density"):
        physics.validate_material(dataclasses.replace(m, density=jnp.asarray(-1.0)))


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_to_physical_is_positive_and_finite_everywhere(dtype):
    raw = jnp.linspace(-1e3, 1e3, 20001, dtype=dtype)
    y = physics.to_physical(raw)
    assert y.dtype == dtype
    assert bool(jnp.all(y > 0)) and bool(jnp.all(jnp.isfinite(y)))
    import jax

    g = jax.vmap(jax.grad(lambda r: physics.to_physical(r)))(raw)
    assert bool(jnp.all(jnp.isfinite(g)))
    # near the identity of log space in the working range
    np.testing.assert_allclose(physics.to_physical(jnp.log(jnp.asarray(250.0))), 250.0, rtol=1e-6)
    m = physics.make_material(stretch=123.0, friction=0.0)
    back = physics.material_from_raw(physics.material_to_raw(m))
    np.testing.assert_allclose(back.stretch, 123.0, rtol=1e-6)
    assert float(back.friction) > 0


@pytest.mark.parametrize(
    "kwargs, exc, match",
    [
        (dict(dt=0.0), ValueError, "dt"),
        (dict(dt=-0.01), ValueError, "dt"),
        (dict(dt=float("nan")), ValueError, "dt"),
        (dict(num_substeps=0), ValueError, "num_substeps"),
        (dict(num_substeps=2.5), TypeError, "num_substeps"),
        (dict(integrator="rk4"), ValueError, "integrator"),
        (dict(gravity=(0, float("nan"), 0)), ValueError, "gravity"),
    ],
)
def test_sim_settings_bad_input(kwargs, exc, match):
    with pytest.raises(exc, match=match):
        physics.make_sim(**kwargs)


def test_validate_state_rejects_nan_and_wrong_shape():
    net = physics.grid_net(3, 3, (1, 1))
    s = physics.rest_state(net)
    physics.validate_state(net, s)
    with pytest.raises(ValueError, match=r"state\.x: must be finite"):
        physics.validate_state(net, physics.ClothState(s.x.at[1, 1, 0].set(jnp.nan), s.v))
    with pytest.raises(ValueError, match=r"state\.v: must be finite"):
        physics.validate_state(net, physics.ClothState(s.x, s.v.at[0, 0, 2].set(jnp.inf)))
    with pytest.raises(ValueError, match="shape"):
        physics.validate_state(net, physics.ClothState(s.x[:2], s.v))
