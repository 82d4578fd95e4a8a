"""Where a foreign capture's held-out-view error comes from: texture x geometry, per image region.

    python benchmarks/foreign_view_split.py CASE_DIR OUT [NAME=APPEARANCE_DIR ...]

CASE_DIR holds ``capture/`` and ``run/`` (a finished ``physavatar run``, as
benchmarks/foreign_capture.py leaves them); OUT gets the renders and ``split.json``.

Textures: ``truth`` (the true albedo and lights), ``run`` (run/appearance: fitted on the tracked
meshes) and each NAME=APPEARANCE_DIR (a fit-appearance folder, e.g. one of
benchmarks/foreign_appearance.py: texture_linear.npy and light.json). Geometry: the held-out
motion on run/animate (what `evaluate` renders: the estimated material's simulation) or on the
true held-out meshes; the capture's held-out cameras on the tracked meshes (what `evaluate`
renders) or on the true ones. Each pair is scored with `evaluate`'s own ``_score_views`` (same
frames, cameras, 64 spp, inside the image masks); then each view's squared error is split by
region: ``silhouette`` (inside the image's mask, background in the render), ``garment`` and
``body`` pixels, and ``unseen`` (pixels of faces no training pixel saw, atlas.npz
``face_pixels`` = 0). Region images are renders of a 0/1 texture under a uniform light, divided
by a render of a white one. Session 26: the plaid skirt's 25 dB (docs/appearance.md).
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path
from types import SimpleNamespace

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np
from PIL import Image, ImageDraw

REGIONS = ("silhouette", "garment", "body", "unseen")


def face_texture(face_uvs: np.ndarray, sel: np.ndarray, size: int = 1024) -> np.ndarray:
    """[size, size, 3]: 1 on the UV triangles of the faces ``sel``, 0 elsewhere (dilated a texel)."""
    from scipy.ndimage import maximum_filter

    img = Image.new("L", (size, size), 0)
    d = ImageDraw.Draw(img)
    for tri in face_uvs[sel]:
        d.polygon([(u * size, (1 - v) * size) for u, v in tri], fill=255, outline=255)
    a = maximum_filter(np.asarray(img, np.float32) / 255, 3)
    return np.repeat(a[..., None], 3, 2)


class Regions:
    """Per (geometry, frame index, camera): the garment and unseen fractions and the alpha."""

    def __init__(self, template, face_uvs, unseen_faces):
        self.t = template
        garment_faces = (template.labels[template.faces] > 0).all(1)
        self.tex = {"garment": face_texture(face_uvs, garment_faces), "unseen": face_texture(face_uvs, unseen_faces)}
        self.cache = {}

    def _render(self, V, cam, tex, spp=16):
        from physavatar.render import SceneSpec, load_scene, render
        from physavatar.render.avatar import AvatarMeshes
        from physavatar.render.lights import named_lights

        t = self.t
        meshes = AvatarMeshes.build(V, t.faces, t.face_uvs, t.labels)
        scene = load_scene(SceneSpec(meshes=meshes.specs(V, tex), lights=named_lights("ambient", V.mean(0))))
        o = render(scene, cam, spp=spp, seed=0)
        return np.asarray(o.rgb)[..., 0], np.asarray(o.alpha)

    def masks(self, name: str, i: int, V, cam, gt_mask) -> dict:
        key = (name, i, cam.name)
        if key not in self.cache:
            one, alpha = self._render(V, cam, np.ones_like(self.tex["garment"]))
            d = np.maximum(one, 1e-3)
            self.cache[key] = (self._render(V, cam, self.tex["garment"])[0] / d,
                               self._render(V, cam, self.tex["unseen"])[0] / d, alpha)
        g, u, alpha = self.cache[key]
        r = alpha > 0.5
        return {"silhouette": gt_mask & ~r, "garment": gt_mask & r & (g > 0.5), "body": gt_mask & r & (g <= 0.5),
                "unseen": gt_mask & r & (u > 0.5)}


def split(regions: Regions, name: str, folder: Path, Vs, frames: dict, cams, paths) -> dict:
    """Each region's share of the squared error (from the saved ours / gt PNGs) and its PSNR."""
    acc = {k: [0.0, 0] for k in REGIONS}
    total, n_px, per_frame = 0.0, 0, {}
    for i, f in frames.items():
        ps = []
        for cam in cams:
            ours = np.asarray(Image.open(folder / f"{cam.name}_{int(f):06d}_ours.png"), np.float32) / 255
            gt = np.asarray(Image.open(folder / f"{cam.name}_{int(f):06d}_gt.png"), np.float32) / 255
            m = np.asarray(Image.open(paths(cam, f)[1]).convert("L"), np.float32) / 255 > 0.5
            se = ((ours - gt) ** 2).mean(-1)
            total += float(se[m].sum())
            n_px += int(m.sum())
            ps.append(float(10 * np.log10(1 / max(float(((ours - gt) ** 2)[m].mean()), 1e-12))))
            for k, sel in regions.masks(name, i, Vs[i], cam, m).items():
                acc[k][0] += float(se[sel].sum())
                acc[k][1] += int(sel.sum())
        per_frame[int(f)] = float(np.mean(ps))
    out = {"mse_in_mask": total / n_px, "psnr_per_frame": per_frame}
    for k, (s, n) in acc.items():
        out[k] = {"pixel_fraction": n / n_px, "se_share": s / total,
                  "psnr": float(10 * np.log10(1 / max(s / max(n, 1), 1e-12)))}
    return out


