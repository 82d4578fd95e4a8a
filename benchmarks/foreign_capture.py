"""Accuracy on captures physavatar did not make (issue 22 part 1): the foreign-capture benchmark.

    python benchmarks/foreign_capture.py [--full] [--cases NAME,NAME] [--work DIR] [--out FILE]
                                         [--dense-points N] [--add-dense] [--before OLD.json]

Builds captures with benchmarks/foreign/ (a generator that shares as little as possible with the
project: NVIDIA Newton's VBD cloth solver with penalty contact and its own membrane and bending
models, procedural garments that are not physavatar's designs, its own textures, lights, camera
rig and body shape; the body model, the file writers and the Mitsuba renderer are physavatar's),
runs `physavatar run` on each (pipeline.run, in process, `--quick` budgets unless --full) and
writes benchmarks/results/foreign_capture.json:

- tracking: garment / body mean and p95 vertex error per frame, and the garment's last-quarter
  over first-quarter ratio (frames after the first); per frame, the garment's error after each
  stage of the chain (start, fit, final), at the hem and the waist, and hidden from every training
  camera or seen (benchmarks/foreign_tracking.py, which also tracks the captures alone);
- material fit: RMS residual of the fit on the tracked garment and of the "oracle" fit on the
  true meshes (the model gap to Newton without tracking error), and the residual split into the
  model gap and the tracking share (`residual_split`);
- held-out motion: garment chamfer distance ×10³ of the estimated material, LBS, a random
  material and the oracle material, the truth's own CD (the sampling floor, `cd_floor`) and each
  row above it; the same rows and floor again at --dense-points (100,000: `evaluate` without
  views, reusing the run's reference, animate and oracle outputs), where the floor is a tenth
  and the raw ratios mean what the issue's targets say (benchmarks/foreign_physics.py measures
  the oracle side of these rows in minutes, without images);
- held-out views: PSNR / SSIM / LPIPS on the held-out motion's novel cameras and on the
  capture's own held-out cameras; texture error against the true texture; the ceiling of those
  scores (the true texture, lights and meshes rendered and scored the same way: the captures'
  and the scoring renders' Monte Carlo noise caps them: 26.8 dB on the plaid skirt at the old
  8 spp, 33.4 dB at the 64 spp the captures are now rendered with);
- checks: the targets of issue 22 (parts 2-4). Today most of them fail; the JSON records that.

--before OLD.json keeps an earlier result's date, code and checks under `before` (read at the start,
so it may be --out itself). Figures without a target (garment p95 and body tracking error, the
fit residual on the tracked and the true meshes and its tracking share, the texture error) are
under `checks` too, with `pass` null and target "reported".

--reuse-tracking keeps each case's finished tracking (and the appearance fitted on it) although
its recorded hash differs from today's, e.g. after a tracking setting was added whose default
does what the run did (session 29: the skirt's run predates `prediction.rest_shape`, whose default
"material" with the carry's cotton preset is the template rest it used): the new hashes are
recorded in run.json, the old ones kept as `hash_before_reuse`, so `run` redoes only the
physics and what follows. It is the caller's word that the tracking code did not change.

--add-dense adds the dense CD figures (and their checks) to the cases of an existing --out file
whose runs have finished, without running anything else.

Captures are cached in --work (default /tmp/foreign_capture): a capture whose config is unchanged
is not rebuilt and `physavatar run` resumes finished stages.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "2")
HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import numpy as np
from _common import cpu_name, quarter_ratio
from foreign.capture import ForeignConfig, build

# The reduced cases (default: fits ~30 min on 2 idle cores) and the full set.
QUICK_CASES = [
    ForeignConfig(name="skirt-plaid-256", garment="flared-skirt", texture="plaid", size=256, cameras=8,
                  frames=16, heldout_frames=12),
    ForeignConfig(name="top-print-512", garment="fitted-top", texture="print", size=512, cameras=6,
                  frames=10, heldout_frames=8, texture_size=1024),
    ForeignConfig(name="top-plain-256", garment="fitted-top", texture="plain", size=256, cameras=6,
                  frames=10, heldout_frames=8, motion="twist", heldout_motion="arm-swing"),
]
FULL_CASES = [
    ForeignConfig(name="skirt-plaid-256", garment="flared-skirt", texture="plaid", size=256, cameras=8,
                  frames=40, heldout_frames=32, spp=128),
    ForeignConfig(name="skirt-plaid-512", garment="flared-skirt", texture="plaid", size=512, cameras=8,
                  frames=40, heldout_frames=32, spp=128),
    ForeignConfig(name="top-print-512", garment="fitted-top", texture="print", size=512, cameras=10,
                  frames=40, heldout_frames=32, spp=128),
    ForeignConfig(name="skirt-plain-256", garment="flared-skirt", texture="plain", size=256, cameras=12,
                  frames=40, heldout_frames=32, spp=128),
]


def _sample(tex: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup [N, 3] of a [H, W, 3] texture at UVs [N, 2] (row 0 = v 1)."""
    from scipy.ndimage import map_coordinates

    H, W = tex.shape[:2]
    x, y = uv[:, 0] * W - 0.5, (1 - uv[:, 1]) * H - 0.5
    return np.stack([map_coordinates(tex[..., c], [y, x], order=1, mode="nearest") for c in range(3)], 1)


