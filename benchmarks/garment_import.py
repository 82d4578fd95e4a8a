"""Garments made by another tool, fitted onto Anny and simulated (issue 24 parts 3-6).

The four Berkeley Garment Library garments in ../shared/data/garments (dress3, skirt, tshirt,
pants: NAME-iso-w.obj world drape on the Library's mannequin + NAME-iso-m.obj rest panels) are
read with their rest shape and seams (physavatar.garment.files), fitted onto Anny's rest pose
(garment_sim.fit_on_body: aligned, then settled on a body that grows from a shrunk one), given
their automatic boundary (garment.boundary) and simulated on the built-in walk and dance and
both CMU clips (each reached from the rest pose by a warm-up transition, simulated and checked
too). Every simulated frame is checked: finite, free of garment-body intersections (ipctk),
seams closed (largest distance across a seam pair < 2 mm); the strain against the rest shape
(largest |σ − 1| per triangle, area-weighted mean) at the first frame < 5 %.

    python benchmarks/garment_import.py            # short clips (0.4 s each, after a 1 s warm-up)
    python benchmarks/garment_import.py --full     # 4 s built-in motions, whole CMU clips
    python benchmarks/garment_import.py --garments skirt --motions walk
    python benchmarks/garment_import.py --garments tshirt --keep --cache /tmp/gi --previews /tmp/gi/previews

Writes benchmarks/results/garment_import.json (figures, seconds per frame, ``checks``); ``--keep``
keeps the garments of an earlier run that this one does not measure (two runs side by side, one
per garment, end in one file); ``--cache DIR`` stores each fitted garment (reused when there) and
each simulated sequence; ``--previews DIR`` writes a picture of every fit and a video and a
picture of every simulated clip (front and side; body skin-coloured, garment blue), looked at.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import time
from pathlib import Path

import numpy as np
from _common import cpu_name

ROOT = Path(__file__).resolve().parent
DATA = ROOT.parent.parent / "shared" / "data"
GARMENTS = ("skirt", "pants", "dress3", "tshirt")
MOTIONS = ("walk", "dance", "cmu_131_01.bvh", "cmu_131_03.bvh")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--full", action="store_true", help="whole clips (4 s built-ins, whole CMU clips)")
    ap.add_argument("--garments", nargs="*", default=list(GARMENTS))
    ap.add_argument("--motions", nargs="*", default=list(MOTIONS))
    ap.add_argument("--material", default="cotton")
    ap.add_argument("--warmup", type=float, default=1.0,
                    help="seconds of transition from the rest pose to a clip's first pose (simulate's default)")
    ap.add_argument("--data", default=str(DATA))
    ap.add_argument("--out", default=str(ROOT / "results" / "garment_import.json"))
    ap.add_argument("--keep", action="store_true", help="keep other garments' figures already in --out")
    ap.add_argument("--cache", default=None, help="folder for fitted garments (reused) and simulated sequences")
    ap.add_argument("--previews", default=None, help="folder for fit pictures and clip videos")
    args = ap.parse_args()

    from physavatar.body import BodyModel
    from physavatar.body.load import load_motion, with_arm_clearance
    from physavatar.errors import PhysavatarError
    from physavatar.garment.boundary import arm_vertices, auto_boundary
    from physavatar.garment.files import load_garment
    from physavatar.garment_sim import GarmentPart, boundary_targets, fit_on_body, rest_strain, simulate_on_body
    from physavatar.sim import SimSettings, preset
    from physavatar.sim.contact import ContactScene
    from physavatar.sim.mesh import ClothTopology
    from physavatar.sim.stitch import seam_gaps
    from physavatar.stages.animate import transition

    data = Path(args.data)
    fps = 25.0
    seconds, warmup = (4.0, args.warmup) if args.full else (0.4, args.warmup)
    material = preset(args.material)
    settings = SimSettings(integrator=material.integrator)
    body = BodyModel(topology="collider")
    load0 = os.getloadavg()
    garments = {}
    all_ok = {"finite_and_intersection_free": True, "strain_first_frame": True, "seams_closed": True}
    for name in args.garments:
        path = data / "garments" / f"{name}-iso-w.obj"
        if not path.exists():
            print(f"{path} missing: skipped")
            continue
        gm = load_garment(path)
        t0 = time.time()
        cached = Path(args.cache) / f"fit_{name}.npz" if args.cache else None
        try:
            if cached is not None and cached.exists():
                z = np.load(cached, allow_pickle=False)
                fitted = GarmentPart(np.arange(len(z["x"])), z["x"], z["faces"], z["boundary"], z["rest"], z["seams"])
                fit = json.loads(str(z["report"]))
            else:
                fitted, fit = fit_on_body(gm, body, material, settings)
                fit["fit_seconds"] = round(time.time() - t0, 1)
                if cached is not None:
                    cached.parent.mkdir(parents=True, exist_ok=True)
                    np.savez(cached, x=fitted.vertices, faces=fitted.faces, boundary=fitted.boundary,
                             rest=fitted.rest, seams=fitted.seams, report=json.dumps(fit, default=float))
        except PhysavatarError as e:  # reported, and a failed check
            print(f"{name}: {e}", flush=True)
            garments[name] = {"fit_error": str(e)}
            all_ok["finite_and_intersection_free"] = False
            write(args, garments, all_ok, load0, material, settings, fps, seconds, warmup)
            continue
        fit_s = fit.get("fit_seconds", time.time() - t0)
        if args.previews:
            preview(Path(args.previews) / f"{name}_fit.png", body.rest_vertices, body.faces, fitted.vertices,
                    fitted.faces, f"{name} fitted on Anny's rest pose")
        fitted.boundary, brep = auto_boundary(fitted.vertices, fitted.faces, body.rest_vertices, body.faces,
                                              avoid=arm_vertices(body))
        area = ClothTopology.build(fitted.rest_shape, fitted.faces).face_area
        entry = {"vertices": len(gm.vertices), "faces": len(gm.faces), "panels": len(np.unique(gm.panels())),
                 "seam_pairs": len(gm.seams), "rest_source": gm.rest_source, "fit": fit,
                 "fit_seconds": round(fit_s, 1), "boundary": brep, "motions": {}}
        print(f"{name}: {len(gm.vertices)} vertices, {len(gm.seams)} seam pairs; fitted in {fit_s:.0f} s "
              f"(grade {fit['alignment']['grade']}, strain {fit['strain_mean'] * 100:.2f} %), "
              f"{brep['vertices']} boundary vertices", flush=True)
        garments[name] = entry
        for mname in args.motions:
            spec = str(data / "motions" / mname) if mname.endswith(".bvh") else mname
            try:
                mot = load_motion(spec, fps, seconds)  # a BVH clip comes whole: cut below unless --full
            except Exception as e:  # noqa: BLE001 - reported, not fatal to the other motions
                entry["motions"][mname] = {"error": str(e)}
                continue
            n = len(mot.rotations) if args.full else min(len(mot.rotations), int(round(seconds * fps)) + 1)
            mot, _ = with_arm_clearance(mot, spec, body, 0.03)  # as `simulate` does for a .bvh clip
            rots, trs = mot.rotations[:n], mot.root_translation[:n]
            trs = trs - trs[0] * np.array([1.0, 1.0, 0.0])  # the clip starts where the body stands
            n_warm = max(2, int(round(warmup * fps)))
            wr, wt = transition(np.zeros_like(rots[0]), np.zeros(3), rots[0], trs[0], n_warm)
            rots, trs = np.concatenate([wr, rots]), np.concatenate([wt, trs])
            bodies = body.pose(rots, trs).vertices
            # what simulate_on_body does to the boundary's targets (garment.unfold_targets, keep_clear), reported
            _, targets_report = boundary_targets(fitted, bodies, body.faces, settings.dhat)
            lifted, unfolded = targets_report["keep_clear"], targets_report["unfold"]
            t0 = time.time()
            X = simulate_on_body(fitted, bodies, body.faces, material, fps, settings=settings)
            secs = time.time() - t0
            scene = ContactScene(fitted.rest_shape, fitted.faces, bodies[0], body.faces, settings.dhat)
            bad = [f for f in range(len(X)) if not np.all(np.isfinite(X[f]))
                   or scene.has_intersections(np.vstack([X[f], bodies[f]]))]
            gaps = np.array([seam_gaps(X[f], fitted.seams).max() if len(fitted.seams) else 0.0 for f in range(len(X))])
            s0 = rest_strain(X[n_warm], fitted.rest_shape, fitted.faces)  # the clip's first frame
            strain_first = float(np.sum(s0 * area) / area.sum())
            res = {"frames": len(X), "warmup_frames": n_warm, "seconds_per_frame": round(secs / (len(X) - 1), 2),
                   "bad_frames": bad, "seam_gap_max_mm": round(float(gaps.max()) * 1000, 4),
                   "strain_first_frame_mean": round(strain_first, 4),
                   "strain_first_frame_p95": round(float(np.percentile(s0, 95)), 4),
                   "boundary_lift": {"floor_mm": round(1e3 * lifted["floor_m"], 4), "frames": lifted["frames_lifted"],
                                     "max_mm": round(1e3 * lifted["max_lift_m"], 4),
                                     "failed_frames": lifted["failed_frames"]},
                   "boundary_unfold": {"frames_crossing": unfolded["frames_crossing"],
                                       "frames_changed": unfolded["frames_changed"],
                                       "max_mm": round(1e3 * unfolded["max_change_m"], 4)}}
            entry["motions"][mname] = res
            tag = f"{name}_{Path(mname).stem}"
            if args.cache:
                np.savez_compressed(Path(args.cache) / f"seq_{tag}.npz", X=X.astype(np.float32),
                                    bodies=bodies.astype(np.float32), faces=fitted.faces, body_faces=body.faces)
            if args.previews:
                video(Path(args.previews) / f"{tag}.mp4", bodies, body.faces, X, fitted.faces, tag, fps, bad)
            write(args, garments, all_ok, load0, material, settings, fps, seconds, warmup)  # after every clip
            all_ok["finite_and_intersection_free"] &= not bad
            all_ok["strain_first_frame"] &= strain_first < 0.05
            all_ok["seams_closed"] &= bool(gaps.max() < 0.002)
            print(f"  {mname}: {len(X)} frames, {res['seconds_per_frame']} s/frame, bad {bad}, "
                  f"seam gap {res['seam_gap_max_mm']} mm, strain {strain_first * 100:.2f} %", flush=True)
        garments[name] = entry
        write(args, garments, all_ok, load0, material, settings, fps, seconds, warmup)  # after every garment


def _draw(ax, meshes, view, box):
    """Painter's algorithm (faces far to near, Lambert-shaded) of meshes [(V, F, rgb, cloth)] seen
    from the front (view 0: from -y) or the side (1: from +x), in the box (centre [3], half-size).
    A body triangle is sorted by its farthest corner, a cloth triangle by its centre 5 mm nearer:
    the collider's triangles are large, the cloth lies a millimetre or two on them."""
    from matplotlib.collections import PolyCollection

    ua, va, da, sgn = [(0, 2, 1, 1.0), (1, 2, 0, -1.0)][view]
    light = np.array([0.3, -0.6, 0.75]) / np.linalg.norm([0.3, -0.6, 0.75])
    polys, depth, cols = [], [], []
    for V, F, col, cloth in meshes:
        tri = V[F]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-12
        polys.append(tri[:, :, [ua, va]])
        d = sgn * tri[:, :, da]
        depth.append(d.mean(1) - 0.005 if cloth else d.max(1))
        cols.append(np.clip(np.asarray(col)[None] * (0.35 + 0.65 * np.abs(n @ light)[:, None]), 0, 1))
    P, D, C = np.concatenate(polys), np.concatenate(depth), np.concatenate(cols)
    o = np.argsort(-D)
    ax.add_collection(PolyCollection(P[o], facecolors=C[o], edgecolors="none", antialiased=False))
    c, r = box
    ax.set_xlim(c[ua] - r, c[ua] + r)
    ax.set_ylim(c[va] - r, c[va] + r)
    ax.set_aspect("equal")
    ax.axis("off")


