"""What `--knee-collapse` auto decides on the CMU clips, before anything is simulated (session 33).

Each CMU clip (``shared/data/motions/cmu_131_0{1,3}.bvh``) is retargeted and corrected as
``simulate`` does (arm clearance 3 cm, the default part-clearance rules) and then given the knee
rules three ways: off (``--no-knee-collapse``), on (``--knee-collapse``, every collapse opened) and
auto (the default: only windows where calf and thigh cross at least ``KNEE_ROOM`` deep). Per clip
and side it reports the windows auto found (frames, deepest crossing [mm], hinge opening that
clears the deepest frame [deg], opened or left), and which of off / on the auto clip is
``np.array_equal`` to, whole and over the quick suite's 1-s excerpts (benchmarks/motion_suite.py
``CLIPS``). The simulator is deterministic, so an auto clip equal to a clip whose whole run was
measured clean (docs/simulation.md "Session 32": the walk with the knee rules off, the hop with them
on) runs as that run did.

    python benchmarks/knee_collapse_auto.py [--out FILE]

Writes benchmarks/results/knee_collapse_auto.json (``checks``: the auto clip equals the measured
clean setting of each clip: the walk off, the hop on).
"""

from __future__ import annotations

import argparse
import datetime
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("NUMBA_NUM_THREADS", "2")
os.environ.setdefault("OMP_NUM_THREADS", "2")
sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402

from _common import cpu_name  # noqa: E402
from motion_suite import CLIPS, MOTIONS, _head  # noqa: E402
from physavatar.body import BodyModel  # noqa: E402
from physavatar.body.clearance import KNEE_ROOM  # noqa: E402
from physavatar.body.load import load_motion, with_arm_clearance, with_part_clearance  # noqa: E402
from physavatar.files import write_json_atomic  # noqa: E402

CLEAN = {"cmu-walk": "off", "cmu-hop": "on"}  # the knee setting whose whole 2-cm run was clean (sessions 31-32)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default=None, help="result file (default benchmarks/results/knee_collapse_auto.json)")
    args = ap.parse_args()
    body, fps, quick = BodyModel(topology="collider"), 25.0, 26  # the quick suite: 1 s at 25 fps, both ends
    load0, figures, checks = os.getloadavg(), {}, {}
    for name, (clip, start) in CLIPS.items():
        path = str(MOTIONS / clip)
        m, _ = with_arm_clearance(load_motion(path, fps, 4.0, body=body), path, body, 0.03)
        clips, summary, seconds = {}, None, {}
        for mode, knee in (("off", False), ("on", True), ("auto", None)):
            t0 = time.perf_counter()
            clips[mode], s = with_part_clearance(m, path, body, True, knee, KNEE_ROOM)
            seconds[mode] = round(time.perf_counter() - t0, 1)
            summary = s if mode == "auto" else summary
        auto = clips["auto"].rotations
        same = {mode: bool(np.array_equal(auto, clips[mode].rotations)) for mode in ("off", "on")}
        ex = slice(start, start + quick)
        same_quick = {mode: bool(np.array_equal(auto[ex], clips[mode].rotations[ex])) for mode in ("off", "on")}
        sides = {}
        for rule, v in (summary or {}).items():
            if rule.startswith("knee-collapse"):
                sides[rule] = {"windows": v.get("windows", []), "frames_turned": v["frames_turned"],
                               "max_angle_deg": v["max_angle_deg"]}
        figures[name] = {"frames": len(auto), "min_depth_m": KNEE_ROOM, "knee_collapse_auto": sides,
                         "auto_equals_whole": same, "auto_equals_quick_excerpt": same_quick,
                         "quick_excerpt_frames": [start, start + quick - 1], "part_clearance_s": seconds}
        checks[f"{name}:auto_equals_measured_clean_{CLEAN[name]}"] = {
            "value": same[CLEAN[name]], "target": f"auto clip np.array_equal to the '{CLEAN[name]}' clip",
            "pass": same[CLEAN[name]]}
        for rule, v in sides.items():
            for w in v["windows"]:
                print(f"{name} {rule}: frames {w['frames'][0]}-{w['frames'][1]}, deepest {1e3 * w['deepest_m']:.2f} mm, "
                      f"opening {w['opening_deg']:.3f} deg: {'opened' if w['opened'] else 'left'}")
        print(f"{name}: auto = off {same['off']}, auto = on {same['on']}; quick excerpt: auto = off "
              f"{same_quick['off']}, auto = on {same_quick['on']}", flush=True)
    out = Path(args.out) if args.out else Path(__file__).resolve().parent / "results" / "knee_collapse_auto.json"
    write_json_atomic(out, {
        "benchmark": "knee_collapse_auto", "code_commit": _head(),
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "machine": {"cores": os.cpu_count(), "cpu": cpu_name(), "gpu": None,
                    "load_average_1_5_15min_start": [round(v, 2) for v in load0],
                    "load_average_1_5_15min_now": [round(v, 2) for v in os.getloadavg()]},
        "config": {"arm_clearance_m": 0.03, "part_clearance": True, "fps": fps, "min_depth_m": KNEE_ROOM},
        "figures": figures, "checks": checks})


if __name__ == "__main__":
    main()
