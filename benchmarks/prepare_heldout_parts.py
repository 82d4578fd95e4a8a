"""Which part of a prepared capture makes its held-out Chamfer (issue 23, session 32).

    python benchmarks/prepare_heldout_parts.py --original EXCERPT --prepared PREP \
        [--true-body PREP_T] [--labels PREP_L] [--true-body-labels PREP_TL] --work W \
        [--only NAME,...] [--results benchmarks/results/prepare_heldout_parts_s32.json]

``EXCERPT`` is the original capture (its template and body.npz), ``PREP`` the capture `physavatar
prepare` made of it with template and body.npz removed; ``PREP_T`` the same prepared with the true
body.npz given (`prepare_accuracy.py --given-body`), ``PREP_L`` with the true labels (`prepare
--labels EXCERPT/template/mesh.ply`, PREP's fitted body.npz given), ``PREP_TL`` both.

Each variant is an avatar (a template's garment, its boundary, the Anny body's shape and frame-1
pose) animated with the TRUE material (``EXCERPT/ground_truth/material.json``) on the held-out
motion as `evaluate`'s true-material row is (`stages.animate.animate`, its 1-s warm-up from the
avatar's frame-1 pose), and scored as `evaluate` scores it: the garment Chamfer ×10³ (10,000
points, seed 0) against the held-out truth re-expressed on the variant's template
(`stages.prepare.truth.carry_truth`, as `prepare` does). Variants replace one part of the prepared
avatar at a time by the truth: the body (shape and pose), the boundary (the template's garment
vertices within 2 cm of a true boundary point), the labels, the garment mesh (the original
garment, its labels and boundary, on the prepared body), and some of their combinations; and the
warm-up (``animate(warmup_s=0)``: its least, 2 frames; or no simulated warm-up: the template
skinned to the held-out motion's first pose, :func:`skinned_start`). The
garment simulation sees only the garment part, its boundary and the Anny collider (the template's
body vertices are skinned, not simulated), so a garment is put on another body by taking that
body's body.npz. Writes ``checks`` (reported figures, no target); W/NAME/result.json caches each.
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
from _common import animate_scored, write_heldout_result

BOUNDARY_RADIUS = 0.02  # [m] a garment vertex this near a boundary point of the other template is boundary


def compose(body_t, garment_t, boundary=None):
    """A template of ``body_t``'s body part and ``garment_t``'s garment part (labels, faces), with
    ``boundary`` [garment_t vertices] instead of ``garment_t``'s own when given."""
    from physavatar.capture import Template

    bo, gp = body_t.labels == 0, garment_t.labels > 0
    nb = int(bo.sum())
    rb = -np.ones(len(body_t.vertices), np.int64)
    rb[bo] = np.arange(nb)
    rg = -np.ones(len(garment_t.vertices), np.int64)
    rg[gp] = nb + np.arange(gp.sum())
    b = garment_t.boundary if boundary is None else boundary
    return Template(np.concatenate([body_t.vertices[bo], garment_t.vertices[gp]]),
                    np.concatenate([rb[body_t.faces[bo[body_t.faces].all(1)]], rg[garment_t.faces[gp[garment_t.faces].all(1)]]]),
                    np.r_[np.zeros(nb, np.int64), garment_t.labels[gp]], np.r_[np.zeros(nb, bool), b[gp]], None, None)


def with_boundary(t, points):
    """``t`` with its boundary: the garment vertices within BOUNDARY_RADIUS of ``points``."""
    from physavatar.capture import Template
    from physavatar.stages.prepare.boundary import boundary_from_points

    b = (t.labels > 0) & boundary_from_points(t.vertices, points, BOUNDARY_RADIUS)
    return Template(t.vertices, t.faces, t.labels, b, t.face_uvs, t.rest)


