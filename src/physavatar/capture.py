"""The capture folder: cameras, frames, images, masks, body poses, template; load, validate, save.

Layout (docs/capture-format.md)::

    capture.json              format version, fps, frame ids, units, up axis, garment source
    cameras.json              [{name, width, height, K, w2c}]
    images/<camera>/<frame>.png
    masks/<camera>/<frame>.png          optional; foreground alpha
    body.npz                  Anny shape + per-frame bone rotations + root translation
    template/mesh.ply         frame-1 mesh: vertices, faces, label, boundary, optional UVs
    ground_truth/             synthetic captures only

``load_capture`` checks everything it reads and raises :class:`CaptureError` naming the file and
the problem; ``validate_capture`` collects every problem instead of stopping at the first.
Nothing is ever written into a capture folder by loading or validating.

An **unprepared** capture (straight from ``physavatar import`` or a rig) has capture.json,
cameras.json and images but lacks what ``physavatar prepare`` fills in (:data:`PREPARED_PARTS`:
body.npz, a labelled template/mesh.ply; masks are optional anyway). Loading one fails with a
single line that says so; ``load_unprepared`` reads and checks the parts it must have.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from .body.model import PHENOTYPES, BodyShape
from .camera import Camera
from .errors import CaptureError, PhysavatarError
from .files import PlyMesh, atomic_path, load_npz, read_json, read_ply, save_npz_atomic, write_json_atomic, write_ply
from .labels import LABEL_BODY, MAX_LABEL

FORMAT_VERSION = 1


def frame_name(frame_id: int) -> str:
    return f"{int(frame_id):06d}"


@dataclass
class Template:
    """The frame-1 mesh of body and garments in one surface.

    Attributes:
        vertices: [V, 3] metres. faces: [F, 3].
        labels: [V] 0 body, 1.. garment id.
        boundary: [V] bool, garment vertices that stay on the body (Dirichlet).
        face_uvs: [F, 3, 2] per-corner UVs or None.
        rest: [V, 3] the garments' stress-free shape (PLY ``rest_x rest_y rest_z``), or None:
            the garments rest as they are in frame 1. Only garment rows are used.
    """

    vertices: np.ndarray
    faces: np.ndarray
    labels: np.ndarray
    boundary: np.ndarray
    face_uvs: np.ndarray | None = None
    rest: np.ndarray | None = None

    @property
    def garment_mask(self) -> np.ndarray:
        return self.labels > LABEL_BODY

    @property
    def rest_shape(self) -> np.ndarray:
        """[V, 3] the stress-free shape: ``rest`` where given, else the frame-1 positions."""
        return self.vertices if self.rest is None else self.rest

    def to_ply(self) -> PlyMesh:
        data = {"label": self.labels.astype(np.uint8), "boundary": self.boundary.astype(np.uint8)}
        if self.rest is not None:
            data |= {f"rest_{a}": self.rest[:, i] for i, a in enumerate("xyz")}
        return PlyMesh(self.vertices, self.faces, data, self.face_uvs)

    def save(self, path: str | Path) -> None:
        write_ply(path, self.to_ply())


@dataclass
class BodyPoses:
    """Contents of body.npz: shape [6] (Anny phenotypes), rotations [T, B, 3], root_translation [T, 3]."""

    shape: BodyShape
    bone_names: list[str]
    rotations: np.ndarray
    root_translation: np.ndarray
    topology: str = "full"

    def save(self, path: str | Path) -> None:
        save_npz_atomic(path, shape=self.shape.as_array(), shape_names=np.array(PHENOTYPES),
                        bone_names=np.array(self.bone_names), rotations=self.rotations,
                        root_translation=self.root_translation, topology=np.array(self.topology),
                        model=np.array("anny"))


@dataclass
class Capture:
    """A loaded capture folder (images are read lazily: ``image(cam, frame)``)."""

    root: Path
    meta: dict
    cameras: list[Camera]
    frames: list[int]
    body: BodyPoses
    template: Template
    has_masks: bool

    @property
    def fps(self) -> float:
        return float(self.meta["fps"])

    def camera(self, name: str) -> Camera:
        for c in self.cameras:
            if c.name == name:
                return c
        raise KeyError(name)

    def image_path(self, cam: str, frame: int) -> Path:
        return self.root / "images" / cam / f"{frame_name(frame)}.png"

    def mask_path(self, cam: str, frame: int) -> Path:
        return self.root / "masks" / cam / f"{frame_name(frame)}.png"

    def image(self, cam: str, frame: int) -> np.ndarray:
        """[H, W, 3] float32 sRGB values in [0, 1]."""
        return _read_png(self.image_path(cam, frame), "RGB")

    def mask(self, cam: str, frame: int) -> np.ndarray:
        """[H, W] float32 in [0, 1] (all ones when the capture has no masks)."""
        if not self.has_masks:
            c = self.camera(cam)
            return np.ones((c.height, c.width), np.float32)
        return _read_png(self.mask_path(cam, frame), "L")

    @property
    def ground_truth(self) -> Path | None:
        p = self.root / "ground_truth"
        return p if p.is_dir() else None


# -- reading and validation ----------------------------------------------------------------------

def _read_png(path: Path, mode: str) -> np.ndarray:
    try:
        with Image.open(path) as im:
            im.load()
            arr = np.asarray(im.convert(mode), dtype=np.float32) / 255.0
    except FileNotFoundError:
        raise CaptureError(path, "file not found") from None
    except Exception as e:
        raise CaptureError(path, f"unreadable or corrupt image ({type(e).__name__})") from None
    return arr


class _Problems:
    """Collects validation problems; in strict mode raises on the first one."""

    def __init__(self, strict: bool):
        self.strict = strict
        self.items: list[CaptureError] = []

    def add(self, path, problem):
        err = CaptureError(path, problem)
        if self.strict:
            raise err
        self.items.append(err)


def rigid_problem(w2c: np.ndarray) -> str | None:
    """What makes ``w2c`` [4, 4] not a rigid world-to-camera transform, or None."""
    if w2c.shape != (4, 4):
        return f"w2c must be 4x4, got {w2c.shape}"
    if not np.isfinite(w2c).all():
        return "w2c has NaN or infinite entries"
    R = w2c[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-4 or abs(np.linalg.det(R) - 1) > 1e-4:
        return "w2c rotation block is not a rotation (RᵀR ≠ I or det ≠ 1)"
    if np.abs(w2c[3] - [0, 0, 0, 1]).max() > 1e-9:
        return "w2c last row must be [0, 0, 0, 1]"
    return None


def _load_cameras(root: Path, P: _Problems) -> list[Camera]:
    path = root / "cameras.json"
    try:
        raw = read_json(path)
    except PhysavatarError as e:
        P.add(path, e.problem)
        return []
    if not isinstance(raw, list) or not raw:
        P.add(path, "must be a non-empty list of cameras")
        return []
    cams, seen = [], set()
    for i, c in enumerate(raw):
        where = f"camera {i}"
        if not isinstance(c, dict) or not {"name", "width", "height", "K", "w2c"} <= set(c):
            P.add(path, f"{where}: needs name, width, height, K, w2c")
            continue
        name = str(c["name"])
        where = f"camera {name!r}"
        if name in seen:
            P.add(path, f"{where}: duplicate name")
            continue
        seen.add(name)
        try:
            K = np.asarray(c["K"], dtype=np.float64)
            w2c = np.asarray(c["w2c"], dtype=np.float64)
            w, h = int(c["width"]), int(c["height"])
        except (TypeError, ValueError):
            P.add(path, f"{where}: K, w2c must be numeric matrices and width/height integers")
            continue
        if w <= 0 or h <= 0:
            P.add(path, f"{where}: width and height must be positive, got {w}x{h}")
            continue
        if K.shape != (3, 3) or not np.isfinite(K).all():
            P.add(path, f"{where}: K must be a finite 3x3 matrix")
            continue
        if K[0, 0] <= 0 or K[1, 1] <= 0 or np.abs(K[2] - [0, 0, 1]).max() > 1e-9:
            P.add(path, f"{where}: K must have positive focal lengths and last row [0, 0, 1]")
            continue
        msg = rigid_problem(w2c)
        if msg:
            P.add(path, f"{where}: {msg}")
            continue
        cams.append(Camera(name, w, h, K, w2c))
    return cams


def _load_meta(root: Path, P: _Problems) -> dict | None:
    path = root / "capture.json"
    try:
        meta = read_json(path)
    except PhysavatarError as e:
        P.add(path, e.problem)
        return None
    if not isinstance(meta, dict):
        P.add(path, "must be a JSON object")
        return None
    for key in ("format_version", "fps", "frames"):
        if key not in meta:
            P.add(path, f"missing key {key!r}")
            return None
    if meta["format_version"] != FORMAT_VERSION:
        P.add(path, f"format_version {meta['format_version']!r} is not supported (expected {FORMAT_VERSION})")
        return None
    try:
        fps = float(meta["fps"])
        frames = [int(f) for f in meta["frames"]]
    except (TypeError, ValueError):
        P.add(path, "fps must be a number and frames a list of integers")
        return None
    if not np.isfinite(fps) or fps <= 0:
        P.add(path, f"fps must be positive, got {meta['fps']}")
        return None
    if not frames:
        P.add(path, "frames is empty")
        return None
    if len(set(frames)) != len(frames) or frames != sorted(frames):
        P.add(path, "frames must be increasing and unique")
        return None
    if meta.get("units", "m") != "m" or meta.get("up", "z") != "z":
        P.add(path, "only units 'm' and up axis 'z' are supported")
        return None
    meta = dict(meta)
    meta["frames"] = frames
    return meta


def _load_body(root: Path, n_frames: int | None, P: _Problems) -> BodyPoses | None:
    path = root / "body.npz"
    try:
        z = load_npz(path)
    except PhysavatarError as e:
        P.add(path, e.problem)
        return None
    missing = [k for k in ("shape", "bone_names", "rotations", "root_translation") if k not in z]
    if missing:
        P.add(path, f"missing arrays {missing}")
        return None
    shape, rot, tr = z["shape"], z["rotations"], z["root_translation"]
    names = [str(b) for b in z["bone_names"]]
    ok = True
    if len(set(names)) != len(names) or "root" not in names:
        P.add(path, "'bone_names' must be unique Anny bone names including 'root'")
        ok = False
    if shape.shape != (len(PHENOTYPES),) or not np.isfinite(shape).all() or (shape < 0).any() or (shape > 1).any():
        P.add(path, f"'shape' must be {len(PHENOTYPES)} finite values in [0, 1] ({', '.join(PHENOTYPES)}), got shape {shape.shape}")
        ok = False
    if rot.ndim != 3 or rot.shape[1:] != (len(names), 3):
        P.add(path, f"'rotations' must have shape [frames, {len(names)} bones, 3], got {list(rot.shape)}")
        ok = False
    elif n_frames is not None and rot.shape[0] != n_frames:
        P.add(path, f"'rotations' has {rot.shape[0]} frames but capture.json lists {n_frames}")
        ok = False
    elif not np.isfinite(rot).all():
        bad = np.argwhere(~np.isfinite(rot))[0]
        P.add(path, f"'rotations' has NaN or infinite values (first at frame {bad[0]}, bone {names[bad[1]]!r})")
        ok = False
    if tr.shape != (rot.shape[0] if rot.ndim == 3 else -1, 3):
        P.add(path, f"'root_translation' must have shape [frames, 3], got {list(tr.shape)}")
        ok = False
    elif not np.isfinite(tr).all():
        P.add(path, "'root_translation' has NaN or infinite values")
        ok = False
    if not ok:
        return None
    topology = str(z["topology"]) if "topology" in z else "full"
    return BodyPoses(BodyShape.from_array(shape), names, rot, tr, topology)


def check_template_mesh(vertices: np.ndarray, faces: np.ndarray) -> list[str]:
    """Problems of a triangle mesh as a simulation/tracking template (empty list: fine)."""
    problems = []
    V = len(vertices)
    if V == 0 or len(faces) == 0:
        return ["mesh has no vertices or no faces"]
    if not np.isfinite(vertices).all():
        problems.append("vertices have NaN or infinite coordinates")
        return problems
    if faces.min() < 0 or faces.max() >= V:
        return [f"face indices out of range [0, {V})"]
    if ((faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 0] == faces[:, 2])).any():
        n = int(((faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 0] == faces[:, 2])).sum())
        problems.append(f"{n} degenerate faces repeat a vertex")
    a, b, c = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    scale = np.sqrt(np.median(area) + 1e-30)
    tiny = area < 1e-8 * max(scale, 1e-12) ** 2 + 1e-20
    if tiny.any():
        problems.append(f"{int(tiny.sum())} degenerate faces have (near) zero area (first: face {int(np.argmax(tiny))})")
    # Edge manifoldness: every undirected edge is used by at most two faces, and consistently
    # oriented (each directed edge at most once).
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    und = np.sort(e, axis=1)
    _, counts = np.unique(und, axis=0, return_counts=True)
    if (counts > 2).any():
        problems.append(f"non-manifold: {int((counts > 2).sum())} edges are shared by more than two faces")
    _, dcounts = np.unique(e, axis=0, return_counts=True)
    if (dcounts > 1).any():
        problems.append(f"inconsistent orientation or duplicate faces: {int((dcounts > 1).sum())} directed edges repeat")
    # Vertex manifoldness: the faces around each vertex form one fan (checked via the number of
    # boundary edges incident to a vertex: more than 2 means a bow-tie).
    bmask = counts == 1
    if bmask.any():
        uniq = np.unique(und, axis=0)
        bverts = uniq[bmask].ravel()
        per_vertex = np.bincount(bverts, minlength=V)
        if (per_vertex > 2).any():
            problems.append(f"non-manifold: {int((per_vertex > 2).sum())} vertices join separate surface sheets")
    unused = V - len(np.unique(faces))
    if unused:
        problems.append(f"{unused} vertices are not used by any face")
    return problems


def _load_template(root: Path, P: _Problems) -> Template | None:
    path = root / "template" / "mesh.ply"
    try:
        ply = read_ply(path)
    except PhysavatarError as e:
        P.add(path, e.problem)
        return None
    for prob in check_template_mesh(ply.vertices, ply.faces):
        P.add(path, prob)
        if "out of range" in prob or "NaN" in prob or "no vertices" in prob:
            return None
    V = len(ply.vertices)
    if "label" not in ply.vertex_data:
        P.add(path, "missing per-vertex property 'label' (0 body, 1.. garment)")
        return None
    labels = np.asarray(ply.vertex_data["label"]).astype(np.int64)
    if labels.min() < 0 or labels.max() > MAX_LABEL:
        P.add(path, f"labels out of range: found {labels.min()}..{labels.max()}, allowed 0..{MAX_LABEL}")
        return None
    boundary = np.asarray(ply.vertex_data.get("boundary", np.zeros(V))).astype(bool)
    if (boundary & (labels == LABEL_BODY)).any():
        P.add(path, f"{int((boundary & (labels == 0)).sum())} body vertices (label 0) are flagged as boundary; only garment vertices can be")
    for g in sorted(set(labels.tolist()) - {LABEL_BODY}):
        if not boundary[labels == g].any():
            P.add(path, f"garment {g} has no boundary vertices: a garment must be attached to the body "
                        "somewhere (shoulder straps, waistband) to be simulated")
    if ply.face_uvs is not None and not np.isfinite(ply.face_uvs).all():
        P.add(path, "texture coordinates have NaN or infinite values")
    rest = template_rest(ply, labels, path, P)
    return Template(ply.vertices, ply.faces, labels, boundary, ply.face_uvs, rest)


def template_rest(ply: PlyMesh, labels: np.ndarray, path: Path, P: _Problems | None = None) -> np.ndarray | None:
    """The template's optional garment rest shape (``rest_x rest_y rest_z``), checked: all three
    properties, finite, no garment triangle degenerate at rest. Problems go to ``P`` (or raise)."""
    P = P or _Problems(strict=True)
    keys = [f"rest_{a}" for a in "xyz"]
    present = [k for k in keys if k in ply.vertex_data]
    if not present:
        return None
    if len(present) < 3:
        P.add(path, f"rest shape needs all of {', '.join(keys)}; found only {', '.join(present)}")
        return None
    rest = np.stack([np.asarray(ply.vertex_data[k], np.float64) for k in keys], axis=1)
    if not np.isfinite(rest).all():
        P.add(path, "rest shape (rest_x/y/z) has NaN or infinite values")
        return None
    g = (labels[ply.faces] > LABEL_BODY).all(axis=1)  # garment triangles
    e1, e2 = rest[ply.faces[g, 1]] - rest[ply.faces[g, 0]], rest[ply.faces[g, 2]] - rest[ply.faces[g, 0]]
    area = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)
    scale = float(np.median(np.linalg.norm(e1, axis=1))) if len(e1) else 0.0
    tiny = area <= 1e-6 * scale * scale
    if tiny.any():
        P.add(path, f"{int(tiny.sum())} garment triangles are degenerate in the rest shape "
                    f"(first: face {int(np.flatnonzero(g)[np.argmax(tiny)])})")
        return None
    return rest


def _check_images(root: Path, cameras: list[Camera], frames: list[int], has_masks: bool, P: _Problems,
                  deep: bool) -> None:
    for kind in ("images", "masks") if has_masks else ("images",):
        for cam in cameras:
            folder = root / kind / cam.name
            if not folder.is_dir():
                P.add(folder, f"missing folder of {kind} for camera {cam.name!r}")
                continue
            missing = [f for f in frames if not (folder / f"{frame_name(f)}.png").is_file()]
            if missing:
                shown = ", ".join(frame_name(f) for f in missing[:5]) + (" ..." if len(missing) > 5 else "")
                P.add(folder, f"{len(missing)} of {len(frames)} frames missing for camera {cam.name!r} ({shown})")
            for f in frames if deep else frames[:1]:
                path = folder / f"{frame_name(f)}.png"
                if not path.is_file():
                    continue
                try:
                    with Image.open(path) as im:
                        size = im.size
                        if deep:
                            im.load()
                except Exception as e:
                    P.add(path, f"unreadable or corrupt image ({type(e).__name__})")
                    continue
                if size != (cam.width, cam.height):
                    P.add(path, f"image is {size[0]}x{size[1]} but camera {cam.name!r} is {cam.width}x{cam.height}")


PREPARED_PARTS = ("body.npz", "template/mesh.ply")


def unprepared_parts(root: str | Path) -> list[str]:
    """The parts ``physavatar prepare`` fills in that the capture lacks (empty: prepared).
    A template/mesh.ply without per-vertex labels (an imported scan) counts as missing."""
    root = Path(root)
    missing = [p for p in PREPARED_PARTS if not (root / p).is_file()]
    t = root / "template" / "mesh.ply"
    if t.is_file() and not _ply_has_property(t, "label"):
        missing.append("labels in template/mesh.ply")
    return missing


def _ply_has_property(path: Path, name: str) -> bool:
    """Whether a PLY header declares a vertex property ``name`` (reads the header only)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(4096).split(b"end_header")[0].decode("ascii", "replace")
    except OSError:
        return False
    return any(line.split()[-1:] == [name] for line in head.splitlines() if line.startswith("property"))


