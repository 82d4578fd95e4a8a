"""``physavatar pose``: an Anny body posed by a motion, written as a mesh sequence (npz + PLY per
frame), the motion and a preview."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from ..body import BodyModel, BodyShape
from ..body.load import load_motion
from ..body.model import TOPOLOGIES
from ..errors import PhysavatarError
from ..files import PlyMesh, save_npz_atomic, write_json_atomic, write_ply
from ..progress import resolve
from .base import option, to_dict


def _shape(text: str) -> BodyShape:
    """'height=0.7,weight=0.4' -> BodyShape (phenotypes in [0, 1])."""
    kw = {}
    for item in filter(None, text.split(",")):
        k, _, v = item.partition("=")
        try:
            kw[k.strip()] = float(v)
        except ValueError:
            raise ValueError(f"{item!r} is not name=value") from None
    return BodyShape(**kw)


@dataclass(frozen=True)
class PoseConfig:
    motion: str = option("walk", "built-in name, .bvh or .npz")
    fps: float = option(25.0, "frames per second")
    duration: float = option(2.0, "seconds (built-in motions)")
    topology: str = option("full", "body topology: full, notoes, collider, coarse, tiny", choices=tuple(TOPOLOGIES))
    shape: str = option("", "phenotypes, e.g. 'height=0.7,weight=0.4' (each in [0, 1])")
    preview: bool = option(True, "also write preview.gif", flag="--preview/--no-preview")


@dataclass
class PoseResult:
    frames: int
    vertices: int
    bones: int
    load_seconds: float
    motion: str
    files: list[str]


def run(*, out: Path, config: PoseConfig, progress=None) -> PoseResult:
    """Pose the body with the motion and write ``out``: body_sequence.npz, meshes/, motion.npz,
    config.json and (with ``preview``) preview.gif."""
    try:
        shape = _shape(config.shape)
    except (TypeError, ValueError) as e:
        raise PhysavatarError(None, f"option --shape: {e}") from None
    t0 = time.time()
    body = BodyModel(shape, topology=config.topology)
    t_load = time.time() - t0
    m = load_motion(config.motion, config.fps, config.duration)
    posed = m.pose(body)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    save_npz_atomic(out / "body_sequence.npz", vertices=posed.vertices.astype("float32"), faces=body.faces,
                    joints=posed.joints.astype("float32"), bone_names=body.bone_names, fps=config.fps,
                    skinning_weights=body.skinning_weights.astype("float32"))
    with resolve(progress).task("writing meshes", total=posed.vertices.shape[0]) as task:
        for t in range(posed.vertices.shape[0]):
            write_ply(out / "meshes" / f"{t:06d}.ply", PlyMesh(posed.vertices[t], body.faces))
            task.advance()
    m.save(out / "motion.npz")
    write_json_atomic(out / "config.json", {"command": "pose", **to_dict(config), "shape": shape.to_dict()})
    files = [f"{out}/body_sequence.npz", f"{out}/meshes/*.ply", f"{out}/motion.npz"]
    if config.preview:
        from ..body.preview import render_frames, write_video

        pv = BodyModel(shape, topology="collider")
        pp = m.pose(pv)
        write_video(out / "preview.gif", render_frames(pp.vertices, pv.faces, pp.joints, pv.parents, title=m.name),
                    config.fps)
        files.append(f"{out}/preview.gif")
    return PoseResult(m.frames, len(body.rest_vertices), len(body.bone_names), t_load, m.name, files)
