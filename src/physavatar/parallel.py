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
"""

from __future__ import annotations

import multiprocessing
import os
import queue as _queue
import time
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


def _child(fn, args, kwargs, q, idx):
    def report(k: int = 1, item=None) -> None:
        q.put((idx, k, item))

    return fn(*args, report=report, **kwargs)


def run_jobs(jobs: list[Job], *, workers: int | None = None, progress=True,
             title: str = "simulating", on_item: Callable | None = None) -> list[Any]:
    """Run ``jobs``; returns their results in order. An exception in a job is raised here (the
    other jobs are cancelled); Ctrl-C stops all of them.

    ``on_item(job_index, item)`` is called in this process for every ``report(k, item)`` a job
    makes with an item (e.g. a finished frame), in the order each job reported them, while the
    jobs run: this process can use the results as they come (synth renders finished frames).
    """
    from .progress import resolve

    workers = default_workers(len(jobs)) if workers is None else max(1, min(workers, len(jobs)))
    prog = resolve(progress)
    tasks = [prog.task(f"{title} {j.label}", total=j.total) for j in jobs]
    try:
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
