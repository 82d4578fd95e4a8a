"""`make demo`: run what the pipeline has so far on built-in data and say what it did.

Stages that have landed are run in order; each writes into its own folder under --out.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path


def run(args: list[str]) -> None:
    cmd = [sys.executable, "-m", "physavatar.cli", *args]
    print("$ physavatar " + " ".join(args), flush=True)
    t = time.time()
    subprocess.run(cmd, check=True)
    print(f"  ({time.time() - t:.1f} s)\n", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", type=Path, default=Path("demo_out"))
    a = ap.parse_args()
    out = a.out
    out.mkdir(parents=True, exist_ok=True)
    run(["motion", "list"])
    run(["pose", "--motion", "walk", "--duration", "2", "--out", str(out / "pose_walk")])
    run(["motion", "preview", "dance", "--duration", "3", "--out", str(out / "dance.gif")])
    capture = out / "capture"
    if not capture.exists():
        run(["synth", str(capture), "--preset", "demo"])
    run(["inspect", str(capture)])
    run(["render-capture", str(capture), "--out", str(out / "contact_sheet.png")])
    print("demo done:")
    print(f"  {out}/capture/       synthetic capture (demo preset) with ground_truth/; contact sheet: {out}/contact_sheet.png")
    print(f"  {out}/pose_walk/     Anny body (full topology) posed by the built-in 'walk' motion:"
          " body_sequence.npz, meshes/*.ply, preview.gif")
    print(f"  {out}/dance.gif      preview of the built-in 'dance' motion")


if __name__ == "__main__":
    main()