def is_unprepared(root: str | Path) -> bool:
    """A capture folder (capture.json, cameras.json) that ``physavatar prepare`` must complete."""
    root = Path(root)
    return (root / "capture.json").is_file() and (root / "cameras.json").is_file() and bool(unprepared_parts(root))


def unprepared_message(root: Path, missing: list[str]) -> str:
    return (f"unprepared capture (no {', '.join(missing)}): run `physavatar prepare {root} OUT` first, "
            "or `physavatar run`, which prepares it")


@dataclass
class RawCapture:
    """The parts every capture has, prepared or not: what ``physavatar prepare`` starts from."""

    root: Path
    meta: dict
    cameras: list[Camera]
    frames: list[int]
    has_masks: bool

    def image_path(self, cam: str, frame: int) -> Path:
        return self.root / "images" / cam / f"{frame_name(frame)}.png"

    def mask_path(self, cam: str, frame: int) -> Path:
        return self.root / "masks" / cam / f"{frame_name(frame)}.png"


def load_unprepared(root: str | Path, deep: bool = False) -> RawCapture:
    """Read and check capture.json, cameras.json, the images (and masks when present) of a
    capture that may lack body.npz and the template; raise CaptureError on the first problem."""
    root = Path(root)
    P = _Problems(strict=True)
    if not root.is_dir():
        P.add(root, "capture folder not found")
    meta = _load_meta(root, P)
    cameras = _load_cameras(root, P)
    has_masks = (root / "masks").is_dir()
    _check_images(root, cameras, meta["frames"], has_masks, P, deep)
    return RawCapture(root, meta, cameras, meta["frames"], has_masks)


