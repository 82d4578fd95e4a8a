"""Collider self-intersection per part pair (docs/simulation.md "Session 23"): buried body vertices
(winding number > 1), their depth below the outer surface and the part that encloses them; and the
forearms' distance to trunk and thighs, on simulated frames F0..F1 (warm-up of 1 s included) of a
motion as `simulate` poses it.

    python benchmarks/collider_overlap.py MOTION.npz F0 F1 OUT.json
"""
import json, sys, time
import numpy as np
from collections import defaultdict
from scipy.spatial import cKDTree
from physavatar.body import BodyModel
from physavatar.body.load import load_motion
from physavatar.body.motion import bone_vertex_mask
from physavatar.sim.crease import buried_vertices
from physavatar.geometry.closest import MeshQuery
from physavatar.stages.simulate import transition

motion, f0, f1, out = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
body = BodyModel(topology="collider"); names = body.bone_names; F = np.asarray(body.faces)
m = load_motion(motion, 25.0, 4.0, body=body)
rots, trs = m.rotations, m.root_translation
n_warm = max(2, int(round(1.0 * 25)))
wr, wt = transition(np.zeros_like(rots[0]), np.zeros(3), rots[0], trs[0], n_warm)
rots, trs = np.concatenate([wr, rots]), np.concatenate([wt, trs])
GROUPS = {"trunk": ("root", "pelvis", "spine"), "thigh": ("upperleg",), "shin": ("lowerleg", "foot", "toe"),
          "uparm": ("upperarm", "clavicle", "shoulder"), "forearm": ("lowerarm", "wrist", "hand", "finger", "thumb", "metacarpal")}
lab = np.array(["other"] * len(body.rest_vertices), dtype=object)
for g, pre in GROUPS.items():
    for side in ("", ".L", ".R"):
        sel = bone_vertex_mask(body, [n for n in names if n.startswith(pre) and (n.endswith(side) if side else not n.endswith((".L", ".R")))])
        lab[sel & (lab == "other")] = g + side
rows = []
for f in range(f0, f1 + 1):
    B = body.pose(rots[f:f + 1], trs[f:f + 1]).vertices[0]
    bur = buried_vertices(B, F)
    ids = np.flatnonzero(bur)
    pairs = defaultdict(lambda: [0, 0.0])
    if len(ids):
        keep = ~bur[F].any(axis=1)
        d, face, _, _ = MeshQuery(B, F[keep], spacing=0.02).closest(B[ids])
        other = lab[F[keep][face][:, 0]]
        for i, dd, o in zip(ids, d, other):
            k = f"{lab[i]} in {o}"
            pairs[k][0] += 1; pairs[k][1] = max(pairs[k][1], 1e3 * dd)
    r = {"frame": f, "buried": int(len(ids)), "pairs": {k: [v[0], round(v[1], 1)] for k, v in sorted(pairs.items(), key=lambda kv: -kv[1][1]) if v[1] >= 2}}
    for side in ("L", "R"):
        arm = (lab == f"forearm.{side}")
        for tgt in ("trunk", f"thigh.{side}"):
            r[f"forearm.{side}-{tgt}_mm"] = round(1e3 * cKDTree(B[lab == tgt]).query(B[arm])[0].min(), 1)
    rows.append(r); print(json.dumps(r), flush=True)
json.dump({"motion": motion, "rows": rows}, open(out, "w"), indent=1)
