"""A garment file (OBJ, PLY, glTF, npz: garment.files) made ready to simulate on an Anny body:
read, fitted onto the body's rest pose (garment_sim.fit_on_body) unless it is already there, and
given its boundary (the file's flags, the automatic choice, or none). Shared by ``simulate
--garment FILE`` and ``animate --garment FILE`` (which replaces the avatar's own garment)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..garment.boundary import arm_vertices, auto_boundary
from ..garment.files import load_garment
from ..garment_sim import GarmentPart, fit_on_body


def file_on_body(path: Path, body, mat, sim_settings, *, up=None, scale="1", rest=None, boundary="auto", fit=True,
                 fit_frames: int = 20, fit_hold: int = 10, repair_limit: float = 0.03, progress=None):
    """(GarmentPart on ``body``'s rest pose, import report) of the garment file ``path``: fitted
    (garment_sim.fit_on_body, with ``mat`` and ``sim_settings``) unless ``fit`` is off (the file
    is already on that pose); its boundary from the file, chosen automatically, or none."""
    gm = load_garment(path, up=up, scale=scale, rest=rest)
    part, imported = garment_part(gm, path)
    if fit:
        part, imported["fit"] = fit_on_body(gm, body, mat, sim_settings, frames=fit_frames, hold=fit_hold,
                                            repair_limit=repair_limit, progress=progress)
    part.boundary, imported["boundary"] = choose_boundary(gm, part.vertices, body.rest_vertices, body.faces, boundary,
                                                          avoid=arm_vertices(body))
    return part, imported


def garment_part(gm, path: Path):
    """(GarmentPart as the file places it, without boundary; the import report) of a loaded garment file."""
    part = GarmentPart(np.arange(len(gm.vertices)), gm.vertices, gm.faces, np.zeros(0, np.int64), gm.rest, gm.seams)
    return part, {"file": str(path), "rest_source": gm.rest_source, "vertices": len(gm.vertices),
                  "seam_pairs": len(gm.seams), "repairs": gm.repairs}


def choose_boundary(gm, vertices, body_vertices, body_faces, boundary: str = "auto", avoid=None):
    """(boundary ids, report): the file's flags, the automatic choice (not on ``avoid``: the arms
    of an Anny body, garment.boundary), or none (``boundary``: auto|none)."""
    if boundary == "none":
        return np.zeros(0, np.int64), {"rule": "none: held by contact and friction alone", "vertices": 0}
    if gm.boundary is not None and len(gm.boundary):
        return gm.boundary, {"rule": "the file's boundary flags", "vertices": len(gm.boundary)}
    return auto_boundary(vertices, gm.faces, body_vertices, body_faces, avoid=avoid)
