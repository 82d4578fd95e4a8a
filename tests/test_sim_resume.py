"""Never lose work, every frame: resumed simulations equal uninterrupted ones, sub-steps are
decided per frame from how far the body moves, progress is logged when output is not a terminal."""

import json
import logging

import numpy as np
import pytest
import trimesh

from cloth_grid import grid
from physavatar.sim import Material, SimSettings, simulate
from physavatar.sim.simulate import Checkpoint, substep_count

MAT = Material(density=0.15, stretch_stiffness=30.0, bend_stiffness=1e-5)


def sphere(radius=0.1):
    m = trimesh.creation.icosphere(subdivisions=2, radius=radius)
    return np.asarray(m.vertices), np.asarray(m.faces)


def rising_sphere(frames=6, speed=0.03):
    """A cloth pinned at its corners and a sphere rising into it, then sideways."""
    V, F = grid(7, 0.3)
    V = V - [0.15, 0.15, 0.0]
    B, BF = sphere()
    path = [np.array([0.0, 0.0, -0.13 + speed * min(t, 4)]) + [0.02 * max(t - 4, 0), 0, 0] for t in range(frames)]
    return V, F, np.stack([B + p for p in path]), BF, [0, 6, 42, 48]


class Stop(Exception):
    pass


@pytest.mark.parametrize("integrator", ["euler", "bdf2"])
def test_an_interrupted_run_resumed_from_its_checkpoint_is_bit_identical(integrator, tmp_path):
    V, F, seq, BF, pins = rising_sphere()
    settings = SimSettings(integrator=integrator, damping_mass=0.5)
    kw = dict(fps=25.0, settings=settings, max_substeps=4)
    full = simulate(V, F, MAT, seq, BF, pins, None, **kw)

    saved = {}

    def on_frame(ck, report):
        ck.save(tmp_path / "state.npz")  # as simulate/animate do: the checkpoint after each frame
        saved[ck.frame] = ck.x

    def interrupt(event):  # a progress listener that stops the run after 3 frames (Ctrl-C)
        if event.kind == "advance" and event.done == 3:
            raise Stop

    with pytest.raises(Stop):
        simulate(V, F, MAT, seq, BF, pins, None, on_frame=on_frame, progress=interrupt, **kw)
    ck = Checkpoint.load(tmp_path / "state.npz")
    assert ck.frame == 3 and sorted(saved) == [1, 2, 3]
    if integrator == "bdf2":
        assert "last_step" in ck.solver  # BDF2's history travels with the checkpoint
    rest = simulate(V, F, MAT, seq, BF, pins, None, resume=ck, **kw)
    assert np.isnan(rest[:3]).all()
    for f in (1, 2, 3):
        assert np.array_equal(saved[f], full[f])
    assert np.array_equal(rest[3:], full[3:])  # bit-identical, not merely close
    assert np.abs(full[-1] - full[0]).max() > 0.02  # the cloth did move



def _widening_box(height: float, frames: int, rise: float = 0.0):
    """A 9 x 9 cloth ``height`` above the top of a box whose top widens (and rises by ``rise`` a
    frame) under it: (V, F, box sequence, box faces)."""
    V, F = grid(9, 0.3, center=True)
    V[:, 2] = 0.01 + height
    box = trimesh.creation.box((0.2, 0.2, 0.02))
    B, BF = np.asarray(box.vertices), np.asarray(box.faces)
    seq = np.stack([B * [1 + 0.03 * t, 1 + 0.02 * t, 1] + [0, 0, rise * t] for t in range(frames)])
    return V, F, seq, BF


def _interrupted_and_resumed(args, kw, at: int):
    """``simulate(*args, **kw)`` stopped after frame ``at`` and resumed from its checkpoint there:
    (the checkpoint, the resumed run)."""
    saved = {}

    def on_frame(ck, report):
        saved[ck.frame] = ck
        if ck.frame == at:
            raise Stop

    with pytest.raises(Stop):
        simulate(*args, on_frame=on_frame, **kw)
    return saved[at], simulate(*args, resume=saved[at], **kw)


