"""The demo walk with skinned in-between bodies (session 30, body.between): bit for bit the same
where no frame is split into sub-steps.

The scene of benchmarks/sim_speed.py (the demo dress on the demo walk, Anny's collider body,
self-contact on) simulated through garment_sim.simulate_on_body:

- ``linear-1``: one step per frame, no in-between (sim_speed's run), by this tree's code and by
  the ``--baseline`` commit's (its src exported as sim_speed does): np.array_equal;
- ``skinned-1``: one step per frame with the in-between given: never asked, the same bits;
- ``linear-16`` / ``skinned-16``: sub-steps decided per frame (at most 16, as ``simulate`` and
  ``animate``): the same bits exactly when no frame was split (the frames split are listed).

    python benchmarks/between_identity.py [--frames N] [--baseline REF] [--out FILE]

Writes benchmarks/results/between_identity_s30.json with ``checks``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

os.environ.setdefault("NUMBA_NUM_THREADS", "2")
os.environ.setdefault("OMP_NUM_THREADS", "2")
HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import numpy as np  # noqa: E402

BASELINE = "659aa6b"  # main before session 30's in-between bodies


def run(scene_file: str, mode: str, out: str):
    """Simulate the scene with whatever ``physavatar`` is on the path in ``mode``
    (linear|skinned)-(1|16); save positions and per-frame sub-step counts to ``out``."""
    from physavatar.garment_sim import GarmentPart, simulate_on_body
    from physavatar.sim import SimSettings, preset

    z = np.load(scene_file)
    part = GarmentPart(z["vertex_ids"], z["vertices"], z["faces"], z["boundary"],
                       z["rest"] if "rest" in z else None, z["seams"] if "seams" in z else None)
    fps = float(z["fps"])
    kind, cap = mode.split("-")
    options = {"max_substeps": int(cap)}
    if kind == "skinned":
        from physavatar.body import BodyModel, BodyShape
        from physavatar.body.between import PoseBetween

        body = BodyModel(BodyShape.from_array(z["shape"]), topology=str(z["topology"]))
        options["between"] = PoseBetween(body, z["rotations"], z["root_translation"])
    reports = []
    X = simulate_on_body(part, z["bodies"], z["body_faces"], preset(str(z["material"])), fps,
                         settings=SimSettings(dt=1.0 / fps, self_contact=True),
                         on_frame=lambda c, r: reports.append(r), **options)
    np.savez(out, X=X, substeps=np.array([r["substeps"] for r in reports]),
             newton=np.array([r["newton_iterations"] for r in reports]), lagged=np.array([r["lagged"] for r in reports]))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=48)
    ap.add_argument("--baseline", default=BASELINE)
    ap.add_argument("--out", default=str(HERE / "results" / "between_identity_s30.json"))
    ap.add_argument("--worker", nargs=3, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        return run(*args.worker)
    from _common import cpu_name
    from physavatar.body import builtin_motion
    from physavatar.synth import PRESETS, build_template
    from sim_speed import baseline_src, build_scene

    arrays, fps, material = build_scene(args.frames)
    cfg = PRESETS["demo"]
    body, _, _ = build_template(cfg)
    motion = builtin_motion(cfg.motion, body.bone_names, cfg.fps, (args.frames - 1) / cfg.fps)
    assert np.array_equal(motion.pose(body).vertices, arrays["bodies"])
    load0 = os.getloadavg()
    runs = {"new": [("linear-1", None), ("skinned-1", None), ("linear-16", None), ("skinned-16", None)],
            "baseline": [("linear-1", None), ("linear-16", None)]}
    out, summary = {}, {}
    with tempfile.TemporaryDirectory(prefix="between-") as tmp:
        scene = str(Path(tmp) / "scene.npz")
        np.savez(scene, **arrays, fps=fps, material=material, shape=body.shape.as_array(), topology=body.topology,
                 rotations=motion.rotations, root_translation=motion.root_translation)
        for code, modes in runs.items():
            src = HERE.parent / "src" if code == "new" else baseline_src(args.baseline)
            for mode, _ in modes:
                f = str(Path(tmp) / f"{code}-{mode}.npz")
                subprocess.run([sys.executable, __file__, "--worker", scene, mode, f], check=True,
                               env=os.environ | {"PYTHONPATH": str(src)})
                z = np.load(f)
                out[f"{code}:{mode}"] = (z["X"], z["substeps"])
                summary[f"{code}:{mode}"] = {"frames_split": [i + 1 for i, n in enumerate(z["substeps"]) if n > 1],
                                             "steps": int(z["substeps"].sum()), "newton_iterations": int(z["newton"].sum()),
                                             "frames_with_lag": [i + 1 for i, g in enumerate(z["lagged"]) if g]}
                print(f"{code:8s} {mode:10s} frames split: {[i + 1 for i, n in enumerate(z['substeps']) if n > 1]}",
                      flush=True)
    same = lambda a, b: bool(np.array_equal(out[a][0], out[b][0], equal_nan=True))  # noqa: E731
    split16 = [i + 1 for i, n in enumerate(out["new:linear-16"][1]) if n > 1]
    checks = {
        "linear-1 new == baseline": {"value": same("new:linear-1", "baseline:linear-1"), "target": True},
        "skinned-1 == linear-1": {"value": same("new:skinned-1", "new:linear-1"), "target": True},
        "linear-16 new == baseline": {"value": same("new:linear-16", "baseline:linear-16"), "target": True},
        "skinned-16 == linear-16 where no frame is split": {
            "value": same("new:skinned-16", "new:linear-16"), "target": not split16},
    }
    for c in checks.values():
        c["pass"] = c["value"] == c["target"]
    diff = float(np.nanmax(np.abs(out["new:skinned-16"][0] - out["new:linear-16"][0])))
    result = {"benchmark": "between_identity", "date": datetime.datetime.now(datetime.timezone.utc).isoformat(
                  timespec="seconds"), "baseline": args.baseline,
              "machine": {"cores": os.cpu_count(), "cpu": cpu_name(), "load_average_1_5_15min_start":
                          [round(v, 2) for v in load0], "load_average_1_5_15min_end": [round(v, 2) for v in os.getloadavg()]},
              "scene": {"garment_vertices": len(arrays["vertices"]), "frames": args.frames, "fps": fps},
              "frames_split_with_max_substeps_16": split16,
              "max_difference_skinned_16_vs_linear_16_m": diff, "runs": summary, "checks": checks}
    Path(args.out).write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(checks, indent=1))


if __name__ == "__main__":
    main()
