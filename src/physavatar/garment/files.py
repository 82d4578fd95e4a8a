"""Garments from other tools' files: OBJ, PLY, glTF/GLB (trimesh) and npz.

:func:`load_garment` returns a :class:`GarmentMesh`: the garment's world shape (where it is
draped), its rest shape (the stress-free shape of every triangle), its triangles, its seams and
the boundary flags the file gives, if any. The vertices are the garment's *panel* vertices: two
triangles share a vertex only when they share both its world position and its rest position, so
a garment sewn from flat panels comes back as its panels, each with its material-space rest
shape, and the seams as pairs of panel vertices that sit at one world point (stitched in the
simulation by :class:`physavatar.sim.stitch.Stitch`).

Where the rest shape comes from (``GarmentMesh.rest_source``):

- ``file``: a separate rest-shape file with the same triangles in the same order (the Berkeley
  Garment Library's ``NAME-m.obj`` beside ``NAME-w.obj``; found by that name, or given);
- ``uv``: the texture coordinates, when they are material coordinates in the world's units
  (the Library's combined ``NAME.obj``: triangle areas in uv within 25 % of the world ones);
- ``world``: the world shape itself (no rest information in the file).

Orientation and units: ``up`` names the file's up axis (``z``, ``y``, ``-y``, …; default ``y``
for glTF, whose convention it is, ``z`` otherwise) and is turned to the simulator's +z;
``scale`` multiplies world and rest (a number, or a unit: m, cm, mm, in).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import PhysavatarError

FORMATS = (".obj", ".ply", ".gltf", ".glb", ".npz")
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254, "ft": 0.3048}
AXES = ("x", "y", "z", "-x", "-y", "-z")


@dataclass
class GarmentMesh:
    """A garment read from a file (module docstring).

    Attributes:
        vertices: [N, 3] world shape [m], z up. rest: [N, 3] rest shape [m] (any placement).
        faces: [F, 3] panel triangles. seams: [S, 2] vertex pairs sewn together.
        boundary: [K] vertex ids the file marks as attached to the body, or None (no flags).
        rest_source: "file", "uv" or "world". path: the file. repairs: what loading fixed.
    """

    vertices: np.ndarray
    rest: np.ndarray
    faces: np.ndarray
    seams: np.ndarray
    boundary: np.ndarray | None
    rest_source: str
    path: Path
    repairs: list

    def panels(self) -> np.ndarray:
        """[N] panel index of every vertex (connected components of the unsewn mesh)."""
        import scipy.sparse as sp
        from scipy.sparse.csgraph import connected_components

        F = self.faces
        n = len(self.vertices)
        A = sp.coo_matrix((np.ones(3 * len(F)), (F.ravel(), F[:, [1, 2, 0]].ravel())), shape=(n, n))
        return connected_components(A, directed=False)[1]


def parse_scale(value) -> float:
    """A scale factor from a number or a unit name (m, cm, mm, in, ft)."""
    if isinstance(value, (int, float)):
        s = float(value)
    elif str(value).strip().lower() in UNITS:
        s = UNITS[str(value).strip().lower()]
    else:
        try:
            s = float(value)
        except ValueError:
            raise PhysavatarError(None, f"option --scale: {value!r} is neither a number nor one of "
                                        f"{', '.join(UNITS)}") from None
    if not np.isfinite(s) or s <= 0:
        raise PhysavatarError(None, f"option --scale: {value!r} must be positive")
    return s


def up_rotation(up: str) -> np.ndarray:
    """The rotation [3, 3] taking the axis ``up`` to +z (a right-handed turn about one axis)."""
    up = str(up).strip().lower()
    if up not in AXES:
        raise PhysavatarError(None, f"option --up: {up!r} is not one of {', '.join(AXES)}")
    R = {"z": np.eye(3),
         "-z": np.diag([1.0, -1.0, -1.0]),  # half-turn about x
         "y": np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]),  # +y -> +z (about x), +z -> -y
         "-y": np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]),
         "x": np.array([[0.0, 0, -1], [0, 1, 0], [1, 0, 0]]),  # +x -> +z (about y)
         "-x": np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])}[up]
    return R


def _corners(path: Path, up_default: list) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, dict]:
    """(positions [F, 3, 3], faces into the file's own vertices [F, 3], uv [F, 3, 2] or None,
    per-vertex data of the file's vertices) of a mesh file, by trimesh (the project's own PLY
    reader first, for its per-vertex properties)."""
    import trimesh

    suffix = path.suffix.lower()
    data = {}
    if suffix == ".ply":
        from ..files import read_ply

        try:
            m = read_ply(path)
            V, F = np.asarray(m.vertices, float), np.asarray(m.faces, np.int64)
            data = {k: np.asarray(v) for k, v in m.vertex_data.items()}
            return V[F], F, None, data
        except Exception:  # noqa: BLE001, S110 - not the project's PLY flavour: trimesh reads any
            pass
    if suffix in (".gltf", ".glb"):
        up_default[0] = "y"
    try:
        loaded = trimesh.load(path, process=False, force="mesh")
    except Exception as e:  # noqa: BLE001 - any reader failure is the file's problem, in one line
        raise PhysavatarError(path, f"cannot read the mesh ({type(e).__name__}: {e})") from None
    V, F = np.asarray(loaded.vertices, float), np.asarray(loaded.faces, np.int64)
    if F.ndim != 2 or F.shape[1] != 3 or not len(F):
        raise PhysavatarError(path, "has no triangles")
    uv = getattr(loaded.visual, "uv", None)
    uv = None if uv is None or len(uv) != len(V) else np.asarray(uv, float)[F]
    return V[F], F, uv, data


def _weld(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(first corner of every distinct key row, corner -> vertex) for corner keys [C, k]."""
    _, first, inverse = np.unique(np.ascontiguousarray(keys), axis=0, return_index=True, return_inverse=True)
    return first, inverse.ravel()


