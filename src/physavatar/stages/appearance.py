"""Physics-based appearance: a relightable diffuse texture by inverse rendering (PhysAvatar Sec. 3.3).

Given the mesh sequence V_1:T (tracked, or the capture's ground truth) and per-face colours c_t
(the tracking stage's Gaussian colours, or colours read from the images here), the paper fits a
time-invariant diffuse texture T and a global ambient light L_a with Mitsuba 3 (Eq. 8):

    L_rgb = min_{T, L_a} sum_{i,t} || I_{i,t} - R(T, L_a, V_t, c_{i,t}) ||²

Steps (``fit_appearance(capture, out, config)``):

1. UV atlas: the template's per-corner UVs, or an automatic ``xatlas`` unwrap when it has none
   (the paper unwraps by hand in Blender).
2. Initial texture T_0 (the paper's initialization): per-face colours averaged over frames,
   splatted into the atlas (each face's UV triangle gets its colour; empty texels are filled
   from the nearest filled one so bilinear lookups at chart borders stay on-chart).
3. Inverse rendering (A.4): each step renders one random (frame, camera) (or a small batch) with
   the ``prb`` path tracer, the loss is the mean squared error in linear RGB inside the
   foreground mask eroded by 2 px, Adam with lr 0.01 halved every 500 steps, texture clipped to
   [0, 1] after each step. Two lighting models:

   - ``ambient`` (the paper): one ambient radiance L_a ∈ R³, initialised to 1.
   - ``studio``: ambient plus the capture's known key light (geometry from the lighting file,
     ``ground_truth/lighting.json`` for synthetic captures), both intensities fitted. Ambient
     light alone cannot produce directional shading, so under a key light the ``ambient`` fit
     bakes the key's shading into the texture; ``studio`` can factor it out.

4. Relighting: :func:`relight` renders a mesh with the texture under any light of
   ``physavatar.render`` (environment maps, sky, sun, point lights, ambient).

Outputs (``out/``)::

    texture.png, texture_linear.npy    fitted albedo atlas (sRGB PNG; linear float32 [H, W, 3])
    texture_init_linear.npy            T_0 (the "w/o appearance" ablation of Table 2)
    atlas.npz                          face_uvs [F, 3, 2], face_colors [F, 3] (T_0's source),
                                       face_pixels [F] (training pixels that saw each face; with
                                       tracked colours counted on 8 frames spread over the sequence)
    light.json                         fitted lights (same format as lighting.json)
    fit_log.csv, loss.png              per-iteration loss, lr, lights, seconds
    preview.png                        target | fitted render of a few training views (final spp)
    config.json                        the exact AppearanceConfig
    checkpoint.npz                     state every ``checkpoint_every`` steps (a rerun resumes)

Shapes follow docs/rendering.md: textures are [H, W, 3] linear, row 0 = v 1 (OBJ convention).
"""

from __future__ import annotations

import csv
import io
import json
import time
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Sequence

import numpy as np

from ..camera import Camera
from ..capture import Capture, Template, frame_name, load_capture, save_png
from ..data.tracked import TrackedSequence
from ..errors import PhysavatarError
from ..files import load_npz, read_json, save_npz_atomic, write_json_atomic, write_text_atomic
from ..optim import Adam
from ..render import (
    Ambient,
    AreaLight,
    MeshSpec,
    PointLight,
    RenderResult,
    SceneSpec,
    SunLight,
    differentiable_scene,
    linear_to_srgb8,
    load_scene,
    make_sensor,
    mitsuba,
    render,
    srgb_to_linear,
)
from ..render.avatar import AvatarMeshes
from ..render.lights import light_center, load_lights, named_lights, save_lights

LOG_COLUMNS = ("iteration", "loss", "lr", "ambient_r", "ambient_g", "ambient_b", "key", "seconds")
LIGHT_MODES = ("ambient", "studio")


@dataclass(frozen=True)
class AppearanceConfig:
    """Everything that defines an appearance fit (saved as config.json).

    Attributes:
        light: ``"ambient"`` (the paper: texture + global ambient L_a) or ``"studio"`` (texture +
            ambient + the known key light's intensity).
        iterations: Adam steps (A.4: 2000). Not part of the resume check, so a run can be extended.
        lr, lr_decay, lr_decay_every: Adam learning rate, halved every 500 steps (A.4).
        spp: samples per pixel while fitting (A.4: 8); final_spp for the preview renders (128).
        texture_size: atlas resolution (square); the official code uses 2048² on a GPU.
        scale: image resolution factor w.r.t. the capture (CPU budget).
        batch: (frame, camera) views per step (A.4: 1).
        erode_px: foreground mask erosion in capture pixels (A.4: 2).
        max_depth: path depth (3 = direct + one bounce, as the synthetic captures are rendered).
        ambient_init: initial L_a (A.4: unit radiance).
        fit_light: optimize the light intensities (False: keep them at their initial values).
        light_lr: Adam learning rate of the light intensities (None: ``lr``).
        cameras: training camera names (None: all cameras of the capture).
        frame_stride: use every k-th frame (the paper uses 200 of ~2000 frames).
        init_frame_stride: every k-th frame for the initial per-face colours.
        checkpoint_every: steps between checkpoints (and log flushes).
        seed: (frame, camera) sampling and Monte Carlo seeds.
    """

    light: str = "ambient"
    iterations: int = 2000
    lr: float = 0.01
    lr_decay: float = 0.5
    lr_decay_every: int = 500
    spp: int = 8
    final_spp: int = 128
    texture_size: int = 512
    scale: float = 1.0
    batch: int = 1
    erode_px: int = 2
    max_depth: int = 3
    ambient_init: float = 1.0
    fit_light: bool = True
    light_lr: float | None = None
    cameras: tuple[str, ...] | None = None
    frame_stride: int = 1
    init_frame_stride: int = 1
    checkpoint_every: int = 50
    seed: int = 0

    def __post_init__(self) -> None:
        if self.light not in LIGHT_MODES:
            raise PhysavatarError(None, f"light model {self.light!r} is not one of {', '.join(LIGHT_MODES)}")
        checks = [("iterations", self.iterations >= 0), ("lr", self.lr > 0), ("spp", self.spp >= 1),
                  ("final_spp", self.final_spp >= 1), ("texture_size", 8 <= self.texture_size <= 8192),
                  ("scale", 0 < self.scale <= 1), ("batch", self.batch >= 1), ("erode_px", self.erode_px >= 0),
                  ("lr_decay_every", self.lr_decay_every >= 1), ("frame_stride", self.frame_stride >= 1),
                  ("init_frame_stride", self.init_frame_stride >= 1), ("checkpoint_every", self.checkpoint_every >= 1),
                  ("ambient_init", self.ambient_init > 0)]
        for name, ok in checks:
            if not ok:
                raise PhysavatarError(None, f"appearance config: {name}={getattr(self, name)!r} is out of range")
        if self.cameras is not None:
            object.__setattr__(self, "cameras", tuple(self.cameras))

    def to_dict(self) -> dict:
        d = asdict(self)
        d["cameras"] = list(self.cameras) if self.cameras is not None else None
        return d

    @staticmethod
    def from_dict(d: dict) -> "AppearanceConfig":
        names = {f.name for f in fields(AppearanceConfig)}
        return AppearanceConfig(**{k: (tuple(v) if k == "cameras" and v is not None else v)
                                   for k, v in d.items() if k in names})


