"""Issue 22 part 4, session 36: the shape term's weight chosen by the frames after the window
(`fit-physics --select-shape-weight`) and the rest solve's static friction, on `run --quick`'s
foreign captures and on the demo's full run (docs/physics.md "Issue 22, session 36").

For each case (a finished `physavatar run` folder RUN beside its CAPTURE):
1. `fit-physics RUN/track --select-shape-weight` with the run's budget (`--window 6 --iterations 3`
   for `run --quick`, `--window 12 --iterations 8` for the demo's full run) into WORK/CASE/fit_sel;
2. the held-out motion simulated as `evaluate` simulates its rows (`animate` on RUN/avatar with the
   material: both candidate fits, `sel_w3` and `sel_w0`; the run's own estimate `before_est` and
   oracle, and its five random draws, in the candidates' rest model, as evaluate gives the draws
   the estimate's) and scored as `evaluate` scores
   them (garment CD ×10³, seed 0, at --points: 100,000 for the foreign captures, where
   foreign_capture.py's floor is, 10,000 for the demo as its evaluate), cached in WORK/CASE/heldout.json;
3. "below random" = 1 − (CD − floor)/(CD of the median draw − floor), "below LBS" the same with the
   run's LBS row; the floor and LBS from the run's evaluate_100000 and --before's figures.

    python benchmarks/shape_weight_select.py --runs /tmp/w34-foreign/fc --work /tmp/w36-shapew \\
        --demo /tmp/demo34/demo_out --before benchmarks/results/foreign_capture_s34.json \\
        --out benchmarks/results/shape_weight_s36.json

The fits run with `--select-shape-weight --rest-friction` (both session-36 options) unless
--no-rest-friction.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _common import animate_scored, machine, write_result  # noqa: E402

CASES = ("skirt-plaid-256", "top-print-512", "top-plain-256")
HOLD = 0.01  # a held-out CD within 1 % of the run's estimate holds (issue 22 point 6)


def fit(track: Path, out: Path, window: int, iterations: int, rest_friction: bool) -> dict:
    if not (out / "material.json").exists():
        subprocess.run([sys.executable, "-m", "physavatar", "fit-physics", str(track), "--out", str(out), "--window",
                        str(window), "--iterations", str(iterations), "--select-shape-weight"]
                       + (["--rest-friction"] if rest_friction else []), check=True)
    return json.loads((out / "material.json").read_text())


def heldout(capture: Path, avatar: Path, cache: Path, materials: dict, points: int) -> dict:
    """{name: row} for every material (a dict) of ``materials``, simulated and scored as evaluate
    does; rows already in ``cache`` are kept."""
    from physavatar.body import Motion
    from physavatar.data.avatar import Avatar
    from physavatar.files import load_npz
    from physavatar.sim import Material

    res = json.loads(cache.read_text()) if cache.exists() else {}
    held = Motion.load(capture / "ground_truth" / "heldout" / "motion.npz")
    gt = load_npz(capture / "ground_truth" / "heldout" / "meshes.npz")["vertices"].astype(np.float64)
    for name, mat in materials.items():
        if name in res:
            continue
        av = Avatar.load(avatar)
        av.material = Material.from_dict({k: v for k, v in mat.items() if k != "units"})
        rows, stats, secs, V = animate_scored(av, held, gt, points)
        rs = stats.get("rest_shape") or {}
        res[name] = {"material": av.material.to_dict(), "cd_x1e3": rows["chamfer_x1e3"],
                     "per_frame": rows["per_frame_chamfer_x1e3"],
                     "vertex_mean_mm": 1e3 * float(np.linalg.norm(V - gt[:, av.template.labels > 0], axis=-1).mean()),
                     "rest": {k: rs.get(k) for k in ("at_rest", "converged", "final_rms_mm", "final_max_mm", "rounds",
                                                      "stopped", "seconds", "friction")},
                     "seconds": round(secs, 1)}
        print(f"{cache.parent.name} {name}: CD {rows['chamfer_x1e3']:.5f}", flush=True)
        cache.write_text(json.dumps(res, indent=1))
    return res


def case_materials(run: Path, sel: dict, draws: bool) -> dict:
    """The candidates, the run's estimate and oracle, and (``draws``) its random draws; the last
    three in the candidates' rest model (their ``rest_friction``), as evaluate gives the draws the
    estimate's model."""
    from physavatar.files import read_json

    out = {f"sel_w{r['shape_weight']:g}": r["material"] for r in sel["shape_selection"]["fits"]}
    friction = {"rest_friction": True} if any(m.get("rest_friction") for m in out.values()) else {}
    out["before_est"] = read_json(run / "physics" / "material.json")["material"]
    if (run / "oracle" / "material.json").exists():
        out["before_oracle"] = read_json(run / "oracle" / "material.json")["material"]
    if draws:
        ev = run / "evaluate_100000" / "metrics.json"
        metrics = read_json(ev if ev.exists() else run / "evaluate" / "metrics.json")
        for s, m in zip(metrics["random_draws"]["seeds"], metrics["random_draws"]["materials"]):
            out[f"random-{s}"] = m
    return {k: v | (friction if v.get("rest_shape") == "equilibrium" and not k.startswith("sel_") else {})
            for k, v in out.items()}


