"""Commands on avatars and runs: build-avatar, animate, render, export, evaluate, reference-sims, run."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ._common import app, bad_option, console, handle_errors, say_clearance

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
    from ..avatar import build_avatar

    tv = None
    if tracked is not None:
        from ..data.tracked import TrackedSequence

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
    from ..avatar import Avatar
    from ..body import BodyModel
    from ..stages.animate import animate as run_animate

    av = Avatar.load(avatar)
    from ..body.load import load_motion, with_arm_clearance

    m = load_motion(motion, av.fps, duration)
    if arm_clearance and str(motion).lower().endswith(".bvh"):
        m, info = with_arm_clearance(m, motion, BodyModel(av.shape, topology="collider"), arm_clearance)
        say_clearance(info, arm_clearance)
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
    from ..data.animated import AnimatedSequence
    from ..stages.render_seq import render_sequence

    s = AnimatedSequence.load(seq)
    cams = None
    if capture is not None:
        from ..capture import load_capture

        cams = load_capture(capture).cameras
        if cameras:
            want = cameras.split(",")
            unknown = [c for c in want if c not in {k.name for k in cams}]
            if unknown:
                bad_option("--cameras", f"unknown camera(s) {unknown}")
            cams = [c for c in cams if c.name in want]
    if spp < 1 or size < 16:
        bad_option("--spp/--size", "spp must be >= 1 and size >= 16")
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
    from ..data.animated import AnimatedSequence
    from ..export import MeshSequence
    from ..export import export as run_export

    s = AnimatedSequence.load(seq)
    tex = None
    if s.avatar is not None and (Path(s.avatar) / "texture.png").exists():
        tex = Path(s.avatar) / "texture.png"
    fmt = fmt or {".usd": "usd", ".usdc": "usd", ".usda": "usd", ".glb": "glb"}.get(out.suffix.lower(), "")
    if fmt not in ("usd", "glb", "obj", "ply"):
        bad_option("--format", "choose usd, glb, obj or ply (or give --out a .usd/.glb name)")
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
    from ..stages.evaluate import evaluate as run_eval

    if points < 100:
        bad_option("--points", "use at least 100 points")
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
    from ..stages.evaluate import reference_sequences

    if frames is not None and frames < 2:
        bad_option("--frames", "use at least 2 frames")
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
    from ..stages.run import run_pipeline, write_report

    rec = run_pipeline(capture, out, quick=quick, track_frames=track_frames, eval_frames=eval_frames,
                       heldout_motion=motion)
    path = write_report(out)
    console.print(f"done in {rec['_total_seconds_this_run']:.0f} s; report: {path}")
