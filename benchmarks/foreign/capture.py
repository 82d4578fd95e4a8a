"""Write a foreign capture: a procedural garment on a non-default Anny body, simulated by Newton
VBD, textured with the benchmark's own fabrics, lit by its own lights, rendered by Mitsuba
(physavatar.render) and saved in physavatar's capture format with its ground truth.

What comes from physavatar: the Anny body model, the capture/PLY/PNG/NPZ writers, the camera
class and the Mitsuba renderer. Everything else (garment shapes, simulator, material, UV atlas,
textures, lights, camera rig, motions chosen) is the benchmark's own.

Ground truth written: meshes.npz, heldout/{motion.npz, meshes.npz, cameras.json, images, masks},
texture_linear.npy / texture.png, lighting.json, foreign.json (this config and the fabric in
Newton's terms). No material.json: the material is not in physavatar's terms.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import time
from pathlib import Path

import numpy as np

from .garments import attach, attached_positions, fitted_top, flared_skirt
from .newton_cloth import Fabric, NewtonSettings, simulate_sequence

# A body shape far from the default (all 0.5): slim, tall, young, short-legged proportions.
FOREIGN_SHAPE = {"gender": 0.2, "age": 0.35, "muscle": 0.3, "weight": 0.7, "height": 0.65, "proportions": 0.35}

# The generator's fabrics in Newton's terms (chosen for Newton, not mapped from physavatar presets).
FABRICS = {
    "flared-skirt": Fabric(density=0.16, tri_ke=1.5e3, tri_ka=6.0e2, edge_ke=2.0e-3, tri_kd=1e-6, edge_kd=1e-6),
    "fitted-top": Fabric(density=0.20, tri_ke=8.0e2, tri_ka=4.0e2, edge_ke=1.0e-3, tri_kd=1e-6, edge_kd=1e-6),
}


@dataclasses.dataclass(frozen=True)
class ForeignConfig:
    name: str = "skirt-plaid-256"
    garment: str = "flared-skirt"  # or "fitted-top"
    texture: str = "plaid"  # "plaid", "plain" or "print"
    size: int = 256  # image width = height [px]
    cameras: int = 8  # capture cameras (run holds two of them out)
    heldout_views: int = 2  # extra cameras that film the held-out motion
    frames: int = 16
    heldout_frames: int = 12
    motion: str = "dance"  # training motion
    heldout_motion: str = "walk"
    fps: float = 25.0
    shape: tuple = tuple(sorted(FOREIGN_SHAPE.items()))
    edge: float = 0.025  # garment edge length [m]
    # the drape before frame 0: 40 frames with the velocities × 0.7 after each, so frame 0 is at rest
    # (the paper's Algorithm 1 and `animate` start from rest). Undamped, 12 frames left the skirt
    # swinging at 0.12 m/s (it went on at ~2.7 mm per frame after 2.4 s on a still body), and that
    # free swing, not the held-out motion, made most of the held-out ground truth.
    settle_frames: int = 40
    settle_damping: float = 0.7
    substeps: int = 10
    iterations: int = 10
    contact_ke: float = 1.0e4  # Newton penalty stiffness [N/m]
    contact_radius: float = 6.0e-3  # particle radius: the cloth's contact thickness [m]
    spp: int = 64  # path-traced samples per pixel: 8 left Monte Carlo noise that capped the truth at 26.8 dB
    texture_size: int = 1024
    seed: int = 3

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["shape"] = dict(self.shape)
        return d


# -- textures -----------------------------------------------------------------------------------

def _smooth_noise(shape, cells, rng):
    from scipy.ndimage import zoom

    g = rng.random((cells + 3, cells + 3))
    z = zoom(g, (shape[0] + 3 * shape[0] / cells) / (cells + 3), order=3)
    return np.clip(z[: shape[0], : shape[1]], 0, 1)


def fabric_colour(kind: str, u: np.ndarray, v: np.ndarray, rng) -> np.ndarray:
    """Linear RGB [..., 3] of a fabric at material coordinates (u, v) [m]."""
    if kind == "plain":
        return np.broadcast_to(np.array([0.10, 0.32, 0.36]), u.shape + (3,)).copy()
    if kind == "plaid":  # a tartan: warp and weft bands at 1.2 cm, 4 cm and 9 cm periods
        def bands(x):
            return np.stack([(np.sin(2 * np.pi * x / 0.012) > 0.55), (np.sin(2 * np.pi * x / 0.04) > 0.3),
                             (np.sin(2 * np.pi * x / 0.09 + 1.0) > 0.7)], -1).astype(float)
        bu, bv = bands(u), bands(v)
        base = np.array([0.42, 0.04, 0.05])
        cols = [np.array([0.9, 0.85, 0.7]), np.array([0.02, 0.08, 0.2]), np.array([0.05, 0.25, 0.06])]
        img = np.broadcast_to(base, u.shape + (3,)).copy()
        for k in (1, 2, 0):
            w = 0.5 * (bu[..., k] + bv[..., k])[..., None]
            img = img * (1 - w) + cols[k] * w
        return img
    if kind == "print":  # scattered blossoms on cream
        img = np.broadcast_to(np.array([0.8, 0.74, 0.6]), u.shape + (3,)).copy()
        cell = 0.05
        iu, iv = np.floor(u / cell), np.floor(v / cell)
        h = np.sin(iu * 12.9898 + iv * 78.233) * 43758.5453
        r1 = h - np.floor(h)
        h2 = np.sin(iu * 39.3468 + iv * 11.135) * 24634.6345
        r2 = h2 - np.floor(h2)
        cu, cv = (iu + 0.25 + 0.5 * r1) * cell, (iv + 0.25 + 0.5 * r2) * cell
        d = np.hypot(u - cu, v - cv)
        ang = np.arctan2(v - cv, u - cu)
        rad = 0.012 + 0.008 * r2
        petal = d < rad * (0.65 + 0.35 * np.cos(5 * ang))
        palette = np.array([[0.7, 0.1, 0.3], [0.1, 0.2, 0.6], [0.85, 0.5, 0.05], [0.2, 0.45, 0.15]])
        col = palette[(np.floor(r1 * 4) % 4).astype(int)]
        img = np.where(petal[..., None], col, img)
        img = np.where((d < 0.3 * rad)[..., None], np.array([0.95, 0.85, 0.2]), img)
        return img
    raise ValueError(f"unknown texture {kind!r}")


def skin_colour(u, v, rng):
    base = np.array([0.36, 0.22, 0.15])
    n = 0.8 + 0.3 * np.sin(u * 40.0) * np.sin(v * 37.0) + 0.1 * np.sin(u * 150.0 + v * 90.0)
    return base * n[..., None]


def bake_texture(face_uvs, face_material_uv, face_is_garment, size, fabric, seed) -> np.ndarray:
    """[size, size, 3] atlas: every texel inside a triangle's UV footprint gets the colour at its
    interpolated material coordinates; the rest is filled from the nearest covered texel."""
    from scipy.ndimage import distance_transform_edt

    rng = np.random.default_rng(seed)
    matu = np.full((size, size), np.nan)
    matv = np.full((size, size), np.nan)
    gar = np.zeros((size, size), bool)
    P = np.stack([face_uvs[..., 0] * size - 0.5, (1 - face_uvs[..., 1]) * size - 0.5], -1)  # [F, 3, 2] px
    for f in range(len(P)):
        p = P[f]
        x0, y0 = np.floor(p.min(0)).astype(int)
        x1, y1 = np.ceil(p.max(0)).astype(int)
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, size - 1), min(y1, size - 1)
        if x1 < x0 or y1 < y0:
            continue
        X, Y = np.meshgrid(np.arange(x0, x1 + 1), np.arange(y0, y1 + 1))
        T = np.array([p[1] - p[0], p[2] - p[0]]).T
        if abs(np.linalg.det(T)) < 1e-12:
            continue
        ab = np.linalg.solve(T, np.stack([X.ravel() - p[0, 0], Y.ravel() - p[0, 1]]))
        w = np.stack([1 - ab.sum(0), ab[0], ab[1]])
        inside = (w >= -0.02).all(0)
        if not inside.any():
            continue
        mu = w[:, inside].T @ face_material_uv[f]
        ys, xs = Y.ravel()[inside], X.ravel()[inside]
        matu[ys, xs], matv[ys, xs] = mu[:, 0], mu[:, 1]
        gar[ys, xs] = face_is_garment[f]
    covered = ~np.isnan(matu)
    _, (iy, ix) = distance_transform_edt(~covered, return_indices=True)
    matu, matv, gar = matu[iy, ix], matv[iy, ix], gar[iy, ix]
    img = np.where(gar[..., None], fabric_colour(fabric, matu, matv, rng), skin_colour(matu, matv, rng))
    return np.clip(img, 0.02, 0.95).astype(np.float32)


def _unwrap_faces(uv: np.ndarray, period: float) -> np.ndarray:
    """Per-face corner coordinates [F, 3, 2] with u unwrapped across the seam of a periodic u."""
    u = uv[..., 0]
    u = np.where(u - u[:, :1] > period / 2, u - period, np.where(u - u[:, :1] < -period / 2, u + period, u))
    return np.stack([u, uv[..., 1]], -1)


def material_coordinates(V, F, center, radius=0.17):
    """Cylindrical material coordinates [m] of a mesh about a vertical axis: (arc at ``radius``, −z)."""
    ang = np.arctan2(V[:, 1] - center[1], V[:, 0] - center[0])
    uv = np.stack([ang * radius, -V[:, 2]], 1)
    return _unwrap_faces(uv[F], 2 * np.pi * radius)


def xatlas_uvs(V, F, size) -> np.ndarray:
    """Per-corner UVs [F, 3, 2] of an xatlas atlas packed at ``size`` texels with padding."""
    import xatlas

    atlas = xatlas.Atlas()
    atlas.add_mesh(V.astype(np.float32), F.astype(np.uint32))
    po = xatlas.PackOptions()
    po.resolution = size
    po.padding = 4
    po.bilinear = True
    atlas.generate(pack_options=po)
    vmap, idx, uvs = atlas[0]
    assert np.array_equal(vmap[idx], F), "xatlas reordered faces"
    return uvs[idx].astype(np.float64)


# -- scene ---------------------------------------------------------------------------------------

def lights_for(center_z: float):
    """Not the project's studio: a warm panel high on the left, a cool point light behind on the
    right and a dim bluish ambient."""
    from physavatar.render.lights import Ambient, AreaLight, PointLight

    return [Ambient((0.16, 0.18, 0.22)),
            AreaLight(center=(-2.0, -1.6, center_z + 1.6), target=(0.0, 0.0, center_z), size=(1.2, 1.2),
                      radiance=(10.0, 8.0, 5.8)),
            PointLight(position=(1.8, 1.5, center_z + 0.8), intensity=(2.0, 2.6, 3.4))]


def cameras_for(cfg: ForeignConfig, center_z: float):
    from physavatar.camera import Camera, look_at

    f = 0.5 * cfg.size / np.tan(0.5 * np.radians(36.0))
    K = np.array([[f, 0, (cfg.size - 1) / 2], [0, f, (cfg.size - 1) / 2], [0, 0, 1.0]])
    target = np.array([0.0, 0.0, center_z])

    def ring(n, start, prefix, radius=2.9):
        out = []
        for i in range(n):
            a = np.radians(start + 360.0 * i / n)
            h = center_z + (0.5 if i % 2 else -0.1)
            eye = np.array([radius * np.cos(a), radius * np.sin(a), h])
            out.append(Camera(f"{prefix}{i:02d}", cfg.size, cfg.size, K, look_at(eye, target)))
        return out

    return ring(cfg.cameras, -75.0, "view"), ring(cfg.heldout_views, -75.0 + 180.0 / cfg.cameras + 30.0, "novel")


# -- building ------------------------------------------------------------------------------------

def _simulate(body, garment, fabric, settings, motion, cfg, BF, info=None):
    posed = motion.pose(body).vertices
    att = attach(garment.vertices[garment.pinned], body.rest_vertices, BF)
    pins = attached_positions(att, posed, BF)
    return posed, simulate_sequence(garment.vertices, garment.faces, garment.pinned, pins, posed, BF, cfg.fps,
                                    fabric, settings, settle_frames=cfg.settle_frames,
                                    settle_damping=cfg.settle_damping, info=info)


def build(out: str | Path, cfg: ForeignConfig, say=print) -> Path:
    """Write the capture of ``cfg`` to ``out`` (kept if it exists with the same config)."""
    from physavatar.body import BodyModel, BodyShape, builtin_motion
    from physavatar.capture import (
        BodyPoses,
        Template,
        frame_name,
        save_cameras,
        save_capture_meta,
        save_png,
    )
    from physavatar.files import save_npz_atomic, write_json_atomic
    from physavatar.render import linear_to_srgb8, load_scene, render, save_lights
    from physavatar.render.avatar import AvatarMeshes
    from physavatar.render.scene import SceneSpec

    out = Path(out)
    meta_file = out / "ground_truth" / "foreign.json"
    if meta_file.exists() and json.loads(meta_file.read_text()).get("config") == json.loads(json.dumps(cfg.to_dict())):
        return out
    work = out.with_name(out.name + ".partial")
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    t0 = time.time()
    body = BodyModel(BodyShape(**dict(cfg.shape)), topology="collider")
    BF = np.asarray(body.faces)
    garment = {"flared-skirt": flared_skirt, "fitted-top": fitted_top}[cfg.garment](body, edge=cfg.edge)
    fabric = FABRICS[cfg.garment]
    settings = NewtonSettings(substeps=cfg.substeps, iterations=cfg.iterations, contact_ke=cfg.contact_ke,
                              radius=cfg.contact_radius)
    motion = builtin_motion(cfg.motion, body.bone_names, cfg.fps, (cfg.frames - 1) / cfg.fps)
    held = builtin_motion(cfg.heldout_motion, body.bone_names, cfg.fps, (cfg.heldout_frames - 1) / cfg.fps)
    say(f"{cfg.name}: simulating {len(garment.vertices)} garment vertices with Newton VBD")
    t_sim = time.time()
    settle = {"training": {}, "heldout": {}}
    body_tr, gar_tr = _simulate(body, garment, fabric, settings, motion, cfg, BF, settle["training"])
    body_he, gar_he = _simulate(body, garment, fabric, settings, held, cfg, BF, settle["heldout"])
    t_sim = time.time() - t_sim
    for name, g in (("training", gar_tr), ("held-out", gar_he)):
        if not np.isfinite(g).all():
            raise RuntimeError(f"{cfg.name}: the Newton simulation of the {name} motion diverged")
    nb = len(body.rest_vertices)
    from physavatar.geometry.intersect import count_intersections

    crossings = {name: [int(count_intersections(g[f], garment.faces, b[f], BF)) for f in range(len(g))]
                 for name, g, b in (("training", gar_tr, body_tr), ("heldout", gar_he, body_he))}
    say(f"{cfg.name}: garment-body crossings per frame {crossings}")
    V0 = np.concatenate([body_tr[0], gar_tr[0]])
    F = np.concatenate([BF, garment.faces + nb])
    labels = np.r_[np.zeros(nb, np.int64), np.ones(len(garment.vertices), np.int64)]
    boundary = np.zeros(len(V0), bool)
    boundary[nb + garment.pinned] = True
    say(f"{cfg.name}: UV atlas (xatlas) and {cfg.texture} texture")
    face_uvs = xatlas_uvs(V0, F, cfg.texture_size)
    center = V0[nb:, :2].mean(0)
    texture = bake_texture(face_uvs, material_coordinates(V0, F, center), labels[F].all(1), cfg.texture_size,
                           cfg.texture, cfg.seed)
    template = Template(V0, F, labels, boundary, face_uvs)
    verts = np.concatenate([body_tr, gar_tr], 1)
    held_verts = np.concatenate([body_he, gar_he], 1)
    center_z = 0.5 * (body.rest_vertices[:, 2].max() + body.rest_vertices[:, 2].min())
    lights = lights_for(center_z)
    cams, novel = cameras_for(cfg, center_z)
    say(f"{cfg.name}: rendering {len(cams)} views x {cfg.frames} frames + {len(novel)} x {cfg.heldout_frames}")
    t_r = time.time()
    for base, cs, V, seed0 in ((work, cams, verts, 0), (work / "ground_truth" / "heldout", novel, held_verts, 7)):
        for f in range(len(V)):
            meshes = AvatarMeshes.build(V[f], F, face_uvs, labels)
            scene = load_scene(SceneSpec(meshes=meshes.specs(V[f], texture), lights=lights))
            for i, c in enumerate(cs):
                r = render(scene, c, spp=cfg.spp, seed=cfg.seed * 1009 + f * 31 + i + seed0)
                save_png(base / "masks" / c.name / f"{frame_name(f)}.png", r.alpha8())
                save_png(base / "images" / c.name / f"{frame_name(f)}.png", r.srgb8())
    t_r = time.time() - t_r
    save_capture_meta(work, fps=cfg.fps, frames=list(range(cfg.frames)),
                      extra={"garment_source": "simulated", "synthetic": True,
                             "generator": "benchmarks/foreign (NVIDIA Newton VBD)"})
    save_cameras(work, cams)
    BodyPoses(body.shape, body.bone_names, motion.rotations, motion.root_translation, "collider").save(work / "body.npz")
    template.save(work / "template" / "mesh.ply")
    gt = work / "ground_truth"
    save_png(gt / "texture.png", linear_to_srgb8(texture))
    np.save(gt / "texture_linear.npy", texture)
    save_lights(gt / "lighting.json", lights, {"note": "foreign capture lights (not the studio default)"})
    save_npz_atomic(gt / "meshes.npz", vertices=verts.astype(np.float32), faces=F, labels=labels.astype(np.uint8),
                    fps=cfg.fps)
    held.save(gt / "heldout" / "motion.npz")
    save_npz_atomic(gt / "heldout" / "meshes.npz", vertices=held_verts.astype(np.float32), faces=F,
                    labels=labels.astype(np.uint8), fps=cfg.fps)
    save_cameras(gt / "heldout", novel)
    write_json_atomic(gt / "foreign.json", {
        "config": cfg.to_dict(), "fabric_newton": dataclasses.asdict(fabric),
        "newton_settings": dataclasses.asdict(settings), "crossing_triangle_pairs": crossings,
        "settle_drift_mm": {k: round(v["settle_drift_mm"], 4) for k, v in settle.items()},
        "seconds": {"simulate": round(t_sim, 1), "render": round(t_r, 1), "total": round(time.time() - t0, 1)},
        "garment_vertices": len(garment.vertices), "template_vertices": len(V0)})
    if out.exists():
        shutil.rmtree(out)
    work.rename(out)
    return out
