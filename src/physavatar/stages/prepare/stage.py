"""``physavatar prepare CAPTURE OUT``: fill in what a capture lacks, each step skipped when its
output is given, and write a capture that ``inspect`` accepts and ``run`` uses.

Steps, in order (docs/prepare.md): images (hard-linked), masks, the first-frame mesh, the Anny
body of every frame, garment segmentation, boundary vertices, UVs, the template, the ground
truth of a synthetic capture, the report. Everything is written into ``.OUT.preparing`` next to
``OUT`` and renamed at the end, so a failed run leaves nothing half written.
"""

from __future__ import annotations

import os
import shutil
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from ...capture import (
    BodyPoses,
    Template,
    _load_body,
    _Problems,
    frame_name,
    load_capture,
    load_unprepared,
    save_cameras,
    save_capture_meta,
    save_png,
)
from ...errors import PhysavatarError
from ...files import read_ply, write_json_atomic
from ...labels import LABEL_BODY
from ..base import to_dict
from .config import PrepareConfig
from .posing import pose_body
from .truth import carry_truth, link_file, link_tree

CORE_META = ("format_version", "fps", "frames", "units", "up")


def _work_dir(out: Path) -> Path:
    if out.exists() and any(out.iterdir()) and not (out / "prepare.json").is_file():
        raise PhysavatarError(out, "output folder exists and is not empty (choose another or remove it)")
    tmp = out.parent / f".{out.name}.preparing"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    return tmp


def _finish(tmp: Path, out: Path) -> None:
    if out.exists():
        shutil.rmtree(out)  # empty, or an earlier prepare output (checked in _work_dir)
    os.replace(tmp, out)


def _read_mask(path: Path) -> np.ndarray:
    from ...capture import _read_png

    return _read_png(path, "L")


def _fit_body(src: Path, tmp: Path, vertices: np.ndarray | None, faces: np.ndarray | None, cfg: PrepareConfig,
              progress, fit_offsets: bool = False) -> tuple[BodyPoses, dict]:
    from ...body.model import BodyShape
    from .body_fit import fit_body

    fit = fit_body(tmp, template_vertices=vertices, config=cfg.body, progress=progress, template_faces=faces,
                   fit_offsets=fit_offsets)
    poses = BodyPoses(BodyShape.from_array(np.asarray(fit.shape)), [str(b) for b in fit.bone_names],
                      np.asarray(fit.rotations, np.float64), np.asarray(fit.root_translation, np.float64),
                      str(fit.topology))
    return poses, dict(getattr(fit, "report", {}) or {})