def summarise(name: str, run: Path, sel: dict, rows: dict, floor: float, points: int) -> tuple[dict, dict]:
    from physavatar.files import read_json

    ev = run / "evaluate_100000" / "metrics.json"
    before = read_json(ev if ev.exists() else run / "evaluate" / "metrics.json")
    cd = {k: r["cd_x1e3"] for k, r in rows.items()}
    draws = sorted(cd[k] for k in cd if k.startswith("random-"))
    median = draws[len(draws) // 2] if draws else None
    lbs = before["rows"]["LBS"]["garment"]["chamfer_x1e3"]
    chosen = f"sel_w{sel['shape_selection']['chosen']:g}"

    def below(v, ref):
        return 1 - (v - floor) / (ref - floor)

    fig = {"points": points, "floor_x1e3": floor, "lbs_x1e3": lbs, "random_median_x1e3": median,
           "random_draws_x1e3": draws, "heldout_cd_x1e3": cd, "chosen": chosen,
           "selection": [{k: r[k] for k in ("shape_weight", "heldout_rms_mm", "fit_rms_mm", "stretch_ratio",
                                            "bend_ratio", "integrator")} for r in sel["shape_selection"]["fits"]],
           "before": {"estimated_x1e3": before["rows"]["estimated material"]["garment"]["chamfer_x1e3"],
                      "random_median_x1e3": before["random_draws"]["garment_chamfer_x1e3_median"]},
           "rest": {k: r["rest"] for k, r in rows.items()}}
    if floor and median:
        fig["below_random"] = {k: below(v, median) for k, v in cd.items() if not k.startswith("random-")}
        fig["below_random_before"] = below(fig["before"]["estimated_x1e3"], fig["before"]["random_median_x1e3"])
        fig["below_lbs"] = {k: below(v, lbs) for k, v in cd.items() if not k.startswith("random-")}
    checks = {}
    if floor:
        checks[f"{name}:heldout_cd_below_random"] = {
            "value": fig["below_random"][chosen], "target": ">= 0.1", "pass": bool(fig["below_random"][chosen] >= 0.1),
            "unit": f"1 - (CD - floor)/(CD_random - floor) at {points} points, the kept fit"}
        checks[f"{name}:heldout_cd_below_lbs"] = {
            "value": fig["below_lbs"][chosen], "target": ">= 0.25", "pass": bool(fig["below_lbs"][chosen] >= 0.25),
            "unit": f"1 - (CD - floor)/(CD_LBS - floor) at {points} points, the kept fit"}
    # the run's estimate as its evaluate scored it, or the same material simulated again here (today's
    # code and, for the foreign captures, the candidates' rest model), whichever is higher, within HOLD
    # (1 %: the same material scored by the run and here differs by up to 0.15 % where the model is
    # the same, the demo and the tops)
    ref = max(fig["before"]["estimated_x1e3"], cd["before_est"])
    checks[f"{name}:heldout_cd_holds"] = {
        "value": cd[chosen] / ref - 1, "target": f"<= {HOLD:g}",
        "pass": bool(cd[chosen] <= ref * (1 + HOLD)), "unit": f"relative change of the garment CD at {points} points "
        f"against the run's estimate (its evaluate {fig['before']['estimated_x1e3']:.6g}, simulated again here "
        f"{cd['before_est']:.6g}), the kept fit {cd[chosen]:.6g}"}
    return fig, checks


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", type=Path, required=True, help="folder of the foreign cases (CASE/capture, CASE/run)")
    p.add_argument("--cases", default=",".join(CASES))
    p.add_argument("--demo", type=Path, help="the demo's output folder (capture, run: a full `run`)")
    p.add_argument("--work", type=Path, required=True)
    p.add_argument("--before", type=Path, required=True, help="foreign_capture.py's JSON of the runs (the floors)")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--rest-friction", action=argparse.BooleanOptionalAction, default=True)
    a = p.parse_args(argv)
    load0 = os.getloadavg()
    checks_before = json.loads(a.before.read_text())["checks"]
    figures, checks = {}, {}
    todo = [(c, a.runs / c, 6, 3, 100000) for c in a.cases.split(",") if c]
    if a.demo:
        todo.append(("demo", a.demo, 12, 8, 10000))
    for name, root, window, iterations, points in todo:
        run, work = root / "run", a.work / name
        work.mkdir(parents=True, exist_ok=True)
        sel = fit(run / "track", work / "fit_sel", window, iterations, a.rest_friction)
        floor = (checks_before.get(f"{name}:heldout_cd_below_random") or {}).get("floor_x1e3", 0.0)
        rows = heldout(root / "capture", run / "avatar", work / "heldout.json", case_materials(run, sel, bool(floor)),
                       points)
        figures[name], c = summarise(name, run, sel, rows, floor, points)
        checks |= c
    out = {"benchmark": "shape_weight_select", "date": time.strftime("%Y-%m-%d %H:%M"), "machine": machine(load0),
           "command": " ".join(sys.argv), "figures": figures, "checks": checks}
    write_result(a.out, out)
    for k, v in checks.items():
        print(k, round(v["value"], 4), v["target"], "pass" if v["pass"] else "FAIL")


if __name__ == "__main__":
    main()