def _frames(bodies, body_faces, X, faces, title, bad=()):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    allv = np.concatenate([bodies.reshape(-1, 3), X.reshape(-1, 3)])
    lo, hi = allv.min(0), allv.max(0)
    box = (0.5 * (lo + hi), 0.55 * float((hi - lo).max()))
    fig, axes = plt.subplots(1, 2, figsize=(6.4, 3.6), dpi=100)
    out = []
    for f in range(len(X)):
        for k, ax in enumerate(axes):
            ax.clear()
            _draw(ax, [(bodies[f], body_faces, (0.80, 0.66, 0.55), False), (X[f], faces, (0.30, 0.50, 0.85), True)],
                  k, box)
        fig.suptitle(f"{title}  frame {f}" + ("  CROSSES" if f in bad else ""), fontsize=8)
        fig.canvas.draw()
        out.append(np.asarray(fig.canvas.buffer_rgba())[..., :3].copy())
    plt.close(fig)
    return out


def preview(path, body_vertices, body_faces, x, faces, title):
    """A PNG of a garment on a body (front and side)."""
    import imageio.v2 as imageio

    path.parent.mkdir(parents=True, exist_ok=True)
    imageio.imwrite(path, _frames(body_vertices[None], body_faces, x[None], faces, title)[0])


