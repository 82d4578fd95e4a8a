"""`physavatar reference-sims` keeps every row it finished (session 34: a stopped run lost them all)."""

import json

import numpy as np
import pytest


def _rows(folder):
    from physavatar.files import load_npz

    return {p.name: load_npz(p / "sequence.npz")["vertices"] for p in sorted(folder.iterdir())
            if (p / "sequence.npz").is_file()}


def test_reference_sims_resume_after_a_stopped_run(tmp_path, tiny_capture, monkeypatch):
    """A run stopped after its first row (the second job raises) leaves that row written; the rerun
    simulates only the missing row, and every row equals an uninterrupted run's bit for bit."""
    import physavatar.stages.animate as animate_mod
    from physavatar.stages.evaluate import reference_sequences

    monkeypatch.setenv("PHYSAVATAR_WORKERS", "1")  # the jobs in this process, in order
    kw = dict(frames=3, random_draws=1, rest_shape="template", progress=False)
    real = animate_mod.animate_job
    calls = []

    def counted(avatar_dir, material, motion, report=None, **k):
        calls.append(material.name)
        if stop_after is not None and len(calls) > stop_after:
            raise RuntimeError("stopped")
        return real(avatar_dir, material, motion, report=report, **k)

    monkeypatch.setattr(animate_mod, "animate_job", counted)
    stop_after = None
    reference_sequences(tiny_capture, tmp_path / "whole", **kw)
    whole = _rows(tmp_path / "whole")
    assert sorted(whole) == ["random-0", "true"] and len(calls) == 2
    true_name = calls[0]

    calls.clear()
    stop_after = 1
    with pytest.raises(RuntimeError, match="stopped"):
        reference_sequences(tiny_capture, tmp_path / "cut", **kw)
    assert not (tmp_path / "cut" / "references.json").exists()
    assert sorted(_rows(tmp_path / "cut")) == ["true"]  # the finished row is on disk
    assert not list((tmp_path / "cut").glob(".*partial"))

    calls.clear()
    stop_after = None
    reference_sequences(tiny_capture, tmp_path / "cut", **kw)
    assert calls == ["random-0"]  # only the missing row is simulated
    again = _rows(tmp_path / "cut")
    assert sorted(again) == sorted(whole)
    for name in whole:
        np.testing.assert_array_equal(again[name], whole[name])
    made = json.loads((tmp_path / "cut" / "references.json").read_text())
    assert made["reused"] == ["true material"] and made["rows"] == ["true material", "random material (seed 0)"]
    assert calls[0] != true_name

    # a third run has nothing to simulate; another contact thickness makes the draw again, not the true row
    calls.clear()
    reference_sequences(tiny_capture, tmp_path / "cut", **kw)
    assert calls == []
    reference_sequences(tiny_capture, tmp_path / "cut", contact_offset=0.002, **kw)
    assert calls == ["random-0"]
    meta = json.loads((tmp_path / "cut" / "random-0" / "sequence.json").read_text())
    assert meta["material"]["contact_offset"] == pytest.approx(0.002)


def test_rows_warmed_up_under_gravity_are_stale_for_a_weightless_warmup(tmp_path, tiny_capture, monkeypatch):
    """evaluate reuses a references folder's rows only where they start the motion as its own
    animate would: a held-out motion that needs a warm-up (here the capture's own, moved 0.01 mm)
    is warmed up without gravity for a template rest shape (session 34), so a row recorded as warmed
    up under gravity, or made before rows recorded it, is stale; one recorded weightless is reused."""
    from physavatar.body import Motion
    from physavatar.capture import load_capture
    from physavatar.data.avatar import Avatar
    from physavatar.stages.animate import warmup_count
    from physavatar.stages.references import _reference_materials, _reuse_references, motion_key, reference_sequences

    monkeypatch.setenv("PHYSAVATAR_WORKERS", "1")
    out = reference_sequences(tiny_capture, tmp_path / "refs", frames=3, random_draws=1, rest_shape="template",
                              progress=False)
    cap = load_capture(tiny_capture)
    av = Avatar.load(out / "avatar")
    held = Motion.load(cap.ground_truth / "heldout" / "motion.npz")
    moved = Motion(held.name, held.fps, held.bone_names, held.rotations,
                   held.root_translation + np.array([1e-5, 0.0, 0.0]))
    assert warmup_count(av, held.slice(0, 3)) == 0 and warmup_count(av, moved.slice(0, 3)) == 2
    made = json.loads((out / "references.json").read_text())
    refs = _reference_materials(cap.ground_truth, 0, 1, made["contact_offset_m"], "template")

    rows, stale = _reuse_references(out, av, refs, 3, held)  # no warm-up: every row as it is
    assert sorted(rows) == sorted(r.row for r in refs) and not stale
    (out / "references.json").write_text(json.dumps(made | {"motion_key": motion_key(moved.slice(0, 3))}))
    rows, stale = _reuse_references(out, av, refs, 3, moved)  # recorded weightless: reused
    assert sorted(rows) == sorted(r.row for r in refs) and not stale
    for r in refs:
        meta_file = out / r.folder / "sequence.json"
        meta = json.loads(meta_file.read_text())
        assert meta["warmup_gravity"] is False
        meta_file.write_text(json.dumps({k: v for k, v in meta.items() if k != "warmup_gravity"}))
    rows, stale = _reuse_references(out, av, refs, 3, moved)
    assert not rows and sorted(stale) == sorted(r.row for r in refs)
    assert all("under gravity" in why for why in stale.values())
