"""physavatar view: the viser server started on 127.0.0.1 inside pytest, what it serves, bad input,
the --save HTML, and (when Debian's chromium is installed) a headless browser screenshot."""

from __future__ import annotations

import base64
import io
import json
import re
import shutil
import socket
import subprocess
import time
import urllib.request

import numpy as np
import pytest

pytest.importorskip("viser")

from typer.testing import CliRunner  # noqa: E402

from physavatar.cli import app  # noqa: E402
from physavatar.data.animated import AnimatedSequence  # noqa: E402
from physavatar.data.tracked import TrackedSequence  # noqa: E402
from physavatar.errors import PhysavatarError  # noqa: E402
from physavatar.files import write_json_atomic  # noqa: E402
from physavatar.viewer import Viewer, load_scene  # noqa: E402

NAN_FRAME = 2


@pytest.fixture(scope="module")
def tiny_run(tiny_capture, tmp_path_factory):
    """A run folder in the shape ``physavatar run`` writes (run.json naming the capture, track/,
    animate/, evaluate/metrics.json), made from the capture's ground truth in a second; the tracked
    sequence has a NaN frame."""
    out = tmp_path_factory.mktemp("viewer_run")
    gt = TrackedSequence.load(tiny_capture / "ground_truth" / "meshes.npz")
    V = np.array(gt.vertices, np.float32)
    V[:, :, 0] += 0.01  # 1 cm off the truth everywhere
    V[NAN_FRAME] = np.nan
    colors = np.random.default_rng(0).random((len(V), len(gt.faces), 3)).astype(np.float32)
    TrackedSequence(V, gt.faces, gt.labels, face_colors=colors, frames=np.arange(len(V)),
                    fps=gt.fps).save(out / "track" / "tracked.npz")
    held = TrackedSequence.load(tiny_capture / "ground_truth" / "heldout" / "meshes.npz")
    AnimatedSequence(held.vertices, held.faces, held.labels, None, 25.0).save(out / "animate", {"command": "test"},
                                                                               ply=False)
    write_json_atomic(out / "evaluate" / "metrics.json", {"geometry": {"chamfer_mm": 1.0}})
    write_json_atomic(out / "run.json", {"_capture": str(tiny_capture), "track": {"status": "done", "seconds": 1}})
    return out


@pytest.fixture(scope="module")
def tiny_avatar(tiny_capture, tmp_path_factory):
    """An avatar folder of the tiny capture with a texture (a colour ramp over UV) and a fitted
    light (ambient + sun), as fit-appearance writes them."""
    from physavatar.capture import load_capture
    from physavatar.files import save_npz_atomic
    from physavatar.render import Ambient, SunLight, linear_to_srgb8, save_lights, write_png
    from physavatar.stages.avatar import build_avatar

    root = tmp_path_factory.mktemp("viewer_avatar")
    cap = load_capture(tiny_capture)
    tex = np.zeros((64, 64, 3), np.float32)
    tex[..., 0] = np.linspace(0, 1, 64)[None, :]
    tex[..., 1] = np.linspace(0, 1, 64)[:, None]
    (root / "fit").mkdir()
    np.save(root / "fit" / "texture_linear.npy", tex)
    write_png(root / "fit" / "texture.png", linear_to_srgb8(tex))
    if cap.template.face_uvs is None:  # the texture's own atlas, as fit-appearance writes when there are no UVs
        F = len(cap.template.faces)
        save_npz_atomic(root / "fit" / "atlas.npz", face_uvs=np.random.default_rng(0).random((F, 3, 2)))
    save_lights(root / "fit" / "light.json", [Ambient((0.3, 0.3, 0.3)), SunLight((0.3, -0.5, 0.8), (2.0, 1.8, 1.5))])
    build_avatar(cap, root / "avatar", material=tiny_capture / "ground_truth" / "material.json",
                 texture_dir=root / "fit")
    return root / "avatar"


def _get(url: str) -> tuple[int, str]:
    with urllib.request.urlopen(url, timeout=10) as r:
        return r.status, r.read().decode("utf-8", "replace")