def _load(root: str | Path, strict: bool, deep: bool) -> tuple[Capture | None, list[CaptureError]]:
    root = Path(root)
    P = _Problems(strict)
    if not root.is_dir():
        P.add(root, "capture folder not found")
        return None, P.items
    meta = _load_meta(root, P)
    cameras = _load_cameras(root, P)
    frames = meta["frames"] if meta else None
    missing = unprepared_parts(root)
    if meta and cameras and missing:  # one line, not one per missing file
        has_masks = (root / "masks").is_dir()
        _check_images(root, cameras, frames, has_masks, P, deep)
        P.add(root, unprepared_message(root, missing))
        return None, P.items
    body = _load_body(root, len(frames) if frames else None, P)
    template = _load_template(root, P)
    has_masks = (root / "masks").is_dir()
    if meta and cameras:
        _check_images(root, cameras, frames, has_masks, P, deep)
    if P.items or meta is None or not cameras or body is None or template is None:
        return None, P.items
    return Capture(root, meta, cameras, frames, body, template, has_masks), []


def load_capture(root: str | Path, deep: bool = False) -> Capture:
    """Load and validate a capture folder; raise CaptureError (file + problem) on the first problem.

    ``deep`` decodes every image (slow) instead of checking every file exists and the first
    frame's images decode at the right size.
    """
    cap, _ = _load(root, strict=True, deep=deep)
    assert cap is not None
    return cap


