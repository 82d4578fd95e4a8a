"""How good a fitted appearance is (benchmarks/appearance_accuracy.py, tests): texture PSNR
against the true albedo, how much shading is baked into a texture, and renders of the held-out
motion against its images."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ...camera import Camera
from ...capture import Capture, frame_name
from ...files import load_npz, read_json
from ...render import Ambient, SceneSpec, load_scene, read_png, render
from ...render.avatar import AvatarMeshes
from .data import load_target
from .texture import texel_face_map


def texture_psnr(texture: np.ndarray, gt: np.ndarray, covered: np.ndarray, align_scale: bool = False) -> float:
    """PSNR [dB] of a linear texture against the ground-truth one over ``covered`` texels
    (a [Hg, Wg] bool mask at the ground truth's resolution; ``texture`` is bilinearly resampled
    there). ``align_scale`` first applies the per-channel least-squares gain: texture and light
    are only determined up to a common factor (T·L is what the images see)."""
    from ...metrics import psnr

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
    from ...metrics import psnr, ssim

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