def test_a_run_on_a_deforming_body_resumes_bit_identical(tmp_path):
    """A body whose edges change length (a box widening under a cloth lying on it, its edges
    parallel to the cloth's): ipctk's edge-edge mollifier thresholds come from the contact
    scene's rest positions, which a resumed run used to take from the body at the frame it
    resumed at (docs/simulation.md "Session 25"; 15 mm apart two frames after the resume)."""
    V, F, seq, BF = _widening_box(0.0005, 8, rise=0.002)  # 0.5 mm above the box's top
    kw = dict(fps=25.0, settings=SimSettings(), max_substeps=4)
    args = (V, F, MAT, seq, BF, [], None)
    full = simulate(*args, **kw)
    ck, rest = _interrupted_and_resumed(args, kw, 3)
    assert np.array_equal(ck.x, full[3])
    assert np.array_equal(rest[3:], full[3:])
    assert np.abs(full[-1] - full[3]).max() > 0.01  # the cloth moved after the resume


def test_a_run_whose_contact_offset_was_lowered_resumes_with_the_same_thickness(tmp_path, caplog):
    """A start too close to the body for the material's contact offset (a pinned vertex 2.5 mm
    above a widening box, the offset 4 mm) is simulated with a lowered thickness (with a
    warning); a resumed run must use that same thickness, not the material's (ipctk's barrier
    is undefined closer than d_min)."""
    import dataclasses

    V, F, seq, BF = _widening_box(0.0025, 7)
    pin = [int(np.argmin(np.linalg.norm(V[:, :2], axis=1)))]  # the centre vertex, held where it is
    args = (V, F, dataclasses.replace(MAT, contact_offset=0.004), seq, BF, pin, None)
    kw = dict(fps=25.0, settings=SimSettings(), max_substeps=4)
    with caplog.at_level(logging.WARNING, logger="physavatar.sim.simulate"):
        full = simulate(*args, **kw)
    assert any("closer than the contact offset" in r.getMessage() for r in caplog.records)
    _, rest = _interrupted_and_resumed(args, kw, 3)
    assert np.isfinite(rest[3:]).all()
    assert np.array_equal(rest[3:], full[3:])


def test_substeps_follow_how_far_the_body_near_the_cloth_moves():
    s = SimSettings(max_body_move=0.05)
    cloth, _ = grid(5, 0.3)
    B, _ = sphere()
    body = B + [0.15, 0.15, -0.12]  # just under the cloth
    assert substep_count(body, body, cloth, s, 1, 16) == (1, 0.0)  # still: one step
    assert substep_count(body, body + [0, 0, 0.04], cloth, s, 1, 16)[0] == 1
    n, move = substep_count(body, body + [0, 0, 0.23], cloth, s, 1, 16)
    assert n == 5 and move == pytest.approx(0.23)  # ceil(0.23 / 0.05)
    assert substep_count(body, body + [0, 0, 2.0], cloth, s, 1, 16)[0] == 16  # capped
    assert substep_count(body, body + [0, 0, 0.23], cloth, s, 1, 1)[0] == 1  # a fixed count
    assert substep_count(body, body + [0, 0, 0.01], cloth, s, 3, 16)[0] == 3  # at least the minimum
    far = body + [5.0, 0, 0]  # fast, but nowhere near the cloth
    assert substep_count(far, far + [0, 0.3, 0], cloth, s, 1, 16)[0] == 1