def validate_capture(root: str | Path, deep: bool = True) -> list[CaptureError]:
    """Every problem of a capture folder (empty list: valid)."""
    _, problems = _load(root, strict=False, deep=deep)
    return problems


# -- writing -------------------------------------------------------------------------------------

def save_capture_meta(root: Path, *, fps: float, frames: list[int], extra: dict | None = None) -> None:
    meta = {"format_version": FORMAT_VERSION, "fps": float(fps), "frames": [int(f) for f in frames],
            "units": "m", "up": "z"}
    meta.update(extra or {})
    write_json_atomic(root / "capture.json", meta)


def save_cameras(root: Path, cameras: list[Camera]) -> None:
    write_json_atomic(root / "cameras.json", [c.to_dict() for c in cameras])


def save_png(path: str | Path, array: np.ndarray) -> None:
    """Write an image atomically. float arrays are taken as [0, 1]; uint8 as is."""
    a = np.asarray(array)
    if a.dtype != np.uint8:
        a = (np.clip(a.astype(np.float64), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    with atomic_path(path) as tmp:
        Image.fromarray(a).save(tmp, format="PNG")


def summarize(cap: Capture) -> dict:
    """The numbers ``physavatar inspect`` prints."""
    t = cap.template
    res = sorted({(c.width, c.height) for c in cap.cameras})
    return {
        "folder": str(cap.root),
        "cameras": len(cap.cameras),
        "resolution": ", ".join(f"{w}x{h}" for w, h in res),
        "frames": len(cap.frames),
        "fps": cap.fps,
        "duration_s": round((len(cap.frames) - 1) / cap.fps, 3),
        "template_vertices": int(len(t.vertices)),
        "template_faces": int(len(t.faces)),
        "body_vertices": int((t.labels == LABEL_BODY).sum()),
        "garment_vertices": int(t.garment_mask.sum()),
        "garments": sorted(int(g) for g in set(t.labels.tolist()) - {LABEL_BODY}),
        "boundary_vertices": int(t.boundary.sum()),
        "uvs": t.face_uvs is not None,
        "masks": cap.has_masks,
        "body_model": f"anny ({cap.body.topology} topology, {len(cap.body.bone_names)} bones)",
        "body_shape": cap.body.shape.to_dict(),
        "garment_source": cap.meta.get("garment_source", "unknown"),
        "ground_truth": cap.ground_truth is not None,
    }
