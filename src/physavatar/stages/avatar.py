"""``physavatar build-avatar``: the avatar folder (data.avatar) from a capture and the stage
outputs: the template (or the tracked frame 1), skinning weights transferred from Anny posed at
frame 1 (paper A.2), the fitted material, the texture and light."""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..body import BodyModel, Motion
from ..body.transfer import transfer_skinning_weights
from ..capture import Capture, Template, load_capture
from ..data.avatar import AVATAR_VERSION, Avatar
from ..data.material import material_file, resolve_material
from ..data.tracked import TrackedSequence
from ..files import load_npz, save_npz_atomic, write_json_atomic
from ..geometry import submesh
from ..sim import Material


@dataclass(frozen=True)
class AvatarConfig:
    """build-avatar has no settings of its own: its inputs (capture, material, appearance,
    tracked) say everything."""


def run(capture: Path, *, out: Path, config: AvatarConfig = AvatarConfig(), material: str | Path,
        appearance: Path | None = None, tracked: Path | None = None, progress=None) -> Avatar:
    """The avatar folder ``out``. ``material``: fit-physics output (its folder or material.json) or a
    preset name; ``appearance``: fit-appearance output; ``tracked``: tracking output, whose frame 1
    replaces the capture's template positions."""
    tv = None
    if tracked is not None:
        tv = TrackedSequence.load(tracked, require=("vertices",)).vertices[0]
    if not isinstance(material, Material) and Path(material).is_dir():
        material = material_file(material)
    return build_avatar(capture, out, material=material, texture_dir=appearance, template_vertices=tv)


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
        t = Template(np.asarray(template_vertices, np.float64), t.faces, t.labels, t.boundary, t.face_uvs, t.rest)
    if texture_dir is not None and (Path(texture_dir) / "atlas.npz").exists():
        # the texture was fitted on this atlas (made by xatlas when the capture's template has
        # no UVs): the avatar must carry the same UVs as its texture
        uv = load_npz(Path(texture_dir) / "atlas.npz").get("face_uvs")
        if uv is not None and uv.shape == (len(t.faces), 3, 2):
            t = Template(t.vertices, t.faces, t.labels, t.boundary, np.asarray(uv, np.float64), t.rest)
    t.save(out / "template.ply")
    resolve_material(material).save(out / "material.json")

    # Skinning weights of the template's body part, transferred from Anny posed at frame 1.
    body = BodyModel(cap.body.shape, topology=cap.body.topology)
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
