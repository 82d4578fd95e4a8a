"""Independent simulations side by side, one process each.

The cloth simulator is single-threaded (ipctk at one thread, numba kernels serial: docs/simulation.md),
so two garment simulations on a 2-core machine take the time of the longer one when they run in
two processes. `synth` (the capture's motion and the held-out motion) and `evaluate` (the true and
the random material on the held-out motion) use this.

Each job is a picklable top-level function called as ``fn(*args, report=report, **kwargs)``;
``report(k)`` tells the parent that k units (frames) of the job are done, and the parent shows one
progress task per job (:mod:`physavatar.progress`). With one worker (or one job) the jobs run in this process, one after the
other, through the same interface, so results never depend on the worker count (each job is a
deterministic single-threaded computation).

On Ray: when a Ray runtime is active in this process (``ray.is_initialized()``: a stage running
as a ``physavatar batch --ray`` task, or a program that started Ray itself) the jobs are Ray
tasks of one CPU each instead (the cluster schedules them; ``PHYSAVATAR_WORKERS`` and ``workers``
only size the local pool), with the same interface, result order and results. Their reports
reach this process through a small actor (no CPU), frame by frame as locally. Ray is never
imported here unless the caller already has it running.
"""

from __future__ import annotations

import multiprocessing
import os
import queue as _queue
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any, Callable


@dataclass
class Job:
    """One unit of work: ``fn(*args, report=..., **kwargs)``; ``total``: its frame count (progress)."""

    label: str
    fn: Callable
    args: tuple = ()
    kwargs: dict = field(default_factory=dict)
    total: int | None = None


def default_workers(n_jobs: int) -> int:
    """Processes to use for ``n_jobs`` single-threaded jobs: the cores this process may use,
    at most the number of jobs (``PHYSAVATAR_WORKERS`` overrides, 1 = run in this process)."""
    env = os.environ.get("PHYSAVATAR_WORKERS")
    if env:
        try:
            cap = max(1, int(env))
        except ValueError:
            cap = 1
    else:
        try:
            cap = len(os.sched_getaffinity(0))
        except AttributeError:  # not Linux
            cap = os.cpu_count() or 1
    return max(1, min(cap, n_jobs))


