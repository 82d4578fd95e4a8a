"""The avatar folder: everything needed to animate, render and export a captured person.

::

    avatar.json        version, body (Anny shape, template body topology), source capture, fps
    template.ply       frame-1 mesh of body + garments: labels, boundary flags, UVs
    skinning.npz       body-part skinning weights [Nb, B] (transferred, paper A.2), bone names,
                       the capture's frame-1 pose (rotations [B, 3], root translation [3])
    material.json      garment material (fit-physics output, or a simulator preset)
    texture.png        albedo atlas (sRGB), texture_linear.npy the same in linear float32
    light.json         fitted lights (optional)

``build_avatar`` assembles one from a capture and the stage outputs; ``Avatar.load`` validates it.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .body import BodyModel, BodyShape
from .body.transfer import transfer_skinning_weights
from .capture import Capture, Template, load_capture
from .data.material import resolve_material
from .errors import PhysavatarError
from .files import load_npz, read_json, read_ply, save_npz_atomic, write_json_atomic
from .geometry import submesh
from .sim import Material

AVATAR_VERSION = 1


@dataclass
class Avatar:
    root: Path
    meta: dict
    template: Template
    body_weights: np.ndarray  # [Nb, B]
    bone_names: list[str]
    rest_rotations: np.ndarray  # [B, 3] the capture's frame-1 pose
    rest_translation: np.ndarray  # [3]
    material: Material
    texture: np.ndarray | None  # [H, W, 3] linear
    light_path: Path | None

    @property
    def shape(self) -> BodyShape:
        return BodyShape(**self.meta["body"]["shape"])

    @property
    def fps(self) -> float:
        return float(self.meta["fps"])

    @staticmethod
    def load(root: str | Path) -> "Avatar":
        root = Path(root)
        if not root.is_dir():
            raise PhysavatarError(root, "avatar folder not found")
        meta = read_json(root / "avatar.json")
        if meta.get("version") != AVATAR_VERSION:
            raise PhysavatarError(root / "avatar.json", f"unsupported avatar version {meta.get('version')!r}")
        ply = read_ply(root / "template.ply")
        if "label" not in ply.vertex_data:
            raise PhysavatarError(root / "template.ply", "missing per-vertex 'label'")
        labels = np.asarray(ply.vertex_data["label"]).astype(np.int64)
        boundary = np.asarray(ply.vertex_data.get("boundary", np.zeros(len(labels)))).astype(bool)
        template = Template(ply.vertices, ply.faces, labels, boundary, ply.face_uvs)
        z = load_npz(root / "skinning.npz")
        W = z["weights"].astype(np.float64)
        if W.shape[0] != int((labels == 0).sum()):
            raise PhysavatarError(root / "skinning.npz", f"weights for {W.shape[0]} vertices, template body has {int((labels == 0).sum())}")
        tex = None
        if (root / "texture_linear.npy").exists():
            tex = np.load(root / "texture_linear.npy").astype(np.float32)
        elif (root / "texture.png").exists():
            from .render import read_png, srgb_to_linear

            tex = srgb_to_linear(read_png(root / "texture.png")[..., :3].astype(np.float32) / 255.0)
        return Avatar(root, meta, template, W, [str(b) for b in z["bone_names"]], z["rest_rotations"],
                      z["rest_translation"], Material.load(root / "material.json"), tex,
                      (root / "light.json") if (root / "light.json").exists() else None)


def build_avatar(capture: str | Path | Capture, out: str | Path, *, material: str | Path | Material,
                 texture_dir: str | Path | None = None, template_vertices: np.ndarray | None = None) -> Avatar:
    """Assemble an avatar folder.

    Args:
        capture: the capture (template, body shape and frame-1 pose).
        material: a material.json (fit-physics output), a Material, or a simulator preset name.
        texture_dir: fit-appearance output (texture.png, texture_linear.npy, light.json), optional.
        template_vertices: [V, 3] frame-1 positions to use instead of the capture's template
            (e.g. the tracked frame 1).
    """
    cap = capture if isinstance(capture, Capture) else load_capture(capture)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t = cap.template
    if template_vertices is not None:
        t = Template(np.asarray(template_vertices, np.float64), t.faces, t.labels, t.boundary, t.face_uvs)
    if texture_dir is not None and (Path(texture_dir) / "atlas.npz").exists():
        # the texture was fitted on this atlas (made by xatlas when the capture's template has
        # no UVs): the avatar must carry the same UVs as its texture
        uv = load_npz(Path(texture_dir) / "atlas.npz").get("face_uvs")
        if uv is not None and uv.shape == (len(t.faces), 3, 2):
            t = Template(t.vertices, t.faces, t.labels, t.boundary, np.asarray(uv, np.float64))
    t.save(out / "template.ply")
    resolve_material(material).save(out / "material.json")

    # Skinning weights of the template's body part, transferred from Anny posed at frame 1.
    body = BodyModel(cap.body.shape, topology=cap.body.topology)
    from .body import Motion

    m0 = Motion("frame1", cap.fps, cap.body.bone_names, cap.body.rotations[:1], cap.body.root_translation[:1])
    m0 = m0.for_bones(body.bone_names)
    posed = body.pose(m0.rotations, m0.root_translation)
    bmask = t.labels == 0
    _, bfaces = submesh(t.faces, bmask)
    W, matched = transfer_skinning_weights(t.vertices[bmask], bfaces, posed.vertices[0], body.faces, body.skinning_weights)
    save_npz_atomic(out / "skinning.npz", weights=W.astype(np.float32), bone_names=np.array(body.bone_names),
                    rest_rotations=m0.rotations[0], rest_translation=m0.root_translation[0],
                    matched=matched)
    if texture_dir is not None:
        texture_dir = Path(texture_dir)
        for name in ("texture.png", "texture_linear.npy", "light.json"):
            if (texture_dir / name).exists():
                shutil.copyfile(texture_dir / name, out / name)
    write_json_atomic(out / "avatar.json", {
        "version": AVATAR_VERSION,
        "source_capture": str(cap.root),
        "fps": cap.fps,
        "body": {"model": "anny", "shape": cap.body.shape.to_dict(), "topology": cap.body.topology},
        "skinning_matched_fraction": float(matched.mean()),
        "template_vertices": int(len(t.vertices)),
        "garment_vertices": int(t.garment_mask.sum()),
    })
    return Avatar.load(out)