def test_capture_served(tiny_capture):
    from physavatar.capture import load_capture

    cap = load_capture(tiny_capture)
    with Viewer(load_scene(tiny_capture)) as v:
        assert v.url.startswith("http://127.0.0.1:")
        status, page = _get(v.url)
        assert status == 200 and "<html" in page.lower()
        assert {f"/cameras/{c.name}" for c in cap.cameras} <= set(v.nodes)
        assert "/capture/ground_truth/body" in v.nodes and "/capture/template/garment1" in v.nodes
        assert v.slider.max == len(cap.frames) - 1
        body = v.scene.layers[[ly.name for ly in v.scene.layers].index("/capture/ground_truth/body")]
        v.set_frame(3)
        assert np.allclose(v.nodes[body.name].vertices, body.frame(3))
        v.snap_to(cap.cameras[1].name)  # no browser connected: a no-op, not an error
        # the template's labels (a layer and a colour each, in a panel) and boundary (points)
        assert set(v.scene.panels["template labels"]) >= {"body", "garment1", "boundary vertices (points)"}
        bnd = v.nodes["/capture/template/boundary"]
        assert len(bnd.points) == int(cap.template.boundary.sum()) > 0 and bnd.visible is False
        v.toggles["/capture/template/boundary"].value = True
        assert bnd.visible is True
        # masks: the frustums show the mask (grey) instead of the image
        frustum = v.nodes[f"/cameras/{cap.cameras[0].name}"]
        v.masks.value = True
        m = frustum.image
        assert np.array_equal(m[..., 0], m[..., 2]) and m.max() == 255 and m.min() == 0
        v.masks.value = False
        assert not np.array_equal(frustum.image, m)
        # the Anny body of body.npz: no node (no model built) until shown, then posed per frame
        assert "/capture/body" not in v.nodes
        v.toggles["/capture/body"].value = True
        posed = v.nodes["/capture/body"]
        assert posed.visible and np.all(np.isfinite(posed.vertices)) and len(posed.faces) > 1000
        v0 = np.array(posed.vertices)
        v.set_frame(len(cap.frames) - 1)
        assert not np.allclose(posed.vertices, v0)


def test_run_layers_error_and_nan_frame(tiny_run):
    scene = load_scene(tiny_run)
    assert scene.kind == "run"
    names = {ly.name for ly in scene.layers}
    assert {"/track/tracked/body", "/track/tracked/garment1", "/animate/body", "/animate_truth/body"} <= names
    assert {"metrics", "run", "capture"} <= set(scene.panels)
    assert any("not finite" in n for n in scene.notes)
    tracked = next(ly for ly in scene.layers if ly.name == "/track/tracked/body")
    assert np.allclose(tracked.error(0), 0.01, atol=1e-5)
    with Viewer(scene) as v:
        assert _get(v.url)[0] == 200
        v.error_toggles["/track/tracked/body"].value = True
        v.set_frame(1)
        assert "/track/tracked/body_error" in v.nodes
        v.set_frame(NAN_FRAME)  # NaN frame: hidden and named, no crash
        assert v.nodes["/track/tracked/garment1"].visible is False
        assert "/track/tracked/body_error" not in v.nodes
        assert "missing" in v.status.content and "track/tracked/body" in v.status.content
        v.set_frame(NAN_FRAME + 1)
        assert v.nodes["/track/tracked/garment1"].visible is True
        # the tracked Gaussians: one per face, built when first shown, sent again per frame
        assert "/track/gaussians" not in v.nodes
        v.toggles["/track/gaussians"].value = True
        g = v.nodes["/track/gaussians"]
        assert type(g).__name__ == "GaussianSplatHandle" and g.visible and len(g.buffer) == len(tracked_faces(v))
        v.set_frame(0)
        assert v.nodes["/track/gaussians"] is not g and not np.array_equal(v.nodes["/track/gaussians"].buffer, g.buffer)
        v.set_frame(NAN_FRAME)
        assert v.nodes["/track/gaussians"].visible is False


def test_avatar_textured_under_its_light(tiny_avatar):
    scene = load_scene(tiny_avatar)
    assert scene.kind == "avatar"
    tex = next(ly for ly in scene.layers if ly.name == "/avatar/textured")
    assert tex.visible and tex.texture.dtype == np.uint8 and tex.uvs.shape == (len(tex.faces), 3, 2)
    assert {L["kind"] for L in scene.lights} == {"ambient", "directional"}
    with Viewer(scene) as v:
        assert type(v.nodes["/avatar/textured"]).__name__ == "GlbHandle"
        assert not v.nodes["/avatar/body"].visible
        assert {"/lights/ambient", "/lights/sun"} <= set(v.nodes)
        v.light_toggle.value = False
        assert v.nodes["/lights/sun"].visible is False
    from physavatar.viewer.server import textured_mesh

    m = textured_mesh(tex.vertices, tex.faces, tex.uvs, tex.texture)
    assert len(m.vertices) == 3 * len(tex.faces) and m.visual.uv.shape == (len(m.vertices), 2)


def test_save_html(tiny_run, tmp_path):
    res = CliRunner().invoke(app, ["view", str(tiny_run / "animate"), "--save", str(tmp_path / "scene.html")])
    assert res.exit_code == 0, res.output
    html = (tmp_path / "scene.html").read_text()
    assert "__VISER_EMBED_DATA__" in html and len(html) > 100_000


