"""A motion from a name or a file: the built-in motions (``motion``), ``.npz`` motions and ``.bvh``
motion capture retargeted to Anny (``bvh``). Sits above both, so neither imports the other's way
back."""

from __future__ import annotations

from pathlib import Path

from ..errors import PhysavatarError
from .bvh import import_bvh
from .motion import BUILTIN, Motion, builtin_motion


def load_motion(spec: str, bone_names: list[str], fps: float = 25.0, duration: float = 4.0) -> Motion:
    """A motion by built-in name, ``.npz`` file or ``.bvh`` file, resampled to ``fps``."""
    if spec in BUILTIN:
        return builtin_motion(spec, bone_names, fps, duration)
    path = Path(spec)
    if path.suffix.lower() == ".bvh":
        return import_bvh(path).resample(fps).for_bones(bone_names)
    if path.suffix.lower() == ".npz":
        return Motion.load(path).resample(fps).for_bones(bone_names)
    if not path.exists():
        raise PhysavatarError(path, f"not a built-in motion ({', '.join(BUILTIN)}) and no such file")
    raise PhysavatarError(path, "motion files must be .npz or .bvh")
