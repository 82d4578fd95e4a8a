"""A few frames of a whole CMU clip (motion_suite --full's dress, 2-cm, cotton, self-contact on), from
a state rebuilt from a whole-clip run's written frames: x = frame F0, v = (x_F0 − x_F0−1)·25, κ
from the run's last state (frames/state.npz); then frames F0+1..F1 as ``simulate`` runs them
(sub-steps per frame, retries up to 16; ``stuck``: one attempt a frame). Each frame is checked:
lag, ipctk's intersection test against the whole body and against its outer surface (the
triangles without a buried corner: sim.crease), cloth vertices inside the body (winding number).
The runs of session 18 (/tmp/w18clip-full, not in the repository) were the source of the states;
session 21's is ``motion_suite.py --full --only cmu-walk --work /tmp/w21clip`` (CLIP_RUNS=/tmp/w21clip).
With CLIP_STATE set to a copy of the run's ``frames/state.npz`` taken right after frame F0 was written,
the frames start from that exact checkpoint instead (v, κ, BDF2 history and lag as the run had them).

    python benchmarks/clip_frames.py cmu-walk 98 102 1 OUT.json [stuck]   # crease_ring 1 (-1: off)
"""
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from physavatar.data.material import resolve_material
from physavatar.garment_sim import simulate_on_body
from physavatar.sim import SimSettings
from physavatar.sim.contact import ContactScene
from physavatar.sim.crease import buried_vertices, winding_numbers
from physavatar.sim.simulate import Checkpoint
from physavatar.stages import simulate as S

clip, f0, f1, ring, out = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), sys.argv[5]
src = os.environ.get("CLIP_RUNS", "/tmp/w18clip-full") + f"/{clip}"
cfg = S.SimulateConfig(edge_length=0.02, duration=4.0, warmup=1.0, preview=False, max_substeps=16, self_contact=True)
mat = resolve_material(cfg.material, option="--material")
ss = SimSettings(integrator=mat.integrator)
part, bodies, bf, n_warm, _, _ = S._on_motion("dress", str(Path(src).parent / f"{clip}-full.npz"), 25.0, cfg, mat, ss, None)
part, _ = S.repaired_start(part, bodies[0], bf, ss.dhat, cfg.repair_limit, "dress")
exclude = part.contact_exclusions()
ss = dataclasses.replace(ss, self_contact=S.self_contact_possible(part.vertices, part.faces, ss.dhat, exclude), crease_ring=ring)
x0 = np.load(f"{src}/frames/{f0:06d}.npz")["x"]; xm = np.load(f"{src}/frames/{f0-1:06d}.npz")["x"]
st = np.load(f"{src}/frames/state.npz", allow_pickle=True)
scal = json.loads(str(st["solver_scalars"]))
solver = {"dt": 0.04, "barrier_stiffness": scal["barrier_stiffness"], "max_barrier_stiffness": scal["max_barrier_stiffness"],
          "kappa_balanced": scal["kappa_balanced"], "stuck": len(sys.argv) > 6 and sys.argv[6] == "stuck"}
ck = Checkpoint(f0, x0, (x0 - xm) * 25.0, solver)
if os.environ.get("CLIP_STATE"):  # the run's own checkpoint after frame f0 (exact)
    ck = Checkpoint.load(os.environ["CLIP_STATE"])
    if ck.frame != f0:
        sys.exit(f"CLIP_STATE holds the state after frame {ck.frame}, not {f0}")
    ck.solver["stuck"] = solver["stuck"] or bool(ck.solver.get("stuck", False))
T = f1 + 1
rows = []
def on_frame(c, r):
    r = dict(r); X = np.vstack([c.x, bodies[c.frame]])
    sc = ContactScene(part.rest_shape, part.faces, bodies[0], bf, ss.dhat)
    r["intersects_body"] = bool(sc.has_intersections(X))
    bur = buried_vertices(bodies[c.frame], bf)
    Fkeep = bf[~bur[bf].any(axis=1)]  # the outer surface: triangles without a buried corner
    so = ContactScene(part.rest_shape, part.faces, bodies[0], Fkeep, ss.dhat)
    r["intersects_outer_surface"] = bool(so.has_intersections(X))
    r["cloth_inside_body"] = int(np.sum(winding_numbers(c.x, bodies[c.frame], bf) > 0.5))
    r["buried_body_vertices"] = int(bur.sum())
    rows.append(r); print(json.dumps(r), flush=True)
    np.save(out.replace(".json", f"_x{c.frame}.npy"), c.x)
    Path(out).write_text(json.dumps({"clip": clip, "crease_ring": ring, "rows": rows}, indent=1))
t = time.time()
simulate_on_body(part, bodies[:T], bf, mat, 25.0, settings=ss, substeps=1, max_substeps=16, resume=ck, on_frame=on_frame)
print("total", time.time() - t)
