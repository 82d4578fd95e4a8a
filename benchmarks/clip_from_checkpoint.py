"""Frames F0+1..F1 of a whole-clip run from its exact checkpoint (docs/simulation.md "Session 23"), on
the body of CLIP_RUNS/CLIP-full.npz: per frame lag, body crossing (ipctk, whole body and its outer
surface), cloth vertices inside the body, s/frame. Checkpoints: CLIP_RUNS/states/state_FFFFFF.npz
(copies of a run's frames/state.npz). BLEND=n and OLD=motion.npz: the checkpoint lies on OLD's body;
move that body to this one's pose F0 over n frames first (a corrected motion).

    CLIP_RUNS=DIR [BLEND=5 OLD=old.npz] python benchmarks/clip_from_checkpoint.py cmu-walk F0 F1 OUT.json

Run without OMP_NUM_THREADS=1 when the checkpoint's run had none: the thread count changes the
garment's and body's last bits, and the checkpoint's cloth then crosses itself.
"""
import dataclasses, json, os, sys, time
from pathlib import Path
import numpy as np
from physavatar.data.material import resolve_material
from physavatar.garment_sim import simulate_on_body
from physavatar.sim import SimSettings
from physavatar.sim.contact import ContactScene
from physavatar.sim.crease import buried_vertices, winding_numbers
from physavatar.sim.simulate import Checkpoint
from physavatar.stages import simulate as S

clip, f0, f1, out = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
root = os.environ["CLIP_RUNS"]
cfg = S.SimulateConfig(edge_length=0.02, duration=4.0, warmup=1.0, preview=False, max_substeps=16, self_contact=True)
mat = resolve_material(cfg.material, option="--material")
ss = SimSettings(integrator=mat.integrator)
part, bodies, bf, n_warm, _, _ = S._on_motion("dress", f"{root}/{clip}-full.npz", 25.0, cfg, mat, ss, None)
part, _ = S.repaired_start(part, bodies[0], bf, ss.dhat, cfg.repair_limit, "dress")
exclude = part.contact_exclusions()
ss = dataclasses.replace(ss, self_contact=S.self_contact_possible(part.vertices, part.faces, ss.dhat, exclude))
BLEND = int(os.environ.get("BLEND", "0"))
if BLEND:  # the checkpoint lies on OLD's body at f0: move that body to this one's over BLEND frames first
    _, old_bodies, _, _, _, _ = S._on_motion("dress", os.environ["OLD"], 25.0, cfg, mat, ss, None)
    a = (np.arange(1, BLEND + 1) / BLEND)[:, None, None]
    a = a * a * (3 - 2 * a)
    blend = (1 - a) * old_bodies[f0] + a * bodies[f0]
    bodies = np.concatenate([old_bodies[:f0 + 1], blend, bodies[f0 + 1:]])
    f1 += BLEND
ck = Checkpoint.load(f"{root}/states/state_{f0:06d}.npz")
assert ck.frame == f0, ck.frame
sc = ContactScene(part.rest_shape, part.faces, bodies[0], bf, ss.dhat)
X = np.vstack([ck.x, bodies[f0]])  # with BLEND: the old body (the checkpoint's own)
start = {"frame": f0, "intersects_body": bool(sc.has_intersections(X)), "min_distance_mm": 1e3 * float(np.sqrt(max(sc.min_distance(X), 0))),
         "cloth_inside_body": int(np.sum(winding_numbers(ck.x, bodies[f0], bf) > 0.5))}
print("start", json.dumps(start), flush=True)
rows = []
def on_frame(c, r):
    t = time.time()
    r = dict(r); X = np.vstack([c.x, bodies[c.frame]])
    r["clip_frame"] = c.frame - BLEND if c.frame > f0 + BLEND else None  # the motion's simulated frame
    r["intersects_body"] = bool(sc.has_intersections(X))
    bur = buried_vertices(bodies[c.frame], bf)
    so = ContactScene(part.rest_shape, part.faces, bodies[0], bf[~bur[bf].any(axis=1)], ss.dhat)
    r["intersects_outer_surface"] = bool(so.has_intersections(X))
    r["cloth_inside_body"] = int(np.sum(winding_numbers(c.x, bodies[c.frame], bf) > 0.5))
    r["buried_body_vertices"] = int(bur.sum())
    r["wall_s"] = round(time.time() - T0[0], 1); T0[0] = time.time()
    rows.append(r); print(json.dumps(r, default=float), flush=True)
    c.save(out.replace(".json", f"_state{c.frame}.npz"))
    Path(out).write_text(json.dumps({"clip": clip, "root": root, "start": start, "rows": rows}, indent=1, default=float))
    T0[0] += time.time() - t
T0 = [time.time()]
simulate_on_body(part, bodies[:f1 + 1], bf, mat, 25.0, settings=ss, substeps=1, max_substeps=16, resume=ck, on_frame=on_frame)
print("total", time.time() - T0[0])