# -- UV atlas and texture splatting --------------------------------------------------------------

def uv_atlas(vertices: np.ndarray, faces: np.ndarray, texture_size: int = 1024, padding: int = 2) -> np.ndarray:
    """Automatic UV atlas with xatlas, every chart counter-clockwise (not mirrored).

    xatlas's parametrization mirrors some charts (a texture painted on them would read
    backwards, and the sign of the UV area flips). Charts are therefore made once, the mirrored
    ones reflected, and the charts packed again from these UVs; rotations stay off in both
    packings because xatlas's chart rotation can mirror too.

    Args:
        vertices: [V, 3]; faces: [F, 3] counter-clockwise seen from outside.
        texture_size: the atlas is packed for this resolution, ``padding`` texels between charts
            so that bilinear lookups never blend two charts.
    Returns:
        [F, 3, 2] per-corner UVs in [0, 1] (OBJ convention, v up), faces in the input order.
    """
    import scipy.sparse as sp
    import xatlas
    from scipy.sparse.csgraph import connected_components

    def pack_options():
        pack = xatlas.PackOptions()
        pack.resolution = int(texture_size)
        pack.padding = int(padding)
        pack.bilinear = True
        pack.rotate_charts = False
        pack.rotate_charts_to_axis = False
        return pack

    faces = np.asarray(faces)
    atlas = xatlas.Atlas()
    atlas.add_mesh(np.ascontiguousarray(vertices, dtype=np.float32), np.ascontiguousarray(faces, dtype=np.uint32))
    atlas.generate(pack_options=pack_options())
    vmap, indices, uvs = atlas[0]
    if indices.shape != faces.shape or not np.array_equal(vmap[indices], faces):
        # xatlas keeps the face order; if a version ever reorders, the per-face data would not
        # line up with the template, so refuse rather than silently scramble colours.
        raise RuntimeError("xatlas changed the face order or topology of the mesh")
    area = _uv_signed_area(uvs[indices])
    F = len(faces)
    inc = sp.csr_matrix((np.ones(3 * F), (np.repeat(np.arange(F), 3), indices.ravel())), shape=(F, len(uvs)))
    _, chart = connected_components(inc @ inc.T, directed=False)
    chart_area = np.bincount(chart, weights=area)
    mirrored = np.zeros(len(uvs), bool)
    mirrored[indices[chart_area[chart] < 0].ravel()] = True
    if mirrored.any():
        uv2 = uvs.astype(np.float64).copy()
        uv2[mirrored, 0] = -uv2[mirrored, 0]
        repack = xatlas.Atlas()
        repack.add_uv_mesh(uv2.astype(np.float32), np.ascontiguousarray(indices, dtype=np.uint32))
        repack.generate(pack_options=pack_options())
        vmap2, indices2, uvs = repack[0]
        if not np.array_equal(vmap2[indices2], indices):
            raise RuntimeError("xatlas changed the face order while repacking")
        indices = indices2
    out = np.asarray(uvs, dtype=np.float64)[indices]
    if (_uv_signed_area(out) <= 0).any():
        raise RuntimeError("xatlas produced flipped UV triangles")
    return out


def _uv_signed_area(face_uvs: np.ndarray) -> np.ndarray:
    """[F] signed area of UV triangles (positive: counter-clockwise, v up)."""
    a, b, c = face_uvs[:, 0], face_uvs[:, 1], face_uvs[:, 2]
    return 0.5 * ((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1]))


def texel_face_map(face_uvs: np.ndarray, size: int) -> np.ndarray:
    """[size, size] int64: the face whose UV triangle contains each texel centre, -1 for none.

    Texel (row r, column c) has its centre at u = (c + ½)/size, v = 1 - (r + ½)/size (row 0 =
    v 1). Centres on a shared edge go to one of the two faces; where UV triangles overlap (an
    atlas that mirrors halves onto the same texels) the later face wins.
    """
    size = int(size)
    uv = np.asarray(face_uvs, np.float64)
    # texel coordinates: x = u·size - ½, y = (1 - v)·size - ½, so the centre of (r, c) is (c, r)
    x = uv[..., 0] * size - 0.5
    y = (1.0 - uv[..., 1]) * size - 0.5
    out = -np.ones((size, size), np.int64)
    x0 = np.clip(np.ceil(x.min(1)), 0, size - 1).astype(np.int64)
    x1 = np.clip(np.floor(x.max(1)), -1, size - 1).astype(np.int64)
    y0 = np.clip(np.ceil(y.min(1)), 0, size - 1).astype(np.int64)
    y1 = np.clip(np.floor(y.max(1)), -1, size - 1).astype(np.int64)
    for f in np.flatnonzero((x1 >= x0) & (y1 >= y0)):
        cx, cy = np.meshgrid(np.arange(x0[f], x1[f] + 1), np.arange(y0[f], y1[f] + 1))
        (ax, bx, qx), (ay, by, qy) = x[f], y[f]
        det = (bx - ax) * (qy - ay) - (qx - ax) * (by - ay)
        if det == 0:
            continue
        l1 = ((cx - ax) * (qy - ay) - (qx - ax) * (cy - ay)) / det
        l2 = ((bx - ax) * (cy - ay) - (cx - ax) * (by - ay)) / det
        inside = (l1 >= 0) & (l2 >= 0) & (l1 + l2 <= 1)
        out[cy[inside], cx[inside]] = f
    return out


