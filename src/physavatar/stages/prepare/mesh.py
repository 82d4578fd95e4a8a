"""The first-frame mesh: the capture's own (imported) mesh, or the visual hull of the masks;
made manifold and remeshed to near-uniform triangles.

* **Visual hull** (:func:`visual_hull`): voxel carving in the cameras' common volume, coarse to
  fine (the volume every camera sees, then the bounding box of what survives, then voxels of
  ``voxel`` metres). A voxel's occupancy is the smallest mask value (bilinear, so the masks'
  anti-aliased edges give sub-voxel positions) over the cameras that see it; it needs
  ``view_share`` of them (all by default: the common volume). The surface is the 0.5 level set by marching cubes (scikit-image),
  closed because the grid is padded with empty voxels. With ``sheet_views`` > 0 (off by default)
  thin sheets standing off the body are kept: up to that many cameras may see a voxel below half
  where it lies on a thin line of their mask (:func:`occupancy`, :func:`thin_part`).
* **Manifold** (:func:`make_manifold`): trimesh merges duplicate vertices, drops degenerate and
  duplicate faces, keeps the largest piece and orients the faces outward; a mesh that still has
  edges shared by more than two faces or bow-tie vertices is refused (one message).
* **Remeshing** (:func:`remesh`): gpytoolbox's ``remesh_botsch`` (Botsch & Kobbelt's isotropic
  remeshing: splits, collapses, flips and tangential relaxation) to ``edge_length``. It is the
  lightest library that does this (a compiled wheel on numpy + scipy, no Qt or VTK).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...capture import check_template_mesh, frame_name
from ...errors import PhysavatarError
from ...files import read_ply
from .config import MeshConfig


def imported_mesh_path(root: Path, first_frame: int) -> Path | None:
    """The capture's own mesh of the first frame: ``meshes/<frame>.ply`` (what ``physavatar
    import`` writes from sources with per-frame meshes), else an unlabelled ``template/mesh.ply``."""
    p = Path(root) / "meshes" / f"{frame_name(first_frame)}.ply"
    if p.is_file():
        return p
    t = Path(root) / "template" / "mesh.ply"
    return t if t.is_file() else None


def read_mesh(path: Path):
    """(vertices [V, 3], faces [F, 3], per-vertex data dict) of a PLY file."""
    ply = read_ply(path)
    return np.asarray(ply.vertices, np.float64), np.asarray(ply.faces, np.int64), dict(ply.vertex_data)


# -- visual hull ---------------------------------------------------------------------------------

def _sample(mask: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear mask values at pixel positions ``uv`` [n, 2] and whether each is inside the image."""
    h, w = mask.shape
    u, v = uv[:, 0], uv[:, 1]
    inside = (u >= -0.5) & (u <= w - 0.5) & (v >= -0.5) & (v <= h - 0.5)
    u = np.clip(u, 0, w - 1)
    v = np.clip(v, 0, h - 1)
    u0 = np.minimum(np.floor(u).astype(np.int64), w - 2) if w > 1 else np.zeros(len(u), np.int64)
    v0 = np.minimum(np.floor(v).astype(np.int64), h - 2) if h > 1 else np.zeros(len(v), np.int64)
    a, b = u - u0, v - v0
    u1, v1 = np.minimum(u0 + 1, w - 1), np.minimum(v0 + 1, h - 1)
    val = ((1 - a) * (1 - b) * mask[v0, u0] + a * (1 - b) * mask[v0, u1]
           + (1 - a) * b * mask[v1, u0] + a * b * mask[v1, u1])
    return val, inside


def thin_part(mask: np.ndarray, width: int, reach: int = 0) -> np.ndarray:
    """[H, W] the part of a mask in structures narrower than ``width`` pixels: the mask less its
    grey opening by a ``width`` x ``width`` square (a white top-hat). A sheet seen nearly edge-on
    is such a line, partly covering its pixels; a solid's anti-aliased edge is not (the opening
    keeps it). With ``reach`` > 0: its largest value within that many pixels (a voxel whose
    footprint the line crosses sees it, not only one whose centre it passes)."""
    from scipy.ndimage import grey_dilation, grey_opening

    thin = np.clip(mask - grey_opening(mask, size=(width, width)), 0.0, 1.0)
    return grey_dilation(thin, size=(2 * reach + 1,) * 2) if reach > 0 else thin


