"""Gaussian splatting: mesh-aligned Gaussians (PhysAvatar Sec. 3.1) and a differentiable rasterizer.

``rasterize`` runs numba kernels on the CPU (checked against a dense PyTorch twin) or gsplat on
CUDA; see docs/splatting.md.
"""

from .mesh_gaussians import longest_edge_index, mesh_to_gaussians, rotmat_to_quat
from .rasterize import BACKENDS, expected_depth, rasterize, rasterize_batch

__all__ = [
    "BACKENDS",
    "expected_depth",
    "longest_edge_index",
    "mesh_to_gaussians",
    "rasterize",
    "rasterize_batch",
    "rotmat_to_quat",
]
