"""Simulate a garment on a moving body (``physavatar simulate``; paper Sec. 3.2, Eq. 5).

Three ways to say what to simulate (the inputs of :func:`run`):

- ``capture``: the garment of a capture's template on its body poses (at the capture's fps);
- ``garment`` (a built-in design: dress, skirt, tshirt) and ``motion`` (a built-in motion, .bvh
  or .npz) on the Anny collider body; a motion that does not start in the rest pose the garment
  is made for is reached by a warm-up transition (simulated, not written);
- ``collider`` (any animated body: .npz or a folder of OBJ/PLY frames) and ``garment`` (a garment
  file already on its first frame: OBJ, PLY, glTF or npz, garment.files; or a garment sequence);
- ``garment`` a garment file and ``motion``: the garment, made for another body, is fitted onto
  Anny's rest pose first (garment_sim.fit_on_body), then simulated like a built-in one.

A garment file's seams are stitched (sim.stitch), its rest shape is its own (a rest-shape file,
material uv), its boundary its flags or chosen where it rests on the body (``--boundary none``:
held by contact and friction alone).

``garment`` and ``motion`` are inputs although they may be a built-in name rather than a file:
they say *what* is simulated, as ``capture`` and ``collider`` do; :class:`SimulateConfig` holds
*how* (material, time stepping, warm-up, the garment's edge length).

The boundary vertices follow the body surface they start on (:mod:`physavatar.garment_sim`).
A start that touches or slightly crosses the body is pushed out to d̂ (sim.start.repair_start;
refused beyond ``--repair-limit``); every written frame is checked for garment–body
intersections and non-finite values. Outputs (``out/``): garment_sequence.npz
(:class:`~physavatar.data.garment_sequence.GarmentSequence`), meshes/NNNNNN.ply, material.json,
config.json (the record of the run, with the config), preview.mp4.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..body import BodyModel, Motion
from ..body.between import BETWEEN_HELP, PoseBetween, between_key
from ..body.load import KNEE_COLLAPSE_HELP, load_motion, with_clearances
from ..data.garment_sequence import FILE as GARMENT_SEQUENCE
from ..data.garment_sequence import GarmentSequence
from ..data.material import resolve_material
from ..data.mesh_sequence import load_mesh_sequence
from ..data.sim_frames import FrameStore, garment_run_key
from ..errors import PhysavatarError
from ..files import PlyMesh, load_npz, write_json_atomic, write_ply
from ..garment import GARMENTS, make_garment
from ..garment.files import FORMATS, load_garment
from ..garment_sim import GarmentPart, layered, simulate_on_body, split_layers, split_template
from ..sim import SimSettings
from ..sim.contact import ContactScene
from ..sim.simulate import self_contact_possible, self_intersecting_frames
from .animate import transition
from .base import option, to_dict
from .garment_file import GarmentFileOptions, choose_boundary, file_on_body, garment_part, repaired_start

INTEGRATORS = ("euler", "bdf2")
log = logging.getLogger("physavatar.progress")


@dataclass(frozen=True)
class SimulateConfig(GarmentFileOptions):
    """How the garment is simulated (the ``simulate`` options besides what to simulate).

    Attributes:
        material: a preset (silk, cotton, denim) or a material .json (fit-physics' too).
        fps: frames per second (a capture's own fps wins); substeps, max_substeps: implicit steps
            per frame, at least / at most (decided per frame, sim.simulate.substep_count).
        self_contact: resolve garment-garment contact (on by default).
        integrator: euler or bdf2 (None: the one the material was fitted with).
        duration: seconds of a built-in motion.
        warmup: seconds of transition from the rest pose to the motion's first pose.
        arm_clearance: with a .bvh motion, raise the arms where a hand comes closer than this [m]
            to the hips/trunk (0: off).
        edge_length: the built-in garment's edge length [m].
        over: built-in garments layered over the garment (comma-separated, innermost first;
            garment_sim.layered), or None.
        preview: write preview.mp4.
        skinned_between: a frame split into sub-steps poses the body in between from the motion
            (body.between.PoseBetween; the default since session 31), the attached targets on
            their straight path; False: the body vertex by vertex too (the collider's straight
            path).
    """

    material: str = option("cotton", "silk, cotton, denim, or a material .json")
    fps: float = option(25.0, "frames per second (one implicit step per frame by default)")
    substeps: int = option(1, "implicit steps per frame (at least)")
    max_substeps: int = option(16, "at most this many implicit steps per frame: more than --substeps where the body "
                                   "near the garment moves fast or a step could not reach the body's pose "
                                   "(docs/simulation.md 'Sub-stepping'); = --substeps for a fixed count")
    self_contact: bool = option(True, "garment-garment contact (ipctk's barrier and CCD between the garment's own "
                                      "triangles); every written frame is checked for self-intersection either way")
    integrator: str | None = option(None, "euler (implicit Euler, the paper's) or bdf2 (second order; "
                                          "docs/simulation.md); default: the one the material was fitted with "
                                          "(euler for presets)", choices=INTEGRATORS)
    duration: float = option(2.0, "seconds (built-in motions)")
    warmup: float = option(1.0, "with --motion: seconds of transition from the garment's rest pose to the motion's "
                                "first pose (simulated, not written)")
    arm_clearance: float = option(0.03, "with a .bvh motion: raise the arms where a hand comes closer than this [m] "
                                        "to the hips/trunk, so the garment is not pinched (0 = off)",
                                  flag="--arm-clearance")
    part_clearance: bool = option(True, "with a .bvh/AMASS motion: keep the parts the garment covers apart where the "
                                         "motion makes the body pass through itself (thigh into the belly, calf into "
                                         "the thigh, hand into the body): bones turned by at most 20-40 deg "
                                         "(body.clearance; docs/motions.md; --no-part-clearance keeps the clip as retargeted)",
                                  flag="--part-clearance/--no-part-clearance")
    knee_collapse: bool | None = option(None, KNEE_COLLAPSE_HELP,  # None: auto (session 33)
                                        flag="--knee-collapse/--no-knee-collapse")
    edge_length: float = option(0.02, "garment edge length [m] (with --garment KIND)")
    over: str | None = option(None, "with --motion: built-in garments worn over --garment, innermost first "
                                    "(comma-separated: dress, skirt, tshirt), simulated together with it as one cloth, "
                                    "each with its own boundary, in contact with each other (self-contact); "
                                    "e.g. --garment skirt --over tshirt")
    preview: bool = option(True, "write preview.mp4")
    skinned_between: bool = option(True, BETWEEN_HELP, flag="--skinned-between/--linear-between")


@dataclass
class SimulateResult:
    """What :func:`run` simulated and wrote.

    Attributes:
        out: the output folder. frames: frames written (the warm-up excluded).
        garment_vertices: vertices of the simulated garment. seconds: simulation wall time.
        bad_frames: written frames that intersect the body or are not finite.
        warmup_frames: leading frames simulated but not written.
        clearance: what arm clearance changed (body.load.with_arm_clearance), or None.
        part_clearance: what --part-clearance changed (body.load.with_part_clearance), or None.
        preview: whether preview.mp4 was written.
        lagged_frames: written frames where the body stopped short of its pose (the step gave
            up even at max_substeps; written with the given pose).
        self_intersecting_frames: written frames where the garment intersects itself.
    """

    out: Path
    frames: int
    garment_vertices: int
    seconds: float
    bad_frames: list
    warmup_frames: int
    clearance: dict | None
    preview: bool
    lagged_frames: list = field(default_factory=list)
    self_intersecting_frames: list = field(default_factory=list)
    part_clearance: dict | None = None


def _bad_option(name: str, problem: str):
    raise PhysavatarError(None, f"option {name}: {problem}")


def run(*, out: Path, config: SimulateConfig, capture: Path | None = None, garment: str | Path | None = None,
        motion: str | Path | None = None, collider: Path | None = None, progress=None) -> SimulateResult:
    """Simulate the garment given by ``capture``, ``garment`` + ``motion`` or ``collider`` +
    ``garment`` (module docstring) with ``config``; write ``out``. ``progress``: anything
    :func:`physavatar.progress.resolve` accepts (the simulator's per-frame task)."""
    cfg = config
    out = Path(out)
    mat = resolve_material(cfg.material, option="--material")
    fps = cfg.fps
    if fps <= 0 or cfg.substeps < 1 or cfg.max_substeps < 1:
        _bad_option("--fps/--substeps", "must be positive")
    integrator = cfg.integrator
    if integrator is None:
        integrator = mat.integrator  # a fitted material is simulated in the model it was fitted in
    if integrator not in INTEGRATORS:
        _bad_option("--integrator", f"{integrator!r} is not euler or bdf2")
    sim_settings = SimSettings(integrator=integrator)
    if cfg.over and (capture is not None or collider is not None or garment is None or motion is None):
        _bad_option("--over", "layers built-in garments over --garment on --motion (Anny's body): give both")
    n_warm = 0  # leading frames simulated but not written (--motion's transition)
    clearance_info = parts_info = between = None  # between: the body between frames from its poses
    imported = None  # what reading, fitting and repairing a garment file did (config.json)
    if capture is not None:
        part, bodies, body_faces, fps, between = _from_capture(Path(capture))
    elif collider is not None:
        if garment is None or not Path(garment).exists():
            _bad_option("--garment", "with --collider, give a garment mesh file (.ply with label/boundary, or .npz)")
        bodies, body_faces = load_mesh_sequence(collider)
        part, imported = garment_file(Path(garment), cfg, bodies[0], body_faces)
    elif garment is not None and motion is not None:
        part, bodies, body_faces, n_warm, clearance_info, parts_info, imported, between = _on_motion(
            garment, motion, fps, cfg, mat, sim_settings, progress)
    else:
        _bad_option("--capture/--garment/--collider",
                    "say what to simulate: --capture C, or --garment KIND --motion M, or --collider SEQ --garment FILE")
    source = garment if garment is not None and Path(str(garment)).exists() else (capture or collider or garment)
    part, repair = repaired_start(part, bodies[0], body_faces, sim_settings.dhat, cfg.repair_limit, source)
    if imported is not None:
        imported["start_repair"] = repair
    if part.layer is not None:  # the repair may have pushed a garment into the one over it: layered again
        part = layered(split_layers(part), bodies[0], body_faces)
    exclude = part.contact_exclusions()  # the primitives that touch at sewn seams
    self_contact = cfg.self_contact and self_contact_possible(part.vertices, part.faces, sim_settings.dhat, exclude,
                                                                warn=not cfg.over)  # layers: refused below
    if cfg.over and cfg.self_contact and not self_contact:
        _bad_option("--over", f"the layers start closer than d̂ = {sim_settings.dhat} m to each other (or a garment "
                              f"to itself: {_closest_pair(part, garment, cfg.over, sim_settings.dhat, exclude)}), "
                              "so they cannot be simulated in contact")
    sim_settings = replace(sim_settings, self_contact=self_contact)
    t0 = time.time()
    X, reports, store, resumed = _simulate_frames(out, part, bodies, body_faces, mat, fps, sim_settings, cfg, n_warm,
                                                  progress, between if cfg.skinned_between else None)
    secs = time.time() - t0
    X, bodies = X[n_warm:], bodies[n_warm:]
    reports = [(f - n_warm, r) for f, r in enumerate(reports, start=1) if f >= n_warm]  # (written frame, report)
    # every frame checked: finite and free of garment-body intersections (ipctk's exact test)
    scene = ContactScene(part.rest_shape, part.faces, bodies[0], body_faces, sim_settings.dhat)
    bad = [f for f in range(len(X))
           if not np.all(np.isfinite(X[f])) or scene.has_intersections(np.vstack([X[f], bodies[f]]))]
    self_bad = self_intersecting_frames(X, part.faces, exclude)
    GarmentSequence(X, part.faces, part.boundary, bodies, body_faces, fps, part.rest_shape,
                    seams=part.seams).save(out / GARMENT_SEQUENCE)
    mat.save(out / "material.json")
    write_json_atomic(out / "config.json", {
        "command": "simulate", "capture": _text(capture), "garment": _text(garment), "motion": _text(motion),
        "collider": _text(collider), "material": mat.to_dict(), "fps": fps, "substeps": cfg.substeps,
        "integrator": integrator, "self_contact": self_contact,
        "frames_with_intersection_or_nan": bad, "frames_with_self_intersection": self_bad,
        "warmup_frames": n_warm, "arm_clearance": clearance_info, "part_clearance": parts_info, "garment_import": imported, "frames": len(X), "seconds": round(secs, 1),
        "resumed_after_frame": resumed, "layers": _layers_record(garment, cfg.over, part),
        **_frame_summary(reports), "config": to_dict(cfg)})
    if cfg.preview:
        from ..body.preview import render_frames, write_video

        Vall = np.concatenate([bodies, X], axis=1)
        Fall = np.concatenate([body_faces, part.faces + bodies.shape[1]])
        write_video(out / "preview.mp4", render_frames(Vall, Fall, None, None, title="simulate"), fps)
    store.remove()  # the final files are written: the per-frame record is no longer needed
    return SimulateResult(out, len(X), len(part.vertices), secs, bad, n_warm, clearance_info, cfg.preview,
                          [f for f, r in reports if r["lagged"]], self_bad, parts_info)


def _simulate_frames(out: Path, part: GarmentPart, bodies, body_faces, mat, fps: float, settings: SimSettings,
                     cfg: SimulateConfig, n_warm: int, progress, between=None):
    """Simulate every frame, writing each as it is finished (out/frames/, data.sim_frames; the
    written frames' PLY meshes in out/meshes/), resuming an interrupted run of the same inputs
    and settings from its last frame. Returns (positions [T, N, 3] of every simulated frame,
    per-frame reports of frames 1..T−1, the FrameStore, the frame resumed after or None).
    ``between``: the body in between frames from its poses (garment_sim.simulate_on_body)."""
    key = garment_run_key(part, bodies, body_faces, mat, settings, fps, substeps=cfg.substeps,
                          max_substeps=cfg.max_substeps, **between_key(between, max(cfg.substeps, cfg.max_substeps)))
    store = FrameStore(out, key, len(bodies))
    ck = store.resume()
    if ck is None and n_warm == 0:
        write_ply(out / "meshes" / f"{0:06d}.ply", PlyMesh(part.vertices, part.faces))
    elif ck is not None:
        log.info("simulate: resuming %s after frame %d of %d", out, ck.frame, len(bodies) - 1)

    def on_frame(checkpoint, report):
        store.write(checkpoint, report)
        if checkpoint.frame >= n_warm:
            write_ply(out / "meshes" / f"{checkpoint.frame - n_warm:06d}.ply", PlyMesh(checkpoint.x, part.faces))

    simulate_on_body(part, bodies, body_faces, mat, fps, settings=settings, substeps=cfg.substeps,
                     max_substeps=cfg.max_substeps, resume=ck, on_frame=on_frame, progress=progress, between=between)
    X, reports = store.positions(part.vertices)
    return X, reports, store, None if ck is None else ck.frame


def _layers_record(garment, over: str | None, part: GarmentPart) -> list | None:
    """config.json's record of layered garments: each one's name and vertex count, innermost first."""
    if not over or part.layer is None:
        return None
    names = [str(garment)] + _over_names(over)
    return [{"garment": n, "vertices": int(np.sum(part.layer == i))} for i, n in enumerate(names)]


def _closest_pair(part: GarmentPart, garment, over: str, dhat: float, exclude) -> str:
    """Which garments of a layered ``part`` start closest (ipctk's contacts within ``dhat``), in words."""
    import ipctk

    from ..sim.contact import cloth_filter

    F = np.asarray(part.faces, np.int32)
    mesh = ipctk.CollisionMesh(part.vertices, ipctk.edges(F), F)
    mesh.can_collide = cloth_filter(len(part.vertices), exclude)
    c = ipctk.NormalCollisions()
    c.build(mesh, part.vertices, dhat)
    if not len(c):
        return "none found"
    E = mesh.edges
    d = [np.sqrt(c[k].compute_distance(c[k].dof(part.vertices, E, F))) for k in range(len(c))]
    k = int(np.argmin(d))
    names = [str(garment)] + _over_names(over)
    lay = sorted({int(part.layer[i]) for i in c[k].vertex_ids(E, F) if i >= 0})
    who = " and ".join(names[i] for i in lay) + (" with itself" if len(lay) == 1 else "")
    return f"{len(c)} pairs, the closest {d[k] * 1e3:.3f} mm apart: {who}"


def _over_names(over: str) -> list[str]:
    names = [n.strip() for n in over.split(",") if n.strip()]
    bad = [n for n in names if n not in GARMENTS]
    if not names or bad:
        _bad_option("--over", f"{', '.join(bad) or repr(over)}: give built-in garments ({', '.join(GARMENTS)}), "
                              "comma-separated, innermost first")
    return names


def _layered(part: GarmentPart, over: str, body, cfg) -> GarmentPart:
    """``part`` with the built-in garments ``over`` (comma-separated, innermost first) made for
    ``body``'s rest pose and layered over it (garment_sim.layered)."""
    parts = [part]
    for name in _over_names(over):
        g = make_garment(name, body, edge_length=cfg.edge_length)
        parts.append(GarmentPart(np.arange(len(g.vertices)), g.vertices, g.faces, np.flatnonzero(g.boundary)))
    return layered(parts, body.rest_vertices, body.faces)


def _frame_summary(reports: list) -> dict:
    """config.json's per-frame record of the written frames, from (written frame, report) pairs
    (the first written frame has one when a warm-up led to it): implicit steps, Newton
    iterations, lag (how far the body stopped short of its pose; written with the given pose)."""
    return {"frames_with_lag": [f for f, r in reports if r["lagged"]],
            "per_frame": {"frame": [f for f, _ in reports], "lag_m": [round(r["lag_m"], 5) for _, r in reports],
                          "substeps": [r["substeps"] for _, r in reports],
                          "newton_iterations": [r["newton_iterations"] for _, r in reports]}}


def _text(value) -> str | None:
    return None if value is None else str(value)


def _from_capture(capture: Path):
    """(garment part, body vertices [T, Nb, 3], body faces, fps, the body between frames:
    body.between.PoseBetween) of a capture's template posed by its body motion."""
    from ..capture import load_capture

    cap = load_capture(capture)
    t = cap.template
    body_ids, body_faces, part = split_template(t.vertices, t.faces, t.labels, t.boundary, t.rest)
    body = BodyModel(cap.body.shape, topology=cap.body.topology)
    if len(body.rest_vertices) != len(body_ids):
        raise PhysavatarError(capture / "template" / "mesh.ply",
                              f"its body has {len(body_ids)} vertices but Anny's {cap.body.topology!r} topology "
                              f"has {len(body.rest_vertices)}")
    m = Motion("capture", cap.fps, cap.body.bone_names, cap.body.rotations, cap.body.root_translation)
    m = m.for_bones(body.bone_names) if m.bone_names != body.bone_names else m  # as Motion.pose does
    return part, m.pose(body).vertices, body_faces, cap.fps, PoseBetween(body, m.rotations, m.root_translation)


def _on_motion(garment, motion, fps: float, cfg: SimulateConfig, mat, sim_settings, progress):
    """(garment part, body vertices, body faces, warm-up frames, arm clearance summary, part
    clearance summary, import report, the body between frames: body.between.PoseBetween) of a built-in garment, or a garment file (fitted onto Anny's rest pose), on the Anny
    collider driven by ``motion``."""
    body = BodyModel(topology="collider")
    imported = None
    if str(garment) in GARMENTS:
        g = make_garment(str(garment), body, edge_length=cfg.edge_length)
        part = GarmentPart(np.arange(len(g.vertices)), g.vertices, g.faces, np.flatnonzero(g.boundary))
    elif Path(garment).suffix.lower() in FORMATS:
        part, imported = file_on_body(Path(garment), body, mat, sim_settings, progress=progress, **cfg.placement())
    else:
        _bad_option("--garment", f"{garment!r} is not one of {', '.join(GARMENTS)} nor a garment file "
                                 f"({', '.join(FORMATS)})")
    if cfg.over:
        part = _layered(part, cfg.over, body, cfg)
    mot = load_motion(motion, fps, cfg.duration)
    mot, clearance_info, parts_info = with_clearances(mot, motion, lambda: body, cfg.arm_clearance,
                                                      cfg.part_clearance, cfg.knee_collapse,
                                                      sim_settings.contact_room(mat))
    rots, trs = mot.rotations, mot.root_translation
    # the garment is made for the rest pose: a motion that starts elsewhere (a BVH clip) is
    # reached by a transition first, as `animate` does, so the garment never starts inside the body
    if cfg.warmup < 0:
        _bad_option("--warmup", "must be >= 0")
    n_warm = 0
    if np.abs(rots[0]).max() > 1e-6 or np.abs(trs[0]).max() > 1e-6:
        n_warm = max(2, int(round(cfg.warmup * fps)))
        wr, wt = transition(np.zeros_like(rots[0]), np.zeros(3), rots[0], trs[0], n_warm)
        rots, trs = np.concatenate([wr, rots]), np.concatenate([wt, trs])
    return (part, body.pose(rots, trs).vertices, body.faces, n_warm, clearance_info, parts_info, imported,
            PoseBetween(body, rots, trs))


def garment_file(path: Path, cfg: SimulateConfig | None = None, body_vertices=None, body_faces=None):
    """(GarmentPart, import report) of a garment file placed on the body's first frame: a garment
    sequence (its rest shape and boundary), or an OBJ/PLY/glTF/npz garment (garment.files; its
    boundary flags, else chosen where it rests on the body, or none with --boundary none)."""
    cfg = cfg or SimulateConfig()
    if path.suffix == ".npz":
        z = load_npz(path)
        if "vertices" in z and np.ndim(z["vertices"]) == 3:
            # a garment sequence (simulate's garment_sequence.npz, another simulator's): its rest shape
            d = GarmentSequence.from_arrays(z, path)
            part = GarmentPart(np.arange(len(d.rest_vertices)), d.rest_vertices, d.faces, d.boundary, seams=d.seams)
            return part, {"file": str(path), "rest_source": "garment sequence", "boundary": {"vertices": len(d.boundary)}}
    gm = load_garment(path, up=cfg.up, scale=cfg.scale, rest=cfg.rest)
    part, imported = garment_part(gm, path)
    if body_vertices is not None:
        part.boundary, imported["boundary"] = choose_boundary(gm, gm.vertices, body_vertices, body_faces, cfg.boundary)
    elif gm.boundary is not None:
        part.boundary = gm.boundary
    return part, imported
