"""The strap joins' variants on a prepared excerpt (issue 23, session 31).

    python benchmarks/prepare_strap_variants.py --work W [--variants shortest,ring1,...] \
        [--results benchmarks/results/prepare_strap_variants_demo_s31.json]

``W``: a ``benchmarks/prepare_accuracy.py --frames N --work W --keep`` folder (its
``inputs/demo/no_template``, its fitted ``prepared/demo/no_template/body.npz`` and its
``excerpt`` with the truth). Each variant prepares the input again with that body given (no body
fit, about 20 s) and a ``segment.strap_evidence`` / ``segment.strap_widen`` setting, into
``W/strap_variants/NAME``, and is measured against the excerpt's truth as ``prepare_accuracy``
measures it (segmentation, boundary chosen -> true and true -> chosen, the template's garment),
plus where the joins' ways lie: in plan (x, y) against the true straps' footprint (the true
garment above z = 1.2 m, projected), against the true surface (body or cloth) and against the
true garment surface. The folders are what ``benchmarks/prepare_drape.py --also`` takes. Writes
a JSON with ``checks`` (reported, no target; the boundary's 2-cm target is checked).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import shutil
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _common import cpu_name

VARIANTS = {  # name: (strap_evidence, strap_widen)
    "shortest": (0.0, 0),  # session 30
    "evidence": (4.0, 0),
    "ring1": (0.0, 1),  # session 31's default
    "evidence_ring1": (4.0, 1),
    "ring2": (0.0, 2),
}


def ways(prepared: Path, excerpt: Path, evidence_weight: float) -> dict:
    """Where the joins' ways (their vertices outside the garment) lie against the truth: the
    joins found again on the first-frame mesh as ``garment_pieces`` finds them."""
    from physavatar.capture import load_capture
    from physavatar.files import load_npz
    from physavatar.geometry import submesh
    from physavatar.stages.prepare.gaps import close_gaps
    from physavatar.stages.prepare.mesh import surface_distance
    from physavatar.stages.prepare.segment import join_parts

    z = load_npz(prepared / "prepare" / "first_frame_mesh.npz")
    V, F, bridge = z["vertices"], z["faces"], z["bridge"]
    mask = join_parts((z["labels"] == 1) & ~bridge, F, bridge)
    _, _, info = close_gaps(mask, V, F, bridge, evidence=z["evidence"], evidence_weight=evidence_weight)
    way = [i for j in info for i in j["way"][1:-1]]
    if not way:
        return {"way_vertices": 0}
    tpl = load_capture(excerpt).template
    T = tpl.vertices
    ids, Fs = submesh(tpl.faces, (tpl.labels > 0) & (T[:, 2] > 1.2))
    gids, Fg = submesh(tpl.faces, tpl.labels > 0)
    P = V[way]
    plan = surface_distance(P * [1, 1, 0], T[ids] * [1, 1, 0], Fs)
    return {"way_vertices": len(way),
            "plan_off_true_straps_mm": {"mean": float(plan.mean() * 1e3), "max": float(plan.max() * 1e3)},
            "to_true_surface_mm_mean": float(surface_distance(P, T, tpl.faces).mean() * 1e3),
            "to_true_garment_mm_mean": float(surface_distance(P, T[gids], Fg).mean() * 1e3)}


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--work", type=Path, required=True, help="a prepare_accuracy.py --frames N --keep work folder")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--results", type=Path, default=HERE / "results" / "prepare_strap_variants_demo_s31.json")
    args = ap.parse_args()
    from prepare_accuracy import evaluate

    from physavatar.stages.prepare import PrepareConfig
    from physavatar.stages.prepare import run as prepare
    from physavatar.stages.prepare.config import SegmentConfig

    src = args.work / "inputs" / "demo" / "no_template"
    body = args.work / "prepared" / "demo" / "no_template" / "body.npz"
    excerpt = args.work / "excerpt"
    for p in (src, body, excerpt):
        if not p.exists():
            raise SystemExit(f"{p}: missing (run prepare_accuracy.py --frames N --work {args.work} --keep first)")
    given = args.work / "strap_variants" / "_input"
    shutil.rmtree(given, ignore_errors=True)
    shutil.copytree(src, given, copy_function=os.link)
    shutil.copy(body, given / "body.npz")
    load0 = os.getloadavg()
    out, checks = {}, {}
    for name in args.variants.split(","):
        ev, widen = VARIANTS[name]
        dst = args.work / "strap_variants" / name
        shutil.rmtree(dst, ignore_errors=True)
        prepare(given, out=dst, config=PrepareConfig(segment=SegmentConfig(strap_evidence=ev, strap_widen=widen)),
                progress=False)
        r = evaluate(excerpt, dst, masks_computed=False)
        rep = json.loads((dst / "prepare.json").read_text())
        out[name] = {"strap_evidence": ev, "strap_widen": widen, "folder": str(dst),
                     "segmentation": r["segmentation"], "boundary": r["boundary"],
                     "template": r["template"], "template_garment_to_true_mean_mm":
                     r["mesh"]["template_garment_to_true_mean_mm"], "clear": r["clear"],
                     "collider_crossings_frame0": r["collider_crossings_frame0"],
                     "joins": [{k: v for k, v in j.items() if k != "way"} for j in rep["numbers"]["strap_joins"]],
                     "ways": ways(dst, excerpt, ev)}
        print(name, json.dumps({k: out[name][k] for k in ("boundary", "template", "ways")}, default=float))
        checks[f"{name}/boundary_chosen_to_true_m"] = {"value": r["boundary"]["chosen_to_true_mean"],
                                                       "target": "<= 0.02", "unit": "m",
                                                       "pass": bool(r["boundary"]["chosen_to_true_mean"] <= 0.02)}
        checks[f"{name}/boundary_true_to_chosen_m"] = {"value": r["boundary"]["true_to_chosen_mean"],
                                                       "target": "reported", "unit": "m", "pass": True}
        checks[f"{name}/segmentation_accuracy"] = {"value": r["segmentation"]["accuracy"], "target": ">= 0.97",
                                                   "unit": "share of vertices",
                                                   "pass": bool(r["segmentation"]["accuracy"] >= 0.97)}
    result = {"benchmark": "prepare_strap_variants", "date": datetime.datetime.now().isoformat(timespec="seconds"),
              "machine": {"cores": os.cpu_count(), "cpu": cpu_name(), "load_average_start": list(load0),
                          "load_average_end": list(os.getloadavg())},
              "work": str(args.work), "variants": out, "checks": checks}
    args.results.parent.mkdir(parents=True, exist_ok=True)
    args.results.write_text(json.dumps(result, indent=2, default=float) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
