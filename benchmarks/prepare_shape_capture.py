"""A short demo-like capture of a body that is not Anny's default, for the body fit's shape (issue 23, session 34).

    python benchmarks/prepare_shape_capture.py OUT [--shape gender=0.2,age=0.35,...] [--frames 12]

Writes OUT/capture (the demo preset's dress, cameras and walk, ``--frames`` frames, two held-out
frames in one view: the body fit does not use them) and OUT/no_template (the same files hard-linked
without template/ and body.npz: what `prepare` gets), then the body fit's benchmark runs on them:

    python benchmarks/prepare_body_fit_variants.py --input OUT/no_template --truth OUT/capture --work W ...

The default shape is the foreign benchmark's body (``benchmarks/foreign/capture.py``:
``FOREIGN_SHAPE``): the demo's phenotypes are all 0.5, the centre of the fit's shape prior, so
the demo alone cannot tell a fit that finds the shape from one that keeps the prior's.
60-100 s on 2 shared cores (12 frames); deterministic (rebuilt: the same body, meshes and masks).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time
from pathlib import Path

# the foreign benchmark's body (benchmarks/foreign/capture.py, FOREIGN_SHAPE; not imported: that
# module loads the Newton simulator)
FOREIGN_SHAPE = {"gender": 0.2, "age": 0.35, "muscle": 0.3, "weight": 0.7, "height": 0.65, "proportions": 0.35}


def build(out: Path, shape: dict, frames: int) -> Path:
    from physavatar.synth import PRESETS, synthesize

    cfg = dataclasses.replace(PRESETS["demo"], preset="custom", shape=dict(shape), frames=frames,
                              heldout_frames=2, heldout_cameras=1)
    cap = out / "capture"
    if not (cap / "body.npz").is_file():
        synthesize(cap, cfg, progress=False)
    inp = out / "no_template"
    if not inp.exists():
        inp.mkdir(parents=True)
        for name in ("cameras.json", "capture.json", "ground_truth", "images", "masks"):
            src = cap / name
            if src.is_dir():
                for f in src.rglob("*"):
                    if f.is_file():
                        (inp / f.relative_to(cap)).parent.mkdir(parents=True, exist_ok=True)
                        os.link(f, inp / f.relative_to(cap))
            else:
                os.link(src, inp / name)
    return cap


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("out", type=Path)
    ap.add_argument("--shape", default="", help="phenotype=value,... (default: the foreign benchmark's body)")
    ap.add_argument("--frames", type=int, default=12)
    args = ap.parse_args()
    shape = dict(FOREIGN_SHAPE)
    for kv in filter(None, args.shape.split(",")):
        k, v = kv.split("=", 1)
        if k not in shape:
            ap.error(f"--shape: {k!r} is not one of {', '.join(shape)}")
        shape[k] = float(v)
    t0 = time.time()
    build(args.out, shape, args.frames)
    print(f"{args.out}: built in {time.time() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
