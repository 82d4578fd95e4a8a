"""The geometry floor: triangle-mesh queries that the body, garments, the simulator, rendering and
export share (numpy + scipy; ipctk for the exact intersection test).

- ``mesh``: vertex normals, edges, vertex adjacency, sub-meshes, quality figures;
- ``closest``: the closest point on a triangle, :class:`MeshQuery` (closest points, signed distance);
- ``intersect``: intersection counts and crossing pairs between two meshes, and a push out of
  the crossings a vertex-wise push misses;
- ``seams``: vertex splitting along UV seams.
"""

from .closest import MeshQuery, closest_point_triangle
from .intersect import count_intersections, intersecting_pairs, push_out_crossings
from .mesh import adjacency, mesh_edges, mesh_quality, submesh, vertex_normals
from .seams import SplitMesh, split_uv_seams

__all__ = ["MeshQuery", "SplitMesh", "adjacency", "closest_point_triangle", "count_intersections", "intersecting_pairs", "push_out_crossings", "mesh_edges",
           "mesh_quality", "split_uv_seams", "submesh", "vertex_normals"]
