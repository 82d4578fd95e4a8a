"""Which part of the fitted body makes the original garment's held-out Chamfer (issue 23, session 34).

    python benchmarks/prepare_body_parts.py --original EXCERPT --prepared PREP --work W \
        [--fitted NAME=BODY.npz ...] [--only NAME,...] [--results benchmarks/results/prepare_body_parts_s34.json]

``EXCERPT`` is the original capture (its template, true body.npz, ground truth, held-out motion),
``PREP`` a capture `physavatar prepare` made of it with template and body.npz removed (its
body.npz is the fitted body). Each variant is the ORIGINAL garment (mesh, labels, boundary) worn on
a body that takes one part from the truth and the rest from the fit, animated with the true material
on the held-out motion and scored as `prepare_heldout_parts.py` scores (its `heldout_cd`, `compose`:
the garment Chamfer ×10³, 10,000 points, seed 0). An avatar uses only the body's shape and its
frame-1 pose (`build_avatar`, `animate`: the held-out motion's poses are applied to the shape), so
the parts are: the shape (phenotypes), the frame-1 root translation, and the frame-1 rotations of
groups of bones. ``--fitted NAME=BODY.npz`` adds the same row for another fitted body (e.g. a body
fit with other settings), with its own frame-0 error by region.

Also written: the fitted body's vertex error (collider topology, mm) per frame and, at frame 0, by
region (the skinning weights' dominant bone: head and neck, shoulders and arms, upper torso
spine01-03, lower torso spine04-05, hips root/pelvis, thighs, lower legs and feet), with each
region's mean offset vector (fitted - true). ``checks``: reported figures, no target.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _common import write_heldout_result
from prepare_heldout_parts import compose, heldout_cd, variant_args

# bone groups of the fit's moving bones (stages/prepare/body_fit.FIT_BONES)
GROUPS = {
    "root": ("root",),
    "spine": ("spine05", "spine03", "spine01"),
    "neck_head": ("neck01", "head"),
    "arms": ("clavicle.L", "upperarm01.L", "lowerarm01.L", "wrist.L",
             "clavicle.R", "upperarm01.R", "lowerarm01.R", "wrist.R"),
    "legs": ("upperleg01.L", "lowerleg01.L", "foot.L", "upperleg01.R", "lowerleg01.R", "foot.R"),
}


def region_of(bone: str) -> str:
    """The body region a vertex mostly skinned to ``bone`` belongs to."""
    if bone.startswith(("head", "neck")):
        return "head/neck"
    if bone.startswith(("clavicle", "shoulder", "upperarm", "lowerarm", "wrist", "finger", "metacarpal")):
        return "shoulders/arms"
    if bone in ("spine01", "spine02", "spine03"):
        return "upper torso (spine01-03)"
    if bone.startswith("spine"):
        return "lower torso (spine04-05)"
    if bone == "root" or bone.startswith("pelvis"):
        return "hips (root/pelvis)"
    if bone.startswith("upperleg"):
        return "thighs"
    return "lower legs/feet"


def body_errors(true, fitted) -> dict:
    """Vertex error [mm] of ``fitted`` against ``true`` (BodyPoses; collider topology): per frame,
    and at frame 0 by region with the mean offset (fitted - true)."""
    from physavatar.stages.prepare.posing import pose_body

    model, Vt = pose_body(true, topology="collider")
    _, Vp = pose_body(fitted, topology="collider")
    n = min(len(Vt), len(Vp))
    d = Vp[:n] - Vt[:n]
    e = np.linalg.norm(d, axis=-1) * 1000
    names = model.bone_names
    region = np.array([region_of(names[i]) for i in model.skinning_weights.argmax(1)])
    regions = {}
    for r in dict.fromkeys(region):
        s = region == r
        regions[r] = {"vertices": int(s.sum()), "frame0_mean_mm": round(float(e[0, s].mean()), 2),
                      "frame0_max_mm": round(float(e[0, s].max()), 2),
                      "frame0_mean_offset_mm": [round(float(x), 1) for x in d[0, s].mean(0) * 1000],
                      "all_frames_mean_mm": round(float(e[:, s].mean()), 2)}
    return {"mean_mm_per_frame": [round(float(x), 2) for x in e.mean(1)], "mean_mm": round(float(e.mean()), 3),
            "frame0_mean_mm": round(float(e[0].mean()), 3), "frame0_by_region": regions}


def mix(fit, true, *, shape=False, translation=False, bones=()):
    """``fit`` (BodyPoses) with the truth's shape, root translation and/or the rotations of ``bones``."""
    rot = fit.rotations.copy()
    ix = {b: i for i, b in enumerate(true.bone_names)}
    for b in bones:
        rot[:, fit.bone_names.index(b)] = true.rotations[:len(rot), ix[b]]
    return dataclasses.replace(fit, shape=true.shape if shape else fit.shape, rotations=rot,
                               root_translation=(true.root_translation[:len(rot)] if translation else
                                                 fit.root_translation))


