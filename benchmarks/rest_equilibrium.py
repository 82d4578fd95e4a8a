"""The garment's rest shape from static equilibrium (issue 22's model gap, session 27): before/after.

    python benchmarks/rest_equilibrium.py [--cases NAME,NAME,tracked:DIR] [--foreign DIR] [--demo DIR] [--work DIR]
                                          [--random-draws N] [--out FILE]

For each foreign capture (DIR/<case>/capture, made by benchmarks/foreign_capture.py: another
simulator's garment, so what counts is the fit on the TRUE meshes, the model gap) the material is
fitted on the true meshes (`fit-physics CAPTURE`, `run --quick`'s budget: foreign_capture.py's
oracle row) twice: with the template as rest shape (before) and with `--rest-shape equilibrium`
(after). One avatar of the capture carries the first; `evaluate` (no views) scores on the held-out
motion LBS, the median of --random-draws random materials, the first ("estimated material" =
oracle, template rest) and the second ("oracle material" = oracle, equilibrium rest; animate
computes its rest shape for it). Per variant: the fit's RMS residual on the true meshes, κs/ρ,
κb/ρ, the held-out garment CD ×10³ (10,000 points) and mean vertex distance [mm], and the
frame-1 sag: the first frame of the training motion simulated from the true frame 0 with the
fitted material (mean z offset and mean distance to the true frame 1, mm).

The demo (--demo: a finished `make demo`, DIR/capture and DIR/run): the material is fitted on the
run's tracked meshes with `run`'s settings and --rest-shape equilibrium; before is the run's own
fit and evaluate (same code without the option). Material error against ground_truth/material.json,
held-out CD of the estimate and of the true material (the run's references).

A case ``tracked:DIR`` (a foreign capture's finished `physavatar run`: DIR/capture, DIR/run) is
measured as the demo is, on that run's tracked meshes, with the budget the run's fit had.

Writes benchmarks/results/rest_equilibrium.json (checks: informative; the option becomes a
default only where every case holds or improves).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import numpy as np
from _common import cpu_name

CASES = ("skirt-plaid-256", "top-print-512", "top-plain-256")


def fit(source: Path, out: Path, rest_shape: str, quick: bool = True) -> dict:
    """fit-physics with `run`'s settings (--quick: foreign_capture's oracle) and the rest shape."""
    from physavatar.stages.physics import run as fit_physics
    from physavatar.stages.physics.config import pipeline_config

    if not (out / "material.json").exists():
        cfg = dataclasses.replace(pipeline_config(quick=quick), rest_shape=rest_shape)
        fit_physics(source, out=out, config=cfg, say=lambda s: print(f"  fit {out.name}: {s}", flush=True))
    return fit_record(out)


def fit_record(folder: Path) -> dict:
    d = json.loads((folder / "material.json").read_text())
    m = d["material"]
    return {"rms_mm": d["rms_mm"], "stretch_ratio": m["stretch_stiffness"] / m["density"],
            "bend_ratio": m["bend_stiffness"] / m["density"], "integrator": d.get("integrator"),
            "contact_offset_mm": 1e3 * m.get("contact_offset", 0.0), "rest_shape": m.get("rest_shape", "template"),
            "rest_solve": {k: v for k, v in ((d.get("start_state") or {}).get("rest_shape") or {}).items()
                           if k != "error_mm"}}


def frame1_sag(capture_or_tracked: Path, material_json: Path) -> dict:
    """The training motion's first frame simulated from the true (or tracked) frame 0 with the
    material: mean z offset and mean distance [mm] from frame 1 over the free garment vertices."""
    from physavatar.data.material import FittedMaterial
    from physavatar.garment_sim import GarmentPart, simulate_on_body
    from physavatar.stages.physics.data import clear_start, load_physics_data

    d = load_physics_data(capture_or_tracked)
    start, _ = clear_start(d.window(0, 3), capture_or_tracked, 0, d)  # (a tracked frame may cross the body)
    mat = FittedMaterial.load(material_json).material
    part = GarmentPart(np.arange(d.reference.shape[1]), start.initial.copy(), d.faces, d.boundary)
    rest = {}
    X = simulate_on_body(part, d.collider[:3], d.collider_faces, mat, d.fps, rest_report=rest)
    free = np.ones(len(part.vertices), bool)
    free[d.boundary] = False
    out = {}
    for f in (1, 2):
        diff = (X[f] - d.reference[f])[free]
        out[f"frame{f}"] = {"mean_z_mm": 1e3 * float(diff[:, 2].mean()),
                            "vertex_mean_mm": 1e3 * float(np.linalg.norm(diff, axis=1).mean())}
    return out | {"rest": {k: v for k, v in rest.items() if k != "error_mm"}}


def vertex_rows(capture: Path, seqs: dict) -> dict:
    """Mean vertex distance [mm] of the garment of each [T, V, 3] sequence to the held-out truth."""
    from physavatar.capture import load_capture
    from physavatar.files import load_npz

    g = load_capture(capture).template.labels > 0
    gt = load_npz(capture / "ground_truth" / "heldout" / "meshes.npz")["vertices"].astype(np.float64)
    return {k: 1e3 * float(np.linalg.norm(V[: len(gt), g] - gt[: len(V), g], axis=-1).mean()) for k, V in seqs.items()}


def foreign_case(name: str, capture: Path, work: Path, draws: int) -> dict:
    from physavatar.body import Motion
    from physavatar.data.avatar import Avatar
    from physavatar.stages.animate import animate
    from physavatar.stages.avatar import build_avatar
    from physavatar.stages.evaluate import evaluate, reference_sequences

    t0 = time.time()
    res = {"fits": {}, "seconds": {}}
    for rest in ("template", "equilibrium"):
        t = time.time()
        res["fits"][rest] = fit(capture, work / f"oracle-{rest}", rest)
        res["seconds"][f"fit_{rest}"] = round(time.time() - t, 1)
    refs = work / "references"
    if not (refs / "references.json").exists():
        reference_sequences(capture, refs, random_draws=draws, rest_shape="template", progress=False)
    seqs = {}
    for rest in ("template", "equilibrium"):
        av_dir = work / f"avatar-{rest}"
        if not (av_dir / "avatar.json").exists():
            build_avatar(capture, av_dir, material=work / f"oracle-{rest}" / "material.json")
        av = Avatar.load(av_dir)
        held = Motion.load(capture / "ground_truth" / "heldout" / "motion.npz")
        t = time.time()
        seq, stats = animate(av, held, progress=False)
        res["seconds"][f"animate_{rest}"] = round(time.time() - t, 1)
        res.setdefault("animate_rest", {})[rest] = {k: v for k, v in stats["rest_shape"].items() if k != "error_mm"}
        seq.save(work / f"animate-{rest}", {"command": "animate", "rest_shape": rest}, ply=False)
        seqs[rest] = seq.vertices
        ev = evaluate(capture, av_dir, work / f"evaluate-{rest}", views=False, full=False, random_draws=draws,
                      references=refs, sequence=work / f"animate-{rest}", progress=False)
        res.setdefault("heldout", {})[rest] = {row: r["garment"]["chamfer_x1e3"] for row, r in ev["rows"].items()}
        res["sag"] = res.get("sag", {}) | {rest: frame1_sag(capture, work / f"oracle-{rest}" / "material.json")}
    res["vertex_mean_mm"] = vertex_rows(capture, seqs)
    floor = None
    try:
        import foreign_capture as FC

        floor = FC.cd_floor(capture, 10000)["chamfer_x1e3"]
    except Exception as e:  # noqa: BLE001 (the floor is for reading only)
        print(f"  floor not computed: {e}")
    res["cd_floor_x1e3"] = floor
    res["seconds"]["total"] = round(time.time() - t0, 1)
    return res


def demo_case(demo: Path, work: Path) -> dict:
    """The demo: the run's fit (before) against a fit with --rest-shape equilibrium (after)."""
    from physavatar.body import Motion
    from physavatar.data.avatar import Avatar
    from physavatar.sim import Material
    from physavatar.stages.animate import animate
    from physavatar.stages.avatar import build_avatar
    from physavatar.stages.evaluate import evaluate
    from physavatar.data.tracked import TrackedSequence

    capture, run = demo / "capture", demo / "run"
    truth_file = capture / "ground_truth" / "material.json"  # (a foreign capture has none)
    truth = Material.load(truth_file) if truth_file.exists() else None
    from physavatar.stages.physics.config import pipeline_config

    t0 = time.time()
    quick = json.loads((run / "physics" / "config.json").read_text())["window"] == pipeline_config(True).window
    after = fit(run / "track", work / "physics-equilibrium", "equilibrium", quick=quick)
    before = fit_record(run / "physics")
    res = {"fits": {"template": before, "equilibrium": after}, "seconds": {"fit_equilibrium": round(time.time() - t0, 1)}}
    for k, r in res["fits"].items() if truth is not None else ():
        r["stretch_ratio_error_pct"] = 100 * abs(r["stretch_ratio"] / truth.stretch_ratio - 1)
        r["bend_ratio_error_pct"] = 100 * abs(r["bend_ratio"] / truth.bend_ratio - 1)
    av_dir = work / "avatar-equilibrium"
    if not (av_dir / "avatar.json").exists():
        tv = TrackedSequence.load(run / "track", require=("vertices",)).vertices[0]
        build_avatar(capture, av_dir, material=work / "physics-equilibrium" / "material.json", template_vertices=tv)
    av = Avatar.load(av_dir)
    before_m = json.loads((run / "evaluate" / "metrics.json").read_text())
    frames = before_m.get("heldout_frames")
    held = Motion.load(capture / "ground_truth" / "heldout" / "motion.npz").slice(0, frames)
    t = time.time()
    seq, stats = animate(av, held, progress=False)
    res["seconds"]["animate_equilibrium"] = round(time.time() - t, 1)
    res["animate_rest"] = {k: v for k, v in stats["rest_shape"].items() if k != "error_mm"}
    seq.save(work / "animate-equilibrium", {"command": "animate", "rest_shape": "equilibrium"}, ply=False)
    ev = evaluate(capture, av_dir, work / "evaluate-equilibrium", frames=frames, views=False, full=False,
                  references=run / "references", sequence=work / "animate-equilibrium", progress=False)
    res["heldout"] = {"template": {row: r["garment"]["chamfer_x1e3"] for row, r in before_m["rows"].items()},
                      "equilibrium": {row: r["garment"]["chamfer_x1e3"] for row, r in ev["rows"].items()}}
    before_seq = run / "animate" / "sequence.npz"
    seqs = {"equilibrium": seq.vertices}
    if before_seq.exists():
        seqs["template"] = np.load(before_seq)["vertices"].astype(np.float64)
    res["vertex_mean_mm"] = vertex_rows(capture, seqs)
    res["sag"] = {k: frame1_sag(run / "track", f) for k, f in (("template", run / "physics" / "material.json"),
                                                               ("equilibrium", work / "physics-equilibrium" / "material.json"))}
    res["seconds"]["total"] = round(time.time() - t0, 1)
    return res


