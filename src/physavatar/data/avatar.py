"""The avatar folder: everything needed to animate, render and export a captured person.

::

    avatar.json        version, body (Anny shape, template body topology), source capture, fps
    template.ply       frame-1 mesh of body + garments: labels, boundary flags, UVs
    skinning.npz       body-part skinning weights [Nb, B] (transferred, paper A.2), bone names,
                       the capture's frame-1 pose (rotations [B, 3], root translation [3])
    material.json      garment material (fit-physics output, or a simulator preset)
    texture.png        albedo atlas (sRGB), texture_linear.npy the same in linear float32
    light.json         fitted lights (optional)

``stages.avatar.build_avatar`` assembles one from a capture and the stage outputs; ``Avatar.load``
validates it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..body import BodyShape
from ..capture import Template, template_rest
from ..errors import PhysavatarError
from ..files import load_npz, read_json, read_ply
from ..sim import Material

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
        template = Template(ply.vertices, ply.faces, labels, boundary, ply.face_uvs,
                            template_rest(ply, labels, root / "template.ply"))
        z = load_npz(root / "skinning.npz")
        W = z["weights"].astype(np.float64)
        if W.shape[0] != int((labels == 0).sum()):
            raise PhysavatarError(root / "skinning.npz", f"weights for {W.shape[0]} vertices, template body has {int((labels == 0).sum())}")
        tex = None
        if (root / "texture_linear.npy").exists():
            tex = np.load(root / "texture_linear.npy").astype(np.float32)
        elif (root / "texture.png").exists():
            from ..render import read_png, srgb_to_linear

            tex = srgb_to_linear(read_png(root / "texture.png")[..., :3].astype(np.float32) / 255.0)
        return Avatar(root, meta, template, W, [str(b) for b in z["bone_names"]], z["rest_rotations"],
                      z["rest_translation"], Material.load(root / "material.json"), tex,
                      (root / "light.json") if (root / "light.json").exists() else None)