def fill_empty(texture: np.ndarray, filled: np.ndarray) -> np.ndarray:
    """Copy to every texel where ``filled`` is False the value of the nearest filled texel
    (dilation to convergence), so bilinear lookups near chart borders stay on-chart."""
    from scipy.ndimage import distance_transform_edt

    if filled.all() or not filled.any():
        return texture.copy()
    _, (ri, ci) = distance_transform_edt(~filled, return_indices=True)
    return texture[ri, ci]


def splat_face_colors(face_uvs: np.ndarray, face_colors: np.ndarray, size: int,
                      valid: np.ndarray | None = None) -> np.ndarray:
    """Initial texture: each face's colour in that face's texels, empty texels dilated.

    Args:
        face_uvs: [F, 3, 2]; face_colors: [F, 3] linear RGB.
        valid: [F] bool, faces whose colour is known (the others are filled from neighbours).
    Returns:
        [size, size, 3] float32 linear texture.
    """
    fmap = texel_face_map(face_uvs, size)
    ok = fmap >= 0
    if valid is not None:
        ok &= np.asarray(valid, bool)[np.maximum(fmap, 0)]
    tex = np.zeros((size, size, 3), np.float32)
    tex[ok] = np.asarray(face_colors, np.float32)[fmap[ok]]
    return np.clip(fill_empty(tex, ok), 0.0, 1.0).astype(np.float32)


# -- inputs ----------------------------------------------------------------------------------------

@dataclass
class AppearanceData:
    """What the fit needs.

    Attributes:
        capture: the loaded capture (images, masks, cameras).
        template: faces [F, 3], labels [V], face_uvs [F, 3, 2] (xatlas-generated if the capture
            has none).
        vertices: [T, V, 3] mesh per used frame; frames: [T] capture frame ids.
        face_colors: [T, F, 3] linear per-face colours from tracking, or None (read from images).
        source: "tracked" or "gt".
    """

    capture: Capture
    template: Template
    vertices: np.ndarray
    frames: list[int]
    face_colors: np.ndarray | None
    source: str
    cameras: list[Camera] = field(default_factory=list)


def load_appearance_data(capture: str | Path | Capture, tracked: str | Path | None = None, meshes: str = "tracked",
                         texture_size: int = 512, cameras: Sequence[str] | None = None) -> AppearanceData:
    """Capture + mesh sequence: ``meshes="tracked"`` reads ``tracked/tracked.npz`` (vertices,
    face_colors, frames); ``"gt"`` reads ``ground_truth/meshes.npz`` (per-face colours then come
    from the tracked folder when given, else from the images)."""
    cap = capture if isinstance(capture, Capture) else load_capture(capture)
    t = cap.template
    colors = None
    tr = None
    if tracked is not None:
        tr = TrackedSequence.load(tracked, require=("vertices", "face_colors", "frames"))
        if tr.vertices.shape[1:] != t.vertices.shape or tr.face_colors.shape[1:] != (len(t.faces), 3):
            raise PhysavatarError(tr.path, "vertices/face_colors do not match the template")
    if meshes == "tracked":
        if tr is None:
            raise PhysavatarError(None, "meshes 'tracked' needs a tracked folder (--tracked DIR), or use --meshes gt")
        V, frames, colors = tr.vertices, [int(f) for f in tr.frames], tr.face_colors
    elif meshes == "gt":
        if cap.ground_truth is None:
            raise PhysavatarError(cap.root, "meshes 'gt' needs ground_truth/meshes.npz (synthetic captures only)")
        gt = load_npz(cap.ground_truth / "meshes.npz")
        V = gt["vertices"]
        if V.shape[1:] != t.vertices.shape or len(V) != len(cap.frames):
            raise PhysavatarError(cap.ground_truth / "meshes.npz", f"vertices {V.shape} do not match the template "
                                  f"({len(t.vertices)} vertices) and {len(cap.frames)} frames")
        frames = list(cap.frames)
        if tr is not None:  # tracked Gaussian colours for the frames the tracker covered
            tf = [int(f) for f in tr.frames]
            keep = [frames.index(f) for f in tf]
            V, frames, colors = V[keep], tf, tr.face_colors
    else:
        raise PhysavatarError(None, f"meshes must be 'tracked' or 'gt', got {meshes!r}")
    if not np.isfinite(V).all():
        raise PhysavatarError(None, "mesh sequence contains non-finite vertices")
    if t.face_uvs is None:
        t = replace(t, face_uvs=uv_atlas(t.vertices, t.faces, texture_size))
    cams = list(cap.cameras)
    if cameras is not None:
        names = {c.name for c in cams}
        bad = [c for c in cameras if c not in names]
        if bad:
            raise PhysavatarError(cap.root / "cameras.json", f"unknown cameras {bad}")
        cams = [c for c in cams if c.name in set(cameras)]
    return AppearanceData(cap, t, np.asarray(V, np.float64), frames,
                          None if colors is None else np.asarray(colors, np.float64),
                          meshes, cams)


def _resize(a: np.ndarray, w: int, h: int) -> np.ndarray:
    """Area-average resize of a float [H, W] or [H, W, C] image (PIL's box filter)."""
    from PIL import Image

    if a.shape[1] == w and a.shape[0] == h:
        return a.astype(np.float32)
    chans = a[..., None] if a.ndim == 2 else a
    out = np.stack([np.asarray(Image.fromarray(np.ascontiguousarray(chans[..., c], np.float32))
                               .resize((w, h), Image.BOX)) for c in range(chans.shape[2])], -1)
    return out[..., 0] if a.ndim == 2 else out


def load_target(capture: Capture, cam: Camera, frame: int, scale: float, erode_px: int) -> tuple[np.ndarray, np.ndarray]:
    """Linear target image [h, w, 3] and loss mask [h, w] (bool) at ``scale``.

    The mask is the foreground (alpha > 0.5) eroded by ``erode_px`` capture pixels (A.4: the
    silhouette's pixels mix foreground and background), then kept only where a downsampled pixel
    lies wholly inside it.
    """
    from scipy.ndimage import binary_erosion

    img = srgb_to_linear(capture.image(cam.name, frame)).astype(np.float32)
    m = capture.mask(cam.name, frame) > 0.5
    if erode_px > 0:
        m = binary_erosion(m, structure=np.ones((3, 3), bool), iterations=erode_px)
    small = cam.scaled(scale)
    w, h = small.width, small.height
    return _resize(img, w, h), _resize(m.astype(np.float32), w, h) > 0.999


