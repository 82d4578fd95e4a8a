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
                     callback=None, **options) -> np.ndarray:
    """Simulate ``part`` on a body sequence [T, Nb, 3] starting at rest; returns [T, N, 3].

    Frame 0 of the body must be the pose the garment was made for (its rest state). Boundary
    vertices follow the body surface point they start on. ``options``: more of
    :func:`physavatar.sim.simulate`'s (max_substeps, resume, on_frame).
    """
    body_sequence = np.asarray(body_sequence, dtype=np.float64)
    att = make_attachment(part.vertices[part.boundary], part.boundary, body_sequence[0], body_faces, "sequence")
    targets = attachment_positions(att, body_sequence)
    return simulate(part.vertices, part.faces, material, body_sequence, body_faces,
                    boundary_indices=part.boundary, boundary_targets=targets, fps=fps, substeps=substeps,
                    settings=settings, progress=progress, callback=callback, **options)



def simulate_on_body_job(part: GarmentPart, body_sequence: np.ndarray, body_faces: np.ndarray, material: Material,
                         fps: float, settings: SimSettings | None = None, send_frames: bool = False,
                         report=None) -> np.ndarray:
    """:func:`simulate_on_body` as a :class:`physavatar.parallel.Job`: ``report(1)`` per frame,
    with ``(frame, positions)`` as the item when ``send_frames``."""
    cb = None if report is None else (
        (lambda f, x, st: report(1, (f, x.copy()))) if send_frames else (lambda f, x, st: report(1)))
    return simulate_on_body(part, body_sequence, body_faces, material, fps, settings=settings, callback=cb)
