"""A whole sequence: a garment simulated on a moving body frame after frame (``simulate``)."""

from __future__ import annotations

import dataclasses

import numpy as np

from ..progress import ProgressLike, resolve
from .material import Material
from .settings import SimSettings
from .solver import ClothSim


def simulate(garment_rest, faces, material: Material, collider_sequence, collider_faces,
             boundary_indices=(), boundary_targets=None, fps: float = 25.0, substeps: int = 1,
             settings: SimSettings | None = None, x0=None, v0=None, callback=None,
             progress: ProgressLike = False, extra_terms=()):
    """Simulate a garment on a moving body for a whole sequence.

    Args:
        garment_rest: [N, 3] rest shape (also the initial state unless ``x0`` is given).
        faces: [F, 3] garment triangles.
        material: :class:`Material`.
        collider_sequence: [T, Nb, 3] body vertices per frame (frame 0 = initial pose).
        collider_faces: [Fb, 3] body triangles.
        boundary_indices: [K] Dirichlet vertices.
        boundary_targets: [T, K, 3] their positions per frame, or a callable
            ``rule(frame, body_vertices [Nb, 3]) -> [K, 3]`` (an attachment rule), or None
            (they stay at their initial positions).
        fps: frames per second of the sequence; substeps: implicit steps per frame
            (dt = 1 / (fps · substeps); body and targets are interpolated linearly in between).
        settings: :class:`SimSettings` (its dt is replaced by the one above); default: the
            defaults with the material's integrator (the one it was fitted with).
        x0, v0: [N, 3] initial positions / velocities (default rest, zero).
        callback: called as ``callback(frame, x [N, 3], stats list)`` after each frame.
        progress: anything :func:`physavatar.progress.resolve` takes (True: a terminal bar;
            a callable or a Progress: its task "simulating", one step per frame).
        extra_terms: further terms of E (ClothSim's, e.g. a seam :class:`~physavatar.sim.stitch.Stitch`).

    Returns:
        [T, N, 3] garment positions per frame (frame 0 = initial state).
    """
    settings = settings or SimSettings(integrator=material.integrator)  # the model it was fitted in
    dt = 1.0 / (fps * substeps)
    settings = dataclasses.replace(settings, dt=dt)
    bodies = np.asarray(collider_sequence, dtype=np.float64)
    T = len(bodies)
    sim = ClothSim(garment_rest, faces, material, settings, boundary_indices, extra_terms=extra_terms)
    order = np.argsort(np.asarray(boundary_indices, dtype=np.int64), kind="stable")
    x = np.array(garment_rest if x0 is None else x0, dtype=np.float64)
    v = np.zeros_like(x) if v0 is None else np.array(v0, dtype=np.float64)

    def targets(frame):
        if len(sim.boundary) == 0:
            return None
        if boundary_targets is None:
            return x0_boundary
        if callable(boundary_targets):
            return np.asarray(boundary_targets(frame, bodies[frame]))[order]
        return np.asarray(boundary_targets[frame])[order]

    x0_boundary = x[sim.boundary].copy()
    out = np.empty((T,) + x.shape)
    out[0] = x
    with resolve(progress).task("simulating", total=T - 1) as task:
        for f in range(1, T):
            stats_frame = []
            tb0, tb1 = targets(f - 1), targets(f)
            for k in range(substeps):
                w0, w1 = k / substeps, (k + 1) / substeps
                b0 = (1 - w0) * bodies[f - 1] + w0 * bodies[f]
                b1 = (1 - w1) * bodies[f - 1] + w1 * bodies[f]
                tgt = None if tb1 is None else (1 - w1) * tb0 + w1 * tb1
                x, v, st = sim.step(x, v, b0, b1, collider_faces, tgt)
                stats_frame.append(st)
            out[f] = x
            if callback is not None:
                callback(f, x, stats_frame)
            task.advance(1)
    return out