# -- scenes ----------------------------------------------------------------------------------------

def initial_lights(cfg: AppearanceConfig, capture: Capture, lighting: str | Path | None = None) -> list:
    """The lights the fit starts from: ``Ambient(ambient_init)`` (the paper, A.4.1), or for
    ``studio`` the known studio lights (``lighting`` or ``ground_truth/lighting.json``)."""
    if cfg.light == "ambient":
        return [Ambient((cfg.ambient_init,) * 3)]
    path = Path(lighting) if lighting is not None else (capture.root / "ground_truth" / "lighting.json")
    if not path.is_file():
        raise PhysavatarError(path, "light model 'studio' needs the studio's lights (a lighting.json; pass --lighting)")
    lights = load_lights(path)
    if sum(isinstance(l, Ambient) for l in lights) == 0:
        lights = [Ambient((cfg.ambient_init,) * 3)] + lights
    return lights


# -- per-face colours from images (when no tracked Gaussian colours exist) -------------------------

def face_id_buffer(vertices: np.ndarray, faces: np.ndarray, camera: Camera) -> np.ndarray:
    """[H, W] int64 index of the face seen through each pixel centre (-1: background), by
    tracing the camera's pixel rays against the mesh with Mitsuba."""
    mi = mitsuba()
    scene = load_scene(SceneSpec(meshes=[MeshSpec("m", vertices, faces, smooth=False)]))
    o, d = camera.pixel_rays()
    d = d.reshape(-1, 3).astype(np.float32)
    ray = mi.Ray3f(mi.Point3f(*[np.full(len(d), float(x), np.float32) for x in o]), mi.Vector3f(d[:, 0], d[:, 1], d[:, 2]))
    si = scene.ray_intersect(ray)
    ids = np.array(si.prim_index, dtype=np.int64)
    ids[~np.array(si.is_valid())] = -1
    return ids.reshape(camera.height, camera.width)


def image_face_colors(data: AppearanceData, frame_stride: int = 1, erode_px: int = 2,
                      progress=None) -> tuple[np.ndarray, np.ndarray]:
    """Per-face colour from the images: the mean linear colour of the (eroded-mask) pixels whose
    centre sees the face, over every used camera and every ``frame_stride``-th frame.

    Returns:
        colors [F, 3] linear (0 where unseen), pixels [F] count of pixels that saw each face.
    """
    from scipy.ndimage import binary_erosion

    F = len(data.template.faces)
    acc = np.zeros((F, 3))
    cnt = np.zeros(F)
    for ti in range(0, len(data.frames), frame_stride):
        f = data.frames[ti]
        for cam in data.cameras:
            ids = face_id_buffer(data.vertices[ti], data.template.faces, cam)
            m = data.capture.mask(cam.name, f) > 0.5
            if erode_px > 0:
                m = binary_erosion(m, structure=np.ones((3, 3), bool), iterations=erode_px)
            sel = m & (ids >= 0)
            img = srgb_to_linear(data.capture.image(cam.name, f))
            np.add.at(acc, ids[sel], img[sel])
            cnt += np.bincount(ids[sel], minlength=F)
            if progress is not None:
                progress()
    colors = np.where(cnt[:, None] > 0, acc / np.maximum(cnt, 1)[:, None], 0.0)
    return colors, cnt


# -- the fit ---------------------------------------------------------------------------------------

VISIBILITY_FRAMES = 8  # frames over which face visibility is counted when tracked colours exist


class InverseRenderer:
    """One differentiable Mitsuba scene of the avatar whose vertex positions are swapped per
    frame; renders the shared texture and lights and returns loss and gradients.

    The body and the garment are separate meshes (one- and two-sided) sampling one atlas; the
    same Dr.Jit texture tensor is assigned to both bitmaps, so its gradient sums both.
    """

    def __init__(self, meshes: AvatarMeshes, rest_vertices: np.ndarray, texture: np.ndarray, lights: list,
                 max_depth: int = 3):
        self.mi = mitsuba()
        self.meshes = meshes
        self.lights = list(lights)
        spec = SceneSpec(meshes=meshes.specs(rest_vertices, texture), lights=self.lights, max_depth=max_depth)
        self.scene, self.params, self.keys = differentiable_scene(spec)
        self.ambient_key = self.keys.ambient
        area = [l.name for l in self.lights if isinstance(l, (AreaLight, PointLight, SunLight))]
        self.key_name = area[0] if area else None
        self.key_key = self.keys.emitters[self.key_name] if self.key_name else None
        self._frame_vertices_id = None
        self._sensors: dict = {}

    def set_vertices(self, vertices: np.ndarray, tag=None) -> None:
        """Move every mesh to template-vertex positions ``vertices`` [V, 3] (BVH and normals are
        rebuilt by ``params.update``); ``tag`` skips the upload when the frame is unchanged."""
        if tag is not None and tag == self._frame_vertices_id:
            return
        for n in self.meshes.names:
            v = vertices[self.meshes.vertex_maps[n]].astype(np.float32).ravel()
            self.params[f"{n}.vertex_positions"] = self.mi.Float(v)
        self.params.update()
        self._frame_vertices_id = tag

    def sensor(self, cam: Camera, spp: int):
        key = (cam.name, cam.width, spp)
        if key not in self._sensors:
            self._sensors[key] = make_sensor(cam, spp)
        return self._sensors[key]

    def _assign(self, texture: np.ndarray, ambient: np.ndarray | None, key: np.ndarray | None, grad: bool):
        import drjit as dr

        mi = self.mi
        T = mi.TensorXf(np.ascontiguousarray(texture, np.float32))
        if grad:
            dr.enable_grad(T)
        for n in self.meshes.names:
            self.params[self.keys.reflectance[n]] = T
        A = K = None
        if ambient is not None and self.ambient_key is not None:
            A = mi.Color3f(*[float(x) for x in ambient])
            if grad:
                dr.enable_grad(A)
            self.params[self.ambient_key] = A
        if key is not None and self.key_key is not None:
            K = mi.Color3f(*[float(x) for x in key])
            if grad:
                dr.enable_grad(K)
            self.params[self.key_key] = K
        self.params.update()
        return T, A, K

    def render(self, cam: Camera, texture, ambient=None, key=None, *, spp: int = 8, seed: int = 0) -> RenderResult:
        """Forward render [h, w] (no gradients)."""
        self._assign(texture, ambient, key, grad=False)
        img = np.array(self.mi.render(self.scene, self.params, sensor=self.sensor(cam, spp), spp=spp, seed=seed),
                       dtype=np.float32)
        return RenderResult(rgb=img[..., :3], alpha=img[..., 3])

    def loss_and_grads(self, cam: Camera, target: np.ndarray, mask: np.ndarray, texture, ambient=None, key=None,
                       *, spp: int = 8, seed: int = 0):
        """Masked mean squared error (linear RGB, Eq. 8) and its gradients w.r.t. the texture
        [Ht, Wt, 3], the ambient RGB and the key light RGB (None when not in the scene)."""
        import drjit as dr

        mi = self.mi
        T, A, K = self._assign(texture, ambient, key, grad=True)
        img = mi.render(self.scene, self.params, sensor=self.sensor(cam, spp), spp=spp, seed=seed)
        w = mask.astype(np.float32)[..., None] / (3.0 * max(float(mask.sum()), 1.0))
        diff = img[..., :3] - mi.TensorXf(np.ascontiguousarray(target, np.float32))
        loss = dr.sum(dr.square(diff) * mi.TensorXf(np.ascontiguousarray(np.repeat(w, 3, -1))), axis=None)
        dr.backward(loss)
        gT = np.array(dr.grad(T), np.float64)
        gA = np.array(dr.grad(A), np.float64).reshape(3) if A is not None else None
        gK = np.array(dr.grad(K), np.float64).reshape(3) if K is not None else None
        return float(np.array(loss).ravel()[0]), gT, gA, gK


