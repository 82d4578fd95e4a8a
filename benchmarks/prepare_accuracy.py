"""``physavatar prepare`` round trip on synthetic captures (issue 23).

    python benchmarks/prepare_accuracy.py [--presets tiny,demo] [--demo PATH] [--work DIR] [--keep]
        [--given-body | --body-npz FILE] [--run [--full] [--original-run DIR]] [--resume] [--cases no_template,no_template_no_masks] [--pose2sim DIR]

For each synthetic capture (the tiny preset is built with ``physavatar synth``; the demo one is
taken from ``--demo`` or built when missing), two cases are prepared from a copy of the capture
(hard links): ``template`` removed (and ``body.npz`` too once the body fitting is installed), and
the same with the ``masks`` removed as well. Measured against the capture's truth:

* mask IoU per camera and frame (masks-removed case), against the rendered alpha > 0.5;
* first-frame mesh: mean distance of the reconstructed surface's vertices to the true
  template surface, target <= 5 mm (and the other way, which includes the body under the
  garment that no camera sees; and the prepared template's garment vertices to the true surface);
* segmentation: per-vertex accuracy of the reconstructed mesh's labels (body / garment) against
  the label of the nearest true surface point, target >= 97 %;
* boundary: mean distance of the chosen boundary vertices to the true ones, target <= 2 cm
  (and the true ones' distance to the chosen: coverage);
* the Anny body's vertex error per frame when it was fitted (target <= 15 mm mean);
* with ``--run``: ``physavatar run --quick`` on the original capture and on the prepared one
  (template removed, body fitted, masks given): tracking error (garment vertices, mm) within
  1.5x and the held-out garment Chamfer of the estimated material within 1.25x of the
  original's (both measured against each capture's own ground truth: the prepared capture's
  ``ground_truth/meshes.npz`` is re-expressed on its template).

* with ``--pose2sim DIR``: ``physavatar import`` + ``prepare`` of the real Pose2Sim clip: the
  share of the fitted body's vertices that project into each camera's mask (target >= 0.95),
  the fit's own report (keypoints in px, the share at the fit's working resolution), seconds.

Writes benchmarks/results/prepare_accuracy.json with a ``checks`` dict.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from physavatar.capture import load_capture
from physavatar.files import load_npz
from physavatar.stages.base import to_dict
from physavatar.stages.prepare import PrepareConfig
from physavatar.stages.prepare import run as prepare
from physavatar.stages.prepare.boundary import boundary_error
from physavatar.stages.prepare.masks import mask_iou
from physavatar.stages.prepare.mesh import surface_distance
from physavatar.stages.prepare.segment import transfer_labels

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _common import cpu_name


def unprepared_copy(src: Path, dst: Path, masks: bool, body: bool) -> Path:
    """A copy of capture ``src`` (hard links) without template/ (and masks/, body.npz when asked)."""
    skip = {"template"} | (set() if masks else {"masks"}) | (set() if body else {"body.npz"})
    dst.mkdir(parents=True)
    for p in src.iterdir():
        if p.name in skip:
            continue
        if p.is_dir():
            shutil.copytree(p, dst / p.name, copy_function=os.link)
        else:
            os.link(p, dst / p.name)
    return dst


def evaluate(original: Path, prepared: Path, masks_computed: bool) -> dict:
    """The numbers of one prepared capture against the original's truth."""
    truth = load_capture(original)
    prep = load_capture(prepared)
    tpl = truth.template
    out: dict = {}
    if masks_computed:
        ious = [mask_iou(prep.mask(c.name, f), truth.mask(c.name, f)) for c in truth.cameras for f in truth.frames]
        out["mask_iou"] = {"mean": float(np.mean(ious)), "min": float(np.min(ious))}
    z = load_npz(prepared / "prepare" / "first_frame_mesh.npz")
    V, F, lab = z["vertices"], z["faces"], z["labels"]
    d = surface_distance(V, tpl.vertices, tpl.faces)
    d_back = surface_distance(tpl.vertices, V, F)
    out["mesh"] = {"vertices": len(V), "to_true_mean_mm": float(d.mean() * 1000),
                   "to_true_median_mm": float(np.median(d) * 1000), "to_true_p90_mm": float(np.percentile(d, 90) * 1000),
                   "true_to_mesh_mean_mm": float(d_back.mean() * 1000)}
    true = transfer_labels(V, tpl.vertices, tpl.faces, tpl.labels)
    out["segmentation"] = {"accuracy": float(((lab > 0) == (true > 0)).mean()),
                           "garment_as_body": int(((lab == 0) & (true > 0)).sum()),
                           "body_as_garment": int(((lab > 0) & (true == 0)).sum())}
    pt = prep.template
    g = pt.labels > 0
    dg = surface_distance(pt.vertices[g], tpl.vertices, tpl.faces)
    out["mesh"]["template_garment_to_true_mean_mm"] = float(dg.mean() * 1000)
    out["mesh"]["template_garment_to_true_median_mm"] = float(np.median(dg) * 1000)
    out["boundary"] = boundary_error(pt.vertices[pt.boundary], tpl.vertices[tpl.boundary]) | {
        "chosen": int(pt.boundary.sum()), "true": int(tpl.boundary.sum())}
    out["template"] = {"vertices": len(pt.vertices), "garment_vertices": int(pt.garment_mask.sum())}
    rep = json.loads((prepared / "prepare.json").read_text())
    out["clear"] = rep["numbers"].get("clear")  # the 'clear' step's own report (session 30)
    out["collider_crossings_frame0"] = collider_crossings(prep)
    out["seconds"] = rep["seconds"]
    out["steps"] = rep["steps"]
    if rep["steps"].get("body", "").startswith("fitted"):
        from physavatar.stages.prepare.posing import pose_body

        _, Vt = pose_body(truth.body)
        _, Vp = pose_body(prep.body)
        if Vt.shape == Vp.shape:
            e = np.linalg.norm(Vt - Vp, axis=-1).mean(1) * 1000
            out["body"] = {"mean_mm_per_frame": e.tolist(), "mean_mm": float(e.mean()), "max_frame_mm": float(e.max())}
    return out


