"""`make demo`: build the built-in synthetic capture and run the whole pipeline on it.

Every step is a `physavatar` command a user could type; each resumes, so `make demo` again
continues where an interrupted one stopped. Ends by printing where the report is, and writes
OUT/demo.json with the wall time of every step (benchmarks/demo_timing.py collects it).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path


def run(args: list[str], times: dict, key: str) -> None:
    print("\n$ physavatar " + " ".join(args), flush=True)
    t = time.time()
    r = subprocess.run([sys.executable, "-m", "physavatar.cli", *args])
    if r.returncode != 0:
        sys.exit(r.returncode)
    times[key] = round(time.time() - t, 1)
    print(f"  ({times[key]:.0f} s)", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", type=Path, default=Path("demo_out"))
    ap.add_argument("--preset", default="demo", help="synthetic capture preset (tiny for a one-minute look)")
    a = ap.parse_args()
    out = a.out
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    capture = out / "capture"
    times: dict = {}
    if not capture.exists():
        run(["synth", str(capture), "--preset", a.preset], times, "synth")
    run(["inspect", str(capture), "--quick"], times, "inspect")
    run(["render-capture", str(capture), "--out", str(out / "contact_sheet.png")], times, "contact_sheet")
    extra = [] if a.preset == "demo" else ["--quick"]
    run(["run", str(capture), str(out / "run"), *extra], times, "run")
    total = time.time() - t0
    record = {"preset": a.preset, "seconds_this_invocation": times, "total_seconds_this_invocation": round(total, 1),
              "cores": os.cpu_count(), "load_average_at_end": list(os.getloadavg())}
    tmp = out / ".demo.json.tmp"
    tmp.write_text(json.dumps(record, indent=2))
    tmp.replace(out / "demo.json")
    print(f"\ndemo done in {total / 60:.1f} min:")
    print(f"  capture (synthetic, with ground truth): {capture}   contact sheet: {out}/contact_sheet.png")
    print(f"  exports: {out}/run/export/avatar.usdc (Blender: File > Import > USD), {out}/run/export-glb/avatar.glb")
    print(f"  report: {out}/run/report.md")


if __name__ == "__main__":
    main()