def run(capture: str | Path, *, out: str | Path, config: PrepareConfig = PrepareConfig(), progress=None) -> Path:
    """Prepare ``capture`` into ``out`` (a new capture folder); returns ``out``."""
    from ...progress import resolve

    src, out = Path(capture), Path(out)
    cfg = config
    raw = load_unprepared(src)
    if src.resolve() == out.resolve():
        raise PhysavatarError(out, "the output must be a new folder, not the capture itself")
    prog = resolve(progress)
    tmp = _work_dir(out)
    t_all = time.time()
    steps: dict[str, str] = {}
    warnings: list[str] = []
    numbers: dict = {}
    seconds: dict[str, float] = {}
    try:
        t = time.time()
        n_img = 0
        for c in raw.cameras:
            for f in raw.frames:
                link_file(raw.image_path(c.name, f), tmp / "images" / c.name / f"{frame_name(f)}.png", cfg.copy_images)
                n_img += 1
        if (src / "background").is_dir():
            link_tree(src / "background", tmp / "background", cfg.copy_images)
        if (src / "meshes").is_dir():
            link_tree(src / "meshes", tmp / "meshes", cfg.copy_images)
        save_cameras(tmp, raw.cameras)
        extra = {k: v for k, v in raw.meta.items() if k not in CORE_META}
        save_capture_meta(tmp, fps=raw.meta["fps"], frames=raw.frames, extra=extra)
        steps["images"] = f"{n_img} images {'copied' if cfg.copy_images else 'linked'}"
        seconds["images"] = time.time() - t

        # -- masks
        t = time.time()
        steps["masks"], mask_numbers, warning = _masks(src, tmp, raw, cfg, prog)
        if mask_numbers:
            numbers["masks"] = mask_numbers
        if warning:
            warnings.append(warning)
        seconds["masks"] = time.time() - t

        def masks_of(frame: int) -> dict[str, np.ndarray]:
            return {c.name: _read_mask(tmp / "masks" / c.name / f"{frame_name(frame)}.png") for c in raw.cameras}

        first = raw.frames[0]
        given_template = src / "template" / "mesh.ply"
        labelled = given_template.is_file() and "label" in read_ply(given_template).vertex_data

        # -- the cameras checked against the person (calibration.py)
        t = time.time()
        from .calibration import calibrate_step
        from .mesh import imported_mesh_path

        given = ("body.npz given" if (src / "body.npz").is_file() else "mesh given"
                 if labelled or imported_mesh_path(src, first) is not None else None)
        raw, steps["cameras"], cam_numbers = calibrate_step(src, tmp, raw, cfg, masks_of, given, prog)
        if cam_numbers:
            numbers["cameras"] = cam_numbers
        seconds["cameras"] = time.time() - t

        # -- first-frame mesh
        t = time.time()
        mesh_source, src_mesh, src_labels = None, None, None
        if labelled:
            steps["mesh"] = "given (labelled template)"
        else:
            from .mesh import (
                imported_mesh_path,
                make_manifold,
                read_mesh,
                reconstruct,
                remesh,
            )

            imp = imported_mesh_path(src, first)
            if imp is not None:
                V0, F0, data = read_mesh(imp)
                src_mesh = (V0, F0)
                if "label" in data:
                    src_labels = np.asarray(data["label"]).astype(np.int64)
                V, F = make_manifold(V0, F0, imp)
                V, F = remesh(V, F, cfg.mesh, imp)
                mesh_source = str(imp.relative_to(src))
                steps["mesh"] = f"imported ({mesh_source}), made manifold, remeshed"
            else:
                V, F = reconstruct(raw.cameras, masks_of(first), cfg.mesh, tmp / "masks")
                mesh_source = "visual hull"
                steps["mesh"] = "reconstructed: visual hull of the masks, made manifold, remeshed"
            numbers["mesh"] = {"vertices": len(V), "faces": len(F), "source": mesh_source}
        seconds["mesh"] = time.time() - t

        # -- body
        t = time.time()
        if (src / "body.npz").is_file():
            link_file(src / "body.npz", tmp / "body.npz", True)
            body = _load_body(tmp, len(raw.frames), _Problems(strict=True))
            steps["body"] = "given"
        else:
            # the clothed surface guides the fit when it is a measured one (an imported mesh) or a
            # visual hull from fine pixels (it keeps the body under the clothing: demo segmentation
            # 96.7 % with it, 92.3 % without); a hull from pixels coarser than
            # cfg.mesh.clothing_footprint is too loose and noisy to bound the body (tiny capture,
            # 2.3 cm pixels, first frame: 49 mm vertex error with it, 8.5 mm without)
            clothed = not labelled and (mesh_source != "visual hull" or _footprint(raw.cameras, V)
                                        <= cfg.mesh.clothing_footprint)
            body, numbers["body"] = _fit_body(src, tmp, V if clothed else None, F if clothed else None, cfg, prog,
                                              fit_offsets=cfg.calibrate and given is None and len(raw.cameras) >= 3)
            body.save(tmp / "body.npz")
            offsets = numbers["body"].get("camera_offsets_px")
            if offsets:  # the cameras' image offsets fitted with the body (body_fit.py), checked like the step's
                from .calibration import hull_check, shifted

                new = [shifted(c, offsets[c.name]) for c in raw.cameras]
                numbers["cameras_body"] = {"offsets_px": offsets} | hull_check(raw.cameras, new, masks_of, raw.frames)
                if numbers["cameras_body"]["applied"]:
                    raw = replace(raw, cameras=new)
                    save_cameras(tmp, raw.cameras)
                    steps["cameras"] += "; offsets refined with the body, checked against the masks' hull"
                else:
                    steps["cameras"] += "; the body fit's offsets not applied (the masks' hull does not rise with them)"
            steps["body"] = "fitted (Anny, every frame)"
        seconds["body"] = time.time() - t

        # -- the hull refined against the images and the body
        V_hull, on_body, photo = None, None, None
        if mesh_source == "visual hull" and (cfg.refine.photo or cfg.refine.body_prior):
            t = time.time()
            V_hull = V
            V, info = _refine(raw, cfg, V, F, body, masks_of(first), prog)
            on_body = info.pop("_on_body", None)
            photo = info.pop("_photo", None)
            numbers["refine"] = info
            steps["mesh"] += "; refined: " + " and ".join(
                [w for w, on in (("photo-consistency", cfg.refine.photo), ("body where unseen", cfg.refine.body_prior))
                 if on])
            seconds["refine"] = time.time() - t

        # -- segmentation, boundary, UVs, template
        if labelled:
            link_file(given_template, tmp / "template" / "mesh.ply", True)
            for k in ("segmentation", "boundary", "uv"):
                steps[k] = "given"
        else:
            _template(src, tmp, raw, cfg, V, F, src_mesh, src_labels, body, masks_of, steps, numbers, seconds, prog,
                      V_hull, on_body, photo)

        if (src / "ground_truth").is_dir():
            t = time.time()
            tpl = read_ply(tmp / "template" / "mesh.ply")
            numbers["ground_truth"] = carry_truth(src / "ground_truth", tmp / "ground_truth", tpl.vertices, tpl.faces,
                                                  np.asarray(tpl.vertex_data["label"]).astype(np.int64))
            seconds["ground_truth"] = time.time() - t

        extra["prepared"] = {"from": str(src.resolve()), "steps": steps} | ({"warnings": warnings} if warnings else {})
        save_capture_meta(tmp, fps=raw.meta["fps"], frames=raw.frames, extra=extra)
        cap = load_capture(tmp)  # what run will read: checked before anything is renamed
        if cfg.report:
            t = time.time()
            from .report import write_report

            write_report(cap, tmp, steps, numbers, prog, warnings)
            seconds["report"] = time.time() - t
        seconds["total"] = time.time() - t_all
        write_json_atomic(tmp / "prepare.json", {"capture": str(src), "steps": steps, "warnings": warnings,
                                                 "seconds": {k: round(v, 2) for k, v in seconds.items()},
                                                 "numbers": _jsonable(numbers), "config": to_dict(cfg)})
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    _finish(tmp, out)
    return out


