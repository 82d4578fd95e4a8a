"""The layered starts of `simulate --over` (garment_sim.layered at Anny's rest pose), measured
by ipctk: the pairs of primitives within d̂ (between the layers and within each), whether the
outer garment crosses itself, the least distance between the layers, and how far and how
unevenly (edge-length ratio) the push over moved the outer garment. A start with any pair within
d̂ is refused by `simulate --over` (docs/simulation.md, "Session 31").

    PYTHONPATH=src python benchmarks/layer_starts.py [--out benchmarks/results/layer_starts.json]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import ipctk  # noqa: E402
import numpy as np  # noqa: E402

from _common import cpu_name  # noqa: E402
from physavatar.body import BodyModel  # noqa: E402
from physavatar.garment import make_garment  # noqa: E402
from physavatar.garment_sim import GarmentPart, layered  # noqa: E402
from physavatar.sim import SimSettings  # noqa: E402

CASES = {"layers-walk": ("skirt", "tshirt"), "layers-dance": ("skirt", "dress")}  # motion_suite.LAYERED's garments


def _pairs(V, F, layer, dist):
    """(distance, between layers?) of every primitive pair of the layered mesh within ``dist``."""
    F = np.asarray(F, np.int32)
    mesh = ipctk.CollisionMesh(V, ipctk.edges(F), F)
    c = ipctk.NormalCollisions()
    c.build(mesh, V, dist)
    out = []
    for k in range(len(c)):
        ids = [i for i in c[k].vertex_ids(mesh.edges, F) if i >= 0]
        out.append((float(np.sqrt(c[k].compute_distance(c[k].dof(V, mesh.edges, F)))), len(set(layer[ids])) > 1))
    return out


def measure(inner: str, outer: str, edge: float, body: BodyModel, dhat: float) -> dict:
    gs = [make_garment(n, body, edge_length=edge) for n in (inner, outer)]
    part = layered([GarmentPart(np.arange(len(g.vertices)), g.vertices, g.faces, np.flatnonzero(g.boundary)) for g in gs],
                   body.rest_vertices, body.faces)
    near = _pairs(part.vertices, part.faces, part.layer, dhat)
    wide = _pairs(part.vertices, part.faces, part.layer, 0.01)
    V0, F = gs[1].vertices, gs[1].faces.astype(np.int32)
    V = part.vertices[part.layer == 1]
    E = ipctk.edges(F)
    ratio = np.linalg.norm(V[E[:, 0]] - V[E[:, 1]], axis=1) / np.linalg.norm(V0[E[:, 0]] - V0[E[:, 1]], axis=1)
    move = np.linalg.norm(V - V0, axis=1)
    return {"inner": inner, "outer": outer, "edge_length": edge, "vertices": len(part.vertices),
            "pairs_within_dhat": len(near), "pairs_within_dhat_between_layers": sum(b for _, b in near),
            "least_distance_between_layers_mm": round(1e3 * min((d for d, b in wide if b), default=np.inf), 3),
            "outer_crosses_itself": bool(ipctk.has_intersections(ipctk.CollisionMesh(V, E, F), V)),
            "outer_max_move_mm": round(1e3 * float(move.max()), 1), "outer_moved_vertices": int((move > 0).sum()),
            "outer_edge_length_ratio": [round(float(ratio.min()), 3), round(float(ratio.max()), 3)]}


def _commit() -> str | None:
    """The commit of the physavatar imported (None outside git: e.g. an exported older tree)."""
    import subprocess

    import physavatar

    r = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], cwd=Path(physavatar.__file__).parent,
                       capture_output=True, text=True, check=False)
    return r.stdout.strip() or None


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--edges", type=float, nargs="*", default=[0.04, 0.02])
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent / "results" / "layer_starts.json"))
    args = ap.parse_args()
    body, dhat = BodyModel(topology="collider"), SimSettings().dhat
    rows = {}
    for edge in args.edges:
        for name, (inner, outer) in CASES.items():
            rows[f"{name} {edge:g}"] = r = measure(inner, outer, edge, body, dhat)
            print(f"{name:13s} {edge:5.2f} m  pairs within d̂ {r['pairs_within_dhat']:4d}  outer crosses itself "
                  f"{r['outer_crosses_itself']!s:5s}  largest move {r['outer_max_move_mm']:5.1f} mm  edge ratio "
                  f"{r['outer_edge_length_ratio']}", flush=True)
    checks = {f"{k}:pairs_within_dhat": {"value": r["pairs_within_dhat"], "target": "0", "pass": r["pairs_within_dhat"] == 0}
              for k, r in rows.items()}
    checks |= {f"{k}:outer_crosses_itself": {"value": r["outer_crosses_itself"], "target": False,
                                             "pass": not r["outer_crosses_itself"]} for k, r in rows.items()}
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({
        "benchmark": "layer_starts", "code_commit": _commit(), "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "machine": {"cores": os.cpu_count(), "cpu": cpu_name(), "load_average_1_5_15min": [round(v, 2) for v in os.getloadavg()]},
        "config": {"dhat": dhat, "edges": args.edges}, "figures": rows, "checks": checks}, indent=1))
    print(f"{sum(c['pass'] for c in checks.values())}/{len(checks)} checks pass")


if __name__ == "__main__":
    main()
