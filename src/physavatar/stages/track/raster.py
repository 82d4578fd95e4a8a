"""Rasterization and projection helpers of the tracking lifts (:mod:`.flow`, :mod:`.silhouette`):
the nearest triangle through every pixel centre, visibility, bilinear sampling and the projection's
Jacobian."""

from __future__ import annotations

import numba
import numpy as np

from ...camera import Camera

@numba.njit(cache=True)
def _raster_kernel(uv, z, faces, H, W, depth, face_id, bary):
    for f in range(faces.shape[0]):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        if z[a] <= 0.0 or z[b] <= 0.0 or z[c] <= 0.0:
            continue
        x0, y0 = uv[a, 0], uv[a, 1]
        x1, y1 = uv[b, 0], uv[b, 1]
        x2, y2 = uv[c, 0], uv[c, 1]
        den = (y1 - y2) * (x0 - x2) + (x2 - x1) * (y0 - y2)
        if abs(den) < 1e-12:
            continue
        umin = max(int(np.ceil(min(x0, x1, x2))), 0)
        umax = min(int(np.floor(max(x0, x1, x2))), W - 1)
        vmin = max(int(np.ceil(min(y0, y1, y2))), 0)
        vmax = min(int(np.floor(max(y0, y1, y2))), H - 1)
        for v in range(vmin, vmax + 1):
            for u in range(umin, umax + 1):
                l0 = ((y1 - y2) * (u - x2) + (x2 - x1) * (v - y2)) / den
                l1 = ((y2 - y0) * (u - x2) + (x0 - x2) * (v - y2)) / den
                l2 = 1.0 - l0 - l1
                if l0 < 0.0 or l1 < 0.0 or l2 < 0.0:
                    continue
                # perspective-correct depth and barycentrics: attribute/z is affine in screen space
                q0, q1, q2 = l0 / z[a], l1 / z[b], l2 / z[c]
                s = q0 + q1 + q2
                d = 1.0 / s
                if d < depth[v, u]:
                    depth[v, u] = d
                    face_id[v, u] = f
                    bary[v, u, 0] = q0 / s
                    bary[v, u, 1] = q1 / s
                    bary[v, u, 2] = q2 / s


def rasterize(vertices: np.ndarray, faces: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest triangle through every pixel centre.

    Args:
        vertices: [V, 3] world points. faces: [F, 3]. camera: the view.
    Returns:
        depth: [H, W] camera-space z of the nearest triangle through the pixel centre (inf where
        none); face: [H, W] int64 that triangle's index (-1 where none); bary: [H, W, 3] the
        pixel centre's barycentric coordinates on that triangle, perspective-correct (the 3D
        point is ``bary @ vertices[faces[face]]``). Triangles with a vertex behind the camera
        are skipped.
    """
    uv, z = camera.project(np.asarray(vertices, np.float64))
    depth = np.full((camera.height, camera.width), np.inf)
    face = np.full((camera.height, camera.width), -1, np.int64)
    bary = np.zeros((camera.height, camera.width, 3))
    _raster_kernel(np.ascontiguousarray(uv), np.ascontiguousarray(z), np.ascontiguousarray(faces, dtype=np.int64),
                   camera.height, camera.width, depth, face, bary)
    return depth, face, bary


def zbuffer(vertices: np.ndarray, faces: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """(depth [H, W], face [H, W]) of :func:`rasterize`."""
    depth, face, _ = rasterize(vertices, faces, camera)
    return depth, face


def visible_vertices(vertices: np.ndarray, faces: np.ndarray, camera: Camera,
                     depth_tolerance: float = 5e-3, depth: np.ndarray | None = None,
                     face: np.ndarray | None = None) -> np.ndarray:
    """[V] bool: vertices inside the image whose depth is within ``depth_tolerance`` [m] of the
    nearest surface at their pixel, or whose pixel shows one of their own triangles (a vertex on
    a steep slope: the pixel centre's depth differs from the vertex's by more than the tolerance).
    ``depth``, ``face``: a :func:`zbuffer` of the same mesh (computed when not given)."""
    if depth is None or face is None:
        depth, face = zbuffer(vertices, faces, camera)
    uv, z = camera.project(np.asarray(vertices, np.float64))
    front, (v, u) = _in_front(uv, z, depth, depth_tolerance)
    f = face[v, u]
    own = (f >= 0) & (np.asarray(faces)[np.maximum(f, 0)] == np.arange(len(uv))[:, None]).any(1)
    H, W = depth.shape
    inside = (z > 0) & (uv[:, 0] > -0.5) & (uv[:, 0] < W - 0.5) & (uv[:, 1] > -0.5) & (uv[:, 1] < H - 0.5)
    return inside & (front | own)


def _in_front(uv: np.ndarray, z: np.ndarray, depth: np.ndarray, tolerance: float) -> tuple[np.ndarray, tuple]:
    """([N] bool: points at pixels ``uv`` [N, 2] with depth ``z`` within ``tolerance`` of the
    z-buffer ``depth`` at their nearest pixel, (row, column) of that pixel)."""
    H, W = depth.shape
    u = np.clip(np.rint(uv[:, 0]), 0, W - 1).astype(np.int64)
    v = np.clip(np.rint(uv[:, 1]), 0, H - 1).astype(np.int64)
    return z <= depth[v, u] + tolerance, (v, u)


def sample_bilinear(field: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """[N, C] ``field`` [H, W, C] at pixel positions ``uv`` [N, 2] (x, y; clamped to the image)."""
    H, W = field.shape[:2]
    x = np.clip(uv[:, 0], 0.0, W - 1.000001)
    y = np.clip(uv[:, 1], 0.0, H - 1.000001)
    x0 = np.floor(x).astype(np.int64)
    y0 = np.floor(y).astype(np.int64)
    fx = (x - x0)[:, None]
    fy = (y - y0)[:, None]
    x1 = np.minimum(x0 + 1, W - 1)
    y1 = np.minimum(y0 + 1, H - 1)
    return (field[y0, x0] * (1 - fx) * (1 - fy) + field[y0, x1] * fx * (1 - fy)
            + field[y1, x0] * (1 - fx) * fy + field[y1, x1] * fx * fy)


def projection_jacobian(camera: Camera, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Projections uv [N, 2], depths z [N] and d(uv)/d(point) [N, 2, 3] of world ``points``."""
    pc = camera.world_to_camera(points)
    z = pc[:, 2]
    fx, fy = camera.K[0, 0], camera.K[1, 1]
    Jc = np.zeros((len(points), 2, 3))
    Jc[:, 0, 0] = fx / z
    Jc[:, 0, 1] = camera.K[0, 1] / z
    Jc[:, 0, 2] = -(fx * pc[:, 0] + camera.K[0, 1] * pc[:, 1]) / z**2
    Jc[:, 1, 1] = fy / z
    Jc[:, 1, 2] = -fy * pc[:, 1] / z**2
    uv = camera.project(points)[0]
    return uv, z, Jc @ camera.w2c[:3, :3]
