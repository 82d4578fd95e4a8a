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
