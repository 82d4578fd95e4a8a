"""A capture's ``ground_truth/`` folder (docs/capture-format.md): what each stage and the
evaluation read from it, checked by ``physavatar inspect``.

Every file is optional; a file that is there must be what its readers expect, so a capture made
by another tool fails in ``inspect`` with one line per problem and not in the middle of a run.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..camera import Camera
from ..errors import PhysavatarError
from ..files import load_npz, read_json

# file -> what it is (the table of docs/capture-format.md)
FILES = {
    "meshes.npz": "vertices [T, V, 3] of the capture's frames in the template's vertex order (+ faces)",
    "material.json": "the garment's material in this simulator's terms (sim.Material JSON)",
    "lighting.json": "the studio lights (light JSON, render/lights.py)",
    "texture_linear.npy": "the true albedo atlas [H, W, 3], linear RGB, on the template's UVs",
    "heldout/motion.npz": "the held-out motion (body.Motion npz)",
    "heldout/meshes.npz": "vertices [T', V, 3] of the held-out motion",
    "heldout/cameras.json": "held-out cameras (cameras.json format) with images/ and masks/ per frame",
}


def _vertices(path: Path, frames: int | None, n_vertices: int) -> tuple[int | None, str | None]:
    try:
        z = load_npz(path)
    except PhysavatarError as e:
        return None, e.problem
    if "vertices" not in z:
        return None, "no 'vertices' array"
    V = z["vertices"]
    if V.ndim != 3 or V.shape[1:] != (n_vertices, 3):
        return None, f"vertices have shape {tuple(V.shape)}, the template needs [T, {n_vertices}, 3]"
    if frames is not None and len(V) != frames:
        return None, f"{len(V)} frames of vertices, the capture has {frames}"
    if not np.isfinite(V).all():
        bad = np.flatnonzero(~np.isfinite(V).reshape(len(V), -1).all(axis=1))
        return None, f"NaN or infinite vertices in {len(bad)} frame(s) (first: {int(bad[0])})"
    return len(V), None


def ground_truth_problems(cap) -> list[tuple[Path, str]]:
    """(path, problem) for every file of ``cap.ground_truth`` that its readers would refuse."""
    from ..body import Motion
    from ..render.lights import load_lights
    from ..sim import Material

    root = cap.ground_truth
    if root is None:
        return []
    out: list[tuple[Path, str]] = []
    nv = len(cap.template.vertices)
    f = root / "meshes.npz"
    if f.exists():
        _, problem = _vertices(f, len(cap.frames), nv)
        if problem:
            out.append((f, problem))
    for name, load in (("material.json", Material.load), ("lighting.json", load_lights)):
        if (root / name).exists():
            try:
                load(root / name)
            except PhysavatarError as e:
                out.append((root / name, e.problem))
            except Exception as e:  # a reader's own complaint about a malformed file
                out.append((root / name, f"unreadable ({type(e).__name__}: {e})"))
    tex = root / "texture_linear.npy"
    if tex.exists():
        try:
            T = np.load(tex, mmap_mode="r")
            if T.ndim != 3 or T.shape[2] != 3 or not np.isfinite(T).all():
                out.append((tex, f"must be a finite [H, W, 3] array, got shape {tuple(T.shape)}"))
        except Exception as e:
            out.append((tex, f"unreadable ({type(e).__name__})"))
    held = root / "heldout"
    if held.is_dir():
        out += _heldout_problems(held, nv, Motion)
    return out


def _heldout_problems(held: Path, nv: int, Motion) -> list[tuple[Path, str]]:
    out = []
    frames = None
    if (held / "motion.npz").exists():
        try:
            frames = Motion.load(held / "motion.npz").frames
        except PhysavatarError as e:
            out.append((held / "motion.npz", e.problem))
        except Exception as e:
            out.append((held / "motion.npz", f"unreadable motion ({type(e).__name__}: {e})"))
    elif (held / "meshes.npz").exists():
        out.append((held / "motion.npz", "missing: held-out meshes need the motion that made them"))
    n = None
    if (held / "meshes.npz").exists():
        n, problem = _vertices(held / "meshes.npz", frames, nv)
        if problem:
            out.append((held / "meshes.npz", problem))
    cams_file = held / "cameras.json"
    if cams_file.exists():
        try:
            cams = [Camera.from_dict(c) for c in read_json(cams_file)]
        except PhysavatarError as e:
            return out + [(cams_file, e.problem)]
        except Exception as e:
            return out + [(cams_file, f"malformed cameras ({type(e).__name__}: {e})")]
        for cam in cams:
            for kind in ("images", "masks"):
                folder = held / kind / cam.name
                count = len(list(folder.glob("*.png"))) if folder.is_dir() else 0
                if n is not None and count < n:
                    out.append((folder, f"{count} of {n} held-out frames' {kind} for camera {cam.name!r}"))
    return out
