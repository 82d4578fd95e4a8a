"""Why a prepared capture's held-out simulation differs from the original's (issue 23, session 30).

    python benchmarks/prepare_drape.py --original W/runs/demo/original --prepared W/runs/demo/prepared \
        --material DEMO/capture/ground_truth/material.json [--frames 25] \
        [--results benchmarks/results/prepare_drape_demo_s30.json]

Two `physavatar run` folders (the original capture's and the prepared one's, as
``benchmarks/prepare_accuracy.py --run`` leaves them). Each avatar is held still in its frame-1
pose for ``--frames`` frames with the true material (animate, no motion), and the drop of the
garment's free part (vertices over 30 cm from a boundary vertex) is measured, for: the original
garment (and without its designed rest shape, when it has one); the prepared garment; the prepared garment
with the true boundary (its vertices within 2 cm of the original's boundary points); the prepared
garment on the true body. Plus the garments' open loops and their pieces above z = 1.2 m (the
straps). Writes a JSON with ``checks`` (reported, no target).
"""

from __future__ import annotations

import argparse
import datetime
import os
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _common import machine, write_result

FREE = 0.3  # [m] a garment vertex this far from every boundary vertex is "free"


def drop_mm(av, material, frames: int) -> float:
    """Mean z change [mm] of the free garment vertices after ``frames`` frames held still."""
    from scipy.spatial import cKDTree

    from physavatar.body.motion import Motion
    from physavatar.stages.animate import animate

    av.material = material
    mo = Motion("hold", av.fps, av.bone_names, np.repeat(av.rest_rotations[None], frames, 0),
                np.repeat(av.rest_translation[None], frames, 0))
    seq, _ = animate(av, mo, progress=False)
    t = av.template
    g = t.labels > 0
    free = cKDTree(t.vertices[t.boundary]).query(t.vertices[g])[0] > FREE
    return 1e3 * float((seq.vertices[-1] - seq.vertices[0])[g, 2][free].mean())


def garment_shape(t) -> dict:
    """Open loops of the garment (vertex counts, z range) and its pieces above z = 1.2 m."""
    import trimesh
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from physavatar.geometry import submesh

    ids, F = submesh(t.faces, t.labels > 0)
    V = t.vertices[ids]
    u, c = np.unique(np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), 1), axis=0, return_counts=True)
    e = u[c == 1]
    _, lab = connected_components(coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(len(V),) * 2), directed=False)
    on = np.unique(e)
    loops = sorted(([int((lab[on] == k).sum()), round(float(V[lab == k][:, 2].min()), 2),
                     round(float(V[lab == k][:, 2].max()), 2)] for k in np.unique(lab[on])), reverse=True)
    sub, Fs = submesh(F, V[:, 2] > 1.2)
    pieces = sorted(([len(p.vertices), round(float(p.vertices[:, 0].mean()), 2), round(float(p.vertices[:, 1].min()), 2),
                      round(float(p.vertices[:, 1].max()), 2)]
                     for p in trimesh.Trimesh(V[sub], Fs, process=False).split(only_watertight=False)), reverse=True)
    return {"open_loops_n_zmin_zmax": loops, "pieces_above_1.2m_n_xmean_ymin_ymax": pieces,
            "boundary_y_min_max": [round(float(t.vertices[t.boundary][:, 1].min()), 3),
                                   round(float(t.vertices[t.boundary][:, 1].max()), 3)]}


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--original", type=Path, required=True, help="the original capture's run folder")
    ap.add_argument("--prepared", type=Path, required=True, help="the prepared capture's run folder")
    ap.add_argument("--material", type=Path, required=True, help="the true material.json")
    ap.add_argument("--frames", type=int, default=25)
    ap.add_argument("--also", type=Path, action="append", default=[],
                    help="another prepared capture of the same body.npz (e.g. `prepare --labels` with the true "
                         "template): its template on the prepared avatar, dropped and described too")
    ap.add_argument("--only-prepared", action="store_true",
                    help="leave out the prepared avatar's variants (true boundary, true body): the original, the "
                         "prepared and each --also")
    ap.add_argument("--results", type=Path, default=HERE / "results" / "prepare_drape_demo_s30.json")
    args = ap.parse_args()
    from physavatar.capture import Template
    from physavatar.data.avatar import Avatar
    from physavatar.sim.material import Material
    from physavatar.stages.prepare.boundary import boundary_from_points

    load0 = os.getloadavg()
    mat = Material.load(args.material)
    orig = lambda: Avatar.load(args.original / "avatar")  # noqa: E731
    prep = lambda: Avatar.load(args.prepared / "avatar")  # noqa: E731
    to, tp = orig().template, prep().template
    drops = {}
    drops["original"] = drop_mm(orig(), mat, args.frames)
    if to.rest is not None:  # a designed rest shape (the demo's has none: rest = frame 1, as a prepared one)
        av = orig()
        av.template = Template(to.vertices, to.faces, to.labels, to.boundary, to.face_uvs, None)
        drops["original, rest = frame-1 shape"] = drop_mm(av, mat, args.frames)
    drops["prepared"] = drop_mm(prep(), mat, args.frames)
    if not args.only_prepared:
        av = prep()
        b = (tp.labels > 0) & boundary_from_points(tp.vertices, to.vertices[to.boundary], 0.02)
        av.template = Template(tp.vertices, tp.faces, tp.labels, b, tp.face_uvs, tp.rest)
        drops[f"prepared, true boundary ({int(b.sum())} vertices)"] = drop_mm(av, mat, args.frames)
        # the prepared garment on the original avatar's (true) body
        bo = to.labels == 0
        nb = int(bo.sum())
        gp = tp.labels > 0
        remap = -np.ones(len(tp.vertices), np.int64)
        remap[gp] = nb + np.arange(gp.sum())
        av = orig()
        av.template = Template(np.concatenate([to.vertices[bo], tp.vertices[gp]]),
                               np.concatenate([to.faces[bo[to.faces].all(1)], remap[tp.faces[gp[tp.faces].all(1)]]]),
                               np.r_[np.zeros(nb, np.int64), tp.labels[gp]], np.r_[np.zeros(nb, bool), tp.boundary[gp]],
                               None, None)
        drops["prepared garment on the true body"] = drop_mm(av, mat, args.frames)
    shapes = {"original": garment_shape(to), "prepared": garment_shape(tp)}
    from physavatar.capture import load_capture

    for other in args.also:
        t = load_capture(other).template
        if not np.allclose(t.vertices[t.labels == 0], tp.vertices[tp.labels == 0]):
            raise SystemExit(f"{other}: its body is not the prepared avatar's (give the same body.npz)")
        av = prep()
        av.template = t
        drops[f"prepared, template of {other}"] = drop_mm(av, mat, args.frames)
        shapes[str(other)] = garment_shape(t)
    for k, v in drops.items():
        print(f"{k:50s} free-part drop {v:7.1f} mm")
    result = {"benchmark": "prepare_drape", "date": datetime.datetime.now().isoformat(timespec="seconds"),
              "machine": machine(load0),
              "original": str(args.original), "prepared": str(args.prepared), "frames": args.frames,
              "free_part_drop_mm": drops, "garment": shapes,
              "checks": {f"drop/{k}": {"value": v, "target": "reported", "unit": "mm (mean z change, free part)",
                                       "pass": True} for k, v in drops.items()}}
    write_result(args.results, result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
