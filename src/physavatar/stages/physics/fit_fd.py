"""The paper's estimator (Algorithm 1): forward finite differences of the objective and Adam.

The 1 + P simulations of an iteration run in a spawn-context process pool (``workers``), each
worker holding the problem once (:func:`_worker_init`). When a Ray runtime is active (a
``physavatar batch --ray`` stage task) they are Ray tasks instead, through
:func:`physavatar.parallel.run_jobs` (the problem in the object store once per iteration).
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import math
import multiprocessing
import os
import time
from collections.abc import Callable

import numpy as np

from ...errors import PhysavatarError
from ...optim import Adam
from ...parallel import SINGLE_THREAD_ENV, Job, ray_active, run_jobs
from ...sim import Material, SimSettings
from .data import PhysicsData
from .objective import (
    fit_residuals,
    history_row,
    ratio_intervals,
    rms_mm,
    rollout,
    settings_record,
    trajectory_loss,
)
from .outputs import FitResult
from .parameters import (
    ADAM_LR,
    ADAM_LR_FINAL_FRACTION,
    FD_STEP,
    PAPER_ITERATIONS,
    PARAMETERS,
    fit_settings,
    log_theta,
    theta_bounds,
    with_log_params,
)

_WORKER: dict = {}


def _worker_init(data, material, settings, names, substeps, shape_weight=0.0):
    _WORKER.update(data=data, material=material, settings=settings, names=names, substeps=substeps,
                   shape_weight=shape_weight)


def _worker_simulate(log_values):
    """One FD simulation in a pool worker: (loss, positions) or (inf, None) if it fails."""
    return _simulate(_WORKER, log_values)


def _simulate_job(problem: dict, log_values, report=None):
    """One FD simulation as a :func:`physavatar.parallel.run_jobs` job (on Ray)."""
    return _simulate(problem, log_values)


def _simulate(w: dict, log_values):
    m = with_log_params(w["material"], w["names"], log_values)
    try:
        r = rollout(w["data"], m, w["settings"], substeps=w["substeps"])
    except (FloatingPointError, np.linalg.LinAlgError, RuntimeError):
        return math.inf, None
    res, _ = fit_residuals(r.positions, w["data"], w["shape_weight"])
    return float(res @ res), r.positions.astype(np.float32)


@contextlib.contextmanager
def _single_threaded_children():
    """Spawned workers inherit the environment: one BLAS / numba / OpenMP thread each, so two
    workers on two cores do not oversubscribe them (set before the children import numpy)."""
    old = {k: os.environ.get(k) for k in SINGLE_THREAD_ENV}
    os.environ.update(SINGLE_THREAD_ENV)
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


class _Evaluator:
    """Runs batches of simulations: Ray tasks when Ray is active, else a spawn-context process
    pool, or inline with workers=0/1."""

    def __init__(self, data, material, settings, names, substeps, workers, shape_weight=0.0):
        self.workers = workers
        self.pool = None
        self.problem = None
        if ray_active() is not None:  # the cluster schedules: ``workers`` does not apply
            self.problem = {"data": data, "material": material, "settings": settings, "names": names,
                            "substeps": substeps, "shape_weight": shape_weight}
        elif workers > 1:
            with _single_threaded_children():
                self.pool = concurrent.futures.ProcessPoolExecutor(
                    max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                    initializer=_worker_init, initargs=(data, material, settings, names, substeps, shape_weight))
                # start the workers now, while the environment says one thread each
                list(self.pool.map(_noop, range(workers)))
        else:
            _worker_init(data, material, settings, names, substeps, shape_weight)

    def map(self, points):
        if self.problem is not None:
            return run_jobs([Job(f"θ+δ{i}" if i else "θ", _simulate_job, (self.problem, p)) for i, p in enumerate(points)],
                            progress=False, title="fd", ray=True)
        if self.pool is None:
            return [_worker_simulate(p) for p in points]
        return list(self.pool.map(_worker_simulate, points))

    def close(self):
        if self.pool is not None:
            self.pool.shutdown(cancel_futures=True)


def _noop(_):
    return None


def fit_fd(data: PhysicsData, initial: Material, settings: SimSettings | None = None,
           iterations: int = PAPER_ITERATIONS, fit_density: bool = False, workers: int = 2,
           substeps: int = 1, callback: Callable | None = None, shape_weight: float = 0.0) -> FitResult:
    """Algorithm 1: forward finite differences (Eq. 7) and Adam, in log space.

    Each iteration simulates θ and θ + δ_p e_p for every fitted p (in parallel over ``workers``
    processes, or as Ray tasks when Ray is active), takes ΔL/δ as the gradient, and makes one Adam step (lr cosine-annealed from
    0.1 to 0.04 on log κ, the paper's values mapped at its start point; module constants).
    The result is the best iterate seen (as the official driver keeps). The residual Jacobian
    of the last iteration's differences gives the confidence intervals. ``shape_weight``: as in
    :func:`fit_exact` (0, the paper's L_sim, by default).
    """
    settings = settings or fit_settings()
    names = PARAMETERS if fit_density else PARAMETERS[1:]
    theta = log_theta(initial, names)
    delta = np.array([FD_STEP[n] for n in names])
    lr0 = np.array([ADAM_LR[n] for n in names])
    lo, hi = theta_bounds(names)
    adam = Adam({"theta": theta.shape})
    t_start = time.perf_counter()
    history = []
    best = (math.inf, theta.copy(), None, None, math.inf)
    sims = 0
    ev = _Evaluator(data, initial, settings, names, substeps, workers, shape_weight)
    ref = data.reference
    try:
        for it in range(iterations):
            points = [theta.copy()] + [theta + d for d in np.diag(delta)]
            results = ev.map(points)
            sims += len(points)
            losses = np.array([r[0] for r in results])
            loss = losses[0]
            if not np.isfinite(loss):
                raise PhysavatarError(None, f"simulation failed at {dict(zip(names, np.exp(theta)))}")
            grad = np.where(np.isfinite(losses[1:]), (losses[1:] - loss) / delta, 0.0)
            base = results[0][1].astype(np.float64)
            lsim = loss if shape_weight <= 0 else trajectory_loss(base, ref)
            if loss < best[0]:
                fd_jac = None
                if all(r[1] is not None for r in results):
                    fd_jac = np.stack([(r[1].astype(np.float64) - base)[1:].ravel() / d
                                       for r, d in zip(results[1:], delta)], axis=1)
                best = (loss, theta.copy(), fd_jac, (base - ref)[1:].ravel(), lsim)
            row = history_row(it, lsim, data, names, theta, t_start, sims, loss)
            history.append(row)
            if callback is not None:
                callback(row)
            # Adam (bias-corrected) with the official driver's cosine learning-rate schedule
            lr = lr0 * (ADAM_LR_FINAL_FRACTION + (1 - ADAM_LR_FINAL_FRACTION) * 0.5 * (1 + math.cos(math.pi * it / iterations)))
            theta = np.clip(adam.step({"theta": theta}, {"theta": grad}, lr)["theta"], lo, hi)
    finally:
        ev.close()
    objective, theta_best, fd_jac, resid, loss = best
    material = dataclasses.replace(with_log_params(initial, names, theta_best), name="fitted (fd)",
                                   integrator=settings.integrator)
    intervals, stds = ratio_intervals(fd_jac, resid, list(names), material) if fd_jac is not None else ({}, {})
    return FitResult(material, initial, float(loss), rms_mm(loss, data), iterations, sims,
                     time.perf_counter() - t_start, "fd", names, history, intervals, stds, data.frames,
                     settings_record(settings, substeps, data.fps), shape_weight=shape_weight, objective=float(objective))