def collider_crossings(cap) -> int:
    """ipctk's crossing pairs between a capture's template garment and its body's collider in the
    first frame's pose: what ``reference-sims``, ``animate`` and ``fit-physics`` start from."""
    from physavatar.geometry import count_intersections, submesh
    from physavatar.stages.prepare.posing import pose_body

    t = cap.template
    model, posed = pose_body(cap.body, [0], topology="collider")
    ids, faces = submesh(t.faces, t.labels > 0)
    return int(count_intersections(t.vertices[ids], faces, posed[0], model.faces))


def run_pipeline(capture: Path, out: Path, quick: bool = True, eval_frames: int | None = None,
                 random_draws: int | None = None) -> dict:
    """``physavatar run [--quick] [--eval-frames N]`` (a subprocess, resumed when ``out`` exists);
    the numbers compared."""
    import subprocess

    t = time.time()
    env = dict(os.environ, PYTHONPATH=str(HERE.parent / "src"))
    proc = subprocess.run([sys.executable, "-m", "physavatar", "run", str(capture), str(out)]
                          + (["--quick"] if quick else [])
                          + (["--eval-frames", str(eval_frames)] if eval_frames else [])
                          + (["--random-draws", str(random_draws)] if random_draws else []),
                          env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, check=False)
    info = {"wall_seconds": time.time() - t, "run": str(out), "quick": quick, "eval_frames": eval_frames,
            "random_draws": random_draws}
    if proc.returncode == 0:
        return run_numbers(out) | info
    # a stage failed: its one-line error, and the tracking error when the tracking finished
    sys.stderr.write(proc.stderr[-2000:])
    errors = [ln for ln in proc.stderr.splitlines() if ln.startswith("error:")]
    info["failed"] = errors[-1] if errors else f"exit status {proc.returncode}"
    if (out / "track" / "meshes").is_dir():
        from physavatar.stages.evaluate import _tracking

        tr = _tracking(load_capture(capture), out / "track")
        info |= {"tracking_garment_mm": tr["garment"]["mean_mm"], "tracking_body_mm": tr["body"]["mean_mm"],
                 "tracking_from": "track/ (evaluate did not run)"}
    return info


def run_numbers(out: Path) -> dict:
    """The numbers compared, from a run folder's evaluate/metrics.json."""
    m = json.loads((out / "evaluate" / "metrics.json").read_text())
    return {"tracking_garment_mm": m["tracking"]["garment"]["mean_mm"],
            "tracking_body_mm": m["tracking"]["body"]["mean_mm"],
            "heldout_garment_chamfer_x1e3": m["rows"]["estimated material"]["garment"]["chamfer_x1e3"],
            "heldout_garment_fscore_1cm": m["rows"]["estimated material"]["garment"]["fscore@1cm"],
            "material": {k: v for k, v in m.items() if "material" in k and k != "rows"}}


