"""The appearance stage alone on a foreign capture's finished run (issue 22 part 3).

    python benchmarks/foreign_appearance.py --case DIR --out WORK [--meshes tracked|gt]
                                            [--set light=env --set lr=0.005 ...] [--label NAME]
                                            [--results FILE]

DIR holds ``capture/`` and ``run/`` (a finished ``physavatar run --quick``, read only). The
texture and light are fitted again into WORK/appearance with ``run --quick``'s appearance settings
(:func:`physavatar.stages.appearance.pipeline_config`) changed by ``--set KEY=VALUE`` (fields of
``AppearanceConfig``), on the tracked meshes (as ``run``) or the true ones (``--meshes gt``: the
appearance model without tracking error), and scored exactly as ``evaluate`` scores a run
(``stages.evaluate._score_views``: 64 spp, inside the masks):

- the capture's held-out cameras (the tracking's ``holdout``) on the tracked meshes, frames first
  / middle / last;
- the held-out motion's novel cameras on the run's ``animate`` sequence, frames first / middle /
  last;
- the texture against the true one (``foreign_capture.texture_error``, on the faces some training
  pixel saw and on all faces);

and the same for T₀ (the projected texture before the Adam steps, under the fit's initial light)
when the fit wrote it. One JSON row per call is appended to ``--results`` (default
WORK/results.json). The run's own evaluate figures are copied beside it as ``run_evaluate``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path
from types import SimpleNamespace

os.environ.setdefault("OMP_NUM_THREADS", "2")
HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import numpy as np


def _parse_set(items: list[str]) -> dict:
    from physavatar.stages.appearance import AppearanceConfig

    types = {f.name: f.type for f in dataclasses.fields(AppearanceConfig)}
    out = {}
    for item in items:
        k, _, v = item.partition("=")
        if k not in types:
            raise SystemExit(f"--set {item}: {k} is not an AppearanceConfig field")
        t = str(types[k])
        out[k] = (float(v) if "float" in t else int(v) if "int" in t else
                  v.lower() in ("1", "true", "yes") if "bool" in t else v)
    return out


def _load_tracked(track: Path) -> np.ndarray:
    from physavatar.stages.evaluate import TrackedSequence

    return TrackedSequence.load(track).vertices


def score_views(capture: Path, run_dir: Path, texture: np.ndarray, light_path: Path, folder: Path,
                spp: int = 64) -> dict:
    """Held-out cameras (tracked meshes) and held-out motion (the run's animate sequence) of
    ``texture`` under ``light_path``, scored as `evaluate` scores them."""
    from physavatar.camera import Camera
    from physavatar.capture import frame_name, load_capture
    from physavatar.files import read_json
    from physavatar.stages.evaluate import AnimatedSequence, _score_views

    cap = load_capture(capture)
    t = cap.template
    av = SimpleNamespace(texture=texture, light_path=light_path)
    res = {}
    hold = tuple(read_json(run_dir / "track" / "config.json").get("holdout") or ())
    if hold:
        V = _load_tracked(run_dir / "track")
        n = len(V)
        frames = {i: cap.frames[i] for i in sorted({0, n // 2, n - 1})}
        r = _score_views(av, V, t.faces, t.face_uvs, t.labels, frames, [c for c in cap.cameras if c.name in hold],
                         lambda cam, f: (capture / "images" / cam.name / f"{frame_name(f)}.png",
                                         capture / "masks" / cam.name / f"{frame_name(f)}.png"),
                         folder / "holdout_views", spp)
        res["capture_heldout_cameras"] = {k: r[k] for k in ("psnr", "ssim", "lpips")}
    held = capture / "ground_truth" / "heldout"
    if (run_dir / "animate").is_dir() and (held / "cameras.json").is_file():
        seq = AnimatedSequence.load(run_dir / "animate")
        m = json.loads((run_dir / "evaluate" / "metrics.json").read_text())
        n = int(m.get("heldout_frames") or len(seq.vertices))
        cams = [Camera.from_dict(c) for c in read_json(held / "cameras.json")]
        r = _score_views(av, seq.vertices[:n], t.faces, t.face_uvs, t.labels, {f: f for f in sorted({0, n // 2, n - 1})},
                         cams, lambda cam, f: (held / "images" / cam.name / f"{f:06d}.png",
                                               held / "masks" / cam.name / f"{f:06d}.png"), folder / "views", spp)
        res["heldout_motion_views"] = {k: r[k] for k in ("psnr", "ssim", "lpips")}
    return res


def main(argv=None) -> int:
    from foreign_capture import texture_error
    from physavatar.files import write_json_atomic
    from physavatar.stages.appearance import pipeline_config
    from physavatar.stages.appearance.fit import fit_appearance

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", required=True, help="folder with capture/ and run/ (read only)")
    ap.add_argument("--out", required=True, help="work folder (the fit is written to OUT/appearance)")
    ap.add_argument("--meshes", default="tracked", choices=("tracked", "gt"))
    ap.add_argument("--schedule", default="quick", choices=("quick", "run"),
                    help="the appearance settings of `run --quick` (default) or of `run` (e.g. the own demo)")
    ap.add_argument("--set", action="append", default=[], help="AppearanceConfig field KEY=VALUE")
    ap.add_argument("--label", default=None)
    ap.add_argument("--no-init", action="store_true", help="do not score T0")
    ap.add_argument("--results", default=None)
    ap.add_argument("--score-run", action="store_true",
                    help="fit nothing: score the run's own appearance (checks that the scoring matches evaluate)")
    a = ap.parse_args(argv)
    case, out = Path(a.case), Path(a.out)
    capture, run_dir = case / "capture", case / "run"
    if a.score_run:
        import numpy as _np

        app = run_dir / "appearance"
        row = {"case": case.name, "label": "run's own appearance (scored here)",
               "fit": score_views(capture, run_dir, _np.load(app / "texture_linear.npy"), app / "light.json",
                                  out / "score_run"),
               "texture_error": texture_error(run_dir, capture)}
        ev = json.loads((run_dir / "evaluate" / "metrics.json").read_text())
        row["run_evaluate"] = {"capture_heldout_cameras": {k: ev["heldout_cameras"][k] for k in ("psnr", "ssim", "lpips")},
                               "heldout_motion_views": {k: ev["appearance"][k] for k in ("psnr", "ssim", "lpips")}}
        results = Path(a.results) if a.results else out / "results.json"
        rows = json.loads(results.read_text()) if results.is_file() else []
        write_json_atomic(results, rows + [row])
        print(json.dumps({k: row[k] for k in ("fit", "run_evaluate")}, indent=1))
        return 0
    cfg = dataclasses.replace(pipeline_config(quick=a.schedule == "quick"), meshes=a.meshes, **_parse_set(a.set))
    t0 = time.time()
    res = fit_appearance(capture, out / "appearance", cfg, tracked=run_dir / "track", progress=False)
    fit_s = time.time() - t0
    row = {"case": case.name, "schedule": a.schedule, "label": a.label or ",".join(a.set) or "default", "meshes": a.meshes,
           "config": cfg.to_dict(), "fit_seconds": round(fit_s, 1),
           "load_average": list(os.getloadavg()),
           "fit": score_views(capture, run_dir, res.texture, out / "appearance" / "light.json", out / "fit"),
           "texture_error": texture_error(out / "appearance", capture)}
    if not a.no_init and res.texture_init is not None:
        # T0 under the lights it was projected with (the fit's light before the Adam steps)
        lp = out / "appearance_init_light.json"
        lights = json.loads((out / "appearance" / "light.json").read_text())
        if cfg.light == "ambient":
            lights["lights"] = [{"type": "Ambient", "radiance": [cfg.ambient_init] * 3, "name": "ambient"}]
        lp.write_text(json.dumps(lights))
        row["init"] = score_views(capture, run_dir, res.texture_init, lp, out / "init")
        row["init"]["texture_error"] = texture_error(out / "appearance", capture, texture="texture_init_linear.npy")
    ev = json.loads((run_dir / "evaluate" / "metrics.json").read_text())
    row["run_evaluate"] = {"capture_heldout_cameras": {k: ev["heldout_cameras"][k] for k in ("psnr", "ssim", "lpips")}
                           if "heldout_cameras" in ev else None,
                           "heldout_motion_views": {k: ev["appearance"][k] for k in ("psnr", "ssim", "lpips")}
                           if "appearance" in ev else None}
    row["seconds"] = round(time.time() - t0, 1)
    results = Path(a.results) if a.results else out / "results.json"
    rows = json.loads(results.read_text()) if results.is_file() else []
    rows.append(row)
    write_json_atomic(results, rows)
    print(json.dumps({k: row[k] for k in ("case", "label", "fit", "texture_error")}, indent=1))
    if "init" in row:
        print("T0:", json.dumps(row["init"], indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
