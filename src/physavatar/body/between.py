"""The body in between two frames, skinned from the poses (the simulator's sub-steps).

A frame the simulator splits into n implicit steps (sim.simulate) needs the body at the times
in between its two poses. Interpolated vertex by vertex, a limb that turns fast cuts along the
chord of the arc its skin really follows: a body spinning at 2 turns/s shrinks by
r (1 − cos(θ/2)) half-way through a frame that turns it by θ, a knee that flexes fast closes its
own crease more in between than in either pose. :class:`PoseBetween` poses the body in between
instead, the way the motion itself is made: per bone, the local (parent-relative) rotation
slerped along its shortest arc and the root translation interpolated linearly
(motion.slerp_rotations, as :meth:`Motion.resample` makes a motion's frames from a capture's),
then Anny's forward kinematics and skinning (BodyModel.pose) as for the frames themselves.

Local rotations rather than world bone transforms: forward kinematics of the slerped local
rotations carries every joint along the composed arcs of its parents (the foot of a spinning
body turns about the spin axis with the hips); slerping each bone's world transform would still
move its head along a straight line between its two positions, the chord again.
"""

from __future__ import annotations

import numpy as np

from .model import BodyModel
from .motion import slerp_rotations


class PoseBetween:
    """``between(f, s)`` -> [S, Nb, 3]: ``body`` posed at the times f − 1 + s (s [S] in [0, 1])
    of the pose sequence ``rotations`` [T, B, 3], ``root_translation`` [T, 3] (in ``body``'s bone
    order: the poses the collider sequence was made with, body.pose(rotations,
    root_translation).vertices). s = 0 and 1 give frames f − 1 and f as skinned here (to
    round-off: the rotations go through a matrix and back); sim.simulate adds the linear blend
    of the differences to the frames it is given (round-off, or corrections made after skinning),
    so the in-between sequence meets those exactly."""

    def __init__(self, body: BodyModel, rotations, root_translation):
        self.body = body
        self.rotations = np.asarray(rotations, np.float64)
        self.root_translation = np.asarray(root_translation, np.float64)
        B = len(body.bone_names)
        if self.rotations.ndim != 3 or self.rotations.shape[1:] != (B, 3) or \
                self.root_translation.shape != (len(self.rotations), 3):
            raise ValueError(f"poses must be rotations [T, {B}, 3] and root translations [T, 3], got "
                             f"{self.rotations.shape} and {self.root_translation.shape}")

    def __len__(self) -> int:
        return len(self.rotations)

    def poses(self, f: int, s) -> tuple[np.ndarray, np.ndarray]:
        """(rotations [S, B, 3], root translations [S, 3]) at the times f − 1 + s."""
        if not 1 <= f < len(self.rotations):
            raise IndexError(f"frame {f} has no frame before it in {len(self.rotations)} poses")
        s = np.atleast_1d(np.asarray(s, np.float64))
        S = len(s)
        r0 = np.broadcast_to(self.rotations[f - 1], (S,) + self.rotations.shape[1:])
        r1 = np.broadcast_to(self.rotations[f], r0.shape)
        rot = slerp_rotations(r0, r1, s[:, None])
        tr = (1 - s)[:, None] * self.root_translation[f - 1] + s[:, None] * self.root_translation[f]
        return rot, tr

    def __call__(self, f: int, s) -> np.ndarray:
        return self.body.pose(*self.poses(f, s)).vertices


BETWEEN_HELP = ("a frame split into sub-steps poses the body in between from the motion (each bone's rotation "
                "slerped, body.between; the default) instead of vertex by vertex (--linear-between: the chord of a "
                "turning limb's arc); the attached targets take the straight line either way. Clean on the motion "
                "suite with fewer Newton iterations (docs/simulation.md, Session 31)")  # simulate's and animate's option


def between_key(between, max_substeps: int) -> dict:
    """What a run's resume key (data.sim_frames.garment_run_key) adds for its in-between bodies:
    {"between": "skinned-body"} where they come from the poses and a frame can be split (the
    attached targets on their straight line since session 31; session 30's "skinned" also carried
    them on the in-between body), else nothing (the key of a run before session 30)."""
    return {"between": "skinned-body"} if between is not None and max_substeps > 1 else {}
