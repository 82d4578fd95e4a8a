"""`physavatar run`: the whole pipeline on the tiny capture, then a rerun that skips every stage."""

import json
import time

from typer.testing import CliRunner

from physavatar.cli import app
from physavatar.parallel import default_workers


def test_run_end_to_end_and_resume(tiny_capture, tmp_path):
    out = tmp_path / "run"
    r = CliRunner().invoke(app, ["run", str(tiny_capture), str(out), "--quick"])
    assert r.exit_code == 0, r.output
    report = (out / "report.md").read_text()
    assert "Geometry (paper Table 2 layout)" in report and "Wall time per stage" in report
    rec = json.loads((out / "run.json").read_text())
    stages = ["track", "references", "physics", "appearance", "avatar", "animate", "render", "relight", "export",
              "export-glb", "evaluate"]
    assert all(rec[s]["status"] == "ok" for s in stages)
    # tracking recorded the plain-garment rule's measure and decision (flow.plain="auto")
    tex = json.loads((out / "track" / "garment_texture.json").read_text())
    assert tex["rule"] == "auto" and tex["decision"] == ("plain" if tex["garment_texture"] < tex["plain_texture"]
                                                         else "patterned")
    m = json.loads((out / "evaluate" / "metrics.json").read_text())
    # the reference rows were simulated beside the other stages (on a multi-core machine) and reused
    assert m["references"].endswith("references")
    assert rec["references"].get("background") == (default_workers(64) >= 2)
    assert m["rows"]["true material"]["garment"]["chamfer_x1e3"] < m["rows"]["LBS"]["garment"]["chamfer_x1e3"]
    assert (out / "render" / "orbit.mp4").exists() and (out / "relight" / "orbit.mp4").exists()
    # the exports hold the animated sequence, frame for frame
    import numpy as np
    from pxr import Usd, UsdGeom

    seq = np.load(out / "animate" / "sequence.npz")
    stage = Usd.Stage.Open(str(out / "export" / "avatar.usdc"))
    mesh = next(UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh))
    times = mesh.GetPointsAttr().GetTimeSamples()
    assert len(times) == len(seq["vertices"])
    assert (out / "export-glb" / "avatar.glb").stat().st_size > 1000
    # evaluate reused the animate stage's sequence instead of simulating it again
    assert m["estimated_sequence"].endswith("animate")
    assert "export/avatar.usdc" in report
    for pic in ("tracking.png", "texture_before.png", "appearance/texture.png", "physics/fit.png"):
        assert f"]({pic})" in report and (out / pic).stat().st_size > 1000
    # a rerun skips every finished stage
    t = time.time()
    r = CliRunner().invoke(app, ["run", str(tiny_capture), str(out), "--quick"])
    assert r.exit_code == 0 and time.time() - t < 30
    assert r.output.count("skipped") == len(stages)
    # an interrupted run (evaluation lost) resumes with just that stage
    (out / "evaluate" / "metrics.json").unlink()
    r = CliRunner().invoke(app, ["run", str(tiny_capture), str(out), "--quick"])
    assert r.exit_code == 0, r.output
    assert r.output.count("skipped") == len(stages) - 1 and (out / "evaluate" / "metrics.json").exists()


def test_a_motion_file_changed_in_place_animates_again(tiny_capture, tmp_path):
    """`run --motion FILE`: the animate step's hash covers the motion file's content, so a file
    changed in place (the body moved by 1 cm) is animated again (session 27: the hash held the
    file's name only, and the rerun skipped animate with the old motion's sequence)."""
    from physavatar.body import BodyModel, builtin_motion
    from physavatar.pipeline import RunConfig, plan, step_hash

    path = tmp_path / "motion.npz"
    m = builtin_motion("arm-swing", BodyModel(topology="collider").bone_names, 25.0, 0.4)
    m.save(path)
    out = tmp_path / "out"
    animate = next(s for s in plan(tiny_capture, out, RunConfig(motion=str(path))) if s.name == "animate")
    before = step_hash(animate, out, {})
    assert step_hash(animate, out, {}) == before
    m.root_translation = m.root_translation + [0.0, 0.0, 0.01]
    m.save(path)
    assert step_hash(animate, out, {}) != before


def test_a_stage_remade_by_hand_runs_the_stages_after_it_again(tmp_path, monkeypatch):
    """A stage re-made by hand in OUT (its command from the report, with other options) keeps its
    result, and the stages that read it run again on the next `run` (session 27: their hashes
    held the earlier stage's recorded hash only, so they were skipped with results made from
    the output that was replaced)."""
    from dataclasses import dataclass

    from physavatar.pipeline import Step, run_step

    (tmp_path / "fake_stages.py").write_text(
        "from pathlib import Path\n"
        "def first(*, out, config, progress=None):\n"
        "    out.mkdir(parents=True, exist_ok=True)\n"
        "    (out / 'a.txt').write_text(str(config.value))\n"
        "def second(source, *, out, config, progress=None):\n"
        "    out.mkdir(parents=True, exist_ok=True)\n"
        "    (out / 'b.txt').write_text('from ' + (Path(source) / 'a.txt').read_text())\n")
    monkeypatch.syspath_prepend(str(tmp_path))

    @dataclass(frozen=True)
    class Cfg:
        value: int = 1

    out = tmp_path / "out"
    a = Step("a", "fake_stages:first", Cfg(), {}, "a.txt")
    b = Step("b", "fake_stages:second", Cfg(), {"source": ("step", "a")}, "b.txt")
    record = {}

    def run_all():
        skipped = []
        for st in (a, b):
            r = run_step(st, out, record)
            record[st.name] = r.entry
            skipped += [st.name] if r.skipped else []
        return skipped

    assert run_all() == [] and (out / "b" / "b.txt").read_text() == "from 1"
    assert run_all() == ["a", "b"]
    (out / "a" / "a.txt").write_text("2")  # `a` re-made by hand with other options
    assert run_all() == ["a"] and (out / "b" / "b.txt").read_text() == "from 2"
    assert run_all() == ["a", "b"]