def test_a_fast_sweep_that_lagged_in_one_step_is_intersection_free_with_substeps():
    """A ball sweeps 0.3 m in one frame through a hanging curtain. With the carry off and a
    10-iteration penalty budget (the penalty phase alone must push the cloth: a small stand-in
    for the CMU hop's 0.2-0.3-m frames) one step per frame gives up, the body lags ~0.1 m and the
    written frames cross the given body. Per-frame sub-steps (4 from the move, then 8 after the
    retry) reach every pose: no lag, no intersection (geometry.count_intersections, ipctk's exact
    edge-triangle test, independent of the solver's own checks)."""
    from physavatar.geometry import count_intersections

    V, F = grid(9, 0.3)
    V = np.c_[V[:, 0] - 0.15, np.zeros(len(V)), V[:, 1] - 0.15]  # vertical, in the x-z plane
    pins = np.flatnonzero(V[:, 2] > 0.149)
    B, BF = sphere(0.06)
    seq = np.stack([B + [0, y, 0] for y in (-0.2, 0.1, 0.1)])
    settings = SimSettings(follow_body=0.0, max_penalty_iterations=10)

    def run(max_substeps):
        reports = []
        X = simulate(V, F, MAT, seq, BF, pins, None, fps=25.0, settings=settings, max_substeps=max_substeps,
                     on_frame=lambda c, r: reports.append(r))
        return X, reports, [count_intersections(X[f], F, seq[f], BF) for f in range(len(X))]

    X1, rep1, cross1 = run(1)
    assert rep1[0]["lagged"] and rep1[0]["lag_m"] > 0.05 and cross1[2] > 0  # before: lag, crossing
    X16, rep16, cross16 = run(16)
    assert [r["lagged"] for r in rep16] == [False, False] and cross16 == [0, 0, 0]
    assert rep16[0]["substeps"] == 8 and rep16[0]["attempts"] == 2  # ceil(0.3 / 0.08) = 4, then doubled
    assert rep16[0]["body_move_m"] == pytest.approx(0.3)
    assert X16[2][:, 1].max() > 0.1  # the curtain was pushed ahead of the ball


def test_progress_lines_are_logged_every_few_frames(caplog):
    V, F, seq, BF, pins = rising_sphere(frames=6)
    with caplog.at_level(logging.INFO, logger="physavatar.progress"):
        simulate(V, F, MAT, seq, BF, pins, None, fps=25.0, settings=SimSettings(damping_mass=0.5), progress=False)
    lines = [r.getMessage() for r in caplog.records if r.name == "physavatar.progress"]
    frame5 = [x for x in lines if x.startswith("simulating: 5/5")]
    assert frame5, lines
    for key in ("frame 5", "s_frame", "newton", "contacts", "substeps", "lag_mm"):
        assert key in frame5[0]


def test_simulate_interrupted_and_run_again_resumes_with_the_same_result(tmp_path):
    """`physavatar simulate`'s stage: frames are on disk as they are finished (frames/, meshes/),
    a second run of the same command resumes after the last one, and the final
    garment_sequence.npz equals an uninterrupted run's; frames/ is gone at the end."""
    from physavatar.data.garment_sequence import GarmentSequence
    from physavatar.files import save_npz_atomic
    from physavatar.stages import simulate as stage

    V, F, seq, BF, pins = rising_sphere(frames=6)
    V = V + [0, 0, 0.002]
    save_npz_atomic(tmp_path / "body.npz", vertices=seq, faces=BF)
    save_npz_atomic(tmp_path / "cloth.npz", vertices=V, faces=F, boundary=np.array(pins))
    cfg = stage.SimulateConfig(preview=False, max_substeps=4)
    kw = dict(config=cfg, collider=tmp_path / "body.npz", garment=tmp_path / "cloth.npz")
    stage.run(out=tmp_path / "whole", **kw)

    def interrupt(event):
        if event.kind == "advance" and event.done == 2:
            raise KeyboardInterrupt

    out = tmp_path / "cut"
    with pytest.raises(KeyboardInterrupt):
        stage.run(out=out, progress=interrupt, **kw)
    assert sorted(p.name for p in (out / "frames").glob("0*.npz")) == ["000001.npz", "000002.npz"]
    assert len(list((out / "meshes").glob("*.ply"))) == 3 and not (out / "garment_sequence.npz").exists()
    starts = []
    r = stage.run(out=out, progress=lambda e: starts.append(e.total) if e.kind == "start" else None, **kw)
    assert starts == [3]  # frames 3, 4, 5: resumed after frame 2
    a, b = GarmentSequence.load(tmp_path / "whole"), GarmentSequence.load(out)
    assert np.array_equal(a.vertices, b.vertices) and not (out / "frames").exists()
    rec = json.loads((out / "config.json").read_text())
    assert rec["resumed_after_frame"] == 2 and rec["frames_with_lag"] == [] and r.bad_frames == []
    assert rec["per_frame"]["frame"] == [1, 2, 3, 4, 5]