def _rest_file_for(path: Path) -> Path | None:
    """The Berkeley Garment Library's rest-shape file beside a world-shape one (NAME-w.obj -> NAME-m.obj)."""
    m = re.match(r"^(.*)-w(\.[A-Za-z]+)$", path.name)
    if m:
        cand = path.with_name(f"{m.group(1)}-m{m.group(2)}")
        return cand if cand.exists() else None
    return None


def load_garment(path, *, up: str | None = None, scale=1.0, rest=None, seam_tolerance: float = 1e-6) -> GarmentMesh:
    """Read a garment (module docstring). ``rest``: a rest-shape file (same triangles), "uv",
    "world", or None (automatic). ``seam_tolerance``: vertices closer than this × the garment's
    size are one world point (sewn)."""
    path = Path(path)
    if not path.exists():
        raise PhysavatarError(path, "garment file not found")
    if path.suffix.lower() not in FORMATS:
        raise PhysavatarError(path, f"unknown garment format {path.suffix!r}; expected one of {', '.join(FORMATS)}")
    s = parse_scale(scale)
    repairs = []
    boundary_flags = None
    listed_seams = np.zeros((0, 2), np.int64)
    up_default = ["z"]
    if path.suffix.lower() == ".npz":
        P, Ff, rest_corners, boundary_flags, listed_seams = _npz(path)
        uv = None
        source = "file" if rest_corners is not None else "world"
    else:
        P, Ff, uv, data = _corners(path, up_default)
        if "boundary" in data:
            boundary_flags = np.asarray(data["boundary"])[Ff]  # per corner
        rest_corners, source = None, "world"
    R = up_rotation(up or up_default[0])
    # -- the rest shape: a file, the uv, or the world shape
    rest_path = None
    if rest is not None and str(rest) not in ("uv", "world"):
        rest_path = Path(rest)
    elif rest is None and path.suffix.lower() != ".npz":
        rest_path = _rest_file_for(path)
    if rest_path is not None:
        if not rest_path.exists():
            raise PhysavatarError(rest_path, "rest-shape file not found")
        Pr, Fr, _, _ = _corners(rest_path, ["z"])
        if len(Fr) != len(Ff):
            raise PhysavatarError(rest_path, f"has {len(Fr)} triangles but {path.name} has {len(Ff)}: a rest-shape "
                                             "file must have the same triangles in the same order")
        rest_corners, source = Pr, "file"
    elif str(rest) == "uv" or (rest is None and uv is not None and _uv_is_material(P, uv)):
        if uv is None:
            raise PhysavatarError(path, "--rest uv: the file has no texture coordinates")
        rest_corners, source = np.concatenate([uv, np.zeros(uv.shape[:2] + (1,))], axis=2), "uv"
    if rest_corners is None:
        rest_corners = P
    P = P @ R.T * s
    rest_corners = rest_corners * s
    # -- weld corners into panel vertices: same world point and same rest point
    size = float(np.linalg.norm(P.reshape(-1, 3).max(0) - P.reshape(-1, 3).min(0)))
    q = max(seam_tolerance * size, 1e-12)
    if source == "world" or path.suffix.lower() == ".npz":
        # no rest information, or per-vertex rest: the file's own vertices (coincident ones are sewn, not merged)
        keys = np.asarray(Ff, np.int64).reshape(-1, 1)
    else:  # one vertex per (world point, rest point): the panels, however the file splits its corners
        keys = np.round(np.concatenate([P, rest_corners], axis=2).reshape(-1, 6) / q).astype(np.int64)
    first, inv = _weld(keys)
    V = P.reshape(-1, 3)[first]
    Vr = rest_corners.reshape(-1, 3)[first]
    F = inv.reshape(-1, 3)
    boundary = None
    if boundary_flags is not None:
        flags = np.zeros(len(V), bool)
        flags[F.ravel()] = np.asarray(boundary_flags).reshape(-1) > 0
        boundary = np.flatnonzero(flags)
    # -- listed seams (npz: pairs of the file's vertices) map through the weld
    if len(listed_seams):
        corner_of = np.full(int(Ff.max()) + 1, -1)
        corner_of[Ff.ravel()] = inv
        listed_seams = corner_of[listed_seams]
        if (listed_seams < 0).any():
            raise PhysavatarError(path, "'seams' names a vertex that is in no triangle")
    V, Vr, F, keep, rep = _repair(V, Vr, F, path)
    repairs += rep
    if boundary is not None:
        boundary = np.flatnonzero(np.isin(keep, boundary))
    remap = np.full(len(keep) and keep.max() + 1, -1)
    remap[keep] = np.arange(len(keep))
    seams = _coincident_pairs(V, q)
    if len(listed_seams):
        listed_seams = remap[listed_seams]
        seams = np.unique(np.sort(np.vstack([seams, listed_seams[(listed_seams >= 0).all(1)]]), axis=1), axis=0)
    seams = seams[seams[:, 0] != seams[:, 1]]
    return GarmentMesh(V, Vr, F, seams, boundary, source, path, repairs)


