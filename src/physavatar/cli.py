"""The ``physavatar`` command-line tool (typer).

Every command turns bad input (a :class:`PhysavatarError`) into one line naming the file and the
problem, and exit code 2 — never a traceback. Ctrl-C stops with exit code 130 and leaves only
finished outputs behind (all writes are atomic).
"""

from __future__ import annotations

import functools
import json
import os
import sys
import time
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.table import Table

from .errors import PhysavatarError

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="Physics-aware 3D avatars of dressed people from multi-view video (PhysAvatar on a CPU).",
    pretty_exceptions_enable=False,
)
motion_app = typer.Typer(no_args_is_help=True, help="Built-in and imported body motions.")
app.add_typer(motion_app, name="motion")

console = Console(stderr=False)
err_console = Console(stderr=True)


def handle_errors(fn):
    """Exit 2 with one clear line for bad input; 130 on Ctrl-C."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except PhysavatarError as e:
            err_console.print(f"[bold red]error:[/] {e}", highlight=False, soft_wrap=True)
            raise typer.Exit(2)
        except KeyboardInterrupt:
            err_console.print("[yellow]interrupted[/]: finished outputs are kept; run again to resume")
            raise typer.Exit(130)

    return wrapper


def _bad_option(name: str, problem: str):
    raise PhysavatarError(None, f"option {name}: {problem}")


# -- inspect -------------------------------------------------------------------------------------

@app.command()
@handle_errors
def inspect(
    capture: Path = typer.Argument(..., help="capture folder"),
    quick: bool = typer.Option(False, "--quick", help="decode only the first frame's images (every file is still checked to exist)"),
    as_json: bool = typer.Option(False, "--json", help="print the summary as JSON"),
):
    """Summarize a capture folder, or list every validation problem (exit code 2)."""
    from .capture import load_capture, summarize, validate_capture

    problems = validate_capture(capture, deep=not quick)
    if problems:
        for p in problems:
            err_console.print(f"[bold red]error:[/] {p}", highlight=False, soft_wrap=True)
        err_console.print(f"{len(problems)} problem(s) in {capture}")
        raise typer.Exit(2)
    s = summarize(load_capture(capture))
    if as_json:
        console.print_json(json.dumps(s))
        return
    t = Table(title=f"capture {capture}", show_header=False)
    for k, v in s.items():
        if isinstance(v, dict):
            v = ", ".join(f"{a}={b:.2f}" for a, b in v.items())
        t.add_row(k.replace("_", " "), str(v))
    console.print(t)


# -- motions -------------------------------------------------------------------------------------

@motion_app.command("list")
def motion_list():
    """List the built-in motions."""
    from .body.motion import BUILTIN

    t = Table("name", "what")
    for name, (_, doc) in BUILTIN.items():
        t.add_row(name, doc)
    console.print(t)


@motion_app.command("preview")
@handle_errors
def motion_preview(
    motion: str = typer.Argument(..., help="built-in name (see 'motion list'), or a .bvh / .npz file"),
    out: Path = typer.Option(..., "--out", "-o", help="output .mp4 or .gif"),
    fps: float = typer.Option(25.0, help="frames per second of the preview"),
    duration: float = typer.Option(4.0, help="seconds (built-in motions)"),
    max_frames: int = typer.Option(150, help="at most this many frames"),
    mapping: Optional[Path] = typer.Option(None, help="BVH joint-name mapping overrides (JSON)"),
):
    """Render a quick preview of a motion on the (decimated) Anny body, front and side."""
    from .body import BodyModel
    from .body.preview import render_frames, write_video

    if out.suffix.lower() not in (".mp4", ".gif"):
        _bad_option("--out", f"{out} must end in .mp4 or .gif")
    m = _load_motion(motion, fps, duration, mapping)
    if m.frames > max_frames:
        m = m.slice(0, max_frames)
    body = BodyModel(topology="collider")
    posed = m.pose(body)
    with console.status(f"rendering {m.frames} frames"):
        frames = render_frames(posed.vertices, body.faces, posed.joints, body.parents, title=m.name)
        write_video(out, frames, fps)
    console.print(f"wrote {out} ({m.frames} frames at {fps:g} fps)")


def _load_motion(spec: str, fps: float, duration: float, mapping: Optional[Path] = None):
    from .body import BodyModel
    from .body.motion import BUILTIN, Motion, builtin_motion

    names = BodyModel(topology="collider").bone_names
    if fps <= 0 or duration <= 0:
        _bad_option("--fps/--duration", "must be positive")
    if spec in BUILTIN:
        return builtin_motion(spec, names, fps, duration)
    p = Path(spec)
    if p.suffix.lower() == ".bvh":
        from .body.bvh import import_bvh

        return import_bvh(p, BodyModel(topology="collider"), mapping=mapping).resample(fps)
    if p.suffix.lower() == ".npz":
        return Motion.load(p).resample(fps).for_bones(names)
    if not p.exists():
        raise PhysavatarError(p, f"not a built-in motion ({', '.join(BUILTIN)}) and no such file")
    raise PhysavatarError(p, "motion files must be .bvh or .npz")


def _arm_clearance(m, spec: str, body, clearance: float):
    """Motion capture (.bvh) with the arms raised where the hands would pinch the garment against
    the trunk (body.motion.arm_clearance); other motions unchanged. Says what it changed."""
    import numpy as np

    if clearance < 0:
        _bad_option("--arm-clearance", "must be >= 0")
    if clearance == 0 or not str(spec).lower().endswith(".bvh"):
        return m, None
    from .body.motion import arm_clearance

    m2, info = arm_clearance(m, body, clearance)
    summary = {side: {"frames_raised": int(np.sum(d["angle_rad"] > 1e-3)),
                      "max_angle_deg": round(float(np.degrees(d["angle_rad"].max())), 1),
                      "min_distance_before_m": round(float(d["distance_before_m"].min()), 4),
                      "min_distance_after_m": round(float(d["distance_after_m"].min()), 4)} for side, d in info.items()}
    raised = {k: v for k, v in summary.items() if v["frames_raised"]}
    if raised:
        console.print("arm clearance: " + "; ".join(
            f"{side} arm raised in {v['frames_raised']} frames (up to {v['max_angle_deg']} deg), hand-to-trunk "
            f"{1000 * v['min_distance_before_m']:.0f} -> {1000 * v['min_distance_after_m']:.0f} mm" for side, v in raised.items())
            + f" (--arm-clearance {clearance:g} m; 0 keeps the motion as it is)")
    return m2, summary


@motion_app.command("import")
@handle_errors
def motion_import(
    bvh: Path = typer.Argument(..., help="a .bvh file"),
    out: Path = typer.Option(..., "--out", "-o", help="output motion .npz"),
    fps: Optional[float] = typer.Option(None, help="resample to this fps (default: keep the file's)"),
    mapping: Optional[Path] = typer.Option(None, help="JSON of {bvh_joint: anny_bone} overrides"),
):
    """Import a BVH file (CMU, Mixamo-style) retargeted to Anny, as a motion .npz."""
    from .body import BodyModel
    from .body.bvh import import_bvh

    m = import_bvh(bvh, BodyModel(topology="collider"), mapping=mapping)
    if fps:
        m = m.resample(fps)
    m.save(out)
    console.print(f"wrote {out}: {m.frames} frames at {m.fps:g} fps, "
                  f"{len(m.meta['mapped_joints'])} joints mapped, {m.meta['scale_m_per_unit']:.4f} m per file unit")


# -- synthetic captures --------------------------------------------------------------------------

@app.command()
@handle_errors
def synth(
    out: Path = typer.Argument(..., help="output capture folder (must not exist or be empty)"),
    preset: str = typer.Option("demo", help="tiny (for tests, seconds) or demo (the standard case)"),
    garment: Optional[str] = typer.Option(None, help="dress, skirt or tshirt (overrides the preset)"),
    motion: Optional[str] = typer.Option(None, help="built-in motion of the capture (overrides the preset)"),
    frames: Optional[int] = typer.Option(None, help="number of frames (overrides the preset)"),
    seed: Optional[int] = typer.Option(None),
):
    """Render a synthetic capture with ground truth (body + garment, textures, soft shadows)."""
    from dataclasses import replace

    from .body.motion import BUILTIN
    from .synth import PRESETS, synthesize

    if preset not in PRESETS:
        _bad_option("--preset", f"{preset!r} is not one of {', '.join(PRESETS)}")
    cfg = PRESETS[preset]
    changes = {}
    if garment is not None:
        from .garment import GARMENTS

        if garment not in GARMENTS:
            _bad_option("--garment", f"{garment!r} is not one of {', '.join(GARMENTS)}")
        changes["garment"] = garment
    if motion is not None:
        if motion not in BUILTIN:
            _bad_option("--motion", f"{motion!r} is not a built-in motion ({', '.join(BUILTIN)})")
        changes["motion"] = motion
    if frames is not None:
        if frames < 2:
            _bad_option("--frames", "needs at least 2 frames")
        changes["frames"] = frames
    if seed is not None:
        changes["seed"] = seed
    cfg = replace(cfg, **changes)
    t0 = time.time()
    path = synthesize(out, cfg)
    console.print(f"wrote capture {path} in {time.time() - t0:.0f} s "
                  f"({cfg.n_ring + cfg.n_elevated} cameras {cfg.width}x{cfg.height}, {cfg.frames} frames, "
                  f"garment {cfg.garment!r}, motion {cfg.motion!r}; held-out motion {cfg.heldout_motion!r})")


@app.command("render-capture")
@handle_errors
def render_capture(
    capture: Path = typer.Argument(..., help="capture folder"),
    out: Path = typer.Option(..., "--out", "-o", help="contact sheet PNG"),
    frame: Optional[int] = typer.Option(None, help="frame id (default: the first)"),
):
    """Write a contact sheet: all cameras of one frame in one labelled PNG."""
    from .capture import save_png
    from .synth import contact_sheet_for

    if out.suffix.lower() != ".png":
        _bad_option("--out", f"{out} must end in .png")
    sheet = contact_sheet_for(capture, frame)
    save_png(out, sheet)
    console.print(f"wrote {out} ({sheet.shape[1]}x{sheet.shape[0]})")


# -- simulate ----------------------------------------------------------------------------------

@app.command()
@handle_errors
def simulate(
    out: Path = typer.Option(..., "--out", "-o", help="output folder"),
    capture: Optional[Path] = typer.Option(None, help="simulate the garment of this capture's template on its body poses"),
    garment: Optional[str] = typer.Option(None, help="dress, skirt, tshirt, or a garment .ply (label/boundary properties) / .npz"),
    motion: Optional[str] = typer.Option(None, help="built-in motion, .bvh or .npz (with --garment KIND)"),
    collider: Optional[Path] = typer.Option(None, help="animated body: .npz (vertices [T,V,3], faces) or a folder of OBJ/PLY frames"),
    material: str = typer.Option("cotton", help="silk, cotton, denim, or a material .json"),
    fps: float = typer.Option(25.0, help="frames per second (one implicit step per frame by default)"),
    substeps: int = typer.Option(1, help="implicit steps per frame"),
    integrator: Optional[str] = typer.Option(None, help="euler (implicit Euler, the paper's) or bdf2 (second order; "
                                                        "docs/simulation.md); default: the one the material was "
                                                        "fitted with (euler for presets)"),
    duration: float = typer.Option(2.0, help="seconds (built-in motions)"),
    warmup: float = typer.Option(1.0, help="with --motion: seconds of transition from the garment's rest pose to the "
                                           "motion's first pose (simulated, not written)"),
    arm_clearance: float = typer.Option(0.03, "--arm-clearance",
                                        help="with a .bvh motion: raise the arms where a hand comes closer than this "
                                             "[m] to the hips/trunk, so the garment is not pinched (0 = off)"),
    edge_length: float = typer.Option(0.02, help="garment edge length [m] (with --garment KIND)"),
    preview: bool = typer.Option(True, help="write preview.mp4"),
):
    """Simulate a garment on a moving body: writes the garment sequence (npz + PLY) and an MP4 preview.

    Three ways to say what to simulate: --capture C; --garment KIND --motion M (on the Anny body);
    --collider SEQ --garment FILE (any animated body; boundary vertices follow the collider surface
    they start on).
    """
    import numpy as np

    from .data.garment_sequence import FILE as GARMENT_SEQUENCE, GarmentSequence
    from .data.material import resolve_material
    from .files import PlyMesh, write_json_atomic, write_ply
    from .data.mesh_sequence import load_mesh_sequence
    from .garment_sim import GarmentPart, simulate_on_body, split_template

    mat = resolve_material(material, option="--material")
    if fps <= 0 or substeps < 1:
        _bad_option("--fps/--substeps", "must be positive")
    if integrator is None:
        integrator = mat.integrator  # a fitted material is simulated in the model it was fitted in
    if integrator not in ("euler", "bdf2"):
        _bad_option("--integrator", f"{integrator!r} is not euler or bdf2")
    from .sim import SimSettings

    sim_settings = SimSettings(integrator=integrator)
    n_warm = 0  # leading frames simulated but not written (--motion's transition)
    clearance_info = None
    if capture is not None:
        from .body import BodyModel
        from .capture import load_capture

        cap = load_capture(capture)
        t = cap.template
        body_ids, body_faces, part = split_template(t.vertices, t.faces, t.labels, t.boundary)
        body = BodyModel(cap.body.shape, topology=cap.body.topology)
        if len(body.rest_vertices) != len(body_ids):
            raise PhysavatarError(capture / "template" / "mesh.ply",
                                  f"its body has {len(body_ids)} vertices but Anny's {cap.body.topology!r} topology has {len(body.rest_vertices)}")
        from .body import Motion

        m = Motion("capture", cap.fps, cap.body.bone_names, cap.body.rotations, cap.body.root_translation)
        bodies = m.pose(body).vertices
        fps = cap.fps
    elif collider is not None:
        if garment is None or not Path(garment).exists():
            _bad_option("--garment", "with --collider, give a garment mesh file (.ply with label/boundary, or .npz)")
        bodies, body_faces = load_mesh_sequence(collider)
        part = _garment_file(Path(garment))
    elif garment is not None and motion is not None:
        from .body import BodyModel
        from .garment import GARMENTS, make_garment

        if garment not in GARMENTS:
            _bad_option("--garment", f"{garment!r} is not one of {', '.join(GARMENTS)}")
        body = BodyModel(topology="collider")
        g = make_garment(garment, body, edge_length=edge_length)
        part = GarmentPart(np.arange(len(g.vertices)), g.vertices, g.faces, np.flatnonzero(g.boundary))
        from .stages.animate import transition

        mot = _load_motion(motion, fps, duration)
        mot, clearance_info = _arm_clearance(mot, motion, body, arm_clearance)
        rots, trs = mot.rotations, mot.root_translation
        # the garment is made for the rest pose: a motion that starts elsewhere (a BVH clip) is
        # reached by a transition first, as `animate` does, so the garment never starts inside the body
        if warmup < 0:
            _bad_option("--warmup", "must be >= 0")
        if np.abs(rots[0]).max() > 1e-6 or np.abs(trs[0]).max() > 1e-6:
            n_warm = max(2, int(round(warmup * fps)))
            wr, wt = transition(np.zeros_like(rots[0]), np.zeros(3), rots[0], trs[0], n_warm)
            rots, trs = np.concatenate([wr, rots]), np.concatenate([wt, trs])
        bodies = body.pose(rots, trs).vertices
        body_faces = body.faces
    else:
        _bad_option("--capture/--garment/--collider", "say what to simulate: --capture C, or --garment KIND --motion M, or --collider SEQ --garment FILE")
    if len(part.boundary) == 0:
        _bad_option("--garment", "the garment has no boundary vertices to attach to the body")
    from .geometry import count_intersections

    n_cross = count_intersections(part.vertices, part.faces, bodies[0], body_faces)
    if n_cross:
        raise PhysavatarError(collider or garment or capture,
                              f"the garment crosses the body's first frame ({n_cross} intersecting triangle pairs): "
                              "it must start outside the body, in the pose it was made for")
    t0 = time.time()
    X = simulate_on_body(part, bodies, body_faces, mat, fps, settings=sim_settings, substeps=substeps, progress=True)
    secs = time.time() - t0
    X, bodies = X[n_warm:], bodies[n_warm:]
    # every frame checked: finite and free of garment-body intersections (ipctk's exact test)
    from .sim.contact import ContactScene

    scene = ContactScene(part.vertices, part.faces, bodies[0], body_faces, sim_settings.dhat)
    bad = [f for f in range(len(X))
           if not np.all(np.isfinite(X[f])) or scene.has_intersections(np.vstack([X[f], bodies[f]]))]
    if bad:
        console.print(f"[yellow]warning:[/] {len(bad)} of {len(X)} frames intersect the body or are not finite: "
                      f"{bad[:20]}{' ...' if len(bad) > 20 else ''}")
    else:
        console.print(f"checked {len(X)} frames: no garment-body intersection, no NaN")
    out.mkdir(parents=True, exist_ok=True)
    GarmentSequence(X, part.faces, part.boundary, bodies, body_faces, fps, part.vertices).save(out / GARMENT_SEQUENCE)
    for f in range(len(X)):
        write_ply(out / "meshes" / f"{f:06d}.ply", PlyMesh(X[f], part.faces))
    mat.save(out / "material.json")
    write_json_atomic(out / "config.json", {"command": "simulate", "capture": str(capture) if capture else None,
                                            "garment": garment, "motion": motion, "collider": str(collider) if collider else None,
                                            "material": mat.to_dict(), "fps": fps, "substeps": substeps, "integrator": integrator,
                                            "frames_with_intersection_or_nan": bad, "warmup_frames": n_warm,
                                            "arm_clearance": clearance_info,
                                            "frames": int(len(X)), "seconds": round(secs, 1)})
    if preview:
        from .body.preview import render_frames, write_video

        Vall = np.concatenate([bodies, X], axis=1)
        Fall = np.concatenate([body_faces, part.faces + bodies.shape[1]])
        write_video(out / "preview.mp4", render_frames(Vall, Fall, None, None, title="simulate"), fps)
    console.print(f"simulated {len(X)} frames of a {len(part.vertices)}-vertex garment in {secs:.0f} s "
                  f"({(len(X) - 1) / max(secs, 1e-9):.2f} frames/s); wrote {out}/garment_sequence.npz, meshes/"
                  + (", preview.mp4" if preview else ""))


def _garment_file(path: Path):
    import numpy as np

    from .data.garment_sequence import GarmentSequence, boundary_ids
    from .files import load_npz, read_ply
    from .garment_sim import GarmentPart

    if path.suffix == ".npz":
        z = load_npz(path)
        if "vertices" in z and np.ndim(z["vertices"]) == 3:
            # a garment sequence (simulate's garment_sequence.npz, another simulator's): its rest shape
            d = GarmentSequence.from_arrays(z, path)
            if not len(d.boundary):
                raise PhysavatarError(path, "the garment sequence has no boundary (attached) vertices")
            return GarmentPart(np.arange(len(d.rest_vertices)), d.rest_vertices, d.faces, d.boundary)
        if not {"vertices", "faces", "boundary"} <= set(z):
            raise PhysavatarError(path, "garment .npz needs 'vertices', 'faces' and 'boundary'")
        V, F = z["vertices"], z["faces"]
        try:
            bidx = boundary_ids(z["boundary"], len(V))  # per-vertex flags, or indices
        except ValueError as e:
            raise PhysavatarError(path, str(e)) from None
        return GarmentPart(np.arange(len(V)), np.asarray(V, float), np.asarray(F, np.int64), bidx)
    m = read_ply(path)
    if "boundary" not in m.vertex_data:
        raise PhysavatarError(path, "needs a per-vertex 'boundary' property (1 = attached to the body)")
    return GarmentPart(np.arange(len(m.vertices)), m.vertices, m.faces, np.flatnonzero(m.vertex_data["boundary"]))


# -- avatar in use: animate, render, export ------------------------------------------------------

@app.command("build-avatar")
@handle_errors
def build_avatar_cmd(
    capture: Path = typer.Argument(..., help="capture folder"),
    out: Path = typer.Option(..., "--out", "-o", help="avatar folder"),
    material: str = typer.Option(..., help="material.json (fit-physics output) or a preset: silk, cotton, denim"),
    appearance: Optional[Path] = typer.Option(None, help="fit-appearance output folder (texture, light)"),
    tracked: Optional[Path] = typer.Option(None, help="tracking output folder: use the tracked frame 1 as the template"),
):
    """Bundle template, transferred skinning weights, material, texture and light into an avatar folder."""
    from .avatar import build_avatar

    tv = None
    if tracked is not None:
        from .data.tracked import TrackedSequence

        tv = TrackedSequence.load(tracked).vertices[0]
    av = build_avatar(capture, out, material=material, texture_dir=appearance, template_vertices=tv)
    console.print(f"wrote avatar {out}: {len(av.template.vertices)} vertices "
                  f"({int(av.template.garment_mask.sum())} garment), material {av.material.name or 'fitted'}, "
                  f"texture {'yes' if av.texture is not None else 'no'}, "
                  f"skinning matched {av.meta['skinning_matched_fraction']:.0%} (rest inpainted)")


@app.command()
@handle_errors
def animate(
    avatar: Path = typer.Argument(..., help="avatar folder (build-avatar)"),
    motion: str = typer.Option(..., help="built-in name, .bvh or .npz"),
    out: Path = typer.Option(..., "--out", "-o", help="sequence folder"),
    duration: float = typer.Option(4.0, help="seconds (built-in motions)"),
    warmup: float = typer.Option(1.0, help="seconds of transition from the capture pose to the motion's first pose"),
    max_frames: Optional[int] = typer.Option(None, help="at most this many frames"),
    arm_clearance: float = typer.Option(0.03, "--arm-clearance",
                                        help="with a .bvh motion: raise the arms where a hand comes closer than this "
                                             "[m] to the hips/trunk, so the garment is not pinched (0 = off)"),
):
    """Drive the avatar with a new motion: body by skinning, garment simulated with its material."""
    from .avatar import Avatar
    from .body import BodyModel
    from .stages.animate import animate as run_animate

    av = Avatar.load(avatar)
    m = _load_motion(motion, av.fps, duration)
    if arm_clearance and str(motion).lower().endswith(".bvh"):
        m, _ = _arm_clearance(m, motion, BodyModel(av.shape, topology="collider"), arm_clearance)
    if max_frames:
        m = m.slice(0, max_frames)
    seq, stats = run_animate(av, m, warmup_s=warmup)
    seq.save(out, {"command": "animate", "motion_spec": motion, **stats})
    console.print(f"animated {stats['frames']} frames (+{stats['warmup_frames']} warm-up) at {stats['sim_fps']:.2f} "
                  f"simulated frames/s; wrote {out}/sequence.npz, meshes/")


@app.command()
@handle_errors
def render(
    seq: Path = typer.Argument(..., help="sequence folder (animate)"),
    out: Path = typer.Option(..., "--out", "-o", help="output folder (frames/ and MP4)"),
    light: str = typer.Option("studio", help="fitted, studio, ambient, sky, sun, point, or an .hdr/.exr environment map "
                              "(docs/rendering.md)"),
    capture: Optional[Path] = typer.Option(None, help="render from this capture's cameras instead of an orbit"),
    cameras: str = typer.Option("", help="with --capture: comma-separated camera names (default all)"),
    spp: int = typer.Option(32, help="samples per pixel"),
    size: int = typer.Option(512, help="orbit image size (pixels)"),
):
    """Render a sequence to PNG frames and MP4 under the fitted or a new light."""
    from .data.animated import AnimatedSequence
    from .stages.render_seq import render_sequence

    s = AnimatedSequence.load(seq)
    cams = None
    if capture is not None:
        from .capture import load_capture

        cams = load_capture(capture).cameras
        if cameras:
            want = cameras.split(",")
            unknown = [c for c in want if c not in {k.name for k in cams}]
            if unknown:
                _bad_option("--cameras", f"unknown camera(s) {unknown}")
            cams = [c for c in cams if c.name in want]
    if spp < 1 or size < 16:
        _bad_option("--spp/--size", "spp must be >= 1 and size >= 16")
    r = render_sequence(s, out, cameras=cams, light=light, spp=spp, width=size, height=size)
    console.print(f"rendered {r['frames']} frames; wrote {', '.join(r['videos'])}")


@app.command()
@handle_errors
def export(
    seq: Path = typer.Argument(..., help="sequence folder (animate)"),
    out: Path = typer.Option(..., "--out", "-o", help="output file (.usd/.usdc/.usda/.glb) or folder (obj, ply)"),
    fmt: str = typer.Option("", "--format", help="usd, glb, obj or ply (default: from --out's extension)"),
):
    """Export a sequence: USD (time-sampled points, UVs, textured material), glTF binary, OBJ/PLY sequences."""
    from .data.animated import AnimatedSequence
    from .export import MeshSequence
    from .export import export as run_export

    s = AnimatedSequence.load(seq)
    tex = None
    if s.avatar is not None and (Path(s.avatar) / "texture.png").exists():
        tex = Path(s.avatar) / "texture.png"
    fmt = fmt or {".usd": "usd", ".usdc": "usd", ".usda": "usd", ".glb": "glb"}.get(out.suffix.lower(), "")
    if fmt not in ("usd", "glb", "obj", "ply"):
        _bad_option("--format", "choose usd, glb, obj or ply (or give --out a .usd/.glb name)")
    if fmt == "usd" and out.suffix.lower() not in (".usd", ".usdc", ".usda"):
        out = out.with_suffix(".usdc")
    if fmt == "glb" and out.suffix.lower() != ".glb":
        out = out.with_suffix(".glb")
    ms = MeshSequence(s.vertices, s.faces, uvs=s.face_uvs, texture=tex, fps=s.fps)
    run_export(out, ms, fmt)
    console.print(f"exported {len(s.vertices)} frames as {fmt}: {out}")


# -- evaluation and the whole pipeline -----------------------------------------------------------

@app.command()
@handle_errors
def evaluate(
    capture: Path = typer.Argument(..., help="synthetic capture (with ground_truth/)"),
    avatar: Path = typer.Option(..., help="avatar folder (build-avatar)"),
    out: Path = typer.Option(..., "--out", "-o", help="output folder: metrics.json, report.md, views/"),
    tracked: Optional[Path] = typer.Option(None, help="tracking output: also report tracking error"),
    frames: Optional[int] = typer.Option(None, help="evaluate the first N held-out frames"),
    points: int = typer.Option(10000, help="points sampled per surface for Chamfer / F-score"),
    sequence: Optional[Path] = typer.Option(None, help="animate output on the held-out motion: reuse it as the estimated-material row"),
    references: Optional[Path] = typer.Option(None, help="reference-sims output of this capture: reuse its true- and random-material rows"),
):
    """Metrics against ground truth: garment/full Chamfer and F-scores on the held-out motion for LBS,
    random, estimated and true material; PSNR/SSIM/LPIPS on held-out views; tracking error."""
    from .stages.evaluate import evaluate as run_eval

    if points < 100:
        _bad_option("--points", "use at least 100 points")
    run_eval(capture, avatar, out, tracked=tracked, frames=frames, n_points=points, sequence=sequence,
             references=references)
    console.print((out / "report.md").read_text())


@app.command("reference-sims")
@handle_errors
def reference_sims(
    capture: Path = typer.Argument(..., help="synthetic capture (with ground_truth/)"),
    out: Path = typer.Option(..., "--out", "-o", help="output folder: avatar/, true/, random/, references.json"),
    frames: Optional[int] = typer.Option(None, help="the first N held-out frames"),
):
    """The evaluation's reference rows ahead of time: the garment on the held-out motion with the
    true and with the random material (they need nothing fitted; `run` makes them while tracking)."""
    from .stages.evaluate import reference_sequences

    if frames is not None and frames < 2:
        _bad_option("--frames", "use at least 2 frames")
    reference_sequences(capture, out, frames=frames)
    console.print(f"wrote {out}/true, {out}/random")


@app.command()
@handle_errors
def run(
    capture: Path = typer.Argument(..., help="capture folder"),
    out: Path = typer.Argument(..., help="output folder (resumes when it exists)"),
    quick: bool = typer.Option(False, help="smaller budgets for every stage (tests, previews)"),
    track_frames: Optional[int] = typer.Option(None, help="track only the first N frames"),
    eval_frames: Optional[int] = typer.Option(None, help="animate / evaluate only the first N held-out frames"),
    motion: Optional[str] = typer.Option(None, help="motion to animate (built-in name, .bvh, .npz); default: the "
                                         "synthetic capture's held-out motion (then also evaluated), else 'dance'"),
):
    """Run the whole pipeline: track, fit-physics, fit-appearance, build-avatar, animate (held-out
    motion), render, relight, export (USD, glTF), evaluate (synthetic captures); skips finished
    stages; writes OUT/report.md."""
    from .stages.run import run_pipeline, write_report

    rec = run_pipeline(capture, out, quick=quick, track_frames=track_frames, eval_frames=eval_frames,
                       heldout_motion=motion)
    path = write_report(out)
    console.print(f"done in {rec['_total_seconds_this_run']:.0f} s; report: {path}")


# -- pose ----------------------------------------------------------------------------------------

@app.command()
@handle_errors
def pose(
    motion: str = typer.Option("walk", help="built-in name, .bvh or .npz"),
    out: Path = typer.Option(..., "--out", "-o", help="output folder"),
    fps: float = typer.Option(25.0),
    duration: float = typer.Option(2.0, help="seconds (built-in motions)"),
    topology: str = typer.Option("full", help="body topology: full, notoes, collider, coarse, tiny"),
    shape: str = typer.Option("", help="phenotypes, e.g. 'height=0.7,weight=0.4' (each in [0, 1])"),
    preview: bool = typer.Option(True, help="also write preview.gif"),
):
    """Build an Anny body, pose it with a motion, write the mesh sequence (npz + PLY per frame)."""
    from .body import BodyModel, BodyShape
    from .body.preview import render_frames, write_video
    from .files import PlyMesh, save_npz_atomic, write_json_atomic, write_ply
    from .body.model import TOPOLOGIES

    if topology not in TOPOLOGIES:
        _bad_option("--topology", f"{topology!r} is not one of {', '.join(TOPOLOGIES)}")
    kw = {}
    for item in filter(None, shape.split(",")):
        k, _, v = item.partition("=")
        try:
            kw[k.strip()] = float(v)
        except ValueError:
            _bad_option("--shape", f"{item!r} is not name=value")
    try:
        bshape = BodyShape(**kw)
    except (TypeError, ValueError) as e:
        _bad_option("--shape", str(e))
    t0 = time.time()
    body = BodyModel(bshape, topology=topology)
    t_load = time.time() - t0
    m = _load_motion(motion, fps, duration)
    posed = m.pose(body)
    out.mkdir(parents=True, exist_ok=True)
    save_npz_atomic(out / "body_sequence.npz", vertices=posed.vertices.astype("float32"), faces=body.faces,
                    joints=posed.joints.astype("float32"), bone_names=body.bone_names, fps=fps,
                    skinning_weights=body.skinning_weights.astype("float32"))
    for t in range(posed.vertices.shape[0]):
        write_ply(out / "meshes" / f"{t:06d}.ply", PlyMesh(posed.vertices[t], body.faces))
    m.save(out / "motion.npz")
    write_json_atomic(out / "config.json", {"command": "pose", "motion": motion, "fps": fps, "duration": duration,
                                            "topology": topology, "shape": bshape.to_dict()})
    if preview:
        pv = BodyModel(bshape, topology="collider")
        pp = m.pose(pv)
        write_video(out / "preview.gif", render_frames(pp.vertices, pv.faces, pp.joints, pv.parents, title=m.name), fps)
    console.print(f"posed Anny ({topology}: {len(body.rest_vertices)} vertices, {len(body.bone_names)} bones; "
                  f"loaded in {t_load:.1f} s) with motion {m.name!r}: {m.frames} frames at {fps:g} fps")
    console.print(f"wrote {out}/body_sequence.npz, {out}/meshes/*.ply, {out}/motion.npz"
                  + (f", {out}/preview.gif" if preview else ""))


# -- fit-physics ---------------------------------------------------------------------------------

@app.command("fit-physics")
@handle_errors
def fit_physics(
    source: Path = typer.Argument(..., help="tracked folder (tracked.npz), capture with ground_truth/meshes.npz, or a "
                                            "garment sequence (simulate's folder / garment_sequence.npz, any .npz of "
                                            "vertices, faces, boundary, body_vertices, body_faces, fps)"),
    out: Path = typer.Option(..., "--out", "-o", help="output folder (material.json, fit_log.csv, fit.png)"),
    gradient: str = typer.Option("exact", help="fd (the paper: finite differences + Adam) or exact (sensitivities + Gauss-Newton)"),
    window: int = typer.Option(24, help="frames fitted (the paper: 24)"),
    start: int = typer.Option(0, help="first frame of the window (simulated from rest there)"),
    iterations: Optional[int] = typer.Option(None, help="optimizer iterations (default: 100 fd, 15 exact)"),
    init: str = typer.Option("far", help="initial material: a material JSON, a preset (silk, cotton, denim) or 'far'"),
    fit_density: bool = typer.Option(False, "--fit-density", help="also fit rho (only ks/rho, kb/rho are identifiable)"),
    density: Optional[float] = typer.Option(None, help="density prior rho in kg/m^2 (default: the initial material's)"),
    noise_mm: float = typer.Option(0.0, "--noise-mm", help="Gaussian noise (mm) added to the reference (benchmarks)"),
    workers: int = typer.Option(2, help="processes for the fd simulations"),
    seed: int = typer.Option(0, help="seed of --noise-mm"),
    friction: float = typer.Option(0.2, help="cloth-body friction coefficient of the simulator (0 = off)"),
    newton_tol: float = typer.Option(1e-4, "--newton-tol", help="Newton tolerance of the fitting simulations [m/s]"),
    substeps: int = typer.Option(1, help="implicit steps per frame of the fitting simulations (more: less "
                                         "time-discretisation error, proportionally slower)"),
    integrator: str = typer.Option("auto", help="time integrator of the fitting simulations: auto (exact: fit in "
                                                "euler, in bdf2 and in their blend with its weight fitted too, keep "
                                                "the best; fd: euler), euler or bdf2. The material records it and "
                                                "simulate/animate use it (docs/physics.md)"),
    max_vertices: int = typer.Option(1200, "--max-vertices",
                                     help="fit on a coarse proxy of at most this many vertices when the garment has "
                                          "more (0 = always the full garment; docs/physics.md)"),
    shape_weight: Optional[float] = typer.Option(None, "--shape-weight",
                                                 help="weight of the local-shape residuals next to L_sim (default: 3 "
                                                      "with exact, 0 = the paper's L_sim with fd; docs/physics.md)"),
):
    """Estimate the garment's cloth material from its tracked motion (PhysAvatar Sec. 3.2)."""
    import dataclasses as _dc

    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from .data.material import resolve_material
    from .stages.physics import (MODELS, PAPER_ITERATIONS, clear_start, far_material, fit_material, fit_settings,
                                 load_physics_data, on_proxy, write_outputs)
    from .stages.proxy import make_proxy

    if gradient not in ("fd", "exact"):
        _bad_option("--gradient", f"{gradient!r} is not fd or exact")
    if window < 2:
        _bad_option("--window", "needs at least 2 frames")
    if iterations is not None and iterations < 1:
        _bad_option("--iterations", "must be at least 1")
    if noise_mm < 0:
        _bad_option("--noise-mm", "must be >= 0")
    if density is not None and not density > 0:
        _bad_option("--density", "must be positive")
    if friction < 0:
        _bad_option("--friction", "must be >= 0")
    if not newton_tol > 0:
        _bad_option("--newton-tol", "must be positive")
    if substeps < 1:
        _bad_option("--substeps", "must be at least 1")
    if integrator not in ("auto", "euler", "bdf2"):
        _bad_option("--integrator", f"{integrator!r} is not auto, euler or bdf2")
    select = integrator == "auto" and gradient == "exact"
    if integrator == "auto":
        integrator = "euler"  # fd: the paper's; exact: the first of the two fits
    if max_vertices != 0 and max_vertices < 20:
        _bad_option("--max-vertices", "must be 0 (no proxy) or at least 20")
    if shape_weight is not None and not shape_weight >= 0:
        _bad_option("--shape-weight", "must be >= 0")
    initial = far_material() if init == "far" else resolve_material(init)
    if density is not None:
        initial = _dc.replace(initial, density=density)
    sequence = load_physics_data(source)
    if start < 0 or start + 2 > sequence.frames:
        _bad_option("--start", f"must leave at least 2 of the {sequence.frames} frames")
    if not len(sequence.boundary):
        console.print("[yellow]note:[/] the garment has no boundary (attached) vertices: it is simulated as held "
                      "by contact and friction alone" + (" (and --friction is 0)" if friction == 0 else ""))
    # the simulation starts from the tracked frame `start` at rest; IPC needs it outside the body
    data, start_info = clear_start(sequence.window(start, window), source, start, sequence)
    if start_info["pushed_vertices"]:
        console.print(f"[yellow]note:[/] frame {start} has the garment {start_info['crossing_pairs']} triangle pairs "
                      f"through the body / {start_info['min_gap_mm']:.2f} mm from it: {start_info['pushed_vertices']} "
                      f"vertices pushed out (at most {start_info['max_push_mm']:.1f} mm) to start the simulations")
    proxy = None
    n_fine = data.reference.shape[1]
    if max_vertices and n_fine > max_vertices:
        proxy = make_proxy(data.rest, data.faces, data.boundary, max_vertices)
        data = on_proxy(data, proxy)
        console.print(f"simulating a {len(proxy.vertices)}-vertex proxy of the {n_fine}-vertex garment "
                      f"(mean edge {100 * proxy.mean_edge:.1f} cm, {len(proxy.boundary)} boundary vertices)")
    # benchmark noise perturbs what is fitted to, not the (template-clean) start state
    data = data.with_noise(noise_mm * 1e-3, seed)
    n_iter = iterations or (PAPER_ITERATIONS if gradient == "fd" else 15)
    console.print(f"fitting {('rho, ' if fit_density else '') + 'ks, kb'} of a {data.reference.shape[1]}-vertex "
                  f"garment over {data.frames} frames ({gradient} gradients, up to {n_iter} iterations)")
    with Progress(TextColumn("[progress.description]{task.description}"), BarColumn(), MofNCompleteColumn(),
                  TimeElapsedColumn(), console=console) as bar:
        task = bar.add_task("fit", total=(n_iter + (1 if gradient == "exact" else 0)) * (len(MODELS) if select else 1))

        def report(row):
            params = "  ".join(f"{k}={row[k]:.4g}" for k in ("density", "stretch_stiffness", "bend_stiffness",
                                                              "bdf2_blend") if k in row)
            line = f"it {row['iteration']:3d}  loss {row['loss']:.4g} m² ({row['rms_mm']:.2f} mm)  {params}"
            if "integrator" in row:
                line += f"  [{row['integrator']}]"
            bar.update(task, advance=1, description=line)
            # one log line per iteration too: a bar alone shows nothing when output is not a terminal
            bar.console.print(f"{line}  {row['wall_time_s']:.0f} s", highlight=False)

        result = fit_material(data, initial, gradient, iterations, fit_density,
                              fit_settings(friction=friction, newton_tol=newton_tol, integrator=integrator),
                              workers=workers, substeps=substeps, callback=report,
                              shape_weight=shape_weight, select_integrator=select)
    result.start_state = start_info
    if proxy is not None:
        result.proxy = {"vertices": len(proxy.vertices), "faces": len(proxy.faces), "boundary": len(proxy.boundary),
                        "mean_edge_m": proxy.mean_edge, "garment_vertices": n_fine, "max_vertices": max_vertices}
    write_outputs(out, result)
    m = result.material
    ci = result.ratio_intervals
    t = Table(title=f"fitted material ({gradient})")
    for col in ("quantity", "value", "95% interval"):
        t.add_column(col)
    t.add_row("rho [kg/m²]", f"{m.density:.4g}", "fitted" if fit_density else "prior")
    t.add_row("ks [N/m]", f"{m.stretch_stiffness:.4g}", "")
    t.add_row("kb [N·m]", f"{m.bend_stiffness:.4g}", "")
    for key, label in (("stretch_ratio", "ks/rho [m²/s²]"), ("bend_ratio", "kb/rho [m³/s²]")):
        iv = ci.get(key)
        t.add_row(label, f"{getattr(m, key):.4g}", "-" if not iv else f"[{iv[0]:.4g}, {iv[1]:.4g}]")
    if m.integrator == "bdf2":
        sd = result.log_std.get("bdf2_blend")
        t.add_row("bdf2 blend γ (0 euler, 1 bdf2)", f"{m.bdf2_blend:.3g}",
                  "fixed" if sd is None else f"± {1.96 * sd:.2g}")
    console.print(t)
    if result.model_selection:
        fits = result.model_selection["fits"]
        def label(k, v):
            return k if v.get("bdf2_blend") is None else f"{k} (γ {v['bdf2_blend']:.3g})"

        console.print("time integrator: " + ", ".join(f"{label(k, v)} objective {v['objective']:.4g} m²"
                                                      for k, v in fits.items())
                      + f" -> kept {result.model_selection['chosen']} (recorded in material.json; simulate and "
                      "animate use it)")
    if result.at_bound():
        console.print(f"[yellow]warning: {', '.join(result.at_bound())} ended on the search bound: the simulation "
                      "cannot reproduce this motion (model error, e.g. a too coarse proxy; docs/physics.md)[/yellow]")
    console.print(f"loss {result.loss:.4g} m² (rms {result.rms_mm:.2f} mm), {result.simulations} simulations, "
                  f"{result.wall_time:.0f} s; wrote {out}/material.json, fit_log.csv, fit.png")


