"""Simulations side by side (physavatar.parallel): same results as one after the other."""

import pickle

import cloth_grid
import numpy as np
import pytest
import trimesh

from physavatar.errors import CaptureError, PhysavatarError
from physavatar.parallel import Job, default_workers, run_jobs
from physavatar.sim import Material, simulate


def _drop(shift: float, frames: int, send: bool = False, report=None):
    """A small cloth falling on a sphere that slides by ``shift`` per frame."""
    V, F = cloth_grid.grid(6, 0.3, 0.11, center=True)
    m = trimesh.creation.icosphere(subdivisions=2, radius=0.1)
    B, BF = np.asarray(m.vertices), np.asarray(m.faces)
    seq = np.stack([B + np.array([shift * t, 0, 0]) for t in range(frames)])
    seen = []

    def cb(f, x, st):
        seen.append(f)
        if report is not None:
            report(1, (f, x.copy()) if send else None)

    out = simulate(V, F, Material(), seq, BF, fps=25.0, callback=cb)
    assert seen == list(range(1, frames))
    return out


def _fail(path: str, report=None):
    raise PhysavatarError(path, "impossible parameters")


def test_two_processes_give_the_results_of_one_and_of_a_direct_call():
    jobs = [Job("a", _drop, (0.004, 5), total=4), Job("b", _drop, (-0.003, 4), total=3)]
    par = run_jobs(jobs, workers=2, progress=False)
    seq = run_jobs(jobs, workers=1, progress=False)
    direct = [_drop(0.004, 5), _drop(-0.003, 4)]
    for p, s, d in zip(par, seq, direct):
        assert np.array_equal(p, s) and np.array_equal(s, d)
    assert par[0].shape[0] == 5 and par[1].shape[0] == 4
    assert not np.allclose(par[0][3], par[1][3])  # the two jobs are different simulations


def test_frames_reach_this_process_as_they_are_made():
    """on_item gets every (frame, positions) of every job, in each job's order (synth renders them)."""
    for workers in (1, 2):
        got = {0: [], 1: []}
        jobs = [Job("a", _drop, (0.004, 5, True)), Job("b", _drop, (-0.003, 4, True))]
        out = run_jobs(jobs, workers=workers, progress=False, on_item=lambda i, item: got[i].append(item))
        for i in (0, 1):
            assert [f for f, _ in got[i]] == list(range(1, len(out[i])))
            for f, x in got[i]:
                assert np.array_equal(x, out[i][f])


def test_an_error_in_a_job_arrives_whole_and_stops_the_others():
    jobs = [Job("slow", _drop, (0.004, 30)), Job("bad", _fail, ("/data/material.json",))]
    with pytest.raises(PhysavatarError) as e:
        run_jobs(jobs, workers=2, progress=False)
    assert e.value.problem == "impossible parameters"
    assert str(e.value.path) == "/data/material.json"


def test_errors_survive_pickling_and_worker_count_is_capped(monkeypatch):
    e = pickle.loads(pickle.dumps(CaptureError("/c/cameras.json", "K is not 3x3")))
    assert type(e) is CaptureError and str(e.path) == "/c/cameras.json" and e.problem == "K is not 3x3"
    monkeypatch.setenv("PHYSAVATAR_WORKERS", "1")
    assert default_workers(5) == 1
    monkeypatch.setenv("PHYSAVATAR_WORKERS", "8")
    assert default_workers(3) == 3


def test_ray_is_never_imported_without_a_caller_that_started_it():
    """Ray is optional: the local path neither imports it nor needs it."""
    import subprocess
    import sys

    code = ("import sys\n"
            "from physavatar.parallel import Job, ray_active, run_jobs\n"
            "import physavatar.stages.physics.fit_fd\n"
            "def f(a, b, report=None):\n    return a + b\n"
            "assert ray_active() is None and run_jobs([Job('a', f, (1, 2))], workers=1, progress=False) == [3]\n"
            "assert 'ray' not in sys.modules\n")
    subprocess.run([sys.executable, "-c", code], check=True)
