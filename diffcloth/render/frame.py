"""One frame (module `frame`; the function is `diffcloth.render.render`): render a tessellated cloth
surface (plus analytic spheres) with one of the seed's shading modes.

Surface --rasterize_gbuffer--> per-pixel attributes --shade--> premultiplied RGBA
        --antialias (silhouettes)--> + ray-cast spheres (depth-composited) --> over background
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth._math import materialize, safe_normalize
from diffcloth.render import shadows as shadowlib
from diffcloth.render import sky as skylib
from diffcloth.render.boxes import BoxPoses, box_mesh, box_neighbors_np
from diffcloth.render.camera import Camera, eye_position, pixel_rays
from diffcloth.render.fringe import fringe_depth, layer_in_front
from diffcloth.render.layers import PLANE_COLOR, ray_cast_layers
from diffcloth.render.lights import Appearance, Lights
from diffcloth.render.raster import antialias, edge_neighbors, rasterize_gbuffer
from diffcloth.render.shade import MODES, ShadingBuffer, blinn_phong, light_vertices, shade
from diffcloth.render.shadows import ShadowMaps, shadow_visibility
from diffcloth.render.sky import SkyMaps, sky_visibility
from diffcloth.render.textures import Textures
from diffcloth.shapes import Plane, Sphere


@functools.lru_cache(maxsize=32)
def _grid_neighbors_np(grid_shape, flipped: bool = False):
    from diffcloth.surface.tessellate import grid_faces_np

    faces = grid_faces_np(*grid_shape)
    if flipped:  # tessellate(flip=True) reverses each face's vertex order (faces[:, ::-1])
        faces = faces[:, ::-1]
    with jax.ensure_compile_time_eval():  # concrete even when first called under a trace
        return np.asarray(edge_neighbors(np.ascontiguousarray(faces)))


def _grid_neighbors(surface):
    """Edge neighbours of a tessellated grid's triangles, computed once in numpy (a traced
    `edge_neighbors` would sort inside every compiled program). None for other meshes.

    Column k is the triangle across the edge opposite vertex k of `surface.faces`, so the table
    follows the winding: a flipped surface (faces[:, ::-1]) gets its columns reversed. (A table
    built from the unflipped faces marks the internal diagonals of a flipped grid as silhouettes
    and its border as internal: `antialias` then blends across the diagonals, and the image
    jumps when the depth order of two such pixels swaps; issue 14.)
    """
    grid_shape = getattr(surface, "grid_shape", None)
    if grid_shape is None:
        return None
    flipped = bool(getattr(surface, "flipped", False))
    return jnp.asarray(_grid_neighbors_np(tuple(grid_shape), flipped))


def _face_normals(positions, faces, normals):
    """(m, 3) unit geometric normals, oriented like the mean of the triangle's vertex normals."""
    p = positions[faces]
    fn = jnp.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    side = jnp.sum(fn * jnp.sum(normals[faces], axis=1), axis=-1)
    return safe_normalize(jnp.where((side < 0)[:, None], -fn, fn))


class _Combined(NamedTuple):
    positions: jax.Array
    normals: jax.Array
    tangents: jax.Array
    bitangents: jax.Array
    uv: jax.Array
    faces: jax.Array


def _with_boxes(surface, boxes: BoxPoses):
    """The cloth surface and the boxes' triangles as one mesh (box faces after the cloth's), and
    its edge-neighbour table (boxes: `boxes.box_neighbors_np`)."""
    from diffcloth.render.mesh import mesh_surface

    verts, nrm, faces = box_mesh(boxes)
    box = mesh_surface(verts, faces, normals=nrm)
    n, m = surface.positions.shape[0], surface.faces.shape[0]
    cloth_nb = _grid_neighbors(surface)
    if cloth_nb is None:
        cloth_nb = edge_neighbors(surface.faces)
    box_nb = box_neighbors_np(boxes.position.shape[0])
    nb = jnp.concatenate([cloth_nb, jnp.asarray(np.where(box_nb >= 0, box_nb + m, -1))])
    cat = lambda a, b: jnp.concatenate([a, b.astype(a.dtype)])
    combined = _Combined(
        positions=cat(surface.positions, box.positions),
        normals=cat(surface.normals, box.normals),
        tangents=cat(surface.tangents, box.tangents),
        bitangents=cat(surface.bitangents, box.bitangents),
        uv=cat(surface.uv, box.uv),
        faces=jnp.concatenate([surface.faces.astype(jnp.int32), box.faces + n]),
    )
    return combined, nb.astype(jnp.int32)