def occupancy(points: np.ndarray, cameras: list, masks: dict[str, np.ndarray], view_share: float,
              chunk: int = 400_000, sheet_views: int = 0, sheet_level: float = 0.15, sheet_px: int = 3,
              sheet_reach: int = 0) -> np.ndarray:
    """[n] in [0, 1]: the smallest mask value over the cameras that see each point (0 where
    fewer than ``view_share`` of the cameras do: 1 = the cameras' common volume).

    With ``sheet_views`` k > 0 thin sheets are kept: up to k cameras may hold the point below
    half where it lies on a thin line of their mask (:func:`thin_part` of ``sheet_px``, within
    ``sheet_reach`` pixels, covering at least ``sheet_level``): a sheet standing off the body,
    seen nearly edge-on, covers under half a pixel there and would be carved away
    (docs/prepare.md, session 37). The value is then min(w₁, v₍ₖ₊₁₎) over the sorted mask values
    v and the sorted values w = max(v, thin · 0.5 / ``sheet_level``), whose 0.5 level is that
    rule; k = 0 is the plain smallest value."""
    need = max(1, int(np.ceil(view_share * len(cameras) - 1e-9)))
    thin = {c.name: thin_part(masks[c.name], sheet_px, sheet_reach) for c in cameras} if sheet_views else {}
    out = np.empty(len(points))
    for s in range(0, len(points), chunk):
        P = points[s:s + chunk]
        vals = np.ones((len(cameras), len(P)))
        lifted = np.ones((len(cameras), len(P)))
        seen = np.zeros(len(P), np.int32)
        for i, c in enumerate(cameras):
            uv, z = c.project(P)
            uv = np.nan_to_num(uv)
            val, inside = _sample(masks[c.name], uv)
            inside &= z > 1e-6
            vals[i] = np.where(inside, val, 1.0)
            if thin:
                lifted[i] = np.where(inside, np.maximum(val, np.minimum(1.0, _sample(thin[c.name], uv)[0]
                                                                        * (0.5 / sheet_level))), 1.0)
            seen += inside
        if thin:
            vals.sort(axis=0)
            occ = np.minimum(lifted.min(0), vals[min(sheet_views, len(vals) - 1)])
        else:
            occ = vals.min(0)
        out[s:s + chunk] = np.where(seen >= need, occ, 0.0)
    return out