def _masks(src: Path, tmp: Path, raw, cfg: PrepareConfig, prog) -> tuple[str, dict, str | None]:
    """The masks step: the capture's masks linked, or computed into ``tmp/masks``; returns what was
    done (one line), the per camera numbers, and the warning when computed masks look unreliable
    (masks.unreliable_warning, already logged)."""
    if raw.has_masks:
        for c in raw.cameras:
            for f in raw.frames:
                link_file(raw.mask_path(c.name, f), tmp / "masks" / c.name / f"{frame_name(f)}.png", cfg.copy_images)
        return "given", {}, None
    from .masks import estimate_masks

    masks, info, warning = estimate_masks(src, raw.cameras, raw.frames, cfg.masks, prog)
    for c in raw.cameras:
        for f, m in zip(raw.frames, masks[c.name]):
            save_png(tmp / "masks" / c.name / f"{frame_name(f)}.png", m.astype(np.uint8) * 255)
    kinds = sorted({v["background"] for v in info.values()})
    step = ("computed: " + ", ".join(kinds) if kinds == ["mediapipe person segmentation"] else
            "computed: background differencing (" + ", ".join(kinds) + ")")
    keep = ("background", "threshold", "clutter", "foreground")
    return step, {k: {q: v[q] for q in keep if q in v} for k, v in info.items()}, warning


def _footprint(cameras, V) -> float:
    from .mesh import pixel_footprint

    return pixel_footprint(cameras, V.mean(0))


def _refine(raw, cfg: PrepareConfig, V, F, body, masks, prog):
    from ...capture import _read_png
    from .refine import refine_hull

    model, posed = pose_body(body, [0])
    images = {c.name: _read_png(raw.image_path(c.name, raw.frames[0]), "RGB") for c in raw.cameras} \
        if cfg.refine.photo else {}
    with prog.task("prepare: refining the hull", total=1) as task:
        V, info = refine_hull(V, F, raw.cameras, images, {k: v.astype(np.float64) for k, v in masks.items()},
                              posed[0], np.asarray(model.faces, np.int64), cfg.refine)
        task.advance()
    return V, info