def checks_for(name: str, res: dict) -> dict:
    """Informative: after against before on the held-out CD of the material fitted on the true
    meshes, and the fit residual."""
    h, f = res["heldout"], res["fits"]
    row = "oracle material" if "oracle material" in h["equilibrium"] else "estimated material"
    before = h["template"]["estimated material"]
    after = h["equilibrium"][row]
    return {f"{name}:heldout_cd_equilibrium_not_worse": {"value": after, "before": before, "unit": "CD x1e3",
                                                          "target": "<= before", "pass": after <= before,
                                                          "informative": True},
            f"{name}:fit_rms_equilibrium_not_worse": {"value": f["equilibrium"]["rms_mm"], "before": f["template"]["rms_mm"],
                                                       "unit": "mm", "target": "<= before",
                                                       "pass": f["equilibrium"]["rms_mm"] <= f["template"]["rms_mm"],
                                                       "informative": True}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default=",".join(CASES) + ",demo")
    ap.add_argument("--foreign", default="/tmp/w22fc", help="folder with <case>/capture (foreign_capture.py's work)")
    ap.add_argument("--demo", default="/tmp/demo26/demo_out", help="a finished make demo (capture/, run/)")
    ap.add_argument("--work", default="/tmp/rest_equilibrium")
    ap.add_argument("--random-draws", type=int, default=3)
    ap.add_argument("--out", default=str(HERE / "results" / "rest_equilibrium.json"))
    args = ap.parse_args(argv)
    out = Path(args.out)
    result = json.loads(out.read_text()) if out.exists() else {"benchmark": "rest_equilibrium", "results": {},
                                                                 "checks": {}}
    result.update(date=datetime.datetime.now().isoformat(timespec="seconds"),
                  machine={"cores": os.cpu_count(), "cpu": cpu_name(), "load_average_start": list(os.getloadavg())})
    for name in args.cases.split(","):
        folder = None
        if name.startswith("tracked:"):  # a foreign capture's `run` (DIR/capture, DIR/run): its tracked meshes
            folder = Path(name.split(":", 1)[1])
            name = f"tracked-{folder.name}"
        work = Path(args.work) / name
        work.mkdir(parents=True, exist_ok=True)
        print(f"== {name}", flush=True)
        if name == "demo":
            res = demo_case(Path(args.demo), work)
        elif folder is not None:
            res = demo_case(folder, work)
        else:
            res = foreign_case(name, Path(args.foreign) / name / "capture", work, args.random_draws)
        result["results"][name] = res
        result["checks"].update(checks_for(name, res))
        result["machine"]["load_average_end"] = list(os.getloadavg())
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(result, indent=1, default=float) + "\n")
        print(json.dumps({k: res[k] for k in ("fits", "heldout", "vertex_mean_mm", "sag") if k in res}, indent=1,
                         default=float), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
