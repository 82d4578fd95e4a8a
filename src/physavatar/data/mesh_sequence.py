"""Animated meshes from files: an .npz of frames or a folder of OBJ/PLY frames (a collider body
for ``physavatar simulate``, another tool's animation)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import PhysavatarError
from ..files import load_npz, read_ply
from .garment_sequence import GarmentSequence


def load_mesh_sequence(path) -> tuple[np.ndarray, np.ndarray]:
    """An animated mesh [T, V, 3] + faces [F, 3]: an .npz (``vertices``, ``faces``; or the body of a
    garment sequence, ``body_vertices``, ``body_faces``, as ``simulate`` writes it) or a folder of
    OBJ/PLY files, one per frame in name order, all with the same topology."""
    import trimesh

    path = Path(path)
    if path.is_file() and path.suffix == ".npz":
        z = load_npz(path)
        if "body_vertices" in z and "body_faces" in z:  # a garment sequence: its body
            seq = GarmentSequence.from_arrays(z, path)
            z = {"vertices": seq.body_vertices, "faces": seq.body_faces}
        if "vertices" not in z or "faces" not in z:
            raise PhysavatarError(path, "needs arrays 'vertices' [T, V, 3] and 'faces' [F, 3]")
        V, F = np.asarray(z["vertices"], np.float64), np.asarray(z["faces"], np.int64)
        if V.ndim != 3 or V.shape[2] != 3 or F.ndim != 2 or F.shape[1] != 3:
            raise PhysavatarError(path, f"vertices must be [T, V, 3] and faces [F, 3], got {V.shape} and {F.shape}")
    elif path.is_dir():
        files = sorted(p for p in path.iterdir() if p.suffix.lower() in (".obj", ".ply"))
        if len(files) < 2:
            raise PhysavatarError(path, "needs at least two .obj or .ply frames")
        frames, F = [], None
        for p in files:
            if p.suffix.lower() == ".ply":
                m = read_ply(p)
                v, f = m.vertices, m.faces
            else:
                try:
                    t = trimesh.load(p, process=False, force="mesh")
                except Exception as e:
                    raise PhysavatarError(p, f"not a readable OBJ ({type(e).__name__})") from None
                v, f = np.asarray(t.vertices, np.float64), np.asarray(t.faces, np.int64)
            if F is None:
                F = f
            elif f.shape != F.shape or not np.array_equal(f, F):
                raise PhysavatarError(p, "topology differs from the first frame (every frame needs the same faces)")
            if frames and v.shape != frames[0].shape:
                raise PhysavatarError(p, f"has {len(v)} vertices, the first frame {len(frames[0])}")
            frames.append(v)
        V = np.stack(frames)
    else:
        raise PhysavatarError(path, "not found (expected an .npz or a folder of .obj/.ply frames)")
    if not np.isfinite(V).all():
        raise PhysavatarError(path, "vertex positions contain NaN or infinite values")
    if F.min() < 0 or F.max() >= V.shape[1]:
        raise PhysavatarError(path, "face indices out of range")
    return V, F
