"""Garment material recovery: the paper's estimator (fd + Adam) against exact gradients (LM).

Three ground-truth materials (sim PRESETS silk / cotton / denim) on the built-in dress over the
Anny collider body walking; the "tracked" reference is the ground-truth simulation plus 2 mm
Gaussian noise. Both estimators start from the same far guess (the official driver's start:
Codim-IPC base fabric, multipliers 1; density prior = the medium fabric's). Then the
PhysAvatar Table 2 comparison on a held-out motion ("dance"): garment Chamfer distance (×10³)
of the LBS-skinned garment, and of simulations with a random, the estimated and the true
material. Prints a table and writes benchmarks/results/physics_recovery.json.

Ground truth is simulated with a tighter Newton tolerance (1e-6 m/s, the "real" motion) than
the fits and held-out simulations (1e-5 m/s; at the default 1e-3 m/s solver error alone puts
L_sim 15 % above the noise floor at the true material), so the true material has a small
non-zero held-out Chamfer distance. The fit starts from the clean rest state and knows ν. Friction is off in this benchmark (docs/physics.md: lagged friction
with ε_v = 1 mm/s makes L_sim jump by tens of percent for 1 % parameter changes on the dress).

    python benchmarks/physics_recovery.py [--quick] [--edge 0.07] [--window 12]
        [--fd-materials cotton] [--fd-iterations 100]

--quick: dress edge 7 cm (~300 vertices), a 12-frame window, fd on cotton only, exact on all
three materials, 24 held-out frames: 18 min with --fd-iterations 30 on the 2 shared cores
(what docs/physics.md reports); the paper's 100 fd iterations add ~35 min under load.
Without --quick: edge 5 cm, the paper's 24-frame window, fd on all three (hours).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import math
import os
import platform
import time
from pathlib import Path

import numpy as np

from physavatar.body import BodyModel, builtin_motion, linear_blend_skinning
from physavatar.garment import attachment_positions, garment_skinning_weights, make_garment
from physavatar.metrics import chamfer_distance, sample_surface
from physavatar.sim import PRESETS, SimSettings
from physavatar.stages.physics import PhysicsData, far_material, fit_exact, fit_fd, rollout

RESULTS = Path(__file__).parent / "results" / "physics_recovery.json"


def scene(edge, window, heldout_frames, fps=25.0):
    body = BodyModel(topology="collider")
    g = make_garment("dress", body, edge_length=edge)
    bidx = np.flatnonzero(g.boundary)
    assert np.array_equal(g.attachment.vertex_ids, bidx)  # attachment rows = sorted boundary ids

    def data_for(motion, frames):
        posed = builtin_motion(motion, body.bone_names, fps, (frames - 1) / fps).pose(body)
        bodies = posed.vertices[:frames]
        ref = np.repeat(g.vertices[None], len(bodies), 0)  # replaced by the ground truth below
        return PhysicsData(ref, g.faces, bidx, collider=bodies, collider_faces=body.faces, fps=fps,
                           rest=g.vertices, boundary_targets=attachment_positions(g.attachment, bodies)), posed

    train, _ = data_for("walk", window)
    held, held_posed = data_for("dance", heldout_frames)
    W = garment_skinning_weights(g.vertices, body, g.faces)
    lbs = linear_blend_skinning(g.vertices, W, held_posed.bone_transforms[:heldout_frames])
    return body, g, train, held, lbs


def garment_chamfer_x1e3(pred, gt, faces, n_points=20_000):
    """Mean over frames ≥ 1 of the Chamfer distance between sampled garment surfaces (×10³ m²).

    Both surfaces are sampled with the same seed per frame (common random numbers): with
    independent samples the sampling alone gives ~0.07 (5k points on the ~300-vertex dress),
    more than the differences between materials; with a shared seed identical meshes give 0.
    """
    cds = [chamfer_distance(sample_surface(p, faces, n_points, seed=t), sample_surface(q, faces, n_points, seed=t))
           for t, (p, q) in enumerate(zip(pred[1:], gt[1:]), start=1)]
    return 1e3 * float(np.mean(cds))


def random_material(rng, density):
    """Log-uniform κs ∈ [2.5, 600] N/m, κb ∈ [2.2e-8, 1e-4] N·m: the paper's ranges (SI) joined
    with the measured fabrics' (docs/physics.md)."""
    ks = math.exp(rng.uniform(math.log(2.5), math.log(600.0)))
    kb = math.exp(rng.uniform(math.log(2.2e-8), math.log(1e-4)))
    return dataclasses.replace(far_material(density), stretch_stiffness=ks, bend_stiffness=kb, name="random")


