"""The prepared garment made a start the simulator can take (docs/prepare.md, "Session 30").

Every later stage that simulates the prepared template starts it on the fitted body's *collider*
(Anny's simulation mesh) in the first frame's pose: ``reference-sims`` and ``animate`` (the
"frame-1 pose"), and ``fit-physics`` (its window starts at the tracked frame 0, which is the
template). IPC needs that start free of garment-collider crossings; those stages push a crossing
garment out themselves but keep its boundary vertices where they are, and refuse it when crossings
are left (session 19's demo: 6 crossing triangle pairs, 3 after their push).

A prepared garment can cross the collider although the body fit keeps the body under the
clothed hull: the hull refinement then moves garment vertices inwards (up to ``refine.search_in``),
and the collider is a coarser mesh than the body the fit saw. :func:`clear_of_collider` moves the
cloth, boundary vertices included, out of the collider to the simulator's contact distance d̂
(garment.push_clear: push_out along the body normal, then the crossings a vertex-wise push cannot
see), checked with ipctk's exact edge-triangle test (geometry.count_intersections). The cloth moves,
not the body: the body is fitted over every frame and skins the whole template, while the few
crossing garment vertices are within the reconstruction's own error of where they were.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...capture import BodyPoses
from ...errors import PhysavatarError
from .posing import pose_body

ROUNDS = 3  # push_clear rounds before a crossing garment is refused


def clear_of_collider(V: np.ndarray, F: np.ndarray, labels: np.ndarray, boundary: np.ndarray, body: BodyPoses,
                      source: str | Path | None = None, clearance: float | None = None) -> tuple[np.ndarray, dict]:
    """Template vertices ``V`` with its garment (``labels`` > 0) intersection-free with, and at
    least ``clearance`` (default the simulator's d̂) off, ``body``'s collider in frame 0's pose
    (:func:`clear_of_body`); and what was done."""
    model, posed = pose_body(body, [0], topology="collider")
    return clear_of_body(V, F, labels, boundary, posed[0], np.asarray(model.faces, np.int64), source, clearance)


def clear_of_body(V: np.ndarray, F: np.ndarray, labels: np.ndarray, boundary: np.ndarray, body_V: np.ndarray,
                  body_F: np.ndarray, source: str | Path | None = None,
                  clearance: float | None = None) -> tuple[np.ndarray, dict]:
    """Template vertices ``V`` (faces ``F``) with its garment (``labels`` > 0; ``boundary`` flags
    included) moved out of the body surface (``body_V``, ``body_F``) until ipctk finds no crossing
    and every vertex pair is at least ``clearance`` (default d̂) apart, or :data:`ROUNDS` rounds of
    garment.push_clear; returns (vertices, report: crossings and least gap before and after, what
    the later stages' own push with the boundary fixed would leave, vertices moved and how far).
    Raises a :class:`PhysavatarError` naming ``source`` when crossings are left."""
    from ...garment.garment import body_clearance, push_clear
    from ...geometry import count_intersections, submesh
    from ...sim import SimSettings

    clearance = SimSettings().dhat if clearance is None else float(clearance)
    BV, BF = np.asarray(body_V, np.float64), np.asarray(body_F, np.int64)
    ids, Fg = submesh(np.asarray(F, np.int64), np.asarray(labels) > 0)
    x0 = np.asarray(V, np.float64)[ids]
    fixed = np.flatnonzero(np.asarray(boundary, bool)[ids])
    crossing = count_intersections(x0, Fg, BV, BF)
    gap = body_clearance(x0, Fg, BV, BF)
    info = {"clearance_mm": 1e3 * clearance, "crossing_pairs_before": int(crossing), "min_gap_mm_before": 1e3 * gap}
    if crossing:  # what the later stages' own push leaves (their boundary vertices stay)
        info["left_with_boundary_fixed"] = int(push_clear(x0, Fg, BV, BF, clearance, fixed=fixed)[1])
    x, rounds = x0, 0
    while (crossing or gap < clearance) and rounds < ROUNDS:
        x, _ = push_clear(x, Fg, BV, BF, clearance)
        crossing, gap = count_intersections(x, Fg, BV, BF), body_clearance(x, Fg, BV, BF)
        rounds += 1
    step = np.linalg.norm(x - x0, axis=1)
    moved = step > 0
    info.update(rounds=rounds, crossing_pairs_after=int(crossing), min_gap_mm_after=1e3 * gap,
                moved_vertices=int(moved.sum()), moved_boundary_vertices=int(moved[fixed].sum()),
                max_move_mm=1e3 * float(step.max(initial=0.0)),
                mean_move_mm=1e3 * float(step[moved].mean()) if moved.any() else 0.0)
    if crossing:
        raise PhysavatarError(source, f"prepare, step 'clear': the prepared garment still crosses the body's "
                                      f"collider in the first frame's pose ({crossing} intersecting triangle pairs "
                                      f"after pushing {int(moved.sum())} vertices out up to "
                                      f"{info['max_move_mm']:.1f} mm: the body passes through the cloth); the "
                                      "simulation needs an intersection-free start: check the body fit "
                                      "(prepare/report.md) or give body.npz or a labelled template/mesh.ply")
    out = np.array(V, np.float64)
    out[ids] = x
    return out, info


def describe(info: dict) -> str:
    """The step's one line for capture.json and the report."""
    if not info["moved_vertices"]:
        return (f"the garment is clear of the fitted body's collider (frame 0: no crossings, "
                f"{info['min_gap_mm_before']:.2f} mm at the closest)")
    return (f"pushed out of the fitted body's collider (frame 0): {info['crossing_pairs_before']} crossing "
            f"triangle pairs and {info['min_gap_mm_before']:.2f} mm at the closest before, "
            f"{info['moved_vertices']} vertices ({info['moved_boundary_vertices']} boundary) moved, "
            f"{info['mean_move_mm']:.2f} mm mean, {info['max_move_mm']:.2f} mm max; after: "
            f"{info['crossing_pairs_after']} crossings, {info['min_gap_mm_after']:.2f} mm")
