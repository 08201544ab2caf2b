"""Box bodies cast shadows (issue 14 acceptance 1) through the public path: a config with a box
body, a `shadows = true` light and a drawn plane -> Scene -> `pipeline.render_frame`. The shadow
footprint is computed analytically (rays toward the light against the box), the image is
compared with the same scene's unshadowed render, and the gradient of a shadow-edge loss w.r.t.
the box position is checked against central finite differences in float64."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth import config as cfg
from diffcloth import pipeline, render, surface
from diffcloth.render.camera import pixel_rays
from diffcloth.render.shadows import shadow_visibility
from diffcloth.scene import build_scene

N = 40
LIGHT = np.array([0.6, 1.0, 0.0]) / np.linalg.norm([0.6, 1.0, 0.0])  # towards the light
BOX_C, BOX_H = np.array([0.3, 0.75, 0.0]), np.array([0.1, 0.03, 0.25])
CLOTH_Y = 0.3
SCENE = {
    # a horizontal cloth at y = 0.3 over x in [-0.3, 0.3], z in [0, 0.45]; the box's shadow
    # falls half on it, half on the ground plane beside it
    "net": {"rows": 5, "cols": 5, "width": 1.2, "height": 0.9, "center": [0.0, CLOTH_Y, 0.225]},
    "sim": {"num_frames": 1, "num_substeps": 8, "integrator": "implicit"},
    "planes": [{"normal": [0.0, 1.0, 0.0], "offset": 0.0}],
    "bodies": [
        {"shape": "box", "mass": 1.0, "half_extents": BOX_H.tolist(), "position": BOX_C.tolist()}
    ],
    "render": {
        "width": N,
        "height": N,
        "level": 2,
        "draw_planes": True,
        "shadow_map_size": 64,
        "background": [0.0, 0.0, 0.0],
    },
    "camera": {
        "eye": [0.0, 3.0, 0.0],
        "target": [0.0, 0.0, 0.0],
        "up": [0.0, 0.0, -1.0],
        "projection": "orthographic",
        "fov_y": 25.0,
    },
    "appearance": {"specular": [0.0, 0.0, 0.0]},
    "lights": {
        "ambient": [0.2, 0.2, 0.2],
        "directional": [{"direction": LIGHT.tolist(), "shadows": True, "softness": 1.0}],
    },
}


def _slab_hit(o, d, lo, hi):
    """(N,) bool: rays o + t d, t > 0, meet the axis-aligned box [lo, hi] (o, d: (N, 3))."""
    par = np.abs(d) < 1e-12
    ds = np.where(par, 1.0, d)
    t1, t2 = (lo - o) / ds, (hi - o) / ds
    tmin = np.where(par, -np.inf, np.minimum(t1, t2)).max(-1)
    tmax = np.where(par, np.inf, np.maximum(t1, t2)).min(-1)
    inside_par = np.all(~par | ((o >= lo) & (o <= hi)), axis=-1)
    return inside_par & (tmax >= np.maximum(tmin, 0.0))


@pytest.fixture(scope="module")
def box_scene():
    sc = build_scene(cfg.parse_config(SCENE))
    poses = render.boxes.box_poses(sc.bodies)
    assert poses is not None and sc.lights.shadows == (True,) and sc.draw_planes
    return sc, poses


def pixel_classes(sc):
    """Pixel classes from the scene's geometry (numpy, margins of about 2 px around every edge):
    plane / cloth pixels well inside the box's shadow, and pixels well away from the box's and
    the cloth's shadows (and from the box and cloth outlines in view)."""
    cam = sc.cameras[0]
    o, d = (np.asarray(a, np.float64).reshape(-1, 3) for a in pixel_rays(cam))
    pos = np.asarray(surface.tessellate(sc.state.x, sc.level, sc.basis, flip=sc.flip).positions)
    c_lo, c_hi = pos.min(0), pos.max(0)
    m = 0.06  # m: > 1.5 px (0.048 m) of antialiasing + the penumbra and PCF radius (~0.03 m)

    def cloth_box(grow):
        return c_lo - [grow, 0.01, grow], c_hi + [grow, 0.01, grow]

    def box_box(grow):
        g = np.array([grow, 0.0, grow])  # the box is thin: its y extent is kept
        return BOX_C - BOX_H - g, BOX_C + BOX_H + g

    # what each pixel sees (top-down orthographic: rays straight down)
    on_box = _slab_hit(o, d, *box_box(m))
    near_cloth = _slab_hit(o, d, *cloth_box(m))
    in_cloth = _slab_hit(o, d, *cloth_box(-m))
    t_cloth = (CLOTH_Y - o[:, 1]) / d[:, 1]
    t_plane = -o[:, 1] / d[:, 1]
    p_cloth = o + t_cloth[:, None] * d
    p_plane = o + t_plane[:, None] * d
    L = np.broadcast_to(LIGHT, o.shape)

    def shadowed(p, grow):
        return _slab_hit(p + 1e-6 * L, L, *box_box(grow))

    def cloth_shadowed(p, grow):
        return _slab_hit(p + 1e-6 * L, L, *cloth_box(grow))

    plane_px = ~on_box & ~near_cloth
    cloth_px = ~on_box & in_cloth
    plane_in = plane_px & shadowed(p_plane, -m)
    cloth_in = cloth_px & shadowed(p_cloth, -m)
    lit_plane = plane_px & ~shadowed(p_plane, m) & ~cloth_shadowed(p_plane, m)
    lit_cloth = cloth_px & ~shadowed(p_cloth, m)
    shape = (N, N)
    out = {
        k: v.reshape(shape)
        for k, v in dict(
            plane_in=plane_in, cloth_in=cloth_in, lit_plane=lit_plane, lit_cloth=lit_cloth
        ).items()
    }
    out["points"] = {"plane": p_plane.reshape(N, N, 3), "cloth": p_cloth.reshape(N, N, 3)}
    return out


