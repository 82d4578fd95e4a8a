"""The GPU paths' tests on a CUDA machine, summarised per file with `checks`.

On a machine with CUDA (a CUDA build of torch, gsplat from the `gsplat` extra, Mitsuba finding the
device), this runs pytest on the test files whose code takes a CUDA path there: the splat renderer
and everything that rasterizes through `backend="auto"` (gsplat there: the flow, the tracking
options, the silhouette and shading channels) and the Mitsuba renderer (`cuda_ad_rgb` there: render,
appearance, median cut). On a CPU machine those tests run on the CPU and gsplat's file skips, so
the check refuses to run there: it would say nothing about CUDA.

    python benchmarks/cuda_check.py --out benchmarks/results/cuda_check.json
    python benchmarks/cuda_check.py --junit JUNIT.xml --versions VERSIONS.txt --out ...   # summarise a run made elsewhere

`--junit` summarises a pytest JUnit report written on the CUDA machine (`pytest --junitxml`), with
the lines the machine printed about its versions (`--versions`), for a machine this script cannot
write files back from.
"""

from __future__ import annotations

import argparse
import collections
import datetime
import subprocess
import sys
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import write_result  # noqa: E402

GPU_TESTS = (
    "test_splat_gsplat.py", "test_splat.py", "test_render.py", "test_appearance_env.py",
    "test_appearance_project.py", "test_median_cut.py", "test_flow.py", "test_track_flow_options.py",
    "test_track_texture_gate.py", "test_track_silhouette.py", "test_track_shading.py",
)


def per_file(junit: Path) -> dict:
    """``{"FILE:passed|failed|skipped": count}`` from a pytest JUnit report."""
    try:
        root = ET.parse(junit).getroot()
    except (OSError, ET.ParseError) as e:
        sys.exit(f"{junit}: not a readable JUnit report ({e})")
    counts: collections.Counter = collections.Counter()
    for case in root.iter("testcase"):
        name = case.get("classname", "?").split(".")[-1] + ".py"
        if case.find("skipped") is not None:
            state = "skipped"
        elif case.find("failure") is not None or case.find("error") is not None:
            state = "failed"
        else:
            state = "passed"
        counts[f"{name}:{state}"] += 1
    if not counts:
        sys.exit(f"{junit}: the report holds no test cases")
    return dict(sorted(counts.items()))


def versions_here() -> list[str]:
    """The lines `--versions` would hold, read on this machine; exits where CUDA is missing."""
    import torch

    if not torch.cuda.is_available():
        sys.exit("no CUDA device here: the check runs on a CUDA machine (the tests would run on the CPU)")
    from physavatar.render.backend import choose_variant
    from physavatar.splat import _gsplat

    lines = [f"python {sys.version.split()[0]} torch {torch.__version__} cuda True {torch.cuda.get_device_name(0)}",
             f"variant {choose_variant()}", f"gsplat available {_gsplat.available()}"]
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--junit", type=Path, help="summarise this JUnit report instead of running the tests")
    ap.add_argument("--versions", type=Path, help="with --junit: the machine's version lines")
    ap.add_argument("--commit", default=None, help="the commit the tests ran on (default: this checkout's HEAD)")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/cuda_check.json"))
    a = ap.parse_args()
    root = Path(__file__).resolve().parents[1]
    if a.junit is None:
        notes = versions_here()
        with tempfile.TemporaryDirectory() as tmp:
            junit = Path(tmp) / "junit.xml"
            subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", f"--junitxml={junit}",
                            *[f"tests/{t}" for t in GPU_TESTS]], cwd=root, check=False)
            counts = per_file(junit)
    else:
        counts = per_file(a.junit)
        notes = a.versions.read_text().splitlines() if a.versions else []
    commit = a.commit or subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True,
                                        text=True).stdout.strip()
    total = collections.Counter()
    for key, n in counts.items():
        total[key.rsplit(":", 1)[1]] += n
    result = {
        "benchmark": "CUDA check of the GPU paths (tests run on a CUDA machine)",
        "date": datetime.date.today().isoformat(), "commit": commit, "machine": notes,
        "command": "python -m pytest " + " ".join(f"tests/{t}" for t in GPU_TESTS),
        "per_file": counts,
        "checks": {"cuda_tests_pass": {"value": total["passed"], "failed": total["failed"],
                                       "skipped": total["skipped"], "target": "0 failed", "unit": "tests",
                                       "pass": total["failed"] == 0 and total["passed"] > 0}},
    }
    write_result(a.out, result)
    print(f"{total['passed']} passed, {total['failed']} failed, {total['skipped']} skipped -> {a.out}")


if __name__ == "__main__":
    main()
