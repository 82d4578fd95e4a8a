"""A garment simulated on a moving body: ``garment_sequence.npz``.

``physavatar simulate`` writes it and any cloth simulator can::

    vertices        [T, N, 3] float32   the garment, T >= 2
    faces           [F, 3]              garment triangles
    boundary        [K] ids or [N] flags   the attached (Dirichlet) vertices; none = held by
                                        contact alone (read by :func:`boundary_ids`)
    body_vertices   [T, Nb, 3] float32  the collider (optional, with body_faces)
    body_faces      [Fb, 3]
    fps             float64             default 25
    rest_vertices   [N, 3] float32      the stress-free shape (default: frame 0)
    seams           [S, 2] int64        vertex pairs sewn together (optional: a garment sewn
                                        from panels, garment.files; held by sim.stitch)

fit-physics fits to it, ``simulate --collider`` takes its body and ``simulate --garment`` its rest
shape, boundary and seams.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from ..errors import PhysavatarError
from ..files import load_npz, save_npz_atomic

FILE = "garment_sequence.npz"


def boundary_ids(values, n: int) -> np.ndarray:
    """Boundary (attached) vertices as sorted ids, from per-vertex flags [n] (bool or 0/1) or from
    vertex ids [K]. Out-of-range ids raise ValueError (callers name their file)."""
    b = np.asarray(values).ravel()
    if b.dtype == bool or (len(b) == n and set(np.unique(b).tolist()) <= {0, 1}):
        b = np.flatnonzero(b)
    b = np.unique(b.astype(np.int64))
    if len(b) and (b[0] < 0 or b[-1] >= n):
        raise ValueError(_boundary_problem(n))
    return b


def _boundary_problem(n: int) -> str:
    return f"boundary must be {n} flags or ids into the {n} garment vertices"


@dataclasses.dataclass(eq=False)  # arrays: compare fields, not objects
class GarmentSequence:
    """A garment sequence (module docstring): positions float64, faces and boundary ids int64;
    ``rest_vertices`` defaults to frame 0. ``path``: the file it was read from (named by errors)."""

    vertices: np.ndarray
    faces: np.ndarray
    boundary: np.ndarray
    body_vertices: np.ndarray | None = None
    body_faces: np.ndarray | None = None
    fps: float = 25.0
    rest_vertices: np.ndarray | None = None
    path: Path | None = None
    seams: np.ndarray | None = None

    def __post_init__(self):
        if self.rest_vertices is None and np.ndim(self.vertices) == 3 and len(self.vertices):
            self.rest_vertices = np.asarray(self.vertices[0])

    @classmethod
    def load(cls, path: str | Path, *, finite: bool = True, mapped: bool = False) -> "GarmentSequence":
        """``path``: an .npz file, or a folder holding ``garment_sequence.npz``. ``finite=False``
        accepts NaN frames (a viewer shows them as missing); ``mapped``: the large arrays stay as
        stored (float32), memory-mapped (:func:`physavatar.files.load_npz`)."""
        path = Path(path)
        if path.is_dir() or path.suffix != ".npz":  # a folder (named in errors with its file)
            path = path / FILE
        return cls.from_arrays(load_npz(path, mapped=mapped), path, finite=finite, as_stored=mapped)

    @classmethod
    def from_arrays(cls, z: dict, path: str | Path | None = None, *, finite: bool = True,
                    as_stored: bool = False) -> "GarmentSequence":
        """The sequence of the arrays ``z`` already read from ``path``; ``as_stored`` keeps the
        positions' dtype (no float64 copy)."""
        pos = np.asarray if as_stored else (lambda a: np.asarray(a, np.float64))
        path = None if path is None else Path(path)
        for key in ("vertices", "faces"):
            if key not in z:
                raise PhysavatarError(path, f"missing array {key!r} (a garment sequence needs vertices [T, N, 3] and faces)")
        V = pos(z["vertices"])
        F = np.asarray(z["faces"], np.int64)
        _check_garment(path, V, F, finite=finite)
        n = V.shape[1]
        try:
            b = boundary_ids(z["boundary"], n) if "boundary" in z else np.zeros(0, np.int64)
        except ValueError as e:
            raise PhysavatarError(path, str(e)) from None
        rest = pos(z["rest_vertices"]) if "rest_vertices" in z else V[0]
        body = body_faces = None
        if "body_vertices" in z:
            body = pos(z["body_vertices"])
            body_faces = np.asarray(z["body_faces"], np.int64) if "body_faces" in z else None
        seams = np.asarray(z["seams"], np.int64).reshape(-1, 2) if "seams" in z else None
        seq = cls(V, F, b, body, body_faces, float(z["fps"]) if "fps" in z else 25.0, rest, path=path, seams=seams)
        seq.validate(finite=finite)
        return seq

    @property
    def n_frames(self) -> int:
        return len(self.vertices)

    def validate(self, finite: bool = True) -> None:
        """Shapes, indices and lengths agree (and the frames are finite with ``finite``); raises
        :class:`PhysavatarError` naming :attr:`path`."""
        path, V = self.path, np.asarray(self.vertices)
        _check_garment(path, V, np.asarray(self.faces), finite)
        T, n = V.shape[:2]
        b = np.asarray(self.boundary)
        if b.ndim != 1 or (len(b) and (b.min() < 0 or b.max() >= n)):
            raise PhysavatarError(path, _boundary_problem(n))
        rest = np.asarray(self.rest_vertices)
        if rest.shape != (n, 3) or not np.all(np.isfinite(rest)):
            raise PhysavatarError(path, f"rest_vertices must be [{n}, 3] finite, got {rest.shape}")
        if self.body_vertices is not None:
            if self.body_faces is None:
                raise PhysavatarError(path, "body_vertices without body_faces")
            body, body_faces = np.asarray(self.body_vertices), np.asarray(self.body_faces)
            if body.ndim != 3 or body.shape[0] != T or body.shape[2] != 3:
                raise PhysavatarError(path, f"body_vertices must be [T={T}, Nb, 3], got {body.shape}")
            if body_faces.ndim != 2 or body_faces.shape[1] != 3 or len(body_faces) == 0 or body_faces.min() < 0 \
                    or body_faces.max() >= body.shape[1]:
                raise PhysavatarError(path, "body_faces must be [F, 3] indices into the body vertices")
            if finite and not np.all(np.isfinite(body)):
                raise PhysavatarError(path, "body_vertices contain non-finite values")
        if not self.fps > 0:
            raise PhysavatarError(path, f"fps must be positive, got {self.fps}")
        if self.seams is not None:
            sm = np.asarray(self.seams)
            if sm.ndim != 2 or sm.shape[1] != 2 or (len(sm) and (sm.min() < 0 or sm.max() >= n)):
                raise PhysavatarError(path, f"seams must be [S, 2] pairs of the {n} garment vertices, got {sm.shape}")

    def save(self, path: str | Path) -> Path:
        """Write atomically (positions float32, boundary as ids); frames that are not finite are
        written as they are (``simulate`` reports them, the reader refuses them)."""
        path = Path(path)
        self.validate(finite=False)
        arrays = {"vertices": np.asarray(self.vertices, np.float32), "faces": self.faces, "boundary": self.boundary}
        if self.body_vertices is not None:
            arrays |= {"body_vertices": np.asarray(self.body_vertices, np.float32), "body_faces": self.body_faces}
        arrays |= {"fps": np.float64(self.fps), "rest_vertices": np.asarray(self.rest_vertices, np.float32)}
        if self.seams is not None and len(self.seams):
            arrays["seams"] = np.asarray(self.seams, np.int64)
        save_npz_atomic(path, **arrays)
        return path


def _check_garment(path, V: np.ndarray, F: np.ndarray, finite: bool) -> None:
    if V.ndim != 3 or V.shape[2] != 3 or len(V) < 2:
        raise PhysavatarError(path, f"vertices must be [T >= 2, N, 3], got {V.shape}")
    n = V.shape[1]
    if F.ndim != 2 or F.shape[1] != 3 or len(F) == 0 or F.min() < 0 or F.max() >= n:
        raise PhysavatarError(path, f"faces must be [F, 3] indices into the {n} garment vertices")
    if finite and not np.all(np.isfinite(V)):
        raise PhysavatarError(path, "vertices contain non-finite values")
