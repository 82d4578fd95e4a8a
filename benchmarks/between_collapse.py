"""Where the body passes through itself between frames: the straight in-between against the one
skinned from the poses (session 30, body.between), on a motion's collider sequence as
``simulate --motion`` makes it (warm-up transition included, simulated frame numbers).

For every frame f and the times f − 1 + k/n (k = 1 … n − 1): the collider vertices buried in
another part of the body (sim.crease.buried_vertices: winding number > 0.5) on the straight
in-between ((1 − s)·V[f−1] + s·V[f]) and on the skinned one (PoseBetween). Reported: per frame,
the most buried on either path and at the frame's two poses; the frames where an in-between is
buried and both poses are not.

    python benchmarks/motion_suite.py --full --targets --only cmu-hop --knee-collapse --work W   # caches W/cmu-hop-full-parts-knee.npz
    python benchmarks/between_collapse.py --motion W/cmu-hop-full-parts-knee.npz [--frames 150:200] [--steps 8] [--out FILE]

Writes benchmarks/results/between_collapse_s30.json (``checks``: the skinned path buries no more
in-between frames than the straight one).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import sys
from pathlib import Path

os.environ.setdefault("NUMBA_NUM_THREADS", "2")
sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--motion", required=True, help="a motion .npz (e.g. motion_suite's cached clip)")
    ap.add_argument("--frames", default=None, help="simulated frames a:b (default all)")
    ap.add_argument("--steps", type=int, default=8, help="in-betweens at k/steps")
    ap.add_argument("--warmup", type=float, default=1.0, help="seconds of warm-up, as simulate --warmup")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent / "results" / "between_collapse_s30.json"))
    args = ap.parse_args()
    from physavatar.data.material import resolve_material
    from physavatar.sim import SimSettings
    from physavatar.sim.crease import buried_vertices
    from physavatar.stages import simulate as S

    cfg = S.SimulateConfig(warmup=args.warmup, edge_length=0.05, preview=False, part_clearance=False,
                           arm_clearance=0.0)  # the clip as given (its corrections are in the file)
    mat = resolve_material(cfg.material, option="--material")
    _, bodies, faces, n_warm, *_, between = S._on_motion("dress", args.motion, 25.0, cfg, mat, SimSettings(), None)
    a, b = (int(x) for x in args.frames.split(":")) if args.frames else (1, len(bodies))
    a, b = max(a, 1), min(b, len(bodies))
    s = np.arange(1, args.steps) / args.steps
    count = lambda V: int(buried_vertices(V, faces).sum())  # noqa: E731
    rows = []
    for f in range(a, b):
        skinned = between(f, np.r_[0.0, s, 1.0])
        skinned = skinned[1:-1] + (1 - s)[:, None, None] * (bodies[f - 1] - skinned[0]) \
            + s[:, None, None] * (bodies[f] - skinned[-1])  # as sim.simulate.between_bodies
        line = (1 - s)[:, None, None] * bodies[f - 1] + s[:, None, None] * bodies[f]
        ends = [count(bodies[f - 1]), count(bodies[f])]
        rows.append({"frame": f, "written": f - n_warm, "poses": ends,
                     "straight": [count(V) for V in line], "skinned": [count(V) for V in skinned]})
        r = rows[-1]
        if max(r["straight"]) or max(r["skinned"]) or max(ends):
            print(f"{f:4d} (written {f - n_warm:4d}) poses {ends} straight {r['straight']} skinned {r['skinned']}",
                  flush=True)
    only = lambda key: [r["frame"] for r in rows if max(r[key]) and not max(r["poses"])]  # noqa: E731
    result = {"benchmark": "between_collapse", "motion": str(args.motion), "warmup_frames": n_warm,
              "frames": [a, b], "steps": args.steps,
              "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
              "frames_buried_in_between_only": {"straight": only("straight"), "skinned": only("skinned")},
              "frames_buried_anywhere": {k: [r["frame"] for r in rows if max(r[k])] for k in ("straight", "skinned", "poses")},
              "per_frame": [r for r in rows if max(r["straight"]) or max(r["skinned"]) or max(r["poses"])]}
    result["checks"] = {"in-between-only buried frames, skinned <= straight": {
        "value": len(only("skinned")), "target": f"<= {len(only('straight'))}",
        "pass": len(only("skinned")) <= len(only("straight"))}}
    Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result["frames_buried_in_between_only"]), json.dumps(result["checks"]))


if __name__ == "__main__":
    main()
