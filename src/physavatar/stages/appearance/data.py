"""What the appearance fit reads: the capture (images, masks, cameras), the mesh sequence
(tracked or ground truth, through :class:`~physavatar.data.tracked.TrackedSequence`), the
per-face colours of tracking, and the training targets (linear images, eroded masks)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path

import numpy as np

from ...camera import Camera
from ...capture import Capture, Template, load_capture
from ...data.tracked import TrackedSequence
from ...errors import PhysavatarError
from ...files import content_key
from ...render import srgb_to_linear
from .texture import uv_atlas


@dataclass
class AppearanceData:
    """What the fit needs.

    Attributes:
        capture: the loaded capture (images, masks, cameras).
        template: faces [F, 3], labels [V], face_uvs [F, 3, 2] (xatlas-generated if the capture
            has none).
        vertices: [T, V, 3] mesh per used frame; frames: [T] capture frame ids.
        face_colors: [T, F, 3] linear per-face colours from tracking, or None (read from images).
        source: "tracked" or "gt".
    """

    capture: Capture
    template: Template
    vertices: np.ndarray
    frames: list[int]
    face_colors: np.ndarray | None
    source: str
    cameras: list[Camera] = field(default_factory=list)

    @cached_property
    def key(self) -> str:
        """The content key (files.content_key) of everything a fit reads from this data: the
        meshes, tracked colours, template (faces, labels, uvs), frames, cameras, and the
        images and masks of those frames and cameras. T_0, the environment map and the
        checkpoint are read back from an output folder only when made with this key."""
        t = self.template
        paths = [p for f in self.frames for c in self.cameras
                 for p in (self.capture.image_path(c.name, f), self.capture.mask_path(c.name, f))]
        extra = [] if self.face_colors is None else [self.face_colors]
        return content_key(self.vertices, t.faces, t.labels, *([] if t.face_uvs is None else [t.face_uvs]), *extra,
                           *paths, frames=[int(f) for f in self.frames], cameras=[c.to_dict() for c in self.cameras],
                           tracked_colors=self.face_colors is not None)


def load_appearance_data(capture: str | Path | Capture, tracked: str | Path | None = None, meshes: str = "tracked",
                         texture_size: int = 512, cameras: Sequence[str] | None = None) -> AppearanceData:
    """Capture + mesh sequence: ``meshes="tracked"`` reads ``tracked/tracked.npz`` (vertices,
    face_colors, frames); ``"gt"`` reads ``ground_truth/meshes.npz`` (per-face colours then come
    from the tracked folder when given, else from the images). Both are read as a
    :class:`~physavatar.data.tracked.TrackedSequence`. ``cameras`` None: every camera but those
    the tracking held out (``tracked/config.json``), which ``evaluate`` scores."""
    cap = capture if isinstance(capture, Capture) else load_capture(capture)
    t = cap.template
    colors = None
    tr = None
    if tracked is not None:
        tr = TrackedSequence.load(tracked, require=("vertices", "face_colors", "frames"))
        if tr.vertices.shape[1:] != t.vertices.shape or tr.face_colors.shape[1:] != (len(t.faces), 3):
            raise PhysavatarError(tr.path, "vertices/face_colors do not match the template")
    if meshes == "tracked":
        if tr is None:
            raise PhysavatarError(None, "option --tracked: needed with --meshes tracked "
                                        "(or pass --meshes gt for a synthetic capture)")
        V, frames, colors = tr.vertices, [int(f) for f in tr.frames], tr.face_colors
    elif meshes == "gt":
        if cap.ground_truth is None:
            raise PhysavatarError(cap.root, "meshes 'gt' needs ground_truth/meshes.npz (synthetic captures only)")
        V = TrackedSequence.load(cap.ground_truth / "meshes.npz").vertices
        if V.shape[1:] != t.vertices.shape or len(V) != len(cap.frames):
            raise PhysavatarError(cap.ground_truth / "meshes.npz", f"vertices {V.shape} do not match the template "
                                  f"({len(t.vertices)} vertices) and {len(cap.frames)} frames")
        frames = list(cap.frames)
        if tr is not None:  # tracked Gaussian colours for the frames the tracker covered
            tf = [int(f) for f in tr.frames]
            keep = [frames.index(f) for f in tf]
            V, frames, colors = V[keep], tf, tr.face_colors
    else:
        raise PhysavatarError(None, f"meshes must be 'tracked' or 'gt', got {meshes!r}")
    if not np.isfinite(V).all():
        raise PhysavatarError(None, "mesh sequence contains non-finite vertices")
    if t.face_uvs is None:
        t = replace(t, face_uvs=uv_atlas(t.vertices, t.faces, texture_size))
    cams = list(cap.cameras)
    if cameras is None and tracked is not None:
        # the cameras the tracking held out are scored by `evaluate`: the texture must not see them
        held = set(tracking_holdout(tracked))
        if held and len(held) < len(cams):
            cams = [c for c in cams if c.name not in held]
    if cameras is not None:
        names = {c.name for c in cams}
        bad = [c for c in cameras if c not in names]
        if bad:
            raise PhysavatarError(cap.root / "cameras.json", f"unknown cameras {bad}")
        cams = [c for c in cams if c.name in set(cameras)]
    return AppearanceData(cap, t, np.asarray(V, np.float64), frames,
                          None if colors is None else np.asarray(colors, np.float64),
                          meshes, cams)


def tracking_holdout(tracked: str | Path) -> tuple[str, ...]:
    """The cameras the tracking stage held out (its ``config.json``'s ``holdout``), () if none."""
    from ...files import read_json

    p = Path(tracked)
    cfg = (p if p.is_dir() else p.parent) / "config.json"
    if not cfg.is_file():
        return ()
    return tuple(read_json(cfg).get("holdout") or ())


def _resize(a: np.ndarray, w: int, h: int) -> np.ndarray:
    """Area-average resize of a float [H, W] or [H, W, C] image (PIL's box filter)."""
    from PIL import Image

    if a.shape[1] == w and a.shape[0] == h:
        return a.astype(np.float32)
    chans = a[..., None] if a.ndim == 2 else a
    out = np.stack([np.asarray(Image.fromarray(np.ascontiguousarray(chans[..., c], np.float32))
                               .resize((w, h), Image.BOX)) for c in range(chans.shape[2])], -1)
    return out[..., 0] if a.ndim == 2 else out


def load_target(capture: Capture, cam: Camera, frame: int, scale: float, erode_px: int) -> tuple[np.ndarray, np.ndarray]:
    """Linear target image [h, w, 3] and loss mask [h, w] (bool) at ``scale``.

    The mask is the foreground (alpha > 0.5) eroded by ``erode_px`` capture pixels (A.4: the
    silhouette's pixels mix foreground and background), then kept only where a downsampled pixel
    lies wholly inside it.
    """
    from scipy.ndimage import binary_erosion

    img = srgb_to_linear(capture.image(cam.name, frame)).astype(np.float32)
    m = capture.mask(cam.name, frame) > 0.5
    if erode_px > 0:
        m = binary_erosion(m, structure=np.ones((3, 3), bool), iterations=erode_px)
    small = cam.scaled(scale)
    w, h = small.width, small.height
    return _resize(img, w, h), _resize(m.astype(np.float32), w, h) > 0.999