def skinned_start(cap, held):
    """``cap`` with its frame-1 pose replaced by ``held``'s first pose and its template carried there
    by linear blend skinning (weights of the closest point of Anny's collider in the frame-1 pose):
    the garment starts at rest in the motion's first pose, as the truth does, with no simulated
    warm-up in between."""
    from physavatar.body import BodyModel, linear_blend_skinning
    from physavatar.body.motion import Motion
    from physavatar.capture import BodyPoses, Template
    from physavatar.geometry.closest import MeshQuery

    b, t = cap.body, cap.template
    body = BodyModel(b.shape, topology="collider")
    m0 = Motion("frame1", cap.fps, b.bone_names, b.rotations[:1], b.root_translation[:1]).for_bones(body.bone_names)
    h = held.resample(cap.fps)
    h1 = h.for_bones(body.bone_names)
    P0, P1 = body.pose(m0.rotations, m0.root_translation), body.pose(h1.rotations[:1], h1.root_translation[:1])
    T = P1.bone_transforms[0] @ np.linalg.inv(P0.bone_transforms[0])
    _, f, bary, _ = MeshQuery(P0.vertices[0], body.faces).closest(t.vertices)
    W = np.einsum("nk,nkb->nb", bary, body.skinning_weights[body.faces[f]])
    V = linear_blend_skinning(t.vertices, W, T[None])[0]
    hb = h.for_bones(b.bone_names)
    poses = BodyPoses(b.shape, b.bone_names, hb.rotations[:1], hb.root_translation[:1], b.topology)
    return dataclasses.replace(cap, body=poses, template=Template(V, t.faces, t.labels, t.boundary, t.face_uvs, None))


def heldout_cd(cap, gt_src: Path, material, work: Path, frames: int | None, own_truth: bool = False,
               truth_on=None, keep_sequence: bool = False, **animate_kw) -> dict:
    """Held-out garment Chamfer ×10³ of ``cap`` (a Capture: template and body) with ``material``,
    against ``gt_src``'s held-out meshes (re-expressed on the template, or on ``truth_on`` (a
    Template of the same vertices) when given, unless ``own_truth``);
    ``animate_kw`` go to :func:`animate` (e.g. ``warmup_s``); ``keep_sequence``: the simulated
    garment [T, Ng, 3] in the result's ``_sequence`` too."""
    from physavatar.body.motion import Motion
    from physavatar.files import load_npz
    from physavatar.stages.avatar import build_avatar
    from physavatar.stages.prepare.truth import carry_truth

    t = cap.template
    gt_dir = gt_src if own_truth else work / "ground_truth"
    if not own_truth:  # the truth on this template's vertices, as prepare writes it
        tt = t if truth_on is None else truth_on
        carry_truth(gt_src, gt_dir, tt.vertices, tt.faces, tt.labels)
    gt = load_npz(gt_dir / "heldout" / "meshes.npz")["vertices"].astype(np.float64)
    held = Motion.load(gt_src / "heldout" / "motion.npz")
    if frames:
        held, gt = held.slice(0, frames), gt[:frames]
    av = build_avatar(cap, work / "avatar", material=material)
    row, stats, secs, V = animate_scored(av, held, gt, 10000, **animate_kw)
    g = t.labels > 0
    out = {"chamfer_x1e3": row["chamfer_x1e3"], "fscore@1cm": row["fscore@1cm"],
           "per_frame_chamfer_x1e3": row["per_frame_chamfer_x1e3"], "frames": int(len(gt)),
           "warmup_frames": stats["warmup_frames"], "garment_vertices": int(g.sum()),
           "boundary_vertices": int(t.boundary.sum()), "animate_s": round(secs, 1),
           "frames_with_lag": stats["frames_with_lag"]}
    if keep_sequence:
        out["_sequence"] = V
    return out


