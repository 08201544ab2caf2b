"""ROBUSTNESS.md rows 1-35 in one place.

Rows whose per-stage test is complete are only mapped here (row -> existing test ids); the
meta-test `test_robustness_map_is_complete_and_points_at_real_tests` parses this table and the test
files (ast) so the map cannot rot. Rows with new coverage have a `test_row_NN_<what>` below (some
rows have both). E = eager ValueError/TypeError naming the argument and the allowed range,
G = finite value and finite gradient, F = flagged status / clear message.

Row -> existing tests, written `row  <file>::<name>` for tests/test_<file>.py::test_<name>
(test_hardening.py's CLI-level cases are mapped where they exercise a row end to end):

   1  physics_forces::coincident_nodes_give_finite_force_and_gradient
   2  physics_net::zero_rest_length_spring_is_an_error
   3  physics_net::material_bad_values_name_field_and_range
   3  hardening::case1_and_8_eager_bad_params_name_the_parameter
   4  physics_net::to_physical_is_positive_and_finite_everywhere
   4  fit_constraints::positive_for_any_raw
   5  physics_dynamics::zero_frames_returns_initial_state_and_bad_counts_raise
   5  physics_net::sim_settings_bad_input
   6  physics_dynamics::stability_estimate_warns_and_explicit_blows_up_where_implicit_holds
   7  physics_dynamics::nan_initial_state_is_rejected_eagerly_and_flagged_in_debug
   7  physics_net::validate_state_rejects_nan_and_wrong_shape
   8  physics_dynamics::all_pinned_state_is_constant_and_none_pinned_moves
   8  physics_net::grid_net_bad_input
   9  physics_dynamics::free_fall_matches_half_g_t_squared
   9  hardening::case10_long_free_fall_is_not_a_blow_up
  10  physics_dynamics::undamped_spring_energy_drift_below_one_percent
  10  physics_dynamics::convergence_order_is_one
  11  physics_forces::internal_forces_invariant_under_rigid_motion
  11  properties::internal_forces_invariant_under_rigid_motion_and_sum_to_zero
  12  surface_collide::vertex_at_centre_is_pushed_along_fallback_with_finite_gradient
  12  physics_dynamics::point_at_sphere_centre_goes_out_along_y_with_finite_gradient
  13  surface_collide::radius_zero_is_a_noop
  13  surface_collide::negative_radius_raises
  14  surface_collide::cloth_deep_inside_sphere_projects_in_one_step
  14  physics_dynamics::no_point_inside_the_sphere_after_any_step
  15  surface_tessellate::degenerate_net_gives_finite_unit_frames_and_gradients
  16  surface_tessellate::level_below_two_raises_with_minimum
  16  surface_tessellate::net_smaller_than_spline_order_raises_with_minimum
  17  surface_basis::partition_of_unity_property
  17  surface_basis::affine_invariance
  17  properties::tessellation_is_affine_invariant
  18  render_raster::zero_area_triangles
  18  render_culling::degenerate_triangle_not_facing
  19  render_raster::near_plane_crossing_floor
  19  render_raster::camera_inside_cloth_bounding_box
  20  render_camera::make_camera_rejects_bad_values
  20  render_camera::singular_views_rejected
  20  render_camera::camera_from_matrices_validates_view
  21  render_raster::empty_scene
  21  render_spheres::perspective_silhouette_and_empty
  22  render_shade::minnaert_grazing_is_finite_row22
  22  properties::minnaert_factor_finite_for_k_in_0_2
  23  render_shade::snell_total_internal_reflection_row23
  23  properties::refract_is_unit_snell_or_mirror
  24  render_textures::cube_map_poles_and_zero_direction_row24
  24  render_shade::degenerate_frame_is_finite_row24_25
  25  render_textures::load_texture_png_and_nan_row25
  25  render_textures::make_textures_shapes_and_zero_height
  26  fit_losses::validate_targets_errors
  26  fit_losses::validate_targets_converts_uint8
  26  pipeline::bad_input_is_rejected_before_compilation
  26  hardening::case4_every_bad_target_folder
  27  fit_losses::equal_images_give_exact_zero_loss_and_grad
  28  fit_loop::nonfinite_stops_with_message_and_keeps_last_finite
  28  fit_loop::nonfinite_not_hidden_by_apply_if_finite
  28  hardening::case6_nonfinite_stop_is_status_nonfinite_exit_1_strict_json
  29  physics_checkpoint::checkpointed_scan_matches_lax_scan
  29  physics_checkpoint::gradient_memory_grows_sublinearly
  29  physics_gradients::material_gradients_30_frames
  30  batch::one_diverging_element_does_not_poison_the_others
  30  fit_loop::multistart_one_diverging_start_does_not_poison_others
  31  batch::mismatched_batch_sizes_name_the_leaves
  32  pipeline::same_config_is_bitwise_deterministic_and_not_retraced
  32  fit_loop::one_compile_for_repeated_fits
  32  surface_tessellate::one_compile_for_new_values
  33  fit_loop::array_parameters_and_float32
  33  surface_collide::float32_strict_promotion
  34  pipeline::same_config_is_bitwise_deterministic_and_not_retraced
  35  physics_forces::internal_forces_are_minus_energy_gradient
  35  physics_forces::differential_matches_jvp_for_stretched_springs
  35  physics_gradients::material_gradients_short_rollout
  35  surface_tessellate::gradient_matches_finite_differences
  35  render_raster::interior_gradients_match_finite_differences
  35  render_shade_grad::phong_grad_lights_and_colours
  35  render_shade_grad::minnaert_grad_exponent
  35  render_shade_grad::reflect_refract_snell_grad_ior
  35  fit_losses::gradients_match_finite_differences
  35  pipeline::whole_pipeline_gradient_matches_finite_differences

New tests below are named test_row_NN_<what>; the scene-level NaN-mid-fit test (row 28, also
26/32/34 through the whole pipeline) and the x64-off subprocess (row 33) are marked slow.

Not covered: row 29's truncated backpropagation (no truncation option exists; checkpointed and
plain gradients are compared instead). Row 33's "time as i*dt" is by construction
(physics/integrate.py computes t = s * h per substep), not tested separately.
"""