def _npz(path: Path):
    from ..files import load_npz

    z = load_npz(path)
    if not {"vertices", "faces"} <= set(z):
        raise PhysavatarError(path, "garment .npz needs 'vertices' [N, 3] and 'faces' [F, 3] "
                                    "(optional: 'rest' [N, 3], 'boundary', 'seams' [S, 2])")
    V, F = np.asarray(z["vertices"], float), np.asarray(z["faces"], np.int64)
    if V.ndim != 2 or V.shape[1] != 3 or F.ndim != 2 or F.shape[1] != 3:
        raise PhysavatarError(path, f"'vertices' must be [N, 3] and 'faces' [F, 3], got {V.shape} and {F.shape}")
    if F.size and (F.min() < 0 or F.max() >= len(V)):
        raise PhysavatarError(path, "'faces' index vertices out of range")
    rest = None
    for key in ("rest", "rest_vertices"):
        if key in z:
            rest = np.asarray(z[key], float)
            if rest.shape != V.shape:
                raise PhysavatarError(path, f"'{key}' must have the shape of 'vertices' {V.shape}, got {rest.shape}")
            rest = rest[F]
    flags = None
    if "boundary" in z:
        b = np.asarray(z["boundary"])
        if b.dtype == bool or (len(b) == len(V) and set(np.unique(b)) <= {0, 1}):
            flags = b.astype(bool)[F]
        else:
            f = np.zeros(len(V), bool)
            f[b.astype(np.int64)] = True
            flags = f[F]
    seams = np.asarray(z["seams"], np.int64).reshape(-1, 2) if "seams" in z else np.zeros((0, 2), np.int64)
    if len(seams) and (seams.min() < 0 or seams.max() >= len(V)):
        raise PhysavatarError(path, "'seams' index vertices out of range")
    return V[F], F, rest, flags, seams


