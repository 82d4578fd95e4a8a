"""Simulated frames per second of physavatar.sim on a dress-like garment over a moving body.

A procedural cone "skirt" (~3,000 vertices) is pinned at its top ring to a capsule-like body
(~1,200 vertices) that sways and bobs like a walk; one implicit step per frame (dt = 0.04 s).
Prints a table and writes benchmarks/results/sim_speed.json (DESIGN.md "Benchmarks").

    python benchmarks/sim_speed.py [--quick] [--frames N]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import time
from pathlib import Path

os.environ.setdefault("NUMBA_NUM_THREADS", "2")
os.environ.setdefault("OMP_NUM_THREADS", "2")

import numpy as np  # noqa: E402

from physavatar.sim import ClothSim, SimSettings, preset  # noqa: E402
from physavatar.sim.assembly import Factorization  # noqa: E402


def cone_garment(rings, segments, top_radius=0.16, bottom_radius=0.30, top_z=1.0, length=0.6):
    """Open cone: [rings*segments, 3] vertices, faces, and the top-ring vertex ids."""
    z = np.linspace(top_z, top_z - length, rings)
    r = np.linspace(top_radius, bottom_radius, rings)
    phi = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    V = np.stack([np.outer(r, np.cos(phi)), np.outer(r, np.sin(phi)), np.repeat(z[:, None], segments, 1)], -1)
    F = []
    for i in range(rings - 1):
        for j in range(segments):
            a, b = i * segments + j, i * segments + (j + 1) % segments
            c, d = a + segments, b + segments
            F += [[a, c, b], [b, c, d]]
    return V.reshape(-1, 3), np.array(F), np.arange(segments)


def capsule_body(rings=40, segments=30, radius=0.14, z0=0.3, z1=1.1):
    """Closed capsule-like body (a cylinder with hemispherical caps), outward normals."""
    verts = []
    n_cap = rings // 4
    for i in range(rings):
        t = i / (rings - 1)
        if i < n_cap:
            a = -np.pi / 2 + (i + 1) / (n_cap + 1) * np.pi / 2
            rr, zz = radius * np.cos(a), z0 + radius * np.sin(a)
        elif i >= rings - n_cap:
            k = i - (rings - n_cap)
            a = (k + 1) / (n_cap + 1) * np.pi / 2
            rr, zz = radius * np.cos(a), z1 + radius * np.sin(a)
        else:
            s = (i - n_cap) / (rings - 2 * n_cap - 1)
            rr, zz = radius, z0 + s * (z1 - z0)
        phi = np.linspace(0, 2 * np.pi, segments, endpoint=False)
        verts.append(np.stack([rr * np.cos(phi), rr * np.sin(phi), np.full(segments, zz)], 1))
    V = np.vstack(verts + [[[0, 0, z0 - radius]], [[0, 0, z1 + radius]]])
    bottom, top = len(V) - 2, len(V) - 1
    F = []
    for i in range(rings - 1):
        for j in range(segments):
            a, b = i * segments + j, i * segments + (j + 1) % segments
            F += [[a, b, a + segments], [b, b + segments, a + segments]]
    for j in range(segments):
        F.append([bottom, (j + 1) % segments, j])
        o = (rings - 1) * segments
        F.append([top, o + j, o + (j + 1) % segments])
    return V, np.array(F)


def body_motion(V, frame, fps=25.0):
    """Walk-like sway: lateral sway, forward/back lean about the hips, vertical bob."""
    t = frame / fps
    out = V.copy()
    lean = 0.15 * np.sin(2 * np.pi * 0.9 * t)  # rad about the x axis, pivot at hip height
    pivot = 0.9
    dz = out[:, 2] - pivot
    y = out[:, 1] * np.cos(lean) - dz * np.sin(lean)
    z = out[:, 1] * np.sin(lean) + dz * np.cos(lean)
    out[:, 1], out[:, 2] = y, z + pivot
    out[:, 0] += 0.05 * np.sin(2 * np.pi * 0.9 * t)
    out[:, 2] += 0.01 * np.sin(4 * np.pi * 0.9 * t)
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="10 frames instead of 50")
    ap.add_argument("--frames", type=int, default=None)
    args = ap.parse_args()
    frames = args.frames or (10 if args.quick else 50)
    fps = 25.0
    Vg, Fg, top = cone_garment(rings=40, segments=75)
    Vb, Fb = capsule_body()
    settings = SimSettings(dt=1.0 / fps)
    material = preset("cotton")
    sim = ClothSim(Vg, Fg, material, settings, top)
    # The top ring is attached to the body: it follows the body motion of its rest position.
    x, v = Vg.copy(), np.zeros_like(Vg)
    stats = []
    t0 = time.perf_counter()
    for f in range(frames):
        b0, b1 = body_motion(Vb, f), body_motion(Vb, f + 1)
        targets = body_motion(Vg[top], f + 1)
        x, v, st = sim.step(x, v, b0, b1, Fb, targets)
        stats.append(st)
        print(f"frame {f + 1:3d}: {st.newton_iterations:3d} Newton its, {st.factorizations} fact, "
              f"{st.cg_iterations:4d} CG its, {st.n_contacts:4d} contacts, "
              f"{st.time['total']:.2f} s, converged={st.converged}")
    wall = time.perf_counter() - t0
    # One sparse factorization of the same (free-DOF) system, for the step/factorization ratio.
    H = sim.assembler_free.assemble([t.hessian(np.vstack([x, b1]), project=True) for t in sim.terms])
    tf = time.perf_counter()
    reps = 3
    for _ in range(reps):
        Factorization(H)
    t_fact = (time.perf_counter() - tf) / reps
    # ... and of the sparsified matrix the CG preconditioner factorises (assembly.NewtonLinearSolver)
    P = sim.assembler_free.preconditioner_matrix(H)
    tf = time.perf_counter()
    for _ in range(reps):
        Factorization(P)
    t_fact_pre = (time.perf_counter() - tf) / reps
    split = {k: float(np.mean([s.time[k] for s in stats])) for k in stats[0].time}
    fps_sim = frames / wall
    figures = {
        "fps": fps_sim,
        "newton_iterations_per_frame": float(np.mean([s.newton_iterations for s in stats])),
        "max_newton_iterations": int(max(s.newton_iterations for s in stats)),
        "converged_frames": int(sum(s.converged for s in stats)),
        "time_split_s_per_frame": split,
        "factorization_s": t_fact,
        "preconditioner_factorization_s": t_fact_pre,
        "step_over_factorization": split["total"] / t_fact,
        "newton_iteration_over_factorization": split["total"] / t_fact / float(np.mean([s.newton_iterations for s in stats])),
        "factorizations_per_frame": float(np.mean([s.factorizations for s in stats])),
        "cg_iterations_per_frame": float(np.mean([s.cg_iterations for s in stats])),
        "newton_iterations_per_frame_series": [s.newton_iterations for s in stats],
        "mean_contacts": float(np.mean([s.n_contacts for s in stats])),
    }
    result = {
        "benchmark": "sim_speed",
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "machine": {"cores": os.cpu_count(), "cpu": platform.processor() or platform.machine(), "gpu": None},
        "config": {
            "frames": frames, "fps": fps, "steps_per_frame": 1, "garment_vertices": len(Vg),
            "garment_faces": len(Fg), "body_vertices": len(Vb), "body_faces": len(Fb),
            "material": material.to_dict(), "dhat": settings.dhat, "friction": settings.friction,
            "newton_tol": settings.newton_tol, "membrane": settings.membrane_model,
            "quick": args.quick,
        },
        "figures": figures,
        "load_average_1_5_15min": list(os.getloadavg()),
        "checks": {"fps": {"value": fps_sim, "target": ">= 0.5", "unit": "frames/s", "pass": bool(fps_sim >= 0.5)}},
    }
    try:
        cpu = [l for l in open("/proc/cpuinfo") if l.startswith("model name")][0].split(":")[1].strip()
        result["machine"]["cpu"] = cpu
    except (OSError, IndexError):
        pass
    print(f"\nfps {fps_sim:.2f} (target >= 0.5); Newton its/frame {figures['newton_iterations_per_frame']:.1f}")
    print("time per frame [s]: " + ", ".join(f"{k} {v:.3f}" for k, v in split.items()))
    print(f"one factorization {t_fact:.3f} s (preconditioner {t_fact_pre:.3f} s); step / factorization = "
          f"{figures['step_over_factorization']:.1f}; factorizations/frame {figures['factorizations_per_frame']:.1f}, "
          f"CG its/frame {figures['cg_iterations_per_frame']:.0f}; load average {os.getloadavg()}")
    out = Path(__file__).resolve().parent / "results" / "sim_speed.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