import ast
import json
import re
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from diffcloth.render import camera as C
from diffcloth.render import lights as Lm
from diffcloth.render.frame import render
from diffcloth.render.sphere_layer import _sphere_layer
from diffcloth.shapes import Sphere
from diffcloth.surface import collide_surface, tessellate

TESTS = Path(__file__).parent
ROWS = range(1, 36)


# ----------------------------------------------------------------------------- the map


def _mapped() -> dict[int, list[tuple[str, str]]]:
    out: dict[int, list[tuple[str, str]]] = {}
    for line in (__doc__ or "").splitlines():
        m = re.match(r"^ *(\d+)  (\w+)::(\w+)$", line)
        if m:
            out.setdefault(int(m.group(1)), []).append((f"test_{m[2]}.py", f"test_{m[3]}"))
    return out


def _test_names(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    return {
        n.name
        for n in ast.walk(tree)
        if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef) and n.name.startswith("test_")
    }


def test_robustness_map_is_complete_and_points_at_real_tests():
    mapped = _mapped()
    here = _test_names(Path(__file__))
    new = {int(m.group(1)) for n in here if (m := re.match(r"test_row_(\d\d)_", n))}
    missing = [r for r in ROWS if r not in mapped and r not in new]
    assert not missing, f"ROBUSTNESS rows without a test: {missing}"
    assert len(mapped) >= 30, sorted(mapped)
    names: dict[str, set[str]] = {}
    for row, ids in mapped.items():
        for file, name in ids:
            path = TESTS / file
            assert path.exists(), f"row {row}: {file} does not exist"
            if file not in names:
                names[file] = _test_names(path)
            assert name in names[file], f"row {row}: {file}::{name} is not a test function"


# ----------------------------------------------------------------------------- shared scene
# One jitted frame function (tessellate -> collide with a sphere -> shade with spheres drawn) and
# its loss gradient, compiled once and reused by rows 12, 15, 19, 21, 32 and 34 (float64) and by
# the float32 subprocess of row 33.

SIZE = 15  # odd: the middle pixel's ray passes exactly through the look-at target
BG = (0.2, 0.3, 0.4)


