"""The tracking stage's entry point: :func:`run` (checks, resume, the frame loop, outputs)."""

from __future__ import annotations

import csv
import io
import logging
import time
from dataclasses import dataclass, fields, is_dataclass, replace
from pathlib import Path

import numpy as np
import torch

from ...camera import Camera
from ...capture import Capture, frame_name, load_capture
from ...data.material import material_file
from ...data.tracked import FILE as TRACKED, TrackedSequence
from ...errors import PhysavatarError
from ...files import PlyMesh, content_key, load_npz, read_json, save_npz_atomic, write_json_atomic, write_ply, write_text_atomic
from ...progress import resolve
from ..base import to_dict
from .config import TrackConfig, fit_scale
from .fit import fit_frame, smoothing_solver
from .gaussians import MeshGaussians
from .losses import AnchorLoss, CollisionLoss, IsometryLoss, NormalLoss
from .flow import BEND_REFERENCES
from .prediction import FrameStarts
from .views import initial_colors, load_views

logger = logging.getLogger("physavatar.progress")
PLAIN_FILE = "garment_texture.json"  # the plain-garment rule's measure and decision (flow.plain)

LOG_COLUMNS = ("frame", "iterations", "loss", "render", "l1", "ssim", "mask", "iso", "normal", "anchor", "collision", "seconds")


