"""Simulated frames per second of physavatar.sim: the demo dress on the demo walk.

The garment and body are those of the synthetic "demo" capture (synth.PRESETS["demo"]): the
2-cm dress (~3,350 vertices) on Anny's collider-topology body, the built-in "walk" at 25 fps,
one implicit step per frame (dt = 0.04 s), the cotton preset, simulated through the project's
own path (garment_sim.simulate_on_body: boundary vertices attached to the body surface). The
one-time body/garment build (Anny loads in ~20 s) is excluded from the timing.

Prints a table and writes benchmarks/results/sim_speed.json (DESIGN.md "Benchmarks"): frames/s,
Newton iterations per frame, the split of a frame's time (energy assembly, contact, linear
solve, CCD, line search) and the step time over the time of one sparse Cholesky factorisation
of the same system (the floor of an implicit step; measured in the same process, so the ratio
survives a loaded machine).

    python benchmarks/sim_speed.py [--quick] [--frames N] [--profile] [--set FIELD=VALUE] [--out FILE]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("NUMBA_NUM_THREADS", "2")
os.environ.setdefault("OMP_NUM_THREADS", "2")
sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402

from _common import cpu_name  # noqa: E402
from physavatar.body import builtin_motion  # noqa: E402
from physavatar.garment import attachment_positions, make_attachment  # noqa: E402
from physavatar.garment_sim import simulate_on_body, split_template  # noqa: E402
from physavatar.sim import ClothSim, SimSettings, preset  # noqa: E402
from physavatar.sim.assembly import Factorization  # noqa: E402
from physavatar.synth import PRESETS, build_template  # noqa: E402


def demo_scene(frames: int):
    """(GarmentPart, body sequence [T, Nb, 3], body faces, fps, material name) of the demo."""
    cfg = PRESETS["demo"]
    body, template, _ = build_template(cfg)
    motion = builtin_motion(cfg.motion, body.bone_names, cfg.fps, (frames - 1) / cfg.fps)
    posed = motion.pose(body)
    _, body_faces, part = split_template(template.vertices, template.faces, template.labels, template.boundary)
    return part, np.asarray(posed.vertices, np.float64), body_faces, cfg.fps, cfg.material


def factorization_time(part, bodies, body_faces, material, settings, x_last, reps=3):
    """Seconds of one sparse Cholesky of the full free-DOF Newton matrix at the last state
    (and of the sparsified matrix the CG preconditioner factorises)."""
    sim = ClothSim(part.vertices, part.faces, material, settings, part.boundary)
    att = make_attachment(part.vertices[part.boundary], part.boundary, bodies[0], body_faces, "sequence")
    tgt = attachment_positions(att, bodies[-1:])[0]
    order = np.argsort(part.boundary, kind="stable")
    # one step from the last state sets up the sim (same system: contacts, κ, pattern)
    sim.step(x_last, np.zeros_like(x_last), bodies[-1], bodies[-1], body_faces, tgt[order])
    X = np.vstack([x_last, bodies[-1]])
    sim.scene.prepare_static(X)
    H = sim.assembler_free.assemble([t.hessian(X, project=True) for t in sim.active_terms()])
    P = sim.assembler_free.preconditioner_matrix(H)
    out = []
    for M in (H, P):
        Factorization(M)  # warm
        t0 = time.perf_counter()
        for _ in range(reps):
            Factorization(M)
        out.append((time.perf_counter() - t0) / reps)
    return out[0], out[1], H.shape[0], H.nnz


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="12 frames instead of 48")
    ap.add_argument("--frames", type=int, default=None, help="frames of the walk (incl. frame 0)")
    ap.add_argument("--profile", action="store_true", help="also print a cProfile of the simulation")
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                    help="override a SimSettings field (e.g. barrier_stiffness_scale=1e12); repeatable")
    ap.add_argument("--out", default=None, help="result file (default benchmarks/results/sim_speed.json)")
    args = ap.parse_args()
    frames = args.frames or (12 if args.quick else PRESETS["demo"].frames)

    t0 = time.perf_counter()
    part, bodies, body_faces, fps, material_name = demo_scene(frames)
    t_build = time.perf_counter() - t0
    material = preset(material_name)
    overrides = {}
    for item in args.set:
        key, _, value = item.partition("=")
        if key not in SimSettings.__dataclass_fields__ or not value:
            sys.exit(f"--set {item!r}: expected FIELD=VALUE with FIELD one of SimSettings' fields")
        kind = type(getattr(SimSettings(), key))
        if kind is bool:
            overrides[key] = value.lower() in ("1", "true", "yes")
        elif kind in (int, float):
            overrides[key] = kind(float(value))
        else:
            overrides[key] = value
    settings = SimSettings(dt=1.0 / fps, **overrides)
    print(f"demo dress: {len(part.vertices)} vertices, {len(part.faces)} faces, {len(part.boundary)} attached; "
          f"body {bodies.shape[1]} vertices; {frames} frames of 'walk' at {fps:g} fps (build {t_build:.1f} s)")

    stats = []
    load0 = os.getloadavg()

    def callback(f, x, st):
        s = st[0]
        stats.append(s)
        print(f"frame {f:3d}: {s.newton_iterations:3d} Newton its ({s.penalty_iterations:2d} penalty), "
              f"{getattr(s, 'step_expansions', 0):2d} step doublings, {s.factorizations} fact, "
              f"{s.cg_iterations:4d} CG its, {s.line_search_iterations:2d} LS halvings, {s.n_contacts:4d} contacts, "
              f"{s.time['total']:.2f} s, converged={s.converged}", flush=True)

    prof = None
    if args.profile:
        import cProfile

        prof = cProfile.Profile()
        prof.enable()
    t0 = time.perf_counter()
    traj = simulate_on_body(part, bodies, body_faces, material, fps, settings=settings, callback=callback)
    wall = time.perf_counter() - t0
    if prof is not None:
        import pstats

        prof.disable()
        pstats.Stats(prof).sort_stats("tottime").print_stats(25)
    load1 = os.getloadavg()

    # every frame intersection-free and finite (ipctk's exact check; not timed)
    from physavatar.sim.contact import ContactScene

    scene = ContactScene(part.vertices, part.faces, bodies[0], body_faces, settings.dhat)
    bad_frames = [f for f in range(len(traj))
                  if not np.all(np.isfinite(traj[f])) or scene.has_intersections(np.vstack([traj[f], bodies[f]]))]
    t_fact, t_fact_pre, n_dofs, nnz = factorization_time(part, bodies, body_faces, material, settings, traj[-1])
    steps = len(stats)
    split = {k: float(np.mean([s.time[k] for s in stats])) for k in stats[0].time}
    its = [s.newton_iterations for s in stats]
    fps_sim = steps / wall
    figures = {
        "fps": fps_sim,
        "newton_iterations_per_frame": float(np.mean(its)),
        "max_newton_iterations": int(max(its)),
        "converged_frames": int(sum(s.converged for s in stats)),
        "time_split_s_per_frame": split,
        "factorization_s": t_fact,
        "preconditioner_factorization_s": t_fact_pre,
        "newton_matrix": {"dofs": int(n_dofs), "nnz": int(nnz)},
        "step_over_factorization": split["total"] / t_fact,
        "newton_iteration_over_factorization": split["total"] / t_fact / float(np.mean(its)),
        "factorizations_per_frame": float(np.mean([s.factorizations for s in stats])),
        "cg_iterations_per_frame": float(np.mean([s.cg_iterations for s in stats])),
        "line_search_halvings_per_frame": float(np.mean([s.line_search_iterations for s in stats])),
        "penalty_iterations_per_frame": float(np.mean([s.penalty_iterations for s in stats])),
        "step_doublings_per_frame": float(np.mean([getattr(s, "step_expansions", 0) for s in stats])),
        "newton_iterations_per_frame_series": its,
        "mean_contacts": float(np.mean([s.n_contacts for s in stats])),
        "min_distance_m": float(min(s.min_distance for s in stats)),
        "frames_with_intersection_or_nan": bad_frames,
        "body_follows_per_frame": float(np.mean([getattr(s, "body_follows", 0) for s in stats])),
    }
    result = {
        "benchmark": "sim_speed",
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "machine": {"cores": os.cpu_count(), "cpu": cpu_name(), "gpu": None,
                    "load_average_1_5_15min_start": [round(v, 2) for v in load0],
                    "load_average_1_5_15min_end": [round(v, 2) for v in load1]},
        "config": {
            "case": "synth demo: dress (edge 2 cm) on Anny 'collider' body, built-in 'walk'",
            "frames": frames, "steps": steps, "fps": fps, "steps_per_frame": 1, "dt": settings.dt,
            "garment_vertices": len(part.vertices), "garment_faces": len(part.faces),
            "attached_vertices": len(part.boundary), "body_vertices": int(bodies.shape[1]),
            "body_faces": len(body_faces), "material": material_name, "material_values": material.to_dict(),
            "dhat": settings.dhat, "friction": settings.friction, "newton_tol": settings.newton_tol,
            "newton_norm": settings.newton_norm, "newton_window": settings.newton_window,
            "membrane": settings.membrane_model, "follow_body": settings.follow_body,
            "follow_segments": settings.follow_segments, "follow_lift": settings.follow_lift,
            "quick": args.quick, "overrides": overrides,
        },
        "figures": figures,
        "checks": {"fps": {"value": fps_sim, "target": ">= 0.5", "unit": "frames/s", "pass": bool(fps_sim >= 0.5)},
                   "no_intersection_or_nan": {"value": len(bad_frames), "target": "0 frames", "unit": "frames",
                                              "pass": not bad_frames}},
    }
    print(f"\nfps {fps_sim:.2f} (target >= 0.5, aim 2); Newton its/frame {figures['newton_iterations_per_frame']:.1f} "
          f"(max {figures['max_newton_iterations']}), converged {figures['converged_frames']}/{steps}")
    print("time per frame [s]: " + ", ".join(f"{k} {v:.3f}" for k, v in split.items()))
    print(f"one factorization {t_fact:.3f} s (preconditioner {t_fact_pre:.3f} s); step / factorization = "
          f"{figures['step_over_factorization']:.1f}; factorizations/frame {figures['factorizations_per_frame']:.1f}, "
          f"CG its/frame {figures['cg_iterations_per_frame']:.0f}; load average {load0[0]:.2f} -> {load1[0]:.2f}")
    out = Path(args.out) if args.out else Path(__file__).resolve().parent / "results" / "sim_speed.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
