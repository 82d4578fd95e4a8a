"""Animation (paper Sec. 3.2, "Animation"): the avatar driven by a new motion.

The body follows the motion by linear blend skinning with the avatar's transferred weights; the
garment is simulated with the avatar's material, its boundary vertices attached to the posed
Anny collider, starting at rest. A motion whose first pose differs from the capture's frame-1
pose is preceded by a warm-up transition (spherical interpolation of every bone), simulated
but not returned, so the garment never starts from a jump; it lasts as long as the body's largest
move needs at a gentle speed (WARMUP_SPEED), at most ``warmup_s`` (session 32: a fitted body's
centimetre of pose error is crossed in 2-3 frames, not a second).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..data.avatar import Avatar
from ..body import BodyModel, Motion, axis_angle_to_matrix, linear_blend_skinning, matrix_to_axis_angle
from ..body.between import BETWEEN_HELP, PoseBetween, between_key
from ..body.load import KNEE_COLLAPSE_HELP
from ..data.animated import AnimatedSequence
from ..data.sim_frames import FrameStore, garment_run_key
from ..errors import PhysavatarError
from ..files import content_key
from ..geometry import count_intersections
from ..garment_sim import simulate_on_body, split_template
from ..sim import SimSettings
from ..sim.simulate import self_contact_possible
from .base import option, to_dict
from .garment_file import GarmentFileOptions, nonnegative

log = logging.getLogger("physavatar.progress")


def _ease(n: int) -> np.ndarray:
    """The n transition frames' fractions of the way (smoothstep in time; the motion's first frame is 1)."""
    s = np.arange(n) / max(n, 1)
    return s * s * (3 - 2 * s)


def transition(r0: np.ndarray, t0: np.ndarray, r1: np.ndarray, t1: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """n poses easing from (r0 [B,3], t0 [3]) to just before (r1, t1) (smoothstep in time)."""
    s = _ease(n)
    R0, R1 = axis_angle_to_matrix(r0), axis_angle_to_matrix(r1)
    rel = matrix_to_axis_angle(np.swapaxes(R0, -1, -2) @ R1)  # [B, 3]
    R = R0[None] @ axis_angle_to_matrix(s[:, None, None] * rel[None])
    return matrix_to_axis_angle(R), (1 - s)[:, None] * t0 + s[:, None] * t1


WARMUP_SPEED = 0.5  # [m/s] the fastest a body point may move in a warm-up transition (smoothstep's peak)


def warmup_frames(move: float, fps: float, warmup_s: float) -> int:
    """Frames of a warm-up whose body moves at most ``move`` [m] (its farthest point, start pose to
    the motion's first): 0 without a move; else the fewest (at least 2) whose largest step is within
    WARMUP_SPEED, at most ``warmup_s`` (at least 2 frames). A warm-up is simulated time: the
    garment, at rest in the start pose, evolves under gravity through it, so a needlessly long one
    (a second to cross a fitted body's centimetres of pose error) starts the motion with a garment
    that has been falling for a second where the capture's started at rest (issue 23, session 32)."""
    if move <= 1e-6:
        return 0
    n_max = max(2, int(round(warmup_s * fps)))
    for n in range(2, n_max):
        if np.diff(np.r_[_ease(n), 1.0]).max() * move * fps <= WARMUP_SPEED:
            return n
    return n_max


def warmup_without_gravity(material, warmup_gravity: bool | None = None) -> bool:
    """Whether :func:`animate`'s warm-up is simulated without gravity (``warmup_gravity`` False), the
    motion then starting from the warm-up's last state at rest. By default (None) it is, unless the
    material's rest shape is its equilibrium (``Material.rest_shape``: there gravity is what holds
    the start still). With the template as rest shape the capture's garment starts its first frame
    at rest and unloaded, and so does every simulation the material was fitted in (`fit-physics`)
    and the held-out truth; a warm-up under gravity starts the motion with a garment already
    falling for the warm-up's frames: the original garment on the demo's true body moved 0.01 mm
    (a 2-frame warm-up) scored 0.0985 against 0.0380 (issue 23, session 34)."""
    if warmup_gravity is not None:
        return not warmup_gravity
    return material.rest_shape != "equilibrium"


def _warmup(avatar: Avatar, motion: Motion, bone_names, warmup_s: float,
            zero_start: bool = False, body: BodyModel | None = None) -> tuple[Motion, Motion, int]:
    """(motion, rest pose) for ``bone_names`` at the avatar's fps, and the warm-up frame count
    (:func:`warmup_frames` of the collider's largest move): from the rest pose, or from the zero
    pose with ``zero_start`` (a garment fitted there). ``body``: Anny in the avatar's shape,
    collider topology (made here when not given)."""
    fps = avatar.fps
    m = motion.resample(fps).for_bones(bone_names)
    rest = Motion("rest", fps, avatar.bone_names, avatar.rest_rotations[None], avatar.rest_translation[None])
    rest = rest.for_bones(bone_names)
    r0 = np.zeros_like(rest.rotations[0]) if zero_start else rest.rotations[0]
    t0 = np.zeros(3) if zero_start else rest.root_translation[0]
    d_rot = np.abs(axis_angle_to_matrix(m.rotations[0]) - axis_angle_to_matrix(r0)).max()
    d_tr = np.abs(m.root_translation[0] - t0).max()
    if d_rot < 1e-6 and d_tr < 1e-6:
        return m, rest, 0
    body = body or BodyModel(avatar.shape, topology="collider")
    start = Motion("start", fps, list(m.bone_names), r0[None], t0[None]).for_bones(body.bone_names)
    first = m.slice(0, 1).for_bones(body.bone_names)
    ends = body.pose(np.concatenate([start.rotations, first.rotations]),
                     np.concatenate([start.root_translation, first.root_translation])).vertices
    move = float(np.linalg.norm(ends[1] - ends[0], axis=1).max())
    return m, rest, max(2, warmup_frames(move, fps, warmup_s))


def sequence_motion_key(avatar: Avatar, motion: Motion, warmup_s: float = 1.0, body: BodyModel | None = None,
                        warmup_gravity: bool | None = None) -> str:
    """The content key (files.content_key) of the motion :func:`animate` simulates for ``motion``:
    at the avatar's fps, over its bones, with the warm-up frames, and a warm-up without gravity
    (:func:`warmup_without_gravity`, since session 34) marked. ``animate`` records it with its frame
    count (``motion_key``, ``motion_frames``), so a sequence reused for another motion, or warmed up
    under gravity before session 34, is caught (evaluate --sequence). ``body``: as :func:`_warmup`'s."""
    m, _, n_warm = _warmup(avatar, motion, avatar.bone_names, warmup_s, body=body)
    weightless = {"warmup_gravity": False} if n_warm and warmup_without_gravity(avatar.material, warmup_gravity) else {}
    return content_key(m.rotations, m.root_translation, fps=float(m.fps), bones=list(m.bone_names),
                       warmup_frames=n_warm, **weightless)


def check_sequence_motion(meta_file: Path, meta: dict, avatar: Avatar, motion: Motion) -> None:
    """Refuse (naming ``meta_file``) a sequence whose recorded motion (``meta``: its sequence.json)
    is not the first frames of ``motion`` with a 1-s warm-up (evaluate's); a sequence made before
    animate recorded its motion passes."""
    key, n = meta.get("motion_key"), int(meta.get("motion_frames", 0))
    if key is not None and (n > motion.frames or key != sequence_motion_key(avatar, motion.slice(0, n))):
        raise PhysavatarError(meta_file, "sequence was animated on another motion than the held-out one "
                              f"({motion.name!r}, its first {n} frames, with a 1-s warm-up): animate the avatar "
                              "with --motion ground_truth/heldout/motion.npz, or leave out --sequence")


def simulated_frames(avatar: Avatar, motion: Motion, warmup_s: float = 1.0) -> int:
    """Frames :func:`animate` simulates for ``motion`` (warm-up included, the rest pose excluded)."""
    m, _, n_warm = _warmup(avatar, motion, avatar.bone_names, warmup_s)
    return len(m.rotations) + n_warm - 1


def warmup_count(avatar: Avatar, motion: Motion, warmup_s: float = 1.0) -> int:
    """Warm-up frames :func:`animate` puts before ``motion`` (0: it starts in the avatar's pose)."""
    return _warmup(avatar, motion, avatar.bone_names, warmup_s)[2]


def animate(avatar: Avatar, motion: Motion, *, warmup_s: float = 1.0, settings: SimSettings | None = None,
            progress=True, report=None, max_substeps: int = 16,
            out: Path | None = None, garment=None, skinned_between: bool = True,
            warmup_gravity: bool | None = None) -> tuple[AnimatedSequence, dict]:
    """Drive ``avatar`` with ``motion`` (resampled to the avatar's fps). Returns (sequence, stats).
    ``progress``: see :mod:`physavatar.progress`; ``report``: called with 1 after every simulated
    frame instead (:mod:`physavatar.parallel`). ``max_substeps``: implicit steps a frame may be
    split into where the body moves fast (sim.simulate.substep_count). ``out``: write each
    simulated frame as it is finished into out/frames/ and resume an interrupted run of the same
    avatar, motion and settings from there (data.sim_frames; the caller removes it). ``garment``: a
    GarmentPart on the zero pose of Anny in the avatar's shape (collider topology; a garment file
    fitted there, stages.garment_file) worn instead of the avatar's own: the warm-up starts from
    that pose, and the sequence holds the avatar's body and that garment. ``skinned_between``: a
    frame split into sub-steps poses the collider in between from the motion (body.between; the
    default since session 31); False: vertex by vertex. ``warmup_gravity``: whether the warm-up is
    simulated under gravity (None: :func:`warmup_without_gravity` decides)."""
    fps = avatar.fps
    body = BodyModel(avatar.shape, topology="collider")
    m, rest, n_warm = _warmup(avatar, motion, body.bone_names, warmup_s, zero_start=garment is not None, body=body)
    rots, trs = m.rotations, m.root_translation
    if n_warm:
        r0, t0 = (np.zeros_like(rots[0]), np.zeros(3)) if garment is not None else (rest.rotations[0],
                                                                                      rest.root_translation[0])
        wr, wt = transition(r0, t0, m.rotations[0], m.root_translation[0], n_warm)
        rots = np.concatenate([wr, rots])
        trs = np.concatenate([wt, trs])
    posed = body.pose(rots, trs)
    posed0 = body.pose(rest.rotations, rest.root_translation)

    t = avatar.template
    body_ids, body_faces, part = split_template(t.vertices, t.faces, t.labels, t.boundary, t.rest)
    # Skinning relative to the capture's frame-1 pose, which the template is in.
    T_rel = posed.bone_transforms @ np.linalg.inv(posed0.bone_transforms[0])[None]
    Vb = linear_blend_skinning(t.vertices[body_ids], avatar.body_weights, T_rel)
    if garment is not None:
        part = garment
    crossing = count_intersections(part.vertices, part.faces, posed.vertices[0], body.faces)
    if crossing:
        # a template prepared from a real capture lies on a fitted body; where the coarse collider
        # cuts it by a millimetre or two, push it out as fit-physics does (docs/physics.md)
        from ..garment.garment import push_clear

        dhat = (settings or SimSettings()).dhat  # the simulation's own barrier distance
        moved, left = push_clear(part.vertices, part.faces, posed.vertices[0], body.faces, dhat,
                                 fixed=part.boundary)
        if left:
            raise PhysavatarError(avatar.root / "template.ply",
                                  f"the garment intersects Anny's collider body in the frame-1 pose ({crossing} "
                                  f"crossing triangle pairs, {left} after pushing it out); the garment must "
                                  "start outside the collider to be simulated")
        log.info("animate: the garment crossed the collider body in %d triangle pairs; pushed out "
                 "(largest move %.2f mm)", crossing, 1e3 * float(np.linalg.norm(moved - part.vertices, axis=1).max()))
        # the rest shape stays the template's (no strain from the push), or with a material whose rest
        # shape is the equilibrium, is solved for the pushed start that is simulated
        keep = part.rest is not None or avatar.material.rest_shape != "equilibrium"
        part = replace(part, vertices=moved, rest=part.rest_shape if keep else None)
    if settings is not None and settings.self_contact and not self_contact_possible(
            part.vertices, part.faces, settings.dhat, part.contact_exclusions()):
        settings = replace(settings, self_contact=False)
    t0 = time.time()
    cb = None if report is None else (lambda f, x, st: report(1))
    rest_report = {}
    between = PoseBetween(body, rots, trs) if skinned_between else None
    options = dict(settings=settings, progress=progress if report is None else False, callback=cb,
                   max_substeps=max_substeps, rest_report=rest_report, between=between)
    reports = []
    Xw, bodies = None, posed.vertices
    if n_warm and warmup_without_gravity(avatar.material, warmup_gravity):
        # the warm-up carries the garment to the motion's first pose without gravity and the motion
        # starts from there at rest: the warm-up changes the pose, not the time (issue 23, session 34)
        s0 = settings or SimSettings(integrator=avatar.material.integrator)
        bw = PoseBetween(body, rots[:n_warm + 1], trs[:n_warm + 1]) if skinned_between else None
        Xw = simulate_on_body(part, posed.vertices[:n_warm + 1], body.faces, avatar.material, fps,
                              settings=replace(s0, gravity=(0.0, 0.0, 0.0)), progress=False, callback=cb,
                              max_substeps=max_substeps, between=bw, on_frame=lambda c, r: reports.append(r))
        part = replace(part, vertices=Xw[-1], rest=part.rest_shape)
        bodies = posed.vertices[n_warm:]
        between = PoseBetween(body, rots[n_warm:], trs[n_warm:]) if skinned_between else None
        options["between"] = between
    if out is None:
        Xg = simulate_on_body(part, bodies, body.faces, avatar.material, fps, on_frame=lambda c, r: reports.append(r),
                              **options)
    else:
        key = garment_run_key(part, bodies, body.faces, avatar.material, settings, fps,
                              max_substeps=max_substeps, **between_key(between, max_substeps))
        store = FrameStore(out, key, len(bodies))
        Xg = simulate_on_body(part, bodies, body.faces, avatar.material, fps, resume=store.resume(),
                              on_frame=store.write, **options)
        Xg, more = store.positions(part.vertices)
        reports += more
    if Xw is not None:
        Xg = np.concatenate([Xw[:n_warm], Xg])
    secs = time.time() - t0
    if garment is None:
        V = np.empty((len(rots), len(t.vertices), 3))
        V[:, body_ids] = Vb
        V[:, part.vertex_ids] = Xg
        faces, labels, face_uvs = t.faces, t.labels, t.face_uvs
    else:
        V = np.concatenate([Vb, Xg], axis=1)
        faces, labels, face_uvs = _with_garment(t, body_ids, part)
    V = V[n_warm:]
    stats = {"frames": int(len(V)), "warmup_frames": n_warm, "simulation_s": round(secs, 2),
             "sim_fps": round((len(rots) - 1) / max(secs, 1e-9), 3), "garment_vertices": int(len(part.vertices)),
             "material": avatar.material.to_dict(), "motion": motion.name, "fps": fps,
             "motion_key": sequence_motion_key(avatar, motion, warmup_s, body, warmup_gravity),
             "motion_frames": int(len(m.rotations)), "warmup_gravity": (Xw is None) if n_warm else None,
             "self_contact": bool(settings is not None and settings.self_contact),
             "rest_shape": {"kind": "equilibrium" if rest_report else "template" if t.rest is None and garment is None
                            else "designed"} | rest_report,
             "frames_with_lag": [f - n_warm for f, r in enumerate(reports, start=1) if r["lagged"] and f >= n_warm],
             "substeps_per_frame": [r["substeps"] for f, r in enumerate(reports, start=1) if f >= n_warm]}
    return AnimatedSequence(V, faces, labels, face_uvs, fps, avatar.root), stats


def _with_garment(t, body_ids, part):
    """(faces, labels, face uvs) of the avatar's body (template order) followed by ``part``: the
    garment takes the avatar garment's label and the texture at the median of its uvs (one colour;
    the avatar's texture has no pattern for it)."""
    gmask = t.labels > 0
    remap = -np.ones(len(t.vertices), np.int64)
    remap[body_ids] = np.arange(len(body_ids))
    body_face = ~gmask[t.faces].any(1)
    faces = np.vstack([remap[t.faces[body_face]], np.asarray(part.faces) + len(body_ids)])
    label = int(t.labels[gmask].min()) if gmask.any() else 1
    labels = np.r_[t.labels[body_ids], np.full(len(part.vertices), label)].astype(t.labels.dtype)
    face_uvs = None
    if t.face_uvs is not None:
        g = t.face_uvs[~body_face].reshape(-1, 2)
        uv = np.median(g, axis=0) if len(g) else np.full(2, 0.5)
        face_uvs = np.concatenate([t.face_uvs[body_face], np.broadcast_to(uv, (len(part.faces), 3, 2))])
    return faces, labels, face_uvs


def simulated_material(material, rest: dict):
    """``material`` in the model a sequence was simulated in, from animate's ``stats["rest_shape"]``
    (``rest``): with the equilibrium rest shape but a garment that was not at rest in its start frame
    (``rest["at_rest"]`` false), the template was the rest shape (garment_sim.equilibrium_part),
    the model a fit records then too (physics.stage.refit_at_equilibrium keeps its first fit)."""
    if material.rest_shape == "equilibrium" and rest.get("at_rest") is False:
        return replace(material, rest_shape="template", rest_friction=False)
    return material


def animate_job(avatar_dir: str | Path, material, motion: Motion, report=None, **kw) -> tuple[np.ndarray, dict]:
    """:func:`animate` of the avatar at ``avatar_dir`` with ``material`` instead of its own, as a
    :class:`physavatar.parallel.Job`; returns the vertices [T, V, 3] and the rest shape it
    simulated with (animate's ``stats["rest_shape"]``)."""
    av = Avatar.load(avatar_dir)
    av.material = material
    seq, stats = animate(av, motion, progress=False, report=report, **kw)
    return seq.vertices, stats["rest_shape"]


@dataclass(frozen=True)
class AnimateConfig(GarmentFileOptions):
    motion: str = option("", "built-in name, .bvh or .npz", check=lambda v: None if v else "give a motion")
    duration: float = option(4.0, "seconds (built-in motions)", check=lambda v: None if v > 0 else "must be positive")
    warmup: float = option(1.0, "at most this many seconds of transition from the capture pose to the motion's first "
                                "pose (shorter where the body moves less: its points at most 0.5 m/s)",
                           check=nonnegative)
    max_frames: int | None = option(None, "at most this many frames",
                                    check=lambda v: None if v >= 1 else "must be at least 1")
    arm_clearance: float = option(0.03, "with motion capture (.bvh, AMASS .npz): raise the arms where a hand comes closer than this [m] "
                                  "to the hips/trunk, so the garment is not pinched (0 = off)", check=nonnegative)
    part_clearance: bool = option(True, "with motion capture: keep the parts the garment covers apart where the motion "
                                         "makes the body pass through itself (thigh into the belly, calf into the "
                                         "thigh, hand into the body): bones turned by at most 20-40 deg "
                                         "(body.clearance; docs/motions.md; --no-part-clearance keeps the clip as retargeted)",
                                  flag="--part-clearance/--no-part-clearance")
    knee_collapse: bool | None = option(None, KNEE_COLLAPSE_HELP,  # None: auto (session 33)
                                        flag="--knee-collapse/--no-knee-collapse")
    max_substeps: int = option(16, "at most this many implicit steps per frame (more where the body moves fast)",
                               check=lambda v: None if v >= 1 else "must be at least 1")
    self_contact: bool = option(True, "garment-garment contact (ipctk's barrier and CCD between the garment's own "
                                      "triangles)")
    garment: str = option("", "a garment file (OBJ, PLY, glTF, npz) worn instead of the avatar's own: fitted onto "
                              "the avatar's body, simulated with the avatar's material (as simulate --garment)")
    skinned_between: bool = option(True, BETWEEN_HELP, flag="--skinned-between/--linear-between")
    warmup_gravity: bool | None = option(None, "the warm-up under gravity (default: only when the material's rest shape "
                                               "is its equilibrium; otherwise the garment is carried to the motion's "
                                               "first pose without gravity and the motion starts from there at rest: "
                                               "docs/motions.md)", flag="--warmup-gravity/--no-warmup-gravity")


def pipeline_config(motion: str, eval_frames: int | None) -> AnimateConfig:
    """What ``physavatar run`` animates: the held-out motion, its first ``eval_frames`` frames."""
    return AnimateConfig(motion=motion, max_frames=eval_frames)


@dataclass
class AnimateResult:
    sequence: AnimatedSequence
    stats: dict
    clearance: dict | None
    part_clearance: dict | None = None


def _file_garment(av: Avatar, config: AnimateConfig, settings: SimSettings, progress):
    """(GarmentPart, import report) of ``config.garment`` on the avatar's body (Anny in its shape,
    collider topology, zero pose): read, fitted, its boundary chosen, its start repaired."""
    from ..garment.files import FORMATS
    from .garment_file import file_on_body, repaired_start

    path = Path(config.garment)
    if not path.exists() or path.suffix.lower() not in FORMATS:
        raise PhysavatarError(path, f"option --garment: not a garment file ({', '.join(FORMATS)})")
    body = BodyModel(av.shape, topology="collider")
    part, imported = file_on_body(path, body, av.material, settings, progress=progress, **config.placement())
    part, imported["start_repair"] = repaired_start(part, body.rest_vertices, body.faces, settings.dhat,
                                                    config.repair_limit, path)
    return part, imported


def run(avatar: Path, *, out: Path, config: AnimateConfig, progress=None) -> AnimateResult:
    """Drive the avatar folder ``avatar`` with ``config.motion``; writes ``out`` (sequence.npz,
    sequence.json with the config and stats, meshes/)."""
    from ..body.load import load_motion, with_clearances

    if not config.motion:
        raise PhysavatarError(None, "option --motion: give a motion (built-in name, .bvh or .npz)")
    av = Avatar.load(avatar)
    m = load_motion(config.motion, av.fps, config.duration)
    settings = SimSettings(integrator=av.material.integrator, self_contact=config.self_contact)
    m, info, parts = with_clearances(m, config.motion, lambda: BodyModel(av.shape, topology="collider"),
                                     config.arm_clearance, config.part_clearance, config.knee_collapse,
                                     settings.contact_room(av.material))
    if config.max_frames:
        m = m.slice(0, config.max_frames)
    garment, imported = _file_garment(av, config, settings, progress) if config.garment else (None, None)
    seq, stats = animate(av, m, warmup_s=config.warmup, settings=settings, progress=progress,
                         max_substeps=config.max_substeps, out=out, garment=garment,
                         skinned_between=config.skinned_between, warmup_gravity=config.warmup_gravity)
    seq.save(Path(out), {"command": "animate", "motion_spec": config.motion, "config": to_dict(config),
                         "arm_clearance": info, "part_clearance": parts, "garment_import": imported, **stats})
    FrameStore(out, "", 0).remove()  # the sequence is written: the per-frame record is no longer needed
    return AnimateResult(seq, stats, info, parts)