def _occluder_mesh(surface, occluders):
    """(positions, faces, neighbors) of the cloth plus extra occluder triangles (boxes...)."""
    pos, faces = surface.positions, jnp.asarray(surface.faces).astype(jnp.int32)
    nbr = _grid_neighbors(surface)
    if nbr is None:
        nbr = edge_neighbors(faces)
    if occluders is None:
        return pos, faces, nbr
    opos, ofaces = occluders[0], jnp.asarray(occluders[1]).astype(jnp.int32)
    onbr = edge_neighbors(ofaces)
    m, n = faces.shape[0], pos.shape[0]
    return (
        jnp.concatenate([pos, opos.astype(pos.dtype)], axis=0),
        jnp.concatenate([faces, ofaces + n], axis=0),
        jnp.concatenate([nbr, jnp.where(onbr >= 0, onbr + m, -1)], axis=0),
    )


def frame_shadow_maps(surface, lights: Lights, *, spheres=None, occluders=None, **options):
    """Shadow data of one frame: the cloth `surface` (plus `occluders` triangles) as the mesh
    occluder, `spheres` analytic; None when no light casts shadows. options: size (default 256),
    taps, fast of `shadows.shadow_maps`.

    Shapes: surface positions (n, 3) m, sphere centres (k, 3) m, occluders (q, 3) / (r, 3) -> ShadowMaps
      (num_lights, size, size).
    """
    if not lights.casts_shadows:
        return None
    mesh = _occluder_mesh(surface, occluders)
    return shadowlib.shadow_maps(lights, mesh=mesh, spheres=spheres, **options)


def _object_mask(surface, camera: Camera):
    """(m,) bool: every face True when the surface's bounding sphere meets the frustum, else all
    False (object-level frustum culling)."""
    from diffcloth.render.culling import bounding_sphere, frustum_planes, sphere_in_frustum

    center, radius = bounding_sphere(jax.lax.stop_gradient(surface.positions))
    visible = sphere_in_frustum(center, radius, frustum_planes(camera))
    return jnp.broadcast_to(visible, (surface.faces.shape[0],))