def compare_runs(preset: str, original: Path, prepared: Path, work: Path, results: dict, checks: dict,
                 quick: bool = True, original_run: Path | None = None, eval_frames: int | None = None,
                 prepared_first: bool = False, random_draws: int | None = None) -> None:
    """Run both captures (or take the original's numbers from ``original_run``, a run folder of the
    same settings) and check the prepared one's numbers against the original's."""
    if prepared_first:  # the run that may fail first (its stage's line is the news)
        b = run_pipeline(prepared, work / "runs" / preset / "prepared", quick, eval_frames, random_draws)
    if original_run is not None:
        cfg = json.loads((original_run / "run.json").read_text()).get("_config", {})
        if bool(cfg.get("quick")) != quick:
            raise SystemExit(f"{original_run}: run with quick={cfg.get('quick')}, not comparable with quick={quick}")
        a = run_numbers(original_run) | {"run": str(original_run), "quick": quick}
    else:
        a = run_pipeline(original, work / "runs" / preset / "original", quick, eval_frames, random_draws)
    if not prepared_first:
        b = run_pipeline(prepared, work / "runs" / preset / "prepared", quick, eval_frames, random_draws)
    def ratio(key):  # None where the prepared run did not measure it (a stage failed)
        return b[key] / a[key] if key in b else None

    ratio_t, ratio_c = ratio("tracking_garment_mm"), ratio("heldout_garment_chamfer_x1e3")
    results[f"{preset}/run"] = {"original": a, "prepared": b, "tracking_ratio": ratio_t, "chamfer_ratio": ratio_c}
    print(f"{preset}/run", json.dumps(results[f"{preset}/run"], default=float))
    checks[f"{preset}/run/tracking_ratio"] = {"value": ratio_t, "target": "<= 1.5", "unit": "prepared / original",
                                              "pass": ratio_t is not None and ratio_t <= 1.5}
    checks[f"{preset}/run/heldout_chamfer_ratio"] = {
        "value": ratio_c, "target": "<= 1.25", "pass": ratio_c is not None and ratio_c <= 1.25,
        "unit": "prepared / original" + (f" (not measured: {b['failed']})" if "failed" in b else "")}


def body_in_masks(prepared: Path) -> dict:
    """Share of the prepared body's vertices that project into each camera's mask at the images'
    own resolution (nearest pixel), every frame; and how far the others are outside (px)."""
    import cv2

    from physavatar.stages.prepare.posing import pose_body

    cap = load_capture(prepared)
    _, V = pose_body(cap.body)
    per_cam, dist = {}, []
    for c in cap.cameras:
        shares = []
        for t, f in enumerate(cap.frames):
            m = (cap.mask(c.name, f) > 0.5).astype(np.uint8)
            dt = cv2.distanceTransform(1 - m, cv2.DIST_L2, 5)
            uv, z = c.project(V[t])
            x = np.clip(np.round(uv[:, 0]).astype(int), 0, c.width - 1)
            y = np.clip(np.round(uv[:, 1]).astype(int), 0, c.height - 1)
            d = dt[y, x]
            shares.append(float((d == 0).mean()))
            dist.append(d)
        per_cam[c.name] = float(np.mean(shares))
    d = np.concatenate(dist)
    return {"mean": float(np.mean(list(per_cam.values()))), "per_camera": per_cam,
            "within_2px": float((d <= 2).mean()), "outside_median_px": float(np.median(d[d > 0])) if (d > 0).any() else 0.0}


