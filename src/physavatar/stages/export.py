"""``physavatar export``: an animate output as USD (time-sampled points, UVs, textured material),
glTF binary (morph targets) or OBJ/PLY sequences (the writers are :mod:`physavatar.export`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ..data.animated import AnimatedSequence
from ..errors import PhysavatarError
from ..export import MeshSequence, export
from .base import option

_SUFFIX_FORMAT = {".usd": "usd", ".usdc": "usd", ".usda": "usd", ".glb": "glb"}


@dataclass(frozen=True)
class ExportConfig:
    format: str = option("", "usd, glb, obj or ply (default: from --out's extension)")


def run(sequence: Path, *, out: Path, config: ExportConfig = ExportConfig(), progress=None) -> Path:
    """Write the sequence folder ``sequence`` to ``out`` (a file for usd/glb, a folder for obj/ply);
    returns the path written (``.usdc`` / ``.glb`` appended when ``out`` lacks the suffix)."""
    s = AnimatedSequence.load(sequence)
    out = Path(out)
    fmt = config.format or _SUFFIX_FORMAT.get(out.suffix.lower(), "")
    if fmt not in ("usd", "glb", "obj", "ply"):
        raise PhysavatarError(None, "option --format: choose usd, glb, obj or ply (or give --out a .usd/.glb name)")
    if fmt == "usd" and out.suffix.lower() not in (".usd", ".usdc", ".usda"):
        out = out.with_suffix(".usdc")
    if fmt == "glb" and out.suffix.lower() != ".glb":
        out = out.with_suffix(".glb")
    tex = None
    if s.avatar is not None and (Path(s.avatar) / "texture.png").exists():
        tex = Path(s.avatar) / "texture.png"
    export(out, MeshSequence(s.vertices, s.faces, uvs=s.face_uvs, texture=tex, fps=s.fps), fmt)
    return out
