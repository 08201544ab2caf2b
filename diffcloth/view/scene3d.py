"""The viewer's 3D scene: the nodes of one `ViewModel` (cloth, target cloth, spheres, planes,
bodies, a mesh cloth's boxes, capped cylinders and triangle-mesh colliders) in a viser server."""

from __future__ import annotations

import numpy as np
import viser

from diffcloth.view.model import ViewModel

TARGET_COLOR = (60, 190, 110)
PLANE_COLOR = (170, 170, 175)
PLANE_SIZE = 4.0  # m, edge of the square drawn for each collision plane
#: spheres are drawn this much smaller, so cloth resting on them (pushed exactly onto the
#: radius) does not z-fight with the sphere's faceted mesh
SPHERE_SHRINK = 0.985
NO_SHADOW = {"cast_shadow": False, "receive_shadow": False}


def _plane_mesh(normal, offset, center):
    """A PLANE_SIZE square on the plane {p: n.p = offset}, centred near `center`."""
    n = np.asarray(normal, np.float64)
    n = n / np.linalg.norm(n)
    c = np.asarray(center, np.float64)
    c = c - (n @ c - offset) * n
    a = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 0.0, 1.0])
    a /= np.linalg.norm(a)
    b = np.cross(n, a)
    h = PLANE_SIZE / 2
    v = np.stack([c + h * (sa * a + sb * b) for sa, sb in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def _lights(server: viser.ViserServer) -> None:
    # Shadows off: they cost a lot in software WebGL (headless browsers, remote desktops).
    server.scene.configure_default_lights(enabled=True, cast_shadow=False)
    server.scene.configure_environment_map(hdri=None)


class _Scene3D:
    """The scene nodes of one model: cloth, target cloth, spheres, planes, bodies, and a mesh
    cloth's static boxes, capped cylinders and triangle-mesh colliders."""

    def __init__(self, server: viser.ViserServer, model: ViewModel):
        self.server, self.model = server, model
        s = server.scene
        s.set_up_direction("+y")
        _lights(server)
        cams = model.cameras()
        if cams:
            ic = server.initial_camera
            ic.position, ic.look_at, ic.up = cams[0]["eye"], cams[0]["look_at"], cams[0]["up"]
            ic.fov = cams[0]["fov"]
        f = model.frames
        self.cloth = s.add_mesh_simple(
            "/cloth", f.cloth[0], model.faces, color=model.cloth_color, side="double", **NO_SHADOW
        )
        center = f.cloth[0].mean(axis=0)
        for i, (normal, offset) in enumerate(model.planes()):
            v, faces = _plane_mesh(normal, offset, center)
            s.add_mesh_simple(
                f"/planes/{i}", v, faces, color=PLANE_COLOR, side="double", **NO_SHADOW
            )
        self.target = None
        self.target_root = None
        roots = ["/"]
        if model.target is not None:
            self.target_root = s.add_frame("/target", show_axes=False)
            self.target = s.add_mesh_simple(
                "/target/cloth", model.target.cloth[0], model.faces, color=TARGET_COLOR,
                side="double", opacity=0.55, **NO_SHADOW,
            )  # fmt: skip
            roots.append("/target/")
        for root in roots:
            for i, (c, r) in enumerate(model.static_spheres()):
                s.add_icosphere(
                    f"{root}spheres/{i}", radius=SPHERE_SHRINK * r, color=model.sphere_color,
                    position=c, subdivisions=4, **NO_SHADOW,
                )  # fmt: skip
        self.bodies = {"/": [], "/target/": []}
        for root in roots:
            for i, b in enumerate(model.bodies()):
                name = f"{root}bodies/{i}"
                if b["shape"] == "sphere":
                    r = SPHERE_SHRINK * b["radius"]
                    h = s.add_icosphere(
                        name, radius=r, color=model.sphere_color, subdivisions=4, **NO_SHADOW
                    )
                else:
                    h = s.add_box(name, dimensions=tuple(2 * b["half_extents"]),
                                  color=model.sphere_color, **NO_SHADOW)  # fmt: skip
                self.bodies[root].append(h)
            for i, b in enumerate(model.boxes()):
                s.add_box(
                    f"{root}boxes/{i}", dimensions=tuple(2 * SPHERE_SHRINK * b["half_extents"]),
                    color=model.sphere_color, position=b["center"], wxyz=b["wxyz"], **NO_SHADOW,
                )  # fmt: skip
            for i, (kind, v, faces) in enumerate(model.collider_meshes()):
                s.add_mesh_simple(
                    f"{root}colliders/{i}_{kind}", v, faces, color=model.sphere_color,
                    side="double", **NO_SHADOW,
                )  # fmt: skip
        self.show(0)

    def show(self, t: int) -> None:
        """Move every node to frame t."""
        m = self.model
        t = int(np.clip(t, 0, m.num_frames - 1))
        with self.server.atomic():
            self.cloth.vertices = m.frames.cloth[t]
            for i, h in enumerate(self.bodies["/"]):
                h.position = m.frames.body_position[t, i]
                h.wxyz = m.frames.body_orientation[t, i]
            if self.target is not None:
                self.target.vertices = m.target.cloth[t]
                for i, h in enumerate(self.bodies["/target/"]):
                    h.position = m.target.body_position[t, i]
                    h.wxyz = m.target.body_orientation[t, i]

    def layout(self, side_by_side: bool) -> None:
        """Target over the fit, or beside it (+x); the initial ("Reset View") camera is scene
        camera 0, moved back and sideways to frame both when they stand side by side."""
        if self.target_root is None:
            return
        rest = np.asarray(self.model.scene.net.rest)
        shift = np.array([1.4 * max(float(np.ptp(rest[..., 0])), 0.5), 0.0, 0.0])
        self.target_root.position = shift if side_by_side else np.zeros(3)
        cams = self.model.cameras()
        if cams:
            eye, at = cams[0]["eye"], cams[0]["look_at"]
            if side_by_side:
                at = at + shift / 2
                eye = at + 1.7 * (eye - cams[0]["look_at"])
            ic = self.server.initial_camera
            ic.position, ic.look_at = eye, at