def make_parts(dtype):
    lights = Lm.make_lights(
        ambient=(0.2, 0.2, 0.2),
        directional=[((0.3, 1.0, 0.6), (1.0, 1.0, 1.0), 1.0)],
        point=[((0.0, 1.0, 1.0), (1.0, 1.0, 1.0), 0.5)],
        dtype=dtype,
    )
    appearance = Lm.make_appearance(dtype=dtype)
    return lights, appearance


def make_camera(eye, target=(0.0, 0.0, 0.0), dtype=None):
    dtype = dtype or jnp.result_type(float)
    return C.make_camera(
        jnp.asarray(eye, dtype),
        jnp.asarray(target, dtype),
        jnp.asarray((0.0, 1.0, 0.0), dtype),
        width=SIZE,
        height=SIZE,
        fov_y=60.0,
        near=0.05,
        far=50.0,
    )


def flat_net(dtype=None, y=0.0, size=1.0):
    """A 4 x 4 control net in the plane y = const, facing +y."""
    u = np.linspace(-size, size, 4)
    x, z = np.meshgrid(u, u)
    return jnp.asarray(np.stack([x, np.full_like(x, y), z], -1), dtype or jnp.result_type(float))


def frame(net, center, radius, camera, lights, appearance):
    surf = tessellate(net, 2)
    sph = Sphere(center, radius)
    surf = collide_surface(surf, sph)
    return render(surf, camera, lights, "phong", appearance, spheres=sph, background=BG)


FRAME = jax.jit(frame)


def _loss(net, center, radius, camera, lights, appearance):
    return jnp.mean((frame(net, center, radius, camera, lights, appearance)[..., :3] - 0.5) ** 2)


LOSS_GRAD = jax.jit(jax.value_and_grad(_loss, argnums=(0, 1, 2)))


def _check_frame(net, center, radius, eye, target=(0.0, 0.0, 0.0)):
    """Image, loss and gradients w.r.t. net, sphere centre and radius; asserts all finite."""
    lights, app = PARTS
    cam = make_camera(eye, target)
    c, r = jnp.asarray(center, net.dtype), jnp.asarray(radius, net.dtype)
    img = np.asarray(FRAME(net, c, r, cam, lights, app))
    loss, grads = LOSS_GRAD(net, c, r, cam, lights, app)
    assert np.all(np.isfinite(img)), "non-finite pixels"
    assert np.isfinite(float(loss))
    for name, g in zip(("net", "center", "radius"), grads, strict=True):
        assert np.all(np.isfinite(np.asarray(g))), f"non-finite gradient w.r.t. {name}"
    return img, float(loss), grads


PARTS = make_parts(jnp.result_type(float))  # float64 under the test suite, float32 with x64 off
EYE = (0.0, 2.0, 2.5)


@pytest.mark.slow  # keeps the default suite under 10 min; runs with -m slow
def test_row_12_vertex_at_sphere_centre_through_collide_and_render():
    net = flat_net()
    centre = tessellate(net, 2).positions[12]  # a tessellated vertex exactly at the centre
    img, _, (g_net, g_c, _) = _check_frame(net, centre, 0.4, EYE)
    assert float(jnp.abs(g_net).sum()) > 0 and float(jnp.abs(g_c).sum()) > 0
    # the vertex went out along the fallback normal (+y), not to NaN
    surf = collide_surface(tessellate(net, 2), Sphere(centre, jnp.asarray(0.4)))
    np.testing.assert_allclose(surf.positions[12], centre + jnp.array([0.0, 0.4, 0.0]), atol=1e-12)


@pytest.mark.slow  # ~13 s: a full render of a degenerate net
def test_row_15_collapsed_control_net_renders_finite():
    point = jnp.asarray([0.1, 0.2, -0.1])
    net = jnp.broadcast_to(point, (4, 4, 3)) * 1.0  # every control point equal
    img, _, (g_net, _, _) = _check_frame(net, jnp.asarray([2.0, 0.0, 0.0]), 0.3, EYE)
    # zero-area triangles draw nothing; the sphere elsewhere still does
    far = np.abs(img[..., :3] - np.asarray(BG)).max(-1) > 1e-9
    assert 0 < far.sum() < SIZE * SIZE
    # collapsed net at the sphere centre: all vertices pushed out along +y, still finite
    _check_frame(net, point, 0.3, EYE)