def _light_values(lights: list) -> tuple[np.ndarray | None, np.ndarray | None]:
    amb = next((np.broadcast_to(np.asarray(l.radiance, float), (3,)).copy() for l in lights if isinstance(l, Ambient)),
               None)
    key = None
    for l in lights:
        if isinstance(l, AreaLight):
            key = np.broadcast_to(np.asarray(l.radiance, float), (3,)).copy()
        elif isinstance(l, PointLight):
            key = np.broadcast_to(np.asarray(l.intensity, float), (3,)).copy()
        elif isinstance(l, SunLight):
            key = np.broadcast_to(np.asarray(l.irradiance, float), (3,)).copy()
        if key is not None:
            break
    return amb, key


def _with_light_values(lights: list, ambient, key) -> list:
    out, key_done = [], False
    for l in lights:
        if isinstance(l, Ambient) and ambient is not None:
            l = replace(l, radiance=tuple(float(x) for x in ambient))
        elif not key_done and key is not None and isinstance(l, (AreaLight, PointLight, SunLight)):
            attr = {AreaLight: "radiance", PointLight: "intensity", SunLight: "irradiance"}[type(l)]
            l = replace(l, **{attr: tuple(float(x) for x in key)})
            key_done = True
        out.append(l)
    return out


def exposure_scale(renderer: InverseRenderer, data: AppearanceData, texture, ambient, key, cfg: AppearanceConfig,
                   n_views: int = 4) -> float:
    """Least-squares factor s minimising Σ‖I − s·R‖² over a few training views (R rendered with
    ``texture`` and the lights). Image radiance is linear in the texture, so s·texture (or
    s·lights) is the best global rescaling of the current state."""
    rng = np.random.default_rng(cfg.seed + 7)
    num = den = 0.0
    for j in range(n_views):
        ti = int(rng.integers(len(data.frames)))
        cam = data.cameras[int(rng.integers(len(data.cameras)))]
        target, mask = load_target(data.capture, cam, data.frames[ti], cfg.scale, cfg.erode_px)
        renderer.set_vertices(data.vertices[ti], tag=ti)
        r = renderer.render(cam.scaled(cfg.scale), texture, ambient, key, spp=cfg.spp, seed=10_000 + j).rgb
        num += float((target[mask] * r[mask]).sum())
        den += float((r[mask] ** 2).sum())
    return num / den if den > 0 else 1.0


@dataclass
class AppearanceResult:
    """Fit outputs (also written to ``out``): texture [H, W, 3] linear, the initial texture,
    fitted lights, per-iteration log rows, the atlas face_uvs [F, 3, 2]."""

    out: Path
    texture: np.ndarray
    texture_init: np.ndarray
    lights: list
    log: list
    face_uvs: np.ndarray
    face_pixels: np.ndarray
    seconds_per_iteration: float