def surface_gbuffer(
    surface,
    camera: Camera,
    lights: Lights,
    appearance: Appearance,
    *,
    shading: str = "phong",
    two_sided: bool = True,
    cull_backfaces: bool = False,
    max_tiles: int | None = None,
    shadows: ShadowMaps | None = None,
    boxes: BoxPoses | None = None,
    triangle_mask=None,
    sky: SkyMaps | None = None,
    batch_axes: tuple = (),
    vertex_light=None,
    vertex_sky=None,
):
    """Rasterize a Surface into the shader's per-pixel inputs.

    shadows: optional `shadows.shadow_maps` output: fills `visibility` per pixel (per vertex,
    interpolated, with `shadows.per_vertex` and no boxes; the Gouraud vertices' lighting too).
    sky: optional `sky.sky_maps` output: fills `ambient_visibility` (ambient occlusion).
    vertex_light (n, nl), vertex_sky (n, 2): those per-vertex values when already looked up
    (`layers.ray_cast_layers`); computed here when None.

    Returns:
      (ShadingBuffer, raster GBuffer (ids, depth, crossings for `antialias`), eye vectors (H, W, 3)
      toward the viewer). face_normal is filled for shading="flat", color (per-vertex lighting
      from `light_vertices`) for shading="gouraud". With two_sided, back-facing pixels get flipped
      normals, bitangents, face normals and the back side's vertex lighting. With `boxes`, their
      triangles are rasterized with the surface (ids >= the surface's face count).
      triangle_mask: optional (m,) bool over the surface's faces; False drops a triangle.
      batch_axes: the vmap axis names this call runs under (see `raster.rasterize`).
    """
    neighbors = _grid_neighbors(surface)
    if boxes is not None:
        if triangle_mask is not None:
            triangle_mask = jnp.concatenate(
                [triangle_mask, jnp.ones((12 * boxes.position.shape[0],), bool)]
            )
        surface, neighbors = _with_boxes(surface, boxes)
    pos, nrm, faces = surface.positions, surface.normals, surface.faces
    eye_rays = -pixel_rays(camera)[1]  # toward the viewer, per pixel (right for every projection)
    attrs = {
        "position": pos,
        "normal": nrm,
        "tangent": surface.tangents,
        "bitangent": surface.bitangents,
        "uv": surface.uv,
    }
    grid = getattr(surface, "grid_shape", None)
    if vertex_sky is None:
        vertex_sky = skylib.vertex_sky_attribute(sky, pos, nrm, grid)
    if vertex_sky is not None:
        attrs["sky"] = vertex_sky  # ambient occlusion per vertex, both sides, interpolated
    per_vertex = shadows is not None and shadows.per_vertex and boxes is None  # boxes: per pixel
    vvis = shadow_visibility(shadows, pos, nrm) if shading == "gouraud" else None
    if per_vertex:  # (n, nl), the same for both sides, interpolated by the rasterizer
        if vertex_light is None:
            vertex_light = shadowlib.vertex_shadow_visibility(shadows, pos, nrm, grid)
        attrs["light_visibility"] = vertex_light
    if shading == "gouraud":
        # per-vertex lighting, for both sides: from the eye point (perspective) or the common
        # direction of the parallel rays (orthographic, oblique, axonometric)
        if camera.is_perspective:
            eye4 = jnp.concatenate([eye_position(camera), jnp.ones(1, pos.dtype)])
        else:
            eye4 = jnp.concatenate([eye_rays[0, 0], jnp.zeros(1, pos.dtype)])
        av, av_back = sky_visibility(sky, pos, nrm), sky_visibility(sky, pos, -nrm)
        attrs["color"] = light_vertices(pos, nrm, eye4, lights, appearance, vvis, av)
        if two_sided:
            attrs["color_back"] = light_vertices(pos, -nrm, eye4, lights, appearance, vvis, av_back)
    buf = rasterize_gbuffer(
        pos,
        faces,
        camera,
        attrs,
        neighbors=neighbors,
        cull_backfaces=cull_backfaces,
        triangle_mask=triangle_mask,
        max_tiles=max_tiles,
        batch_axes=batch_axes,
    )
    a = buf.attributes
    mask = buf.mask.astype(pos.dtype)
    normal, bitangent = a["normal"], a["bitangent"]
    face_normal = None
    if shading == "flat":
        fn = _face_normals(pos, faces, nrm)
        face_normal = jnp.where(buf.mask[..., None], fn[jnp.maximum(buf.surface_id, 0)], 0.0)
    color = a.get("color")
    # the raster marks counter-clockwise (normal side) pixels as front-facing
    back = (buf.mask & ~buf.front_facing & two_sided)[..., None]
    if two_sided:
        normal = jnp.where(back, -normal, normal)
        bitangent = jnp.where(back, -bitangent, bitangent)
        if face_normal is not None:
            face_normal = jnp.where(back, -face_normal, face_normal)
        if color is not None:
            color = jnp.where(back, a["color_back"], color)
    vis = a["light_visibility"] if per_vertex else shadow_visibility(shadows, a["position"], normal)
    gb = ShadingBuffer(
        position=a["position"],
        normal=normal,
        tangent=a["tangent"],
        bitangent=bitangent,
        uv=a["uv"],
        mask=mask,
        face_normal=face_normal,
        color=color,
        visibility=vis,
        ambient_visibility=skylib.pixel_sky_visibility(sky, a, a["position"], normal, back),
    )
    return gb, buf, eye_rays


