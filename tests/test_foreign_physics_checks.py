"""Issue 22 part 4's checks in benchmarks/foreign_capture.py: held-out chamfer distances are
compared above the truth's own CD (the sampling floor), and the fit residual is split into the
model gap (the fit on the true meshes) and the tracking share."""

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import foreign_capture as FC


def fig(est, lbs, rnd, floor):
    cd = {"estimated material": est, "LBS": lbs, "random material": rnd}
    return {"heldout_garment_cd_x1e3": cd, "heldout_garment_cd_floor_x1e3": floor,
            "heldout_garment_cd_above_floor_x1e3": {k: v - floor for k, v in cd.items()}}


def test_a_perfect_prediction_passes_where_the_raw_ratio_cannot():
    """On a tight top every row is near the floor (truth 0.0089, LBS 0.0098): the truth itself is
    only 9 % below LBS in raw CD, so the raw 25 % target is out of reach of any prediction; above
    the floor it is 100 % below LBS and passes, and a row at LBS's CD is 0 % below it."""
    c = FC.physics_checks("top", fig(est=0.0089, lbs=0.0098, rnd=0.0163, floor=0.0089))
    lbs = c["top:heldout_cd_below_lbs"]
    assert lbs["raw_value"] == pytest.approx(1 - 0.0089 / 0.0098) and lbs["raw_value"] < 0.25
    assert lbs["value"] == pytest.approx(1.0) and lbs["pass"]
    c = FC.physics_checks("top", fig(est=0.0098, lbs=0.0098, rnd=0.0163, floor=0.0089))
    assert c["top:heldout_cd_below_lbs"]["value"] == pytest.approx(0.0) and not c["top:heldout_cd_below_lbs"]["pass"]
    # random: (0.0098 - 0.0089) / (0.0163 - 0.0089) = 0.1216 -> 87.8 % below
    assert c["top:heldout_cd_below_random"]["value"] == pytest.approx(1 - 0.0009 / 0.0074)


def test_without_a_floor_the_checks_are_the_raw_ratios():
    f = fig(est=0.5, lbs=1.0, rnd=0.6, floor=0.0)
    del f["heldout_garment_cd_above_floor_x1e3"], f["heldout_garment_cd_floor_x1e3"]
    c = FC.physics_checks("skirt", f)
    assert c["skirt:heldout_cd_below_lbs"]["value"] == pytest.approx(0.5) and c["skirt:heldout_cd_below_lbs"]["pass"]
    assert c["skirt:heldout_cd_below_random"]["value"] == pytest.approx(1 / 6)


def test_residual_split_in_quadrature(tmp_path):
    """tracked 5 mm, true 3 mm: the tracking share is 4 mm (5² = 3² + 4²) and the model gap 36 %
    of the squared residual; a tracked fit below the true one gives a negative share."""
    s = FC.residual_split(tmp_path, tmp_path, {"rms_mm": 5.0}, {"rms_mm": 3.0})
    assert s["tracking_share_mm"] == pytest.approx(4.0)
    assert s["model_gap_fraction_of_squared_residual"] == pytest.approx(0.36)
    s = FC.residual_split(tmp_path, tmp_path, {"rms_mm": 3.0}, {"rms_mm": 5.0})
    assert s["tracking_share_mm"] == pytest.approx(-4.0)
    assert FC.residual_split(tmp_path, tmp_path, None, {"rms_mm": 5.0}) is None


def test_floor_of_a_surface_is_its_sampling_floor():
    """The CD of a surface against itself, sampled as `evaluate` samples (10,000 points, seeds t,
    t + 1), is the Poisson floor A / (π n) per side (docs/evaluation.md), not 0."""
    from physavatar.stages.evaluate import _surface_rows

    n = 21
    xs = np.linspace(0, 0.5, n)
    X, Y = np.meshgrid(xs, xs)
    V = np.stack([X.ravel(), Y.ravel(), np.zeros(n * n)], 1)
    F = np.array([[i * n + j, i * n + j + 1, (i + 1) * n + j + 1] for i in range(n - 1) for j in range(n - 1)]
                 + [[i * n + j, (i + 1) * n + j + 1, (i + 1) * n + j] for i in range(n - 1) for j in range(n - 1)])
    seq = np.repeat(V[None], 2, 0)
    r = _surface_rows(seq, seq, F, 10000, 0)
    expect = 0.25 / (np.pi * 10000) * 1e3  # area 0.25 m²; edges of the square add a little
    assert expect < r["chamfer_x1e3"] < 1.3 * expect


def test_with_dense_rows_the_checks_are_taken_above_the_dense_floor():
    """The dense CD (100,000 points: the floor a tenth) is the check, above its own floor; the
    raw ratios and the 10,000-point one above the floor are kept beside it. Plain-top numbers of
    session 17's foreign_physics run at 100,000 points: truth 0.00089, LBS 0.00114, so even a
    perfect prediction is only 22 % below LBS in raw CD (not yet the 25 %), 100 % above the floor."""
    f = fig(est=0.0089, lbs=0.0092, rnd=0.0138, floor=0.0089)
    f["heldout_garment_cd_dense"] = {"points": 100000, "floor_x1e3": 0.00089,
                                     "heldout_garment_cd_x1e3": {"estimated material": 0.00089, "LBS": 0.00114,
                                                                 "random material": 0.00560}}
    c = FC.physics_checks("top", f)
    lbs = c["top:heldout_cd_below_lbs"]
    assert lbs["value"] == pytest.approx(1.0) and lbs["pass"] and "100000 points" in lbs["unit"]
    assert lbs["raw_value_dense"] == pytest.approx(1 - 0.00089 / 0.00114) and lbs["raw_value_dense"] < 0.25
    assert lbs["raw_value"] == pytest.approx(1 - 0.0089 / 0.0092) and lbs["value_10k"] == pytest.approx(1.0)
    # the oracle's dense CD: (0.00148 - 0.00089) / (0.00114 - 0.00089) = 2.36 -> -1.36, fails
    f["heldout_garment_cd_dense"]["heldout_garment_cd_x1e3"]["estimated material"] = 0.00148
    c = FC.physics_checks("top", f)
    assert c["top:heldout_cd_below_lbs"]["value"] == pytest.approx(1 - 0.00059 / 0.00025)
    assert not c["top:heldout_cd_below_lbs"]["pass"]
    assert c["top:heldout_cd_below_random"]["value"] == pytest.approx(1 - 0.00059 / (0.00560 - 0.00089))