def texture_error(run_dir: Path, capture: Path, texture: str = "texture_linear.npy") -> dict | None:
    """The fitted albedo against the true one on the surface: both textures are looked up at the
    same surface points (7 barycentric points per template face; the true texture through the
    template's UVs, the fitted one through the appearance stage's own atlas, atlas.npz) and
    compared: PSNR [dB] of the sRGB values and mean absolute error of the linear ones, garment and
    body apart, as they are and after the per-channel gain that fits them best (the fitted light
    and albedo share a scale).

    Each part is scored on the faces some training pixel saw (``atlas.npz``'s ``face_pixels`` > 0:
    the top level of each part's figures) and on all of its faces (``all_faces``: the body under a
    garment and the soles, which no image shows, are inpainted and count there too).
    ``psnr_srgb_truth_at_fit_size``: the true texture area-averaged to the fitted atlas' size and
    scored the same way, the best a texture of that size can score (print top, 1024² truth, 512²
    fit: garment 26 dB; the plaid 20 dB: most of the garments' texture error is detail no texture
    of the fitted size, and no 256 px image, holds). ``texture``:
    the file in ``run_dir/appearance`` (or ``run_dir`` itself when it is an appearance folder) to
    score, e.g. ``texture_init_linear.npy`` for T₀."""
    from physavatar.capture import load_capture
    from physavatar.render import linear_to_srgb

    app = run_dir / "appearance" if (run_dir / "appearance").is_dir() else run_dir
    true_file = capture / "ground_truth" / "texture_linear.npy"
    if not (app / texture).exists() or not (app / "atlas.npz").exists() or not true_file.exists():
        return None
    true, fit = np.load(true_file), np.load(app / texture)
    atlas = np.load(app / "atlas.npz")
    fit_uvs = atlas["face_uvs"]
    seen = atlas["face_pixels"] > 0 if "face_pixels" in atlas.files else np.ones(len(fit_uvs), bool)
    t = load_capture(capture).template
    if len(fit_uvs) != len(t.faces):
        return None
    w = np.array([[1, 1, 1], [4, 1, 1], [1, 4, 1], [1, 1, 4], [2, 2, 1], [2, 1, 2], [1, 2, 2]], float)
    w /= w.sum(1, keepdims=True)

    def scores(sel):
        a = _sample(true, np.einsum("sk,fkd->fsd", w, t.face_uvs[sel]).reshape(-1, 2))
        b = _sample(fit, np.einsum("sk,fkd->fsd", w, fit_uvs[sel]).reshape(-1, 2))

        def psnr(x):
            mse = float(np.mean((linear_to_srgb(np.clip(a, 0, 1)) - linear_to_srgb(np.clip(x, 0, 1))) ** 2))
            return float(10 * np.log10(1 / max(mse, 1e-12)))

        # albedo and light trade a scale: also after the best per-channel gain
        gain = (a * b).sum(0) / np.maximum((b * b).sum(0), 1e-12)
        return {"faces": int(sel.sum()), "psnr_srgb": psnr(b), "mae_linear": float(np.mean(np.abs(a - b))),
                "gain_rgb": gain.tolist(), "psnr_srgb_after_gain": psnr(b * gain),
                "mae_linear_after_gain": float(np.mean(np.abs(a - b * gain)))}

    def floor(sel):
        # the truth itself at the fitted atlas' resolution (area-averaged), scored the same way:
        # what a perfect fit of this size scores (the images resolve less still)
        k = true.shape[0] // fit.shape[0]
        if k <= 1 or true.shape[0] % fit.shape[0] or true.shape[1] != true.shape[0] * fit.shape[1] // fit.shape[0]:
            return None
        small = true.reshape(fit.shape[0], k, fit.shape[1], k, 3).mean((1, 3))
        a = _sample(true, np.einsum("sk,fkd->fsd", w, t.face_uvs[sel]).reshape(-1, 2))
        b = _sample(small, np.einsum("sk,fkd->fsd", w, t.face_uvs[sel]).reshape(-1, 2))
        mse = float(np.mean((linear_to_srgb(np.clip(a, 0, 1)) - linear_to_srgb(np.clip(b, 0, 1))) ** 2))
        return float(10 * np.log10(1 / max(mse, 1e-12)))

    out = {}
    for part, sel in (("garment", (t.labels[t.faces] > 0).all(1)), ("body", (t.labels[t.faces] == 0).all(1))):
        out[part] = {**scores(sel & seen), "all_faces": scores(sel), "psnr_srgb_truth_at_fit_size": floor(sel & seen)}
    return out


