"""Per-frame meshes and body-parameter files that come with a source.

Mesh files (OBJ, PLY, OFF, GLB) are read with trimesh, without processing (vertex order and count
as in the file, so per-vertex labels stay aligned). Pickled meshes (4D-DRESS) are read with a
restricted unpickler that builds only numpy arrays and plain containers: a pickle can run code
when loaded, and a dataset file must not.
"""

from __future__ import annotations

import io
import pickle
from functools import partial
from pathlib import Path

import numpy as np

from ..errors import PhysavatarError
from .common import numbered_files

MESH_SUFFIXES = (".obj", ".ply", ".off", ".glb", ".gltf", ".stl")


def _load_trimesh(path: Path):
    import trimesh

    try:
        m = trimesh.load(path, force="mesh", process=False)
    except Exception as e:
        raise PhysavatarError(path, f"not a readable mesh ({type(e).__name__}: {e})") from None
    v, f = np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)
    if len(v) == 0 or len(f) == 0:
        raise PhysavatarError(path, "mesh has no vertices or no faces")
    data = {}
    if getattr(m.visual, "kind", None) == "vertex":
        c = np.asarray(m.visual.vertex_colors)
        if c.shape[0] == len(v):
            data = {"red": c[:, 0].astype(np.uint8), "green": c[:, 1].astype(np.uint8), "blue": c[:, 2].astype(np.uint8)}
    return v, f, data


def mesh_files(folder: Path) -> dict:
    """Frame id -> loader of every mesh file in ``folder`` (frame id = the last number of the name)."""
    return {f: partial(_load_trimesh, p) for f, p in numbered_files(folder, MESH_SUFFIXES).items()}


class _SafeUnpickler(pickle.Unpickler):
    ALLOWED = {
        ("numpy", "ndarray"), ("numpy", "dtype"), ("numpy.core.multiarray", "_reconstruct"),
        ("numpy._core.multiarray", "_reconstruct"), ("numpy.core.multiarray", "scalar"),
        ("numpy._core.multiarray", "scalar"), ("collections", "OrderedDict"), ("builtins", "set"),
        ("builtins", "frozenset"), ("builtins", "complex"), ("_codecs", "encode"),
    }

    def find_class(self, module, name):
        if (module, name) in self.ALLOWED:
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"refusing to load {module}.{name} (only numpy arrays and plain containers)")


def load_pickle(path: Path):
    """A pickle holding only numpy arrays, numbers, strings and containers (latin1 for Python 2 pickles)."""
    if not path.is_file():
        raise PhysavatarError(path, "file not found")
    try:
        return _SafeUnpickler(io.BytesIO(path.read_bytes()), encoding="latin1").load()
    except Exception as e:
        raise PhysavatarError(path, f"not a readable pickle of arrays ({type(e).__name__}: {e})") from None
