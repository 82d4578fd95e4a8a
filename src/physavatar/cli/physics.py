"""Commands of the material stage: simulate, fit-physics (options from the stages' configs)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer
from rich.table import Table

from ..stages import physics, simulate as simulate_stage
from ..stages.physics import PhysicsConfig
from ..stages.simulate import SimulateConfig
from ._common import app, console, handle_errors, say_clearance
from .options import config_command


@config_command(app, "simulate", SimulateConfig, wrap=handle_errors)
def simulate(
    out: Path = typer.Option(..., "--out", "-o", help="output folder"),
    capture: Optional[Path] = typer.Option(None, help="simulate the garment of this capture's template on its body poses"),
    garment: Optional[str] = typer.Option(None, help="dress, skirt, tshirt, or a garment .ply (label/boundary properties) / .npz"),
    motion: Optional[str] = typer.Option(None, help="built-in motion, .bvh or .npz (with --garment KIND)"),
    collider: Optional[Path] = typer.Option(None, help="animated body: .npz (vertices [T,V,3], faces) or a folder of OBJ/PLY frames"),
    *,
    config: SimulateConfig,
):
    """Simulate a garment on a moving body: writes the garment sequence (npz + PLY) and an MP4 preview.

    Three ways to say what to simulate: --capture C; --garment KIND --motion M (on the Anny body);
    --collider SEQ --garment FILE (any animated body; boundary vertices follow the collider surface
    they start on).
    """
    r = simulate_stage.run(out=out, config=config, capture=capture, garment=garment, motion=motion,
                           collider=collider, progress=True)
    say_clearance(r.clearance, config.arm_clearance, r.part_clearance)
    if r.bad_frames:
        bad = r.bad_frames
        console.print(f"[yellow]warning:[/] {len(bad)} of {r.frames} frames intersect the body or are not finite: "
                      f"{bad[:20]}{' ...' if len(bad) > 20 else ''}")
    else:
        console.print(f"checked {r.frames} frames: no garment-body intersection, no NaN")
    for what, frames in (("the body lagged behind its pose (config.json per_frame.lag_m)", r.lagged_frames),
                         ("the garment intersects itself", r.self_intersecting_frames)):
        if frames:
            console.print(f"[yellow]warning:[/] in {len(frames)} of {r.frames} frames {what}: "
                          f"{frames[:20]}{' ...' if len(frames) > 20 else ''}")
    console.print(f"simulated {r.frames} frames of a {r.garment_vertices}-vertex garment in {r.seconds:.0f} s "
                  f"({(r.frames - 1) / max(r.seconds, 1e-9):.2f} frames/s); wrote {out}/garment_sequence.npz, meshes/"
                  + (", preview.mp4" if r.preview else ""))


def _say(line: str) -> None:
    """A line of the fit: notes in yellow, iteration lines as they are."""
    if line.startswith("note:"):
        console.print("[yellow]note:[/]" + line[len("note:"):])
    else:
        console.print(line, highlight=not line.startswith("it "))


@config_command(app, "fit-physics", PhysicsConfig, wrap=handle_errors)
def fit_physics(
    source: Path = typer.Argument(..., help="tracked folder (tracked.npz), capture with ground_truth/meshes.npz, or a "
                                            "garment sequence (simulate's folder / garment_sequence.npz, any .npz of "
                                            "vertices, faces, boundary, body_vertices, body_faces, fps)"),
    out: Path = typer.Option(..., "--out", "-o", help="output folder (material.json, fit_log.csv, fit.png)"),
    *,
    config: PhysicsConfig,
):
    """Estimate the garment's cloth material from its tracked motion (PhysAvatar Sec. 3.2)."""
    result = physics.run(source, out=out, config=config, progress=True, say=_say)
    m = result.material
    ci = result.ratio_intervals
    t = Table(title=f"fitted material ({config.gradient})")
    for col in ("quantity", "value", "95% interval"):
        t.add_column(col)
    t.add_row("rho [kg/m²]", f"{m.density:.4g}", "fitted" if config.fit_density else "prior")
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
