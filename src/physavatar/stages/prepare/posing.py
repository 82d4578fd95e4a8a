"""The capture's body posed at some of its frames (Anny, bones body.npz leaves out at rest)."""

from __future__ import annotations

import numpy as np

from ...capture import BodyPoses


def pose_body(body: BodyPoses, index: list[int] | None = None, topology: str | None = None):
    """(BodyModel, [S, Nb, 3] vertices) of the capture's body at frame positions ``index`` (all:
    None); bones body.npz leaves out stay at rest. ``topology``: the mesh posed (default
    body.npz's; "collider": the simulator's)."""
    from ...body import BodyModel

    model = BodyModel(body.shape, topology=topology or body.topology)
    idx = np.arange(len(body.rotations)) if index is None else np.asarray(index)
    rot = np.zeros((len(idx), len(model.bone_names), 3))
    pos = {n: i for i, n in enumerate(body.bone_names)}
    for j, n in enumerate(model.bone_names):
        if n in pos:
            rot[:, j] = body.rotations[idx, pos[n]]
    return model, model.pose(rot, body.root_translation[idx]).vertices