def appearance_ceiling(capture: Path, spp: int = 64) -> dict:
    """What a perfect appearance scores on the held-out views: the true texture under the true
    lights on the true meshes, rendered and scored as `evaluate` renders and scores the fitted
    avatar (same frames, cameras, spp, masks). The captures are path traced (64 spp, ForeignConfig.spp),
    so even this render differs from their images by their and its own Monte Carlo noise: the
    PSNR / LPIPS targets are measured against this ceiling."""
    from types import SimpleNamespace

    from physavatar.camera import Camera
    from physavatar.capture import frame_name, load_capture
    from physavatar.files import load_npz, read_json
    from physavatar.stages.evaluate import _score_views

    cap = load_capture(capture)
    t = cap.template
    gt = capture / "ground_truth"
    av = SimpleNamespace(texture=np.load(gt / "texture_linear.npy"), light_path=gt / "lighting.json")
    out = Path(os.environ.get("TMPDIR", "/tmp")) / "foreign_ceiling_views"
    held = gt / "heldout"
    V = load_npz(held / "meshes.npz")["vertices"]
    n = len(V)
    cams = [Camera.from_dict(c) for c in read_json(held / "cameras.json")]
    motion = _score_views(av, V, t.faces, t.face_uvs, t.labels, {f: f for f in sorted({0, n // 2, n - 1})}, cams,
                          lambda cam, f: (held / "images" / cam.name / f"{f:06d}.png",
                                          held / "masks" / cam.name / f"{f:06d}.png"), out / "motion", spp)
    res = {"heldout_motion_views": {k: motion[k] for k in ("psnr", "ssim", "lpips")}}
    track_cfg = capture.parent / "run" / "track" / "config.json"
    hold = tuple(read_json(track_cfg).get("holdout") or ()) if track_cfg.is_file() else ()
    if hold:
        Vc = load_npz(gt / "meshes.npz")["vertices"]
        tracked = capture.parent / "run" / "track" / "tracked.npz"
        m = len(load_npz(tracked)["vertices"]) if tracked.is_file() else len(Vc)
        frames = {i: cap.frames[i] for i in sorted({0, m // 2, m - 1})}
        r = _score_views(av, Vc, t.faces, t.face_uvs, t.labels, frames, [c for c in cap.cameras if c.name in hold],
                         lambda cam, f: (capture / "images" / cam.name / f"{frame_name(f)}.png",
                                         capture / "masks" / cam.name / f"{frame_name(f)}.png"), out / "cams", spp)
        res["capture_heldout_cameras"] = {k: r[k] for k in ("psnr", "ssim", "lpips")}
    return res


def figures_for(cfg: ForeignConfig, capture: Path, run_dir: Path, record: dict) -> dict:
    m = json.loads((run_dir / "evaluate" / "metrics.json").read_text())
    fig: dict = {"size_px": cfg.size, "cameras": cfg.cameras, "frames": cfg.frames, "heldout_frames": cfg.heldout_frames,
                 "garment": cfg.garment, "texture": cfg.texture, "motion": cfg.motion, "heldout_motion": cfg.heldout_motion}
    tr = m.get("tracking", {})
    if tr:
        g = tr["garment"]
        fig["tracking"] = {"garment_mean_mm": g["mean_mm"], "garment_p95_mm": g["p95_mm"],
                           "garment_per_frame_mean_mm": g["per_frame_mean_mm"],
                           "garment_last_over_first_quarter": quarter_ratio(g["per_frame_mean_mm"]),
                           "body_mean_mm": tr["body"]["mean_mm"], "body_p95_mm": tr["body"]["p95_mm"]}
        track_dir = run_dir / "track"
        if (track_dir / "config.json").exists():  # stage by stage, hem / waist, hidden / seen
            from foreign_tracking import tracking_figures
            from physavatar.capture import load_capture

            held = json.loads((track_dir / "config.json").read_text())["holdout"]
            cap = load_capture(capture)
            names = [c.name for c in cap.cameras if c.name not in held]
            fig["tracking"]["breakdown_mm"] = tracking_figures(capture, track_dir, cap.frames[:len(g["per_frame_mean_mm"])],
                                                               names)["per_frame_mm"]
    fig.update(physics_figures(capture, run_dir, m))
    app = m.get("appearance")
    if app:
        fig["heldout_motion_views"] = {k: app[k] for k in ("psnr", "ssim", "lpips")}
    hc = m.get("heldout_cameras")
    if hc:
        fig["capture_heldout_cameras"] = {"cameras": hc["cameras"], **{k: hc[k] for k in ("psnr", "ssim", "lpips")}}
    fig["texture_error"] = texture_error(run_dir, capture)
    if (capture / "ground_truth" / "texture_linear.npy").exists() and (capture / "ground_truth" / "heldout").exists():
        fig["appearance_ceiling"] = appearance_ceiling(capture)
    fig["seconds"] = {k: v.get("seconds") for k, v in record.items() if isinstance(v, dict) and "seconds" in v}
    return fig


def cd_floor(capture: Path, n_points: int, frames: int | None = None, seed: int = 0) -> dict:
    """The held-out garment chamfer distance ×10³ of the truth itself: the true meshes against
    themselves, sampled as `evaluate` samples a row and the truth (n_points, seeds seed + t and
    seed + t + 1). Two samplings of one surface are not at distance 0 (docs/evaluation.md: E[d²]
    = A / (π n) per side), so no row can score below this; on the fitted tops (area ~0.3 m²,
    10,000 points) it is 0.0088, nearly all of LBS's 0.0098."""
    from physavatar.capture import load_capture
    from physavatar.files import load_npz
    from physavatar.geometry import submesh
    from physavatar.stages.evaluate import _surface_rows

    t = load_capture(capture).template
    g = t.labels > 0
    V = load_npz(capture / "ground_truth" / "heldout" / "meshes.npz")["vertices"].astype(np.float64)[:frames, g]
    _, gf = submesh(t.faces, g)
    r = _surface_rows(V, V, gf, n_points, seed)
    return {"chamfer_x1e3": r["chamfer_x1e3"], "per_frame_chamfer_x1e3": r["per_frame_chamfer_x1e3"]}


DENSE_POINTS = 100_000


def dense_cd(capture: Path, run_dir: Path, metrics: dict, points: int = DENSE_POINTS) -> dict | None:
    """The held-out garment CD rows again at ``points`` surface points, and the floor at that
    count: `evaluate` without views or full-mesh rows on the run's own outputs (the references'
    random draws, the animate sequence, the oracle fit; only the oracle row and LBS are
    simulated / skinned again),
    cached in run_dir/evaluate_<points> while it is newer than the run's evaluate."""
    from physavatar.stages.evaluate import evaluate

    base = run_dir / "evaluate" / "metrics.json"
    if not base.is_file() or not metrics.get("rows"):
        return None
    folder = run_dir / f"evaluate_{points}"
    t0 = time.time()
    f = folder / "metrics.json"
    if f.is_file() and f.stat().st_mtime > base.stat().st_mtime:
        m = json.loads(f.read_text())
    else:
        m = evaluate(capture, run_dir / "avatar", folder, frames=metrics.get("heldout_frames"), n_points=points,
                     sequence=run_dir / "animate", references=run_dir / "references",
                     oracle=run_dir / "oracle" if (run_dir / "oracle" / "material.json").is_file() else None,
                     views=False, full=False, progress=False)
    floor = cd_floor(capture, points, metrics.get("heldout_frames"))
    cd = {r: v["garment"]["chamfer_x1e3"] for r, v in m["rows"].items()}
    return {"points": points, "heldout_garment_cd_x1e3": cd, "floor_x1e3": floor["chamfer_x1e3"],
            "above_floor_x1e3": {r: v - floor["chamfer_x1e3"] for r, v in cd.items()},
            "random_draws": {k: m["random_draws"][k] for k in ("seeds", "garment_chamfer_x1e3", "median_seed")},
            "seconds": round(time.time() - t0, 1)}


def _fit_record(folder: Path) -> dict | None:
    f = folder / "material.json"
    if not f.exists():
        return None
    d = json.loads(f.read_text())
    mat = d.get("material", d)
    cfg = json.loads((folder / "config.json").read_text()) if (folder / "config.json").exists() else {}
    return {"rms_mm": d.get("rms_mm"), "initial_rms_mm": d.get("initial_rms_mm"),
            "stretch_ratio": d.get("ratios", {}).get("stretch_ratio", {}).get("value"),
            "bend_ratio": d.get("ratios", {}).get("bend_ratio", {}).get("value"),
            "stretch_stiffness": mat.get("stretch_stiffness"), "bend_stiffness": mat.get("bend_stiffness"),
            "density": mat.get("density"), "integrator": d.get("integrator"), "bdf2_blend": mat.get("bdf2_blend"),
            "at_bound": d.get("at_bound"), "iterations": d.get("iterations"),
            "window": cfg.get("window"), "start": cfg.get("start", 0)}


def residual_split(capture: Path, run_dir: Path, tracked: dict | None, oracle: dict | None) -> dict | None:
    """How much of the fit residual on the tracked meshes is tracking error and how much the
    model gap: the fit on the true meshes (the oracle) has no tracking error, so its RMS residual
    is the model gap to Newton; the tracked fit's residual, in quadrature, is that plus the
    tracking error's share (negative when the tracked meshes are easier to follow than the truth,
    e.g. when tracking smooths away motion). Also the tracking error itself over the fitted window."""
    if not tracked or not oracle or tracked.get("rms_mm") is None or oracle.get("rms_mm") is None:
        return None
    out = {"fit_on_tracked_rms_mm": tracked["rms_mm"], "fit_on_true_rms_mm_model_gap": oracle["rms_mm"]}
    d2 = tracked["rms_mm"] ** 2 - oracle["rms_mm"] ** 2
    out["tracking_share_mm"] = float(np.sign(d2) * np.sqrt(abs(d2)))
    out["model_gap_fraction_of_squared_residual"] = float(oracle["rms_mm"] ** 2 / max(tracked["rms_mm"] ** 2, 1e-12))
    tr_file = run_dir / "track" / "tracked.npz"
    if tr_file.exists() and tracked.get("window"):
        from physavatar.capture import load_capture
        from physavatar.files import load_npz

        g = load_capture(capture).template.labels > 0
        a, w = int(tracked.get("start") or 0), int(tracked["window"])
        T = load_npz(tr_file)["vertices"][a:a + w][:, g].astype(np.float64)
        G = load_npz(capture / "ground_truth" / "meshes.npz")["vertices"][a:a + len(T)][:, g].astype(np.float64)
        out["tracking_error_rms_mm_on_window"] = 1e3 * float(np.sqrt(((T - G) ** 2).sum(-1).mean()))
    return out


def physics_figures(capture: Path, run_dir: Path, metrics: dict) -> dict:
    """Issue 22 part 4: the material fits (tracked and true meshes), the residual's split, the
    held-out garment CD rows, the truth's own CD (the sampling floor) and every row above it."""
    fits = {"tracked": _fit_record(run_dir / "physics"), "true_meshes_oracle": _fit_record(run_dir / "oracle")}
    out: dict = {"material_fit": fits,
                 "fit_residual_split": residual_split(capture, run_dir, fits["tracked"], fits["true_meshes_oracle"])}
    rows = metrics.get("rows", {})
    out["heldout_garment_cd_x1e3"] = {r: rows[r]["garment"]["chamfer_x1e3"] for r in rows}
    out["heldout_garment_cd_per_frame_x1e3"] = {r: rows[r]["garment"]["per_frame_chamfer_x1e3"] for r in rows}
    if rows and (capture / "ground_truth" / "heldout" / "meshes.npz").exists():
        floor = cd_floor(capture, metrics.get("n_points", 10000), metrics.get("heldout_frames"))
        out["heldout_garment_cd_floor_x1e3"] = floor["chamfer_x1e3"]
        out["heldout_garment_cd_above_floor_x1e3"] = {r: v - floor["chamfer_x1e3"]
                                                      for r, v in out["heldout_garment_cd_x1e3"].items()}
    return out


def physics_checks(name: str, fig: dict) -> dict:
    """CD ≥ 25 % below LBS and ≥ 10 % below random (the median of `evaluate`'s draws), on the CD
    above the truth's own (the floor, :func:`cd_floor`): at 10,000 points the raw ratio cannot
    tell rows apart where every row is within a few percent of the floor (the tops: the truth
    itself is only 9 % below LBS). With the dense CD (:func:`dense_cd`, 100,000 points: the floor
    a tenth of 10,000's, and its sampling noise far smaller) the check is the ratio above the
    floor there; the raw ratios (``raw_value`` at 10,000 points, ``raw_value_dense``) and the
    10,000-point ratio above the floor (``value_10k``) are kept beside it. The raw ratio alone is
    not yet the check: at 100,000 points the plain top's truth is still only 22 % below LBS."""
    c = {}
    cd = fig.get("heldout_garment_cd_x1e3", {})
    above = fig.get("heldout_garment_cd_above_floor_x1e3") or {}
    dense = fig.get("heldout_garment_cd_dense") or {}
    est = cd.get("estimated material")
    for row, key, target in (("LBS", "below_lbs", 0.25), ("random material", "below_random", 0.10)):
        if est is None or row not in cd:
            continue
        raw = 1 - est / cd[row]
        dcd = dense.get("heldout_garment_cd_x1e3", {})
        if "estimated material" in dcd and row in dcd:
            fl = dense["floor_x1e3"]
            v = 1 - (dcd["estimated material"] - fl) / max(dcd[row] - fl, 1e-12)
            c[f"{name}:heldout_cd_{key}"] = {
                "value": v, "target": f">= {target}",
                "unit": f"1 - (CD - floor)/(CD_{row} - floor) at {dense['points']} points",
                "floor_x1e3": fl, "raw_value_dense": 1 - dcd["estimated material"] / dcd[row], "raw_value": raw,
                "value_10k": 1 - above["estimated material"] / max(above[row], 1e-12) if above else None,
                "floor_10k_x1e3": fig.get("heldout_garment_cd_floor_x1e3"), "pass": v >= target}
        elif above:
            v = 1 - above["estimated material"] / max(above[row], 1e-12)
            c[f"{name}:heldout_cd_{key}"] = {"value": v, "target": f">= {target}",
                                             "unit": f"1 - (CD - floor)/(CD_{row} - floor)", "raw_value": raw,
                                             "floor_x1e3": fig["heldout_garment_cd_floor_x1e3"], "pass": v >= target}
        else:
            c[f"{name}:heldout_cd_{key}"] = {"value": raw, "target": f">= {target}", "unit": f"1 - CD/CD_{row}",
                                             "pass": raw >= target}
    return c


def checks_for(name: str, fig: dict) -> dict:
    c = {}
    tr = fig.get("tracking")
    if tr:
        lim = 5.0 if fig["size_px"] >= 512 else 8.0
        c[f"{name}:tracking_garment_mean"] = {"value": tr["garment_mean_mm"], "target": f"<= {lim}", "unit": "mm",
                                              "pass": tr["garment_mean_mm"] <= lim}
        r = tr["garment_last_over_first_quarter"]
        c[f"{name}:tracking_no_drift"] = {"value": r, "target": "<= 1.5", "unit": "last/first quarter",
                                          "pass": bool(r <= 1.5)}
    app = fig.get("heldout_motion_views")
    if app:
        c[f"{name}:heldout_views_psnr"] = {"value": app["psnr"], "target": ">= 28", "unit": "dB", "pass": app["psnr"] >= 28}
        c[f"{name}:heldout_views_lpips"] = {"value": app["lpips"], "target": "<= 0.03", "unit": "LPIPS",
                                            "pass": app["lpips"] <= 0.03}
    hc = fig.get("capture_heldout_cameras")
    if hc:  # the same targets on the capture's own held-out cameras (the tracked meshes rendered)
        c[f"{name}:capture_heldout_cameras_psnr"] = {"value": hc["psnr"], "target": ">= 28", "unit": "dB",
                                                     "pass": hc["psnr"] >= 28}
        c[f"{name}:capture_heldout_cameras_lpips"] = {"value": hc["lpips"], "target": "<= 0.03", "unit": "LPIPS",
                                                      "pass": hc["lpips"] <= 0.03}
    c.update(physics_checks(name, fig))
    c.update(reported(name, fig))
    return c


def reported(name: str, fig: dict) -> dict:
    """The figures issue 22 asks to report without a target, as checks with ``pass`` None
    (``target`` "reported"): the garment p95 and body mean tracking error, the material fit's RMS
    residual on the tracked and on the true meshes and the residual's tracking share, and the
    fitted texture against the true one (sRGB PSNR after the best gain, seen faces)."""
    out = {}

    def put(key, value, unit):
        if value is not None:
            out[f"{name}:{key}"] = {"value": value, "target": "reported", "unit": unit, "pass": None}

    tr = fig.get("tracking") or {}
    put("tracking_garment_p95", tr.get("garment_p95_mm"), "mm")
    put("tracking_body_mean", tr.get("body_mean_mm"), "mm")
    fits = fig.get("material_fit") or {}
    put("fit_residual_tracked_rms", (fits.get("tracked") or {}).get("rms_mm"), "mm")
    put("fit_residual_true_meshes_rms", (fits.get("true_meshes_oracle") or {}).get("rms_mm"), "mm (model gap)")
    put("fit_residual_tracking_share", (fig.get("fit_residual_split") or {}).get("tracking_share_mm"),
        "mm (in quadrature)")
    te = fig.get("texture_error") or {}
    for part in ("garment", "body"):
        put(f"texture_psnr_{part}", (te.get(part) or {}).get("psnr_srgb_after_gain"), "dB sRGB after gain")
    return out


def pass_count(checks: dict) -> str:
    """"N/M pass" over the checks with a target (reported figures apart)."""
    judged = [c["pass"] for c in checks.values() if c.get("pass") is not None]
    return f"{sum(judged)}/{len(judged)} pass ({len(checks) - len(judged)} reported without a target)"


def reuse_tracking(capture: Path, run_dir: Path, rc) -> list[str]:
    """--reuse-tracking: record today's hash for the finished ``track`` step of ``run_dir`` (and
    for ``appearance`` when it was up to date with that tracking), keeping the old ones as
    ``hash_before_reuse``. Returns the steps re-recorded. Nothing changes for a run whose track
    step did not finish or whose hash is today's."""
    from physavatar.files import read_json, write_json_atomic
    from physavatar.pipeline import plan, step_hash

    rec_path = run_dir / "run.json"
    if not rec_path.is_file():
        return []
    rec = read_json(rec_path)
    steps = {st.name: st for st in plan(capture, run_dir, rc)}
    tr = rec.get("track", {})
    if "track" not in steps or tr.get("status") != "ok" or not (run_dir / "track" / steps["track"].done_file).exists():
        return []
    old = dict(rec)
    new_hash = step_hash(steps["track"], run_dir, rec)
    if tr.get("hash") == new_hash:
        return []
    done = ["track"]
    rec["track"] = tr | {"hash": new_hash, "hash_before_reuse": tr.get("hash")}
    app = rec.get("appearance", {})
    if "appearance" in steps and app.get("status") == "ok" and app.get("hash") == step_hash(steps["appearance"], run_dir, old):
        rec["appearance"] = app | {"hash": step_hash(steps["appearance"], run_dir, rec), "hash_before_reuse": app["hash"]}
        done.append("appearance")
    write_json_atomic(rec_path, rec)
    return done


def _metrics(run_dir: Path) -> dict:
    return json.loads((run_dir / "evaluate" / "metrics.json").read_text())


def add_dense(out: Path, work: Path, cases: str | None, points: int) -> int:
    """--add-dense: the dense CD rows of each finished case of ``out``, its checks again."""
    result = json.loads(out.read_text())
    for name, fig in result["figures"].items():
        if "error" in fig or (cases and name not in cases.split(",")):
            continue
        run_dir = work / name / "run"
        fig["heldout_garment_cd_dense"] = dense_cd(work / name / "capture", run_dir, _metrics(run_dir), points)
        result["checks"].update(checks_for(name, fig))
        out.write_text(json.dumps(result, indent=2) + "\n")
        d = fig["heldout_garment_cd_dense"]
        print(name, json.dumps({k: d[k] for k in ("heldout_garment_cd_x1e3", "floor_x1e3", "seconds")}), flush=True)
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--full", action="store_true", help="all cases, 40 frames, full `physavatar run` budgets")
    ap.add_argument("--cases", default=None, help="comma-separated case names, run in this order (default: all of the set)")
    ap.add_argument("--frames", type=int, default=None, help="override the training frames of every case")
    ap.add_argument("--heldout-frames", type=int, default=None, help="override the held-out frames of every case")
    ap.add_argument("--work", default="/tmp/foreign_capture", help="captures and runs are kept here")
    ap.add_argument("--out", default=str(HERE / "results" / "foreign_capture.json"))
    ap.add_argument("--dense-points", type=int, default=DENSE_POINTS,
                    help="surface points of the dense CD rows (0: none)")
    ap.add_argument("--before", default=None,
                    help="an earlier result file: its date, code and checks are kept under `before`")
    ap.add_argument("--reuse-tracking", action="store_true",
                    help="keep each case's finished tracking (and appearance) although its hash differs from today's")
    ap.add_argument("--add-dense", action="store_true",
                    help="only add the dense CD rows and their checks to the finished cases of --out")
    args = ap.parse_args(argv)
    if args.add_dense:
        return add_dense(Path(args.out), Path(args.work), args.cases, args.dense_points)
    from physavatar.pipeline import RunConfig, run

    cases = FULL_CASES if args.full else QUICK_CASES
    if args.cases:
        want = args.cases.split(",")  # run in the order given (session 34: the short tops before the skirt)
        cases = sorted((c for c in cases if c.name in want), key=lambda c: want.index(c.name))
    if args.frames or args.heldout_frames:
        cases = [dataclasses.replace(c, frames=args.frames or c.frames,
                                     heldout_frames=args.heldout_frames or c.heldout_frames) for c in cases]
    work = Path(args.work)
    out = Path(args.out)
    result = {"benchmark": "foreign_capture", "date": datetime.datetime.now().isoformat(timespec="seconds"),
              "machine": {"cores": os.cpu_count(), "cpu": cpu_name(), "gpu": None,
                          "load_average_start": list(os.getloadavg())},
              "config": {"full": args.full, "run": "physavatar run " + ("" if args.full else "--quick"),
                         "reuse_tracking": args.reuse_tracking,
                         "cases": [c.to_dict() for c in cases]},
              "figures": {}, "checks": {}}
    if args.before:  # an earlier file's checks beside today's (read now: --out may be the same file)
        old = json.loads(Path(args.before).read_text())
        # its checks recomputed from its figures by today's rules, so every check has a before
        result["before"] = {"file": args.before, "date": old.get("date"), "code": old.get("config", {}).get("code"),
                            "checks": {k: v for n, f in old.get("figures", {}).items() if "error" not in f
                                       for k, v in checks_for(n, f).items()}}
    for cfg in cases:
        t0 = time.time()
        cap = build(work / cfg.name / "capture", cfg, say=lambda s: print(s, flush=True))
        run_dir = work / cfg.name / "run"
        rc = RunConfig(quick=not args.full)
        from physavatar.errors import PhysavatarError

        if args.reuse_tracking:
            kept = reuse_tracking(cap, run_dir, rc)
            if kept:
                print(f"[{cfg.name}] --reuse-tracking: kept the finished {', '.join(kept)} (today's hash recorded)", flush=True)

        try:
            record = run(cap, run_dir, rc, say=lambda s, n=cfg.name: print(f"[{n}] {s}", flush=True))
        except PhysavatarError as e:  # recorded, and the next case still runs
            print(f"[{cfg.name}] run failed: {e}", flush=True)
            result["figures"][cfg.name] = {"error": str(e)}
            result["checks"][f"{cfg.name}:run_completes"] = {"value": 0, "target": "1", "unit": "bool", "pass": False}
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_text(json.dumps(result, indent=2) + "\n")
            continue
        fig = figures_for(cfg, cap, run_dir, record)
        if args.dense_points:
            fig["heldout_garment_cd_dense"] = dense_cd(cap, run_dir, _metrics(run_dir), args.dense_points)
        gen = json.loads((cap / "ground_truth" / "foreign.json").read_text())
        # from the files, so a rerun that reuses the cached capture and run reports the same times
        fig["seconds"]["stages_sum"] = round(sum(v for v in fig["seconds"].values() if isinstance(v, (int, float))), 1)
        fig["seconds"]["build_capture"] = gen["seconds"]["total"]
        fig["seconds"]["wall_this_invocation"] = round(time.time() - t0, 1)
        fig["generator"] = {k: gen[k] for k in ("fabric_newton", "newton_settings", "seconds", "garment_vertices")}
        result["figures"][cfg.name] = fig
        result["checks"].update(checks_for(cfg.name, fig))
        result["machine"]["load_average_end"] = list(os.getloadavg())
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(result, indent=2) + "\n")  # after every case: a partial result survives
        print(json.dumps({cfg.name: {k: v for k, v in fig.items() if k not in ("seconds",)}}, indent=1)[:3000], flush=True)
    print(f"checks: {pass_count(result['checks'])}; wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
