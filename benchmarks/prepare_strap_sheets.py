"""Where a prepared template puts the demo dress's straps and holds (issue 23, session 37).

    python benchmarks/prepare_strap_sheets.py --original W/excerpt --prepared NAME=P [NAME=P ...] \
        [--heldout NAME=JSON ...] [--results benchmarks/results/prepare_strap_sheets_s37.json]

For each prepared capture of ``--original`` (its first frame): the true strap points (the original
template's garment vertices above ``--strap-z`` standing more than ``--off`` from its body) to the
prepared template's garment surface and to its refined first-frame surface (quartiles, mm); the
chosen holds against the true ones (mean distance of each true hold to the nearest chosen, the
number missed by more than 2 cm, those behind the shoulder, y > ``--back-y``). ``--heldout``
attaches a ``prepare_heldout_parts.py`` results JSON's Chamfer to a case. Writes a results JSON
with ``checks`` (reported).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _common import machine, write_result  # noqa: E402


def true_straps(original: Path, strap_z: float, off: float):
    """(the true template, [n, 3] strap points standing off its body, [m, 3] true holds)."""
    from physavatar.capture import load_capture
    from physavatar.geometry import MeshQuery

    t = load_capture(original).template
    V, F, lab = np.asarray(t.vertices), t.faces, t.labels
    d = MeshQuery(V, F[(lab[F] == 0).all(1)]).closest(V, max_dist=0.3)[0]
    return t, V[(lab > 0) & (V[:, 2] > strap_z) & (d > off)], V[np.asarray(t.boundary).astype(bool)]


def strap_case(prepared: Path, straps: np.ndarray, holds: np.ndarray, back_y: float) -> dict:
    from scipy.spatial import cKDTree

    from physavatar.capture import load_capture
    from physavatar.files import load_npz
    from physavatar.geometry import MeshQuery

    t = load_capture(prepared).template
    V, F = np.asarray(t.vertices), t.faces
    to_garment = MeshQuery(V, F[(t.labels[F] > 0).all(1)]).closest(straps, max_dist=0.3)[0] * 1000
    ff = load_npz(prepared / "prepare" / "first_frame_mesh.npz")
    to_surface = MeshQuery(ff["vertices"], ff["faces"]).closest(straps, max_dist=0.3)[0] * 1000
    B = V[np.asarray(t.boundary).astype(bool)]
    d = cKDTree(B).query(holds)[0]
    back = holds[:, 1] > back_y
    q = lambda x: [round(float(v), 2) for v in np.percentile(x, [25, 50, 75, 90])]  # noqa: E731
    return {"strap_points_to_template_garment_mm_q25_50_75_90": q(to_garment),
            "strap_points_to_refined_surface_mm_q25_50_75_90": q(to_surface),
            "holds": int(len(B)), "true_holds": int(len(holds)),
            "true_to_chosen_mean_cm": float(d.mean() * 100), "true_missed_over_2cm": int((d > 0.02).sum()),
            "true_behind_shoulder": int(back.sum()), "behind_shoulder_missed_over_2cm": int((d[back] > 0.02).sum())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--original", type=Path, required=True, help="the excerpt with its true template")
    ap.add_argument("--prepared", nargs="+", required=True, help="NAME=FOLDER, prepared captures of it")
    ap.add_argument("--heldout", nargs="*", default=[], help="NAME=JSON, prepare_heldout_parts.py results")
    ap.add_argument("--strap-z", type=float, default=1.2)
    ap.add_argument("--off", type=float, default=0.008)
    ap.add_argument("--back-y", type=float, default=0.03)
    ap.add_argument("--results", type=Path)
    args = ap.parse_args()
    load0 = os.getloadavg()
    _, straps, holds = true_straps(args.original, args.strap_z, args.off)
    cases = {}
    for item in args.prepared:
        name, folder = item.split("=", 1)
        cases[name] = strap_case(Path(folder), straps, holds, args.back_y)
        print(name, json.dumps(cases[name]))
    for item in args.heldout:
        name, path = item.split("=", 1)
        v = json.loads(Path(path).read_text())["variants"]["prepared"]
        cases.setdefault(name, {})["heldout_garment_cd_x1e3"] = v["chamfer_x1e3"]
        cases[name]["heldout_fscore_1cm"] = v["fscore@1cm"]
    checks = {f"{k}/strap_points_to_template_garment_median_mm": {
        "value": c["strap_points_to_template_garment_mm_q25_50_75_90"][1], "target": "reported", "unit": "mm",
        "pass": None} for k, c in cases.items() if "strap_points_to_template_garment_mm_q25_50_75_90" in c}
    result = {"benchmark": "prepare_strap_sheets", "date": datetime.datetime.now().isoformat(timespec="seconds"),
              "machine": machine(load0), "original": str(args.original), "strap_points": int(len(straps)),
              "cases": cases, "checks": checks}
    if args.results:
        write_result(args.results, result)


if __name__ == "__main__":
    main()