ROW_19_VIEWS = [
    ((0.1, 0.05, 0.1), (0.0, -0.3, -1.0), "inside_cloth"),  # eye just above the sheet
    ((0.0, 0.8, 0.2), (0.0, 0.6, -1.0), "inside_sphere"),  # eye inside the sphere
    ((0.0, 0.8, 0.0), (0.0, 0.6, -1.0), "at_sphere_centre"),
    ((0.0, 0.3, 0.1), (0.0, 0.0, -0.5), "cloth_behind_camera"),  # half the cloth behind
]


def test_row_19_camera_inside_cloth_or_sphere_and_triangles_behind():
    # the four views in one test: one worker compiles the frame and its gradient once (as
    # parameters, pytest-xdist ran them on both workers, each compiling it: ~50 s apiece)
    for eye, target, what in ROW_19_VIEWS:
        img, _, _ = _check_frame(flat_net(), jnp.asarray([0.0, 0.8, 0.0]), 0.5, eye, target)
        assert np.all((img[..., 3] >= 0) & (img[..., 3] <= 1)), what
        if what in ("inside_cloth", "cloth_behind_camera"):
            assert img[..., 3].max() > 0, what  # the cloth in front is drawn


def test_row_19_camera_aimed_at_sphere_centre_has_finite_gradient():
    """The middle pixel's ray passes exactly through the centre (distance 0)."""
    centre = jnp.zeros(3)
    img, _, (_, g_c, g_r) = _check_frame(flat_net(), centre, 0.5, (0.0, 0.0, 3.0), centre)
    assert img[SIZE // 2, SIZE // 2, 3] == 1.0
    assert float(jnp.abs(g_c).sum()) > 0 and float(g_r) != 0.0


@pytest.mark.slow  # eager on purpose: ~10 s of per-op dispatch
def test_row_19_sphere_coverage_gradient_through_the_centre_eagerly():
    """The sphere layer's coverage used |closest - centre| via jnp.linalg.norm, whose gradient is
    NaN at distance 0 (seen without jit; XLA happened to hide it under jit). Now safe_norm."""
    lights, app = PARTS
    centre = jnp.zeros(3)
    cam = make_camera((0.0, 0.0, 3.0), centre)

    def coverage(c, r):
        return jnp.sum(_sphere_layer(cam, Sphere(c, r), lights, app)[0])

    g_c, g_r = jax.grad(coverage, argnums=(0, 1))(centre, jnp.asarray(0.5))
    assert np.all(np.isfinite(np.asarray(g_c))) and np.isfinite(float(g_r))
    assert float(g_r) > 0  # a bigger sphere covers more


def test_row_21_empty_image_is_background_with_zero_gradients():
    # cloth and sphere both behind the camera: nothing covers any pixel
    net = flat_net(y=0.0) + jnp.asarray([0.0, 0.0, 8.0])[None, None]
    img, loss, grads = _check_frame(net, jnp.asarray([0.0, 0.0, 9.0]), 0.5, (0.0, 0.0, 3.0))
    np.testing.assert_array_equal(img[..., :3], np.broadcast_to(BG, (SIZE, SIZE, 3)))
    np.testing.assert_array_equal(img[..., 3], 0.0)
    assert loss == pytest.approx(float(np.mean((np.asarray(BG) - 0.5) ** 2)))
    for g in grads:
        np.testing.assert_array_equal(np.asarray(g), 0.0)


def test_row_32_34_fresh_equal_inputs_no_retrace_and_bitwise_equal_image_and_gradients():
    lights, app = PARTS
    c, r = jnp.asarray([0.3, 0.2, 0.0]), jnp.asarray(0.4, jnp.float64)  # strong types
    first = (FRAME(flat_net(), c, r, make_camera(EYE), lights, app),) + tuple(
        LOSS_GRAD(flat_net(), c, r, make_camera(EYE), lights, app)
    )
    sizes = FRAME._cache_size(), LOSS_GRAD._cache_size()
    fresh_lights, fresh_app = make_parts(jnp.float64)  # new but equal pytrees
    second = (FRAME(flat_net(), c + 0.0, r, make_camera(EYE), fresh_lights, fresh_app),) + tuple(
        LOSS_GRAD(flat_net(), c + 0.0, r, make_camera(EYE), fresh_lights, fresh_app)
    )
    assert (FRAME._cache_size(), LOSS_GRAD._cache_size()) == sizes, "equal inputs retraced"
    for a, b in zip(
        jax.tree_util.tree_leaves(first), jax.tree_util.tree_leaves(second), strict=True
    ):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert float(jnp.abs(first[2][0]).sum()) > 0  # a real gradient, not a trivially equal zero


# ----------------------------------------------------------------------------- scene-level fit

TINY = {
    "net": {
        "rows": 4,
        "cols": 4,
        "width": 0.8,
        "height": 0.8,
        "center": [0.0, 0.75, 0.0],
        "pinned": "top_corners",
        "plane": "xy",
    },
    "material": {"stretch": 30.0, "shear": 10.0, "bend": 1e-3, "damping": 1e-4, "density": 0.3},
    "sim": {"dt": 1.0 / 60.0, "num_frames": 1, "num_substeps": 2},
    "render": {"width": 8, "height": 8, "level": 2, "shading": "flat"},
    "camera": {"eye": [0.0, 0.6, 1.6], "target": [0.0, 0.5, 0.0]},
}


HUGE_SGD = optax.sgd(1e20)  # the gradient w.r.t. log(stretch) is about -3e-13


def _tiny_scene():
    from diffcloth import config, scene

    return scene.build_scene(config.parse_config(TINY), dtype=jnp.float64)


@pytest.fixture(scope="module")
def tiny():
    import diffcloth as dc

    sc = _tiny_scene()
    video = np.asarray(dc.fit.make_targets(sc, {}))  # truth: the scene's own stretch (30)
    return sc, video


def test_row_26_scene_fit_rejects_bad_targets_before_compiling():
    import diffcloth as dc

    sc = _tiny_scene()
    video = np.full(sc.video_shape, 0.5)
    kw = dict(steps=1, progress=False)
    with pytest.raises(ValueError, match=r"targets .*4 channels instead of 3"):
        dc.fit.fit(sc, np.concatenate([video, video[..., :1]], -1), ["stretch"], **kw)
    with pytest.raises(ValueError, match=r"targets has dtype int64"):
        dc.fit.fit(sc, (video * 255).astype(np.int64), ["stretch"], **kw)
    with pytest.raises(ValueError, match=r"targets .*divide 0..255"):
        dc.fit.fit(sc, video * 255.0, ["stretch"], **kw)
    with pytest.raises(ValueError, match=r"targets has shape \(1, 1, 8, 4, 3\)"):
        dc.fit.fit(sc, video[..., :4, :], ["stretch"], **kw)
    bad = video.copy()
    bad[0, 0, 2, 3, 1] = np.inf
    with pytest.raises(ValueError, match=r"targets .*NaN or inf"):
        dc.fit.fit(sc, bad, ["stretch"], **kw)


@pytest.mark.slow  # ~15-30 s: compiles the whole pipeline's gradient
def test_row_28_scene_fit_stops_on_nan_mid_fit_deterministically_without_retrace(tiny):
    """A huge SGD learning rate sends log(stretch) up by ~1e7 in one step: stretch = inf, the
    physics turns NaN at step 1. The scene-level fit stops there with the step and the last finite
    parameters. Also rows 26 (uint8 targets = float targets / 255), 32 (a fresh, equal scene
    reuses the compiled step) and 34 (bitwise-equal losses and gradients)."""
    import diffcloth as dc
    from diffcloth.fit import loop

    sc, video = tiny
    kw = dict(init={"stretch": 3.0}, optimizer=HUGE_SGD, steps=5, progress=False, patience=None)
    first = dc.fit.fit(sc, video, ["stretch"], **kw)
    assert first.status == "nonfinite" and not first.ok
    assert first.message.startswith("non-finite loss/grad at step 1 ")
    assert "last finite params saved to FitResult.last_finite" in first.message
    assert first.iterations == 1
    assert float(first.last_finite["stretch"]) == pytest.approx(3.0)
    assert first.history.grad_norm["stretch"][0] > 0
    assert not np.isfinite(first.history.grad_norm["stretch"][1])
    assert all(np.isfinite(float(v)) for v in first.params.values())

    def same(a, b):  # bitwise, NaN in the same place
        assert a.message == b.message
        np.testing.assert_array_equal(a.history.loss, b.history.loss)
        np.testing.assert_array_equal(
            a.history.grad_norm["stretch"], b.history.grad_norm["stretch"]
        )
        np.testing.assert_array_equal(a.history.params["stretch"], b.history.params["stretch"])

    compiled = loop._step._cache_size()
    same(first, dc.fit.fit(_tiny_scene(), video.copy(), ["stretch"], **kw))
    u8 = np.round(np.clip(video, 0, 1) * 255).astype(np.uint8)
    as_float = u8.astype(np.float32) / 255  # the documented uint8 rule (validate_targets)
    same(dc.fit.fit(sc, u8, ["stretch"], **kw), dc.fit.fit(sc, as_float, ["stretch"], **kw))
    assert loop._step._cache_size() == compiled, "an equal scene or new targets retraced the step"


# ----------------------------------------------------------------------------- fit_params path


def _image_loss(p, target):
    from diffcloth.fit import image_loss

    img = jnp.broadcast_to(p["level"], (4, 4, 3))
    return image_loss(img, target)


def test_row_26_fit_params_targets_wrong_shape_dtype_or_nan():
    from diffcloth.fit import image_loss
    from diffcloth.fit.engines import adam as fit_params

    kw = dict(steps=3, learning_rate=0.1, progress=False)
    init = {"level": 0.3}
    with pytest.raises(ValueError, match=r"pred shape \(4, 4, 3\) != target shape \(4, 4, 4\)"):
        fit_params(_image_loss, init, {"level": "positive"}, loss_args=(jnp.ones((4, 4, 4)),), **kw)
    # uint8 targets follow validate_targets' rule (/ 255), they are not compared as 0..255
    u8 = np.full((4, 4, 3), 51, np.uint8)
    assert float(image_loss(jnp.full((4, 4, 3), 0.2), u8)) == pytest.approx(0.0, abs=1e-12)
    r = fit_params(_image_loss, init, {"level": "positive"}, loss_args=(jnp.asarray(u8),), **kw)
    assert r.status == "max_steps" and float(r.params["level"]) < 0.3  # moves toward 0.2
    with pytest.raises(ValueError, match=r"target dtype int32.*uint8"):
        image_loss(jnp.zeros((4, 4, 3)), np.zeros((4, 4, 3), np.int32))
    # NaN pixels inside a jitted loss cannot raise: the fit stops at step 0, flagged
    nan_target = jnp.full((4, 4, 3), 0.2).at[1, 2, 0].set(jnp.nan)
    r = fit_params(_image_loss, init, {"level": "positive"}, loss_args=(nan_target,), **kw)
    assert r.status == "nonfinite" and r.message.startswith("non-finite loss/grad at step 0")
    assert float(r.last_finite["level"]) == pytest.approx(0.3)


# ----------------------------------------------------------------------------- batches


def _drop(k, args):
    """A 2 x 2 net falling under gravity with springs of stiffness k (a huge k diverges)."""
    import dataclasses

    from diffcloth import physics

    net, sim, state = args
    mat = physics.make_material(dtype=net.rest.dtype)
    mat = dataclasses.replace(mat, stretch=k, shear=k)
    x = physics.rollout(net, sim, mat, state, num_frames=1).x
    return jnp.sum(x[-1, :, :, 1])


@jax.jit
def _drop_batch(ks, args):
    from diffcloth import batch

    return batch.vmap_batched(lambda p, a: jax.value_and_grad(_drop)(p["k"], a), {"k": ks}, args)


def drop_args(dtype=None):
    from diffcloth import physics

    net = physics.grid_net(2, 2, (0.3, 0.3), pinned=[(0, 0)], dtype=dtype)
    sim = physics.make_sim(1.0 / 30.0, num_substeps=3, dtype=dtype)
    return net, sim, physics.rest_state(net)


def test_row_30_one_diverging_element_keeps_others_and_their_gradients():
    args = drop_args()
    # the middle element blows up (an explicit step far too stiff), the others are unaffected
    (vals, grads), ok = _drop_batch(jnp.asarray([5.0, 1e200, 20.0]), args)
    (ref_vals, ref_grads), ref_ok = _drop_batch(jnp.asarray([5.0, 6.0, 20.0]), args)
    np.testing.assert_array_equal(np.asarray(ok), [True, False, True])
    assert bool(ref_ok.all()) and not np.isfinite(float(vals[1]) + float(grads[1]))
    for i in (0, 2):
        assert float(vals[i]) == float(ref_vals[i]) and float(grads[i]) == float(ref_grads[i])
        assert np.isfinite(float(grads[i])) and float(grads[i]) != 0.0


def test_row_31_mismatched_batch_sizes_in_multistart_and_sharding():
    from diffcloth import batch
    from diffcloth.fit.engines import adam_multistart as fit_multistart

    loss = lambda p: (p["a"] - 1.0) ** 2 + (p["b"] - 2.0) ** 2
    with pytest.raises(ValueError, match=r"leading sizes \{'a': 3, 'b': 2\}"):
        fit_multistart(loss, {"a": jnp.ones(3), "b": jnp.ones(2)}, steps=1, progress=False)
    with pytest.raises(
        ValueError, match=r"inits\[1\]\['a'\] has shape \(2,\), inits\[0\] has \(\)"
    ):
        fit_multistart(loss, [{"a": 1.0, "b": 1.0}, {"a": [1.0, 2.0], "b": 1.0}], steps=1)
    with pytest.raises(ValueError, match=r"\['a'\]: 3, \['b'\]: 2"):
        batch.vmap_batched(loss, {"a": jnp.ones(3), "b": jnp.ones(2)})
    with pytest.raises(ValueError, match=r"\['a'\]: 4, \['b'\]: 2"):
        batch.shard_batch({"a": jnp.ones(4), "b": jnp.ones(2)}, batch.make_mesh(1))


def test_row_32_unhashable_static_config_is_a_clear_error():
    import dataclasses

    from diffcloth import pipeline

    sc = dataclasses.replace(_tiny_scene(), level=[2])  # a list where an int belongs
    with pytest.raises((TypeError, ValueError), match="hash|level"):
        jax.jit(pipeline.simulate_and_render)(sc)


# ----------------------------------------------------------------------------- x64 off / on

X32_SCRIPT = """
import json, sys
import jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_numpy_rank_promotion", "raise")
sys.path.insert(0, sys.argv[1])
import test_robustness as T
assert jnp.result_type(float) == jnp.float32
lights, app = T.PARTS
net = T.flat_net()
img = T.FRAME(net, jnp.asarray([0.0, 0.8, 0.0], net.dtype), jnp.asarray(0.5, net.dtype),
              T.make_camera(T.EYE), lights, app)
(vals, grads), ok = T._drop_batch(jnp.asarray([5.0, 20.0], jnp.float32), T.drop_args())
out = {"dtypes": sorted({str(x.dtype) for x in (net, img, vals, grads)}),
       "img": np.asarray(img).tolist(), "vals": np.asarray(vals).tolist(),
       "grads": np.asarray(grads).tolist()}
print("X32" + json.dumps(out))
"""


@pytest.mark.slow  # a fresh process compiles the frame and a rollout gradient in float32
def test_row_33_x64_off_runs_in_float32_and_matches_float64():
    import os

    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    res = subprocess.run(
        [sys.executable, "-c", X32_SCRIPT, str(TESTS)], env=env, capture_output=True, text=True
    )
    lines = [l for l in res.stdout.splitlines() if l.startswith("X32")]
    assert lines, res.stderr[-3000:]
    out = json.loads(lines[0][3:])
    assert out["dtypes"] == ["float32"]
    lights, app = PARTS
    net = flat_net()
    img = FRAME(net, jnp.asarray([0.0, 0.8, 0.0]), jnp.asarray(0.5), make_camera(EYE), lights, app)
    assert np.asarray(img).dtype == np.float64
    np.testing.assert_allclose(out["img"], np.asarray(img), atol=2e-4)
    (vals, grads), _ = _drop_batch(jnp.asarray([5.0, 20.0]), drop_args())
    np.testing.assert_allclose(out["vals"], np.asarray(vals), rtol=1e-5)
    np.testing.assert_allclose(out["grads"], np.asarray(grads), rtol=1e-3)
