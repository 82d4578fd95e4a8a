"""What the viewer shows: a folder recognized and turned into layers, cameras and panels.

Everything is read through the objects that own the files (``capture.load_capture``,
``data.TrackedSequence``, ``GarmentSequence``, ``AnimatedSequence``, ``Avatar``,
``FittedMaterial``); sequences are opened memory-mapped (``mapped=True``) and with NaN frames
accepted (``finite=False``), so a layer reads one frame when the time slider asks for it and a
frame that is not finite is reported missing instead of failing the whole folder.

Kinds of folder (:func:`detect`): a run (``run.json``), an avatar (``avatar.json``), an animate
output (``sequence.npz``), a simulate output (``garment_sequence.npz``), a tracking output
(``tracked.npz``) and a capture (``capture.json``). An ``.npz`` file is read as the sequence it
holds.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import PhysavatarError
from ..files import read_json

KINDS = {  # marker file -> kind, in the order tried
    "run.json": "run",
    "avatar.json": "avatar",
    "sequence.npz": "animation",
    "garment_sequence.npz": "simulation",
    "tracked.npz": "tracking",
    "capture.json": "capture",
}
BODY = (200, 186, 170)
GARMENTS = [(70, 130, 220), (230, 140, 50), (90, 180, 90), (200, 80, 160), (150, 110, 220)]
TRUTH = (60, 200, 120)
BOUNDARY = (230, 40, 40)
ERROR_MM = 20.0  # the error colour map saturates here (red)


def garment_color(label: int) -> tuple[int, int, int]:
    return BODY if label == 0 else GARMENTS[(label - 1) % len(GARMENTS)]


@dataclasses.dataclass(eq=False)
class Layer:
    """One mesh over time: ``vertices`` [T, N, 3] (or [N, 3], static) array-like, read one frame at a
    time; ``index`` picks this layer's vertices out of a larger mesh (a label's part), ``faces``
    index the picked ones. ``truth`` (same shape as ``vertices``, same ``index``) colours the
    layer by per-vertex distance to it."""

    name: str
    vertices: object
    faces: np.ndarray
    color: tuple[int, int, int] = BODY
    index: np.ndarray | None = None
    truth: object | None = None
    visible: bool = True
    opacity: float | None = None
    offset: int = 0  # the layer's frame 0 is the timeline's frame ``offset``
    points: bool = False  # drawn as a point cloud of its vertices (``faces`` empty)
    texture: np.ndarray | None = None  # [H, W, 3] uint8 sRGB, with ``uvs`` [F, 3, 2] (static layers)
    # drawn as Gaussian splats: timeline frame -> {centers, covariances, rgbs, opacities} or None
    splats: Callable[[int], dict | None] | None = None
    uvs: np.ndarray | None = None
    # computed, not read: nothing is built until the layer is first shown (``faces`` None until
    # then, filled by :meth:`materialize`), and it is never scanned for missing frames
    deferred: bool = False

    def materialize(self) -> None:
        """Build what a deferred layer needs to be drawn (its faces; frames come one at a time)."""
        if self.faces is None:
            self.faces = np.asarray(self.vertices.faces, np.int64)

    @property
    def static(self) -> bool:
        return np.ndim(self.vertices) == 2

    @property
    def n_frames(self) -> int:
        return 1 if self.static else len(self.vertices)

    def frame(self, t: int) -> np.ndarray | None:
        """[N, 3] float32 at timeline frame ``t``; None when missing (outside the sequence or not
        finite)."""
        V = self._read(self.vertices, t)
        return None if V is None or not np.all(np.isfinite(V)) else V

    def error(self, t: int) -> np.ndarray | None:
        """Per-vertex distance (metres) to :attr:`truth` at frame ``t``; None without truth there."""
        if self.truth is None:
            return None
        V, G = self.frame(t), self._read(self.truth, t)
        if V is None or G is None or not np.all(np.isfinite(G)):
            return None
        return np.linalg.norm(V - G, axis=1)

    def _read(self, arr, t: int) -> np.ndarray | None:
        if np.ndim(arr) == 2:
            V = arr
        else:
            t = t - self.offset
            if t < 0 or t >= len(arr):
                return None
            V = arr[t]
        V = np.asarray(V if self.index is None else V[self.index], np.float32)
        return V


@dataclasses.dataclass(eq=False)
class ViewCamera:
    """A capture camera: its pose and a function giving its (downscaled, uint8) image at a
    timeline frame (None where there is none)."""

    name: str
    c2w: np.ndarray
    fov_y: float  # radians
    aspect: float
    image: Callable[[int], np.ndarray | None]
    mask: Callable[[int], np.ndarray | None] | None = None  # the foreground mask, as an RGB image


@dataclasses.dataclass(eq=False)
class Scene:
    """What one folder shows; ``notes`` are lines shown in the panel (what is missing and why)."""

    path: Path
    kind: str
    fps: float = 25.0
    layers: list[Layer] = dataclasses.field(default_factory=list)
    cameras: list[ViewCamera] = dataclasses.field(default_factory=list)
    panels: dict[str, dict] = dataclasses.field(default_factory=dict)
    notes: list[str] = dataclasses.field(default_factory=list)
    up: str = "+z"
    # lights drawn as viser light nodes: {"kind": ambient|directional|point, "name", "color" (sRGB
    # 0-255), "intensity", "position"}; the fitted light of an avatar
    lights: list[dict] = dataclasses.field(default_factory=list)

    @property
    def n_frames(self) -> int:
        return max([ly.offset + ly.n_frames for ly in self.layers] + [1])

    def missing(self, t: int) -> list[str]:
        """Names of the (non-static) layers without a finite frame at ``t`` though ``t`` is in
        their range: NaN frames."""
        return [ly.name for ly in self.layers if not ly.static and not ly.deferred
                and ly.offset <= t < ly.offset + ly.n_frames and ly.frame(t) is None]


def detect(path: str | Path) -> tuple[str, Path]:
    """The kind of ``path`` and the folder (or .npz file) to read; raises a clear
    :class:`PhysavatarError` for anything else."""
    path = Path(path)
    if not path.exists():
        raise PhysavatarError(path, "not found")
    if path.is_file():
        if path.suffix == ".npz" and path.name in KINDS:
            return KINDS[path.name], path.parent
        if path.suffix == ".npz":
            return "npz", path
        if path.name in KINDS:
            return KINDS[path.name], path.parent
        raise PhysavatarError(path, "the viewer shows folders (a capture, a run, a track, simulate, animate or avatar "
                                    "output) or a sequence .npz")
    for marker, kind in KINDS.items():
        if (path / marker).is_file():
            return kind, path
    raise PhysavatarError(path, "not a folder the viewer knows: expected one of " + ", ".join(KINDS)
                          + " (a run, an avatar, an animate, simulate or tracking output, a capture)")


def load_scene(path: str | Path) -> Scene:
    kind, root = detect(path)
    scene = Scene(root, kind)
    {"run": _run, "avatar": _avatar, "animation": _animation, "simulation": _simulation, "tracking": _tracking,
     "capture": _capture, "npz": _npz}[kind](scene, root)
    if not scene.layers:
        raise PhysavatarError(root, "nothing to show (no mesh found)")
    return scene


# -- builders ------------------------------------------------------------------------------------

def _split(scene: Scene, prefix: str, vertices, faces, labels, *, truth=None, color=None, visible=True,
           opacity=None, offset=0) -> list[Layer]:
    """One layer per label (body, garment 1, ...) of a labelled mesh, or one when unlabelled."""
    faces = np.asarray(faces, np.int64)
    out = []
    if labels is None:
        out.append(Layer(prefix, vertices, faces, color or GARMENTS[0], truth=truth, visible=visible,
                         opacity=opacity, offset=offset))
    else:
        labels = np.asarray(labels)
        face_label = labels[faces].min(axis=1)  # a face touching the body belongs to the body
        for lab in np.unique(labels):
            fsel = faces[face_label == lab]
            if not len(fsel):
                continue
            idx = np.unique(fsel)
            remap = np.full(len(labels), -1, np.int64)
            remap[idx] = np.arange(len(idx))
            name = f"{prefix}/{'body' if lab == 0 else f'garment{int(lab)}'}"
            out.append(Layer(name, vertices, remap[fsel], color or garment_color(int(lab)), index=idx, truth=truth,
                             visible=visible, opacity=opacity, offset=offset))
    scene.layers.extend(out)
    return out


def _nan_note(scene: Scene, name: str, V) -> None:
    if np.ndim(V) != 3:
        return
    bad = [t for t in range(len(V)) if not np.all(np.isfinite(V[t]))]
    if bad:
        scene.notes.append(f"{name}: {len(bad)} of {len(V)} frames are not finite (shown as missing): "
                           + ", ".join(map(str, bad[:10])) + (" ..." if len(bad) > 10 else ""))


def _capture(scene: Scene, root: Path, *, layers: bool = True, overlay: bool = False) -> object:
    from ..capture import load_capture

    cap = load_capture(root)
    scene.fps = cap.fps
    scene.up = {"z": "+z", "y": "+y", "x": "+x"}.get(str(cap.meta.get("up", "z")), "+z")
    scene.panels["capture"] = {k: v for k, v in cap.meta.items() if k != "frames"} | {
        "frames": len(cap.frames), "cameras": [c.name for c in cap.cameras]}
    for cam in cap.cameras:
        scene.cameras.append(ViewCamera(cam.name, cam.c2w, np.radians(cam.fov_y_deg), cam.width / cam.height,
                                        _image_reader(cap, cam.name),
                                        _image_reader(cap, cam.name, mask=True) if cap.has_masks else None))
    tpl = cap.template
    if layers:
        _split(scene, "/capture/template", tpl.vertices, tpl.faces, tpl.labels, visible=False)
        labels = np.asarray(tpl.labels)
        scene.panels["template labels"] = {
            ("body" if lab == 0 else f"garment{int(lab)}"): {"vertices": int((labels == lab).sum()),
                                                             "colour": list(garment_color(int(lab)))}
            for lab in np.unique(labels)} | {"boundary vertices (points)": int(np.sum(tpl.boundary))}
        if np.any(tpl.boundary):
            scene.layers.append(Layer("/capture/template/boundary", np.asarray(tpl.vertices)[np.asarray(tpl.boundary, bool)],
                                      np.zeros((0, 3), np.int64), BOUNDARY, visible=False, points=True))
        if len(cap.body.rotations):
            scene.layers.append(Layer("/capture/body", _PosedBody(cap.body), None, BODY, visible=False, deferred=True))
    gt = cap.ground_truth
    if gt is not None and (gt / "meshes.npz").is_file():
        from ..data.tracked import TrackedSequence

        truth = TrackedSequence.load(gt / "meshes.npz", finite=False, mapped=True)
        _nan_note(scene, "ground truth", truth.vertices)
        if layers:
            _split(scene, "/capture/ground_truth", truth.vertices, tpl.faces if truth.faces is None else truth.faces,
                   tpl.labels, color=TRUTH if overlay else None)
        if (gt / "material.json").is_file():
            scene.panels["true material"] = read_json(gt / "material.json")
        return cap, truth
    return cap, None


def _image_reader(cap, name: str, max_px: int = 256, mask: bool = False) -> Callable[[int], np.ndarray | None]:
    """Camera ``name``'s image (or foreground mask, grey) at timeline frame t, downscaled to
    ``max_px`` on its long side, uint8 RGB."""
    def image(t: int) -> np.ndarray | None:
        if not 0 <= t < len(cap.frames):
            return None
        try:
            img = cap.mask(name, cap.frames[t]) if mask else cap.image(name, cap.frames[t])
        except PhysavatarError:
            return None
        step = max(1, int(np.ceil(max(img.shape[:2]) / max_px)))
        img = img[::step, ::step]
        img = np.repeat(img[..., None], 3, axis=2) if img.ndim == 2 else img[..., :3]
        return (np.clip(img, 0, 1) * 255).astype(np.uint8)

    return image


class _PosedBody:
    """The capture's Anny body (body.npz) posed one frame at a time, as a [T, N, 3] array-like: the
    model (``BodyModel(shape, topology=body.npz's)``, about 2 s, a minute on a machine without
    Anny's disk cache) is built on the first frame or faces asked for."""

    def __init__(self, poses):
        self.poses = poses
        self._model = None

    def _body(self):
        if self._model is None:
            from ..body import BodyModel

            self._model = BodyModel(self.poses.shape, topology=self.poses.topology)
        return self._model

    @property
    def faces(self) -> np.ndarray:
        return self._body().faces

    def __len__(self):
        return len(self.poses.rotations)

    @property
    def ndim(self):
        return 3

    def __getitem__(self, t):
        p = self.poses
        return self._body().pose(p.rotations[t:t + 1], p.root_translation[t:t + 1]).vertices[0]


def _tracking(scene: Scene, root: Path, *, cap=None, truth=None) -> None:
    from ..data.tracked import TrackedSequence

    seq = TrackedSequence.load(root, finite=False, mapped=True)
    if seq.fps:
        scene.fps = seq.fps
    own_capture = cap is not None  # a run shows its capture's ground truth already
    if cap is None:
        cap, truth = _capture_of(scene, root / "config.json")
    tv = None
    if truth is not None and truth.vertices.shape[1:] == seq.vertices.shape[1:]:
        if seq.frames is not None and cap is not None:
            pos = {f: i for i, f in enumerate(cap.frames)}
            if all(int(f) in pos for f in seq.frames):
                tv = _Rows(truth.vertices, [pos[int(f)] for f in seq.frames])
        elif len(truth.vertices) >= len(seq.vertices):
            tv = truth.vertices
    faces = seq.faces if seq.faces is not None else (cap.template.faces if cap is not None else None)
    if faces is None:
        raise PhysavatarError(seq.path, "no faces (and no capture to take them from)")
    _nan_note(scene, "tracked", seq.vertices)
    _split(scene, "/track/tracked", seq.vertices, faces, seq.labels, truth=tv)
    if tv is not None and not own_capture:
        _split(scene, "/track/ground_truth", tv, faces, seq.labels, color=TRUTH, visible=False, opacity=0.5)
    if tv is None:
        scene.notes.append("tracked: no ground truth to colour the error by (a synthetic capture has one)")
    if seq.face_colors is not None:
        scene.layers.append(Layer("/track/gaussians", seq.vertices, np.asarray(faces, np.int64), visible=False,
                                  deferred=True, splats=_Splats(seq, faces)))
        if seq.log_scales is None:
            scene.notes.append("tracked Gaussians: no log_scales in tracked.npz: each face's Gaussian drawn with "
                               "in-plane scales of a third of its edge lengths")


class _Splats:
    """The tracked mesh-aligned Gaussians at a frame (``splat.mesh_gaussians``: one flat Gaussian per
    face at its barycentre in the face's frame, the first frame's in-plane scales, the face's
    tracked colour at that frame, the first frame's opacity)."""

    def __init__(self, seq, faces):
        self.seq, self.faces = seq, np.asarray(faces, np.int64)

    def __call__(self, t: int) -> dict | None:
        import torch

        from ..splat.mesh_gaussians import NORMAL_SCALE, mesh_to_gaussians

        seq = self.seq
        if not 0 <= t < len(seq.vertices):
            return None
        V = np.array(seq.vertices[t], np.float32)  # a writable copy (torch.from_numpy)
        if not np.all(np.isfinite(V)):
            return None
        F = torch.from_numpy(self.faces)
        Vt = torch.from_numpy(V)
        if seq.log_scales is not None:
            log_s = torch.from_numpy(np.asarray(seq.log_scales, np.float32))
        else:
            tri = V[self.faces]
            edge = np.linalg.norm(tri - np.roll(tri, -1, axis=1), axis=2).mean(1, keepdims=True)
            log_s = torch.from_numpy(np.log(np.maximum(edge, 1e-6) / 3).repeat(2, 1).astype(np.float32))
        edge_index = None if seq.edge_index is None else torch.from_numpy(np.asarray(seq.edge_index, np.int64))
        with torch.no_grad():
            means, quats, scales = mesh_to_gaussians(Vt, F, log_s, edge_index, NORMAL_SCALE)
        w, x, y, z = quats.double().numpy().T
        R = np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                      np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                      np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], 1)
        S = scales.double().numpy()
        cov = np.einsum("fij,fj,fkj->fik", R, S * S, R)
        rgb = np.clip(np.asarray(seq.face_colors[t], np.float64), 0, 1)
        rgb = np.where(rgb <= 0.0031308, 12.92 * rgb, 1.055 * rgb ** (1 / 2.4) - 0.055)  # linear -> sRGB
        op = (np.ones(len(self.faces)) if seq.opacity_logits is None
              else 1 / (1 + np.exp(-np.asarray(seq.opacity_logits, np.float64))))
        return {"centers": means.numpy().astype(np.float32), "covariances": cov.astype(np.float32),
                "rgbs": rgb.astype(np.float32), "opacities": op[:, None].astype(np.float32)}