def _lr(cfg: AppearanceConfig, it: int, base: float) -> float:
    return base * cfg.lr_decay ** (it // cfg.lr_decay_every)


def _views(cfg: AppearanceConfig, it: int, n_frames: int, n_cams: int) -> list[tuple[int, int]]:
    """The (frame index, camera index) pairs of step ``it`` (A.4.3: random per step); seeded by
    (seed, it) so that the sequence does not depend on where a run was resumed."""
    rng = np.random.default_rng([cfg.seed, it])
    return [(int(rng.integers(n_frames)) , int(rng.integers(n_cams))) for _ in range(cfg.batch)]


def _resume_key(cfg: AppearanceConfig) -> dict:
    d = cfg.to_dict()
    d.pop("iterations")
    d.pop("checkpoint_every")
    d.pop("final_spp")
    return d


def fit_appearance(capture: str | Path | Capture, out: str | Path, config: AppearanceConfig = AppearanceConfig(), *,
                   tracked: str | Path | None = None, meshes: str = "tracked", lighting: str | Path | None = None,
                   progress: bool = True, data: AppearanceData | None = None) -> AppearanceResult:
    """Fit the texture and lights (module doc) and write everything into ``out``.

    Args:
        capture: capture folder. tracked: tracking output folder (``tracked.npz``).
        meshes: ``"tracked"`` or ``"gt"`` (ground-truth meshes of a synthetic capture).
        lighting: lights file for ``light="studio"`` (default ``ground_truth/lighting.json``).
        data: preloaded :class:`AppearanceData` (tests, benchmarks) instead of the three above.
    """
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    cfg = config
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if data is None:
        data = load_appearance_data(capture, tracked, meshes, cfg.texture_size, cfg.cameras)
    t = data.template
    frames_idx = list(range(0, len(data.frames), cfg.frame_stride))
    write_json_atomic(out / "config.json", {**cfg.to_dict(), "meshes": data.source,
                                            "tracked": None if tracked is None else str(tracked),
                                            "capture": str(data.capture.root)})

    cols = (TextColumn("[bold]appearance[/] {task.description}"), BarColumn(), MofNCompleteColumn(),
            TimeElapsedColumn(), TimeRemainingColumn())
    with Progress(*cols, disable=not progress, transient=False) as bar:
        # 1-2. atlas and initial texture T_0 from per-face colours averaged over frames
        atlas_path = out / "atlas.npz"
        init_key = json.dumps({"texture_size": cfg.texture_size, "init_frame_stride": cfg.init_frame_stride,
                               "erode_px": cfg.erode_px, "meshes": data.source, "frames": data.frames,
                               "cameras": [c.name for c in data.cameras],
                               "tracked_colors": data.face_colors is not None})
        a = load_npz(atlas_path) if atlas_path.is_file() else {}
        if str(a.get("init_key", "")) == init_key and (out / "texture_init_linear.npy").is_file():
            face_uvs, face_colors, face_pixels = a["face_uvs"], a["face_colors"], a["face_pixels"]
            tex0 = np.load(out / "texture_init_linear.npy")
        else:
            face_uvs = t.face_uvs
            used = range(0, len(data.frames), cfg.init_frame_stride)
            # With tracked colours the image pass only counts which faces the training pixels
            # see (``face_pixels``): a few frames spread over the sequence suffice for that.
            stride = cfg.init_frame_stride if data.face_colors is None else \
                max(cfg.init_frame_stride, len(data.frames) // VISIBILITY_FRAMES)
            task = bar.add_task("per-face colours" if data.face_colors is None else "face visibility",
                                total=len(range(0, len(data.frames), stride)) * len(data.cameras))
            img_colors, face_pixels = image_face_colors(data, stride, cfg.erode_px,
                                                        progress=lambda: bar.advance(task))
            if data.face_colors is not None:
                # the paper: mean over t of the tracked Gaussian colours (Sec. 3.3)
                face_colors = data.face_colors[list(used)].mean(0)
                seen = np.ones(len(t.faces), bool)
            else:
                face_colors, seen = img_colors, face_pixels > 0
            tex0 = splat_face_colors(face_uvs, face_colors, cfg.texture_size, seen)
            np.save(out / ".texture_init_linear.tmp.npy", tex0)
            (out / ".texture_init_linear.tmp.npy").replace(out / "texture_init_linear.npy")
            save_npz_atomic(atlas_path, face_uvs=face_uvs, face_colors=face_colors, face_pixels=face_pixels,
                            init_key=np.array(init_key))

        meshes_ = AvatarMeshes.build(t.vertices, t.faces, face_uvs, t.labels)
        lights0 = initial_lights(cfg, data.capture, lighting)
        renderer = InverseRenderer(meshes_, data.vertices[0], tex0, lights0, cfg.max_depth)
        amb0, key0 = _light_values(lights0)
        if renderer.key_key is None:
            key0 = None

        # 3. inverse rendering, resumable
        ckpt = out / "checkpoint.npz"
        state = {"texture": tex0.astype(np.float64)}
        if amb0 is not None:
            state["ambient"] = amb0
        if key0 is not None:
            state["key"] = key0
        fitted_keys = ["texture"] + ([k for k in ("ambient", "key") if k in state] if cfg.fit_light else [])
        adam = Adam({k: state[k].shape for k in fitted_keys})
        log: list[dict] = []
        start = 0
        exposure = None
        if ckpt.is_file():
            z = load_npz(ckpt)
            if json.loads(str(z["resume_key"])) == _resume_key(cfg):
                for k in state:
                    state[k] = z[k]
                adam.load_state_dict(z)
                start = int(z["iteration"])
                log = _read_log(out / "fit_log.csv")[:start]
                exposure = float(z["exposure"])
        if exposure is None:
            if cfg.light == "studio":
                # Known lights: T_0 holds shaded radiance, so bring it to the right overall level
                # (one global factor) before Adam's small steps have to climb there.
                exposure = exposure_scale(renderer, data, tex0, state.get("ambient"), state.get("key"), cfg)
                state["texture"] = np.clip(tex0 * exposure, 0.0, 1.0)
            else:
                exposure = 1.0  # the paper: T_0 as is, L_a = 1
        lr_of = {"texture": cfg.lr, "ambient": cfg.light_lr or cfg.lr, "key": cfg.light_lr or cfg.lr}

        task = bar.add_task(f"inverse rendering ({cfg.light})", total=cfg.iterations)
        bar.advance(task, min(start, cfg.iterations))
        for it in range(start, cfg.iterations):
            t0 = time.time()
            grads = {k: np.zeros_like(state[k]) for k in fitted_keys}
            loss = 0.0
            for j, (ti, ci) in enumerate(_views(cfg, it, len(frames_idx), len(data.cameras))):
                fi = frames_idx[ti]
                cam = data.cameras[ci]
                target, mask = load_target(data.capture, cam, data.frames[fi], cfg.scale, cfg.erode_px)
                renderer.set_vertices(data.vertices[fi], tag=fi)
                l, gT, gA, gK = renderer.loss_and_grads(cam.scaled(cfg.scale), target, mask, state["texture"],
                                                        state.get("ambient"), state.get("key"), spp=cfg.spp,
                                                        seed=it * cfg.batch + j)
                loss += l / cfg.batch
                grads["texture"] += gT / cfg.batch
                if "ambient" in grads and gA is not None:
                    grads["ambient"] += gA / cfg.batch
                if "key" in grads and gK is not None:
                    grads["key"] += gK / cfg.batch
            adam.step(state, grads, {k: _lr(cfg, it, lr_of[k]) for k in fitted_keys})
            state["texture"] = np.clip(state["texture"], 0.0, 1.0)  # A.4.3: legal colours
            for k in ("ambient", "key"):
                if k in state:
                    state[k] = np.maximum(state[k], 0.0)
            amb = state.get("ambient", np.full(3, np.nan))
            log.append({"iteration": it, "loss": loss, "lr": _lr(cfg, it, cfg.lr), "ambient_r": amb[0],
                        "ambient_g": amb[1], "ambient_b": amb[2],
                        "key": float(np.mean(state["key"])) if "key" in state else float("nan"),
                        "seconds": time.time() - t0})
            bar.advance(task)
            if (it + 1) % cfg.checkpoint_every == 0 or it + 1 == cfg.iterations:
                save_npz_atomic(ckpt, iteration=np.int64(it + 1), resume_key=np.array(json.dumps(_resume_key(cfg))),
                                exposure=np.float64(exposure), **state, **adam.state_dict())
                _write_log(out / "fit_log.csv", log)
        # per-iteration time from the log, so that a resumed run reports the same figure
        sec_it = float(np.mean([r["seconds"] for r in log])) if log else float("nan")

        texture = state["texture"].astype(np.float32)
        lights = _with_light_values(lights0, state.get("ambient"), state.get("key"))
        np.save(out / ".texture_linear.tmp.npy", texture)
        (out / ".texture_linear.tmp.npy").replace(out / "texture_linear.npy")
        save_png(out / "texture.png", linear_to_srgb8(texture))
        save_lights(out / "light.json", lights, {"model": cfg.light, "exposure_init": exposure,
                                                 "note": "fitted lights; radiance in linear RGB"})
        _write_log(out / "fit_log.csv", log)
        plot_loss(log, out / "loss.png")

        # final renders at final_spp: target | fit, a few training views of the first frame
        task = bar.add_task("preview", total=min(4, len(data.cameras)))
        tiles, labels = [], []
        renderer.set_vertices(data.vertices[0], tag=0)
        for cam in data.cameras[:4]:
            target, _ = load_target(data.capture, cam, data.frames[0], 1.0, 0)
            r = renderer.render(cam, texture, state.get("ambient"), state.get("key"), spp=cfg.final_spp, seed=1)
            tiles += [linear_to_srgb8(target), r.srgb8()]
            labels += [f"{cam.name} image", f"{cam.name} fit"]
            bar.advance(task)
        from ..render import contact_sheet

        save_png(out / "preview.png", contact_sheet(tiles, labels))
    return AppearanceResult(out, texture, tex0, lights, log, face_uvs, face_pixels, sec_it)


def _write_log(path: Path, rows: list[dict]) -> None:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=LOG_COLUMNS)
    w.writeheader()
    for r in rows:
        w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    write_text_atomic(path, buf.getvalue())


def _read_log(path: Path) -> list[dict]:
    if not path.is_file():
        return []
    with open(path) as f:
        return [{k: (int(v) if k == "iteration" else float(v)) for k, v in r.items()} for r in csv.DictReader(f)]


def plot_loss(log: list[dict], path: Path) -> None:
    """Loss per iteration (and its running mean: single random views are noisy) as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..files import atomic_path

    if not log:
        return
    it = np.array([r["iteration"] for r in log])
    loss = np.array([r["loss"] for r in log])
    k = max(1, min(100, len(loss) // 10))  # views differ ~10x in loss: average many
    smooth = np.convolve(loss, np.ones(k) / k, mode="valid")
    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=100)
    ax.semilogy(it, loss, lw=0.5, alpha=0.4, label="loss (one random view)")
    ax.semilogy(it[k - 1:], smooth, lw=1.5, label=f"running mean ({k})")
    ax.set_xlabel("iteration")
    ax.set_ylabel("masked MSE (linear RGB)")
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


# -- relighting ------------------------------------------------------------------------------------

def relight(mesh_vertices: np.ndarray, faces: np.ndarray, face_uvs: np.ndarray, texture: np.ndarray, camera: Camera,
            light, *, labels: np.ndarray | None = None, spp: int = 128, seed: int = 0, max_depth: int = 3) -> RenderResult:
    """Render a textured avatar under new light.

    Args:
        mesh_vertices: [V, 3] one frame (tracked, simulated or ground truth).
        faces: [F, 3]; face_uvs: [F, 3, 2] the atlas of ``texture``; texture: [H, W, 3] linear albedo.
        camera: OpenCV camera.
        light: a light of ``physavatar.render``, a list of them, or a name of
            :func:`physavatar.render.lights.named_lights` (aimed at :func:`~physavatar.render.lights.light_center`).
        labels: [V] 0 body / >0 garment, to render the body one-sided and garments two-sided
            like the capture (None: one two-sided mesh).
    Returns:
        ``RenderResult`` (rgb linear with black background, alpha).
    """
    V = np.asarray(mesh_vertices, np.float64)
    if isinstance(light, str):
        light = named_lights(light, light_center(V))
    lights = list(light) if isinstance(light, (list, tuple)) else [light]
    m = AvatarMeshes.build(V, np.asarray(faces), np.asarray(face_uvs, np.float64), labels)
    spec = SceneSpec(meshes=m.specs(V, np.asarray(texture, np.float32)), lights=lights, max_depth=max_depth)
    return render(spec, camera, spp=spp, seed=seed)


@dataclass
class FittedAppearance:
    """A fit's output folder loaded: texture [H, W, 3] linear, face_uvs [F, 3, 2], lights."""

    texture: np.ndarray
    texture_init: np.ndarray | None
    face_uvs: np.ndarray
    lights: list

    @staticmethod
    def load(folder: str | Path) -> "FittedAppearance":
        folder = Path(folder)
        p = folder / "texture_linear.npy"
        if not p.is_file():
            raise PhysavatarError(p, "file not found (is this a fit-appearance output folder?)")
        init = folder / "texture_init_linear.npy"
        return FittedAppearance(np.load(p), np.load(init) if init.is_file() else None,
                                load_npz(folder / "atlas.npz")["face_uvs"], load_lights(folder / "light.json"))


# -- evaluation (benchmarks, tests) ----------------------------------------------------------------

def texture_psnr(texture: np.ndarray, gt: np.ndarray, covered: np.ndarray, align_scale: bool = False) -> float:
    """PSNR [dB] of a linear texture against the ground-truth one over ``covered`` texels
    (a [Hg, Wg] bool mask at the ground truth's resolution; ``texture`` is bilinearly resampled
    there). ``align_scale`` first applies the per-channel least-squares gain: texture and light
    are only determined up to a common factor (T·L is what the images see)."""
    from ..metrics import psnr

    tex = np.asarray(texture, np.float32)
    if tex.shape[:2] != gt.shape[:2]:
        from PIL import Image

        tex = np.stack([np.asarray(Image.fromarray(np.ascontiguousarray(tex[..., c], np.float32))
                                   .resize((gt.shape[1], gt.shape[0]), Image.BILINEAR)) for c in range(3)], -1)
    if align_scale:
        a, b = tex[covered].astype(np.float64), gt[covered].astype(np.float64)
        tex = tex * ((a * b).sum(0) / np.maximum((a * a).sum(0), 1e-12))
    return psnr(np.clip(tex, 0, 1), gt, mask=covered)


def baked_shading(texture: np.ndarray, gt: np.ndarray, face_uvs: np.ndarray, seen_faces: np.ndarray,
                  min_texels: int = 8) -> float:
    """How much shading is baked into ``texture``: the standard deviation over faces of
    log(mean texture / mean true albedo) of each face's texels (grey level, faces some
    training pixel saw, at the ground truth's resolution). A pure albedo, at any global scale,
    gives 0; shadows and light fall-off baked into the texture make it grow."""
    size = gt.shape[0]
    tex = np.asarray(texture, np.float32)
    if tex.shape[:2] != gt.shape[:2]:
        from PIL import Image

        tex = np.stack([np.asarray(Image.fromarray(np.ascontiguousarray(tex[..., c], np.float32))
                                   .resize((gt.shape[1], gt.shape[0]), Image.BILINEAR)) for c in range(3)], -1)
    fmap = texel_face_map(face_uvs, size)
    ok = fmap >= 0
    F = len(face_uvs)
    n = np.bincount(fmap[ok], minlength=F)
    a = np.bincount(fmap[ok], weights=tex[ok].mean(-1), minlength=F)
    b = np.bincount(fmap[ok], weights=gt[ok].mean(-1), minlength=F)
    use = (n >= min_texels) & np.asarray(seen_faces, bool) & (a > 0) & (b > 0)
    return float(np.std(np.log(a[use] / b[use])))


def covered_texels(face_uvs: np.ndarray, size: int, seen_faces: np.ndarray | None = None) -> np.ndarray:
    """[size, size] bool: texels inside a UV triangle (of a face that was seen, when given)."""
    fmap = texel_face_map(face_uvs, size)
    ok = fmap >= 0
    if seen_faces is not None:
        ok &= np.asarray(seen_faces, bool)[np.maximum(fmap, 0)]
    return ok


def heldout_metrics(capture: Capture, face_uvs: np.ndarray, texture: np.ndarray, lights: list, *,
                    frames: Sequence[int] | None = None, spp: int = 128, seed: int = 0) -> dict:
    """PSNR and SSIM of renders of the held-out motion (``ground_truth/heldout``: meshes,
    cameras, images, masks) against its images, both in sRGB.

    PSNR over the foreground mask (alpha > 0.5); SSIM on the mask's bounding box (+5 px) with
    pixels outside the mask set to black in both (so the empty background does not inflate it).
    Returns {"psnr", "ssim", "per_view": [...]} averaged over views.
    """
    from ..metrics import psnr, ssim
    from ..render import read_png

    root = capture.root / "ground_truth" / "heldout"
    gt = load_npz(root / "meshes.npz")
    cams = [Camera.from_dict(d) for d in read_json(root / "cameras.json")]
    V = gt["vertices"]
    frames = list(range(len(V))) if frames is None else list(frames)
    t = capture.template
    m = AvatarMeshes.build(t.vertices, t.faces, face_uvs, t.labels)
    rows = []
    for f in frames:
        scene = load_scene(SceneSpec(meshes=m.specs(V[f], texture), lights=lights))
        for i, cam in enumerate(cams):
            res = render(scene, cam, spp=spp, seed=seed + 31 * f + i)
            pred = res.srgb8().astype(np.float64) / 255.0
            img = read_png(root / "images" / cam.name / f"{frame_name(f)}.png")[..., :3].astype(np.float64) / 255.0
            mask = read_png(root / "masks" / cam.name / f"{frame_name(f)}.png") > 127
            p = psnr(pred, img, mask=mask)
            ys, xs = np.nonzero(mask)
            y0, y1 = max(ys.min() - 5, 0), min(ys.max() + 6, mask.shape[0])
            x0, x1 = max(xs.min() - 5, 0), min(xs.max() + 6, mask.shape[1])
            mk = mask[y0:y1, x0:x1, None]
            s = ssim(pred[y0:y1, x0:x1] * mk, img[y0:y1, x0:x1] * mk)
            rows.append({"frame": f, "camera": cam.name, "psnr": p, "ssim": s})
    return {"psnr": float(np.mean([r["psnr"] for r in rows])), "ssim": float(np.mean([r["ssim"] for r in rows])),
            "per_view": rows}


def best_ambient(capture: Capture, face_uvs: np.ndarray, texture: np.ndarray, vertices: np.ndarray,
                 frames: Sequence[int], cameras: Sequence[Camera], *, scale: float = 0.5, spp: int = 16,
                 erode_px: int = 2) -> np.ndarray:
    """Per-channel ambient radiance that best reproduces training images with ``texture`` alone
    (closed form: the image is linear in L_a). Used to render the initial texture T_0 for the
    "w/o appearance" ablation at its best exposure."""
    t = capture.template
    m = AvatarMeshes.build(t.vertices, t.faces, face_uvs, t.labels)
    num = np.zeros(3)
    den = np.zeros(3)
    for ti, f in enumerate(frames):
        scene = load_scene(SceneSpec(meshes=m.specs(vertices[ti], texture), lights=[Ambient(1.0)]))
        for cam in cameras:
            target, mask = load_target(capture, cam, f, scale, erode_px)
            r = render(scene, cam.scaled(scale), spp=spp, seed=ti).rgb
            num += (target[mask] * r[mask]).sum(0)
            den += (r[mask] ** 2).sum(0)
    return num / np.maximum(den, 1e-12)
