"""What the tracker's flow corrections can and cannot see, measured against ground truth.

    python benchmarks/tracking_corrections.py CAPTURE [--tracked RUN/track/tracked.npz] [--frames 5,10,15]
        [--corrections 3] [--variant NAME=field=JSON,field=JSON ...] [--shift-mm 8] [--out FILE]

The corrections (docs/tracking.md, "Method", step 2) move the free garment toward where frame t's
images put it, measured by optical flow from a synthetic view (the estimate rendered with the first
frame's projective texture) to the real one. Three figures per frame of a capture with
``ground_truth/meshes.npz``:

- **bias**: the corrections started *at the true mesh* of the frame. Whatever distance they walk
  from it is their fixed point's error (the regularisers' pull toward the template, the flow's own
  noise, the stale first-frame texture). Per ``--variant`` (FlowConfig fields, e.g.
  ``bend0=correction_bend=0``), with the first frame as reference (the tracker's) and with the true
  previous frame as reference (``ref_previous``: what is left when the texture is one frame old).
- **from the tracked state** (``--tracked``): the same corrections started at a tracked run's
  frame: the error before and after, i.e. whether more corrections would recover the drift.
- **sensitivity**: the correction flow's measured offset at each observed vertex against the true
  offset (the true vertex's projection minus the estimate's) at the tracked state, and at the true
  mesh shifted rigidly by ``--shift-mm`` along x (the positive control: an error the flow must see).
  Reported: the correlation of measured and true offsets, and the median gain along the true offset
  where it exceeds 1 px.

Writes JSON (default benchmarks/results/tracking_corrections.json); every check is "reported".
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import numpy as np
from _common import machine, write_result


def _setup(capture: Path, flow_sets: dict):
    """(capture, training cameras, frames, truth [T, V, 3], FlowStart, free mask) with the
    tracker's defaults and ``flow_sets`` applied to its FlowConfig (the plain-garment rule too)."""
    from physavatar.capture import load_capture
    from physavatar.stages.track.config import TrackConfig
    from physavatar.stages.track.prediction import FrameStarts, flow_start
    from physavatar.stages.track.stage import _check_config
    from physavatar.stages.track.views import flow_views

    cap = load_capture(capture)
    cfg = TrackConfig()
    cfg = replace(cfg, flow=replace(cfg.flow, **flow_sets))
    train, frames = _check_config(cfg, cap)
    truth = np.load(capture / "ground_truth" / "meshes.npz")["vertices"].astype(np.float64)
    starts = FrameStarts(cap, cfg, train, frames)
    first = flow_views(cap, frames[0], train, cfg.flow.channels)
    starts.flow_cfg = starts._flow_settings(truth[0], first)
    fs = flow_start(starts.flow_cfg, cap.template, train, truth[0], first, starts.skinned)
    return cap, cfg, train, frames, truth, fs, ~starts.skinned


def _views(cap, frame, train, channels):
    from physavatar.stages.track.views import flow_views

    return flow_views(cap, frame, train, channels)


def _mean_mm(X, G, sel) -> float:
    return float(np.linalg.norm(X[sel] - G[sel], axis=1).mean() * 1e3)


def corrections_from(setup: tuple, frames_sel: list[int], n: int, start: str,
                     reference: str = "first", tracked: np.ndarray | None = None) -> dict:
    """Per frame: free-garment error [mm] of ``n`` corrections started at the true mesh
    (``start="truth"``) or at ``tracked`` (``start="tracked"``): {frame: [before, after]}.
    ``setup``: :func:`_setup`'s tuple for the variant."""
    from physavatar.stages.track.flow import ReferenceAppearance

    cap, cfg, train, frames, truth, fs, free = setup
    out = {}
    for i in frames_sel:
        ref = fs.reference
        if reference == "previous":
            ref = ReferenceAppearance(truth[i - 1], fs.flow.faces, train, _views(cap, frames[i - 1], train, cfg.flow.channels),
                                      colour=fs.reference.grey[0].shape[-1] == 3)
        masks = [cap.mask(c.name, frames[i]) for c in train] if cfg.flow.silhouette > 0 and cap.has_masks else None
        X0 = truth[i].copy() if start == "truth" else np.asarray(tracked[i], np.float64)
        X = fs.flow.correct(X0, train, _views(cap, frames[i], train, cfg.flow.channels), ref, n, masks=masks,
                            previous=truth[i - 1], **fs.correction)
        out[int(i)] = [round(_mean_mm(X0, truth[i], free), 4), round(_mean_mm(X, truth[i], free), 4)]
        print(f"  frame {i}: {out[int(i)][0]:.3f} -> {out[int(i)][1]:.3f} mm", flush=True)
    return out


