"""The same dress and walk run by physavatar's simulator and by NVIDIA Newton's VBD (issue 25 part 5).

    python benchmarks/sim_compare.py [--frames N] [--substeps K] [--out FILE]

The scene is the demo capture's (synth.PRESETS["demo"]): the 2-cm dress (~3.4k vertices) on Anny's
collider body (1.2k vertices), the built-in walk at 25 fps, its boundary vertices attached to the
body surface (physavatar.garment.attachment_positions: the same targets for both simulators).

Matched settings:
- frame step 0.04 s for both: physavatar takes one implicit (IPC) step per frame; VBD, an
  explicit-in-contact block-descent method, takes ``--substeps`` steps of 0.04/K s per frame with
  10 iterations each (Newton's own cloth examples use 10 substeps at 60 fps);
- material: the cotton preset (ρ = 0.187 kg/m², κs = 30.9 N/m, κb = 2.07e-5 N·m, ν = 0) mapped by
  foreign.newton_cloth.Fabric.from_physical: Lamé μ = κs/(2(1+ν)), λ = κs ν/(1−ν²) (kept ≥ 0.1 μ,
  as Newton's stable Neo-Hookean needs λ > 0), hinge k = 3 κb/(√3/2 ℓ) for the mean edge ℓ;
  physavatar's StVK against Newton's stable Neo-Hookean membrane;
- contact: physavatar's IPC barrier (d̂ = 1 mm, friction 0.2) against Newton's penalty springs
  between particles of radius 4 mm and the body mesh (friction 0.2);
- self-contact off in both (``SimSettings``' default; `simulate` and `animate` turn physavatar's on,
  `benchmarks/sim_speed.py` measures it on); ``config`` records both.

Measured in one process, one after the other: simulated frames/s (Newton's kernel compilation,
cached in ~/.cache/warp, is done in a warm-up before the clock starts) and frames in which the
garment crosses the body (physavatar.geometry.intersect: garment edges through body triangles
and body edges through garment triangles), NaN frames, and the distance between the two
simulators' garments per frame (mean vertex distance). Writes benchmarks/results/sim_compare.json.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "2")
HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import numpy as np
from _common import cpu_name


def crossing_frames(traj, faces, bodies, body_faces) -> list[int]:
    from physavatar.geometry.intersect import count_intersections

    return [f for f in range(len(traj)) if not np.isfinite(traj[f]).all()
            or count_intersections(traj[f], faces, bodies[f], body_faces) > 0]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=24, help="frames of the walk, frame 0 included (demo: 48)")
    ap.add_argument("--substeps", type=int, default=10, help="VBD steps per frame")
    ap.add_argument("--iterations", type=int, default=10, help="VBD iterations per step")
    ap.add_argument("--out", default=str(HERE / "results" / "sim_compare.json"))
    args = ap.parse_args(argv)

    from foreign.newton_cloth import ClothOnBody, Fabric, NewtonSettings

    from physavatar.body import builtin_motion
    from physavatar.garment import attachment_positions, make_attachment
    from physavatar.garment_sim import simulate_on_body, split_template
    from physavatar.sim import SimSettings, preset
    from physavatar.synth import PRESETS, build_template

    cfg = PRESETS["demo"]
    body, template, _ = build_template(cfg)
    motion = builtin_motion(cfg.motion, body.bone_names, cfg.fps, (args.frames - 1) / cfg.fps)
    bodies = np.asarray(motion.pose(body).vertices, np.float64)
    _, body_faces, part = split_template(template.vertices, template.faces, template.labels, template.boundary)
    mat = preset(cfg.material)
    E = np.concatenate([part.faces[:, [0, 1]], part.faces[:, [1, 2]], part.faces[:, [2, 0]]])
    edge = float(np.linalg.norm(part.vertices[E[:, 0]] - part.vertices[E[:, 1]], axis=1).mean())
    fabric = Fabric.from_physical(mat.density, mat.stretch_stiffness, mat.bend_stiffness, mat.poisson, edge)
    settings = SimSettings(dt=1.0 / cfg.fps)
    nsettings = NewtonSettings(substeps=args.substeps, iterations=args.iterations, friction=settings.friction)
    dt = 1.0 / cfg.fps
    att = make_attachment(part.vertices[part.boundary], part.boundary, bodies[0], body_faces, "sequence")
    targets = attachment_positions(att, bodies)  # [T, K, 3] in part.boundary order
    print(f"demo dress: {len(part.vertices)} vertices ({len(part.boundary)} attached), body {bodies.shape[1]}; "
          f"{args.frames} frames of walk at {cfg.fps:g} fps; VBD {args.substeps} x {args.iterations}", flush=True)

    # physavatar
    load0 = os.getloadavg()
    t0 = time.perf_counter()
    pa = simulate_on_body(part, bodies, body_faces, mat, cfg.fps, settings=settings)
    t_pa = time.perf_counter() - t0
    print(f"physavatar: {(args.frames - 1) / t_pa:.3f} frames/s", flush=True)

    # Newton VBD: warm-up (kernel compilation) on one frame, then the timed run
    warm = ClothOnBody(part.vertices, part.faces, part.boundary, bodies[0], body_faces, fabric, nsettings)
    warm.advance(dt, bodies[1], targets[1])
    sim = ClothOnBody(part.vertices, part.faces, part.boundary, bodies[0], body_faces, fabric, nsettings)
    nv = np.empty_like(pa)
    nv[0] = sim.positions
    t0 = time.perf_counter()
    for f in range(1, args.frames):
        nv[f] = sim.advance(dt, bodies[f], targets[f])
    t_nv = time.perf_counter() - t0
    load1 = os.getloadavg()
    print(f"newton VBD: {(args.frames - 1) / t_nv:.3f} frames/s", flush=True)

    bad_pa = crossing_frames(pa, part.faces, bodies, body_faces)
    bad_nv = crossing_frames(nv, part.faces, bodies, body_faces)
    diff = np.linalg.norm(pa - nv, axis=2).mean(1) * 1e3
    n = args.frames - 1
    figures = {
        "physavatar": {"frames_per_s": n / t_pa, "seconds": t_pa, "frames_crossing_body_or_nan": bad_pa,
                       "n_bad": len(bad_pa)},
        "newton_vbd": {"frames_per_s": n / t_nv, "seconds": t_nv, "frames_crossing_body_or_nan": bad_nv,
                       "n_bad": len(bad_nv), "fabric": fabric.__dict__, "settings": nsettings.__dict__},
        "mean_vertex_distance_between_simulators_mm": diff.tolist(),
        "hem_height_m": {"physavatar": [float(x) for x in pa[:, :, 2].min(1)],
                         "newton_vbd": [float(x) for x in nv[:, :, 2].min(1)]},
    }
    result = {
        "benchmark": "sim_compare",
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "machine": {"cores": os.cpu_count(), "cpu": cpu_name(), "gpu": None,
                    "load_average_start": [round(v, 2) for v in load0], "load_average_end": [round(v, 2) for v in load1]},
        "config": {"case": "synth demo dress (edge 2 cm) on Anny collider body, built-in walk",
                   "frames": args.frames, "fps": cfg.fps, "garment_vertices": len(part.vertices),
                   "body_vertices": int(bodies.shape[1]), "material": mat.to_dict(), "mean_edge_m": edge,
                   "physavatar_settings": {"dt": settings.dt, "dhat": settings.dhat, "friction": settings.friction,
                                           "self_contact": settings.self_contact, "membrane": settings.membrane_model},
                   "newton": {"substeps": args.substeps, "iterations": args.iterations, "dt": dt / args.substeps,
                              "device": "cpu (warp-lang kernels)", "self_contact": False}},
        "figures": figures,
        "checks": {
            "physavatar_no_crossing": {"value": len(bad_pa), "target": "0 frames", "unit": "frames", "pass": not bad_pa},
            "newton_runs_finite": {"value": int(np.isfinite(nv).all()), "target": "1", "unit": "bool",
                                   "pass": bool(np.isfinite(nv).all())},
            "physavatar_fps_at_least_newton_cpu": {"value": (n / t_pa) / (n / t_nv), "target": ">= 1",
                                                   "unit": "fps ratio physavatar / newton (both on this CPU)",
                                                   "pass": t_pa <= t_nv},
        },
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"physavatar {n / t_pa:.3f} fps, {len(bad_pa)} crossing frames; Newton VBD {n / t_nv:.3f} fps, "
          f"{len(bad_nv)} crossing frames; mean distance between them {diff[-1]:.1f} mm at the last frame; wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
