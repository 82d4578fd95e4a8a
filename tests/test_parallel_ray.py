"""Independent simulations as Ray tasks (physavatar.parallel on an active Ray; fit_fd's simulations):
the same results, order and reports as locally, and no deadlock when a one-CPU task submits them."""

import dataclasses
import os
import time
from pathlib import Path

import numpy as np
import pytest

ray = pytest.importorskip("ray")

from test_parallel import _drop, _fail
from test_physics import hanging_cloth

from physavatar.batch import _stage_task
from physavatar.errors import PhysavatarError
from physavatar.parallel import Job, ray_active, run_jobs
from physavatar.pipeline import Step
from physavatar.stages.physics import fit_fd as fit_fd_module
from physavatar.stages.physics.parameters import far_material


@pytest.fixture(scope="module")
def local_ray():
    """A local Ray of 2 CPUs whose workers can import the test modules (tests/ on their path)."""
    if ray.is_initialized():
        ray.shutdown()
    old = os.environ.get("PYTHONPATH")
    here = str(Path(__file__).parent)
    os.environ["PYTHONPATH"] = here + (os.pathsep + old if old else "")
    try:
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    finally:
        if old is None:
            os.environ.pop("PYTHONPATH")
        else:
            os.environ["PYTHONPATH"] = old
    yield ray
    ray.shutdown()


def _walk(seed: int, n: int, report=None):
    """A small deterministic job that reports each step with its value."""
    rng = np.random.default_rng(seed)
    x = np.zeros(3)
    for i in range(n):
        x = x + rng.standard_normal(3)
        if report is not None:
            report(1, (i, x.copy()))
    return x


def _events(log):
    def listen(ev):
        log.append((ev.kind, ev.task, ev.done))
    return listen


def test_jobs_on_ray_give_the_local_results_order_and_reports(local_ray):
    assert ray_active() is local_ray
    jobs = [Job("a", _walk, (1, 6), total=6), Job("b", _walk, (2, 3), total=3), Job("c", _walk, (3, 5), total=5)]
    runs = {}
    for where in ("ray", "local"):
        items, log = {0: [], 1: [], 2: []}, []
        out = run_jobs(jobs, workers=1, progress=_events(log), title="walk",
                       on_item=lambda i, item, items=items: items[i].append(item), ray=None if where == "ray" else False)
        runs[where] = out, items, log
    (ro, ri, rl), (lo, li, ll) = runs["ray"], runs["local"]
    for j in jobs:  # each job's progress events as locally (the jobs' events interleave differently)
        name = f"walk {j.label}"
        assert [e for e in rl if e[1] == name] == [e for e in ll if e[1] == name]
    for a, b in zip(ro, lo):
        np.testing.assert_array_equal(a, b)
    for i in range(3):  # every report, in each job's order, with the same items
        assert [s for s, _ in ri[i]] == list(range(jobs[i].args[1]))
        for (s, x), (t, y) in zip(ri[i], li[i]):
            assert s == t and np.array_equal(x, y)
    # progress: each job's task advanced to its total and ended
    for j in jobs:
        name = f"walk {j.label}"
        assert max(d for k, t, d in rl if t == name and k == "advance") == j.total
        assert ("end", name, j.total) in rl


def test_a_cloth_simulation_on_ray_equals_the_local_one(local_ray):
    jobs = [Job("a", _drop, (0.004, 5, True), total=4), Job("b", _drop, (-0.003, 4, True), total=3)]
    got = {0: [], 1: []}
    on_ray = run_jobs(jobs, progress=False, on_item=lambda i, item: got[i].append(item))
    local = run_jobs(jobs, workers=2, progress=False, ray=False)
    for r, l in zip(on_ray, local):
        np.testing.assert_array_equal(r, l)
    for i in (0, 1):  # the frames arrived as they were made
        assert [f for f, _ in got[i]] == list(range(1, len(on_ray[i])))
        for f, x in got[i]:
            assert np.array_equal(x, on_ray[i][f])


def test_an_error_on_ray_arrives_whole_and_stops_the_others(local_ray):
    jobs = [Job("slow", _walk, (0, 10**7)), Job("bad", _fail, ("/data/material.json",))]
    t0 = time.time()
    with pytest.raises(PhysavatarError) as e:
        run_jobs(jobs, progress=False)
    assert type(e.value) is PhysavatarError and e.value.problem == "impossible parameters"
    assert str(e.value.path) == "/data/material.json"
    assert time.time() - t0 < 60


@dataclasses.dataclass
class _WalkConfig:
    seed: int = 0


def _walk_stage(out, config, progress=False):
    """A stage function as batch runs them: it sees Ray active and runs its jobs as sub-tasks."""
    assert ray_active() is not None
    out.mkdir(parents=True, exist_ok=True)
    xs = run_jobs([Job(str(i), _walk, (config.seed + i, 4)) for i in range(3)], progress=progress)
    np.save(out / "walk.npy", np.stack(xs))


def test_batch_stage_tasks_of_one_cpu_run_their_jobs_on_ray_without_deadlock(local_ray, tmp_path):
    """Two stage tasks (batch's own task function, one CPU each) fill the 2-CPU Ray; each waits for
    3 one-CPU jobs (its CPU is released while it waits), as two captures' fit-physics would."""
    task = ray.remote(num_cpus=1)(_stage_task)
    steps = [Step("walk", "test_parallel_ray:_walk_stage", _WalkConfig(seed), done_file="walk.npy")
             for seed in (10, 20)]
    refs = [task.remote(st, tmp_path / f"cap{k}", {}, 1) for k, st in enumerate(steps)]
    results = ray.get(refs, timeout=180)
    for k, (st, r) in enumerate(zip(steps, results)):
        assert r.ok, r.entry
        got = np.load(tmp_path / f"cap{k}" / "walk" / "walk.npy")
        for i in range(3):
            np.testing.assert_array_equal(got[i], _walk(st.config.seed + i, 4))


@pytest.mark.slow
def test_fit_fd_on_ray_gives_the_local_material(local_ray, monkeypatch):
    data = hanging_cloth(frames=4)
    on_ray = fit_fd_module.fit_fd(data, far_material(), iterations=2, workers=2)
    monkeypatch.setattr(fit_fd_module, "ray_active", lambda: None)  # the local pool, Ray running or not
    local = fit_fd_module.fit_fd(data, far_material(), iterations=2, workers=2)
    assert on_ray.simulations == local.simulations == 2 * 3
    assert [r["loss"] for r in on_ray.history] == [r["loss"] for r in local.history]
    for n in ("stretch_stiffness", "bend_stiffness"):
        assert getattr(on_ray.material, n) == getattr(local.material, n)
    assert on_ray.ratio_intervals == local.ratio_intervals