def default_holdout(camera_names: list[str]) -> tuple[str, ...]:
    """Two held-out cameras (as the paper), half a rig apart: positions 1 and 1 + C/2 in the
    capture's order. Captures with fewer than six cameras keep every view for fitting."""
    C = len(camera_names)
    if C < 6:
        return ()
    return (camera_names[1], camera_names[1 + C // 2])


def _check_config(cfg: TrackConfig, capture: Capture) -> tuple[list[Camera], list[int]]:
    """(training cameras, frames to track) of ``cfg`` on ``capture``; bad settings raise one
    :class:`PhysavatarError` (naming the option where the setting has one)."""
    fit, loss, pred, flow = cfg.fit, cfg.loss, cfg.prediction, cfg.flow
    names = [c.name for c in capture.cameras]
    hold = default_holdout(names) if cfg.holdout is None else cfg.holdout
    unknown = [h for h in hold if h not in names]
    if unknown:
        raise PhysavatarError(capture.root / "cameras.json",
                              f"held-out camera(s) {', '.join(unknown)} not in the capture (cameras: {', '.join(names)})")
    train = [c for c in capture.cameras if c.name not in hold]
    if not train:
        raise PhysavatarError(None, f"option --holdout: holding out {', '.join(hold)} leaves no camera to fit")
    n = len(capture.frames) if cfg.n_frames is None else cfg.n_frames
    if n < 1 or n > len(capture.frames):
        raise PhysavatarError(None, f"option --frames: must be between 1 and {len(capture.frames)} (the capture's frames), got {n}")
    if not 0 < fit.scale <= 1:
        raise PhysavatarError(None, f"option --scale: must be in (0, 1], got {fit.scale}")
    if fit.iters < 1 or fit.iters_first < 1:
        raise PhysavatarError(None, "options --iters/--iters-first: need at least one iteration")
    if fit.first_vertex_iters < 0:
        raise PhysavatarError(None, f"fit.first_vertex_iters must be >= 0 (0: frame 1 held), got {fit.first_vertex_iters}")
    if pred.init not in ("mixed", "lbs", "velocity"):
        raise PhysavatarError(None, f"init must be 'mixed', 'lbs' or 'velocity', got {pred.init!r}")
    if fit.vertex_optimizer not in ("uniform", "adam"):
        raise PhysavatarError(None, f"vertex_optimizer must be 'uniform' or 'adam', got {fit.vertex_optimizer!r}")
    if loss.normal_mode not in ("paper", "rest"):
        raise PhysavatarError(None, f"normal_mode must be 'paper' or 'rest', got {loss.normal_mode!r}")
    if not fit.levels or any(not 0 < lv <= 1 for lv in fit.levels):
        raise PhysavatarError(None, f"levels must be fractions in (0, 1], got {fit.levels}")
    if fit.level_iters is not None and (len(fit.level_iters) != len(fit.levels) or min(fit.level_iters) < 1):
        raise PhysavatarError(None, f"level_iters needs one count >= 1 per level {fit.levels}, got {fit.level_iters}")
    if pred.garment not in ("velocity", "physics", "flow"):
        raise PhysavatarError(None, f"garment_prediction must be 'velocity', 'physics' or 'flow', got {pred.garment!r}")
    numeric = [f.name for f in fields(flow) if f.name not in ("channels", "bend_reference", "correction_bend_reference",
                                                               "carry", "plain")]
    if min(getattr(flow, k) for k in numeric) < 0:
        raise PhysavatarError(None, "the flow_* settings must be >= 0, got "
                                    + ", ".join(f"flow_{k}={getattr(flow, k)}" for k in numeric))
    if flow.channels not in ("luma", "colour"):
        raise PhysavatarError(None, f"flow.channels must be 'luma' or 'colour', got {flow.channels!r}")
    lifts = [r for r in BEND_REFERENCES if r != "previous"]  # "previous" is for the corrections alone
    if flow.bend_reference not in lifts or flow.correction_bend_reference not in ("", *BEND_REFERENCES):
        raise PhysavatarError(None, f"flow.bend_reference must be one of {', '.join(lifts)} and "
                                    f"flow.correction_bend_reference '' or one of {', '.join(BEND_REFERENCES)}, got "
                                    f"{flow.bend_reference!r}, {flow.correction_bend_reference!r}")
    if not 0 <= flow.fit_blend <= 1:
        raise PhysavatarError(None, f"flow.fit_blend must be in [0, 1], got {flow.fit_blend}")
    if flow.carry not in CARRY:
        raise PhysavatarError(None, f"flow.carry must be one of {', '.join(CARRY)}, got {flow.carry!r}")
    if flow.plain not in ("auto", "plain", "patterned"):
        raise PhysavatarError(None, f"flow.plain must be 'auto', 'plain' or 'patterned', got {flow.plain!r}")
    if flow.carry == "near" and flow.carry_range <= 0:
        raise PhysavatarError(None, f"flow.carry_range must be > 0 with flow.carry='near', got {flow.carry_range}")
    if pred.garment == "physics" or flow.carry == "physics":
        from ...sim import PRESETS

        if pred.material not in PRESETS and not pred.material.endswith(".json"):
            raise PhysavatarError(None, f"prediction.material must be one of {sorted(PRESETS)} or a material .json "
                                        f"(fit-physics' material.json), got {pred.material!r}")
        if pred.material.endswith(".json"):
            from ...sim import Material

            Material.load(pred.material)  # a file that is not a material: its one message now
    scale = fit_scale(fit, train)
    for c in train:
        if min(round(c.width * scale * min(fit.levels)), round(c.height * scale * min(fit.levels))) < 11:
            raise PhysavatarError(None, f"option --scale: camera {c.name} would be smaller than 11 px "
                                        "at the coarsest level (SSIM's window); use a larger --scale")
    return train, capture.frames[:n]


CARRY = ("still", "body", "near", "velocity", "physics")  # flow.carry


def _read_log(path: Path) -> dict[int, dict]:
    if not path.is_file():
        return {}
    rows = {}
    with open(path, newline="") as f:
        for r in csv.DictReader(f):
            rows[int(r["frame"])] = r
    return rows


def _write_log(path: Path, rows: dict[int, dict]) -> None:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=LOG_COLUMNS, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for f in sorted(rows):
        w.writerow(rows[f])
    write_text_atomic(path, buf.getvalue())

def _flat(d: dict, prefix: str = "") -> dict:
    """A nested config dict as {dotted key: value}."""
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[prefix + k] = v
    return out


def _unhashed(config, prefix: str = "") -> set[str]:
    """Dotted names of the config's fields that do not change outputs (``hash=False``)."""
    out = set()
    for f in fields(config):
        v = getattr(config, f.name)
        if is_dataclass(v):
            out |= _unhashed(v, f"{prefix}{f.name}.")
        elif not f.metadata.get("hash", True):
            out.add(prefix + f.name)
    return out


# settings a run folder's config.json may not record, with the value such a run had: defaults that
# changed after config.json began to record the setting (flow.channels: grey until session 15),
# and settings added later (session 18: a run that does not record them ran with them off; session
# 24: nor with fit_blend, it kept the whole fit)
UNRECORDED = {"flow.channels": "luma", "flow.highpass": 0.0, "flow.texture_blur": 0.0, "flow.plain": "patterned",
              "flow.silhouette": 0.0, "flow.fit_blend": 1.0, "fit.first_vertex_iters": 0}


def _check_resume(out: Path, saved: dict, wanted: dict) -> None:
    """Refuse to resume a run folder whose config.json (``saved``) differs from ``wanted`` in
    anything but the fields that do not change outputs (``n_frames``: a run can be extended). A
    setting missing from ``saved`` (written before it existed) ran with its default, or with the
    value it had then where the default has changed since (:data:`UNRECORDED`)."""
    defaults = {**_flat(to_dict(TrackConfig())), **UNRECORDED}
    old = _flat(saved)
    old = {**{k: v for k, v in defaults.items() if k not in old}, **old}
    new = _flat(wanted)
    skip = _unhashed(TrackConfig())
    diff = sorted(k for k in set(old) | set(new) if k not in skip and old.get(k) != new.get(k))
    if diff:
        raise PhysavatarError(out, f"holds a tracking run with another config (differs in: {', '.join(diff)}); "
                                   "choose another --out or delete it")


def capture_key(cap: Capture) -> str:
    """The content of the capture files every tracked frame depends on: cameras, frames and fps,
    the template, the body poses (:func:`frame_key` chains each frame's images onto it)."""
    root = Path(cap.root)
    return content_key(root / "cameras.json", root / "capture.json", root / "template", root / "body.npz")


def frame_key(cap: Capture, train: list[Camera], frame: int, previous: str) -> str:
    """What frame ``frame``'s fit is made from: the key of the frame before it (its fit starts
    from that one's, :func:`capture_key` for the first) and this frame's training images and masks.
    A frame file with another key is tracked again, and so is every frame after it."""
    return content_key(previous, *[p for c in train for p in (cap.image_path(c.name, frame),
                                                             cap.mask_path(c.name, frame))])


@dataclass
class TrackResult:
    """vertices [T, V, 3] float32, face_colors [T, F, 3], frames [T], computed: frames fitted by
    this call (the others were read back from a previous run), seconds per fitted frame."""

    out: Path
    frames: list[int]
    vertices: np.ndarray
    face_colors: np.ndarray
    computed: list[int]
    seconds: dict[int, float]


def run(capture: Path, *, out: Path, config: TrackConfig, progress=None, material: Path | None = None) -> TrackResult:
    """Track the capture's template through its frames into ``out`` (package docstring: outputs).

    ``capture``: the capture folder (or a loaded :class:`~physavatar.capture.Capture`). A rerun
    into the same ``out`` with the same config (``n_frames`` may differ) skips finished frames made
    from the same capture data (:func:`frame_key`); another config there is refused. ``progress``: see :func:`physavatar.progress.resolve`.
    ``material``: a fit-physics output folder (or its material.json) as ``prediction.material``: the
    physics step of a second tracking pass (the paper's loop; ``config.second_pass_config``)."""
    if material is not None:
        path = material_file(material)
        if not path.is_file():
            raise PhysavatarError(path, "material not found (a fit-physics output folder or its material.json)")
        config = replace(config, prediction=replace(config.prediction, material=str(path.resolve())))
    cap = capture if isinstance(capture, Capture) else load_capture(capture)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise PhysavatarError(out, "output exists and is not a folder")
    train, frames = _check_config(config, cap)
    train_names = {c.name for c in train}
    cfg = replace(config, holdout=tuple(c.name for c in cap.cameras if c.name not in train_names))
    cfg_json = {**to_dict(cfg), "capture": str(Path(cap.root).resolve())}
    cfg_path = out / "config.json"
    if cfg_path.is_file():
        _check_resume(out, read_json(cfg_path), cfg_json)
    write_json_atomic(cfg_path, cfg_json)
    torch.manual_seed(cfg.seed)
    import numba

    old_threads = (torch.get_num_threads(), numba.get_num_threads())
    torch.set_num_threads(cfg.threads)
    numba.set_num_threads(min(cfg.threads, numba.config.NUMBA_NUM_THREADS))
    try:
        return _track(cap, out, cfg, train, frames, progress)
    finally:
        torch.set_num_threads(old_threads[0])
        numba.set_num_threads(old_threads[1])


def track(capture: Capture | str | Path, out: str | Path, config: TrackConfig | None = None,
          progress=None) -> TrackResult:
    """:func:`run` with ``out`` and ``config`` (default: :class:`TrackConfig`'s) given by position."""
    return run(capture, out=Path(out), config=config or TrackConfig(), progress=progress)


def _track(cap: Capture, out: Path, cfg: TrackConfig, train: list[Camera], frames: list[int],
           progress) -> TrackResult:
    t = cap.template
    model = MeshGaussians.init(t.vertices, t.faces, cfg.subdivide, cfg.opacity, cfg.antialiased, cfg.splat_backend)
    logger.info("tracking: splats rendered by the %s backend", model.backend)
    iso = IsometryLoss(t.vertices, t.faces) if cfg.loss.iso_weight > 0 else None
    normal = (NormalLoss(t.faces, t.vertices if cfg.loss.normal_mode == "rest" else None)
              if cfg.loss.normal_weight > 0 else None)
    factors = [fit_scale(cfg.fit, train) * lv for lv in cfg.fit.levels]
    solve = smoothing_solver(len(t.vertices), t.faces, cfg.fit.smoothing) if cfg.fit.smoothing > 0 else None
    log_path = out / "track_log.csv"
    log = _read_log(log_path)
    starts = FrameStarts(cap, cfg, train, frames)
    collision = anchor = None
    if starts.mixed:
        skinned = starts.skinned
        if cfg.loss.anchor_weight > 0:
            anchor = AnchorLoss(np.flatnonzero(skinned))
        body_faces = t.faces[(~t.garment_mask[t.faces]).all(1)]
        if cfg.loss.collision_weight > 0 and len(body_faces) and (~skinned).any():
            collision = CollisionLoss(np.flatnonzero(~skinned), np.flatnonzero(~t.garment_mask), body_faces,
                                      cfg.loss.collision_margin)

    verts: list[np.ndarray] = []
    cols: list[np.ndarray] = []
    computed: list[int] = []
    seconds: dict[int, float] = {}
    m = cfg.prediction.material  # a prior material file (physics carry): its content, not its name
    key = content_key(capture_key(cap), *([Path(m)] if m.endswith(".json") else []))
    stale: list[int] = []
    with resolve(progress).task("track", total=len(frames)) as task:
        for i, f in enumerate(frames):
            fpath = out / "frames" / f"{frame_name(f)}.npz"
            key = frame_key(cap, train, f, key)
            z = load_npz(fpath) if fpath.is_file() else None
            if z is not None and str(z.get("input_key", "")) != key:
                stale.append(f)
                z = None
            if z is not None:  # resumed
                verts.append(z["vertices"])
                cols.append(z["face_colors"])
                model.colors = torch.from_numpy(z["gaussian_colors"]).float()
                if i == 0:
                    model.log_scales = torch.from_numpy(z["log_scales"]).float()
                    model.opacity_logits = torch.from_numpy(z["opacity_logits"]).float()
                    model.edge_index = torch.from_numpy(z["edge_index"]).long()
                task.advance(frame=frame_name(f))
                continue
            t0 = time.perf_counter()
            images = [cap.image(c.name, f) for c in train]
            pyramid = [load_views(cap, f, train, s, cfg.fit.target_blur, images) for s in factors]
            starts.observe(f, images)
            if i == 0:
                gv = model.gaussian_vertices(torch.from_numpy(np.asarray(t.vertices, np.float32))).numpy()
                model.colors = torch.from_numpy(initial_colors(gv, model.faces.numpy(), pyramid[-1]))
                init = np.asarray(t.vertices, np.float32)
            else:
                init = starts.start(i, verts)
                for term in (collision, anchor):
                    if term is not None:
                        term.update(init)
            res = fit_frame(model, init, pyramid, cfg, first=(i == 0), iso=iso, normal=normal, solve=solve,
                            collision=collision, anchor=anchor)
            if i == 0 and cfg.fit.first_vertex_iters > 0:  # the template's own error at frame 1
                for term in (collision, anchor):
                    if term is not None:
                        term.update(init)
                res = fit_frame(model, init, pyramid, cfg, first=False, iso=iso, normal=normal, solve=solve,
                                collision=collision, anchor=anchor, refine_first=True)
            # the chain's stages, kept for diagnosis: the start (prediction and corrections) and the fit
            extra = {} if i == 0 else dict(start_vertices=np.asarray(init, np.float32), fit_vertices=res.vertices)
            res.vertices = starts.refine(i, res.vertices, None if i == 0 else init)
            dt = time.perf_counter() - t0
            if i == 0:
                extra = dict(log_scales=model.log_scales.numpy(), opacity_logits=model.opacity_logits.numpy(),
                             edge_index=model.edge_index.numpy())
            face_colors = model.face_colors(len(t.faces))
            save_npz_atomic(fpath, vertices=res.vertices, face_colors=face_colors, gaussian_colors=res.colors,
                            frame=np.int64(f), input_key=np.array(key), **extra)
            write_ply(out / "meshes" / f"{frame_name(f)}.ply",
                      PlyMesh(res.vertices, t.faces, {"label": t.labels.astype(np.uint8),
                                                      "boundary": t.boundary.astype(np.uint8)}))
            row = {"frame": f, "iterations": res.iterations, "seconds": f"{dt:.3f}"}
            row.update({k: f"{res.terms.get(k, 0.0):.6g}" for k in LOG_COLUMNS[2:-1]})
            log[f] = row
            _write_log(log_path, log)
            verts.append(res.vertices)
            cols.append(face_colors)
            computed.append(f)
            seconds[f] = dt
            task.advance(frame=frame_name(f), it=res.iterations, loss=res.terms["loss"], s=round(dt, 1))
    if stale:
        logger.info("track: %d frames in %s (from frame %d) were tracked from other capture data, or before "
                    "frames recorded theirs: tracked again", len(stale), out / "frames", stale[0])
    if starts.plain is not None:  # decided in this run (a fully resumed run keeps the file it wrote)
        decision = "plain" if starts.plain else "patterned"
        write_json_atomic(out / PLAIN_FILE, {"rule": cfg.flow.plain, "garment_texture": starts.garment_texture,
                                             "plain_texture": cfg.flow.plain_texture, "decision": decision})
        if starts.garment_texture is not None:
            logger.info("track: garment texture %.2f (threshold %.2f): %s", starts.garment_texture,
                        cfg.flow.plain_texture, decision)
    V = np.stack(verts).astype(np.float32)
    C = np.stack(cols).astype(np.float32)
    TrackedSequence(V, t.faces, t.labels, t.boundary, C, np.asarray(frames, np.int64),
                    log_scales=model.log_scales.numpy(), opacity_logits=model.opacity_logits.numpy(),
                    edge_index=model.edge_index.numpy(), fps=float(cap.fps)).save(out / TRACKED)
    return TrackResult(out, list(frames), V, C, computed, seconds)