def sensitivity(setup: tuple, frames_sel: list[int], tracked: np.ndarray | None, shift_mm: float) -> dict:
    """Measured correction flow against the true offsets (module docstring), at the tracked state
    and at the rigidly shifted truth; ``setup``: :func:`_setup`'s tuple with the defaults."""
    cap, cfg, train, frames, truth, fs, free = setup
    lift, ref = fs.flow, fs.reference
    res = {}
    for i in frames_sel:
        views = _views(cap, frames[i], train, cfg.flow.channels)
        states = {"shifted_truth": truth[i] + np.array([shift_mm * 1e-3, 0, 0]) * free[:, None]}
        if tracked is not None:
            states["tracked"] = np.asarray(tracked[i], np.float64)
        for name, X in states.items():
            meas, true = [], []
            for cam, v in zip(train, views):
                synth, valid, depth, face = ref.render(X, cam, fill=v)
                ob = lift._observation(X, cam, synth, v, depth, face, valid, lift.preset, fs.correction["channels"], 1,
                                       fs.correction.get("opponent", (True, True)))
                uv = cam.project(X[ob.vertex])[0]
                meas.append(ob.target - uv)
                true.append(cam.project(truth[i][ob.vertex])[0] - uv)
            m, t = np.concatenate(meas), np.concatenate(true)
            nt = np.linalg.norm(t, axis=1)
            big = nt > 1.0
            along = (m * t).sum(1) / np.maximum(nt, 1e-12)
            corr = float(np.corrcoef(m.ravel(), t.ravel())[0, 1])
            res.setdefault(name, {})[int(i)] = {
                "observations": int(len(m)), "true_offset_px_median": round(float(np.median(nt)), 3),
                "measured_px_median": round(float(np.median(np.linalg.norm(m, axis=1))), 3),
                "correlation": round(corr, 3), "over_1px": int(big.sum()),
                "gain_along_true_over_1px": round(float(np.median(along[big] / nt[big])), 3) if big.any() else None}
            print(f"  {name} frame {i}: {res[name][int(i)]}", flush=True)
    return res


def _variant(text: str) -> tuple[str, dict]:
    name, _, fields = text.partition("=")
    sets = {}
    for item in filter(None, fields.split(",")):
        k, _, v = item.partition("=")
        sets[k] = json.loads(v)
    return name, sets


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("capture", type=Path)
    ap.add_argument("--tracked", type=Path, default=None, help="a run's track/tracked.npz (from-tracked and sensitivity)")
    ap.add_argument("--frames", default="", help="frame indices (default: every frame after the first)")
    ap.add_argument("--corrections", type=int, default=3)
    ap.add_argument("--variant", action="append", default=[], help="NAME=field=JSON,field=JSON (FlowConfig)")
    ap.add_argument("--shift-mm", type=float, default=8.0)
    ap.add_argument("--out", type=Path, default=HERE / "results" / "tracking_corrections.json")
    a = ap.parse_args()
    load0 = os.getloadavg()
    t0 = time.time()
    n_frames = len(np.load(a.capture / "ground_truth" / "meshes.npz")["vertices"])
    sel = [int(x) for x in a.frames.split(",")] if a.frames else list(range(1, n_frames))
    tracked = np.load(a.tracked)["vertices"] if a.tracked else None
    variants = dict([("defaults", {})] + [_variant(v) for v in a.variant])
    fig: dict = {"bias": {}, "bias_reference_previous": {}, "from_tracked": {}}
    for name, sets in variants.items():
        setup = _setup(a.capture, sets)
        print(f"[{name}] corrections from the truth", flush=True)
        fig["bias"][name] = corrections_from(setup, sel, a.corrections, "truth")
        print(f"[{name}] the same, the true previous frame as reference", flush=True)
        fig["bias_reference_previous"][name] = corrections_from(setup, sel, a.corrections, "truth", "previous")
        if tracked is not None:
            print(f"[{name}] corrections from the tracked state", flush=True)
            fig["from_tracked"][name] = corrections_from(setup, sel, a.corrections, "tracked", tracked=tracked)
    print("sensitivity", flush=True)
    fig["sensitivity"] = sensitivity(_setup(a.capture, {}), sel, tracked, a.shift_mm)
    checks = {}
    for key in ("bias", "bias_reference_previous", "from_tracked"):
        for name, rows in fig[key].items():
            if rows:
                checks[f"{key}:{name}:mean_after_mm"] = {"value": float(np.mean([r[1] for r in rows.values()])),
                                                        "target": "reported", "unit": "mm", "pass": None}
    for state, rows in fig["sensitivity"].items():
        checks[f"sensitivity:{state}:correlation"] = {"value": float(np.mean([r["correlation"] for r in rows.values()])),
                                                     "target": "reported", "unit": "1", "pass": None}
    result = {"benchmark": "tracking_corrections", "date": datetime.datetime.now().isoformat(timespec="seconds"),
              "machine": machine(load0),
              "config": {"capture": str(a.capture), "tracked": str(a.tracked) if a.tracked else None, "frames": sel,
                         "corrections": a.corrections, "variants": variants, "shift_mm": a.shift_mm},
              "figures": fig, "checks": checks, "seconds": round(time.time() - t0, 1)}
    write_result(a.out, result)
    print(json.dumps(checks, indent=1))


if __name__ == "__main__":
    main()
