"""``python -m physavatar.garment KIND [KIND ...] [--edge-length M] [--out FILE]``: build garments
for the average Anny body and print their quality figures (docs/garments.md)."""

from __future__ import annotations

import argparse
import time
from pathlib import Path


def main(argv=None) -> int:
    from ..body.model import BodyModel
    from .garment import GARMENTS, make_garment

    ap = argparse.ArgumentParser(prog="python -m physavatar.garment", description=__doc__)
    ap.add_argument("kinds", nargs="+", choices=sorted(GARMENTS))
    ap.add_argument("--edge-length", type=float, default=0.02, help="target edge length (m)")
    ap.add_argument("--clearance", type=float, default=0.008, help="body-cloth gap where fitted (m)")
    ap.add_argument("--out", type=Path, help=".ply or .npz; with several kinds the kind is appended to the name")
    a = ap.parse_args(argv)
    body = BodyModel(topology="full")
    cols = ("n_vertices", "n_faces", "min_angle_deg", "max_angle_deg", "area_ratio", "mean_edge", "min_clearance_m")
    print(f"{'garment':8s} " + " ".join(f"{c:>15s}" for c in cols) + f" {'boundary':>9s} {'seconds':>8s}")
    for kind in a.kinds:
        t = time.perf_counter()
        g = make_garment(kind, body, edge_length=a.edge_length, clearance=a.clearance)
        dt = time.perf_counter() - t
        q = g.quality()
        print(f"{kind:8s} " + " ".join(f"{q[c]:>15.4g}" for c in cols) + f" {int(g.boundary.sum()):>9d} {dt:>8.1f}")
        if a.out is not None:
            out = a.out if len(a.kinds) == 1 else a.out.with_name(f"{a.out.stem}_{kind}{a.out.suffix}")
            g.save(out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