@pytest.fixture(scope="module")
def classes(box_scene):
    out = pixel_classes(box_scene[0])
    for k, v in out.items():
        if k == "points":
            continue
        assert v.sum() >= 4, (k, v.sum())  # the scene puts every class in view
    return out


@jax.jit
def _render(sc, poses):
    """Frame 0 of the scene with its box (H, W, 3); `sc.lights.shadows` is static."""
    return pipeline.render_frame(sc, sc.state.x, boxes=poses)[0]


def _analytic(sc, img, classes, *, lit_image=None):
    """Check the umbra and lit pixel classes of `img` against their analytic values: a
    Lambertian receiver (matte plane; cloth without specular) in the umbra keeps only
    albedo * ambient, one away from every shadow gets albedo * (ambient + N.L). With
    `lit_image` (the unshadowed render) the lit pixels must equal it and the umbra be darker."""
    ka = np.asarray(sc.appearance.ambient) * np.asarray(sc.lights.ambient)
    nl = LIGHT[1]  # N.L of the horizontal plane and cloth (white light, intensity 1)
    albedo = {"plane": np.asarray(render.PLANE_COLOR), "cloth": np.asarray(sc.appearance.diffuse)}
    for k in ("plane", "cloth"):
        dark, lit = classes[k + "_in"], classes["lit_" + k]
        want_dark = np.broadcast_to(albedo[k] * ka, img[dark].shape)
        np.testing.assert_allclose(img[dark], want_dark, atol=1e-6, err_msg=k)
        want_lit = np.broadcast_to(albedo[k] * (ka + nl), img[lit].shape)
        np.testing.assert_allclose(img[lit], want_lit, atol=1e-6, err_msg=k)
        if lit_image is not None:
            want_off = np.broadcast_to(albedo[k] * (ka + nl), lit_image[dark].shape)
            np.testing.assert_allclose(lit_image[dark], want_off, atol=1e-6, err_msg=k)
            assert np.all(img[dark].sum(-1) < lit_image[dark].sum(-1) - 0.1), k
            np.testing.assert_allclose(img[lit], lit_image[lit], atol=1e-9, err_msg=k)


