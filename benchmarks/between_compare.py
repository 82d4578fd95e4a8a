"""Session 30's motion suite, before and after skinned in-between bodies (body.between): two
motion_suite runs side by side, and how far the straight in-between strays from the skinned one.

Reads the result files and work folders of two ``benchmarks/motion_suite.py`` runs of the same
motions (``--before``: the old code or ``--no-skinned-between``; ``--after``: this tree's
default) and writes per motion: frames, frames with lag, body and self intersection, NaN,
s/frame, mean and max sub-steps, Newton iterations and steps (summed over the written frames'
reports, the run's config.json ``per_frame``), and whether the written frames are bit-identical. Also per motion,
from its poses (the motion's frames, no warm-up; Anny's collider): the largest distance between
the straight in-between and the skinned one half-way through a frame, over the body and over
the frames (``chord_error_mm``: max and 95th percentile over frames of the per-frame max).

    python benchmarks/between_compare.py --before B.json:WORK_B --after A.json:WORK_A [--out FILE]

Writes benchmarks/results/motion_suite_between_s30.json (``checks``: after, no more lagging,
crossing or NaN frames than before, per motion; and no more Newton iterations than before over
the motions, ``total:newton_iterations``, since session 31).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402

KEYS = ("frames_with_lag", "frames_with_body_intersection", "frames_with_self_intersection", "frames_with_nan")


def _side(spec: str) -> tuple[dict, Path]:
    result, work = spec.split(":")
    return json.loads(Path(result).read_text()), Path(work)


def _row(fig: dict, work: Path, name: str) -> dict:
    rec = json.loads((work / name / "config.json").read_text())
    return {k: len(fig[k]) for k in KEYS} | {
        "frames": fig["frames"], "s_per_frame": round(fig["s_per_frame"], 3), "mean_substeps": round(fig["mean_substeps"], 3),
        "max_substeps": fig["max_substeps"], "newton_iterations": int(sum(rec["per_frame"]["newton_iterations"])),
        "steps": int(sum(rec["per_frame"]["substeps"])), "max_lag_m": fig["max_lag_m"],
        "load_average_1_5_15min": fig.get("run", {}).get("load_average_1_5_15min_now")}


def chord_error(name: str, work: Path) -> dict | None:
    """How far the straight in-between strays from the skinned one half-way through a frame."""
    from physavatar.body import BodyModel, Motion
    from physavatar.body.between import PoseBetween
    from physavatar.body.load import load_motion

    body = BodyModel(topology="collider")
    specs = [work / f"{name}.npz"] + sorted(work.glob(f"{name}-*.npz"))
    spec = next((p for p in specs if p.exists()), None)
    m = Motion.load(spec).for_bones(body.bone_names) if spec else load_motion(name, 25.0, 1.0, body=body)
    V = body.pose(m.rotations, m.root_translation).vertices
    between = PoseBetween(body, m.rotations, m.root_translation)
    err = np.array([np.linalg.norm(between(f, [0.5])[0] - 0.5 * (V[f - 1] + V[f]), axis=1).max()
                    for f in range(1, len(V))])
    return {"max_mm": round(1e3 * float(err.max()), 2), "p95_mm": round(1e3 * float(np.percentile(err, 95)), 2),
            "frame_of_max": int(err.argmax()) + 1, "motion_file": spec.name if spec else f"built-in {name}, 1 s"}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", required=True, help="RESULT.json:WORK of the run before")
    ap.add_argument("--after", required=True, help="RESULT.json:WORK of the run after")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent / "results" / "motion_suite_between_s30.json"))
    args = ap.parse_args()
    (rb, wb), (ra, wa) = _side(args.before), _side(args.after)
    rows, checks = {}, {}
    for name in [n for n in ra["figures"] if n in rb["figures"]]:
        before, after = _row(rb["figures"][name], wb, name), _row(ra["figures"][name], wa, name)
        xb = np.load(wb / name / "garment_sequence.npz")["vertices"]
        xa = np.load(wa / name / "garment_sequence.npz")["vertices"]
        rows[name] = {"before": before, "after": after, "written_frames_bit_identical": bool(np.array_equal(xa, xb)),
                      "chord_error_mm": chord_error(name, wa)}
        for k in KEYS:
            checks[f"{name}:{k}"] = {"value": after[k], "before": before[k], "target": f"<= {before[k]} (before)",
                                     "unit": "frames", "pass": after[k] <= before[k]}
        print(f"{name:15s} newton {before['newton_iterations']:5d} -> {after['newton_iterations']:5d}  s/frame "
              f"{before['s_per_frame']:.2f} -> {after['s_per_frame']:.2f}  lag {before['frames_with_lag']} -> "
              f"{after['frames_with_lag']}  chord {rows[name]['chord_error_mm']['max_mm']} mm", flush=True)
    total = {side: sum(r[side]["newton_iterations"] for r in rows.values()) for side in ("before", "after")}
    checks["total:newton_iterations"] = {"value": total["after"], "before": total["before"],
                                         "target": f"<= {total['before']} (before)", "unit": "iterations",
                                         "pass": total["after"] <= total["before"]}
    print(f"total newton {total['before']} -> {total['after']}", flush=True)
    out = {"benchmark": "motion_suite_between", "date": datetime.datetime.now(datetime.timezone.utc).isoformat(
               timespec="seconds"), "machine": {"cores": os.cpu_count(), "load_average_1_5_15min": os.getloadavg()},
           "before": {"code_commit": rb.get("code_commit"), "config": rb["config"], "date": rb["date"]},
           "after": {"code_commit": ra.get("code_commit"), "config": ra["config"], "date": ra["date"]},
           "figures": rows, "checks": checks}
    Path(args.out).write_text(json.dumps(out, indent=2) + "\n")


if __name__ == "__main__":
    main()
