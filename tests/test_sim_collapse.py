"""The collider's own collapse undone for a frame that pinches (sim.collapse, sim.simulate)."""

import cloth_grid
import numpy as np
import trimesh

from physavatar.geometry.closest import MeshQuery
from physavatar.sim import Material, SimSettings, simulate
from physavatar.sim.collapse import uncollapse
from physavatar.sim.crease import buried_vertices


def box(center, extents, subdivisions=3):
    m = trimesh.creation.box(extents=extents)
    V, F = m.vertices, m.faces
    for _ in range(subdivisions):
        V, F = trimesh.remesh.subdivide(V, F)
    return np.asarray(V) + center, np.asarray(F)


def knee():
    """A (the thigh: top face z = 0) and B (the calf: x in [0.05, 0.15], standing on A with its
    bottom 1 cm inside A), one mesh, and the same body a frame later with one vertex of B's wall
    (the one facing the cloth, 1.6 cm above A) collapsed 8 cm deep into A, under the cloth, as
    linear blend skinning folds the back of a knee (docs/simulation.md "Session 27")."""
    VA, FA = box([0.0, 0.0, -0.06], (0.3, 0.12, 0.12))
    VB, FB = box([0.1, 0.0, 0.095], (0.1, 0.12, 0.21))
    B0, F = np.vstack([VA, VB]), np.vstack([FA, FB + len(VA)])
    wall = np.flatnonzero((np.abs(VB[:, 0] - 0.05) < 1e-9) & (np.abs(VB[:, 1]) < 1e-9))
    p = len(VA) + wall[np.argmin(np.abs(VB[wall, 2] - 0.0225))]
    B1 = B0.copy()
    B1[p] = (-0.02, 0.0, -0.08)
    return B0, B1, F


crosses = cloth_grid.body_crossings


def test_uncollapse_moves_the_buried_vertices_onto_the_outer_surface():
    B0, B1, F = knee()
    assert buried_vertices(B1, F).sum() > 10  # B's bottom, A's top inside B, the collapsed vertex
    U, moved = uncollapse(B1, F)
    assert not buried_vertices(U, F).any()
    np.testing.assert_array_equal(np.flatnonzero(np.any(U != B1, axis=1)), moved)
    # each moved vertex ends on the body's surface (within 2 cm of it as given: it was up to 8 cm deep)
    assert np.all(MeshQuery(B1, F, spacing=0.01).closest(U[moved])[0] < 0.02)
    # a body that does not pass through itself is given back as it is
    V, _ = box([0.0, 0.0, 0.0], (0.1, 0.1, 0.1))
    Fv = box([0.0, 0.0, 0.0], (0.1, 0.1, 0.1))[1]
    assert uncollapse(V, Fv)[0] is V and len(uncollapse(V, Fv)[1]) == 0


def test_a_frame_pinched_by_the_bodys_collapse_is_retried_on_the_uncollapsed_body():
    """Cloth on A next to B; B's wall collapses into A through it. On the given body the frame
    lags (the collapsing triangles sweep the cloth into A), and the crease rule's retry leaves it
    crossing the body. Retried first on the uncollapsed body, the frame is written without lag
    and without crossing the body as given."""
    B0, B1, Fb = knee()
    V, F = cloth_grid.grid(9, 0.09, 0.0015, center=True)  # on A's top, x in [-0.045, 0.045]
    out = {}
    for unc in (False, True):
        reports = []
        X = simulate(V, F, Material(), np.stack([B0, B1]), Fb, fps=25.0, max_substeps=4,
                     settings=SimSettings(friction=0.0, uncollapse=unc),
                     on_frame=lambda c, r, reports=reports: reports.append((c, r)))
        out[unc] = (X[-1], reports[-1][0], reports[-1][1])
    assert crosses(out[False][0], F, B1, Fb)  # main's rule: through the body
    x, ck, rep = out[True]
    assert rep["attempts"] == 2 and rep["lag_m"] == 0.0 and rep["buried_vertices"] == 0
    assert not crosses(x, F, B1, Fb) and not crosses(x, F, uncollapse(B1, Fb)[0], Fb)
    assert ck.solver["uncollapsed"]  # a resumed run starts the next frame on the same body


def test_a_crease_attempt_left_through_the_body_gives_way_to_shorter_steps():
    """B's wall folds over the cloth in one frame, to 4 mm above A (2.5 mm above the cloth): room
    for the cloth, but one step lags (as the 2-cm dress's lap on the sit-down, written frame 22,
    docs/simulation.md "Session 33: sit-down"). The uncollapsed retry lags too, and the crease
    rule's attempt does not lag but leaves the cloth through the triangles it hid, which the
    frame-end untangle cannot clear (its result still crosses the body and the cloth itself, so
    it is not kept): before, that attempt was written, through the body. Now the whole body in shorter steps comes first: 16
    steps without lag, and the frame is written free of intersections (ipctk's exact test,
    cloth against body and itself)."""
    B0, B1, Fb = knee()
    B1[np.flatnonzero(np.any(B0 != B1, axis=1))] = (-0.02, 0.0, 0.004)
    V, F = cloth_grid.grid(9, 0.09, 0.0015, center=True)
    reports = []
    X = simulate(V, F, Material(), np.stack([B0, B1]), Fb, fps=25.0, max_substeps=16,
                 settings=SimSettings(friction=0.0, self_contact=True), on_frame=lambda c, r: reports.append(r))
    rep = reports[-1]
    assert not crosses(X[1], F, B1, Fb)  # before: crossing (the crease attempt, 1 step)
    assert not rep["lagged"] and rep["lag_m"] == 0.0 and rep["substeps"] == 16 and rep["attempts"] > 3


def test_a_frame_after_an_untangle_that_flattened_a_triangle_does_not_stop():
    """Session 27's knee with ``uncollapse`` off, held at its collapsed pose for a second frame:
    frame 1's untangle puts three vertices of a cloth triangle on one edge of the box (no area),
    and frame 2's bending gradient stopped with ZeroDivisionError. It now runs, and the membrane
    gives the triangle its area back (each triangle ≥ 90 % of its rest area)."""
    B0, B1, Fb = knee()
    V, F = cloth_grid.grid(9, 0.09, 0.0015, center=True)
    seen = []
    X = simulate(V, F, Material(), np.stack([B0, B1, B1]), Fb, fps=25.0, max_substeps=16,
                 settings=SimSettings(friction=0.0, uncollapse=False), on_frame=lambda c, r: seen.append(c.x))

    def area(x):
        return 0.5 * np.linalg.norm(np.cross(x[F[:, 1]] - x[F[:, 0]], x[F[:, 2]] - x[F[:, 0]]), axis=1)

    assert np.min(area(seen[0]) / area(V)) < 1e-6  # the flattened triangle the frame starts from
    assert len(X) == 3 and np.isfinite(X).all()
    assert np.min(area(X[2]) / area(V)) > 0.9