def _uv_is_material(P: np.ndarray, uv: np.ndarray) -> bool:
    """Whether per-corner uv [F, 3, 2] are material coordinates in the units of P [F, 3, 3]."""
    a3 = 0.5 * np.linalg.norm(np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]), axis=1)
    e1, e2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    a2 = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    ok = a3 > 0
    if not ok.any():
        return False
    return bool(abs(np.median(a2[ok] / a3[ok]) - 1.0) < 0.25)


def _repair(V, Vr, F, path):
    """Drop degenerate and duplicate triangles and unused vertices; fix the panels' winding
    (trimesh); refuse what cannot be repaired (an edge of more than two triangles). Returns
    (V, rest, F, kept vertex ids, repairs)."""
    import trimesh

    repairs = []

    def area(X):
        return np.linalg.norm(np.cross(X[F[:, 1]] - X[F[:, 0]], X[F[:, 2]] - X[F[:, 0]]), axis=1)

    scale = max(float(np.ptp(V, axis=0).max()), 1e-9)
    good = (area(V) > 1e-12 * scale**2) & (area(Vr) > 1e-12 * max(float(np.ptp(Vr, axis=0).max()), 1e-9) ** 2)
    good &= (F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 0] != F[:, 2])
    _, uniq = np.unique(np.sort(F, axis=1), axis=0, return_index=True)
    dup = np.ones(len(F), bool)
    dup[uniq] = False
    good &= ~dup
    if (~good).any():
        repairs.append(f"dropped {int((~good).sum())} degenerate or duplicate triangles")
        F = F[good]
    if not len(F):
        raise PhysavatarError(path, "no usable triangles")
    keep = np.unique(F)
    if len(keep) < len(V):
        repairs.append(f"dropped {len(V) - len(keep)} vertices in no triangle")
    remap = np.full(len(V), -1)
    remap[keep] = np.arange(len(keep))
    V, Vr, F = V[keep], Vr[keep], remap[F]
    e = np.sort(np.vstack([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    if (counts > 2).any():
        raise PhysavatarError(path, f"non-manifold: {int((counts > 2).sum())} edges are shared by more than two "
                                    "triangles within a panel (cannot be repaired; split the panels or remove the "
                                    "extra triangles)")
    mesh = trimesh.Trimesh(V, F, process=False)
    if not mesh.is_winding_consistent:
        trimesh.repair.fix_winding(mesh)
        if not mesh.is_winding_consistent:
            raise PhysavatarError(path, "its triangles cannot be oriented consistently (a Möbius-like panel)")
        F = np.asarray(mesh.faces, np.int64)
        repairs.append("re-oriented triangles to a consistent winding")
    return V, Vr, F, keep, repairs


def _coincident_pairs(V: np.ndarray, tol: float) -> np.ndarray:
    """Seam pairs [S, 2]: every group of vertices at one world point (within ``tol``) as pairs of
    its first vertex with each other one (a layered seam is a group of three or more)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    pairs = cKDTree(V).query_pairs(max(tol, 1e-12), output_type="ndarray")
    if not len(pairs):
        return np.zeros((0, 2), np.int64)
    n = len(V)
    _, comp = connected_components(coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n)),
                                   directed=False)
    order = np.argsort(comp, kind="stable")
    c = comp[order]
    start = np.r_[True, c[1:] != c[:-1]]
    first = order[np.flatnonzero(start)][np.cumsum(start) - 1]
    sel = first != order
    return np.stack([first[sel], order[sel]], axis=1).astype(np.int64)