# -- track (paper Sec. 3.1) ----------------------------------------------------------------------

@app.command()
@handle_errors
def track(
    capture: Path = typer.Argument(..., help="capture folder"),
    out: Path = typer.Option(..., "--out", "-o", help="output folder (a rerun with the same config resumes)"),
    frames: Optional[int] = typer.Option(None, "--frames", help="track only the first N frames"),
    holdout: Optional[str] = typer.Option(None, "--holdout", help="cameras excluded from fitting, CAM,CAM ('' for none; default: two)"),
    iters_first: Optional[int] = typer.Option(None, "--iters-first", help="max iterations per pyramid level, frame 1"),
    iters: Optional[int] = typer.Option(None, "--iters", help="max iterations per pyramid level, later frames"),
    scale: Optional[float] = typer.Option(None, "--scale", help="resolution factor of the finest level, in (0, 1]"),
    no_iso: bool = typer.Option(False, "--no-iso", help="drop the isometry loss (ablation)"),
    no_normal: bool = typer.Option(False, "--no-normal", help="drop the normal loss (ablation)"),
    init: Optional[str] = typer.Option(None, "--init", help="start of each frame: mixed (body and garment boundary skinned from body.npz, the rest of the garment "
                                        "by constant velocity; default), lbs (all skinned + carried residual) or velocity"),
    garment_start: Optional[str] = typer.Option(None, "--garment-start", help="start of the free garment under --init mixed: "
                                                 "flow (multi-view optical flow + model-based corrections; default), velocity or physics"),
):
    """Track the template through the capture with mesh-aligned Gaussians (docs/tracking.md)."""
    from dataclasses import replace as _replace

    from .stages.track import TrackConfig, track as run_track

    cfg = TrackConfig()
    changes = {}
    if frames is not None:
        changes["n_frames"] = frames
    if holdout is not None:
        changes["holdout"] = tuple(h.strip() for h in holdout.split(",") if h.strip())
    if init is not None and init not in ("mixed", "lbs", "velocity"):
        _bad_option("--init", f"{init!r} is not mixed, lbs or velocity")
    if garment_start is not None:
        if garment_start not in ("flow", "velocity", "physics"):
            _bad_option("--garment-start", f"{garment_start!r} is not flow, velocity or physics")
        changes["garment_prediction"] = garment_start
    for name, value in (("iters_first", iters_first), ("iters", iters), ("scale", scale), ("init", init)):
        if value is not None:
            changes[name] = value
    if no_iso:
        changes["iso_weight"] = 0.0
    if no_normal:
        changes["normal_weight"] = 0.0
    cfg = _replace(cfg, **changes)
    t0 = time.time()
    res = run_track(capture, out, cfg)
    console.print(f"tracked {len(res.frames)} frames ({len(res.computed)} fitted now, the rest resumed) "
                  f"in {time.time() - t0:.0f} s; wrote {out}/tracked.npz, frames/, meshes/, track_log.csv")


