"""A :class:`~physavatar.importers.common.Source` -> a capture folder (docs/capture-format.md).

The capture is written into a hidden temporary folder beside ``OUT`` and renamed to ``OUT`` at
the end, so an error or Ctrl-C leaves no half-written capture. Frames are selected, pictures
undistorted and resized, cameras and meshes moved into the placed world (z up, metres), and
``capture.json`` records how (``import``: format, source, up axis, scale, the world matrix, the
number of source frames), so anything else the source holds can be converted by hand.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..capture import frame_name, save_cameras, save_capture_meta, save_png
from ..errors import PhysavatarError
from ..files import PlyMesh, write_ply
from ..progress import resolve
from .common import (
    AXES,
    FrameFilter,
    ImportOptions,
    Placement,
    Source,
    SourceCamera,
    estimate_up,
    log,
    parse_resolution,
    rotation_to_z,
    select_frames,
)
from .media import (
    Undistorter,
    VideoFrames,
    fit_to_image,
    image_size,
    read_image,
    resize,
    resized_K,
    target_size,
    video_info,
)


@dataclass
class ImportResult:
    out: Path
    format: str
    cameras: list[str]
    frames: list[int]
    fps: float
    up: str
    source_frames: int
    masks: bool
    meshes: int
    body: bool
    body_files: int
    warnings: list[str] = field(default_factory=list)


class _Warnings(logging.Handler):
    def __init__(self):
        super().__init__(logging.WARNING)
        self.items: list[str] = []

    def emit(self, record):
        self.items.append(record.getMessage())


def write_capture(source: Source, out: str | Path, options: ImportOptions, progress=None) -> ImportResult:
    """Write ``source`` as a capture folder ``out`` (which must not exist, or be empty)."""
    options.check()
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise PhysavatarError(out, "output exists and is not an empty folder")
    warnings = _Warnings()
    log.addHandler(warnings)
    try:
        return _write(source, out, options, progress, warnings)
    finally:
        log.removeHandler(warnings)


def _frame_rate(source: Source, options: ImportOptions) -> tuple[float, dict]:
    infos = {name: video_info(v.video) for name, v in source.views.items() if v.video is not None}
    rates = {name: i.fps for name, i in infos.items() if i.fps > 0}
    if rates and max(rates.values()) - min(rates.values()) > 1e-3 * max(rates.values()) and options.fps is None:
        shown = ", ".join(f"{n} {r:g}" for n, r in rates.items())
        raise PhysavatarError(source.views[next(iter(rates))].video.parent,
                              f"videos have different frame rates ({shown}); pass --fps to use one")
    fps = options.fps or source.fps or (next(iter(rates.values())) if rates else None)
    if fps is None:
        fps = source.default_fps
        log.warning("%s: the source does not say its frame rate: %g fps assumed (set it with --fps)",
                    source.calibration, fps)
    return float(fps), infos


def _common_image_frames(source: Source, options: ImportOptions) -> list[int]:
    sets = {name: set(v.images) for name, v in source.views.items() if v.video is None}
    if not sets:
        return []
    for name, s in sets.items():
        if not s:
            raise PhysavatarError(source.root, f"camera {name!r} has no images")
    union = set().union(*sets.values())
    common = set.intersection(*sets.values())
    if common != union:
        worst = min(sets, key=lambda n: len(sets[n]))
        missing = sorted(union - sets[worst])
        shown = ", ".join(map(str, missing[:5])) + (" ..." if len(missing) > 5 else "")
        where = next(iter(source.views[worst].images.values())).parent
        if not options.truncate:
            raise PhysavatarError(where, f"camera {worst!r} lacks {len(missing)} of the {len(union)} frames the other "
                                         f"cameras have ({shown}); pass --truncate to keep only the frames all cameras have")
        log.warning("%s: cameras have different frames: keeping the %d frames all %d cameras have",
                    where, len(common), len(sets))
    if not common:
        raise PhysavatarError(source.root, "no frame is present in every camera")
    return sorted(common)


def _placement(source: Source, options: ImportOptions, first_frame: int | None) -> Placement:
    up = options.up if options.up != "auto" else estimate_up(source.cameras, source.calibration)
    p = Placement(up, options.scale, rotation_to_z(AXES[up]), np.zeros(3))
    if options.floor == "auto":
        if first_frame is not None and first_frame in source.meshes:
            v, _, _ = source.meshes[first_frame]()
            p.offset = np.array([0.0, 0.0, -p.points(v)[:, 2].min()])
    elif options.floor != "keep":
        p.offset = np.array([0.0, 0.0, -float(options.floor)])
    return p


def _write(source: Source, out: Path, options: ImportOptions, progress, warnings: _Warnings) -> ImportResult:
    if not source.cameras:
        raise PhysavatarError(source.calibration, "no cameras in the calibration")
    names = [c.name for c in source.cameras]
    for name in names:
        if not name or name in (".", "..") or "/" in name or "\\" in name or name.startswith("."):
            raise PhysavatarError(source.calibration, f"camera name {name!r} cannot be a folder name")
        if names.count(name) > 1:
            raise PhysavatarError(source.calibration, f"two cameras are named {name!r}")
    for cam in source.cameras:
        v = source.views.get(cam.name)
        if v is None or (v.video is None and not v.images):
            raise PhysavatarError(source.calibration, f"camera {cam.name!r} has no images or video")
    fps, infos = _frame_rate(source, options)
    image_frames = _common_image_frames(source, options)
    selected = select_frames(image_frames, options, fps) if image_frames else []
    if infos:
        declared = {n: i.frames for n, i in infos.items() if i.frames > 0}
        if len(set(declared.values())) > 1 and not options.truncate:
            _raise_counts(source, declared)
    if image_frames and not selected:
        raise PhysavatarError(source.root, f"the frame options keep none of the {len(image_frames)} frames")
    placement = _placement(source, options, selected[0] if selected else (0 if infos else None))
    resolution = parse_resolution(options.resolution)

    parent = out.parent
    parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.importing-", dir=parent))
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o777 & ~umask)  # mkdtemp makes 0700; the capture gets the usual permissions
    try:
        cams, kept, decoded, masks = _write_pictures(source, tmp, options, fps, selected, placement, resolution, infos,
                                                     progress)
        frames = sorted(set.intersection(*(set(k) for k in kept.values())))
        n_meshes = _write_meshes(source, tmp, frames, placement)
        n_body = _copy_body_files(source, tmp, frames)
        source_ids = image_frames or list(range(min(decoded.values())))
        source_frames = len(source_ids)
        if options.anny is not None:
            from .anny import read_anny_poses  # Anny (torch) is loaded only for this

            read_anny_poses(options.anny, source_ids, frames, placement).save(tmp / "body.npz")
        meta = {
            "import": {
                "format": source.format,
                "source": str(source.root.resolve()),
                "up": placement.up,
                "scale": placement.scale,
                "world_from_source": placement.matrix.tolist(),
                "undistorted": any(c.distorted for c in source.cameras),
                "source_frames": source_frames,
                "meshes": "meshes/" if n_meshes else None,
                "source_body": sorted(source.body_files) if n_body else [],
                "body": str(Path(options.anny).resolve()) if options.anny is not None else None,
                **source.notes,
            }
        }
        save_capture_meta(tmp, fps=fps, frames=frames, extra=meta)
        save_cameras(tmp, cams)
        if out.exists():
            out.rmdir()  # checked empty above
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return ImportResult(out, source.format, [c.name for c in cams], frames, fps, placement.up, source_frames,
                        masks, n_meshes, options.anny is not None, n_body, warnings.items)


def _raise_counts(source: Source, counts: dict[str, int]):
    values = sorted(counts.values())
    majority = max(set(values), key=values.count)
    odd = next(n for n, c in counts.items() if c != majority)
    shown = ", ".join(f"{n} {c}" for n, c in counts.items())
    raise PhysavatarError(source.views[odd].video, f"frame counts differ between cameras ({shown}); "
                                                   f"pass --truncate to keep the first {min(values)} frames of every camera")


def _output_camera(cam: SourceCamera, placement: Placement, resolution) -> tuple[Camera, tuple[int, int]]:
    size = target_size(cam.width, cam.height, resolution)
    K = resized_K(cam.K, (cam.width, cam.height), size)
    return Camera(cam.name, size[0], size[1], K, placement.w2c(cam.w2c)), size


def _write_pictures(source: Source, tmp: Path, options: ImportOptions, fps: float, selected: list[int],
                    placement: Placement, resolution, infos: dict, progress):
    prog = resolve(progress)
    with_masks = all(v.masks for v in source.views.values())
    if not with_masks and any(v.masks for v in source.views.values()):
        log.warning("%s: only some cameras have masks: masks are left out", source.root)
    cams, kept, decoded = [], {}, {}
    total = 0
    for cam in source.cameras:  # videos: as many as their declared lengths allow
        info = infos.get(cam.name)
        total += len(selected) if info is None else len(select_frames(range(info.frames), options, fps))
    with prog.task(f"import {source.format}", total=total or None) as task:
        for cam in source.cameras:
            view = source.views[cam.name]
            if view.video is None:
                first = view.images[selected[0]]
                cam = fit_to_image(cam, *image_size(first), first)
                frames_iter = ((f, read_image(view.images[f]), view.images[f]) for f in selected)
            else:
                info = infos[cam.name]
                cam = fit_to_image(cam, info.width, info.height, view.video)
                video = VideoFrames(view.video, FrameFilter(options, fps, 0))
                frames_iter = ((i, img, view.video) for i, img in video)
            out_cam, size = _output_camera(cam, placement, resolution)
            undistort = Undistorter(cam)
            kept[cam.name] = []
            for f, img, where in frames_iter:
                if img.shape[:2] != (cam.height, cam.width):
                    raise PhysavatarError(where, f"frame {f} is {img.shape[1]}x{img.shape[0]} but the other pictures "
                                                 f"of camera {cam.name!r} are {cam.width}x{cam.height}")
                save_png(tmp / "images" / cam.name / f"{frame_name(f)}.png", resize(undistort(img), size))
                if with_masks:
                    mpath = view.masks.get(f)
                    if mpath is None:
                        raise PhysavatarError(where, f"camera {cam.name!r} has no mask for frame {f}")
                    m = read_image(mpath, "L")
                    if m.shape != (cam.height, cam.width):
                        raise PhysavatarError(mpath, f"mask is {m.shape[1]}x{m.shape[0]} but camera {cam.name!r} "
                                                     f"is {cam.width}x{cam.height}")
                    save_png(tmp / "masks" / cam.name / f"{frame_name(f)}.png", resize(undistort(m), size))
                kept[cam.name].append(f)
                task.advance(1, camera=cam.name, frame=f)
            if view.video is not None:
                decoded[cam.name] = video.count
            if not kept[cam.name]:
                raise PhysavatarError(view.video or source.root, f"the frame options keep no frame of camera {cam.name!r}")
            cams.append(out_cam)
    _check_video_counts(source, tmp, kept, decoded, options)
    return cams, kept, decoded, with_masks


def _check_video_counts(source: Source, tmp: Path, kept: dict[str, list[int]], decoded: dict[str, int],
                        options: ImportOptions) -> None:
    """Videos decoded to different lengths: an error, or (``--truncate``) every camera cut to the shortest."""
    videos = {n: source.views[n].video for n in decoded}
    if len(set(decoded.values())) <= 1:
        return
    if not options.truncate:
        _raise_counts(source, decoded)
    last = min(decoded.values()) - 1
    for n in videos:
        for f in [f for f in kept[n] if f > last]:
            for kind in ("images", "masks"):
                p = tmp / kind / n / f"{frame_name(f)}.png"
                if p.exists():
                    p.unlink()
        kept[n] = [f for f in kept[n] if f <= last]
    log.warning("%s: videos have different lengths (%s): every camera cut to the first %d frames",
                next(iter(videos.values())).parent, ", ".join(f"{n} {c}" for n, c in decoded.items()), last + 1)


def _write_meshes(source: Source, tmp: Path, frames: list[int], placement: Placement) -> int:
    n = 0
    for f in frames:
        load = source.meshes.get(f)
        if load is None:
            continue
        v, faces, data = load()
        write_ply(tmp / "meshes" / f"{frame_name(f)}.ply", PlyMesh(placement.points(v), faces, data))
        n += 1
    return n


def _copy_body_files(source: Source, tmp: Path, frames: list[int]) -> int:
    n = 0
    for kind, files in source.body_files.items():
        for f in frames:
            p = files.get(f)
            if p is None:
                continue
            dst = tmp / "source_body" / kind / f"{frame_name(f)}{p.suffix}"
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(p, dst)
            n += 1
    return n