def test_self_contact_needs_a_start_with_the_garments_own_triangles_apart():
    from physavatar.sim.simulate import self_contact_possible

    V, F = grid(5, 0.2)
    two = np.vstack([F, F + len(V)])
    assert self_contact_possible(V, F, 1e-3)
    assert self_contact_possible(np.vstack([V, V + [0, 0, 5e-3]]), two, 1e-3)  # layers 5 mm apart
    assert not self_contact_possible(np.vstack([V, V + [0, 0, 5e-4]]), two, 1e-3)  # 0.5 mm < d̂


def test_a_run_resumes_on_other_thread_counts_but_not_on_other_settings():
    """The fingerprint a written run resumes by leaves out the settings that change no result
    (thread counts: bit-identical on any number) and keeps every other one."""
    from physavatar.data.sim_frames import fingerprint, run_settings

    V, F, *_ = rising_sphere()

    def key(settings):
        return fingerprint(V, F, settings=run_settings(settings), fps=25.0)

    default = key(SimSettings())
    assert key(SimSettings(ccd_threads=2)) == default
    # candidate builds on 1 or 2 threads sort the barrier sets: the same bits as each other, not as 0's
    assert key(SimSettings(candidate_threads=2)) == key(SimSettings(candidate_threads=1)) != default
    assert key(SimSettings(dhat=2e-3)) != default and key(SimSettings(max_penalty_iterations=20)) != default
    assert run_settings(None) is None


@pytest.mark.parametrize("ends_short", [False, True])
def test_a_frame_whose_body_catches_up_before_its_end_is_not_stuck(ends_short, monkeypatch):
    """Session 29: after a frame whose last attempt (max_substeps) lagged, the next frame is
    retried in shorter steps unless that frame's body was still short of its pose at the frame's
    end ("stuck": no room for the cloth at the pose). The solver's steps are real; the lag is
    reported by a wrapper of ``_frame``: frame 1 lags in its first step in every attempt (and in
    its last step too when ``ends_short``), frame 2's first attempt lags in every step."""
    import sys

    S = sys.modules["physavatar.sim.simulate"]  # (the package exports the function under that name)

    V, F, seq, BF, pins = rising_sphere(frames=4)
    real, calls = S._frame, []

    def frame(sim, x, v, b0, b1, faces, tb0, tb1, n, fps, stop_on_lag=False, **kw):
        x, v, stats = real(sim, x, v, b0, b1, faces, tb0, tb1, n, fps, stop_on_lag, **kw)
        f = next(i for i in range(len(seq)) if np.array_equal(seq[i], b1))
        calls.append((f, n))
        if f == 1:
            stats[0].body_gap = 1e-5
            if ends_short:
                stats[-1].body_gap = 1e-5
        if f == 2 and sum(c[0] == 2 for c in calls) == 1:
            for s in stats:
                s.body_gap = 1e-5
        return x, v, stats

    monkeypatch.setattr(S, "_frame", frame)
    reports, stuck = {}, {}

    def on_frame(ck, report):
        reports[ck.frame], stuck[ck.frame] = report, ck.solver["stuck"]

    simulate(V, F, MAT, seq, BF, pins, None, fps=25.0, max_substeps=2, on_frame=on_frame)
    assert [n for f, n in calls if f == 1] == [1, 2]  # lagged, retried once, up to max_substeps
    assert stuck[1] == ends_short
    # frame 2: retried in shorter steps after a frame that caught up; one attempt after a stuck one
    assert reports[2]["attempts"] == (1 if ends_short else 2)
    assert [n for f, n in calls if f == 2] == ([1] if ends_short else [1, 2])
