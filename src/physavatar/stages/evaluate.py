"""Evaluation against synthetic ground truth (DESIGN.md, "Evaluation protocol"; paper Tables 1, 2).

Geometry on the held-out motion (``ground_truth/heldout``): the garment is animated with
  - LBS: skinned with weights transferred from the body (no simulation),
  - random material: the median of several seeded draws in the paper's parameter ranges (seeds
    ``seed`` … ``seed + random_draws − 1``, default 0–4: one draw can land near the truth or far
    from it, the paper's baseline is a typical random material); the row is the draw whose
    garment CD is the median, and every draw's CD is kept under ``random_draws``; each draw is
    simulated with the estimated material's contact thickness (Material.contact_offset), so the
    two rows differ in the material alone,
  - estimated material: the avatar's (fit-physics),
  - true material: ``ground_truth/material.json`` (the oracle),
  - oracle material: for a capture whose material is not in this simulator's terms (no
    ``material.json``; another simulator made it), the material fitted on the true meshes
    (``fit-physics CAPTURE``), so the fit's residual splits into tracking error and model gap,
and compared with the ground-truth garment and full mesh per frame: Chamfer distance (×10³ m²)
and F-score at 1 cm, 2 cm (plain distances) and the squared-distance τ = 0.001 variant, on
points sampled uniformly on the surfaces.

Appearance on the held-out views: the estimated-material sequence rendered with the avatar's
texture and light from the held-out cameras vs the ground-truth images, inside the masks:
PSNR, SSIM, LPIPS (AlexNet).

Tracking (when a tracked folder is given): per-frame mean and 95th-percentile vertex error (mm)
for garment and body.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..data.avatar import Avatar
from ..body import Motion, linear_blend_skinning
from ..capture import load_capture
from ..data.tracked import TrackedSequence
from ..errors import PhysavatarError
from ..files import load_npz, read_json, write_json_atomic, write_text_atomic
from ..geometry import submesh
from ..sim.material import FIT_REST_FRICTION, FIT_REST_SHAPE, REST_SHAPES
from .base import camera_list, option, setting
from .references import (RANDOM_DRAWS, Reference, _reference_materials, _reuse_references, _reuse_sequence,  # noqa: F401
                         motion_key, random_draw_row, random_material, random_seeds, reference_sequences)

log = logging.getLogger(__name__)

ROWS = ("LBS", "random material", "estimated material", "true material", "oracle material")


def median_random_row(draw_rows: dict[int, dict]) -> tuple[dict, dict]:
    """The "random material" row from the rows of several draws (seed -> {"garment", "full"}):
    the draw whose garment CD is the median (an odd count has one), and the audit record of all
    draws (seeds, each one's garment and full CD, the median's seed)."""
    seeds = sorted(draw_rows)
    if len(seeds) % 2 == 0:
        raise ValueError(f"an odd number of random draws is needed for a median draw, got {len(seeds)}")
    cd = {s: draw_rows[s]["garment"]["chamfer_x1e3"] for s in seeds}
    mid = sorted(seeds, key=lambda s: (cd[s], s))[len(seeds) // 2]
    audit = {"seeds": seeds, "median_seed": mid, "garment_chamfer_x1e3": [cd[s] for s in seeds],
             "full_chamfer_x1e3": [draw_rows[s]["full"]["chamfer_x1e3"] for s in seeds]
             if all("full" in draw_rows[s] for s in seeds) else None,
             "garment_chamfer_x1e3_median": float(np.median([cd[s] for s in seeds]))}
    return draw_rows[mid], audit


def _surface_rows(pred: np.ndarray, gt: np.ndarray, faces: np.ndarray, n_points: int, seed: int) -> dict:
    from ..metrics import surface_metrics

    per = [surface_metrics(pred[t], faces, gt[t], faces, n_points=n_points, seed=seed + t) for t in range(len(gt))]
    keys = ["chamfer_x1e3", "fscore@1cm", "fscore@2cm", "fscore@sq0.001"]
    return {k: float(np.mean([p[k] for p in per])) for k in keys} | {"per_frame_chamfer_x1e3": [p["chamfer_x1e3"] for p in per]}


def evaluate(capture: str | Path, avatar_dir: str | Path, out: str | Path, *, tracked: str | Path | None = None,
             frames: int | None = None, n_points: int = 10000, views_spp: int = 64, seed: int = 0,
             random_draws: int = RANDOM_DRAWS, sequence: str | Path | None = None, references: str | Path | None = None,
             holdout: tuple[str, ...] | None = None, oracle: str | Path | None = None, views: bool = True,
             full: bool = True, progress=True) -> dict:
    """Write ``metrics.json`` and ``report.md`` into ``out``; returns the metrics.

    ``references``: a :func:`reference_sequences` folder of this capture; its true- and
    random-material rows are used instead of simulating them here.

    ``sequence``: an ``animate`` output of this avatar on the held-out motion, used as the
    estimated-material row instead of simulating it again (it must cover the evaluated frames
    and have the avatar's topology).

    ``oracle``: a ``fit-physics`` folder fitted on the true meshes (``fit-physics CAPTURE``): its
    material is one more row, the best this simulator's model can do on the capture.

    ``holdout``: capture cameras scored as held-out views (the tracked meshes rendered with the
    avatar's texture and light against their images); default: the cameras the tracking held
    out. This part needs no ground truth, so a real capture is evaluated too.

    ``views=False``: geometry and tracking only, no rendered views (e.g. the rows again at
    another ``n_points``); ``full=False``: the garment rows only, no full-mesh rows.
    """
    cap = load_capture(capture)
    gt_root = cap.ground_truth
    out = Path(out)
    av = Avatar.load(avatar_dir)
    hold = _holdout_cameras(cap, tracked, holdout)
    has_heldout_motion = gt_root is not None and (gt_root / "heldout" / "meshes.npz").exists()
    if not has_heldout_motion and not hold:
        raise PhysavatarError(cap.root, "nothing to evaluate: no ground_truth/heldout (a synthetic capture's held-out "
                              "motion) and no held-out cameras (pass --tracked of a tracking that held cameras out, "
                              "or --holdout CAMS)")
    metrics: dict = {"capture": str(cap.root), "avatar": str(av.root), "n_points": n_points, "rows": {}, "seconds": {}}
    if hold and views:
        metrics["heldout_cameras"] = _capture_views(cap, av, Path(tracked), hold, out, views_spp)
    if has_heldout_motion:
        _heldout_motion(metrics, cap, av, out, frames=frames, n_points=n_points, views_spp=views_spp, seed=seed,
                        random_draws=random_draws, sequence=sequence, references=references, oracle=oracle,
                        views=views, full=full, progress=progress)
    # Tracking accuracy.
    if tracked is not None and gt_root is not None and (gt_root / "meshes.npz").is_file():
        metrics["tracking"] = _tracking(cap, Path(tracked))
    write_json_atomic(out / "metrics.json", metrics)
    write_text_atomic(out / "report.md", report_markdown(metrics))
    return metrics


def _heldout_motion(metrics: dict, cap, av, out: Path, *, frames, n_points, views_spp, seed, random_draws, sequence, references,
                    oracle, views, full, progress) -> None:
    """The geometry rows (and the views of ``ground_truth/heldout``'s cameras) on the held-out motion."""
    from ..garment import garment_skinning_weights
    from ..body import BodyModel
    from ..parallel import Job, run_jobs
    from .animate import animate, animate_job, simulated_frames

    gt_root = cap.ground_truth
    held = held_all = Motion.load(gt_root / "heldout" / "motion.npz")
    gtz = load_npz(gt_root / "heldout" / "meshes.npz")
    gt = gtz["vertices"].astype(np.float64)
    if frames:
        held, gt = held.slice(0, frames), gt[:frames]
    t = av.template
    gmask = t.labels > 0
    _, gfaces_local = submesh(t.faces, gmask)
    metrics["heldout_frames"] = int(len(gt))

    # The four garment rows.
    seqs = {}
    t0 = time.time()
    est = _reuse_sequence(sequence, av, len(gt), av.material, held_all) if sequence is not None else None
    if est is None:
        est, _ = animate(av, held, progress=progress)
    else:
        metrics["estimated_sequence"] = str(sequence)
    seqs["estimated material"] = est.vertices
    metrics["seconds"]["animate_estimated"] = round(time.time() - t0, 1)
    # The reference materials: two independent simulations, side by side (physavatar.parallel),
    # or taken from a `reference_sequences` folder made earlier (`physavatar run` makes it while
    # tracking runs).
    references_ = _reference_materials(gt_root, seed, random_draws, av.material.contact_offset, av.material.rest_shape,
                                       av.material.rest_friction)
    refs = {r.row: r.material for r in references_}
    if oracle is not None:
        from ..data.material import FittedMaterial

        refs["oracle material"] = FittedMaterial.load(Path(oracle) / "material.json").material
    if references is not None:
        reused, stale = _reuse_references(Path(references), av, references_, len(gt), held_all)
        seqs.update(reused)
        metrics["references"] = str(references)
        if stale:  # simulated again below, in the estimate's model
            metrics["references_simulated_again"] = stale
            log.warning("evaluate: %s of %s simulated again: %s", ", ".join(stale), references, next(iter(stale.values())))
    todo = [(row, mat) for row, mat in refs.items() if row not in seqs]
    if todo:
        n_sim = simulated_frames(av, held)
        jobs = [Job(row, animate_job, (av.root, mat, held), total=n_sim) for row, mat in todo]
        for (row, _), (V, _) in zip(todo, run_jobs(jobs, progress=progress, title="evaluate: simulating")):
            seqs[row] = V
    metrics["seconds"]["references"] = round(time.time() - t0 - metrics["seconds"]["animate_estimated"], 1)
    # LBS: the garment skinned with weights transferred from the body (no physics).
    body = BodyModel(av.shape, topology="collider")
    Wg = garment_skinning_weights(t.vertices[gmask], body)
    from ..body import Motion as _M

    rest = _M("rest", av.fps, av.bone_names, av.rest_rotations[None], av.rest_translation[None]).for_bones(body.bone_names)
    hm = held.resample(av.fps).for_bones(body.bone_names)
    T_rel = body.pose(hm.rotations, hm.root_translation).bone_transforms @ \
        np.linalg.inv(body.pose(rest.rotations, rest.root_translation).bone_transforms[0])[None]
    lbs = est.vertices.copy()
    lbs[:, gmask] = linear_blend_skinning(t.vertices[gmask], Wg, T_rel)
    seqs["LBS"] = lbs

    def rows_of(V):
        V = V[: len(gt)]
        r = {"garment": _surface_rows(V[:, gmask], gt[:, gmask], gfaces_local, n_points, seed)}
        return r | ({"full": _surface_rows(V, gt, t.faces, n_points, seed)} if full else {})

    draws = {s: rows_of(seqs[random_draw_row(s)]) for s in random_seeds(seed, random_draws)}
    metrics["rows"]["random material"], metrics["random_draws"] = median_random_row(draws)
    metrics["random_draws"]["materials"] = [refs[random_draw_row(s)].to_dict() for s in metrics["random_draws"]["seeds"]]
    metrics["random_draws"]["contact_offset_mm"] = 1e3 * av.material.contact_offset
    for row in ROWS:
        if row in seqs:
            metrics["rows"][row] = rows_of(seqs[row])
    metrics["rows"] = {row: metrics["rows"][row] for row in ROWS if row in metrics["rows"]}
    median_mat = refs[random_draw_row(metrics["random_draws"]["median_seed"])]
    metrics["materials"] = {"estimated": av.material.to_dict(), "random": median_mat.to_dict(),
                            "true": refs["true material"].to_dict() if "true material" in refs else None,
                            "oracle": refs["oracle material"].to_dict() if "oracle material" in refs else None}

    # Appearance on the held-out views.
    cams_file = gt_root / "heldout" / "cameras.json"
    if views and cams_file.exists() and av.texture is not None:
        metrics["appearance"] = _appearance(cap, av, est, gt_root / "heldout", out, views_spp)


def _appearance(cap, av, seq, held_dir: Path, out: Path, spp: int) -> dict:
    """Views of ``ground_truth/heldout``'s cameras: the held-out motion's sequence against its images."""
    from ..camera import Camera

    cams = [Camera.from_dict(c) for c in read_json(held_dir / "cameras.json")]
    textured = av.texture is not None and seq.face_uvs is not None
    n = len(seq.vertices)
    return _score_views(av, seq.vertices, seq.faces, seq.face_uvs if textured else None, seq.labels,
                        {f: f for f in sorted({0, n // 2, n - 1})}, cams,
                        lambda cam, f: (held_dir / "images" / cam.name / f"{f:06d}.png",
                                        held_dir / "masks" / cam.name / f"{f:06d}.png"),
                        out / "views", spp)


def _holdout_cameras(cap, tracked, holdout) -> tuple[str, ...]:
    """The capture cameras to score: ``holdout`` as given, else those the tracking held out
    (its config.json), else none."""
    names = [c.name for c in cap.cameras]
    if holdout is None:
        cfg = Path(tracked) / "config.json" if tracked is not None else None
        holdout = tuple(read_json(cfg).get("holdout") or ()) if cfg is not None and cfg.is_file() else ()
    elif tracked is None and holdout:
        raise PhysavatarError(None, "option --holdout: scoring held-out cameras needs --tracked (the meshes to render)")
    unknown = [h for h in holdout if h not in names]
    if unknown:
        raise PhysavatarError(cap.root / "cameras.json", f"held-out camera(s) {', '.join(unknown)} not in the capture "
                              f"(cameras: {', '.join(names)})")
    return tuple(holdout)


def _capture_views(cap, av, tracked: Path, hold: tuple[str, ...], out: Path, spp: int) -> dict:
    """The capture's own held-out cameras: the tracked meshes at three frames (first, middle,
    last tracked), rendered with the avatar's texture and light, against the capture's images
    inside its masks (or inside the rendered silhouette when the capture has no masks)."""
    from ..capture import frame_name

    V = TrackedSequence.load(tracked).vertices
    t = av.template
    if V.shape[1] != len(t.vertices):
        raise PhysavatarError(tracked, f"tracked meshes have {V.shape[1]} vertices, the avatar {len(t.vertices)}: "
                              "not a tracking of this avatar's capture")
    n = len(V)
    frames = {i: cap.frames[i] for i in sorted({0, n // 2, n - 1})}
    cams = [c for c in cap.cameras if c.name in hold]
    textured = av.texture is not None and t.face_uvs is not None
    paths = lambda cam, f: (cap.root / "images" / cam.name / f"{frame_name(f)}.png",
                            cap.root / "masks" / cam.name / f"{frame_name(f)}.png")
    res = _score_views(av, V, t.faces, t.face_uvs if textured else None, t.labels, frames, cams, paths,
                       out / "holdout_views", spp)
    return {"cameras": list(hold), **res}


def _score_views(av, vertices, faces, face_uvs, labels, frames: dict, cams, paths, folder: Path, spp: int) -> dict:
    """PSNR, SSIM and LPIPS of renders of ``vertices[i]`` (i -> frame id in ``frames``) from
    ``cams`` against the images ``paths(cam, frame)`` gives (image, mask; the mask may be
    missing: then the rendered silhouette is the mask). Saves each pair under ``folder``."""
    from PIL import Image

    from ..capture import save_png
    from ..metrics import lpips, psnr, ssim
    from ..render import SceneSpec, linear_to_srgb8, load_scene, render
    from ..render.avatar import AvatarMeshes
    from ..render.lights import named_lights

    lights = named_lights("fitted" if av.light_path else "studio", vertices[0].mean(0), fitted=av.light_path)
    meshes = AvatarMeshes.build(vertices[0], faces, face_uvs, labels)
    rows = []
    for i, f in frames.items():
        scene = load_scene(SceneSpec(meshes=meshes.specs(vertices[i], av.texture if face_uvs is not None else None),
                                     lights=lights))
        for cam in cams:
            image_path, mask_path = paths(cam, f)
            gt_img = np.asarray(Image.open(image_path).convert("RGB"), np.float32) / 255
            out = render(scene, cam, spp=spp, seed=int(f))
            img = linear_to_srgb8(out.rgb).astype(np.float32) / 255
            if mask_path.is_file():
                m = np.asarray(Image.open(mask_path).convert("L"), np.float32) / 255 > 0.5
            else:
                m = np.asarray(out.alpha) > 0.5
            rows.append({"frame": int(f), "camera": cam.name, "psnr": float(psnr(img, gt_img, mask=m)),
                         "ssim": float(ssim(img * m[..., None], gt_img * m[..., None])),
                         "lpips": float(lpips(img * m[..., None], gt_img * m[..., None]))})
            save_png(folder / f"{cam.name}_{int(f):06d}_ours.png", img)
            save_png(folder / f"{cam.name}_{int(f):06d}_gt.png", gt_img)
    return {"views": rows, "psnr": float(np.mean([r["psnr"] for r in rows])),
            "ssim": float(np.mean([r["ssim"] for r in rows])), "lpips": float(np.mean([r["lpips"] for r in rows]))}


def _tracking(cap, tracked: Path) -> dict:
    from ..metrics import vertex_error_mm

    V = TrackedSequence.load(tracked).vertices
    gt = load_npz(cap.ground_truth / "meshes.npz")["vertices"]
    n = min(len(V), len(gt))
    labels = cap.template.labels
    out = {}
    for part, sel in (("garment", labels > 0), ("body", labels == 0)):
        e = vertex_error_mm(V[:n, sel], gt[:n, sel])
        out[part] = {"mean_mm": float(np.mean(e["mean_mm"])), "p95_mm": float(np.mean(e["p95_mm"])),
                     "per_frame_mean_mm": [float(x) for x in np.atleast_1d(e["mean_mm"])]}
    return out


def report_markdown(m: dict) -> str:
    lines = ["# Evaluation", "", f"Capture `{m['capture']}`, avatar `{m['avatar']}`."
             + (f" Held-out motion, {m['heldout_frames']} frames; surfaces sampled with {m['n_points']} points."
                if "heldout_frames" in m else ""), ""]
    if "heldout_cameras" in m:
        h = m["heldout_cameras"]
        lines += [f"## Held-out cameras of the capture ({', '.join(h['cameras'])})", "",
                  "The tracked meshes rendered with the avatar's texture and light, against the capture's images.", "",
                  "| PSNR ↑ | SSIM ↑ | LPIPS ↓ |", "| --- | --- | --- |",
                  f"| {h['psnr']:.2f} | {h['ssim']:.4f} | {h['lpips']:.4f} |", ""]
    if m["rows"]:
        lines += ["## Geometry (paper Table 2 layout)", "",
                  "| garment animated with | garment CD ×10³ (m²) ↓ | F@1cm ↑ | F@2cm ↑ | F@sq0.001 ↑ | full-mesh CD ×10³ ↓ | full F@1cm ↑ |",
                  "| --- | --- | --- | --- | --- | --- | --- |"]
    for row in ROWS:
        r = m["rows"].get(row)
        if r is None:
            continue
        g, f = r["garment"], r.get("full")
        full = f"{f['chamfer_x1e3']:.4f} | {f['fscore@1cm']:.3f}" if f else "– | –"
        lines.append(f"| {row} | {g['chamfer_x1e3']:.4f} | {g['fscore@1cm']:.3f} | {g['fscore@2cm']:.3f} | "
                     f"{g['fscore@sq0.001']:.3f} | {full} |")
    if "random_draws" in m:
        d = m["random_draws"]
        lines += ["", f"Random material: the median of {len(d['seeds'])} draws (seeds "
                  f"{', '.join(map(str, d['seeds']))}; garment CD ×10³ "
                  f"{', '.join(f'{v:.4f}' for v in d['garment_chamfer_x1e3'])}), the draw of seed {d['median_seed']}"
                  + (f"; simulated with the estimate's contact offset, {d['contact_offset_mm']:.2f} mm."
                     if d.get("contact_offset_mm") else ".")]
    if m["rows"]:
        lines += ["", "F@1cm and F@2cm use plain distances; F@sq0.001 compares squared distances with 0.001 m² "
                  "(≈3.2 cm), the convention of widely copied code.", ""]
    if "appearance" in m:
        a = m["appearance"]
        lines += ["## Appearance on held-out views (paper Table 1 layout)", "",
                  "| PSNR ↑ | SSIM ↑ | LPIPS ↓ |", "| --- | --- | --- |",
                  f"| {a['psnr']:.2f} | {a['ssim']:.4f} | {a['lpips']:.4f} |", ""]
    if "tracking" in m:
        lines += ["## Tracking", "", "| part | mean (mm) | p95 (mm) |", "| --- | --- | --- |"]
        for part, r in m["tracking"].items():
            lines.append(f"| {part} | {r['mean_mm']:.2f} | {r['p95_mm']:.2f} |")
        lines.append("")
    mat = m.get("materials", {})
    if mat.get("true"):
        e, tr = mat["estimated"], mat["true"]
        rel = lambda a, b: abs(a / b - 1)
        lines += ["## Material", "", "| | ρ (kg/m²) | κs (N/m) | κb (N·m) | κs/ρ | κb/ρ |", "| --- | --- | --- | --- | --- | --- |"]
        for name, d in (("estimated", e), ("true", tr), ("random", mat["random"])):
            lines.append(f"| {name} | {d['density']:.4g} | {d['stretch_stiffness']:.4g} | {d['bend_stiffness']:.4g} | "
                         f"{d['stretch_stiffness'] / d['density']:.4g} | {d['bend_stiffness'] / d['density']:.4g} |")
        lines += ["", f"Relative error of κs/ρ: {rel(e['stretch_stiffness'] / e['density'], tr['stretch_stiffness'] / tr['density']):.1%}; "
                  f"of κb/ρ: {rel(e['bend_stiffness'] / e['density'], tr['bend_stiffness'] / tr['density']):.1%}.", ""]
    return "\n".join(lines) + "\n"


# -- the stage entry points ----------------------------------------------------------------------

def _frames_ok(v):
    return None if v >= 2 else "use at least 2 frames"


def _draws_ok(v):
    return None if v >= 1 and v % 2 == 1 else "use an odd number of draws (the row is the median draw)"


@dataclass(frozen=True)
class EvaluateConfig:
    frames: int | None = option(None, "evaluate the first N held-out frames", check=_frames_ok)
    points: int = option(10000, "points sampled per surface for Chamfer / F-score",
                         check=lambda v: None if v >= 100 else "use at least 100 points")
    random_draws: int = option(RANDOM_DRAWS, "random materials drawn (seeds 0..N-1); the random row is their median",
                               check=_draws_ok)
    holdout: tuple[str, ...] | None = option(None, "capture cameras scored as held-out views, CAM,CAM "
                                             "(default: those the tracking held out)", parse=camera_list)


@dataclass(frozen=True)
class ReferencesConfig:
    frames: int | None = option(None, "the first N held-out frames", check=_frames_ok)
    seed: int = setting(0)
    random_draws: int = option(RANDOM_DRAWS, "random materials drawn (seeds seed..seed+N-1)", check=_draws_ok)
    contact_offset: float | None = option(None, "cloth contact thickness in m of the random draws (default: "
                                                "estimated on the template, as fit-physics estimates it)",
                                          flag="--contact-offset",
                                          check=lambda v: None if 0 <= v < 0.05 else "must be in [0, 0.05) m")
    rest_shape: str = option(FIT_REST_SHAPE, "the random draws' rest shape, the fit's (fit-physics --rest-shape): "
                                         "template or equilibrium", flag="--rest-shape", choices=REST_SHAPES)
    rest_friction: bool = option(FIT_REST_FRICTION, "the random draws' rest solve with static friction, the fit's "
                                                    "(fit-physics --rest-friction)", flag="--rest-friction")


def run(capture: Path, *, out: Path, config: EvaluateConfig = EvaluateConfig(), avatar: Path,
        tracked: Path | None = None, sequence: Path | None = None, references: Path | None = None,
        oracle: Path | None = None, progress=None) -> dict:
    """:func:`evaluate` as a stage: metrics.json and report.md in ``out``."""
    return evaluate(capture, avatar, out, tracked=tracked, frames=config.frames, n_points=config.points,
                    random_draws=config.random_draws, sequence=sequence, references=references, holdout=config.holdout, oracle=oracle,
                    progress=progress)


def run_references(capture: Path, *, out: Path, config: ReferencesConfig = ReferencesConfig(), progress=None) -> Path:
    """:func:`reference_sequences` as a stage (``physavatar reference-sims``)."""
    return reference_sequences(capture, out, frames=config.frames, seed=config.seed, random_draws=config.random_draws,
                               contact_offset=config.contact_offset, rest_shape=config.rest_shape,
                               rest_friction=config.rest_friction, progress=progress)
