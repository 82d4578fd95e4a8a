"""benchmarks/cuda_check.py: its summary of a JUnit report that pytest itself wrote (passed, failed
and skipped tests counted per file), and its refusal to run the check where there is no CUDA."""

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import cuda_check  # noqa: E402


def test_summary_of_a_report_pytest_wrote(tmp_path):
    (tmp_path / "test_a.py").write_text(
        "import pytest\n"
        "def test_one(): pass\n"
        "def test_two(): pass\n"
        "def test_bad(): assert 1 == 2\n"
        "@pytest.mark.skip(reason='x')\n"
        "def test_skipped(): pass\n")
    (tmp_path / "test_b.py").write_text("def test_three(): pass\n")
    junit = tmp_path / "junit.xml"
    subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", f"--junitxml={junit}",
                    "test_a.py", "test_b.py"], cwd=tmp_path, capture_output=True, check=False)
    assert cuda_check.per_file(junit) == {"test_a.py:failed": 1, "test_a.py:passed": 2, "test_a.py:skipped": 1,
                                          "test_b.py:passed": 1}
    versions = tmp_path / "v.txt"
    versions.write_text("python 3.12 torch x\nvariant cuda_ad_rgb\n")
    out = tmp_path / "r.json"
    subprocess.run([sys.executable, str(ROOT / "benchmarks" / "cuda_check.py"), "--junit", str(junit),
                    "--versions", str(versions), "--commit", "abc", "--out", str(out)], check=True, capture_output=True)
    check = json.loads(out.read_text())["checks"]["cuda_tests_pass"]
    assert (check["value"], check["failed"], check["skipped"], check["pass"]) == (3, 1, 1, False)


def test_a_broken_report_is_one_message(tmp_path):
    bad = tmp_path / "junit.xml"
    bad.write_text("<testsuites><testsuite")
    r = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "cuda_check.py"), "--junit", str(bad),
                        "--out", str(tmp_path / "r.json")], capture_output=True, text=True)
    assert r.returncode != 0 and "junit.xml: not a readable JUnit report" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.skipif(torch.cuda.is_available(), reason="on a CUDA machine the check runs")
def test_refuses_without_cuda(tmp_path):
    r = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "cuda_check.py"), "--out", str(tmp_path / "r.json")],
                       capture_output=True, text=True, cwd=ROOT)
    assert r.returncode != 0 and "no CUDA device here" in r.stderr and not (tmp_path / "r.json").exists()