class _Rows:
    """``arr[rows[t]]`` for ``t`` (a sequence re-indexed without copying)."""

    def __init__(self, arr, rows):
        self.arr, self.rows = arr, list(rows)

    def __len__(self):
        return len(self.rows)

    def __getitem__(self, t):
        return self.arr[self.rows[t]]

    @property
    def ndim(self):
        return 3

    @property
    def shape(self):
        return (len(self.rows), *self.arr.shape[1:])


def _capture_of(scene: Scene, config: Path):
    """The capture a stage output names in its config.json (``capture``), when it is still there."""
    if not config.is_file():
        return None, None
    src = read_json(config).get("capture")
    if not src or not (Path(src) / "capture.json").is_file():
        return None, None
    try:
        return _capture(scene, Path(src), layers=False)
    except PhysavatarError as e:
        scene.notes.append(f"capture {src}: {e}")
        return None, None


def _simulation(scene: Scene, root: Path) -> None:
    from ..data.garment_sequence import GarmentSequence

    seq = GarmentSequence.load(root, finite=False, mapped=True)
    scene.fps = seq.fps
    _nan_note(scene, "garment", seq.vertices)
    _split(scene, "/simulate/garment", seq.vertices, seq.faces, None, color=GARMENTS[0])
    if seq.body_vertices is not None:
        _split(scene, "/simulate/body", seq.body_vertices, seq.body_faces, None, color=BODY)
    if (root / "config.json").is_file():
        scene.panels["simulate"] = read_json(root / "config.json")