def _template(src, tmp, raw, cfg, V, F, src_mesh, src_labels, body, masks_of, steps, numbers, seconds, prog,
              V_hull=None, on_body=None, photo=None):
    """Segmentation, garment pieces, boundary and UVs; writes template/mesh.ply. When the hull
    was refined (``V_hull``: the same vertices before), the segmentation's margin is the refined
    surface's (``refined_margin``) and the boundary's contact test looks at the hull positions
    (a refined strap lies on the body all along, the contact test is set for the hull); the
    vertices the refinement drew onto the body (``on_body``, unseen) are body and, like the hull's
    bridges, not cut into a garment."""
    from .boundary import boundary_from_points, boundary_points, find_boundary
    from .segment import garment_pieces, segment, transfer_labels, user_labels
    from .uv import atlas

    first = raw.frames[0]
    T = len(raw.frames)
    sample = sorted(set(np.linspace(0, T - 1, min(T, max(cfg.boundary.frames, 2))).round().astype(int).tolist()) | {0})
    model, posed = pose_body(body, sample)
    BV, BF = posed[0], np.asarray(model.faces, np.int64)

    t = time.time()
    bridge, evidence = None, None
    if cfg.segment.labels is not None:
        labels = user_labels(cfg.segment.labels, V, src_mesh)
        steps["segmentation"] = f"from {cfg.segment.labels}"
    elif src_labels is not None and src_mesh is not None and (src_labels > 0).any():
        labels = transfer_labels(V, src_mesh[0], src_mesh[1], np.clip(src_labels, 0, 15))
        steps["segmentation"] = "from the imported mesh's labels"
    else:
        from ...capture import _read_png

        images = {c.name: _read_png(raw.image_path(c.name, first), "RGB") for c in raw.cameras}
        seg = cfg.segment
        if src_mesh is None:  # a visual hull is off by up to a pixel: the margin is at least that
            from dataclasses import replace

            from .mesh import pixel_footprint

            foot = pixel_footprint(raw.cameras, V.mean(0))
            # a refined surface is not the hull's slack above a tight garment: a smaller margin
            if V_hull is None:
                seg = replace(seg, margin=max(seg.margin, foot), softness=max(seg.softness, foot / 3))
            else:
                f = seg.refined_footprint * foot
                seg = replace(seg, margin=max(seg.refined_margin, f), softness=max(seg.refined_softness, f / 3))
            numbers["segmentation_margin"] = round(seg.margin, 4)
        with prog.task("prepare: segmentation", total=1) as task:
            labels, info = segment(V, F, BV, BF, raw.cameras, images, seg, cfg.mesh.edge_length, photo=photo)
            task.advance(garment=info["garment_vertices"])
        numbers["segmentation"] = {k: v for k, v in info.items() if not isinstance(v, np.ndarray)}
        numbers["_distance"] = info["signed_distance"]
        bridge, evidence = info["bridge_mask"], info["logit"]
        if on_body is not None:
            # the hull's underside (a hem to the legs) is body; an unseen top (a strap over the
            # shoulder, which the cameras see only edge-on) keeps the segmentation's label
            from ...geometry.mesh import vertex_normals

            on_body = on_body & (vertex_normals(V if V_hull is None else V_hull, F)[:, 2] < 0)
            labels = np.where(on_body, LABEL_BODY, labels)
            bridge = bridge | on_body
        steps["segmentation"] = "automatic: distance to the body + colour, graph cut"
    if not (labels > LABEL_BODY).any():
        raise PhysavatarError(src, "no garment found on the first-frame mesh (every vertex is within the garment "
                              "margin of the body): give --labels, or a smaller --garment-margin")
    # the garments are cut out without the hull's bridges: cloth ends at its hem
    cut = np.where(bridge, LABEL_BODY, labels) if bridge is not None else labels
    joins: list = []
    pieces = garment_pieces(V, F, cut, BV, BF, min_share=cfg.segment.min_piece, exclude=bridge,
                            max_gap=cfg.segment.strap_gap, joins=joins, evidence=evidence,
                            evidence_weight=cfg.segment.strap_evidence,
                            widen=cfg.segment.strap_widen)
    numbers["strap_joins"] = joins
    # the boundary's contact test is set for the hull too (the refined surface of a strap or a
    # bodice lies on the body all along): the same pieces at their hull positions
    contact_pieces = pieces
    if V_hull is not None:
        hp = garment_pieces(V_hull, F, cut, BV, BF, min_share=cfg.segment.min_piece, exclude=bridge,
                            max_gap=cfg.segment.strap_gap, gap_vertices=V, evidence=evidence,
                            evidence_weight=cfg.segment.strap_evidence,
                            widen=cfg.segment.strap_widen)
        if [(g, f.shape) for g, _, f in hp] == [(g, f.shape) for g, _, f in pieces]:
            contact_pieces = hp
        numbers["contact_pieces_on_hull"] = contact_pieces is hp
    if not pieces:
        raise PhysavatarError(src, "the garment region of the first-frame mesh has no usable surface piece")
    from ...files import save_npz_atomic

    save_npz_atomic(tmp / "prepare" / "first_frame_mesh.npz", vertices=V, faces=F, labels=labels,
                    bridge=bridge if bridge is not None else np.zeros(len(V), bool),
                    **({} if evidence is None else {"evidence": evidence}))
    seconds["segmentation"] = time.time() - t

    t = time.time()
    bnd, kept = [], []
    info_b = {}
    override = boundary_points(cfg.boundary.file) if cfg.boundary.file is not None else None
    with prog.task("prepare: boundary", total=len(pieces)) as task:
        for (g, Vg, Fg), (_, Vc, _) in zip(pieces, contact_pieces):
            if override is not None:
                b = boundary_from_points(Vg, override, cfg.mesh.edge_length)
                if not b.any():
                    raise PhysavatarError(cfg.boundary.file, f"no vertex of garment {g} is within "
                                          f"{cfg.mesh.edge_length} m of the boundary points")
            else:
                b, info_b[str(g)] = find_boundary(Vc, Fg, posed, BF, raw.cameras,
                                                  lambda i: masks_of(raw.frames[sample[i]]), sample, cfg.boundary)
            unheld = info_b[str(g)].pop("_unheld", None) if override is None else None
            if unheld is not None and unheld.any():  # fragments nothing holds: dropped
                from .segment import _face_submesh

                ids, Fg = _face_submesh(Fg, ~unheld[Fg].any(1))
                Vg, b = Vg[ids], b[ids]
            kept.append((g, Vg, Fg))
            bnd.append(b)
            task.advance(garment=g, boundary=int(b.sum()))
    steps["boundary"] = f"from {cfg.boundary.file}" if override is not None else "automatic: contact with the body over the frames"
    numbers["boundary"] = info_b
    seconds["boundary"] = time.time() - t

    t = time.time()
    verts, faces, labs, bflags, n = [BV], [BF], [np.zeros(len(BV), np.int64)], [np.zeros(len(BV), bool)], len(BV)
    for (g, Vg, Fg), b in zip(kept, bnd):
        verts.append(Vg)
        faces.append(Fg + n)
        labs.append(np.full(len(Vg), g, np.int64))
        bflags.append(b)
        n += len(Vg)
    Vt, Ft, Lt, Bt = np.concatenate(verts), np.concatenate(faces), np.concatenate(labs), np.concatenate(bflags)
    seconds["uv"] = time.time() - t

    # -- the garment off the fitted body's collider, where the simulation starts (clear.py)
    t = time.time()
    from .clear import clear_of_collider, describe

    Vt, numbers["clear"] = clear_of_collider(Vt, Ft, Lt, Bt, body, source=src)
    steps["clear"] = describe(numbers["clear"])
    seconds["clear"] = time.time() - t

    t = time.time()
    uvs = atlas(Vt, Ft)
    Template(Vt, Ft, Lt, Bt, uvs).save(tmp / "template" / "mesh.ply")
    steps["uv"] = "xatlas"
    numbers["template"] = {"vertices": len(Vt), "faces": len(Ft), "garments": [int(p[0]) for p in pieces],
                           "boundary": int(Bt.sum())}
    seconds["uv"] += time.time() - t


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items() if not str(k).startswith("_")}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return None
    if isinstance(x, (np.integer, np.floating)):
        return x.item()
    return x