# -- fit-appearance, relight (paper Sec. 3.3) ----------------------------------------------------

@app.command("fit-appearance")
@handle_errors
def fit_appearance_cmd(
    capture: Path = typer.Argument(..., help="capture folder"),
    out: Path = typer.Option(..., "--out", "-o", help="output folder (a rerun with the same config resumes)"),
    tracked: Optional[Path] = typer.Option(None, "--tracked", help="tracking output folder (tracked.npz: meshes + Gaussian colours)"),
    meshes: str = typer.Option("tracked", "--meshes", help="tracked, or gt (ground_truth/meshes.npz of a synthetic capture)"),
    light: str = typer.Option("ambient", "--light", help="ambient (the paper: texture + L_a) or studio (+ the known key light's intensity)"),
    lighting: Optional[Path] = typer.Option(None, "--lighting", help="studio lights file (default ground_truth/lighting.json)"),
    iterations: int = typer.Option(2000, "--iterations", help="Adam steps (paper: 2000)"),
    texture_size: int = typer.Option(512, "--texture-size", help="atlas resolution in texels"),
    scale: float = typer.Option(1.0, "--scale", help="image resolution factor in (0, 1]"),
    spp: int = typer.Option(8, "--spp", help="samples per pixel while fitting (paper: 8)"),
    final_spp: int = typer.Option(128, "--final-spp", help="samples per pixel of the preview renders"),
    batch: int = typer.Option(1, "--batch", help="random (frame, camera) views per step"),
    lr: float = typer.Option(0.01, "--lr", help="Adam learning rate, halved every --decay-every steps"),
    decay_every: int = typer.Option(500, "--decay-every"),
    frame_stride: int = typer.Option(1, "--frame-stride", help="fit every k-th frame"),
    cameras: Optional[str] = typer.Option(None, "--cameras", help="training cameras CAM,CAM (default: all)"),
    fix_light: bool = typer.Option(False, "--fix-light", help="keep the light at its initial value"),
    seed: int = typer.Option(0, "--seed"),
    quick: bool = typer.Option(False, "--quick", help="a few-minute CPU budget: 200 iterations (lr 0.02) on half-resolution images, 32-spp previews"),
):
    """Fit a relightable diffuse texture and the light by inverse rendering (docs/appearance.md)."""
    import numpy as np

    from .stages.appearance import AppearanceConfig, fit_appearance

    if meshes not in ("tracked", "gt"):
        _bad_option("--meshes", f"{meshes!r} is not tracked or gt")
    if meshes == "tracked" and tracked is None:
        _bad_option("--tracked", "needed with --meshes tracked (or pass --meshes gt for a synthetic capture)")
    cams = tuple(c.strip() for c in cameras.split(",") if c.strip()) if cameras else None
    cfg = AppearanceConfig(light=light, iterations=iterations, texture_size=texture_size, scale=scale, spp=spp,
                           final_spp=final_spp, batch=batch, lr=lr, lr_decay_every=decay_every,
                           frame_stride=frame_stride, cameras=cams, fit_light=not fix_light, seed=seed)
    if quick:
        from dataclasses import replace as _replace

        cfg = _replace(cfg, iterations=min(iterations, 200), scale=min(scale, 0.5), final_spp=min(final_spp, 32),
                       lr=max(lr, 0.02), lr_decay_every=min(decay_every, 50), init_frame_stride=4)
    t0 = time.time()
    res = fit_appearance(capture, out, cfg, tracked=tracked, meshes=meshes, lighting=lighting)
    amb = next((l.radiance for l in res.lights if type(l).__name__ == "Ambient"), None)
    losses = [r["loss"] for r in res.log]
    k = max(1, min(50, len(losses) // 4))
    msg = (f"fitted {cfg.texture_size}² texture + {cfg.light} light in {time.time() - t0:.0f} s "
           f"({res.seconds_per_iteration:.2f} s/iteration)")
    if losses:
        msg += f"; loss {np.mean(losses[:k]):.3g} -> {np.mean(losses[-k:]):.3g} (mean of {k} steps)"
    if amb is not None:
        msg += f"; ambient {tuple(round(float(a), 3) for a in np.broadcast_to(amb, 3))}"
    console.print(msg)
    console.print(f"wrote {out}/texture.png, texture_linear.npy, light.json, fit_log.csv, loss.png, preview.png")


@app.command()
@handle_errors
def relight(
    source: Path = typer.Argument(..., help="capture folder (ground-truth mesh) or tracking folder (tracked.npz)"),
    texture: Path = typer.Option(..., "--texture", help="fit-appearance output folder"),
    light: str = typer.Option("sky", "--light", help="fitted, studio, ambient, sky, sun, point, or an .hdr/.exr "
                              "environment map (docs/rendering.md)"),
    frame: Optional[int] = typer.Option(None, "--frame", help="frame id (default: the first)"),
    out: Path = typer.Option(..., "--out", "-o", help="contact sheet PNG"),
    capture: Optional[Path] = typer.Option(None, "--capture", help="capture folder for the cameras (when SOURCE is a tracking folder)"),
    spp: int = typer.Option(128, "--spp"),
    strength: float = typer.Option(1.0, "--strength", help="environment map scale"),
    scale: float = typer.Option(1.0, "--scale", help="image resolution factor"),
):
    """Render the avatar with its fitted texture under a new light, from every capture camera."""
    from .capture import load_capture, save_png
    from .data.tracked import FILE as TRACKED, TrackedSequence
    from .files import load_npz, read_json
    from .render import contact_sheet
    from .render.lights import light_center, named_lights
    from .stages.appearance import FittedAppearance, relight as run_relight

    if out.suffix.lower() != ".png":
        _bad_option("--out", f"{out} must end in .png")
    if spp < 1 or not (0 < scale <= 1):
        _bad_option("--spp/--scale", "spp >= 1 and scale in (0, 1]")
    fit = FittedAppearance.load(texture)
    if (source / TRACKED).is_file():
        tr = TrackedSequence.load(source, require=("vertices", "frames"))
        V_all, frames = tr.vertices, [int(f) for f in tr.frames]
        if capture is None:
            cfg_path = source / "config.json"
            guess = read_json(cfg_path).get("capture") if cfg_path.is_file() else None
            if not guess:
                _bad_option("--capture", "needed to find the cameras of a tracking folder")
            capture = Path(guess)
        cap = load_capture(capture)
    else:
        cap = load_capture(source)
        if cap.ground_truth is None or not (cap.ground_truth / "meshes.npz").is_file():
            raise PhysavatarError(source, "no ground_truth/meshes.npz: pass a tracking folder instead")
        V_all, frames = load_npz(cap.ground_truth / "meshes.npz")["vertices"], list(cap.frames)
    f = frames[0] if frame is None else frame
    if f not in frames:
        _bad_option("--frame", f"{f} is not one of the frames {frames[0]}..{frames[-1]}")
    V = V_all[frames.index(f)]
    t = cap.template
    if fit.face_uvs.shape != (len(t.faces), 3, 2):
        raise PhysavatarError(texture / "atlas.npz", "the atlas does not match this capture's template")
    lights = named_lights(light, light_center(V), fitted=fit.lights, strength=strength)
    imgs = []
    for cam in cap.cameras:
        r = run_relight(V, t.faces, fit.face_uvs, fit.texture, cam.scaled(scale), lights, labels=t.labels, spp=spp)
        imgs.append(r.srgb8())
    sheet = contact_sheet(imgs, [f"{c.name} {light if len(light) < 20 else Path(light).name}" for c in cap.cameras])
    save_png(out, sheet)
    console.print(f"wrote {out} ({len(imgs)} views of frame {f}, {sheet.shape[1]}x{sheet.shape[0]})")


def main():  # console-script entry point
    app()


if __name__ == "__main__":
    main()
