"""Commands of the material stage: simulate, fit-physics."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import typer
from rich.table import Table

from ..errors import PhysavatarError
from ._common import app, bad_option, console, handle_errors, say_clearance

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

    from ..data.garment_sequence import FILE as GARMENT_SEQUENCE, GarmentSequence
    from ..data.material import resolve_material
    from ..files import PlyMesh, write_json_atomic, write_ply
    from ..data.mesh_sequence import load_mesh_sequence
    from ..garment_sim import GarmentPart, simulate_on_body, split_template

    mat = resolve_material(material, option="--material")
    if fps <= 0 or substeps < 1:
        bad_option("--fps/--substeps", "must be positive")
    if integrator is None:
        integrator = mat.integrator  # a fitted material is simulated in the model it was fitted in
    if integrator not in ("euler", "bdf2"):
        bad_option("--integrator", f"{integrator!r} is not euler or bdf2")
    from ..sim import SimSettings

    sim_settings = SimSettings(integrator=integrator)
    n_warm = 0  # leading frames simulated but not written (--motion's transition)
    clearance_info = None
    if capture is not None:
        from ..body import BodyModel
        from ..capture import load_capture

        cap = load_capture(capture)
        t = cap.template
        body_ids, body_faces, part = split_template(t.vertices, t.faces, t.labels, t.boundary)
        body = BodyModel(cap.body.shape, topology=cap.body.topology)
        if len(body.rest_vertices) != len(body_ids):
            raise PhysavatarError(capture / "template" / "mesh.ply",
                                  f"its body has {len(body_ids)} vertices but Anny's {cap.body.topology!r} topology has {len(body.rest_vertices)}")
        from ..body import Motion

        m = Motion("capture", cap.fps, cap.body.bone_names, cap.body.rotations, cap.body.root_translation)
        bodies = m.pose(body).vertices
        fps = cap.fps
    elif collider is not None:
        if garment is None or not Path(garment).exists():
            bad_option("--garment", "with --collider, give a garment mesh file (.ply with label/boundary, or .npz)")
        bodies, body_faces = load_mesh_sequence(collider)
        part = _garment_file(Path(garment))
    elif garment is not None and motion is not None:
        from ..body import BodyModel
        from ..garment import GARMENTS, make_garment

        if garment not in GARMENTS:
            bad_option("--garment", f"{garment!r} is not one of {', '.join(GARMENTS)}")
        body = BodyModel(topology="collider")
        g = make_garment(garment, body, edge_length=edge_length)
        part = GarmentPart(np.arange(len(g.vertices)), g.vertices, g.faces, np.flatnonzero(g.boundary))
        from ..stages.animate import transition

        from ..body.load import load_motion, with_arm_clearance

        mot = load_motion(motion, fps, duration)
        mot, clearance_info = with_arm_clearance(mot, motion, body, arm_clearance)
        say_clearance(clearance_info, arm_clearance)
        rots, trs = mot.rotations, mot.root_translation
        # the garment is made for the rest pose: a motion that starts elsewhere (a BVH clip) is
        # reached by a transition first, as `animate` does, so the garment never starts inside the body
        if warmup < 0:
            bad_option("--warmup", "must be >= 0")
        if np.abs(rots[0]).max() > 1e-6 or np.abs(trs[0]).max() > 1e-6:
            n_warm = max(2, int(round(warmup * fps)))
            wr, wt = transition(np.zeros_like(rots[0]), np.zeros(3), rots[0], trs[0], n_warm)
            rots, trs = np.concatenate([wr, rots]), np.concatenate([wt, trs])
        bodies = body.pose(rots, trs).vertices
        body_faces = body.faces
    else:
        bad_option("--capture/--garment/--collider", "say what to simulate: --capture C, or --garment KIND --motion M, or --collider SEQ --garment FILE")
    if len(part.boundary) == 0:
        bad_option("--garment", "the garment has no boundary vertices to attach to the body")
    from ..geometry import count_intersections

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
    from ..sim.contact import ContactScene

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
        from ..body.preview import render_frames, write_video

        Vall = np.concatenate([bodies, X], axis=1)
        Fall = np.concatenate([body_faces, part.faces + bodies.shape[1]])
        write_video(out / "preview.mp4", render_frames(Vall, Fall, None, None, title="simulate"), fps)
    console.print(f"simulated {len(X)} frames of a {len(part.vertices)}-vertex garment in {secs:.0f} s "
                  f"({(len(X) - 1) / max(secs, 1e-9):.2f} frames/s); wrote {out}/garment_sequence.npz, meshes/"
                  + (", preview.mp4" if preview else ""))


def _garment_file(path: Path):
    import numpy as np

    from ..data.garment_sequence import GarmentSequence, boundary_ids
    from ..files import load_npz, read_ply
    from ..garment_sim import GarmentPart

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

    from ..data.material import resolve_material
    from ..stages.physics import (MODELS, PAPER_ITERATIONS, clear_start, far_material, fit_material, fit_settings,
                                 load_physics_data, on_proxy, write_outputs)
    from ..stages.proxy import make_proxy

    if gradient not in ("fd", "exact"):
        bad_option("--gradient", f"{gradient!r} is not fd or exact")
    if window < 2:
        bad_option("--window", "needs at least 2 frames")
    if iterations is not None and iterations < 1:
        bad_option("--iterations", "must be at least 1")
    if noise_mm < 0:
        bad_option("--noise-mm", "must be >= 0")
    if density is not None and not density > 0:
        bad_option("--density", "must be positive")
    if friction < 0:
        bad_option("--friction", "must be >= 0")
    if not newton_tol > 0:
        bad_option("--newton-tol", "must be positive")
    if substeps < 1:
        bad_option("--substeps", "must be at least 1")
    if integrator not in ("auto", "euler", "bdf2"):
        bad_option("--integrator", f"{integrator!r} is not auto, euler or bdf2")
    select = integrator == "auto" and gradient == "exact"
    if integrator == "auto":
        integrator = "euler"  # fd: the paper's; exact: the first of the two fits
    if max_vertices != 0 and max_vertices < 20:
        bad_option("--max-vertices", "must be 0 (no proxy) or at least 20")
    if shape_weight is not None and not shape_weight >= 0:
        bad_option("--shape-weight", "must be >= 0")
    initial = far_material() if init == "far" else resolve_material(init)
    if density is not None:
        initial = _dc.replace(initial, density=density)
    sequence = load_physics_data(source)
    if start < 0 or start + 2 > sequence.frames:
        bad_option("--start", f"must leave at least 2 of the {sequence.frames} frames")
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
