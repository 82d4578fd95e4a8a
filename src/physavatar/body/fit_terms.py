"""Image and mesh terms for fitting a body to calibrated views (torch, differentiable).

- Silhouettes: a mask's distance transform outside the foreground, sampled bilinearly at the
  projected body points, penalises body outside any mask (the body lies under the clothing); the
  mask's contour points pull the nearest projected body points onto them with a robust
  (Geman-McClure) kernel, so contours of skin (arms, head, legs below a skirt) fit the body's
  outline while contours of loose clothing, far from it, are ignored.
- 2D keypoints: robust reprojection error weighted by the detector's confidence.
- Clothed mesh: body points outside the clothed surface (signed distance along the nearest
  clothed vertex's normal), and clothed vertices near the body drawn onto it (skin).

Distances are converted from pixels to metres at each point's depth (``px * z / f``), so the
terms weigh views of different resolution and distance alike.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from scipy import ndimage
from scipy.spatial import cKDTree

from ..camera import Camera

DTYPE = torch.float64


@dataclass
class MaskView:
    """One camera's silhouette at one frame, at the working resolution of ``camera``."""

    camera: Camera
    dt: torch.Tensor  # [H, W] signed distance [px] to the mask's edge (> 0 outside, < 0 inside)
    contour: torch.Tensor  # [N, 2] points on the mask's edge (u, v), between pixel centres
    mask: np.ndarray  # [H, W] bool

    @staticmethod
    def build(camera: Camera, mask: np.ndarray, max_contour: int, rng: np.random.Generator) -> "MaskView":
        m = np.asarray(mask) > 0.5
        if m.any() and not m.all():
            # pixel centres lie half a pixel from the edge between a pixel and its neighbour:
            # this signed distance is 0 on that edge, so bilinear lookups are unbiased there
            dt = np.where(m, 0.5 - ndimage.distance_transform_edt(m), ndimage.distance_transform_edt(~m) - 0.5)
        else:
            dt = np.full(m.shape, -1e3 if m.all() else 1e3)
        # edge points: midpoints between horizontally or vertically neighbouring pixels that differ
        vh, uh = np.nonzero(m[:, 1:] != m[:, :-1])
        vv, uv_ = np.nonzero(m[1:] != m[:-1])
        pts = np.concatenate([np.stack([uh + 0.5, vh], 1), np.stack([uv_, vv + 0.5], 1)]).astype(np.float64)
        if len(pts) > max_contour:
            pts = pts[rng.choice(len(pts), max_contour, replace=False)]
        return MaskView(camera, torch.as_tensor(dt, dtype=torch.float32), torch.as_tensor(pts, dtype=DTYPE), m)


def camera_tensors(cam: Camera) -> tuple[torch.Tensor, torch.Tensor]:
    return torch.as_tensor(cam.K, dtype=DTYPE), torch.as_tensor(cam.w2c, dtype=DTYPE)


def project(points: torch.Tensor, cam: Camera) -> tuple[torch.Tensor, torch.Tensor]:
    """[..., N, 3] world -> uv [..., N, 2] px and depth [..., N]."""
    K, w2c = camera_tensors(cam)
    pc = points @ w2c[:3, :3].T + w2c[:3, 3]
    z = pc[..., 2]
    uv = (pc @ K.T)[..., :2] / z.clamp(min=1e-3)[..., None]
    return uv, z