def test_every_figure_is_under_checks_the_untargeted_ones_reported():
    """Issue 22 part 6: every figure under `checks`. The targets on both view sets (PSNR >= 28 dB,
    LPIPS <= 0.03; a capture camera at 27.9 dB fails, one at 28.1 passes), and the figures without
    a target (p95 and body tracking, the fit residual on tracked and true meshes and its tracking
    share, texture error) with pass None, left out of the pass count."""
    f = fig(est=0.05, lbs=0.5, rnd=0.06, floor=0.03)
    f |= {"size_px": 256,
          "tracking": {"garment_mean_mm": 5.0, "garment_last_over_first_quarter": 2.0, "garment_p95_mm": 15.0,
                       "body_mean_mm": 0.46},
          "heldout_motion_views": {"psnr": 28.1, "ssim": 0.97, "lpips": 0.02},
          "capture_heldout_cameras": {"psnr": 27.9, "ssim": 0.97, "lpips": 0.031},
          "material_fit": {"tracked": {"rms_mm": 5.0}, "true_meshes_oracle": {"rms_mm": 4.0}},
          "fit_residual_split": FC.residual_split(Path("/nonexistent"), Path("/nonexistent"), {"rms_mm": 5.0},
                                                  {"rms_mm": 4.0}),
          "texture_error": {"garment": {"psnr_srgb_after_gain": 16.0}, "body": {"psnr_srgb_after_gain": 21.0}}}
    c = FC.checks_for("s", f)
    assert c["s:heldout_views_psnr"]["pass"] and c["s:heldout_views_lpips"]["pass"]
    assert not c["s:capture_heldout_cameras_psnr"]["pass"] and not c["s:capture_heldout_cameras_lpips"]["pass"]
    assert c["s:fit_residual_tracked_rms"]["value"] == 5.0 and c["s:fit_residual_true_meshes_rms"]["value"] == 4.0
    assert c["s:fit_residual_tracking_share"]["value"] == pytest.approx(3.0)  # sqrt(25 - 16)
    assert c["s:tracking_body_mean"]["pass"] is None and c["s:texture_psnr_body"]["value"] == 21.0
    judged = [k for k, v in c.items() if v["pass"] is not None]
    assert len(judged) == 8 and FC.pass_count(c).startswith(f"{sum(c[k]['pass'] for k in judged)}/8 pass")


def test_reuse_tracking_records_todays_hash_so_run_skips_only_the_tracking(tiny_capture, tmp_path):
    """--reuse-tracking: a finished track step recorded under an old hash (a setting added since)
    is marked done with today's hash, judged by the pipeline's own is_done; the appearance fitted
    on it follows only when it was up to date with that tracking; a stale physics step is left to
    run again, and an unfinished tracking is not touched."""
    from physavatar.files import read_json, write_json_atomic
    from physavatar.pipeline import RunConfig, is_done, plan, step_hash

    rc = RunConfig(quick=True)
    out = tmp_path / "run"
    (out / "track").mkdir(parents=True)
    (out / "track" / "tracked.npz").write_bytes(b"x")
    (out / "appearance").mkdir()
    (out / "appearance" / "texture.png").write_bytes(b"x")
    steps = {st.name: st for st in plan(tiny_capture, out, rc)}
    rec = {"track": {"hash": "old-track", "status": "ok"}}
    rec["appearance"] = {"hash": step_hash(steps["appearance"], out, rec), "status": "ok"}  # made on that tracking
    rec["physics"] = {"hash": "old-physics", "status": "ok"}
    write_json_atomic(out / "run.json", rec)
    assert not is_done(steps["track"], out, rec["track"], step_hash(steps["track"], out, rec))

    assert FC.reuse_tracking(tiny_capture, out, rc) == ["track", "appearance"]
    new = read_json(out / "run.json")
    for name in ("track", "appearance"):
        assert is_done(steps[name], out, new[name], step_hash(steps[name], out, new)), name
    assert new["track"]["hash_before_reuse"] == "old-track"
    assert new["physics"] == rec["physics"]
    assert FC.reuse_tracking(tiny_capture, out, rc) == []  # already today's: nothing to do

    # an appearance made on other tracking than the recorded one stays stale
    rec["appearance"]["hash"] = "other"
    write_json_atomic(out / "run.json", rec)
    assert FC.reuse_tracking(tiny_capture, out, rc) == ["track"]
    # an unfinished tracking is not reused
    rec["track"]["status"] = "failed"
    write_json_atomic(out / "run.json", rec)
    assert FC.reuse_tracking(tiny_capture, out, rc) == []
    assert read_json(out / "run.json") == rec