def _animation(scene: Scene, root: Path, *, prefix: str = "/animate", truth=None) -> None:
    from ..data.animated import AnimatedSequence

    seq = AnimatedSequence.load(root, finite=False, mapped=True)
    scene.fps = seq.fps
    tv = truth.vertices if truth is not None and truth.vertices.shape == seq.vertices.shape else None
    _nan_note(scene, "animated", seq.vertices)
    _split(scene, prefix, seq.vertices, seq.faces, seq.labels, truth=tv)
    if truth is not None:
        _split(scene, prefix + "_truth", truth.vertices, seq.faces, seq.labels, color=TRUTH, visible=False,
               opacity=0.5)
    if (root / "sequence.json").is_file():
        scene.panels["animation"] = read_json(root / "sequence.json")


def _avatar(scene: Scene, root: Path) -> None:
    from ..data.avatar import Avatar

    av = Avatar.load(root)
    scene.fps = av.fps
    tpl = av.template
    textured = av.texture is not None and tpl.face_uvs is not None
    if textured:
        if (root / "texture.png").is_file():
            from ..render.image import read_png

            tex = np.asarray(read_png(root / "texture.png"))[..., :3].astype(np.uint8)
        else:
            from ..render.image import linear_to_srgb8

            tex = linear_to_srgb8(av.texture)
        scene.layers.append(Layer("/avatar/textured", np.asarray(tpl.vertices), np.asarray(tpl.faces, np.int64),
                                  texture=tex, uvs=np.asarray(tpl.face_uvs, np.float32)))
    else:
        scene.notes.append("avatar: no texture" + (" UVs" if av.texture is not None else "")
                           + ": drawn in label colours")
    _split(scene, "/avatar", tpl.vertices, tpl.faces, tpl.labels, visible=not textured)
    scene.panels["avatar"] = av.meta
    scene.panels["material"] = read_json(root / "material.json")
    if av.light_path is not None:
        scene.panels["light"] = read_json(av.light_path)
        scene.lights = _viser_lights(scene.panels["light"], tpl.vertices, scene.notes, av.light_path.parent)


