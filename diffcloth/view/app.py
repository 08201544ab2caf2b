"""The browser viewer: a viser server showing a `ViewModel` (see `diffcloth.view`).

    viewer = Viewer(load_view("configs/drape.toml"), port=8080)   # serves http://127.0.0.1:8080
    viewer.serve_forever()
    export_html(load_view("results/drape_fit"), "results/drape_fit/viewer.html")

Threads: viser runs GUI callbacks on its own thread pool; slider moves only record the wanted
values and wake one re-simulation worker (the latest values win, so a drag does not queue dozens
of runs); a playback thread advances frames; a render worker draws the diffcloth image panel.
"""

from __future__ import annotations

import logging
import math
import socket
import threading
import time
from pathlib import Path

import numpy as np
import viser

from diffcloth.view.model import ViewModel, slider_range
from diffcloth.view.scene3d import _lights, _Scene3D

__all__ = ["Viewer", "export_html", "free_port"]

log = logging.getLogger("diffcloth.view")


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that is free on `host` now."""
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


class Viewer:
    """A live viewer of `model` on http://host:port (127.0.0.1 by default: local only).

    Args:
      model: the ViewModel.
      host, port: where to serve (port None: a free one).
      autoplay: start playing.
      fps: playback frames per second (default: real time, 1 / dt).
    """

    def __init__(
        self,
        model: ViewModel,
        *,
        host: str = "127.0.0.1",
        port: int | None = 8080,
        autoplay: bool = True,
        fps: float | None = None,
    ):
        self.model = model
        self.host = host
        self.port = free_port(host) if port is None else int(port)
        self.server = viser.ViserServer(host=host, port=self.port, verbose=False)
        self.port = self.server.get_port()
        self.frame = model.num_frames - 1 if not autoplay else 0
        self.latencies: list[float] = []  # s, slider message -> new frame sent, per re-simulation
        self._stop = threading.Event()
        self._stopped = False
        self._pending: dict = {}
        self._pending_since: float | None = None
        self._cv = threading.Condition()
        self._render_request = threading.Event()
        self._rendered: set[str] = set()  # shading modes compiled so far
        self.scene3d = _Scene3D(self.server, model)
        self._build_gui(autoplay, fps or min(60.0, 1.0 / max(model.dt, 1e-3)))
        self.scene3d.layout(side_by_side=True)
        self.scene3d.show(self.frame)
        self._threads = [
            threading.Thread(target=self._resim_worker, daemon=True, name="diffcloth-resim"),
            threading.Thread(target=self._play_loop, daemon=True, name="diffcloth-play"),
            threading.Thread(target=self._render_worker, daemon=True, name="diffcloth-render"),
        ]
        for th in self._threads:
            th.start()

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    # ---- GUI ----------------------------------------------------------------------------------
    def _build_gui(self, autoplay: bool, fps: float) -> None:
        m, gui = self.model, self.server.gui
        gui.add_markdown(f"**diffcloth** `{m.name}`: {m.describe()}")
        self.status = gui.add_markdown(f"first simulation, with the compile: {m.compile_s:.1f} s")
        with gui.add_folder("Playback"):
            self.play = gui.add_checkbox("play", initial_value=autoplay)
            self.frame_slider = gui.add_slider(  # one frame (an equilibrium): shown disabled
                "frame",
                min=0,
                max=max(m.num_frames - 1, 1),
                step=1,
                initial_value=self.frame,
                disabled=m.num_frames < 2,
            )
            self.fps = gui.add_slider("fps", min=1.0, max=60.0, step=1.0,
                                      initial_value=float(round(fps)))  # fmt: skip
        self.frame_slider.on_update(lambda _: self._set_frame(self.frame_slider.value))
        cams = m.cameras()
        with gui.add_folder("Cameras"):
            gui.add_markdown("Drag to orbit, scroll to zoom; or jump to a scene camera:")
            for i, pose in enumerate(cams):
                gui.add_button(f"camera {i}").on_click(lambda _, pose=pose: self.set_camera(pose))
        self.sliders = {}
        off = m.sliders_note is not None
        with gui.add_folder("Material" if m.kind == "grid" else "Fabric"):
            if m.kind == "mesh":
                gui.add_markdown(
                    m.sliders_note
                    or (
                        "A move re-solves the rest shape from the start state (seconds; moves "
                        "made meanwhile are merged into the next solve)."
                        if m.scene.sim.mode == "equilibrium"
                        else "A move re-runs the rollout from the start state."
                    )
                )
            for name, (label, unit, scale) in m.sliders.items():
                value = m.values[name]
                lo, hi = slider_range(name, value, scale)
                if scale == "log":
                    init = math.log10(value) if value > 0 else lo
                    h = gui.add_slider(
                        f"log10 {label} ({unit})",
                        min=round(lo, 2),
                        max=round(hi, 2),
                        step=0.05,
                        initial_value=round(init, 2),
                        disabled=off,
                    )
                else:  # fmt: skip
                    h = gui.add_slider(f"{label} ({unit})", min=lo, max=round(hi, 3),
                                       step=round(hi / 100, 4), initial_value=value,
                                       disabled=off)  # fmt: skip
                h.on_update(lambda _, name=name: self._slider_moved(name))
                self.sliders[name] = h
        if m.has_wind:
            with gui.add_folder("Wind (m/s)"):
                for k, axis in enumerate("xyz"):
                    w = float(m.values["wind"][k])
                    lo, hi = slider_range("wind", w)
                    h = gui.add_slider(f"wind {axis}", min=lo, max=hi, step=0.1,
                                       initial_value=w, disabled=off)  # fmt: skip
                    h.on_update(lambda _: self._slider_moved("wind"))
                    self.sliders[f"wind_{axis}"] = h
        self.values_md = gui.add_markdown(self._values_text())
        with gui.add_folder("diffcloth render"):
            from diffcloth.render import SHADING_MODES

            self.shading = gui.add_dropdown(
                "shading", ("off",) + tuple(SHADING_MODES), initial_value="off"
            )
            self.render_cam = gui.add_dropdown(
                "camera",
                tuple(f"camera {i}" for i in range(len(cams))),
                initial_value="camera 0",
            )
            self.image = gui.add_image(np.zeros((8, 8, 3), np.uint8), label="render (sRGB)")
            self.render_note = gui.add_markdown("choose a shading mode (first use compiles it)")
        self.shading.on_update(lambda _: self._render_request.set())
        self.render_cam.on_update(lambda _: self._render_request.set())
        if m.scene.bodies:
            self._build_forces_gui()
        if m.fit is not None:
            self._build_fit_gui()

    def _build_forces_gui(self) -> None:
        gui, m = self.server.gui, self.model
        with self.server.gui.add_folder("Forces"):
            gui.add_markdown("Acts on the body after the current frame, then re-simulates.")
            self.body = gui.add_dropdown(
                "body", tuple(f"body {i} ({b['shape']})" for i, b in enumerate(m.bodies())),
            )  # fmt: skip
            self.force_dir = gui.add_vector3("direction", (0.0, 1.0, 0.0), step=0.1)
            self.push_dv = gui.add_number("push dv (m/s)", 1.0, min=0.0, max=50.0, step=0.1)
            gui.add_button("push").on_click(lambda _: self._force("push"))
            self.thrust_a = gui.add_number("thrust (m/s^2)", 20.0, min=0.0, max=500.0, step=1.0)
            self.thrust_frames = gui.add_number("thrust frames", 10, min=1, max=m.num_frames,
                                                step=1)  # fmt: skip
            gui.add_button("fire thruster").on_click(lambda _: self._force("fire"))

    def _build_fit_gui(self) -> None:
        gui, fit = self.server.gui, self.model.fit
        with gui.add_folder("Fit result"):
            gui.add_markdown(
                "Cloth: fitted parameters. Green, translucent: the target (the config's [truth])."
                if self.model.target is not None
                else "Cloth: fitted parameters (no [truth] in the config: no target to show)."
            )
            self.layout = gui.add_dropdown(
                "layout", ("side by side", "overlay"), initial_value="side by side"
            )
            self.layout.on_update(
                lambda _: self.scene3d.layout(self.layout.value == "side by side")
            )
            gui.add_markdown(fit.table_markdown())
            if fit.loss.size >= 2:
                steps = np.arange(fit.loss.size, dtype=np.float64)
                gui.add_uplot(
                    data=(steps, np.log10(np.maximum(fit.loss, 1e-30))),
                    series=({"label": "step"}, {"label": "log10 loss", "stroke": "red"}),
                    title="loss",
                    aspect=1.6,
                )

    def _values_text(self) -> str:
        m = self.model
        v = m.values
        parts = [f"{label} {v[n]:.3g}" for n, (label, _, _) in m.sliders.items()]
        if m.has_wind:
            parts.append("wind ({}) m/s".format(", ".join(f"{a:.2g}" for a in v["wind"])))
        return "Values: " + "; ".join(parts)

    def set_camera(self, pose) -> None:
        """Move every connected client's camera to a scene camera pose (`model.camera_pose`)."""
        for client in self.server.get_clients().values():
            with client.atomic():
                client.camera.position = pose["eye"]
                client.camera.look_at = pose["look_at"]
                client.camera.up_direction = pose["up"]
                client.camera.fov = pose["fov"]

    # ---- playback -----------------------------------------------------------------------------
    def _set_frame(self, t: int) -> None:
        if int(t) == self.frame:  # the slider echoing a frame the playback already showed
            return
        self.frame = int(t)
        self.scene3d.show(self.frame)
        if self.shading.value != "off":
            self._render_request.set()

    def _play_loop(self) -> None:
        while not self._stop.is_set():
            if self.play.value:
                nxt = (self.frame + 1) % self.model.num_frames
                self._set_frame(nxt)
                self.frame_slider.value = nxt
            self._stop.wait(1.0 / max(float(self.fps.value), 1.0))

    # ---- re-simulation ------------------------------------------------------------------------
    def _slider_value(self, name: str):
        if name == "wind":
            return np.array([self.sliders[f"wind_{a}"].value for a in "xyz"], np.float64)
        v = float(self.sliders[name].value)
        return 10.0**v if self.model.sliders[name][2] == "log" else v

    def _slider_moved(self, name: str) -> None:
        with self._cv:
            self._pending[name] = self._slider_value(name)
            if self._pending_since is None:
                self._pending_since = time.perf_counter()
            self._cv.notify()

    def _resim_worker(self) -> None:
        while not self._stop.is_set():
            with self._cv:
                while not self._pending and not self._stop.is_set():
                    self._cv.wait(0.2)
                if self._stop.is_set():
                    return
                changes, since = self._pending, self._pending_since
                self._pending, self._pending_since = {}, None
            if self.model.kind == "mesh":  # seconds, not milliseconds: say so meanwhile
                self.status.content = f"re-solving with {self._changes_text(changes)} ..."
            try:
                wall = self.model.resimulate(changes)
            except ValueError as err:
                self.status.content = f"**{err}**"
                log.warning("%s", err)
                self._reset_sliders()
                continue
            self.scene3d.show(self.frame)
            latency = time.perf_counter() - since
            self.latencies.append(latency)
            what = f"re-simulated {self.model.num_frames} frames"
            st = self.model.mesh_status
            if st is not None and self.model.scene.sim.mode == "equilibrium":
                what = f"re-solved the rest shape ({int(st['iterations'][0])} Newton steps)"
            msg = f"{what} in {1e3 * wall:.0f} ms (slider -> frames {1e3 * latency:.0f} ms)"
            self.status.content = msg
            self.values_md.content = self._values_text()
            log.info("%s: %s", msg, changes)
            if self.shading.value != "off":
                self._render_request.set()

    @staticmethod
    def _changes_text(changes) -> str:
        return ", ".join(
            f"{k} {np.round(v, 2).tolist()}" if k == "wind" else f"{k} {v:.3g}"
            for k, v in changes.items()
        )

    def _reset_sliders(self) -> None:
        for name, (_, _, scale) in self.model.sliders.items():
            v = self.model.values[name]
            self.sliders[name].value = math.log10(v) if scale == "log" and v > 0 else v

    def _force(self, kind: str) -> None:
        body = int(str(self.body.value).split()[1])
        try:
            if kind == "push":
                d = np.asarray(self.force_dir.value, np.float64)
                n = np.linalg.norm(d)
                if n == 0:
                    raise ValueError("the force direction is zero")
                wall = self.model.push(body, self.frame, d / n * float(self.push_dv.value))
            else:
                wall = self.model.fire(
                    body, self.frame, self.force_dir.value, float(self.thrust_a.value),
                    int(self.thrust_frames.value),
                )  # fmt: skip
        except ValueError as err:
            self.status.content = f"**{err}**"
            log.warning("%s", err)
            return
        self.scene3d.show(self.frame)
        self.status.content = f"{kind}: re-simulated in {1e3 * wall:.0f} ms"
        log.info("%s", self.model.log[-1])

    # ---- diffcloth render panel ---------------------------------------------------------------
    def _render_worker(self) -> None:
        while not self._stop.is_set():
            if not self._render_request.wait(0.2):
                continue
            self._render_request.clear()
            mode = self.shading.value
            if mode == "off":
                continue
            cam = int(str(self.render_cam.value).split()[1])
            t0 = time.perf_counter()
            try:
                img = self.model.render(self.frame, cam, mode)
            except Exception as err:  # show any render failure in the panel, keep serving
                self.render_note.content = f"**render failed: {err}**"
                log.exception("render failed")
                continue
            self.image.image = img
            ms = 1e3 * (time.perf_counter() - t0)
            first = "" if mode in self._rendered else " (first use: includes the compile)"
            self._rendered.add(mode)
            self.render_note.content = (
                f"{mode}, camera {cam}, frame {self.frame}: {ms:.0f} ms{first}; "
                "linear render, shown sRGB-encoded"
            )

    # ---- lifetime -----------------------------------------------------------------------------
    def serve_forever(self) -> None:
        """Block until Ctrl-C (or `stop()` from another thread), then stop."""
        try:
            while not self._stop.wait(0.5):
                pass
        except KeyboardInterrupt:
            pass
        finally:
            self.stop()

    def stop(self) -> None:
        """Stop the worker threads and the server (idempotent)."""
        if self._stopped:
            return
        self._stopped = True
        self._stop.set()
        with self._cv:
            self._cv.notify_all()
        for th in self._threads:
            th.join(timeout=5)
        self.server.stop()


def export_html(model: ViewModel, path, *, side_by_side: bool = True, speed: float = 1.0) -> Path:
    """Write a self-contained HTML recording of the model's frames (viser's embedded client and
    the scene, zstd-compressed, base64 inside one file). It opens from the file system, offline,
    and plays the sequence with viser's timeline (play, pause, scrub). A fit's target stands beside
    the fit (side_by_side) or over it. Returns the path."""
    path = Path(path)
    server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    try:
        scene3d = _Scene3D(server, model)
        scene3d.layout(side_by_side)
        serializer = server.get_scene_serializer()
        _lights(server)  # the lighting messages are not part of the snapshot: record them
        for t in range(model.num_frames):
            scene3d.show(t)
            serializer.insert_sleep(model.dt / speed)
        html = serializer.as_html()
    finally:
        server.stop()
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(html, encoding="utf-8")
    return path
