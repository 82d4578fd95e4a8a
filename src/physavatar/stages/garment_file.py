"""A garment file (OBJ, PLY, glTF, npz: garment.files) made ready to simulate on an Anny body:
read, fitted onto the body's rest pose (garment_sim.fit_on_body) unless it is already there, and
given its boundary (the file's flags, the automatic choice, or none). Shared by ``simulate
--garment FILE`` and ``animate --garment FILE`` (which replaces the avatar's own garment)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..errors import PhysavatarError
from ..garment.boundary import arm_vertices, auto_boundary
from ..garment.files import load_garment
from ..garment_sim import GarmentPart, fit_on_body
from .base import option, setting

PLACEMENT = ("up", "scale", "rest", "boundary", "fit", "repair_limit", "fit_frames", "fit_hold")


def nonnegative(v):
    """An option check: None when ``v`` >= 0, else the problem."""
    return None if v >= 0 else "must be >= 0"


@dataclass(frozen=True)
class GarmentFileOptions:
    """How a garment file (``--garment FILE``) is read and put on the body: the options that
    ``simulate`` and ``animate`` share (their configs derive from this class)."""

    up: str | None = option(None, "a garment file's up axis: x, y, z, -x, -y, -z (default z; y for glTF)",
                            choices=("x", "y", "z", "-x", "-y", "-z"))
    scale: str = option("1", "a garment file's scale: a factor or its unit (m, cm, mm, in)")
    rest: str | None = option(None, "a garment file's rest shape: a file with the same triangles, 'uv' or 'world' "
                                    "(default: NAME-m.obj beside NAME-w.obj, else material uv, else the world shape)")
    boundary: str = option("auto", "a garment file's attached vertices: auto (the file's flags, else where it rests "
                                   "on the body: waistband, shoulders) or none (held by contact and friction alone)",
                           choices=("auto", "none"))
    fit: bool = option(True, "fit a garment file onto the body's rest pose (align, then settle while the body grows "
                             "from a shrunk one); off: it is already on that pose")
    repair_limit: float = option(0.03, "largest move [m] the start repair may make to push the garment out of "
                                       "the body (beyond it the start is refused)", flag="--repair-limit",
                                 check=nonnegative)
    fit_frames: int = setting(20)  # frames of the body growing to full size while fitting
    fit_hold: int = setting(10)  # frames the fitted garment settles on the full body

    def placement(self) -> dict:
        """These options as keyword arguments of :func:`file_on_body`."""
        return {k: getattr(self, k) for k in PLACEMENT}


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


def repaired_start(part, body_vertices, body_faces, dhat: float, limit: float, source):
    """(``part`` with its start pushed out of the body's first frame to >= d̂, the repair's report)
    (sim.start.repair_start); refused beyond ``limit`` (--repair-limit), or when the garment is
    nowhere near the body (nothing would hold it)."""
    from ..geometry import MeshQuery
    from ..sim.start import repair_start

    d = MeshQuery(body_vertices, body_faces).closest(part.vertices, max_dist=0.1)[0]
    if d.min() > 0.05:
        raise PhysavatarError(source, f"the garment is {d.min() * 100:.0f} cm from the body's first frame at its "
                                      "closest: nothing holds it (place it on the body, or give --motion to fit it "
                                      "onto Anny)")
    try:
        x, report = repair_start(part.vertices, part.faces, body_vertices, body_faces, dhat, limit, seams=part.seams)
    except PhysavatarError as e:
        raise PhysavatarError(source, f"{e.problem} (--repair-limit)") from None
    return replace(part, vertices=x), report
