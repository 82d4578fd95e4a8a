"""Garment material recovery: the paper's estimator (fd + Adam) against exact gradients (LM).

Three ground-truth materials (sim PRESETS silk / cotton / denim) on the built-in dress over the
Anny collider body walking; the "tracked" reference is the ground truth plus 2 mm Gaussian
noise. Both estimators start from the same far guess (the official driver's start: Codim-IPC
base fabric, multipliers 1; density prior = the medium fabric's). Then the PhysAvatar Table 2
comparison on held-out motions (``--heldout-motions``, default dance, turn, twist and jump, 24
frames each): garment Chamfer distance (×10³) of the LBS-skinned garment, and of simulations with
random materials (``--random-draws``, 5: the check takes their median, one draw can land near the
truth), the estimated and the true material, per motion and their mean, which the checks judge
(a single contact-rich clip moves by ~15 % between machines, as much as the differences judged).
Prints a table and writes benchmarks/results/physics_recovery.json.

Model error. A ground truth made by the fitting simulator itself gives the true material a
held-out distance of ~0 (only the Newton tolerance), which makes "estimated within 10 % of
true" meaningless. Real data (or another simulator) carries model error, so the ground truth
here is simulated differently from the fits: ``--truth-substeps`` implicit steps per frame
(default 2; the fits take 1, and implicit Euler's numerical damping depends on the step) and a
10× tighter Newton tolerance (1e-6 m/s vs 1e-5); optionally on a finer mesh than the fitted
one (``--proxy-vertices N``: the fits run on a decimated proxy, stages/physics/proxy.py, the fine
motion mapped onto it — the fit-physics path for big garments; its bias is large, see
docs/physics.md "Coarse proxy"). The "true" row simulates the true material in the fitting
model. The fit starts from the clean rest state and knows ν. Friction is off (docs/physics.md:
lagged friction makes L_sim rough at the 1 % scale).

Four settings (``--settings noise,model_error,other_simulator,foreign``):
- "noise": the issue's literal setup (the fitting simulator's own ground truth + noise); the
  κb/ρ-within-10 % checks are made here.
- "model_error": the ground truth above (``--truth-substeps`` implicit steps per frame).
- "other_simulator": a ground truth from a differently built simulator, standing in for the
  unseen simulator the issue will be checked with: BDF2 (``--other-integrator``) at 4 steps per
  frame (``--other-substeps``) with the neo-Hookean membrane (``--other-membrane``) instead of
  implicit Euler at 1 with StVK; optional mass damping (``--other-damping``).
- "foreign": a ground truth from code that shares nothing with physavatar.sim
  (benchmarks/foreign_cloth.py): an explicit mass-spring cloth (edge springs, so ν = 1/3 whatever
  the fabric's; Bridson et al.'s hinge bending; air damping and spring dashpots; closest-point
  collision with friction; symplectic Euler at tens of steps per frame), with the same fabric
  parameters. The "true" rows simulate the preset in physavatar.sim, so they measure how far the
  two simulators are apart as much as the estimator.
The held-out "within 10 % of true" checks are made in the model-error settings, where the
true material's distance is not ~0. κb/ρ's error there is *reported* against the same 10 % but
is not a check: under model error the true material is not the fitting model's best one (in
other_simulator the estimate predicts the held-out motion better than the true material), so
that error measures the model gap rather than the estimator. The paper's estimator's κb/ρ is
reported the same way. The exact estimator fits as ``fit-physics`` does by default
(``--fit-integrator auto``): in implicit Euler, in BDF2 and in their blend with γ fitted,
keeping the lowest objective (stages.physics.select.fit_selecting_integrator); each material's held-out row is
simulated in the model it was fitted in (with its γ), and "true_bdf2" (the true material in BDF2,
γ = 1) is added where an estimate kept BDF2 or the blend.
The exact estimator runs with the local-shape residuals
(``--shape-weight``, default 3) and, as "exact_eq6", on the paper's L_sim alone; fd and the
fd-vs-exact comparison use L_sim.

    python benchmarks/physics_recovery.py [--quick] [--edge 0.07] [--window 12]
        [--settings noise,model_error,other_simulator,foreign] [--truth-substeps 2] [--other-substeps 4]
        [--other-integrator bdf2] [--other-membrane neohookean] [--other-damping 0]
        [--foreign-alpha 0.2] [--foreign-beta 2e-4] [--foreign-friction 0.2]
        [--shape-weight 3] [--no-eq6-rows] [--proxy-vertices 0] [--fd-edge 0.10]
        [--fd-materials silk,cotton,denim] [--fd-setting noise] [--fd-iterations 100]
        [--fit-integrator auto|euler|bdf2] [--heldout-motions dance,turn,twist,jump] [--random-draws 5]
        [--out JSON]

--quick: dress edge 7 cm (299 vertices) for the accuracy runs (exact on all three materials),
the fd-vs-exact comparison on all three materials in the issue's setting (noise) with a coarser
dress (edge 10 cm, 152 vertices) so that the paper's 100 fd iterations finish; a 12-frame window, 24 held-out
frames (~1.5 h on 2 idle cores, four settings; ``--fd-materials ''`` runs the accuracy part alone,
``--settings ''`` the fd-vs-exact part alone, e.g. side by side into two ``--out`` files). Without --quick: edge 5 cm, the paper's 24-frame window, fd on all three (hours).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

from physavatar.body import BodyModel, builtin_motion, linear_blend_skinning
from physavatar.garment import attachment_positions, garment_skinning_weights, make_garment
from physavatar.metrics import chamfer_distance, sample_surface
from physavatar.sim import PRESETS, SimSettings
from physavatar.stages.physics.data import PhysicsData
from physavatar.stages.physics.fit_exact import fit_exact
from physavatar.stages.physics.fit_fd import fit_fd
from physavatar.stages.physics.objective import fit_residuals, rollout, trajectory_loss
from physavatar.stages.physics.parameters import SHAPE_WEIGHT, far_material
from physavatar.stages.physics.proxy import GarmentProxy, make_proxy, on_proxy
from physavatar.stages.physics.select import fit_material
from physavatar.stages.physics.stage import refit_at_equilibrium
from physavatar.sim.rest import describe, equilibrium_rest, static_equilibrium

sys.path.insert(0, str(Path(__file__).parent))
from _common import cpu_name  # noqa: E402
from foreign_cloth import ForeignCloth, ForeignSettings  # noqa: E402

RESULTS = Path(__file__).parent / "results" / "physics_recovery.json"


HELDOUT_MOTIONS = ("dance", "turn", "twist", "jump")


def scene(edge, window, heldout_frames, fps=25.0, heldout_motions=HELDOUT_MOTIONS):
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
    W = garment_skinning_weights(g.vertices, body, g.faces)
    held, lbs = {}, {}
    for motion in heldout_motions:
        held[motion], posed = data_for(motion, heldout_frames)
        lbs[motion] = linear_blend_skinning(g.vertices, W, posed.bone_transforms[:heldout_frames])
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


def fit_row(res, true, noise_floor):
    m = res.material
    return {
        "bend_ratio_rel_error": m.bend_ratio / true.bend_ratio - 1,
        "stretch_ratio_rel_error": m.stretch_ratio / true.stretch_ratio - 1,
        "bend_ratio_interval95": res.ratio_intervals.get("bend_ratio"),
        "stretch_ratio_interval95": res.ratio_intervals.get("stretch_ratio"),
        "loss_m2": res.loss, "loss_over_noise_floor": res.loss / noise_floor, "rms_mm": res.rms_mm,
        "objective_m2": res.objective, "shape_weight": res.shape_weight,
        "iterations": res.iterations, "simulations": res.simulations, "wall_time_s": res.wall_time,
        "fitted": {"stretch_stiffness": m.stretch_stiffness, "bend_stiffness": m.bend_stiffness,
                   "density_prior": m.density},
        "integrator": m.integrator,
        "bdf2_blend": m.bdf2_blend if m.integrator == "bdf2" else None,
        "model_selection": None if res.model_selection is None else {
            "chosen": res.model_selection["chosen"],
            **{f"{k}_{q}": v.get(q) for k, v in res.model_selection["fits"].items()
               for q in ("objective", "loss", "bend_ratio", "stretch_ratio", "bdf2_blend")}},
        "loss_history": [r["loss"] for r in res.history],
        "time_history_s": [r["wall_time_s"] for r in res.history],
    }


class Case:
    """One resolution pair: the ground truth is simulated on the dress at ``truth_edge``, the fits
    (and the held-out rows) on a decimated proxy of it with at most ``proxy_vertices`` vertices
    (stages/physics/proxy.py, as fit-physics does on a big garment), mapped by barycentric coordinates.
    With ``proxy_vertices`` 0 (or >= the dress's vertex count) the fit uses the dress itself."""

    def __init__(self, truth_edge, proxy_vertices, window, heldout_frames, heldout_motions=HELDOUT_MOTIONS):
        self.edge = truth_edge
        self.body, self.g, self.train, self.held, lbs = scene(truth_edge, window, heldout_frames,
                                                              heldout_motions=heldout_motions)
        n = len(self.g.vertices)
        self.identity = not 0 < proxy_vertices < n
        if not self.identity:
            self.proxy = make_proxy(self.g.vertices, self.g.faces, self.train.boundary, proxy_vertices)
        else:  # the identity "proxy"
            ids = np.arange(n)
            self.proxy = GarmentProxy(self.g.vertices, self.g.faces, self.train.boundary,
                                      np.stack([ids, ids, ids], 1), np.tile([1.0, 0.0, 0.0], (n, 1)))
        self.lbs = {k: self.proxy.map(v) for k, v in lbs.items()}
        self.faces = self.proxy.faces
        self.n_fit = len(self.proxy.vertices)

    def truth(self, material, settings, substeps, start="template"):
        """Ground truth (fine mesh) of the training window and of each held-out motion {name: [T, N, 3]}.

        ``start`` "template": from the template (the designed rest shape) at rest, which is not in
        equilibrium (the dress drops ~13 cm in its first frames); "settled": from the template's
        static equilibrium in the true material on the motion's body frame 0 (a real garment's
        first frame: its pattern hanging at rest; sim.rest.static_equilibrium, frictionless as
        every simulation here), the rest shape staying the template."""
        settled = {}

        def run(d):
            if start == "settled":
                key = d.collider[0].tobytes() + d.boundary_targets[0].tobytes()
                if key not in settled:
                    x = self.g.vertices.copy()
                    x[d.boundary] = d.boundary_targets[0]
                    settled[key], info = static_equilibrium(self.g.vertices, d.faces, material, x, d.boundary,
                                                            d.collider[0], d.collider_faces, settings, tol=1e-5)
                    sag = np.linalg.norm(settled[key] - self.g.vertices, axis=1)
                    print(f"  settled start ({material.name}): the template sags {1e3 * sag.max():.1f} mm max, "
                          f"{1e3 * np.sqrt(np.mean(sag ** 2)):.1f} mm RMS ({info['steps']} steps)", flush=True)
                d = dataclasses.replace(d, initial=settled[key])
            return rollout(d, material, settings, substeps=substeps).positions

        return run(self.train), {k: run(d) for k, d in self.held.items()}

    def foreign_truth(self, material, settings: ForeignSettings):
        """Ground truth by the independent simulator (foreign_cloth.py) on the fine dress."""
        sim = ForeignCloth(self.g.vertices, self.g.faces, self.train.boundary, material.density,
                           material.stretch_stiffness, material.bend_stiffness, settings)
        run = lambda d: sim.simulate(d.rest, d.boundary_targets, d.collider, d.collider_faces, d.fps)[0]  # noqa: E731
        return run(self.train), {k: run(d) for k, d in self.held.items()}

    def fit_data(self, gt_train):
        """What is fitted: the fine ground truth mapped onto the proxy (noise is added after); the
        rest shape is the observed (clean) frame 0, as fit-physics takes the template (for a truth
        started from the template, the template itself)."""
        return self.on_proxy(dataclasses.replace(self.train, reference=gt_train, initial=gt_train[0], rest=gt_train[0]))

    def on_proxy(self, data):
        """``data`` on what is fitted: the proxy (stages/physics/proxy.on_proxy), or unchanged for the
        identity proxy (on_proxy's push-out of the start to a few mm from the body would move a
        settled start off its equilibrium and into the body: 2.9 mm, 6 crossings, cotton)."""
        return data if self.identity else on_proxy(data, self.proxy)

    def model_rest(self, label, mat, held, cache, settings):
        """The rest shape a held-out row simulates ``held`` (on the proxy) with: the true rows the
        designed one (the template); an estimate or a random draw its model's: the observed start
        frame, or (Material.rest_shape "equilibrium") the one whose static equilibrium it is
        (sim.rest.equilibrium_rest for that material, as garment_sim.equilibrium_part does; a start
        not at rest keeps itself)."""
        if label.startswith("true"):
            return held.rest
        if mat.rest_shape != "equilibrium":
            return held.initial
        key = (label, held.initial.tobytes(), held.collider[0].tobytes())
        if key not in cache:
            X, rep = equilibrium_rest(held.initial, held.faces, mat, held.boundary, held.collider[0],
                                      held.collider_faces, settings)
            cache[key] = X if rep["at_rest"] else held.initial
            print(f"  held-out {label}: {describe(rep, 'the start frame')}" + ("" if rep["at_rest"] else
                  " (not at rest: start frame kept)"), flush=True)
        return cache[key]

    def heldout_cd(self, materials, gt_held, settings):
        """Chamfer ×10³ on each held-out motion between the fine ground truth mapped to the proxy
        and each row's proxy simulation (the same proxy surface for all, same samples).

        Returns (mean over the motions {row: CD}, per motion {motion: {row: CD}}). One contact-rich
        24-frame clip is a noisy judge: the same row moved by ~15 % between runs of the same code
        on two machines (docs/physics.md, "Eleventh session"), as much as the differences the
        checks judge; the mean over four motions is what the checks use."""
        per, cache = {}, {}
        for motion, d in self.held.items():
            held = self.on_proxy(dataclasses.replace(d, reference=gt_held[motion], initial=gt_held[motion][0]))
            gt = held.reference
            cd = {"lbs": garment_chamfer_x1e3(self.lbs[motion], gt, self.faces)}
            for label, mat in materials:
                try:  # each material in the model it was fitted in (the presets: implicit Euler)
                    s = dataclasses.replace(settings, integrator=mat.integrator)
                    h = dataclasses.replace(held, rest=self.model_rest(label, mat, held, cache, settings))
                    cd[label] = garment_chamfer_x1e3(rollout(h, mat, s).positions, gt, self.faces)
                except (FloatingPointError, RuntimeError) as e:
                    cd[label] = math.inf
                    print(f"  held-out {motion} {label} failed: {e}", flush=True)
            per[motion] = cd
        mean = {label: float(np.mean([cd[label] for cd in per.values()])) for label in next(iter(per.values()))}
        return mean, per


SETTINGS = {
    # the literal setup: ground truth by the fitting simulator itself (1 step per frame,
    # a 10x tighter Newton tolerance) + noise; the true material's held-out distance is ~0 here
    "noise": "ground truth by the fitting simulator (1 step per frame, Newton tol 1e-6) + 2 mm noise",
    # a ground truth the fitting model cannot reproduce exactly
    "model_error": "ground truth at {k} implicit steps per frame (Newton tol 1e-6) + 2 mm noise; fits 1 step per frame",
    # a ground truth from a differently built simulator: another integrator, step and membrane law
    "other_simulator": "ground truth by {oi} at {ok} steps per frame with the {om} membrane{od} (Newton tol 1e-6) "
                       "+ 2 mm noise; fits implicit Euler, 1 step per frame, StVK",
    # a ground truth from code that shares nothing with physavatar.sim (benchmarks/foreign_cloth.py)
    "foreign": "ground truth by an independent explicit mass-spring simulator (benchmarks/foreign_cloth.py: "
               "edge springs, Bridson hinge bending, mass damping {fa} 1/s, spring dashpots {fb} s, "
               "closest-point collision with friction {fm}, symplectic Euler below its stability limit) + 2 mm noise",
}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--edge", type=float, default=None, help="ground-truth dress edge length [m] (accuracy runs)")
    ap.add_argument("--proxy-vertices", type=int, default=0,
                    help="fit a proxy of at most N vertices of the ground-truth dress (0 = the dress itself)")
    ap.add_argument("--fd-edge", type=float, default=None, help="ground-truth dress edge length [m] (fd-vs-exact)")
    ap.add_argument("--fd-proxy-vertices", type=int, default=0, help="the same for the fd-vs-exact runs")
    ap.add_argument("--window", type=int, default=None, help="fitted frames")
    ap.add_argument("--heldout-frames", type=int, default=24)
    ap.add_argument("--heldout-motions", default=",".join(HELDOUT_MOTIONS),
                    help="built-in motions the estimates are judged on; the checks use the mean Chamfer over them")
    ap.add_argument("--materials", default="silk,cotton,denim")
    ap.add_argument("--settings", default="noise,model_error,other_simulator,foreign",
                    help="comma-separated: noise (the fitting simulator's own ground truth + noise: the issue's "
                         "literal setup), model_error (ground truth at --truth-substeps), other_simulator (--other-*), "
                         "foreign (the independent simulator of foreign_cloth.py, --foreign-*)")
    ap.add_argument("--fd-materials", default=None, help="comma-separated presets fitted with fd too ('' = none)")
    ap.add_argument("--fd-setting", default="noise",
                    help="the ground truth of the fd-vs-exact runs (default: the issue's literal setup)")
    ap.add_argument("--fd-iterations", type=int, default=100)
    ap.add_argument("--exact-iterations", type=int, default=12)
    ap.add_argument("--fit-integrator", choices=("auto", "euler", "bdf2"), default="auto",
                    help="the exact estimator's time integrator: auto (fit-physics' default: fit with both, keep the "
                         "lower objective; physics.fit_selecting_integrator), euler or bdf2. fd and the fd-vs-exact "
                         "comparison use implicit Euler (the paper's)")
    ap.add_argument("--truth-substeps", type=int, default=2,
                    help="implicit steps per frame of the model_error ground truth (the fits take 1)")
    ap.add_argument("--other-substeps", type=int, default=4,
                    help="steps per frame of the other_simulator ground truth")
    ap.add_argument("--other-integrator", choices=("euler", "bdf2"), default="bdf2",
                    help="time integrator of the other_simulator ground truth (the fits use implicit Euler)")
    ap.add_argument("--other-membrane", choices=("stvk", "neohookean"), default="neohookean",
                    help="membrane model of the other_simulator ground truth (the fits use StVK)")
    ap.add_argument("--other-damping", type=float, default=0.0,
                    help="mass damping alpha [1/s] of the other_simulator ground truth (the fits use none)")
    ap.add_argument("--foreign-alpha", type=float, default=ForeignSettings.alpha,
                    help="mass (air) damping [1/s] of the foreign ground truth")
    ap.add_argument("--foreign-beta", type=float, default=ForeignSettings.beta,
                    help="spring dashpot coefficient [s] of the foreign ground truth (c = beta k)")
    ap.add_argument("--foreign-friction", type=float, default=ForeignSettings.friction,
                    help="body friction of the foreign ground truth")
    ap.add_argument("--noise-mm", type=float, default=2.0)
    ap.add_argument("--random-draws", type=int, default=5,
                    help="random materials per case; the check compares with their median held-out error")
    ap.add_argument("--shape-weight", type=float, default=SHAPE_WEIGHT,
                    help="the exact estimator's local-shape residual weight (fit_residuals); the 'exact_eq6' rows and "
                         "the fd-vs-exact comparison use 0 (the paper's L_sim)")
    ap.add_argument("--no-eq6-rows", action="store_true", help="skip the exact fits on L_sim alone")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--truth-start", choices=("template", "settled"), default="template",
                    help="the ground truth's first frame: the template at rest (not in equilibrium: it drops), or "
                         "its static equilibrium in the true material (a real garment's first frame)")
    ap.add_argument("--rest-shapes", default="template",
                    help="the fits' rest-shape models: template (the observed frame 0), and with 'equilibrium' "
                         "also fit-physics --rest-shape equilibrium (refit_at_equilibrium) from the first fit")
    ap.add_argument("--out", type=Path, default=RESULTS, help="results JSON (default benchmarks/results/physics_recovery.json)")
    args = ap.parse_args()
    edge = args.edge or (0.07 if args.quick else 0.05)
    proxy_vertices = args.proxy_vertices
    fd_edge = args.fd_edge or (0.10 if args.quick else edge)
    fd_proxy_vertices = args.fd_proxy_vertices
    window = args.window or (12 if args.quick else 24)
    materials = [m for m in args.materials.split(",") if m]
    settings_run = [s for s in args.settings.split(",") if s]
    unknown = set(settings_run + [args.fd_setting]) - set(SETTINGS)
    if unknown:
        ap.error(f"unknown settings {sorted(unknown)}; choose from {sorted(SETTINGS)}")
    truth_substeps = {"noise": 1, "model_error": args.truth_substeps, "other_simulator": args.other_substeps,
                      "foreign": None}
    foreign_settings = ForeignSettings(alpha=args.foreign_alpha, beta=args.foreign_beta, friction=args.foreign_friction)
    fd_materials = [m for m in (args.fd_materials if args.fd_materials is not None
                                else args.materials).split(",") if m]
    # the ∞-norm stopping rule these tolerances were chosen with (stages.physics.parameters.fit_settings)
    fit_settings = SimSettings(friction=0.0, newton_tol=1e-5, newton_norm="max")
    truth_base = SimSettings(friction=0.0, newton_tol=1e-6, newton_norm="max")
    truth_settings = {"noise": truth_base, "model_error": truth_base,
                      "other_simulator": dataclasses.replace(truth_base, integrator=args.other_integrator,
                                                             membrane_model=args.other_membrane,
                                                             damping_mass=args.other_damping)}
    load_start = list(os.getloadavg())
    t_all = time.perf_counter()

    if args.random_draws < 1:
        ap.error("--random-draws must be at least 1")
    heldout_motions = tuple(m for m in args.heldout_motions.split(",") if m)
    if not heldout_motions or "walk" in heldout_motions:
        ap.error("--heldout-motions: one or more built-in motions other than the fitted walk")
    case = Case(edge, proxy_vertices, window, args.heldout_frames, heldout_motions)
    same = (fd_edge, fd_proxy_vertices) == (edge, proxy_vertices)
    fd_case = case if same else (Case(fd_edge, fd_proxy_vertices, window, args.heldout_frames, heldout_motions)
                                   if fd_materials else None)
    for c in {id(c): c for c in (case, fd_case) if c is not None}.values():
        print(f"ground truth: dress edge {c.edge} m, {len(c.g.vertices)} vertices, {len(c.train.boundary)} boundary; "
              f"fitted proxy: {c.n_fit} vertices ({len(c.proxy.boundary)} boundary, mean edge "
              f"{100 * c.proxy.mean_edge:.1f} cm); body {len(c.body.rest_vertices)} vertices", flush=True)
    print(f"window {window} frames (walk), held-out {args.heldout_frames} of {', '.join(heldout_motions)}; settings {settings_run}; "
          f"model_error ground truth {args.truth_substeps} substeps/frame; other_simulator {args.other_integrator} "
          f"{args.other_substeps} substeps/frame {args.other_membrane}; fits implicit Euler 1 step/frame StVK",
          flush=True)
    rows = {}
    figures = {"per_material": {s: {} for s in settings_run}, "fd_comparison": {}}

    def logger(name, method, every):
        def log(row):
            if row["iteration"] % every == 0:
                print(f"  [{name} {method}] it {row['iteration']:3d} loss {row['loss']:.5g} "
                      f"ks {row['stretch_stiffness']:.4g} kb {row['bend_stiffness']:.4g} "
                      + (f"gamma {row['bdf2_blend']:.3f} " if "bdf2_blend" in row else "")
                      + f"t {row['wall_time_s']:.0f} s", flush=True)
        return log

    def exact_fit(data, start, callback, shape_weight):  # as fit-physics does (--integrator)
        auto = args.fit_integrator == "auto"
        return fit_material(data, start, "exact", args.exact_iterations, callback=callback, shape_weight=shape_weight,
                            settings=dataclasses.replace(fit_settings, integrator="euler" if auto else args.fit_integrator),
                            select_integrator=auto)

    def prepare(c, true, mi, setting):
        t0 = time.perf_counter()
        if setting == "foreign":
            gt_train, gt_held = c.foreign_truth(true, foreign_settings)
        else:
            gt_train, gt_held = c.truth(true, truth_settings[setting], truth_substeps[setting], args.truth_start)
        print(f"[{true.name} @ {c.edge} m, {setting}] ground truth simulated in {time.perf_counter() - t0:.0f} s",
              flush=True)
        # the fit starts from the clean rest state (the template), not the noisy frame 0
        data = c.fit_data(gt_train).with_noise(args.noise_mm * 1e-3, seed=mi)
        return data, gt_held

    def material_case(c, name, mi, setting):
        """(true material, far start, fit data, held-out truth, noise-floor loss) of one material."""
        true = PRESETS[name]
        # ν is a model setting, not estimated (the paper fixes it too): the fit uses the true one
        start = dataclasses.replace(far_material(), poisson=true.poisson)
        data, gt_held = prepare(c, true, mi, setting)
        return true, start, data, gt_held, data.reference[1:].size * (args.noise_mm * 1e-3) ** 2

    rest_shapes = [r for r in args.rest_shapes.split(",") if r]
    if set(rest_shapes) - {"template", "equilibrium"} or "template" not in rest_shapes:
        ap.error("--rest-shapes: template, optionally with equilibrium")
    if args.truth_start == "settled" and "foreign" in settings_run:
        ap.error("--truth-start settled: not for the foreign setting (its simulator settles nothing)")
    c_rest = case.proxy.map(case.g.vertices)  # the true (designed) rest shape on what is fitted
    for setting in settings_run:
        rng = np.random.default_rng(0)  # the same random materials in every setting
        for mi, name in enumerate(materials):
            true, start, data, gt_held, noise_floor = material_case(case, name, mi, setting)
            res = exact_fit(data, start, callback=logger(f"{name} {setting}", "exact", 1),
                            shape_weight=args.shape_weight)
            rows[(setting, name, "exact")] = fit_row(res, true, noise_floor)
            true_x = rollout(dataclasses.replace(data, rest=c_rest), true, fit_settings).positions
            rows[(setting, name, "exact")]["true_material_loss_m2"] = trajectory_loss(true_x, data.reference)
            r_true, _ = fit_residuals(true_x, data, args.shape_weight)
            rows[(setting, name, "exact")]["true_material_objective_m2"] = float(r_true @ r_true)
            estimates = [("estimated_exact", res.material)]
            if "equilibrium" in rest_shapes:  # fit-physics --rest-shape equilibrium: from the first fit
                eq, eq_report, _ = refit_at_equilibrium(
                    data, res, dataclasses.replace(fit_settings, integrator="euler"),
                    lambda d, init: exact_fit(d, init, callback=logger(f"{name} {setting}", "exact_rest_eq", 1),
                                              shape_weight=args.shape_weight), print)
                rows[(setting, name, "exact_rest_eq")] = fit_row(eq, true, noise_floor) | {"rest_shape": {
                    k: eq_report.get(k) for k in ("used", "at_rest", "converged", "final_rms_mm", "final_max_mm",
                                                  "sag_mm", "rounds", "seconds", "refit_sag_mm")}}
                estimates.append(("estimated_exact_rest_eq", eq.material))
            if not args.no_eq6_rows and args.shape_weight > 0:
                eq6 = exact_fit(data, start, callback=logger(f"{name} {setting}", "exact_eq6", 1), shape_weight=0.0)
                rows[(setting, name, "exact_eq6")] = fit_row(eq6, true, noise_floor)
                estimates.append(("estimated_exact_eq6", eq6.material))
            if name in fd_materials and fd_case is case and setting == args.fd_setting:
                fd_res = fit_fd(data, start, fit_settings, iterations=args.fd_iterations, workers=args.workers,
                                callback=logger(name, "fd", 10))
                rows[(setting, name, "fd")] = fit_row(fd_res, true, noise_floor)
                estimates.append(("estimated_fd", fd_res.material))
            # Table 2 on the held-out motion; "true" = the true material in the fitting model.
            # "random": one draw as before (the same sequence of draws); "random_median": the median
            # over --random-draws draws (one lucky draw can land near the truth: foreign denim's
            # first, κs/ρ −32 %, κb/ρ +6 %, predicted that motion better than the true material)
            rnd = random_material(rng, start.density)
            extra_rng = np.random.default_rng(1000 + mi)  # the same extra draws in every setting too
            rnds = [("random", rnd)] + [(f"random_{k + 2}", random_material(extra_rng, start.density))
                                        for k in range(args.random_draws - 1)]
            # "true": the true material as the simulator runs a preset (implicit Euler); where an
            # estimate was fitted in BDF2, the true material in BDF2 too (the check takes the better)
            trues = [("true", true)] + ([("true_bdf2", dataclasses.replace(true, integrator="bdf2"))]
                                        if any(m.integrator == "bdf2" for _, m in estimates) else [])
            cd, cd_per = case.heldout_cd(rnds + estimates + trues, gt_held, fit_settings)
            for c in [cd] + list(cd_per.values()):
                c["random_median"] = float(np.median([c[k] for k, _ in rnds]))
            figures["per_material"][setting][name] = {
                "true": {"stretch_ratio": true.stretch_ratio, "bend_ratio": true.bend_ratio},
                "random_material": {"stretch_stiffness": rnd.stretch_stiffness, "bend_stiffness": rnd.bend_stiffness},
                "random_materials": {k: {"stretch_stiffness": m.stretch_stiffness, "bend_stiffness": m.bend_stiffness,
                                         "stretch_ratio_rel_error": m.stretch_ratio / true.stretch_ratio - 1,
                                         "bend_ratio_rel_error": m.bend_ratio / true.bend_ratio - 1}
                                     for k, m in rnds},
                "noise_floor_loss_m2": noise_floor,
                "heldout_chamfer_x1e3": cd,
                "heldout_chamfer_x1e3_per_motion": cd_per,
                "estimators": {k: rows[(setting, name, k)] for k in ("exact", "exact_rest_eq", "exact_eq6", "fd")
                               if (setting, name, k) in rows},
            }
            for motion, c in cd_per.items():
                print(f"[{name} {setting}] held-out {motion} CD×1e3: " + ", ".join(f"{k} {v:.4f}" for k, v in c.items()),
                      flush=True)
            print(f"[{name} {setting}] held-out mean CD×1e3: " + ", ".join(f"{k} {v:.4f}" for k, v in cd.items()),
                  flush=True)

    if fd_case is not None and fd_case is not case:
        setting = args.fd_setting
        for mi, name in enumerate(fd_materials):
            true, start, data, gt_held, noise_floor = material_case(fd_case, name, mi, setting)
            ex = fit_exact(data, start, fit_settings, iterations=args.exact_iterations,
                           callback=logger(name, "exact@fd-edge", 1))
            fd = fit_fd(data, start, fit_settings, iterations=args.fd_iterations, workers=args.workers,
                        callback=logger(name, "fd", 10))
            rows[(setting, name, "exact@fd_edge")] = fit_row(ex, true, noise_floor)
            rows[(setting, name, "fd")] = fit_row(fd, true, noise_floor)
            rnd = random_material(np.random.default_rng(100 + mi), start.density)
            cd, cd_per = fd_case.heldout_cd([("random", rnd), ("estimated_exact", ex.material),
                                             ("estimated_fd", fd.material), ("true", true)], gt_held, fit_settings)
            figures["fd_comparison"][name] = {
                "setting": setting, "edge_length_m": fd_edge, "garment_vertices": len(fd_case.g.vertices),
                "fitted_vertices": fd_case.n_fit, "noise_floor_loss_m2": noise_floor, "heldout_chamfer_x1e3": cd,
                "heldout_chamfer_x1e3_per_motion": cd_per,
                "estimators": {"exact": rows[(setting, name, "exact@fd_edge")], "fd": rows[(setting, name, "fd")]},
            }
            print(f"[{name} @ {fd_edge} m] held-out CD×1e3: " + ", ".join(f"{k} {v:.4f}" for k, v in cd.items()),
                  flush=True)
    for setting, per in figures["per_material"].items():
        for name, fig in per.items():
            if "fd" in fig["estimators"]:
                ex = fig["estimators"].get("exact_eq6", fig["estimators"]["exact"])
                figures["fd_comparison"][name] = {"setting": setting, "edge_length_m": edge,
                                                  "garment_vertices": len(case.g.vertices), "fitted_vertices": case.n_fit,
                                                  "heldout_chamfer_x1e3": fig["heldout_chamfer_x1e3"],
                                                  "estimators": {"exact": ex, "fd": fig["estimators"]["fd"]}}

    # checks: the targets. κb/ρ within 10 %: in the literal setup ("noise": ground
    # truth meshes + 2 mm noise). Held-out Chamfer within 10 % of the true material's: only with
    # model error (without it the true material's distance is the Newton tolerance's, ~0); below
    # LBS and random: every setting. The exact estimator reaching fd's loss in a third of fd's time.
    # reported: the same κb/ρ figure under model error, and the paper's estimator's κb/ρ. Under model
    # error the true material is not the fitting model's best one (other_simulator: the estimate
    # predicts the held-out motion better than the true material does), so κb/ρ's distance from
    # the truth there measures the model gap, not the estimator; it is reported against the same
    # 10 % for comparison, not counted as a check.
    checks, reported = {}, {}
    for setting, per in figures["per_material"].items():
        for name, fig in per.items():
            r = fig["estimators"]["exact"]
            (checks if setting == "noise" else reported)[f"{setting}:{name}_exact_bend_ratio_within_10pct"] = {
                "value": abs(r["bend_ratio_rel_error"]), "target": "<= 0.10", "unit": "relative error",
                "setting": setting, "pass": abs(r["bend_ratio_rel_error"]) <= 0.10}
            cd = fig["heldout_chamfer_x1e3"]
            est = cd.get("estimated_exact", math.inf)
            if setting != "noise":
                true_cd = min(cd["true"], cd.get("true_bdf2", math.inf))  # the better of the two models
                checks[f"{setting}:{name}_heldout_cd_estimated_within_10pct_of_true"] = {
                    "value": est / true_cd if true_cd > 0 else math.inf,
                    "target": "<= 1.10 (true: the better of implicit Euler and, if an estimate chose it, BDF2)",
                    "unit": "CD ratio", "setting": setting, "pass": est <= 1.10 * true_cd}
            rnd_cd = cd["random_median"]
            checks[f"{setting}:{name}_heldout_cd_estimated_below_lbs_and_random"] = {
                "value": est, "target": f"< min(lbs {cd['lbs']:.4g}, random {rnd_cd:.4g}: the median over "
                                        f"{args.random_draws} draws; the first draw alone {cd['random']:.4g})",
                "unit": "CD x1e3", "setting": setting, "pass": est < min(cd["lbs"], rnd_cd)}
            if "estimated_exact_rest_eq" in cd:  # the rest shape from static equilibrium (session 28)
                eq = cd["estimated_exact_rest_eq"]
                checks[f"{setting}:{name}_heldout_cd_rest_eq_holds_against_template"] = {
                    "value": eq / est if est > 0 else math.inf,
                    "target": "<= 1.10 (the estimate with --rest-shape equilibrium / with the template)",
                    "unit": "CD ratio", "setting": setting, "pass": eq <= 1.10 * est}
                checks[f"{setting}:{name}_heldout_cd_rest_eq_below_lbs_and_random"] = {
                    "value": eq, "target": f"< min(lbs {cd['lbs']:.4g}, random {rnd_cd:.4g} (template rest))",
                    "unit": "CD x1e3", "setting": setting, "pass": eq < min(cd["lbs"], rnd_cd)}
                r_eq = fig["estimators"]["exact_rest_eq"]
                reported[f"{setting}:{name}_rest_eq_bend_ratio_error"] = {
                    "value": abs(r_eq["bend_ratio_rel_error"]), "template_value": abs(r["bend_ratio_rel_error"]),
                    "target": "<= 0.10", "unit": "relative error", "setting": setting,
                    "pass": abs(r_eq["bend_ratio_rel_error"]) <= 0.10}
    for name, fig in figures["fd_comparison"].items():
        fd, ex = fig["estimators"]["fd"], fig["estimators"]["exact"]
        setting = fig["setting"]
        reported[f"{setting}:{name}_fd_bend_ratio_within_10pct"] = {
            "value": abs(fd["bend_ratio_rel_error"]), "target": "<= 0.10 (the paper's estimator; edge "
            f"{fig['edge_length_m']} m)", "unit": "relative error", "setting": setting,
            "pass": abs(fd["bend_ratio_rel_error"]) <= 0.10}
        target = fd["loss_m2"] * 1.01
        t_exact = time_to_reach([{"loss": l, "wall_time_s": t} for l, t in
                                 zip(ex["loss_history"], ex["time_history_s"])], target)
        checks[f"{setting}:{name}_exact_reaches_fd_loss_in_third_of_fd_time"] = {
            "value": t_exact / fd["wall_time_s"],
            "target": f"<= 0.333 (exact time to reach 1.01 x fd final loss / fd time; edge {fig['edge_length_m']} m, "
                      f"fd {fd['iterations']} iterations)",
            "unit": "time ratio", "setting": setting, "pass": t_exact <= fd["wall_time_s"] / 3}
    figures["total_wall_time_s"] = time.perf_counter() - t_all

    result = {
        "benchmark": "physics_recovery",
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "machine": {"cores": os.cpu_count(), "cpu": cpu_name(), "gpu": None,
                    "load_average_1_5_15min_start": load_start, "load_average_1_5_15min_end": list(os.getloadavg())},
        "config": {
            "command": "python " + " ".join([Path(sys.argv[0]).as_posix()] + sys.argv[1:]),
            "quick": args.quick, "garment": "dress", "edge_length_m": edge, "garment_vertices": len(case.g.vertices),
            "fitted_proxy_vertices": case.n_fit, "proxy_max_vertices": proxy_vertices,
            "fd_edge_length_m": fd_edge,
            "fd_garment_vertices": len(fd_case.g.vertices) if fd_case is not None else None,
            "fd_fitted_proxy_vertices": fd_case.n_fit if fd_case is not None else None,
            "body": "Anny collider topology", "train_motion": "walk", "window_frames": window,
            "heldout_motions": list(heldout_motions), "heldout_frames": args.heldout_frames, "fps": 25.0,
            "heldout_judged_by": "mean over the held-out motions of the garment Chamfer distance",
            "noise_mm": args.noise_mm, "initial": far_material().to_dict(), "materials": materials,
            "settings": {s: SETTINGS[s].format(
                k=args.truth_substeps, ok=args.other_substeps, oi=args.other_integrator, om=args.other_membrane,
                od=f", mass damping {args.other_damping} 1/s" if args.other_damping else "",
                fa=args.foreign_alpha, fb=args.foreign_beta, fm=args.foreign_friction) for s in settings_run},
            "fd_materials": fd_materials, "fd_setting": args.fd_setting,
            "fd_iterations": args.fd_iterations, "exact_max_iterations": args.exact_iterations,
            "workers": args.workers, "fit_settings": {"friction": 0.0, "newton_tol": 1e-5, "dt": 0.04, "substeps": 1,
                                                     "integrator": args.fit_integrator},
            "shape_weight": {"exact": args.shape_weight, "exact_eq6": 0.0, "fd": 0.0, "exact@fd_edge": 0.0},
            "truth_settings": {s: {"friction": 0.0, "newton_tol": 1e-6, "dt": 0.04 / truth_substeps[s],
                                   "substeps": truth_substeps[s], "integrator": truth_settings[s].integrator,
                                   "membrane_model": truth_settings[s].membrane_model,
                                   "damping_mass": truth_settings[s].damping_mass}
                               if s != "foreign" else {"simulator": "benchmarks/foreign_cloth.py",
                                                       **dataclasses.asdict(foreign_settings)}
                               for s in settings_run},
            "model_error": (f"model_error: ground truth simulated with {args.truth_substeps} implicit steps per frame "
                            "and a 10x tighter Newton tolerance (1e-6 m/s); the fits and the held-out rows (the "
                            "'true' row too) take 1 step per frame at 1e-5 m/s"
                            + (f", on a proxy of at most {proxy_vertices} vertices of the ground-truth dress "
                               "(stages/physics/proxy.py) that the fine motion is mapped onto" if proxy_vertices else
                               ", on the same mesh") + "; plus the noise on the reference"),
            "poisson": "the true preset's (a setting, not estimated)", "fit_start_state": "clean frame 0 (the truth's start)",
            "truth_start": args.truth_start, "rest_shapes": rest_shapes,
            "rest_models": "held-out rows: estimates and random draws with their model's rest shape (template: the "
                           "observed start frame; equilibrium: solved for the material on it); the true rows with the "
                           "designed rest (the template); random draws in the template model",
            "chamfer": "mean over held-out frames of CD between 20000-point surface samples (same seed for both), x1e3 m^2",
        },
        "figures": figures,
        "checks": checks,
        "reported": reported,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_name(args.out.name + ".tmp")
    tmp.write_text(json.dumps(result, indent=2, default=float) + "\n")
    tmp.replace(args.out)

    print(f"\n{'setting':16s} {'material':8s} {'method':14s} {'model':6s} {'kb/rho err':>10s} {'ks/rho err':>10s} "
          f"{'loss/floor':>10s} {'sims':>5s} {'time s':>7s}")
    for (setting, name, method), r in rows.items():
        print(f"{setting:16s} {name:8s} {method:14s} {r['integrator']:6s} {r['bend_ratio_rel_error']:+10.3f} "
              f"{r['stretch_ratio_rel_error']:+10.3f} {r['loss_over_noise_floor']:10.3f} {r['simulations']:5d} "
              f"{r['wall_time_s']:7.0f}")
    print(f"\nheld-out Chamfer x1e3, mean over {', '.join(heldout_motions)} (and each motion):")
    for setting, per in figures["per_material"].items():
        for name, fig in per.items():
            print(f"  {setting:16s} {name:8s} " + "  ".join(f"{k} {v:.4g}" for k, v in fig["heldout_chamfer_x1e3"].items()))
            for motion, c in fig["heldout_chamfer_x1e3_per_motion"].items():
                print(f"  {'':16s} {'':8s}   {motion:6s} " + "  ".join(f"{k} {v:.4g}" for k, v in c.items()))
    for name, fig in figures["fd_comparison"].items():
        print(f"  {fig['setting']:12s} {name:8s} @ {fig['edge_length_m']} m " + "  ".join(
            f"{k} {v:.4g}" for k, v in fig["heldout_chamfer_x1e3"].items()))
    print("\nchecks (the issue's targets):")
    for k, c in checks.items():
        print(f"  {'PASS' if c['pass'] else 'FAIL'} {k}: {c['value']:.4g} (target {c['target']})")
    print("reported (model error's κb/ρ and the paper's estimator, against the same 10 %; not targets):")
    for k, c in reported.items():
        print(f"  {'within' if c['pass'] else 'outside'} {k}: {c['value']:.4g} ({c['target']})")
    print(f"wrote {args.out} ({figures['total_wall_time_s']:.0f} s)")


if __name__ == "__main__":
    main()
