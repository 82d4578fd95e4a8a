"""The viser server: a :class:`~physavatar.viewer.scene.Scene` as scene nodes and a panel.

One mesh node per layer; a frame change sends only that frame's vertices of the visible layers
(``handle.vertices = ...``), so a long sequence never travels to the browser at once. Layers with
ground truth get a second, hidden node coloured by per-vertex error (a GLB with vertex colours,
rebuilt for the current frame only while it is shown). Capture cameras are frustums with their
image at the current frame; a button per camera moves every browser's view to it.
"""

from __future__ import annotations

import contextlib
import errno
import io
import json
import socket
import threading
import time
from pathlib import Path

import numpy as np

from ..errors import PhysavatarError
from .scene import ERROR_MM, Scene

HOST = "127.0.0.1"
REPORT_FRAMES = 60  # the frames of a run's OUT/view.html (``physavatar run``'s report links it)


def check_port(port: int, host: str = HOST) -> None:
    """Raise a clear :class:`PhysavatarError` when ``port`` cannot be bound on ``host`` (viser would
    silently move to the next port)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind((host, port))
        except OSError as e:
            why = "is in use" if e.errno == errno.EADDRINUSE else f"cannot be bound ({e.strerror})"
            raise PhysavatarError(f"{host}:{port}", f"port {port} {why}; pick another with --port N, "
                                                    "or leave --port out for a free one") from None


@contextlib.contextmanager
def _quiet(on: bool):
    if not on:
        yield
        return
    with contextlib.redirect_stdout(io.StringIO()):
        yield


def error_colors(err_m: np.ndarray) -> np.ndarray:
    """[N] distances (metres) -> [N, 3] uint8, blue (0) to red (:data:`ERROR_MM`)."""
    x = np.clip(err_m * 1000.0 / ERROR_MM, 0.0, 1.0)[:, None]
    lo, mid, hi = np.array([40, 80, 220.0]), np.array([240, 240, 240.0]), np.array([220, 40, 30.0])
    c = np.where(x < 0.5, lo + (mid - lo) * (2 * x), mid + (hi - mid) * (2 * x - 1))
    return c.astype(np.uint8)


def textured_mesh(vertices, faces, uvs, texture):
    """A trimesh with ``texture`` ([H, W, 3] uint8 sRGB) on per-corner ``uvs`` ([F, 3, 2], v up):
    one vertex per face corner (UV seams), a double-sided, rough, non-metallic glTF material."""
    import trimesh
    from PIL import Image

    faces = np.asarray(faces, np.int64)
    V = np.asarray(vertices, np.float32)[faces].reshape(-1, 3)
    mat = trimesh.visual.material.PBRMaterial(baseColorTexture=Image.fromarray(np.ascontiguousarray(texture)),
                                              metallicFactor=0.0, roughnessFactor=1.0, doubleSided=True)
    visual = trimesh.visual.TextureVisuals(uv=np.asarray(uvs, np.float32).reshape(-1, 2), material=mat)
    return trimesh.Trimesh(V, np.arange(len(V)).reshape(-1, 3), visual=visual, process=False)


class Viewer:
    """A running viewer of ``scene``. ``port=None``: a free port. ``nodes``: scene-node name ->
    viser handle; ``slider``: the time slider; :meth:`set_frame` is what the slider calls."""

    def __init__(self, scene: Scene, port: int | None = None, verbose: bool = False):
        import viser

        self.scene = scene
        if port is not None:
            check_port(port)
        with _quiet(not verbose):  # viser prints its own URL table; the CLI prints one line
            self.server = viser.ViserServer(host=HOST, port=port or 0, label=f"physavatar · {scene.kind}",
                                            verbose=verbose)
        if port is not None and self.server.get_port() != port:  # lost a race for the port
            self.server.stop()
            raise PhysavatarError(f"{HOST}:{port}", f"port {port} is in use; pick another with --port N")
        self.port = self.server.get_port()
        self.url = f"http://{HOST}:{self.port}"
        self.nodes: dict[str, object] = {}
        self.t = 0
        self._lock = threading.RLock()
        self._playing = False
        self._stop = threading.Event()
        self._build()
        self._player = threading.Thread(target=self._play_loop, daemon=True, name="physavatar-viewer-play")
        self._player.start()

    # -- building ----------------------------------------------------------------------------
    def _build(self) -> None:
        sc, srv = self.scene, self.server
        srv.scene.set_up_direction(sc.up)
        srv.scene.add_grid("/grid", width=4.0, height=4.0, plane={"+z": "xy", "+y": "xz", "+x": "yz"}[sc.up],
                           cell_size=0.25)
        self._init_camera()
        for ly in sc.layers:
            if not ly.deferred:  # a deferred layer's node is made when it is first shown
                self._add_node(ly, ly.visible and self._present(ly, 0))
        for cam in sc.cameras:
            from viser import transforms as tf

            img = cam.image(0)
            h = srv.scene.add_camera_frustum(f"/cameras/{cam.name}", fov=cam.fov_y, aspect=cam.aspect, scale=0.15,
                                             image=img, wxyz=tf.SO3.from_matrix(cam.c2w[:3, :3]).wxyz,
                                             position=cam.c2w[:3, 3], color=(60, 60, 60))
            self.nodes[f"/cameras/{cam.name}"] = h
        for L in sc.lights:
            add = {"ambient": srv.scene.add_light_ambient, "directional": srv.scene.add_light_directional,
                   "point": srv.scene.add_light_point}[L["kind"]]
            kw = {"position": L["position"]} if "position" in L else {}
            self.nodes[f"/lights/{L['name']}"] = add(f"/lights/{L['name']}", color=L["color"],
                                                     intensity=L["intensity"], **kw)
        if sc.lights:  # under its fitted light only (viser's default lights off)
            srv.scene.configure_default_lights(enabled=False)
        self._build_gui()

    def _add_node(self, ly, visible: bool, t: int | None = None):
        ly.materialize()
        if t is None:
            t = 0 if ly.static else self._first_index(ly)
        V = ly.frame(t) if t is not None else None
        if V is None:
            V = np.zeros((int(ly.faces.max()) + 1 if ly.faces.size else 0, 3), np.float32)
        if ly.splats is not None:
            d = ly.splats(t if t is not None else 0)
            if d is None:
                d = {k: np.zeros((0, *sh), np.float32) for k, sh in
                     (("centers", (3,)), ("covariances", (3, 3)), ("rgbs", (3,)), ("opacities", (1,)))}
            h = self.server.scene.add_gaussian_splats(ly.name, **d, visible=visible)
        elif ly.texture is not None:
            h = self.server.scene.add_mesh_trimesh(ly.name, textured_mesh(V, ly.faces, ly.uvs, ly.texture),
                                                   visible=visible)
        elif ly.points:
            h = self.server.scene.add_point_cloud(ly.name, V, colors=ly.color, point_size=0.008, point_shape="circle",
                                                  visible=visible)
        else:
            h = self.server.scene.add_mesh_simple(ly.name, V, ly.faces, color=ly.color, opacity=ly.opacity,
                                                  side="double", visible=visible)
        self.nodes[ly.name] = h
        return h

    @staticmethod
    def _first_index(ly) -> int | None:
        """The timeline index of the layer's first frame without NaN (None: every frame has)."""
        return next((t for t in range(ly.offset, ly.offset + ly.n_frames) if ly.frame(t) is not None), None)

    def _first_frame(self, ly):
        t = self._first_index(ly)
        return None if t is None else ly.frame(t)

    def _present(self, ly, t: int) -> bool:
        return ly.static or ly.frame(t) is not None

    def _init_camera(self) -> None:
        """Look at the first frame's centre from inside the camera ring (from the first capture
        camera's side, nearer and a little above), or from the front."""
        sc, cam = self.scene, self.server.initial_camera
        up = np.array({"+z": (0.0, 0.0, 1.0), "+y": (0.0, 1.0, 0.0), "+x": (1.0, 0.0, 0.0)}[sc.up])
        Vs = [v for v in (self._first_frame(ly) for ly in sc.layers if ly.visible) if v is not None]
        V = np.concatenate(Vs) if Vs else np.zeros((1, 3))
        centre, size = (V.min(0) + V.max(0)) / 2, float(np.ptp(V, axis=0).max()) or 1.0
        side = sc.cameras[0].c2w[:3, 3] - centre if sc.cameras else -np.cross(up, np.roll(up, 1))
        side = side - up * (side @ up)
        side /= np.linalg.norm(side) or 1.0
        cam.position = tuple(centre + side * 1.25 * size + up * 0.2 * size)
        cam.look_at = tuple(centre)
        cam.up = tuple(up)

    def _build_gui(self) -> None:
        sc, gui = self.scene, self.server.gui
        n = sc.n_frames
        with gui.add_folder("time"):
            self.slider = gui.add_slider("frame", min=0, max=max(n - 1, 0), step=1, initial_value=0,
                                         disabled=n <= 1)
            self.play = gui.add_button("play / pause", disabled=n <= 1)
            self.fps = gui.add_number("fps", initial_value=float(sc.fps), min=0.1, max=240.0, step=0.1)
            self.status = gui.add_markdown(self._status_text(0))
        # setting the slider from set_frame fires this too: only a change from the browser re-draws
        self.slider.on_update(lambda _: int(self.slider.value) != self.t and self.set_frame(int(self.slider.value)))
        self.play.on_click(lambda _: self.toggle_play())
        with gui.add_folder("layers"):
            self.toggles = {}
            for ly in sc.layers:
                cb = gui.add_checkbox(ly.name.strip("/"), initial_value=ly.visible)
                cb.on_update(lambda ev, ly=ly: self._set_visible(ly, ev.target.value))
                self.toggles[ly.name] = cb
            self.error_toggles = {}
            for ly in sc.layers:
                if ly.truth is None:
                    continue
                cb = gui.add_checkbox(f"{ly.name.strip('/')}: error vs truth", initial_value=False,
                                      hint=f"per-vertex distance to the ground truth, blue 0 to red {ERROR_MM:g} mm")
                cb.on_update(lambda ev, ly=ly: self._set_error(ly, ev.target.value))
                self.error_toggles[ly.name] = cb
            if sc.cameras:
                cb = gui.add_checkbox("cameras", initial_value=True)
                cb.on_update(lambda ev: [setattr(self.nodes[f"/cameras/{c.name}"], "visible", ev.target.value)
                                         for c in sc.cameras])
            if sc.lights:
                cb = gui.add_checkbox("fitted light", initial_value=True,
                                      hint="the avatar's fitted light (light.json) instead of the viewer's default lights")
                cb.on_update(lambda ev: self._set_lights(ev.target.value))
                self.light_toggle = cb
            self.masks = None
            if any(c.mask is not None for c in sc.cameras):
                self.masks = gui.add_checkbox("cameras: masks", initial_value=False,
                                              hint="show each camera's foreground mask instead of its image")
                self.masks.on_update(lambda _: self._update_images())
        if sc.cameras:
            with gui.add_folder("views", expand_by_default=False):
                for cam in sc.cameras:
                    b = gui.add_button(cam.name)
                    b.on_click(lambda ev, cam=cam: self.snap_to(cam.name, ev.client))
        if sc.notes:
            with gui.add_folder("notes"):
                gui.add_markdown("\n".join(f"- {n}" for n in sc.notes))
        for title, data in sc.panels.items():
            with gui.add_folder(title, expand_by_default=False):
                gui.add_markdown("```\n" + json.dumps(data, indent=1, default=str)[:6000] + "\n```")

    # -- state ---------------------------------------------------------------------------------
    def _status_text(self, t: int) -> str:
        missing = self.scene.missing(t)
        s = f"frame **{t}** of {self.scene.n_frames}"
        if missing:
            s += "  \n⚠ missing (not finite): " + ", ".join(m.strip("/") for m in missing)
        return s

    def set_frame(self, t: int) -> None:
        """Show timeline frame ``t``: send the current frame of every visible layer (and its error
        colours when shown), hide layers without a frame there, move the camera images."""
        with self._lock:
            t = int(np.clip(t, 0, max(self.scene.n_frames - 1, 0)))
            self.t = t
            for ly in self.scene.layers:
                self._update_layer(ly)
            self._update_images()
            self.status.content = self._status_text(t)
            if int(self.slider.value) != t:
                self.slider.value = t

    def _update_layer(self, ly) -> None:
        want = self.toggles[ly.name].value if hasattr(self, "toggles") else ly.visible
        h = self.nodes.get(ly.name)
        if h is None:  # deferred, not built yet
            if not want:
                return
            h = self._add_node(ly, False, self.t)
        err_on = ly.name in getattr(self, "error_toggles", {}) and self.error_toggles[ly.name].value
        V = None if ly.static or not want else ly.frame(self.t)  # a hidden layer's frame is not read
        if not ly.static:
            if V is not None and want and not err_on:
                if ly.splats is not None:  # a frame's Gaussians: the node is sent again
                    h = self._add_node(ly, True, self.t)
                elif ly.points:
                    h.points = V
                else:
                    h.vertices = V
            h.visible = bool(want and not err_on and V is not None)
        else:
            h.visible = bool(want and not err_on)
        if err_on:
            self._show_error(ly)

    def _set_lights(self, on: bool) -> None:
        for L in self.scene.lights:
            self.nodes[f"/lights/{L['name']}"].visible = on
        self.server.scene.configure_default_lights(enabled=not on)

    def _update_images(self) -> None:
        """Each camera frustum's image (or mask, when ``cameras: masks`` is on) at the current frame."""
        with self._lock:
            masks = getattr(self, "masks", None) is not None and self.masks.value
            for cam in self.scene.cameras:
                img = (cam.mask if masks and cam.mask is not None else cam.image)(self.t)
                if img is not None:
                    self.nodes[f"/cameras/{cam.name}"].image = img

    def _show_error(self, ly) -> None:
        import trimesh

        name = ly.name + "_error"
        err = ly.error(self.t)
        old = self.nodes.pop(name, None)
        if old is not None:
            old.remove()
        if err is None:
            return
        mesh = trimesh.Trimesh(ly.frame(self.t), ly.faces, vertex_colors=error_colors(err), process=False)
        self.nodes[name] = self.server.scene.add_mesh_trimesh(name, mesh)

    def _set_visible(self, ly, on: bool) -> None:
        with self._lock:
            self._update_layer(ly)

    def _set_error(self, ly, on: bool) -> None:
        with self._lock:
            if not on and ly.name + "_error" in self.nodes:
                self.nodes.pop(ly.name + "_error").remove()
            self._update_layer(ly)

    def snap_to(self, camera: str, client=None) -> None:
        """Move ``client``'s view (every connected browser when None) to capture camera ``camera``."""
        from viser import transforms as tf

        cam = next(c for c in self.scene.cameras if c.name == camera)
        clients = [client] if client is not None else list(self.server.get_clients().values())
        for c in clients:
            with c.atomic():
                c.camera.wxyz = tf.SO3.from_matrix(cam.c2w[:3, :3]).wxyz
                c.camera.position = cam.c2w[:3, 3]
                c.camera.fov = cam.fov_y

    def toggle_play(self) -> None:
        self._playing = not self._playing

    def _play_loop(self) -> None:
        while not self._stop.is_set():
            if not self._playing or self.scene.n_frames <= 1:
                time.sleep(0.05)
                continue
            t0 = time.perf_counter()
            self.set_frame((self.t + 1) % self.scene.n_frames)
            dt = 1.0 / max(float(self.fps.value), 0.1)
            time.sleep(max(0.0, dt - (time.perf_counter() - t0)))

    # -- saving and stopping ---------------------------------------------------------------------
    def save_html(self, path: str | Path, max_frames: int = 300) -> Path:
        """A self-contained HTML file (viser's embed build with the scene inlined) that plays the
        sequence without the server: every frame of the visible layers, at the sequence's fps.
        The GUI (slider, toggles, panels) is not part of viser's scene serialization."""
        from ..files import write_text_atomic

        path = Path(path)
        with self._lock:
            playing, self._playing = self._playing, False
            t_keep = self.t
            self.set_frame(0)
            ser = self.server.get_scene_serializer()
            n = min(self.scene.n_frames, max_frames)
            for t in range(1, n):
                ser.insert_sleep(1.0 / self.scene.fps)
                self.set_frame(t)
            if n > 1:
                ser.insert_sleep(1.0 / self.scene.fps)
            html = ser.as_html()
            self.set_frame(t_keep)
            self._playing = playing
        write_text_atomic(path, html)
        return path

    def stop(self) -> None:
        self._stop.set()
        with _quiet(True):
            self.server.stop()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()


def save_view(path: str | Path, dest: str | Path, max_frames: int = 300) -> Path:
    """``physavatar view PATH --save DEST`` as a function: the folder's scene served on a free port
    just long enough to serialize it into a self-contained HTML file."""
    from .scene import load_scene

    with Viewer(load_scene(path)) as v:
        return v.save_html(dest, max_frames=max_frames)