def video(path, bodies, body_faces, X, faces, title, fps, bad):
    """An MP4 of a simulated clip and a PNG of its last frame."""
    import imageio.v2 as imageio

    from physavatar.body.preview import write_video

    path.parent.mkdir(parents=True, exist_ok=True)
    frames = _frames(bodies, body_faces, X, faces, title, bad)
    write_video(path, frames, fps)
    imageio.imwrite(path.with_suffix(".png"), frames[-1])


def write(args, garments, all_ok, load0, material, settings, fps, seconds, warmup):
    """benchmarks/results/garment_import.json (atomic): what has been measured so far (with
    ``--keep``, the other garments' figures already there too)."""
    load1 = os.getloadavg()
    out = Path(args.out)
    if args.keep and out.exists():
        old = json.loads(out.read_text()).get("figures", {})
        # a garment run again keeps the motions of the earlier run that this one did not measure
        garments = {**{k: v for k, v in old.items() if k not in garments},
                    **{k: {**v, "motions": {**old.get(k, {}).get("motions", {}), **v.get("motions", {})}}
                       if "motions" in v else v for k, v in garments.items()}}
        all_ok = {"finite_and_intersection_free": all(not m.get("bad_frames", [1]) for g in garments.values()
                                                      for m in g.get("motions", {}).values())
                  and all("fit_error" not in g for g in garments.values()),
                  "strain_first_frame": all(m.get("strain_first_frame_mean", 1.0) < 0.05 for g in garments.values()
                                            for m in g.get("motions", {}).values()),
                  "seams_closed": all(m.get("seam_gap_max_mm", 1e9) < 2.0 for g in garments.values()
                                      for m in g.get("motions", {}).values())}
    result = {
        "benchmark": "garment_import",
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "machine": {"cores": os.cpu_count(), "cpu": cpu_name(), "gpu": None,
                    "load_average_1_5_15min_start": [round(v, 2) for v in load0],
                    "load_average_1_5_15min_end": [round(v, 2) for v in load1]},
        "config": {"garments": sorted(garments), "motions": args.motions, "full": args.full, "fps": fps,
                   "clip_seconds": None if args.full else seconds, "warmup_seconds": warmup,
                   "material": material.to_dict(), "dhat": settings.dhat, "friction": settings.friction},
        "figures": garments,
        "checks": {
            "finite_and_intersection_free": {"value": all_ok["finite_and_intersection_free"], "target": "every frame",
                                             "pass": all_ok["finite_and_intersection_free"]},
            "strain_first_frame": {"value": max((m["strain_first_frame_mean"] for g in garments.values()
                                                 for m in g.get("motions", {}).values() if "strain_first_frame_mean" in m),
                                                default=None),
                                   "target": "< 0.05", "unit": "area-weighted mean of max |sigma - 1|",
                                   "pass": all_ok["strain_first_frame"]},
            "seams_closed": {"value": max((m["seam_gap_max_mm"] for g in garments.values()
                                           for m in g.get("motions", {}).values() if "seam_gap_max_mm" in m), default=None),
                             "target": "< 2", "unit": "mm", "pass": all_ok["seams_closed"]},
        },
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps(result, indent=2, default=float) + "\n")
    tmp.replace(out)
    print(json.dumps(result["checks"], indent=1), flush=True)


if __name__ == "__main__":
    main()
