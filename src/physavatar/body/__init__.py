"""The Anny body model and motions (built-in, npz, BVH)."""

from .load import load_motion
from .model import (BodyModel, BodyShape, PosedBody, PHENOTYPES, TOPOLOGIES, axis_angle_to_matrix, bone_vertex_mask,
                    linear_blend_skinning, matrix_to_axis_angle)
from .motion import BUILTIN, Motion, builtin_motion

__all__ = ["BodyModel", "BodyShape", "PosedBody", "PHENOTYPES", "TOPOLOGIES", "Motion", "BUILTIN",
           "builtin_motion", "load_motion", "axis_angle_to_matrix", "matrix_to_axis_angle",
           "linear_blend_skinning", "bone_vertex_mask"]
