"""Appearance accuracy (PhysAvatar Sec. 3.3, Table 2 "w/o appearance") on the demo capture.

    python benchmarks/appearance_accuracy.py [--capture /tmp/demo_capture] [--quick] [--iterations N]

Fits the texture by inverse rendering on the capture's ground-truth meshes (so that only the
appearance stage is measured) with both lighting models, ``ambient`` (the paper: texture + L_a)
and ``studio`` (texture + ambient + the known key light's intensity), then renders the held-out
motion (``ground_truth/heldout``: unseen frames of another motion) from its cameras and compares
with the held-out images inside their masks:

- PSNR / SSIM (sRGB) of the fitted texture + fitted light, and of the initial per-face-colour
  texture T_0 under its best ambient light (the "w/o appearance" ablation);
- texture PSNR against the true albedo atlas over covered texels (inside a UV chart of a face
  some training pixel saw), raw and after the per-channel least-squares gain (texture and light
  are only determined up to a common factor);
- seconds per iteration at the demo resolution.

Writes benchmarks/results/appearance_accuracy.json.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from physavatar.capture import load_capture
from physavatar.render import Ambient, light_to_json
from physavatar.stages.appearance import AppearanceConfig
from physavatar.stages.appearance.data import load_appearance_data
from physavatar.stages.appearance.evaluation import (
    baked_shading,
    best_ambient,
    covered_texels,
    heldout_metrics,
    texture_psnr,
)
from physavatar.stages.appearance.fit import fit_appearance

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _common import cpu_name  # noqa: E402




def check(value, target: str, unit: str) -> dict:
    op, bound = target.split()
    ok = value >= float(bound) if op == ">=" else value > float(bound)
    return {"value": round(float(value), 4), "target": target, "unit": unit, "pass": bool(ok)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--capture", type=Path, default=Path("/tmp/demo_capture"))
    ap.add_argument("--work", type=Path, default=Path("/tmp/appearance_benchmark"))
    ap.add_argument("--quick", action="store_true", help="fewer iterations and held-out frames, lower spp")
    ap.add_argument("--iterations", type=int, default=None)
    ap.add_argument("--texture-size", type=int, default=512)
    ap.add_argument("--lr", type=float, default=0.02)
    ap.add_argument("--modes", default="ambient,studio")
    args = ap.parse_args()

    if not args.capture.is_dir():
        print(f"building the demo capture at {args.capture} (about 10 minutes)")
        subprocess.run([sys.executable, "-m", "physavatar", "synth", str(args.capture), "--preset", "demo"], check=True)
    cap = load_capture(args.capture)
    iters = args.iterations or (120 if args.quick else 600)
    eval_spp = 32 if args.quick else 128
    n_held = len(np.load(args.capture / "ground_truth" / "heldout" / "meshes.npz")["vertices"])
    held_frames = list(range(0, n_held, 16 if args.quick else 8))  # the held-out motion's own length
    modes = [m for m in args.modes.split(",") if m]

    base = dict(iterations=iters, texture_size=args.texture_size, scale=1.0, spp=8, final_spp=eval_spp,
                lr=args.lr, lr_decay_every=max(iters // 4, 1), init_frame_stride=4, checkpoint_every=50)
    data = load_appearance_data(cap, None, "gt", args.texture_size)
    gt_tex = np.load(args.capture / "ground_truth" / "texture_linear.npy")

    results, configs = {}, {}
    init = None
    for mode in modes:
        cfg = AppearanceConfig(light=mode, **base)
        configs[mode] = cfg.to_dict()
        t0 = time.time()
        res = fit_appearance(cap, args.work / mode, cfg, data=data, progress=True)
        fit_s = time.time() - t0
        cov = covered_texels(res.face_uvs, gt_tex.shape[0], res.face_pixels > 0)
        if init is None:
            # T_0 under the ambient light that best reproduces the training images
            amb = best_ambient(cap, res.face_uvs, res.texture_init, data.vertices[::12], data.frames[::12],
                               data.cameras, scale=0.5)
            held = heldout_metrics(cap, res.face_uvs, res.texture_init, [Ambient(tuple(amb))], frames=held_frames,
                                   spp=eval_spp)
            init = {"heldout_psnr": held["psnr"], "heldout_ssim": held["ssim"], "ambient": amb.tolist(),
                    "texture_psnr": texture_psnr(res.texture_init, gt_tex, cov),
                    "texture_psnr_aligned": texture_psnr(res.texture_init, gt_tex, cov, align_scale=True),
                    "baked_shading": baked_shading(res.texture_init, gt_tex, res.face_uvs, res.face_pixels > 0)}
            print(f"init: {init}")
        held = heldout_metrics(cap, res.face_uvs, res.texture, res.lights, frames=held_frames, spp=eval_spp)
        loss = np.array([r["loss"] for r in res.log])
        k = max(1, len(loss) // 10)
        results[mode] = {
            "heldout_psnr": held["psnr"], "heldout_ssim": held["ssim"],
            "texture_psnr": texture_psnr(res.texture, gt_tex, cov),
            "texture_psnr_aligned": texture_psnr(res.texture, gt_tex, cov, align_scale=True),
            "baked_shading": baked_shading(res.texture, gt_tex, res.face_uvs, res.face_pixels > 0),
            "seconds_per_iteration": res.seconds_per_iteration,
            # the fit loop's own time from its log (a resumed run would otherwise report ~0)
            "fit_loop_seconds": float(sum(r["seconds"] for r in res.log)), "wall_seconds_this_run": fit_s,
            "loss_first_tenth": float(loss[:k].mean()), "loss_last_tenth": float(loss[-k:].mean()),
            "lights": [light_to_json(l) for l in res.lights],
            "per_view_psnr": [round(r["psnr"], 2) for r in held["per_view"]],
        }
        print(f"{mode}: " + ", ".join(f"{a}={b:.4g}" for a, b in results[mode].items() if isinstance(b, float)))

    checks = {}
    for mode, r in results.items():
        checks[f"{mode}_heldout_psnr_improves"] = check(r["heldout_psnr"] - init["heldout_psnr"], "> 0", "dB")
        checks[f"{mode}_heldout_ssim_improves"] = check(r["heldout_ssim"] - init["heldout_ssim"], "> 0", "")
        checks[f"{mode}_texture_psnr_improves"] = check(r["texture_psnr_aligned"] - init["texture_psnr_aligned"],
                                                        "> 0", "dB")
        checks[f"{mode}_baked_shading_reduced"] = check(init["baked_shading"] - r["baked_shading"], "> 0",
                                                        "std of log(texture / true albedo) over faces")
        checks[f"{mode}_heldout_psnr"] = check(r["heldout_psnr"], ">= 30", "dB")
    figures = {"init": init, **results,
               "table": {name: {"heldout_psnr": round(r["heldout_psnr"], 2), "heldout_ssim": round(r["heldout_ssim"], 4),
                                "texture_psnr": round(r["texture_psnr"], 2),
                                "texture_psnr_aligned": round(r["texture_psnr_aligned"], 2),
                                "baked_shading": round(r["baked_shading"], 3)}
                         for name, r in {"init (w/o appearance)": init, **results}.items()}}
    out = {"benchmark": "appearance_accuracy", "date": datetime.datetime.now().isoformat(timespec="seconds"),
           "machine": {"cores": os.cpu_count(), "cpu": cpu_name(), "gpu": None,
                       "load_average_at_end": [round(x, 2) for x in os.getloadavg()]},
           "config": {"capture": str(args.capture), "quick": args.quick, "meshes": "gt",
                      "heldout_frames": held_frames, "eval_spp": eval_spp, "fits": configs},
           "figures": figures, "checks": checks}
    if not args.quick:
        path = HERE / "results" / "appearance_accuracy.json"
    else:
        path = args.work / "appearance_accuracy_quick.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=2) + "\n")
    print(f"{'':24s} {'PSNR':>7s} {'SSIM':>7s} {'tex PSNR':>9s} {'tex PSNR*':>9s} {'baked':>6s}")
    for name, r in figures["table"].items():
        print(f"{name:24s} {r['heldout_psnr']:7.2f} {r['heldout_ssim']:7.4f} {r['texture_psnr']:9.2f} "
              f"{r['texture_psnr_aligned']:9.2f} {r['baked_shading']:6.3f}")
    for name, c in checks.items():
        print(f"{'PASS' if c['pass'] else 'FAIL'} {name}: {c['value']} ({c['target']} {c['unit']})")
    print(f"wrote {path}")
    return 0 if all(c["pass"] for c in checks.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