ENV_LIGHTS = 16  # directional lights an environment map is drawn with (median cut)


def _viser_lights(data: dict, vertices, notes: list[str], root: Path | None = None) -> list[dict]:
    """light.json's lights (``render.lights``' JSON) as viser (three.js) light nodes: Ambient ->
    ambient, SunLight -> directional from ``to_sun``, PointLight -> point, AreaLight -> a point light
    at its centre, EnvMap -> its median cut (``render.median_cut``): its floor as ambient and
    ``ENV_LIGHTS`` directional lights. Colour: the linear RGB value over its largest channel, to
    sRGB; intensity: that largest channel, in three.js's units, where a diffuse surface gets
    ``intensity`` from a directional light and π × radiance from an ambient one (so Mitsuba's ambient
    radiance L is three.js's ambient intensity πL). A preview of the fit, not a re-rendering: no
    shadows, and three.js's tone mapping."""
    V = np.asarray(vertices, np.float64)
    size = float(np.ptp(V, axis=0).max()) or 1.0
    far = 10.0 * (size + float(np.linalg.norm((V.min(0) + V.max(0)) / 2)))
    out = []
    for i, L in enumerate(data.get("lights", [])):
        kind = L.get("type")
        if kind == "EnvMap":
            for sub in _envmap_lights(L, root, notes):
                out += _viser_lights({"lights": [sub]}, vertices, notes)
            continue
        value = L.get("radiance", L.get("irradiance", L.get("intensity", 1.0)))
        rgb = np.broadcast_to(np.asarray(value, np.float64), (3,))
        if kind == "Ambient":
            rgb = np.pi * rgb
        peak = float(rgb.max()) if rgb.max() > 0 else 1.0
        srgb = np.where(rgb / peak <= 0.0031308, 12.92 * rgb / peak, 1.055 * (rgb / peak) ** (1 / 2.4) - 0.055)
        spec = {"name": str(L.get("name", f"light{i}")), "color": tuple(int(c) for c in np.clip(srgb * 255, 0, 255)),
                "intensity": peak}
        if kind == "Ambient":
            spec["kind"] = "ambient"
        elif kind == "SunLight":  # three.js aims a directional light from its position at the origin
            d = np.asarray(L.get("to_sun", (0.3, -0.5, 0.8)), np.float64)
            spec |= {"kind": "directional", "position": tuple(float(x) for x in far * d / (np.linalg.norm(d) or 1.0))}
        elif kind in ("PointLight", "AreaLight"):
            spec |= {"kind": "point", "position": tuple(map(float, L.get("position", L.get("center", V.mean(0)))))}
        else:
            notes.append(f"light {spec['name']} ({kind}): not drawn (its values are in the light panel)")
            continue
        out.append(spec)
    return out