def render(
    surface,
    camera: Camera,
    lights: Lights,
    shading: str,
    appearance: Appearance,
    *,
    spheres: Sphere | None = None,
    textures: Textures | None = None,
    background=(0.0, 0.0, 0.0),
    refraction: str = "shortened",
    draw_spheres: bool = True,
    boxes: BoxPoses | None = None,
    cull: bool = False,
    antialiased: bool = True,
    cull_backfaces: bool = False,
    two_sided: bool = True,
    max_tiles: int | None = None,
    planes: Plane | None = None,
    plane_color=PLANE_COLOR,
    occluders=None,
    shadow_map_size: int = 256,
    return_cloth_mask: bool = False,
    shadow_maps: ShadowMaps | None = None,
    ambient_occlusion: int = 0,
    sky_maps: SkyMaps | None = None,
    batch_axes: tuple = (),
    shadow_quality: str = "full",
):
    """Rasterize, shade and composite a cloth surface.

    Args:
      surface: a `diffcloth.surface.Surface` (positions, normals, tangents, bitangents (n, 3),
        uv (n, 2), faces (m, 3)); or any object with those attributes. Differentiable.
      camera: a `Camera` (any projection kind).
      lights, appearance: differentiable lighting and material parameters.
      shading: static mode, one of `shade.MODES`.
      spheres: analytic spheres: drawn (ray cast, depth-composited, antialiased rims) when
        `draw_spheres`, and seen in reflections by the modes that trace them.
      textures: colour / bump / environment / Minnaert textures (see `textures.make_textures`).
      background: (3,) colour under uncovered pixels, or None for a premultiplied transparent
        result.
      refraction: "shortened" (seed) or "snell" for mode "reflect_refract".
      boxes: optional `boxes.BoxPoses` of one frame: box bodies rasterized with the cloth
        (mutual occlusion, antialiased edges, gradients w.r.t. pose) and shaded like the spheres:
        sphere_color * (ambient + diffuse) + specular, flat per face.
      cull: object-level frustum culling: when the surface's bounding sphere lies outside the
        camera's frustum (`culling.sphere_in_frustum`), none of its triangles is drawn.
      antialiased: apply the rasterizer's silhouette antialiasing (gives edge gradients).
      two_sided: light the back side of the cloth with the flipped normal (cloth is thin).
      max_tiles: rasterizer window budget (see `raster.rasterize`).
      planes: optional ground planes (e.g. the scene's plane colliders) drawn as opaque matte
        surfaces (ray cast from their free side up to the camera's far plane), depth-composited
        with the cloth and spheres; they receive shadows.
      plane_color: (3,) linear albedo of the planes.
      occluders: optional extra shadow-casting triangle mesh (positions (n, 3), faces (m, 3)),
        e.g. box bodies; differentiable in the positions. (Cast only; drawing is the caller's.)
      shadow_map_size: static shadow-map size in texels (used only by lights with shadows).
      shadow_maps: optional precomputed `frame_shadow_maps(surface, lights, ...)` (shared by
        several cameras of one frame); built here when None and a light casts shadows.
      ambient_occlusion: static number K of sky directions of the occluded ambient light (0: off,
        the ambient term unoccluded as before); the cloth, boxes, spheres and planes block the
        ambient environment on every drawn surface (`diffcloth.render.sky`). Its maps use
        `shadow_map_size` // 2 texels (at least 8).
      sky_maps: optional precomputed `sky.frame_sky_maps(...)` (shared by several cameras).
      shadow_quality: static map sizes and filters of the maps built here: "full" or "fit"
        (maps sized to this camera's image, one tap each; `render.shadow_quality`).
      return_cloth_mask: also return the visible cloth coverage (H, W) in [0, 1]: the antialiased
        cloth alpha (soft at silhouettes, so differentiable w.r.t. the geometry there) times the
        part of each pixel not covered by a sphere or plane drawn in front. The image is unchanged.
      batch_axes: names of the vmap axes this call runs under (e.g. `pipeline.render_frames`'
        frames and cameras): the rasterizer's work budgets then suit the batch's largest image
        and one branch runs for all (`raster.rasterize`).
    Shadows: lights whose `shadows` flag is set (see `make_lights`) are occluded by the cloth
      (plus `occluders`) through a shadow map and by `spheres` analytically, on the cloth, the
      spheres and the planes (`diffcloth.render.shadows`). Without shadow-casting lights no
      shadow code runs and the image is exactly the unshadowed one.
    Returns:
      (H, W, 4) image: linear RGB (not clipped) and alpha = coverage. With a background the RGB is
      composited over it; the alpha channel still reports coverage of cloth, spheres and planes.
      With return_cloth_mask: (image, cloth_mask).
    """
    if shading not in MODES:
        raise ValueError(f"shading must be one of {MODES}, got {shading!r}")
    maps, sky = shadow_maps, sky_maps
    if boxes is not None and occluders is None:
        box_verts, _, box_faces = box_mesh(boxes)
        occluders = (box_verts, box_faces)  # boxes cast shadows too
    if (maps is None and lights.casts_shadows) or (sky is None and ambient_occlusion):
        from diffcloth.render.shadow_quality import frame_maps

        new_maps, new_sky = frame_maps(
            surface, lights, ambient_occlusion if sky is None else 0, quality=shadow_quality,
            shadow_map_size=shadow_map_size, image_size=max(camera.width, camera.height),
            spheres=spheres, occluders=occluders, planes=planes,
        )  # fmt: skip
        maps = new_maps if maps is None else maps
        sky = new_sky if sky is None else sky
    # the ray-cast layers and, without boxes, the cloth's per-vertex lookups: one of each kind
    grid = getattr(surface, "grid_shape", None)
    cloth = None if boxes is not None else (surface.positions, surface.normals, grid)
    layers = ray_cast_layers(
        camera, lights, appearance, spheres=spheres if draw_spheres else None, planes=planes,
        plane_color=plane_color, shadows=maps, sky=sky, cloth=cloth,
    )  # fmt: skip
    gb, buf, eye_rays = surface_gbuffer(
        surface,
        camera,
        lights,
        appearance,
        vertex_light=layers.vertex_light,
        vertex_sky=layers.vertex_sky,
        shading=shading,
        two_sided=two_sided,
        cull_backfaces=cull_backfaces,
        max_tiles=max_tiles,
        shadows=maps,
        boxes=boxes,
        triangle_mask=_object_mask(surface, camera) if cull else None,
        sky=sky,
        batch_axes=batch_axes,
    )
    img = shade(
        gb,
        eye_rays,
        lights,
        appearance,
        mode=shading,
        textures=textures,
        spheres=spheres,
        refraction=refraction,
    )
    if boxes is not None:
        # box pixels: the spheres' material (Blinn-Phong with sphere_color), flat face normals
        on_box = (buf.surface_id >= surface.faces.shape[0])[..., None]
        diffuse, specular = blinn_phong(
            gb.normal, eye_rays, gb.position, lights, appearance, gb.visibility
        )
        amb = jnp.reshape(appearance.ambient * lights.ambient, (1, 1, 3))
        if gb.ambient_visibility is not None:
            amb = amb * gb.ambient_visibility[..., None]
        albedo = jnp.reshape(appearance.sphere_color, (1, 1, 3))
        spec = jnp.reshape(appearance.specular, (1, 1, 3))
        box_rgb = (albedo * (amb + diffuse) + spec * specular) * gb.mask[..., None]
        box_rgba = jnp.concatenate([box_rgb, gb.mask[..., None]], axis=-1).astype(img.dtype)
        cloth_alpha = jnp.where(on_box[..., 0], 0.0, img[..., 3])
        img = jnp.concatenate([jnp.where(on_box, box_rgba, img), cloth_alpha[..., None]], -1)
    if antialiased:
        # computed once: fused into antialias's shifted neighbour reads, the shading (texture
        # gathers, bump maps) would be recomputed for each neighbour and channel (with the
        # materializations in shade: minnaert render 265 -> 46 ms at 256^2, benchmarks/shading.py)
        # the antialiased image and the sphere's weight in front are materialized too: the
        # compositing below reads each pixel's alpha in every channel, and fused it recomputed
        # the neighbour blend and the fringe depth test per channel (frame 0.96x, phong 256^2)
        img = materialize(antialias(materialize(img), buf))
    if boxes is not None:  # the extra channel: coverage of the cloth alone
        img, cloth_mask = img[..., :4], img[..., 4]
    else:
        cloth_mask = img[..., 3]
    # depth tests of the ray-cast layers: the fringe (antialiased cloth on a pixel whose centre
    # misses it) takes its covered neighbour's depth (render/fringe.py); against spheres with a
    # soft test (a hard one flipped whole fringe pixels of cloth resting on a sphere as it moved:
    # a jump in the loss)
    depth = buf.depth
    if layers.sphere is not None:
        sphere_rgba, sphere_depth = layers.sphere
        # weight of the sphere in front; cloth resting on a sphere wins ties
        pixel = 2.0 / (camera.height * camera.projection[1, 1])
        front = layer_in_front(
            buf.surface_id >= 0, buf.depth, sphere_depth, pixel, camera.is_perspective
        )[..., None]
        front = materialize(front)
        over = sphere_rgba + (1.0 - sphere_rgba[..., 3:]) * img  # sphere over cloth
        under = img + (1.0 - img[..., 3:]) * sphere_rgba  # cloth over sphere
        blend = under + front * (over - under)
        img = jnp.where(front >= 1.0, over, jnp.where(front <= 0.0, under, blend))
        cloth_mask = cloth_mask * (1.0 - front[..., 0] * sphere_rgba[..., 3])
        depth = jnp.minimum(depth, sphere_depth)
    if planes is not None:
        depth = jnp.minimum(depth, fringe_depth(buf.surface_id >= 0, buf.depth))
        plane_rgba, plane_depth = layers.plane
        front = (plane_depth < depth)[..., None]
        cloth_mask = jnp.where(front[..., 0], (1.0 - plane_rgba[..., 3]) * cloth_mask, cloth_mask)
        img = jnp.where(
            front,
            plane_rgba + (1.0 - plane_rgba[..., 3:]) * img,
            img + (1.0 - img[..., 3:]) * plane_rgba,
        )
    if background is not None:
        # rgb + (1 - alpha) bg and alpha + (1 - alpha) 0 = alpha: one elementwise pass (XLA's CPU
        # backend evaluates a concatenate of the two parts entry by entry)
        bg = jnp.concatenate([jnp.asarray(background, img.dtype), jnp.zeros(1, img.dtype)])
        img = img + (1.0 - img[..., 3:]) * bg.reshape(1, 1, 4)
    if return_cloth_mask:
        return img, cloth_mask
    return img
