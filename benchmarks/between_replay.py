"""Replay a motion-suite case through ``simulate``'s stage up to a simulated frame, every implicit
step of the frames from F0 logged (lag, Newton and penalty iterations, buried and released
vertices, closest distance, the largest body move in the step): how session 30 traced the 2-cm
CMU walk's simulated frame 27 on the skinned in-between path (docs/simulation.md "Session 30").

    python benchmarks/motion_suite.py --only cmu-walk --work W --skinned-between --edge 0.02   # caches W/cmu-walk-parts.npz
    python benchmarks/between_replay.py W/cmu-walk-parts.npz skinned 27 27 OUT   # or: linear
``skinned``: the body skinned in between, the attached targets on the straight line (session 31;
session 30's mode of that name also carried the targets on the in-between body, its
``skinned-noride`` is today's ``skinned``: replay session 30's at commit f6e6bf5).
"""

import json
import sys
from pathlib import Path

import numpy as np

import physavatar.garment_sim as G
import physavatar.sim.simulate  # noqa: F401
from physavatar.stages import simulate as stage

S = sys.modules["physavatar.sim.simulate"]  # (the package exports the function under that name)


def main():
    motion, mode, F0, F1, out = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), Path(sys.argv[5])
    cur = {"f": 1}
    step0 = S.ClothSim.step

    def step(self, x, v, bt, bt1, faces, tg=None, history=None):
        res = step0(self, x, v, bt, bt1, faces, tg, history)
        st = res[2]
        if cur["f"] >= F0:
            print(f"frame {cur['f']}: lag {1e3 * st.body_gap:.2f} mm, {st.lag_vertices} lagging, Newton "
                  f"{st.newton_iterations}, penalty {st.penalty_iterations}, buried {st.buried_vertices}, released "
                  f"{st.released_vertices}, closest {1e3 * st.min_distance:.3f} mm, body move "
                  f"{1e3 * np.linalg.norm(bt1 - bt, axis=1).max():.1f} mm", flush=True)
        return res

    simulate0 = G.simulate

    def simulate(*a, on_frame=None, **kw):
        def each(ck, r):
            if on_frame:
                on_frame(ck, r)
            cur["f"] = ck.frame + 1
            if ck.frame >= F0:
                print("frame", ck.frame, json.dumps({k: r[k] for k in ("substeps", "attempts", "newton_iterations",
                                                                       "lag_m", "buried_vertices", "released_vertices")}))
            if ck.frame >= F1:
                raise SystemExit(0)
        return simulate0(*a, on_frame=each, **kw)

    S.ClothSim.step, G.simulate = step, simulate
    cfg = stage.SimulateConfig(edge_length=0.02, duration=1.0, warmup=0.4, preview=False,
                               skinned_between=mode == "skinned")
    stage.run(out=out, config=cfg, garment="dress", motion=motion)


if __name__ == "__main__":
    main()
