"""Simulating the garment of a template on a moving body (paper Sec. 3.2, Eq. 5).

The template's garment vertices (label > 0) are the cloth; its boundary vertices are attached to
the body surface they start on (closest point, barycentric coordinates and an offset in the
triangle's frame) and follow it; the body part (label 0), posed per frame, is the collider.
Used by synthetic captures (ground-truth garment motion), ``physavatar simulate`` and animation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .garment import attachment_positions, make_attachment
from .sim import Material, SimSettings, simulate


@dataclass
class GarmentPart:
    """The garment of a template, re-indexed on its own.

    Attributes:
        vertex_ids: [N] template indices of the garment vertices.
        vertices: [N, 3] rest positions. faces: [F, 3] (garment-local indices).
        boundary: [K] garment-local indices of the Dirichlet vertices.
    """

    vertex_ids: np.ndarray
    vertices: np.ndarray
    faces: np.ndarray
    boundary: np.ndarray


def split_template(vertices: np.ndarray, faces: np.ndarray, labels: np.ndarray, boundary: np.ndarray):
    """(body vertex ids [Nb], body faces [Fb, 3] (body-local), GarmentPart) of a labelled mesh."""
    gmask = labels > 0
    body_ids = np.flatnonzero(~gmask)
    gar_ids = np.flatnonzero(gmask)
    remap = -np.ones(len(vertices), np.int64)
    remap[body_ids] = np.arange(len(body_ids))
    remap[gar_ids] = np.arange(len(gar_ids))
    fg = gmask[faces]
    if (fg.any(1) & ~fg.all(1)).any():
        raise ValueError("a face joins body and garment vertices; garments must be separate pieces")
    body_faces = remap[faces[~fg.any(1)]]
    gar_faces = remap[faces[fg.all(1)]]
    part = GarmentPart(gar_ids, vertices[gar_ids].copy(), gar_faces, np.flatnonzero(boundary[gar_ids]))
    return body_ids, body_faces, part


def simulate_on_body(part: GarmentPart, body_sequence: np.ndarray, body_faces: np.ndarray, material: Material,
                     fps: float, settings: SimSettings | None = None, substeps: int = 1, progress: bool = False,
                     callback=None) -> np.ndarray:
    """Simulate ``part`` on a body sequence [T, Nb, 3] starting at rest; returns [T, N, 3].

    Frame 0 of the body must be the pose the garment was made for (its rest state). Boundary
    vertices follow the body surface point they start on.
    """
    body_sequence = np.asarray(body_sequence, dtype=np.float64)
    att = make_attachment(part.vertices[part.boundary], part.boundary, body_sequence[0], body_faces, "sequence")
    targets = attachment_positions(att, body_sequence)
    return simulate(part.vertices, part.faces, material, body_sequence, body_faces,
                    boundary_indices=part.boundary, boundary_targets=targets, fps=fps, substeps=substeps,
                    settings=settings, progress=progress, callback=callback)



def simulate_on_body_job(part: GarmentPart, body_sequence: np.ndarray, body_faces: np.ndarray, material: Material,
                         fps: float, settings: SimSettings | None = None, send_frames: bool = False,
                         report=None) -> np.ndarray:
    """:func:`simulate_on_body` as a :class:`physavatar.parallel.Job`: ``report(1)`` per frame,
    with ``(frame, positions)`` as the item when ``send_frames``."""
    cb = None if report is None else (
        (lambda f, x, st: report(1, (f, x.copy()))) if send_frames else (lambda f, x, st: report(1)))
    return simulate_on_body(part, body_sequence, body_faces, material, fps, settings=settings, callback=cb)


# -- inputs of `physavatar simulate` -----------------------------------------------------------

def load_mesh_sequence(path) -> tuple[np.ndarray, np.ndarray]:
    """An animated mesh [T, V, 3] + faces [F, 3]: an .npz (``vertices``, ``faces``; or the body of a
    garment sequence, ``body_vertices``, ``body_faces``, as ``simulate`` writes it) or a folder of
    OBJ/PLY files, one per frame in name order, all with the same topology."""
    from pathlib import Path

    import trimesh

    from .data.garment_sequence import GarmentSequence
    from .errors import PhysavatarError
    from .files import load_npz, read_ply

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