def time_to_reach(history, target):
    for row in history:
        if row["loss"] <= target:
            return row["wall_time_s"]
    return math.inf


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--edge", type=float, default=None, help="dress edge length [m]")
    ap.add_argument("--window", type=int, default=None, help="fitted frames")
    ap.add_argument("--heldout-frames", type=int, default=24)
    ap.add_argument("--fd-materials", default=None, help="comma-separated presets fitted with fd too")
    ap.add_argument("--fd-iterations", type=int, default=100)
    ap.add_argument("--exact-iterations", type=int, default=12)
    ap.add_argument("--noise-mm", type=float, default=2.0)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    edge = args.edge or (0.07 if args.quick else 0.05)
    window = args.window or (12 if args.quick else 24)
    fd_materials = (args.fd_materials or ("cotton" if args.quick else "silk,cotton,denim")).split(",")
    fit_settings = SimSettings(friction=0.0, newton_tol=1e-5)
    truth_settings = SimSettings(friction=0.0, newton_tol=1e-6)
    t_all = time.perf_counter()

    body, g, train, held, lbs = scene(edge, window, args.heldout_frames)
    print(f"dress: {len(g.vertices)} vertices, {len(g.faces)} faces, {len(train.boundary)} boundary; "
          f"body {len(body.rest_vertices)} vertices; window {window} frames (walk), held-out {args.heldout_frames} (dance)",
          flush=True)
    start = far_material()
    rng = np.random.default_rng(0)
    rows, figures = {}, {"per_material": {}}
    for mi, name in enumerate(("silk", "cotton", "denim")):
        true = PRESETS[name]
        t0 = time.perf_counter()
        gt_train = rollout(train, true, truth_settings).positions
        gt_held = rollout(held, true, truth_settings).positions
        print(f"[{name}] ground truth simulated in {time.perf_counter() - t0:.0f} s", flush=True)
        # the fit starts from the clean rest state (the template), not the noisy frame 0
        data = dataclasses.replace(train, reference=gt_train, initial=gt_train[0]).with_noise(args.noise_mm * 1e-3, seed=mi)
        # ν is a model setting, not estimated (the paper fixes it too): the fit uses the true one
        start = dataclasses.replace(far_material(), poisson=true.poisson)
        noise_floor = data.reference[1:].size * (args.noise_mm * 1e-3) ** 2
        fits = {}
        for method in ("exact", "fd"):
            if method == "fd" and name not in fd_materials:
                continue

            def log(row, method=method):
                if row["iteration"] % (10 if method == "fd" else 1) == 0:
                    print(f"  [{name} {method}] it {row['iteration']:3d} loss {row['loss']:.5g} "
                          f"ks {row['stretch_stiffness']:.4g} kb {row['bend_stiffness']:.4g} "
                          f"t {row['wall_time_s']:.0f} s", flush=True)

            if method == "exact":
                res = fit_exact(data, start, fit_settings, iterations=args.exact_iterations, callback=log)
            else:
                res = fit_fd(data, start, fit_settings, iterations=args.fd_iterations, workers=args.workers,
                             callback=log)
            m = res.material
            fits[method] = res
            rows[(name, method)] = {
                "bend_ratio_rel_error": m.bend_ratio / true.bend_ratio - 1,
                "stretch_ratio_rel_error": m.stretch_ratio / true.stretch_ratio - 1,
                "bend_ratio_interval95": res.ratio_intervals.get("bend_ratio"),
                "stretch_ratio_interval95": res.ratio_intervals.get("stretch_ratio"),
                "loss_m2": res.loss, "loss_over_noise_floor": res.loss / noise_floor, "rms_mm": res.rms_mm,
                "iterations": res.iterations, "simulations": res.simulations, "wall_time_s": res.wall_time,
                "fitted": {"stretch_stiffness": m.stretch_stiffness, "bend_stiffness": m.bend_stiffness,
                           "density_prior": m.density},
                "loss_history": [r["loss"] for r in res.history],
                "time_history_s": [r["wall_time_s"] for r in res.history],
            }
        # Table 2 on the held-out motion
        cd = {"lbs": garment_chamfer_x1e3(lbs, gt_held, g.faces)}
        rnd = random_material(rng, start.density)
        for label, mat in [("random", rnd)] + [(f"estimated_{k}", v.material) for k, v in fits.items()] + [("true", true)]:
            try:
                pos = rollout(held, mat, fit_settings).positions
                cd[label] = garment_chamfer_x1e3(pos, gt_held, g.faces)
            except (FloatingPointError, RuntimeError) as e:
                cd[label] = math.inf
                print(f"  [{name}] held-out {label} failed: {e}")
        figures["per_material"][name] = {
            "true": {"stretch_ratio": true.stretch_ratio, "bend_ratio": true.bend_ratio},
            "random_material": {"stretch_stiffness": rnd.stretch_stiffness, "bend_stiffness": rnd.bend_stiffness},
            "noise_floor_loss_m2": noise_floor,
            "heldout_chamfer_x1e3": cd,
            "estimators": {k: rows[(name, k)] for k in fits},
        }
        print(f"[{name}] held-out CD×1e3: " + ", ".join(f"{k} {v:.4f}" for k, v in cd.items()), flush=True)

    # checks
    checks = {}
    for name, fig in figures["per_material"].items():
        for method, r in fig["estimators"].items():
            checks[f"{name}_{method}_bend_ratio_within_10pct"] = {
                "value": abs(r["bend_ratio_rel_error"]), "target": "<= 0.10", "unit": "relative error",
                "pass": abs(r["bend_ratio_rel_error"]) <= 0.10}
        cd = fig["heldout_chamfer_x1e3"]
        est = cd.get("estimated_exact", math.inf)
        checks[f"{name}_heldout_cd_estimated_within_10pct_of_true"] = {
            "value": est / cd["true"] if cd["true"] > 0 else math.inf, "target": "<= 1.10", "unit": "CD ratio",
            "pass": est <= 1.10 * cd["true"]}
        checks[f"{name}_heldout_cd_estimated_below_lbs_and_random"] = {
            "value": est, "target": f"< min(lbs {cd['lbs']:.4g}, random {cd['random']:.4g})", "unit": "CD x1e3",
            "pass": est < min(cd["lbs"], cd["random"])}
        if "fd" in fig["estimators"]:
            fd, ex = fig["estimators"]["fd"], fig["estimators"]["exact"]
            target = fd["loss_m2"] * 1.01
            t_exact = time_to_reach([{"loss": l, "wall_time_s": t} for l, t in
                                     zip(ex["loss_history"], ex["time_history_s"])], target)
            checks[f"{name}_exact_reaches_fd_loss_in_third_of_fd_time"] = {
                "value": t_exact / fd["wall_time_s"], "target": "<= 0.333 (exact time to reach 1.01 x fd final loss / fd time)",
                "unit": "time ratio", "pass": t_exact <= fd["wall_time_s"] / 3}
    figures["total_wall_time_s"] = time.perf_counter() - t_all

    cpu = platform.processor() or platform.machine()
    try:
        cpu = [l for l in open("/proc/cpuinfo") if l.startswith("model name")][0].split(":")[1].strip()
    except (OSError, IndexError):
        pass
    result = {
        "benchmark": "physics_recovery",
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "machine": {"cores": os.cpu_count(), "cpu": cpu, "gpu": None, "load_average_1_5_15min": list(os.getloadavg())},
        "config": {
            "quick": args.quick, "garment": "dress", "edge_length_m": edge, "garment_vertices": len(g.vertices),
            "body": "Anny collider topology", "train_motion": "walk", "window_frames": window,
            "heldout_motion": "dance", "heldout_frames": args.heldout_frames, "fps": 25.0,
            "noise_mm": args.noise_mm, "initial": start.to_dict(), "fd_materials": fd_materials,
            "fd_iterations": args.fd_iterations, "exact_max_iterations": args.exact_iterations,
            "workers": args.workers, "fit_settings": {"friction": 0.0, "newton_tol": 1e-5, "dt": 0.04},
            "truth_settings": {"friction": 0.0, "newton_tol": 1e-6, "dt": 0.04},
            "poisson": "the true preset's (a setting, not estimated)", "fit_start_state": "clean rest (template)",
            "chamfer": "mean over held-out frames of CD between 20000-point surface samples (same seed for both), x1e3 m^2",
        },
        "figures": figures,
        "checks": checks,
    }
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(result, indent=2, default=float) + "\n")

    print(f"\n{'material':8s} {'method':6s} {'kb/rho err':>10s} {'ks/rho err':>10s} {'loss/floor':>10s} "
          f"{'sims':>5s} {'time s':>7s}")
    for (name, method), r in rows.items():
        print(f"{name:8s} {method:6s} {r['bend_ratio_rel_error']:+10.3f} {r['stretch_ratio_rel_error']:+10.3f} "
              f"{r['loss_over_noise_floor']:10.3f} {r['simulations']:5d} {r['wall_time_s']:7.0f}")
    print("\nheld-out Chamfer x1e3 (dance):")
    for name, fig in figures["per_material"].items():
        print(f"  {name:8s} " + "  ".join(f"{k} {v:.4f}" for k, v in fig["heldout_chamfer_x1e3"].items()))
    print("\nchecks:")
    for k, c in checks.items():
        print(f"  {'PASS' if c['pass'] else 'FAIL'} {k}: {c['value']:.4g} (target {c['target']})")
    print(f"wrote {RESULTS} ({figures['total_wall_time_s']:.0f} s)")


if __name__ == "__main__":
    main()