def main(argv=None) -> int:
    from physavatar.camera import Camera
    from physavatar.capture import frame_name, load_capture
    from physavatar.data.animated import AnimatedSequence
    from physavatar.files import load_npz, read_json, write_json_atomic
    from physavatar.stages.evaluate import TrackedSequence, _score_views

    argv = sys.argv[1:] if argv is None else argv
    if len(argv) < 2:
        raise SystemExit(__doc__.split("\n\n")[1])
    case, out = Path(argv[0]), Path(argv[1])
    cap_dir, run_dir = case / "capture", case / "run"
    cap = load_capture(cap_dir)
    t = cap.template
    gt_dir = cap_dir / "ground_truth"
    held = gt_dir / "heldout"
    textures = {"truth": (gt_dir / "texture_linear.npy", gt_dir / "lighting.json"),
                "run": (run_dir / "appearance" / "texture_linear.npy", run_dir / "appearance" / "light.json")}
    for a in argv[2:]:
        k, v = a.split("=", 1)
        textures[k] = (Path(v) / "texture_linear.npy", Path(v) / "light.json")
    atlas = np.load(run_dir / "appearance" / "atlas.npz")
    if not np.allclose(atlas["face_uvs"], t.face_uvs):
        raise SystemExit("the fit's atlas is not the template's UVs")
    regions = Regions(t, atlas["face_uvs"], atlas["face_pixels"] == 0)

    seq = AnimatedSequence.load(run_dir / "animate")
    m = json.loads((run_dir / "evaluate" / "metrics.json").read_text())
    n = int(m.get("heldout_frames") or len(seq.vertices))
    sets = {}
    hcams = [Camera.from_dict(c) for c in read_json(held / "cameras.json")]
    sets["heldout_motion"] = (
        {"animate": seq.vertices[:n], "true": load_npz(held / "meshes.npz")["vertices"][:n]},
        {f: f for f in sorted({0, n // 2, n - 1})}, hcams,
        lambda cam, f: (held / "images" / cam.name / f"{f:06d}.png", held / "masks" / cam.name / f"{f:06d}.png"))
    hold = tuple(read_json(run_dir / "track" / "config.json").get("holdout") or ())
    if hold:
        Vt = TrackedSequence.load(run_dir / "track").vertices
        nt = len(Vt)
        sets["capture_heldout_cameras"] = (
            {"tracked": Vt, "true": load_npz(gt_dir / "meshes.npz")["vertices"][:nt]},
            {i: cap.frames[i] for i in sorted({0, nt // 2, nt - 1})}, [c for c in cap.cameras if c.name in hold],
            lambda cam, f: (cap_dir / "images" / cam.name / f"{frame_name(f)}.png",
                            cap_dir / "masks" / cam.name / f"{frame_name(f)}.png"))
    results = {}
    for tex_name, (tex, light) in textures.items():
        av = SimpleNamespace(texture=np.load(tex), light_path=light)
        for set_name, (geoms, frames, cams, paths) in sets.items():
            for gname, V in geoms.items():
                folder = out / f"{set_name}_{tex_name}_{gname}"
                r = _score_views(av, V, t.faces, t.face_uvs, t.labels, frames, cams, paths, folder, 64)
                key = f"{set_name} | texture {tex_name} | meshes {gname}"
                results[key] = {k: r[k] for k in ("psnr", "ssim", "lpips")} | {
                    "split": split(regions, f"{set_name}/{gname}", folder, V, frames, cams, paths)}
                print(key, f"PSNR {r['psnr']:.2f} SSIM {r['ssim']:.3f} LPIPS {r['lpips']:.4f}", flush=True)
        write_json_atomic(out / "split.json", {"case": str(case), "textures": {k: str(v[0]) for k, v in textures.items()},
                                               "results": results})
    return 0


if __name__ == "__main__":
    sys.exit(main())