def variants(args) -> dict:
    """name -> (description, a function giving the Capture[, animate's keywords])."""
    from physavatar.capture import load_capture

    from physavatar.body.motion import Motion

    held = Motion.load(args.original / "ground_truth" / "heldout" / "motion.npz")
    orig = load_capture(args.original)
    prep = load_capture(args.prepared)
    to, tp = orig.template, prep.template
    tb_pts, pb_pts = to.vertices[to.boundary], tp.vertices[tp.boundary]
    rep = dataclasses.replace
    v = {
        "original": ("the original capture (all true)", lambda: orig),
        "prepared": ("the prepared capture (all prepared)", lambda: prep),
        "prepared+true_boundary": ("prepared, boundary = its garment vertices within 2 cm of the true boundary",
                                   lambda: rep(prep, template=with_boundary(tp, tb_pts))),
        "prepared_garment+true_body": ("the prepared garment (its boundary) on the true body (shape, frame-1 pose)",
                                       lambda: rep(orig, template=compose(to, tp))),
        "prepared_garment+true_body+true_boundary": ("the prepared garment on the true body, true boundary",
                                                     lambda: rep(orig, template=compose(to, with_boundary(tp, tb_pts)))),
        "true_garment+prepared_body": ("the original garment (mesh, labels, boundary) on the prepared (fitted) body",
                                       lambda: rep(prep, template=compose(tp, to))),
        "true_garment+prepared_body+prepared_boundary": (
            "the original garment on the fitted body, boundary = its vertices within 2 cm of the prepared boundary",
            lambda: rep(prep, template=compose(tp, to, with_boundary(to, pb_pts).boundary))),
        "prepared, warmup_s=0": ("prepared, animate's warm-up 0 s (its least: 2 frames)", lambda: prep,
                                 {"warmup_s": 0.0}),
        "true_garment+prepared_body, warmup_s=0": ("the original garment on the fitted body, warm-up 0 s (2 frames)",
                                                   lambda: rep(prep, template=compose(tp, to)), {"warmup_s": 0.0}),
        "prepared, skinned start": ("prepared, its template skinned to the held-out motion's first pose and "
                                    "simulated from rest there (no simulated warm-up)", lambda: skinned_start(prep, held), {"truth_on": tp}),
        "true_garment+prepared_body, skinned start": ("the original garment on the fitted body, skinned start",
                                                      lambda: skinned_start(rep(prep, template=compose(tp, to)), held),
                                                      {"truth_on": compose(tp, to)}),
        "true_garment+prepared_boundary": ("the original garment on the true body, the prepared boundary (2 cm)",
                                           lambda: rep(orig, template=with_boundary(to, pb_pts))),
    }
    for name, path, what in (("prepare_true_body", args.true_body, "prepare with the true body.npz given"),
                             ("prepare_true_labels", args.labels, "prepare with the true labels (fitted body given)"),
                             ("prepare_true_body_labels", args.true_body_labels,
                              "prepare with the true body.npz and the true labels")):
        if path is not None:
            v[name] = (what, lambda p=path: load_capture(p))
            v[name + "+true_boundary"] = (what + ", true boundary (2 cm)",
                                          lambda p=path: (lambda c: rep(c, template=with_boundary(c.template, tb_pts)))(
                                              load_capture(p)))
    return v


def variant_args(ap: argparse.ArgumentParser, results: str, **extra: dict) -> argparse.Namespace:
    """Parses the options of a held-out variant benchmark (this one, prepare_body_parts): the
    original and prepared captures, ``extra`` options (name -> add_argument keywords), the
    material, frames, variants, work folder and results file (default ``results`` in results/)."""
    ap.add_argument("--original", type=Path, required=True, help="the original capture (template, body.npz)")
    ap.add_argument("--prepared", type=Path, required=True, help="its prepared capture (fitted body)")
    for name, kw in extra.items():
        ap.add_argument(name, **kw)
    ap.add_argument("--material", type=Path, help="default: ORIGINAL/ground_truth/material.json")
    ap.add_argument("--frames", type=int, default=None, help="held-out frames (default: all)")
    ap.add_argument("--only", default="", help="comma-separated variant names")
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--results", type=Path, default=HERE / "results" / results)
    return ap.parse_args()


def main() -> int:
    args = variant_args(argparse.ArgumentParser(), "prepare_heldout_parts_s32.json", **{
        "--true-body": dict(type=Path, help="the input prepared with the true body.npz given"),
        "--labels": dict(type=Path, help="the input prepared with the true labels (the fitted body given)"),
        "--true-body-labels": dict(type=Path, help="the input prepared with the true body and labels")})
    from physavatar.sim.material import Material

    load0 = os.getloadavg()
    gt_src = args.original / "ground_truth"
    mat = Material.load(args.material or gt_src / "material.json")
    vs = variants(args)
    only = [s for s in args.only.split(",") if s]
    results = {}
    for name, (what, make, *kw) in vs.items():
        if only and name not in only:
            continue
        w = args.work / name
        cached = w / "result.json"
        if cached.is_file():
            results[name] = json.loads(cached.read_text())
        else:
            w.mkdir(parents=True, exist_ok=True)
            try:
                r = heldout_cd(make(), gt_src, mat, w, args.frames, own_truth=name == "original",
                               **(kw[0] if kw else {}))
            except Exception as e:  # noqa: BLE001 (a variant the simulation refuses is reported, not fatal)
                r = {"error": f"{type(e).__name__}: {e}"}
            r["what"] = what
            cached.write_text(json.dumps(r, indent=1) + "\n")
            results[name] = r
        r = results[name]
        print(f"{name:48s} " + (f"held-out garment CD x1e3 {r['chamfer_x1e3']:.4f}  F@1cm {r['fscore@1cm']:.3f}"
                                 if "error" not in r else r["error"]), flush=True)
    write_heldout_result(args.results, "prepare_heldout_parts", load0,
                         {"original": str(args.original), "prepared": str(args.prepared),
                          "true_body": str(args.true_body), "labels": str(args.labels),
                          "true_body_labels": str(args.true_body_labels), "material": mat.to_dict()},
                         results, "Chamfer x1e3 (true material)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