def variants(orig, prep, extra: dict) -> dict:
    """name -> (description, BodyPoses)."""
    fb, tb = prep.body, orig.body
    fit_bones = set(sum(GROUPS.values(), ()))
    others = tuple(b for b in tb.bone_names if b not in fit_bones)
    v = {
        "fitted": ("the fitted body (shape, frame-1 pose and translation)", fb),
        "true": ("the true body", mix(fb, tb, shape=True, translation=True, bones=tuple(tb.bone_names))),
        "true_shape": ("true shape, fitted frame-1 pose and translation", mix(fb, tb, shape=True)),
        "true_pose": ("fitted shape, true frame-1 rotations and translation",
                      mix(fb, tb, translation=True, bones=tuple(tb.bone_names))),
        "true_translation": ("fitted shape and rotations, true root translation", mix(fb, tb, translation=True)),
        "true_root+translation": ("fitted, the root's rotation and translation true",
                                  mix(fb, tb, translation=True, bones=GROUPS["root"])),
        "true_lower_body": ("fitted, true root (rotation, translation), spine and legs",
                            mix(fb, tb, translation=True, bones=GROUPS["root"] + GROUPS["spine"] + GROUPS["legs"])),
    }
    tb_moved = mix(fb, tb, shape=True, translation=True, bones=tuple(tb.bone_names))
    tb_moved = dataclasses.replace(tb_moved, root_translation=tb_moved.root_translation + [1e-5, 0.0, 0.0])
    v["true+warmup"] = ("the true body moved 0.01 mm (its frame-1 pose no longer the held-out motion's first, so "
                        "animate puts its least warm-up, 2 frames, before the motion)", tb_moved)
    for g, bones in GROUPS.items():
        v[f"true_{g}"] = (f"fitted, true rotations of {', '.join(bones)}", mix(fb, tb, bones=bones))
    v["true_unfitted_bones"] = ("fitted, true rotations of the bones the fit leaves at rest (twists, fingers, ...)",
                                mix(fb, tb, bones=others))
    for name, path in extra.items():
        from physavatar.capture import BodyPoses
        from physavatar.body.model import BodyShape

        d = np.load(path)
        b = BodyPoses(BodyShape.from_array(d["shape"]), [str(x) for x in d["bone_names"]], d["rotations"],
                      d["root_translation"], str(d["topology"]))
        v[name] = (f"fitted body {path}", b)
    return v


def main() -> int:
    args = variant_args(argparse.ArgumentParser(), "prepare_body_parts_s34.json", **{
        "--fitted": dict(action="append", default=[], help="NAME=BODY.npz: another fitted body")})
    from physavatar.capture import load_capture
    from physavatar.sim.material import Material

    load0 = os.getloadavg()
    gt_src = args.original / "ground_truth"
    mat = Material.load(args.material or gt_src / "material.json")
    orig, prep = load_capture(args.original), load_capture(args.prepared)
    extra = dict(s.split("=", 1) for s in args.fitted)
    template = compose(prep.template, orig.template)  # the original garment, labels and boundary
    only = [s for s in args.only.split(",") if s]
    results = {}
    for name, (what, body) in variants(orig, prep, extra).items():
        if only and name not in only:
            continue
        w = args.work / name
        cached = w / "result.json"
        if cached.is_file():
            r = json.loads(cached.read_text())
        else:
            w.mkdir(parents=True, exist_ok=True)
            try:
                r = heldout_cd(dataclasses.replace(prep, body=body, template=template), gt_src, mat, w, args.frames)
            except Exception as e:  # noqa: BLE001 (a variant the simulation refuses is reported, not fatal)
                r = {"error": f"{type(e).__name__}: {e}"}
            r["what"] = what
            r["body_error"] = body_errors(orig.body, body)
            cached.write_text(json.dumps(r, indent=1) + "\n")
        results[name] = r
        print(f"{name:28s} " + (f"held-out garment CD x1e3 {r['chamfer_x1e3']:.4f}  F@1cm {r['fscore@1cm']:.3f}"
                                 if "error" not in r else r["error"])
              + f"  body frame 0 {r['body_error']['frame0_mean_mm']:.2f} mm", flush=True)
    write_heldout_result(args.results, "prepare_body_parts", load0,
                         {"original": str(args.original), "prepared": str(args.prepared), "fitted": extra,
                          "material": mat.to_dict(),
                          "fitted_body_error": body_errors(orig.body, prep.body)},
                         results, "Chamfer x1e3 (true material)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