@pytest.mark.slow  # 7 s; moved out of the default suite (10-minute budget)
def test_box_shadow_visibility_at_the_receivers(box_scene, classes):
    """The shadow data `render` builds for a frame with boxes (`frame_shadow_maps` with the box
    mesh as occluder: cloth + box in one shadow map) gives visibility 0 at the plane and cloth
    points in the box's analytic footprint and 1 away from every shadow. Cheap (no image)."""
    sc, poses = box_scene
    box_verts, _, box_faces = render.boxes.box_mesh(poses)
    surf = surface.tessellate(sc.state.x, sc.level, sc.basis, flip=sc.flip)
    pts, want = [], []
    for k in ("plane", "cloth"):
        for cls, v in ((k + "_in", 0.0), ("lit_" + k, 1.0)):
            p = classes["points"][k][classes[cls]]
            pts.append(p)
            want.append(np.full(len(p), v))
    pts = jnp.asarray(np.concatenate(pts))
    up = jnp.broadcast_to(jnp.asarray([0.0, 1.0, 0.0]), pts.shape)

    @jax.jit
    def vis(surf, verts):
        maps = render.frame_shadow_maps(
            surf, sc.lights, occluders=(verts, box_faces), size=sc.shadow_map_size
        )
        return shadow_visibility(maps, pts, up)[:, 0]

    np.testing.assert_allclose(np.asarray(vis(surf, box_verts)), np.concatenate(want), atol=1e-9)


@pytest.mark.slow  # one render compile of the shadowed frame with a box (~20 s CPU)
def test_box_casts_shadows_on_plane_and_cloth(box_scene, classes):
    """config -> Scene -> `render_frame` with the box: plane and cloth pixels in the box's
    footprint get only ambient light, pixels away from every shadow the full analytic light (so
    they equal the unshadowed image, which is the analytic lit value everywhere: checked in the
    on/off test below)."""
    sc, poses = box_scene
    _analytic(sc, np.asarray(_render(sc, poses)), classes)


@pytest.mark.slow  # two simulate_and_render compiles (~40 s CPU)
def test_simulate_and_render_box_shadows_on_vs_off(box_scene, classes):
    """Through `simulate_and_render` (first_frame = 0: the initial state): with shadows on, the
    box's footprint on the plane and the cloth is darker than with shadows off, and every pixel
    away from the shadows is unchanged."""
    sc, _ = box_scene
    sc = dataclasses.replace(sc, first_frame=0)
    off = dataclasses.replace(sc, lights=dataclasses.replace(sc.lights, shadows=()))
    f = jax.jit(pipeline.simulate_and_render)
    on_img, off_img = (np.asarray(f(s))[0, 0] for s in (sc, off))
    _analytic(sc, on_img, classes, lit_image=off_img)


@pytest.mark.slow  # a value-and-gradient compile of the shadowed render (~45 s CPU)
@pytest.mark.gate  # the gating slow tier (.ci/run)
def test_box_shadow_gradient_wrt_box_position_matches_fd(box_scene, classes):
    """d/d(box position) of a weighted image loss over the box's shadow edges on the plane and
    the cloth (penumbra: antialiased shadow-map coverage + bilinear PCF, so the edge moves
    smoothly) vs central differences in float64."""
    sc, poses = box_scene
    near = classes["plane_in"] | classes["cloth_in"]
    # the loss weights the rows through the umbra and their neighbours (the shadow's edges)
    rows = np.nonzero(near.any(1))[0]
    w = np.zeros((N, N, 3))
    w[rows.min() - 2 : rows.max() + 3] = np.random.default_rng(0).uniform(0.5, 1.5, (1, N, 3))
    w = jnp.asarray(w)
    v = jnp.asarray([0.7, -0.3, 0.5])

    def loss(t):
        p = dataclasses.replace(poses, position=poses.position + t * v[None])
        return jnp.sum(w * pipeline.render_frame(sc, sc.state.x, boxes=p)[0])

    vg = jax.jit(jax.value_and_grad(loss))
    g = float(vg(0.0)[1])
    assert abs(g) > 1e-2, g
    # measured: FD/AD - 1 = 1e-5 (h 3e-5), 1.9e-4 (1e-5: a step spanning a kink, e.g. a tap
    # crossing a texel), -2.8e-6 (3e-6), -3.1e-7 (1e-6), -2.8e-9 (1e-7): converged to AD
    for h, tol in ((1e-6, 3e-6), (1e-7, 1e-7)):
        fd = (float(vg(h)[0]) - float(vg(-h)[0])) / (2 * h)
        assert abs(fd - g) <= tol * abs(g), (h, g, fd)