def sample_field(field: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Bilinear lookup of [H, W] ``field`` at pixel coordinates uv [N, 2] (clamped to the border)."""
    H, W = field.shape
    g = torch.stack([(uv[:, 0] + 0.5) / W * 2 - 1, (uv[:, 1] + 0.5) / H * 2 - 1], -1)
    out = F.grid_sample(field[None, None].to(uv.dtype), g[None, None], mode="bilinear", padding_mode="border",
                        align_corners=False)
    return out[0, 0, 0]


def gm(d2: torch.Tensor, sigma) -> torch.Tensor:
    """Geman-McClure on squared distances: ~d^2 near 0, at most sigma^2 far away."""
    s2 = sigma * sigma
    return s2 * d2 / (d2 + s2)


def silhouette_terms(points: torch.Tensor, views: list[MaskView], sigma: float,
                     margin_px: float = 0.0, offsets: torch.Tensor | None = None,
                     contour_on: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean squared outside distance [m^2] (outside the mask shrunk by ``margin_px``) and mean
    robust contour distance [m^2] of body ``points`` [N, 3] over the views of one frame
    (``offsets`` [C, 2] px added to each view's projections: its image offset). With
    ``contour_on`` [N] bool, only the contour points whose nearest projected body point is one of
    those count (the contour of skin, not of clothing)."""
    out, cont = points.new_zeros(()), points.new_zeros(())
    for i, view in enumerate(views):
        uv, z = project(points, view.camera)
        if offsets is not None:
            uv = uv + offsets[i]
        f = float(view.camera.K[0, 0])
        scale = z.clamp(min=1e-3) / f  # metres per pixel at each point
        d_out = torch.relu(sample_field(view.dt, uv) + margin_px) * scale
        out = out + (d_out ** 2).mean()
        q = view.contour
        if len(q):
            with torch.no_grad():
                nn = torch.as_tensor(cKDTree(uv.detach().numpy()).query(q.numpy())[1])
            if contour_on is not None:
                keep = contour_on[nn]
                q, nn = q[keep], nn[keep]
                if not len(q):
                    continue
            d2 = ((q - uv[nn]) ** 2).sum(-1) * scale[nn] ** 2
            # the kernel is never narrower than a pixel (edges are only known to a pixel)
            cont = cont + gm(d2, torch.clamp(scale[nn].detach(), min=sigma)).mean()
    n = max(len(views), 1)
    return out / n, cont / n


def keypoint_term(joints: torch.Tensor, kp2d: np.ndarray, conf: np.ndarray, cams: list[Camera],
                  sigma: float, offsets: torch.Tensor | None = None) -> torch.Tensor:
    """Robust confidence-weighted reprojection error [m^2] of [K, 3] model keypoints against
    detections kp2d [C, K, 2] px with confidences [C, K]."""
    total, wsum = joints.new_zeros(()), 0.0
    for c, cam in enumerate(cams):
        w = torch.as_tensor(conf[c], dtype=DTYPE)
        if float(w.sum()) <= 0:
            continue
        uv, z = project(joints, cam)
        if offsets is not None:
            uv = uv + offsets[c]
        scale = z.clamp(min=1e-3) / float(cam.K[0, 0])
        d2 = ((uv - torch.as_tensor(kp2d[c], dtype=DTYPE)) ** 2).sum(-1) * scale ** 2
        total = total + (w * gm(d2, sigma)).sum()
        wsum += float(w.sum())
    return total / max(wsum, 1e-9)


class ClothedSurface:
    """The clothed first-frame mesh as points with outward normals, for inside/near terms.

    With faces, normals are the mesh's (area-weighted vertex normals, oriented outward by the
    sign of the enclosed volume); with points only, by local PCA, oriented away from the
    vertical axis through the points' centroid at that height (a standing person).
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray | None = None):
        from scipy.spatial import cKDTree

        V = np.asarray(vertices, dtype=np.float64)
        if faces is not None and len(faces):
            Fc = np.asarray(faces, dtype=np.int64)
            a, b, c = V[Fc[:, 0]], V[Fc[:, 1]], V[Fc[:, 2]]
            fn = np.cross(b - a, c - a)
            n = np.zeros_like(V)
            for k in range(3):
                np.add.at(n, Fc[:, k], fn)
            if np.einsum("ij,ij->", a, fn) < 0:  # inward-oriented mesh (negative volume)
                n = -n
        else:
            k = min(12, len(V))
            _, idx = cKDTree(V).query(V, k)
            nb = V[idx] - V[idx].mean(1, keepdims=True)
            _, _, vt = np.linalg.svd(nb, full_matrices=False)
            n = vt[:, -1]
            # orient away from the local vertical axis (slices of 5 cm)
            zbin = np.round(V[:, 2] / 0.05)
            centre = np.zeros_like(V)
            for zb in np.unique(zbin):
                sel = zbin == zb
                centre[sel] = V[sel].mean(0)
            radial = V - centre
            radial[:, 2] = 0.0
            n = np.where((np.einsum("ij,ij->i", n, radial) < 0)[:, None], -n, n)
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        self.vertices = V
        self.normals = n
        self.tree = cKDTree(V)
        self.Vt = torch.as_tensor(V, dtype=DTYPE)
        self.Nt = torch.as_tensor(n, dtype=DTYPE)

    def signed_distance(self, points: torch.Tensor) -> torch.Tensor:
        """[N] distance along the nearest clothed vertex's normal (> 0: outside the clothing)."""
        with torch.no_grad():
            _, idx = self.tree.query(points.detach().numpy())
        idx = torch.as_tensor(idx)
        return ((points - self.Vt[idx]) * self.Nt[idx]).sum(-1)

    def terms(self, points: torch.Tensor, margin, sigma: float,
              near_on: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(mean squared depth of body points outside the clothing (less ``margin``, a number or
        [N] per point), mean robust distance [m^2] from clothed vertices to the nearest body
        point; with ``near_on`` [N] bool only the clothed vertices whose nearest body point is
        one of those)."""
        s = self.signed_distance(points)
        outside = (torch.relu(s + margin) ** 2).mean()
        with torch.no_grad():
            from scipy.spatial import cKDTree

            _, nn = cKDTree(points.detach().numpy()).query(self.vertices)
        nn = torch.as_tensor(nn)
        d2 = ((self.Vt - points[nn]) ** 2).sum(-1)
        if near_on is not None:
            d2 = d2[near_on[nn]]
        return outside, (gm(d2, sigma).mean() if len(d2) else outside.new_zeros(()))
