"""The initial texture T_0, one of two ways (``AppearanceConfig.init``):

- ``"project"`` (default): every texel looked up in the training views that see its surface point,
  the lights' shading divided out in closed form, unseen texels inpainted along the surface
  (:mod:`.project`);
- ``"faces"`` (the paper's initialization, Sec. 3.3): per-face colours averaged over frames,
  splatted into the atlas. The colours are the tracking stage's Gaussian colours, or, without
  them, each face's mean colour over the image pixels that see it (a face-id buffer traced per
  camera and frame).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ...camera import Camera
from ...files import load_npz, save_npz_atomic
from ...progress import resolve
from ...render import MeshSpec, SceneSpec, load_scene, mitsuba, srgb_to_linear
from .config import AppearanceConfig
from .data import AppearanceData, load_target
from .project import Occlusion, Projection, TexelPoints, solve_texture
from .texture import fill_empty, splat_face_colors

VISIBILITY_FRAMES = 8  # frames over which face visibility is counted when tracked colours exist


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
                      advance=None) -> tuple[np.ndarray, np.ndarray]:
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
            if advance is not None:
                advance()
    colors = np.where(cnt[:, None] > 0, acc / np.maximum(cnt, 1)[:, None], 0.0)
    return colors, cnt


def projection_views(n_frames: int, n_cams: int, max_views: int) -> list[int]:
    """The frame indices of the projection: evenly spread, at most ``max_views // n_cams`` (≥ 1)."""
    n = max(1, min(n_frames, max_views // max(n_cams, 1)))
    return sorted({int(round(x)) for x in np.linspace(0, n_frames - 1, n)})


def twosided_faces(template) -> np.ndarray:
    """[F] bool: faces rendered two-sided (garments; everything when the template has one label),
    as :class:`~physavatar.render.avatar.AvatarMeshes` renders them."""
    lab = np.zeros(len(template.vertices), int) if template.labels is None else np.asarray(template.labels)
    garment = lab > 0
    if not garment.any() or garment.all():
        return np.ones(len(template.faces), bool)
    return garment[template.faces].all(1)


def projected_texture(data: AppearanceData, cfg: AppearanceConfig, renderer, ambient, key,
                      advance=None) -> tuple[np.ndarray, np.ndarray]:
    """T_0 by projection (:mod:`.project`): for each used (frame, camera), the image and the
    white-texture render under the lights ``ambient`` / ``key`` (``renderer``: the fit's
    :class:`~.scene.InverseRenderer`), accumulated per texel; then solved and inpainted.

    Returns:
        T_0 [size, size, 3] float32 linear albedo; face_views [F]: texel observations per face.
    """
    t = data.template
    pts = TexelPoints.of(t.face_uvs, cfg.texture_size)
    proj = Projection.empty(pts)
    white = np.ones((cfg.texture_size, cfg.texture_size, 3), np.float32)
    two = twosided_faces(t)
    views = []  # (frame index, camera, image, allowed pixels, irradiance), kept for the later passes
    for ti in projection_views(len(data.frames), len(data.cameras), cfg.project_views):
        V = data.vertices[ti]
        renderer.set_vertices(V, tag=ti)
        occ = Occlusion(V, t.faces)
        for ci, cam in enumerate(data.cameras):
            image, mask = load_target(data.capture, cam, data.frames[ti], 1.0, cfg.erode_px)
            E = renderer.render(cam, white, ambient, key, spp=cfg.project_spp, seed=1000 + 97 * ti + ci)
            allowed = mask & (E.alpha > 0.99)
            proj.add_view(cam, V, t.faces, image, allowed, E.rgb, occlusion=occ, twosided=two)
            if cfg.project_passes > 1:
                views.append((ti, cam, image, allowed, E.rgb))
            if advance is not None:
                advance()
    tex, _ = solve_texture(proj, t.faces, prior_views=cfg.prior_views)
    face_views = np.bincount(pts.face, weights=proj.views, minlength=len(t.faces))
    # Later passes: iterative back-projection. The render of the current texture is compared with
    # each image and the residual, divided by the irradiance, is added back at the texels: this
    # undoes the blur of the first pass (it reads the images at one point per texel, while a
    # pixel averages its whole area and bilinear texture lookups blend four texels) and replaces
    # the white-texture bounce light by the one of the current texture.
    for p in range(1, cfg.project_passes):
        corr = Projection.empty(pts)
        last = None
        for ti, cam, image, allowed, E in views:
            V = data.vertices[ti]
            renderer.set_vertices(V, tag=ti)
            if last != ti:
                occ, last = Occlusion(V, t.faces), ti
            R = renderer.render(cam, tex, ambient, key, spp=cfg.project_spp, seed=5000 + 1000 * p + 97 * ti)
            corr.add_view(cam, V, t.faces, image - R.rgb, allowed, E, occlusion=occ, twosided=two)
            if advance is not None:
                advance()
        lam = cfg.prior_views * np.median(corr.den[corr.weight > 0] / corr.weight[corr.weight > 0][:, None], 0)
        delta = np.zeros((cfg.texture_size ** 2, 3), np.float32)
        delta[pts.index] = corr.num / (corr.den + lam)
        filled = np.zeros(cfg.texture_size ** 2, bool)
        filled[pts.index] = True
        delta = fill_empty(delta.reshape(tex.shape), filled.reshape(tex.shape[:2]))
        tex = np.clip(tex + delta, 0.0, 1.0).astype(np.float32)
    return tex, face_views


def initial_texture(data: AppearanceData, cfg: AppearanceConfig, out: Path, progress=None, renderer=None,
                    ambient=None, key=None, light_key=None):
    """Steps 1-2 of the fit: the atlas and T_0, read back from ``out`` (``atlas.npz``,
    ``texture_init_linear.npy``) when they were made with the same settings from the same data
    (:attr:`AppearanceData.key`), else computed and written there. ``init="project"`` needs the fit's ``renderer`` and its initial lights
    (``light_key``: anything else that identifies them, e.g. a fitted environment map).

    Returns:
        face_uvs [F, 3, 2], face_pixels [F] (training pixels that saw each face), T_0 [size,
        size, 3] float32 linear. ``atlas.npz`` also keeps face_colors [F, 3], T_0's source.
    """
    t = data.template
    atlas_path = out / "atlas.npz"
    init_key = json.dumps({"texture_size": cfg.texture_size, "init_frame_stride": cfg.init_frame_stride,
                           "erode_px": cfg.erode_px, "meshes": data.source, "data": data.key, "frames": data.frames,
                           "cameras": [c.name for c in data.cameras],
                           "tracked_colors": data.face_colors is not None, "init": cfg.init,
                           **({"project_views": cfg.project_views, "project_spp": cfg.project_spp,
                               "prior_views": cfg.prior_views, "light": cfg.light,
                              "project_passes": cfg.project_passes,
                               "ambient": None if ambient is None else [float(x) for x in ambient],
                               "key": None if key is None else [float(x) for x in key],
                               **({"light_key": light_key} if light_key is not None else {})}
                              if cfg.init == "project" else {})})
    a = load_npz(atlas_path) if atlas_path.is_file() else {}
    if str(a.get("init_key", "")) == init_key and (out / "texture_init_linear.npy").is_file():
        return a["face_uvs"], a["face_pixels"], np.load(out / "texture_init_linear.npy")
    face_uvs = t.face_uvs
    if cfg.init == "project":
        n = len(projection_views(len(data.frames), len(data.cameras), cfg.project_views)) * len(data.cameras) \
            * cfg.project_passes
        with resolve(progress).task("appearance: projected texture", total=n) as task:
            tex0, face_pixels = projected_texture(data, cfg, renderer, ambient, key, advance=task.advance)
        np.save(out / ".texture_init_linear.tmp.npy", tex0)
        (out / ".texture_init_linear.tmp.npy").replace(out / "texture_init_linear.npy")
        save_npz_atomic(atlas_path, face_uvs=face_uvs, face_colors=np.zeros((len(t.faces), 3)),
                        face_pixels=face_pixels, init_key=np.array(init_key))
        return face_uvs, face_pixels, tex0
    used = range(0, len(data.frames), cfg.init_frame_stride)
    # With tracked colours the image pass only counts which faces the training pixels see
    # (``face_pixels``): a few frames spread over the sequence suffice for that.
    stride = cfg.init_frame_stride if data.face_colors is None else \
        max(cfg.init_frame_stride, len(data.frames) // VISIBILITY_FRAMES)
    name = "appearance: per-face colours" if data.face_colors is None else "appearance: face visibility"
    with resolve(progress).task(name, total=len(range(0, len(data.frames), stride)) * len(data.cameras)) as task:
        img_colors, face_pixels = image_face_colors(data, stride, cfg.erode_px, advance=task.advance)
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
    return face_uvs, face_pixels, tex0