def _envmap_lights(L: dict, root: Path | None, notes: list[str]) -> list[dict]:
    """An EnvMap entry of light.json as the JSON of its median-cut lights (an inline map, or its
    .hdr/.exr file read by Mitsuba's bitmap reader, relative to ``root``)."""
    from ..render.lights import light_to_json
    from ..render.median_cut import median_cut_lights

    name = str(L.get("name", "envmap"))
    image = L.get("image")
    try:
        if isinstance(image, list):
            img = np.asarray(image, np.float64)
        else:
            from ..render.backend import mitsuba

            path = Path(image)
            path = path if path.is_absolute() or root is None else root / path
            img = np.asarray(mitsuba().Bitmap(str(path)).convert(srgb_gamma=False), np.float64)[..., :3]
        lights = median_cut_lights(img, ENV_LIGHTS, rotation_deg=float(L.get("rotation_deg", 0.0)),
                                   scale=float(L.get("scale", 1.0)), name=name)
    except Exception as e:  # noqa: BLE001 - a light the viewer cannot draw is a note, not a failure
        notes.append(f"light {name} (EnvMap): not drawn ({e})")
        return []
    notes.append(f"light {name} (EnvMap): drawn as its median cut, {len(lights)} lights")
    return [light_to_json(x) for x in lights]


