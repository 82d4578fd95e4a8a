"""The tracking stage's output, ``tracked.npz``: a labelled mesh sequence.

::

    vertices        [T, V, 3] float32   tracked positions, template vertex order
    faces           [F, 3]              the template's triangles
    labels          [V] uint8           0 body, >= 1 garment
    boundary        [V] uint8           1 = garment vertex attached to the body
    face_colors     [T, F, 3] float32   mean Gaussian colour per face (linear RGB)
    frames          [T] int64           capture frame ids
    log_scales, opacity_logits, edge_index   the first frame's Gaussians (resuming, appearance)
    fps             float64

A capture's ``ground_truth/meshes.npz`` (vertices, faces, labels, fps) and another tool's
sequence are read the same way. Only ``vertices`` is always needed; each reader names the
arrays it uses (``require``), and what is present is checked for consistency.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from ..errors import PhysavatarError
from ..files import load_npz, save_npz_atomic

FILE = "tracked.npz"

# the arrays written, in this order (an absent optional one is left out)
ARRAYS = ("vertices", "faces", "labels", "boundary", "face_colors", "frames", "log_scales", "opacity_logits",
          "edge_index", "fps")


@dataclasses.dataclass(eq=False)  # arrays: compare fields, not objects
class TrackedSequence:
    """A labelled mesh sequence (module docstring). Arrays are as stored except ``faces`` and
    ``labels`` (int64), ``boundary`` (bool flags), ``frames`` (int64) and ``fps`` (float);
    ``path`` is the file it was read from (named by validation errors)."""

    vertices: np.ndarray
    faces: np.ndarray | None = None
    labels: np.ndarray | None = None
    boundary: np.ndarray | None = None
    face_colors: np.ndarray | None = None
    frames: np.ndarray | None = None
    log_scales: np.ndarray | None = None
    opacity_logits: np.ndarray | None = None
    edge_index: np.ndarray | None = None
    fps: float | None = None
    path: Path | None = None

    @classmethod
    def load(cls, path: str | Path, *, require=("vertices",), min_frames: int = 1, finite: bool = True,
             mapped: bool = False) -> "TrackedSequence":
        """``path``: a tracking folder (its ``tracked.npz``) or an .npz file. ``require``: arrays
        that must be present; ``min_frames``: the fewest frames the caller can use. ``finite=False``
        accepts NaN frames (a viewer shows them as missing); ``mapped``: large arrays are memory
        maps (:func:`physavatar.files.load_npz`)."""
        path = Path(path)
        if path.is_dir() or path.suffix != ".npz":  # a folder (named in errors with its file)
            path = path / FILE
        return cls.from_arrays(load_npz(path, mapped=mapped), path, require=require, min_frames=min_frames,
                               finite=finite)

    @classmethod
    def from_arrays(cls, z: dict, path: str | Path | None = None, *, require=("vertices",),
                    min_frames: int = 1, finite: bool = True) -> "TrackedSequence":
        """The sequence of the arrays ``z`` already read from ``path`` (:meth:`load`)."""
        path = None if path is None else Path(path)
        for key in ("vertices", *require):
            if key not in z:
                raise PhysavatarError(path, f"missing array {key!r}")

        def get(key, dtype=None):
            if key not in z:
                return None
            return np.asarray(z[key]) if dtype is None else np.asarray(z[key]).astype(dtype)

        seq = cls(vertices=np.asarray(z["vertices"]), faces=get("faces", np.int64), labels=get("labels", np.int64),
                  boundary=get("boundary", bool), face_colors=get("face_colors"), frames=get("frames", np.int64),
                  log_scales=get("log_scales"), opacity_logits=get("opacity_logits"), edge_index=get("edge_index"),
                  fps=float(z["fps"]) if "fps" in z else None, path=path)
        seq.validate(min_frames, finite=finite)
        return seq

    @property
    def n_frames(self) -> int:
        return len(self.vertices)

    def validate(self, min_frames: int = 1, finite: bool = True) -> None:
        """Shapes and lengths agree (and the vertices are finite with ``finite``); raises
        :class:`PhysavatarError` naming :attr:`path`."""
        path, V = self.path, np.asarray(self.vertices)
        n = len(np.atleast_1d(self.labels)) if self.labels is not None else (V.shape[1] if V.ndim == 3 else None)
        if V.ndim != 3 or V.shape[2] != 3 or V.shape[1] != n or len(V) < min_frames:
            what = f"V={n}" if self.labels is not None else "V"
            raise PhysavatarError(path, f"vertices must be [T >= {min_frames}, {what}, 3], got {V.shape}")
        T, n = V.shape[:2]
        F = self.faces
        if F is not None and (F.ndim != 2 or F.shape[1] != 3 or (F.size and (F.min() < 0 or F.max() >= n))):
            raise PhysavatarError(path, "faces must be [F, 3] indices into the vertices")
        if finite and not np.all(np.isfinite(V)):
            raise PhysavatarError(path, "vertices contain non-finite values")
        if self.boundary is not None and len(self.boundary) != n:
            raise PhysavatarError(path, f"boundary has {len(self.boundary)} flags for {n} vertices")
        C = self.face_colors
        if C is not None:
            C = np.asarray(C)
            nf = len(F) if F is not None else (C.shape[1] if C.ndim == 3 else None)
            if C.ndim != 3 or C.shape != (T, nf, 3):
                raise PhysavatarError(path, f"face_colors must be [T={T}, F={'F' if nf is None else nf}, 3], "
                                            f"got {C.shape}")
        if self.frames is not None and np.shape(self.frames) != (T,):
            raise PhysavatarError(path, f"frames has shape {np.shape(self.frames)} for {T} frames of vertices")
        if self.fps is not None and not self.fps > 0:
            raise PhysavatarError(path, f"fps must be positive, got {self.fps}")

    def save(self, path: str | Path) -> Path:
        """Write atomically (vertices and colours float32, labels and boundary uint8); NaN frames
        are written as they are (the reader refuses them)."""
        path = Path(path)
        self.validate(finite=False)
        dtypes = {"vertices": np.float32, "faces": np.int64, "labels": np.uint8, "boundary": np.uint8,
                  "face_colors": np.float32, "frames": np.int64, "fps": np.float64}
        arrays = {}
        for key in ARRAYS:
            value = getattr(self, key)
            if value is not None:
                arrays[key] = np.asarray(value, dtypes[key]) if key in dtypes else np.asarray(value)
        save_npz_atomic(path, **arrays)
        return path