def test_references_are_drawn_in_the_fits_model(tiny_capture, tmp_path, monkeypatch):
    """`run`'s reference-sims step draws its random materials with the contact thickness and the
    rest shape the fit will record (session 28: with --rest-shape equilibrium the draws made with
    the template rest were simulated again by evaluate): both follow physics.pipeline_config."""
    import dataclasses

    from physavatar.pipeline import RunConfig, plan
    from physavatar.stages import physics

    def refs(out):
        return next(s for s in plan(tiny_capture, out, RunConfig()) if s.name == "references").config

    assert refs(tmp_path / "a").rest_shape == physics.pipeline_config(True).rest_shape
    base = physics.pipeline_config
    monkeypatch.setattr(physics, "pipeline_config",
                        lambda quick=False: dataclasses.replace(base(quick), rest_shape="equilibrium",
                                                                contact_offset=0.002))
    cfg = refs(tmp_path / "b")
    assert (cfg.rest_shape, cfg.contact_offset) == ("equilibrium", 0.002)


def test_random_draws_reach_the_references(tiny_capture, tmp_path):
    """`run --random-draws N` sets the reference-sims step's draws (the default stays the
    evaluation's RANDOM_DRAWS); an even count is refused by the option's check."""
    from physavatar.pipeline import RunConfig, _odd_positive, plan
    from physavatar.stages.evaluate import RANDOM_DRAWS

    def cfg_of(cfg, name):
        return next(s for s in plan(tiny_capture, tmp_path / "o", cfg) if s.name == name).config

    assert cfg_of(RunConfig(), "references").random_draws == cfg_of(RunConfig(), "evaluate").random_draws == RANDOM_DRAWS
    # reference-sims simulates them, evaluate reads them: both the same
    assert cfg_of(RunConfig(random_draws=1), "references").random_draws == 1
    assert cfg_of(RunConfig(random_draws=1), "evaluate").random_draws == 1
    assert _odd_positive(2) is not None and _odd_positive(3) is None


def test_track_passes_2_tracks_again_with_the_fitted_material(tiny_capture, tmp_path, monkeypatch):
    """`run --track-passes 2` (session 37, the paper's loop): a second tracking step after
    fit-physics whose physics prediction takes that material (the stage's ``material`` input, so
    its hash follows the fit), with the equilibrium rest shape and the bending reference
    "physics"; appearance and evaluate read the second pass, fit-physics the first. The default
    plan is the one-pass plan. The track stage resolves the material folder to its material.json
    (recorded in its config.json), and a missing one is one message naming the file."""
    import pytest
    from typer.testing import CliRunner

    from physavatar.errors import PhysavatarError
    from physavatar.pipeline import RunConfig, _passes, plan
    from physavatar.stages.track import pipeline_config, second_pass_config, stage

    one = {s.name: s for s in plan(tiny_capture, tmp_path / "o", RunConfig())}
    two_list = plan(tiny_capture, tmp_path / "o", RunConfig(track_passes=2))
    two = {s.name: s for s in two_list}
    assert "retrack" not in one and one["appearance"].inputs["tracked"] == ("step", "track")
    assert one["evaluate"].inputs["tracked"] == ("step", "track")
    names = [s.name for s in two_list]
    assert names.index("physics") < names.index("retrack") < names.index("appearance") < names.index("avatar")
    assert two["retrack"].inputs["material"] == ("step", "physics")
    assert two["physics"].inputs["source"] == ("step", "track")
    assert two["appearance"].inputs["tracked"] == two["evaluate"].inputs["tracked"] == ("step", "retrack")
    cfg = two["retrack"].config
    assert cfg == second_pass_config(None) and cfg != pipeline_config(None)
    assert (cfg.prediction.rest_shape, cfg.flow.bend_reference) == ("equilibrium", "physics")
    assert two["retrack"].command[:4] == ["track", str(tiny_capture), "--out", str(tmp_path / "o" / "retrack")]
    assert "--material" in two["retrack"].command
    assert _passes(1) is None and _passes(2) is None and _passes(3) is not None
    r = CliRunner().invoke(app, ["run", str(tiny_capture), str(tmp_path / "bad"), "--track-passes", "3"])
    assert r.exit_code == 2 and "track" in r.output and "Traceback" not in r.output

    seen = {}
    monkeypatch.setattr(stage, "_track", lambda cap, out, cfg, *a: seen.setdefault("cfg", cfg))
    fit = tmp_path / "physics"
    fit.mkdir()
    (fit / "material.json").write_text("{}")
    stage.run(tiny_capture, out=tmp_path / "t", config=second_pass_config(2), material=fit)
    assert seen["cfg"].prediction.material == str((fit / "material.json").resolve())
    written = json.loads((tmp_path / "t" / "config.json").read_text())
    assert written["prediction"]["material"] == str((fit / "material.json").resolve())
    with pytest.raises(PhysavatarError, match="material not found"):
        stage.run(tiny_capture, out=tmp_path / "t2", config=second_pass_config(2), material=tmp_path / "none")
