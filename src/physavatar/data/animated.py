"""An animated avatar, the ``animate`` folder (also ``reference-sims``' true/ and random/)::

    sequence.npz    vertices [T, V, 3] float32 (template order), faces [F, 3], labels [V] uint8,
                    fps float64, face_uvs [F, 3, 2] float32 (when the avatar has UVs)
    sequence.json   what made it (command, motion, material, timings), "avatar": the avatar folder,
                    "frames", "fps"
    meshes/         one PLY per frame (label per vertex, UVs)

``render``, ``export`` and ``evaluate --sequence`` read it.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from ..errors import PhysavatarError
from ..files import PlyMesh, load_npz, read_json, save_npz_atomic, write_json_atomic, write_ply

NPZ = "sequence.npz"
META = "sequence.json"


@dataclasses.dataclass(eq=False)  # arrays: compare fields, not objects
class AnimatedSequence:
    """An animated avatar: vertices [T, V, 3] in template order, with what rendering needs.
    ``avatar``: the avatar folder it animates (its texture and light), when known."""

    vertices: np.ndarray
    faces: np.ndarray
    labels: np.ndarray
    face_uvs: np.ndarray | None
    fps: float
    avatar: Path | None = None

    def save(self, out: str | Path, meta: dict, ply: bool = True) -> None:
        """``out``/sequence.npz, sequence.json (``meta`` + avatar, frames, fps) and, with ``ply``,
        meshes/<frame>.ply, each written atomically."""
        out = Path(out)
        self.validate(out / NPZ, finite=False)
        out.mkdir(parents=True, exist_ok=True)
        save_npz_atomic(out / NPZ, vertices=self.vertices.astype(np.float32), faces=self.faces,
                        labels=self.labels.astype(np.uint8), fps=np.float64(self.fps),
                        **({"face_uvs": self.face_uvs.astype(np.float32)} if self.face_uvs is not None else {}))
        if ply:
            for t in range(len(self.vertices)):
                write_ply(out / "meshes" / f"{t:06d}.ply", PlyMesh(self.vertices[t], self.faces,
                                                                  {"label": self.labels.astype(np.uint8)}, self.face_uvs))
        write_json_atomic(out / META, {**meta, "avatar": str(self.avatar) if self.avatar else None,
                                       "frames": int(len(self.vertices)), "fps": self.fps})

    @classmethod
    def load(cls, path: str | Path, *, finite: bool = True, mapped: bool = False) -> "AnimatedSequence":
        """The ``animate`` folder ``path``: vertices float64, labels int64. ``finite=False`` accepts
        NaN frames (a viewer shows them as missing); ``mapped``: vertices stay float32, memory-mapped
        (:func:`physavatar.files.load_npz`)."""
        path = Path(path)
        z = load_npz(path / NPZ, mapped=mapped)
        meta = read_json(path / META)
        for key in ("vertices", "faces", "labels", "fps"):
            if key not in z:
                raise PhysavatarError(path / NPZ, f"missing array {key!r}")
        seq = cls(z["vertices"] if mapped else z["vertices"].astype(np.float64), z["faces"], z["labels"].astype(np.int64),
                  z["face_uvs"] if "face_uvs" in z else None, float(z["fps"]),
                  Path(meta["avatar"]) if meta.get("avatar") else None)
        seq.validate(path / NPZ, finite=finite)
        return seq

    def validate(self, path: str | Path | None = None, finite: bool = True) -> None:
        """Shapes and lengths agree (and the vertices are finite with ``finite``); raises
        :class:`PhysavatarError` naming ``path``. Face indices are the avatar's, checked against
        it by whoever pairs the two (``evaluate``)."""
        V, F, L = np.asarray(self.vertices), np.asarray(self.faces), np.asarray(self.labels)
        if V.ndim != 3 or V.shape[2] != 3 or len(V) < 1:
            raise PhysavatarError(path, f"vertices must be [T >= 1, V, 3], got {V.shape}")
        T, n = V.shape[:2]
        if F.ndim != 2 or F.shape[1] != 3:
            raise PhysavatarError(path, f"faces must be [F, 3], got {F.shape}")
        if L.shape != (n,):
            raise PhysavatarError(path, f"labels has shape {L.shape} for {n} vertices")
        if self.face_uvs is not None and np.shape(self.face_uvs) != (len(F), 3, 2):
            raise PhysavatarError(path, f"face_uvs must be [F={len(F)}, 3, 2], got {np.shape(self.face_uvs)}")
        if finite and not np.all(np.isfinite(V)):
            t = int(np.argwhere(~np.isfinite(V))[0, 0])
            raise PhysavatarError(path, f"vertices contain non-finite values (first in frame {t})")
        if not (np.isfinite(self.fps) and self.fps > 0):
            raise PhysavatarError(path, f"fps must be positive, got {self.fps}")
