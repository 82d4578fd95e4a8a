"""Anny's own pose parameters -> ``body.npz`` in the capture's convention (``--anny FILE``).

Other Anny tools keep a pose as Anny's forward takes it: per bone a 4x4 delta transform in one of
Anny's pose parameterizations (``local-ref`` by default: relative to the bone's *reference*
pose, in world-aligned axes; also ``local-bone``, ``local-bone-world``, ``world-orient``,
``world``), plus the 6 phenotypes. The file read here is an ``.npz`` with

    pose_parameters        [T, B, 4, 4]   Anny's bone order (``bone_labels`` [B] to check it)
    phenotype              [6]            gender, age, muscle, weight, height, proportions in [0, 1]
    pose_parameterization  str            optional, default ``local-ref``
    frames                 [T]            optional source frame ids (default: the source's frames in order)
    topology               str            optional, default ``full``

in the source's world (the world of its cameras, Anny's coordinates without physavatar's floor
offset). Anny's own forward kinematics gives each bone's posed pose ``W_b``; the capture's
convention (docs/capture-format.md, body/model.py) wants world-aligned rotations relative to
*rest*: ``X_b = A·W_b[:3, :3]·R_rest_bᵀ`` (``A``: the import's world rotation), the bone's
rotation ``X_parentᵀ·X_b`` (the root's ``X_0``), and the root translation ``head_0' − h_0 −
(0, 0, floor_offset)`` with ``head_0' = A·head_0 + o``. Anny's reference pose differs from the
rest pose by about a centimetre, which is why deltas cannot be copied as they are. Bones do not
stretch in the capture's convention, so deltas with translations on non-root bones are refused.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..body.model import (
    PHENOTYPES,
    TOPOLOGIES,
    BodyModel,
    BodyShape,
    matrix_to_axis_angle,
)
from ..capture import BodyPoses
from ..errors import PhysavatarError
from ..files import load_npz
from .common import Placement

PARAMETERIZATIONS = ("local-ref", "local-bone", "local-bone-world", "world-orient", "world")


def read_anny_poses(path: Path, source_frames: list[int], frames: list[int], placement: Placement) -> BodyPoses:
    """The body poses of ``frames`` (a subset of ``source_frames``) from an Anny pose file."""
    import torch

    path = Path(path)
    z = load_npz(path)
    if "pose_parameters" not in z or "phenotype" not in z:
        raise PhysavatarError(path, "needs 'pose_parameters' [T, B, 4, 4] and 'phenotype' [6] (Anny's pose parameters)")
    P = np.asarray(z["pose_parameters"], np.float64)
    param = str(z["pose_parameterization"]) if "pose_parameterization" in z else "local-ref"
    topology = str(z["topology"]) if "topology" in z else "full"
    if param not in PARAMETERIZATIONS:
        raise PhysavatarError(path, f"pose_parameterization {param!r} is not one of {', '.join(PARAMETERIZATIONS)}")
    if topology not in TOPOLOGIES:
        raise PhysavatarError(path, f"topology {topology!r} is not one of {', '.join(TOPOLOGIES)}")
    try:
        shape = BodyShape.from_array(z["phenotype"])
    except ValueError:
        raise PhysavatarError(path, f"'phenotype' must be {len(PHENOTYPES)} values ({', '.join(PHENOTYPES)})") from None
    if not all(0.0 <= v <= 1.0 for v in shape.as_array()):
        raise PhysavatarError(path, "'phenotype' values must lie in [0, 1]")
    body = BodyModel(shape, topology)
    B = len(body.bone_names)
    if P.ndim != 4 or P.shape[1:] != (B, 4, 4) or not np.isfinite(P).all():
        raise PhysavatarError(path, f"'pose_parameters' must be finite with shape [T, {B}, 4, 4], got {list(P.shape)}")
    if "bone_labels" in z and [str(b) for b in z["bone_labels"]] != body.bone_names:
        raise PhysavatarError(path, "'bone_labels' are not Anny's bones in Anny's order")
    ids = [int(f) for f in z["frames"]] if "frames" in z else list(source_frames)
    if len(ids) != len(P):
        raise PhysavatarError(path, f"{len(P)} poses for {len(ids)} frames ('frames' or the source's {len(source_frames)} frames)")
    row = {f: i for i, f in enumerate(ids)}
    missing = [f for f in frames if f not in row]
    if missing:
        raise PhysavatarError(path, f"no pose for frames {missing[:5]}{' ...' if len(missing) > 5 else ''}")
    if placement.scale != 1.0:
        raise PhysavatarError(path, "Anny poses are in metres: import with --scale 1 (the body cannot be scaled)")
    sel = P[[row[f] for f in frames]]
    model, phen = body._model, body._phen  # Anny itself, at this shape: its own forward kinematics
    with torch.no_grad():
        W = model(torch.as_tensor(sel), phenotype_kwargs=phen.expand(len(sel), -1),
                  pose_parameterization=param)["bone_poses"].numpy()
    rest = body.rest_bone_axes  # [B, 3, 3]
    h = body.rest_joints - [0.0, 0.0, body.floor_offset]  # Anny's rest heads
    A = placement.R
    X = np.einsum("ij,tbjk,bkl->tbil", A, W[:, :, :3, :3], rest.transpose(0, 2, 1))
    par = body.parents
    local = X.copy()
    local[:, 1:] = np.einsum("tbji,tbjk->tbik", X[:, par[1:]], X[:, 1:])
    head = W[:, :, :3, 3] @ A.T + placement.offset
    root_translation = head[:, 0] - h[0] - [0.0, 0.0, body.floor_offset]
    rotations = matrix_to_axis_angle(local)
    # bones do not stretch here: our kinematics must put every head where Anny's did
    ours = body.world_bone_poses(rotations, root_translation)[:, :, :3, 3] + [0.0, 0.0, body.floor_offset]
    err = float(np.abs(ours - head).max())
    if err > 1e-4:
        raise PhysavatarError(path, f"bone heads move by up to {err * 1000:.1f} mm relative to their parents (translations "
                                    "in non-root deltas): the capture's body keeps bone lengths")
    return BodyPoses(shape, body.bone_names, rotations, root_translation, topology)
