"""`physavatar batch`: captures from folders, globs and lists; a batch with a failing capture; resume;
Ray missing; on Ray the same outputs as `physavatar run` of each capture alone."""

import json
import shutil
import sys

import numpy as np
import pytest
from typer.testing import CliRunner

from physavatar.batch import collect, import_ray
from physavatar.cli import app
from physavatar.errors import PhysavatarError


def test_collect_folders_globs_lists(tmp_path):
    for p in ("a/cap1", "a/cap2", "b/cap1", "c"):
        (tmp_path / p).mkdir(parents=True)
    (tmp_path / "a" / "notes.txt").write_text("x")
    lst = tmp_path / "list.txt"
    lst.write_text("# my captures\nb/cap1\na/cap1   # again: kept once\nmissing\n")
    caps = collect([str(tmp_path / "a" / "*"), str(lst), str(tmp_path / "c")])
    assert [c.name for c in caps] == ["cap1", "cap2", "cap1-2", "missing", "c"]
    assert caps[2].path == tmp_path / "b" / "cap1" and caps[3].path == tmp_path / "missing"
    with pytest.raises(PhysavatarError, match="matches no folder"):
        collect([str(tmp_path / "z*")])


def test_ray_missing_says_how_to_install(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray fails as when it is not installed
    with pytest.raises(PhysavatarError, match=r"pip install 'physavatar\[ray\]'"):
        import_ray()
    (tmp_path / "cap").mkdir()
    r = CliRunner().invoke(app, ["batch", str(tmp_path / "cap"), "--out", str(tmp_path / "out"), "--ray"])
    assert r.exit_code == 2 and "physavatar[ray]" in r.output, r.output
    assert not (tmp_path / "out").exists()  # nothing ran


@pytest.mark.slow
def test_batch_local_failure_summary_and_resume(tiny_capture, tmp_path):
    bad = tmp_path / "not_a_capture"
    bad.mkdir()
    out = tmp_path / "out"
    args = ["batch", str(tiny_capture), str(bad), "--out", str(out), "--quick"]
    r = CliRunner().invoke(app, args + ["--jobs", "1"])
    assert r.exit_code == 1, r.output  # one capture failed
    assert "not_a_capture" in r.output and "capture.json" in r.output
    b = json.loads((out / "batch.json").read_text())
    ok, failed = b["captures"]
    assert (b["ok"], b["failed"]) == (1, 1)
    # the capture that failed is reported with its error; the other one finished
    assert failed["status"] == "failed" and "capture.json" in failed["error"]
    assert ok["status"] == "ok" and ok["name"] == tiny_capture.name and not ok["skipped"]
    # the summary's numbers are the run's own
    run = json.loads((out / ok["name"] / "run.json").read_text())
    assert ok["stage_seconds"] == {k: v["seconds"] for k, v in run.items() if isinstance(v, dict) and "seconds" in v}
    assert all(v["status"] == "ok" for k, v in run.items() if isinstance(v, dict) and "status" in v)
    assert len(ok["stage_seconds"]) == 11
    m = json.loads((out / ok["name"] / "evaluate" / "metrics.json").read_text())
    assert ok["metrics"]["garment_chamfer_x1e3"] == m["rows"]["estimated material"]["garment"]["chamfer_x1e3"]
    assert ok["metrics"]["tracking_garment_mm"] == m["tracking"]["garment"]["mean_mm"]
    assert ok["metrics"]["psnr"] == m["appearance"]["psnr"]
    mat = json.loads((out / ok["name"] / "physics" / "material.json").read_text())["material"]
    assert ok["metrics"]["stretch_stiffness"] == mat["stretch_stiffness"]
    md = (out / "batch.md").read_text()
    assert f"[report.md]({ok['name']}/report.md)" in md and (out / ok["name"] / "report.md").exists()
    assert f"| {ok['name']} | ok | {sum(ok['stage_seconds'].values()):.1f} |" in md
    # a second batch (two captures side by side, in processes) resumes: the finished capture's
    # stages are all skipped by run's hashes, the failing one fails again
    r = CliRunner().invoke(app, args + ["--jobs", "2"])
    assert r.exit_code == 1, r.output
    b2 = json.loads((out / "batch.json").read_text())
    ok2, failed2 = b2["captures"]
    assert sorted(ok2["skipped"]) == sorted(ok["stage_seconds"]) and ok2["stage_seconds"] == ok["stage_seconds"]
    assert failed2["status"] == "failed" and (out / failed2["name"] / "batch.log").exists()
    assert "done earlier" in (out / ok2["name"] / "batch.log").read_text()


def _numbers(x, prefix=""):
    """Every number in a JSON tree, by its path (timings and paths left out)."""
    if isinstance(x, dict):
        return {k: v for key, val in x.items() if key != "seconds" for k, v in _numbers(val, f"{prefix}/{key}").items()}
    if isinstance(x, list):
        return {k: v for i, val in enumerate(x) for k, v in _numbers(val, f"{prefix}/{i}").items()}
    return {prefix: x} if isinstance(x, (int, float)) and not isinstance(x, bool) else {}


@pytest.mark.slow
def test_ray_batch_gives_the_outputs_of_run_alone(tiny_capture, tmp_path):
    pytest.importorskip("ray")
    # each capture alone, with `physavatar run`
    alone = tmp_path / "alone"
    r = CliRunner().invoke(app, ["run", str(tiny_capture), str(alone), "--quick"])
    assert r.exit_code == 0, r.output
    # two captures (copies of it) on a local Ray of 2 CPUs: every stage a task
    caps = tmp_path / "caps"
    for name in ("a", "b"):
        shutil.copytree(tiny_capture, caps / name)
    out = tmp_path / "batch"
    r = CliRunner().invoke(app, ["batch", str(caps / "*"), "--out", str(out), "--quick", "--ray", "--ray-cpus", "2"])
    assert r.exit_code == 0, r.output
    b = json.loads((out / "batch.json").read_text())
    assert [c["name"] for c in b["captures"]] == ["a", "b"] and b["mode"] == "Ray local"
    ref_run = json.loads((alone / "run.json").read_text())
    ref_mat = json.loads((alone / "physics" / "material.json").read_text())["material"]
    ref_trk = np.load(alone / "track" / "tracked.npz")
    ref_m = _numbers(json.loads((alone / "evaluate" / "metrics.json").read_text()))
    for name in ("a", "b"):
        o = out / name
        run = json.loads((o / "run.json").read_text())
        # the driver merged every task's entry, in whatever order they finished: the stages of the run
        # alone, all ok (their hashes differ: the held-out motion's path is in animate's config)
        assert sorted(k for k, v in run.items() if isinstance(v, dict) and v.get("status") == "ok") == \
               sorted(k for k, v in ref_run.items() if isinstance(v, dict) and "hash" in v)
        assert json.loads((o / "physics" / "material.json").read_text())["material"] == ref_mat
        trk = np.load(o / "track" / "tracked.npz")
        for k in ref_trk.files:
            if np.issubdtype(ref_trk[k].dtype, np.number):
                np.testing.assert_array_equal(trk[k], ref_trk[k], err_msg=k)
        m = _numbers(json.loads((o / "evaluate" / "metrics.json").read_text()))
        assert m.keys() == ref_m.keys()
        for k in ref_m:
            assert m[k] == pytest.approx(ref_m[k], rel=1e-6, abs=1e-9), k
        assert (o / "report.md").exists() and (o / "appearance" / "stage.log").exists()
    # a second batch skips every stage of both (run's hashes, in the tasks)
    r = CliRunner().invoke(app, ["batch", str(caps / "*"), "--out", str(out), "--quick", "--ray", "--ray-cpus", "2"])
    assert r.exit_code == 0, r.output
    b = json.loads((out / "batch.json").read_text())
    assert all(len(c["skipped"]) == 11 for c in b["captures"])