def _npz(scene: Scene, path: Path) -> None:
    from ..data.tracked import TrackedSequence

    seq = TrackedSequence.load(path, finite=False, mapped=True)
    if seq.faces is None:
        raise PhysavatarError(path, "a sequence without faces: nothing to draw")
    if seq.fps:
        scene.fps = seq.fps
    _nan_note(scene, path.stem, seq.vertices)
    _split(scene, "/" + path.stem, seq.vertices, seq.faces, seq.labels)


def _run(scene: Scene, root: Path) -> None:
    record = read_json(root / "run.json")
    scene.panels["run"] = {k: (v.get("status"), v.get("seconds")) if isinstance(v, dict) and "status" in v else v
                           for k, v in record.items() if k != "_config"}
    cap = truth = None
    src = record.get("_capture")
    if src and (Path(src) / "capture.json").is_file():
        cap, truth = _capture(scene, Path(src), overlay=True)
        for ly in scene.layers:  # the capture's own meshes start hidden in a run
            ly.visible = False
    else:
        scene.notes.append(f"run: its capture {src!r} is not there (no cameras, no ground truth)")
    if (root / "track" / "tracked.npz").is_file():
        _tracking(scene, root / "track", cap=cap, truth=truth)
    if (root / "animate" / "sequence.npz").is_file():
        held = None
        if cap is not None and cap.ground_truth is not None and (cap.ground_truth / "heldout" / "meshes.npz").is_file():
            from ..data.tracked import TrackedSequence

            held = TrackedSequence.load(cap.ground_truth / "heldout" / "meshes.npz", finite=False, mapped=True)
        _animation(scene, root / "animate", truth=held)
        for ly in scene.layers:
            if ly.name.startswith("/animate"):
                ly.visible = False  # a different motion than the capture's: shown on request
    if (root / "physics" / "material.json").is_file():
        from ..data.material import FittedMaterial

        scene.panels["fitted material"] = FittedMaterial.load(root / "physics" / "material.json").to_json()
    for metrics in ("evaluate/metrics.json", "metrics.json"):
        if (root / metrics).is_file():
            scene.panels["metrics"] = read_json(root / metrics)
            break
    if not scene.layers:
        raise PhysavatarError(root, "a run without a capture, track or animate output yet: nothing to show")