# what a job's process gets locally (fit_fd's pool, the Ray tasks): one BLAS / OpenMP / numba thread
SINGLE_THREAD_ENV = {k: "1" for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")}


def ray_active():
    """The ``ray`` module when a Ray runtime is active in this process, else None (Ray is not
    imported: only a caller that imported and started it makes this true)."""
    ray = sys.modules.get("ray")
    try:
        return ray if ray is not None and ray.is_initialized() else None
    except Exception:  # noqa: BLE001 - a half-imported or foreign "ray" module
        return None


def _child(fn, args, kwargs, q, idx):
    def report(k: int = 1, item=None) -> None:
        q.put((idx, k, item))

    return fn(*args, report=report, **kwargs)


def run_jobs(jobs: list[Job], *, workers: int | None = None, progress=True,
             title: str = "simulating", on_item: Callable | None = None, ray: bool | None = None) -> list[Any]:
    """Run ``jobs``; returns their results in order. An exception in a job is raised here (the
    other jobs are cancelled); Ctrl-C stops all of them.

    ``ray``: None (default) runs the jobs as Ray tasks when a Ray runtime is active in this
    process (:func:`ray_active`), else here; False always here (``workers`` processes); True
    requires Ray to be active.

    ``on_item(job_index, item)`` is called in this process for every ``report(k, item)`` a job
    makes with an item (e.g. a finished frame), in the order each job reported them, while the
    jobs run: this process can use the results as they come (synth renders finished frames).
    """
    from .progress import resolve

    workers = default_workers(len(jobs)) if workers is None else max(1, min(workers, len(jobs)))
    ray_mod = ray_active() if ray is not False else None
    if ray and ray_mod is None:
        raise RuntimeError("run_jobs(ray=True) needs an active Ray runtime (ray.init)")
    prog = resolve(progress)
    tasks = [prog.task(f"{title} {j.label}", total=j.total) for j in jobs]
    try:
        if ray_mod is not None and jobs:
            return _run_ray(ray_mod, jobs, tasks, title, on_item, reports=progress not in (False, None))
        if workers == 1:
            out = []
            for i, (j, t) in enumerate(zip(jobs, tasks)):
                def report(k=1, item=None, t=t, i=i):
                    t.advance(k)
                    if item is not None and on_item is not None:
                        on_item(i, item)

                out.append(j.fn(*j.args, report=report, **j.kwargs))
            return out
        ctx = multiprocessing.get_context("spawn")
        with ctx.Manager() as mgr:
            q = mgr.Queue()
            pool = ctx.Pool(processes=workers)
            try:
                res = [pool.apply_async(_child, (j.fn, j.args, j.kwargs, q, i)) for i, j in enumerate(jobs)]
                while not all(r.ready() for r in res):
                    for r in res:  # the first failure stops everything (terminate below)
                        if r.ready() and not r.successful():
                            r.get()
                    if not _drain(q, tasks, on_item):
                        time.sleep(0.2)
                _drain(q, tasks, on_item)
                out = [r.get() for r in res]
                pool.close()
                return out
            finally:
                pool.terminate()
                pool.join()
    finally:
        for t in tasks:
            t.end()


def _drain(q, tasks, on_item=None) -> bool:
    """Apply the queued reports; True when there were any."""
    got = False
    while True:
        try:
            idx, k, item = q.get_nowait()
        except _queue.Empty:
            return got
        got = True
        tasks[idx].advance(k)
        if item is not None and on_item is not None:
            on_item(idx, item)


# ---- Ray ---------------------------------------------------------------------------------------

class _Reports:
    """The Ray actor (no CPU) that the jobs' ``report`` calls go to; the caller drains it."""

    def __init__(self):
        self.items = []

    def put(self, idx, k, item):
        self.items.append((idx, k, item))

    def flush(self):
        return None

    def drain(self):
        items, self.items = self.items, []
        return items


def _ray_child(fn, kwargs, idx, reporter, *args):
    """One job in a Ray task. Its ``report`` calls go to the actor without waiting (calls from one
    task reach it in order); the last one is awaited before the task returns, so every report is
    there when the caller sees the job done."""
    if reporter is None:
        def report(k: int = 1, item=None) -> None:
            return None
    else:
        def report(k: int = 1, item=None) -> None:
            reporter.put.remote(idx, k, item)
    try:
        return fn(*args, report=report, **kwargs)
    finally:
        if reporter is not None:
            import ray

            ray.get(reporter.flush.remote())


_SCALARS = (int, float, complex, str, bytes, bool, type(None))


def _run_ray(ray, jobs: list[Job], tasks, title: str, on_item, reports: bool) -> list[Any]:
    """:func:`run_jobs` on Ray: one task of one CPU per job (single-threaded, as the local
    processes), results in order, reports forwarded through a :class:`_Reports` actor. An argument
    object that several jobs pass (fit_fd's problem) goes to the object store once."""
    reporter = None
    if reports or on_item is not None:
        reporter = ray.remote(num_cpus=0)(_Reports).remote()
    uses = Counter(id(a) for j in jobs for a in j.args if not isinstance(a, _SCALARS))
    shared = {}
    for j in jobs:
        for a in j.args:
            if uses[id(a)] > 1 and id(a) not in shared:
                shared[id(a)] = ray.put(a)
    remote = ray.remote(_ray_child)
    refs = [remote.options(num_cpus=1, name=f"{title} {j.label}", runtime_env={"env_vars": SINGLE_THREAD_ENV})
            .remote(j.fn, j.kwargs, i, reporter, *[shared.get(id(a), a) for a in j.args])
            for i, j in enumerate(jobs)]

    def drain() -> None:
        if reporter is None:
            return
        for idx, k, item in ray.get(reporter.drain.remote()):
            tasks[idx].advance(k)
            if item is not None and on_item is not None:
                on_item(idx, item)

    pending = list(refs)
    try:
        while pending:
            # waiting releases this task's CPU (in a batch stage task) to the jobs
            done, pending = ray.wait(pending, num_returns=len(pending), timeout=0.2)
            for r in done:  # the first failure stops everything (cancel below)
                try:
                    ray.get(r)
                except ray.exceptions.RayTaskError as e:
                    raise (e.cause if isinstance(e.cause, BaseException) else e) from None
            drain()
        drain()
        return ray.get(refs)
    finally:
        for r in pending:
            ray.cancel(r, force=True)
        if reporter is not None:
            ray.kill(reporter)