def tracked_faces(v):
    return next(ly for ly in v.scene.layers if ly.name == "/track/gaussians").faces


def test_report_links_view_html(tiny_run, tmp_path):
    """``physavatar run``'s report (write_report) writes OUT/view.html and links it; a run folder the
    viewer cannot show gets a line saying why, not a failed report."""
    from physavatar.report import write_report

    report = write_report(tiny_run).read_text()
    assert "[view.html](view.html)" in report
    html = (tiny_run / "view.html").read_text()
    assert "__VISER_EMBED_DATA__" in html
    write_json_atomic(tmp_path / "run.json", {"_capture": str(tmp_path / "gone")})
    report = write_report(tmp_path).read_text()
    assert "view.html was not written" in report and not (tmp_path / "view.html").exists()


def test_unknown_folder_and_port_in_use(tmp_path):
    with pytest.raises(PhysavatarError, match="not a folder the viewer knows"):
        load_scene(tmp_path)
    res = CliRunner().invoke(app, ["view", str(tmp_path)])
    assert res.exit_code == 2 and "not a folder the viewer knows" in res.output
    (tmp_path / "x.npz").write_bytes(b"not a zip")
    res = CliRunner().invoke(app, ["view", str(tmp_path / "x.npz")])
    assert res.exit_code == 2 and "not a readable .npz" in res.output


def test_port_in_use(tiny_run):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        res = CliRunner().invoke(app, ["view", str(tiny_run / "animate"), "--port", str(port)])
    assert res.exit_code == 2 and f"port {port} is in use" in res.output


# -- a real browser ------------------------------------------------------------------------------

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


class _Browser:
    """Headless Chromium driven over the DevTools protocol (websockets, which viser brings)."""

    def __init__(self, tmp):
        from websockets.sync.client import connect

        self.proc = subprocess.Popen(
            [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
             "--disable-background-networking", "--disable-component-update", "--disable-sync",
             f"--user-data-dir={tmp}", "--remote-debugging-port=0", "--window-size=800,600", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        ws = None
        t0 = time.time()
        for line in self.proc.stderr:
            m = re.search(r"DevTools listening on (ws://\S+)", line)
            if m:
                ws = m.group(1)
                break
            if time.time() - t0 > 30:
                break
        if ws is None:
            self.close()
            pytest.skip("chromium did not start its DevTools endpoint")
        port = int(re.search(r":(\d+)/", ws).group(1))
        targets = json.load(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10))
        self.ws = connect(next(t for t in targets if t["type"] == "page")["webSocketDebuggerUrl"], max_size=None)
        self.i = 0

    def call(self, method, **params):
        self.i += 1
        self.ws.send(json.dumps({"id": self.i, "method": method, "params": params}))
        while True:
            m = json.loads(self.ws.recv(timeout=30))
            if m.get("id") == self.i:
                return m.get("result", m)

    def screenshot(self) -> np.ndarray:
        from PIL import Image

        data = self.call("Page.captureScreenshot", format="png")["data"]
        return np.asarray(Image.open(io.BytesIO(base64.b64decode(data))).convert("RGB")).astype(np.int16)

    def close(self):
        self.proc.kill()
        self.proc.wait()


def _wait_changed(browser, before, region, timeout=20.0):
    t0 = time.time()
    while time.time() - t0 < timeout:
        time.sleep(0.5)
        img = browser.screenshot()
        if before is None or np.abs(img[region] - before[region]).max() > 30:
            return img
    return browser.screenshot()


@pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed (scripts/setup_env.sh installs it)")
def test_browser_draws_mesh_and_slider_changes_picture(tiny_run, tmp_path):
    scene = load_scene(tiny_run / "animate")
    with Viewer(scene) as v:
        b = _Browser(tmp_path / "chromium")
        try:
            b.call("Page.enable")
            b.call("Page.navigate", url=v.url)
            view = (slice(100, None), slice(0, 440))  # the 3D canvas left of the GUI panel, below the toast
            t0 = time.time()
            while True:  # wait for the mesh: pixels in the canvas unlike the background
                time.sleep(1.0)
                first = b.screenshot()
                region = first[view]
                background = np.median(region.reshape(-1, 3), axis=0)
                drawn = np.abs(region - background).max(axis=2) > 40
                body = np.abs(region[..., 0] - region[..., 2]) > 25  # skin or garment, not the grey grid
                if (drawn & body).mean() > 0.002 or time.time() - t0 > 40:
                    break
            assert (drawn & body).mean() > 0.002, "no mesh pixels in the canvas"
            v.set_frame(scene.n_frames - 1)  # the time slider, through the server
            later = _wait_changed(b, first, view)
            assert np.abs(later[view] - first[view]).max(axis=2).__gt__(30).sum() > 50, "the picture did not change"
        finally:
            b.close()