def pose2sim_case(src: Path, work: Path, prepared: Path | None, results: dict, checks: dict) -> None:
    """``physavatar import`` (every 5th frame, half size) + ``prepare`` on the real Pose2Sim clip
    (or the evaluation alone of ``prepared``): the fitted body against the masks and keypoints."""
    import subprocess

    env = dict(os.environ, PYTHONPATH=str(HERE.parent / "src"))
    t = time.time()
    if prepared is None:
        cap, prepared = work / "pose2sim" / "capture", work / "pose2sim" / "prepared"
        shutil.rmtree(work / "pose2sim", ignore_errors=True)
        subprocess.run([sys.executable, "-m", "physavatar", "import", str(src), str(cap), "--every", "5",
                        "--resolution", "0.5"], check=True, env=env, stdout=subprocess.DEVNULL)
        subprocess.run([sys.executable, "-m", "physavatar", "prepare", str(cap), str(prepared)], check=True, env=env,
                       stdout=subprocess.DEVNULL)
    rep = json.loads((prepared / "prepare.json").read_text())
    body = rep["numbers"].get("body", {})
    r = {"steps": rep["steps"], "seconds": rep["seconds"], "frames": len(load_capture(prepared).frames),
         "fit_report": {k: body.get(k) for k in ("inside_masks", "keypoints_px", "detector", "shape", "jitter")},
         "body_in_masks_native": body_in_masks(prepared), "wall_seconds": time.time() - t}
    r["frames_per_second"] = r["frames"] / max(rep["seconds"].get("total", sum(rep["seconds"].values())), 1e-9)
    results["pose2sim"] = r
    print("pose2sim", json.dumps({k: v for k, v in r.items() if k != "steps"}, default=float))
    share = r["body_in_masks_native"]
    checks["pose2sim/body_in_masks"] = {"value": min(share["per_camera"].values()), "target": ">= 0.95",
                                        "unit": "share of the body's vertices in the mask, worst camera",
                                        "pass": bool(min(share["per_camera"].values()) >= 0.95)}
    worst = (r["fit_report"].get("keypoints_px") or {}).get("worst_keypoint")
    if worst:  # a limb lost inside another's silhouette is counted inside the masks: it shows here
        checks["pose2sim/worst_keypoint_px"] = {"value": worst["median_px"], "target": "reported",
                                                "unit": f"median px of the worst keypoint (MediaPipe {worst['mediapipe_index']})",
                                                "pass": True}


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--presets", default="tiny,demo")
    ap.add_argument("--demo", type=Path, default=HERE.parent / "demo_out" / "capture",
                    help="an existing demo capture (built with physavatar synth when missing)")
    ap.add_argument("--work", type=Path, default=None)
    ap.add_argument("--keep", action="store_true")
    ap.add_argument("--given-body", action="store_true",
                    help="keep the capture's body.npz (skip the body fit: the other steps alone, in minutes)")
    ap.add_argument("--body-npz", type=Path, default=None,
                    help="give this body.npz (a body fitted before) instead of the capture's true one: the steps "
                         "after the body fit with a fitted body, without refitting it (implies --given-body)")
    ap.add_argument("--run", action="store_true",
                    help="also `physavatar run --quick` the original and the prepared capture (no_template case) and compare")
    ap.add_argument("--full", action="store_true", help="with --run: full budgets (no --quick), as `make demo` runs")
    ap.add_argument("--original-run", type=Path, default=None,
                    help="with --run: the original capture's existing run folder (same budgets) instead of running it")
    ap.add_argument("--resume", action="store_true",
                    help="with --work: keep a capture already prepared there, and resume its run (tracking resumes per frame)")
    ap.add_argument("--frames", type=int, default=None,
                    help="the demo preset: its first N frames only (an excerpt in --work, hard links; body.npz and "
                         "the ground truth cut to them, as benchmarks/prepare_tracking.py cuts them)")
    ap.add_argument("--eval-frames", type=int, default=None,
                    help="with --run: `run --eval-frames N` (the first N held-out frames) for both captures")
    ap.add_argument("--random-draws", type=int, default=None,
                    help="with --run: `run --random-draws N` (the random-material reference row's draws) for both")
    ap.add_argument("--prepared-first", action="store_true",
                    help="with --run: run the prepared capture before the original one")
    ap.add_argument("--cases", default="no_template,no_template_no_masks")
    ap.add_argument("--pose2sim", type=Path, default=None,
                    help="also import + prepare the real Pose2Sim clip at this path (../shared/data/pose2sim); "
                         "with --presets none, only it")
    ap.add_argument("--pose2sim-prepared", type=Path, default=None,
                    help="evaluate this already prepared Pose2Sim capture instead of preparing it")
    ap.add_argument("--results", type=Path, default=HERE / "results" / "prepare_accuracy.json")
    args = ap.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="prepare_bench_"))
    work.mkdir(parents=True, exist_ok=True)
    load_start = os.getloadavg()
    fit = not (args.given_body or args.body_npz is not None)
    results, checks = {}, {}
    for preset in [p for p in args.presets.split(",") if p and p != "none"]:
        cap = args.demo if preset == "demo" else work / preset
        if preset == "demo" and args.frames:
            from prepare_tracking import excerpt

            if not (work / "excerpt" / "capture.json").is_file():
                shutil.rmtree(work / "excerpt", ignore_errors=True)
                excerpt(args.demo, work / "excerpt", args.frames)
            cap = work / "excerpt"
        if not (cap / "capture.json").is_file():
            from physavatar.synth import PRESETS, synthesize

            cap = work / preset
            if not (cap / "capture.json").is_file():
                synthesize(cap, PRESETS[preset], progress=False)
        for case, keep_masks in (("no_template", True), ("no_template_no_masks", False)):
            if case not in args.cases.split(","):
                continue
            name = f"{preset}/{case}"
            src = work / "inputs" / preset / case
            dst = work / "prepared" / preset / case
            t = time.time()
            if not (args.resume and (dst / "prepare.json").is_file()):
                shutil.rmtree(src, ignore_errors=True)
                shutil.rmtree(dst, ignore_errors=True)
                unprepared_copy(cap, src, masks=keep_masks, body=not fit)
                if args.body_npz is not None:
                    (src / "body.npz").unlink()
                    shutil.copy(args.body_npz, src / "body.npz")
                prepare(src, out=dst, config=PrepareConfig(), progress=False)
            r = evaluate(cap, dst, masks_computed=not keep_masks)
            r["wall_seconds"] = time.time() - t
            results[name] = r
            print(name, json.dumps({k: v for k, v in r.items() if k not in ("steps", "seconds")}, default=float))
            checks[f"{name}/segmentation_accuracy"] = {
                "value": r["segmentation"]["accuracy"], "target": ">= 0.97", "unit": "share of vertices",
                "pass": bool(r["segmentation"]["accuracy"] >= 0.97)}
            checks[f"{name}/boundary_mean_m"] = {
                "value": r["boundary"]["chosen_to_true_mean"], "target": "<= 0.02", "unit": "m (chosen to true)",
                "pass": bool(r["boundary"]["chosen_to_true_mean"] <= 0.02)}
            checks[f"{name}/collider_crossings_frame0"] = {
                "value": r["collider_crossings_frame0"], "target": "0", "pass": r["collider_crossings_frame0"] == 0,
                "unit": "ipctk crossing pairs, template garment vs the body's collider, first frame"}
            checks[f"{name}/mesh_mean_mm"] = {
                "value": r["mesh"]["to_true_mean_mm"], "target": "<= 5", "unit": "mm (mesh to true surface)",
                "pass": bool(r["mesh"]["to_true_mean_mm"] <= 5)}
            if "mask_iou" in r:
                checks[f"{name}/mask_iou"] = {"value": r["mask_iou"]["mean"], "target": "reported", "unit": "IoU",
                                              "pass": True}
            if "body" in r:
                checks[f"{name}/body_mean_mm"] = {"value": r["body"]["mean_mm"], "target": "<= 15", "unit": "mm",
                                                  "pass": bool(r["body"]["mean_mm"] <= 15)}
            if args.run and case == "no_template":
                compare_runs(preset, cap, dst, work, results, checks, quick=not args.full, original_run=args.original_run,
                             eval_frames=args.eval_frames, prepared_first=args.prepared_first,
                             random_draws=args.random_draws)
    if args.pose2sim is not None or args.pose2sim_prepared is not None:
        pose2sim_case(args.pose2sim, work, args.pose2sim_prepared, results, checks)
    result = {"benchmark": "prepare_accuracy", "date": datetime.datetime.now().isoformat(timespec="seconds"),
              "machine": {"cores": os.cpu_count(), "cpu": cpu_name(), "gpu": None,
                          "load_average_start": list(load_start), "load_average_end": list(os.getloadavg())},
              "config": to_dict(PrepareConfig()), "body_fit": fit, "frames": args.frames, "eval_frames": args.eval_frames,
              "random_draws": args.random_draws,
              "body_given": str(args.body_npz) if args.body_npz is not None else ("true" if not fit else None), "cases": results, "checks": checks}
    for k, c in checks.items():
        v = "not measured" if c["value"] is None else f"{c['value']:.4f}"
        print(f"{k:48s} {v} (target {c['target']}) {'PASS' if c['pass'] else 'FAIL'}")
    args.results.parent.mkdir(parents=True, exist_ok=True)
    args.results.write_text(json.dumps(result, indent=2, default=float) + "\n")
    if not args.keep and args.work is None:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