def _grid(lo: np.ndarray, hi: np.ndarray, step: float):
    n = np.maximum(np.ceil((hi - lo) / step).astype(int) + 1, 2)
    axes = [lo[i] + step * np.arange(n[i]) for i in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    return pts, tuple(n)


def pixel_footprint(cameras: list, centre: np.ndarray) -> float:
    """[m] the finest camera's pixel size at ``centre``: how far a visual hull can be off."""
    return float(min(np.linalg.norm(c.center - centre) / c.K[0, 0] for c in cameras))


def auto_voxel(cameras: list, centre: np.ndarray, edge_length: float) -> float:
    """The finest camera's pixel footprint at ``centre``, but at least a third of the target edge
    length (the occupancy is continuous, so marching cubes places the surface between voxels),
    within 4 mm .. 2 cm."""
    return float(np.clip(max(pixel_footprint(cameras, centre), edge_length / 3), 0.004, 0.02))


def visual_hull(cameras: list, masks: dict[str, np.ndarray], cfg: MeshConfig, where: Path | None = None):
    """(vertices, faces) of the visual hull of the masks (one frame's, {camera: [H, W] in [0, 1]}).

    Coarse to fine: the cameras' common volume on a coarse grid, then the bounding box of what
    survives on a finer one, then the final voxels only in the cells where the finer grid
    changes from outside to inside (the rest takes that grid's value)."""
    from scipy.ndimage import binary_dilation, binary_erosion
    from skimage.measure import marching_cubes

    centres = np.array([c.center for c in cameras])
    span = float(np.linalg.norm(np.ptp(centres, axis=0))) or 1.0
    lo, hi = centres.min(0) - 0.5 * span, centres.max(0) + 0.5 * span
    for step in (span / 40, span / 80):
        pts, n = _grid(lo, hi, step)
        occ = occupancy(pts, cameras, masks, cfg.view_share)
        keep = occ > 0.5
        if not keep.any():
            raise PhysavatarError(where, "the masks have no common foreground: no point is inside every camera's "
                                  "mask (check the masks and the cameras' calibration)")
        lo, hi = pts[keep].min(0) - 2 * step, pts[keep].max(0) + 2 * step
    voxel = cfg.voxel or auto_voxel(cameras, pts[keep].mean(0), cfg.edge_length)
    coarse = max(4 * voxel, 0.02)
    cpts, cn = _grid(lo, hi, coarse)
    cin = (occupancy(cpts, cameras, masks, cfg.view_share) > 0.5).reshape(cn)
    band = binary_dilation(cin, iterations=1) & ~binary_erosion(cin, iterations=1)
    if cfg.sheet_views > 0:
        # a sheet off the body may pass between the coarse points: the band also takes the cells
        # the cameras' masks may hold anywhere (each mask's largest value within a cell's reach)
        from scipy.ndimage import grey_dilation

        fp = pixel_footprint(cameras, pts[keep].mean(0))
        r = int(np.ceil(0.5 * np.sqrt(3) * coarse / fp))
        wide = {k: grey_dilation(m, size=(2 * r + 1,) * 2) for k, m in masks.items()}
        band |= (occupancy(cpts, cameras, wide, cfg.view_share) > 0.5).reshape(cn) & ~binary_erosion(cin, iterations=1)
    sheet = {"sheet_views": cfg.sheet_views, "sheet_level": cfg.sheet_level, "sheet_px": cfg.sheet_px,
             "sheet_reach": int(np.ceil(cfg.sheet_reach * voxel / pixel_footprint(cameras, pts[keep].mean(0)) - 1e-9))}
    pts, n = _grid(lo, hi, voxel)
    cell = np.minimum(np.round((pts - lo) / coarse).astype(np.int64), np.array(cn) - 1)
    in_band = band[cell[:, 0], cell[:, 1], cell[:, 2]]
    occ = cin[cell[:, 0], cell[:, 1], cell[:, 2]].astype(np.float64)
    occ[in_band] = occupancy(pts[in_band], cameras, masks, cfg.view_share, **sheet)
    occ = np.pad(occ.reshape(n), 1)  # closed surface
    verts, faces, _, _ = marching_cubes(occ.astype(np.float32), level=0.5, spacing=(voxel,) * 3)
    verts = verts + lo - voxel
    return verts.astype(np.float64), faces[:, ::-1].astype(np.int64)  # outward normals


# -- manifold and remeshing ----------------------------------------------------------------------

def make_manifold(vertices: np.ndarray, faces: np.ndarray, where: Path | None = None, process: bool = True):
    """(vertices, faces) repaired: duplicates merged, degenerate / duplicate faces dropped, the
    largest connected piece kept, outward orientation. Raises a :class:`PhysavatarError` naming
    ``where`` when the result is still not a manifold surface."""
    import trimesh

    if len(vertices) == 0 or len(faces) == 0:
        raise PhysavatarError(where, "mesh has no vertices or no faces")
    if not np.isfinite(vertices).all():
        raise PhysavatarError(where, "mesh has NaN or infinite vertex coordinates")
    m = trimesh.Trimesh(vertices, faces, process=process, validate=process)
    if len(m.faces) == 0:
        raise PhysavatarError(where, "cannot be made manifold: every face is degenerate")
    labels = trimesh.graph.connected_component_labels(m.face_adjacency, node_count=len(m.faces))
    if labels.max() > 0:
        m = m.submesh([np.flatnonzero(labels == np.argmax(np.bincount(labels)))], append=True)
    trimesh.repair.fix_winding(m)
    if m.is_watertight and m.volume < 0:
        m.invert()
    V, F = np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)
    problems = [p for p in check_template_mesh(V, F) if "non-manifold" in p or "orientation" in p]
    if problems:
        raise PhysavatarError(where, "cannot be made manifold: " + "; ".join(problems))
    return V, F


def remesh(vertices: np.ndarray, faces: np.ndarray, cfg: MeshConfig, where: Path | None = None):
    """(vertices, faces) isotropically remeshed to ``cfg.edge_length`` (gpytoolbox.remesh_botsch)."""
    from gpytoolbox import remesh_botsch

    V, F = remesh_botsch(np.ascontiguousarray(vertices, np.float64), np.ascontiguousarray(faces, np.int32),
                         i=cfg.remesh_iterations, h=cfg.edge_length, project=True)
    return make_manifold(np.asarray(V, np.float64), np.asarray(F, np.int64), where)


def smooth(vertices: np.ndarray, faces: np.ndarray, iterations: int) -> np.ndarray:
    """Taubin smoothing (trimesh; shrink-free) against the voxel staircase."""
    import trimesh

    if iterations <= 0:
        return vertices
    m = trimesh.Trimesh(vertices, faces, process=False)
    trimesh.smoothing.filter_taubin(m, iterations=iterations)
    return np.asarray(m.vertices, np.float64)


def reconstruct(cameras: list, masks: dict[str, np.ndarray], cfg: MeshConfig, where: Path | None = None):
    """The first frame's surface from its masks: hull, manifold, smoothed, remeshed."""
    V, F = visual_hull(cameras, masks, cfg, where)
    V, F = make_manifold(V, F, where, process=False)  # marching cubes: no duplicates to merge
    V = smooth(V, F, cfg.smooth)
    return remesh(V, F, cfg, where)


def surface_distance(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """[n] distance of each point to the closest point of a triangle mesh."""
    from ...geometry.closest import MeshQuery

    d, _, _, _ = MeshQuery(vertices, faces, spacing=0.02).closest(points)
    return d
