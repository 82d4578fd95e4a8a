"""Pinhole cameras in the OpenCV convention, and the rigs that synthetic captures use.

Convention (DESIGN.md): camera axes x right, y down, z forward; intrinsics ``K`` [3, 3] in pixels;
extrinsics ``w2c`` [4, 4] map world points (metres, z up) to camera coordinates. A pixel's
centre is at integer coordinates: pixel (u, v) covers [u - 0.5, u + 0.5] × [v - 0.5, v + 0.5].
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Camera:
    """One calibrated view.

    Attributes:
        name: folder name of this camera's images (``images/<name>/``).
        width, height: image size in pixels.
        K: [3, 3] intrinsics (fx, fy, cx, cy in pixels).
        w2c: [4, 4] rigid world-to-camera transform.
    """

    name: str
    width: int
    height: int
    K: np.ndarray = field(repr=False)
    w2c: np.ndarray = field(repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "K", np.asarray(self.K, dtype=np.float64).reshape(3, 3))
        object.__setattr__(self, "w2c", np.asarray(self.w2c, dtype=np.float64).reshape(4, 4))

    # -- derived quantities -------------------------------------------------------------------
    @property
    def c2w(self) -> np.ndarray:
        """[4, 4] camera-to-world transform (inverse of a rigid ``w2c``)."""
        R, t = self.w2c[:3, :3], self.w2c[:3, 3]
        out = np.eye(4)
        out[:3, :3] = R.T
        out[:3, 3] = -R.T @ t
        return out

    @property
    def center(self) -> np.ndarray:
        """[3] camera centre in world coordinates."""
        return self.c2w[:3, 3]

    @property
    def fov_x_deg(self) -> float:
        """Horizontal field of view in degrees (for renderers that take an angle)."""
        return float(np.degrees(2.0 * np.arctan(0.5 * self.width / self.K[0, 0])))

    @property
    def fov_y_deg(self) -> float:
        return float(np.degrees(2.0 * np.arctan(0.5 * self.height / self.K[1, 1])))

    # -- geometry -------------------------------------------------------------------------------
    def world_to_camera(self, points: np.ndarray) -> np.ndarray:
        """[N, 3] world points -> [N, 3] camera coordinates."""
        p = np.asarray(points, dtype=np.float64)
        return p @ self.w2c[:3, :3].T + self.w2c[:3, 3]

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points.

        Args:
            points: [N, 3] world coordinates.
        Returns:
            uv: [N, 2] pixel coordinates (pixel centres at integers).
            depth: [N] camera-space z (positive in front of the camera).
        """
        pc = self.world_to_camera(points)
        z = pc[:, 2]
        uvw = pc @ self.K.T
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = uvw[:, :2] / uvw[:, 2:3]
        return uv, z

    def pixel_rays(self) -> tuple[np.ndarray, np.ndarray]:
        """World-space rays through every pixel centre.

        Returns:
            origin: [3]; directions: [H, W, 3], unit length.
        """
        u, v = np.meshgrid(np.arange(self.width), np.arange(self.height))
        pix = np.stack([u, v, np.ones_like(u)], -1).reshape(-1, 3).astype(np.float64)
        d_cam = pix @ np.linalg.inv(self.K).T
        d_world = d_cam @ self.c2w[:3, :3].T
        d_world /= np.linalg.norm(d_world, axis=1, keepdims=True)
        return self.center, d_world.reshape(self.height, self.width, 3)

    def scaled(self, factor: float) -> "Camera":
        """The same view at ``factor`` times the resolution (for coarse-to-fine work)."""
        w = max(1, int(round(self.width * factor)))
        h = max(1, int(round(self.height * factor)))
        sx, sy = w / self.width, h / self.height
        K = self.K.copy()
        K[0, 0] *= sx
        K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
        K[1, 1] *= sy
        K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
        return Camera(self.name, w, h, K, self.w2c)

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "width": int(self.width),
            "height": int(self.height),
            "K": self.K.tolist(),
            "w2c": self.w2c.tolist(),
        }

    @staticmethod
    def from_dict(d: dict) -> "Camera":
        return Camera(str(d["name"]), int(d["width"]), int(d["height"]), d["K"], d["w2c"])


def intrinsics(width: int, height: int, fov_y_deg: float) -> np.ndarray:
    """[3, 3] intrinsics with square pixels and the principal point at the image centre."""
    f = 0.5 * height / np.tan(0.5 * np.radians(fov_y_deg))
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """[4, 4] OpenCV world-to-camera matrix of a camera at ``eye`` looking at ``target``.

    The camera's y axis (image down) points along -``up`` projected on the image plane.
    """
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    z /= np.linalg.norm(z)
    up = np.asarray(up, dtype=np.float64)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # looking along up: pick any perpendicular
        x = np.cross(z, np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: camera axes in world coordinates
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ eye
    return w2c


def ring_rig(
    n: int,
    radius: float,
    height: float,
    target,
    width: int,
    height_px: int,
    fov_y_deg: float,
    *,
    n_elevated: int = 0,
    elevated_height: float | None = None,
    start_deg: float = -90.0,
    prefix: str = "cam",
) -> list[Camera]:
    """A ring of ``n`` cameras at ``height`` around ``target`` plus ``n_elevated`` looking down.

    Angles start at ``start_deg`` (−90° puts the first camera on the −y axis, in front of an
    Anny body, which faces −y) and go counter-clockwise seen from above.
    """
    target = np.asarray(target, dtype=np.float64)
    K = intrinsics(width, height_px, fov_y_deg)
    cams = []
    for i in range(n):
        a = np.radians(start_deg + 360.0 * i / n)
        eye = target + np.array([radius * np.cos(a), radius * np.sin(a), 0.0])
        eye[2] = height
        cams.append(Camera(f"{prefix}{i:02d}", width, height_px, K, look_at(eye, target)))
    eh = elevated_height if elevated_height is not None else height + 0.8 * radius
    for j in range(n_elevated):
        a = np.radians(start_deg + 180.0 / max(n, 1) + 360.0 * j / n_elevated)
        eye = target + np.array([radius * np.cos(a), radius * np.sin(a), 0.0])
        eye[2] = eh
        cams.append(Camera(f"{prefix}{n + j:02d}", width, height_px, K, look_at(eye, target)))
    return cams
