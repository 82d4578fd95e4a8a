"""`make demo`: build the built-in synthetic capture and run the whole pipeline on it.

Every step is a `physavatar` command a user could type; each resumes, so `make demo` again
continues where an interrupted one stopped. Ends by printing where the report is.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path


def run(args: list[str]) -> None:
    print("\n$ physavatar " + " ".join(args), flush=True)
    t = time.time()
    r = subprocess.run([sys.executable, "-m", "physavatar.cli", *args])
    if r.returncode != 0:
        sys.exit(r.returncode)
    print(f"  ({time.time() - t:.0f} s)", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", type=Path, default=Path("demo_out"))
    ap.add_argument("--preset", default="demo", help="synthetic capture preset (tiny for a one-minute look)")
    a = ap.parse_args()
    out = a.out
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    capture = out / "capture"
    if not capture.exists():
        run(["synth", str(capture), "--preset", a.preset])
    run(["inspect", str(capture), "--quick"])
    run(["render-capture", str(capture), "--out", str(out / "contact_sheet.png")])
    extra = [] if a.preset == "demo" else ["--quick"]
    run(["run", str(capture), str(out / "run"), *extra])
    print(f"\ndemo done in {(time.time() - t0) / 60:.1f} min:")
    print(f"  capture (synthetic, with ground truth): {capture}   contact sheet: {out}/contact_sheet.png")
    print(f"  report: {out}/run/report.md")


if __name__ == "__main__":
    main()
