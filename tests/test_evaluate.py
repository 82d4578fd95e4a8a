"""Evaluation: the Table-2 rows are ordered as physics says on a tiny synthetic capture."""

import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pytest

from physavatar.stages.avatar import build_avatar
from physavatar.files import save_npz_atomic
from physavatar.stages.evaluate import random_material


@pytest.fixture(scope="module")
def result(tmp_path_factory, tiny_capture):
    from physavatar.stages.evaluate import evaluate

    root = tmp_path_factory.mktemp("eval")
    cap = tiny_capture
    av = build_avatar(cap, root / "avatar", material=cap / "ground_truth" / "material.json")
    shutil.copyfile(cap / "ground_truth" / "texture_linear.npy", root / "avatar" / "texture_linear.npy")
    gt = np.load(cap / "ground_truth" / "meshes.npz")
    save_npz_atomic(root / "tracked" / "tracked.npz", vertices=gt["vertices"], faces=gt["faces"])
    m = evaluate(cap, root / "avatar", root / "out", tracked=root / "tracked", n_points=4000, views_spp=4,
                 progress=False)
    return m, root


def test_rows_and_physics_ordering(result):
    m, root = result
    rows = m["rows"]
    assert set(rows) == {"LBS", "random material", "estimated material", "true material"}
    g = {k: v["garment"]["chamfer_x1e3"] for k, v in rows.items()}
    # the estimated material is the true one here: identical simulations
    assert g["estimated material"] == pytest.approx(g["true material"], rel=1e-6)
    assert g["true material"] < g["LBS"]
    assert all(0 <= v["garment"]["fscore@1cm"] <= 1 for v in rows.values())
    assert m["tracking"]["garment"]["mean_mm"] < 1e-3  # the 'tracked' meshes are the ground truth
    assert (root / "out" / "report.md").read_text().count("| true material |") == 1
    assert m["appearance"]["psnr"] > 15 and 0 < m["appearance"]["lpips"] < 0.5


def test_random_material_is_seeded_and_in_range():
    a, b, c = random_material(0), random_material(0), random_material(1)
    assert a == b and a != c
    assert 200 * 0.328e-3 * 0.99 <= a.density <= 640 * 0.328e-3 * 1.01


def test_reused_sequence_gives_the_same_row_and_bad_ones_are_refused(result, tiny_capture):
    """`evaluate --sequence` (the animate stage's output) = simulating the estimated row again."""
    from physavatar.data.avatar import Avatar
    from physavatar.body import Motion
    from physavatar.errors import PhysavatarError
    from physavatar.stages.animate import animate
    from physavatar.stages.evaluate import _reuse_sequence

    m, root = result
    av = Avatar.load(root / "avatar")
    held = Motion.load(tiny_capture / "ground_truth" / "heldout" / "motion.npz")
    seq, stats = animate(av, held, progress=False)
    seq.save(root / "seq", {"command": "animate"} | stats, ply=False)
    n = m["heldout_frames"]
    reused = _reuse_sequence(root / "seq", av, n, av.material, held)
    assert reused.vertices.shape[0] == n
    np.testing.assert_allclose(reused.vertices, seq.vertices[:n], atol=1e-6)  # float32 on disk
    with pytest.raises(PhysavatarError, match="frames"):
        _reuse_sequence(root / "seq", av, len(seq.vertices) + 1)
    # ... one animated on another motion (its key, recorded by animate, is not the held-out motion's)
    other = Motion(held.name, held.fps, held.bone_names, held.rotations.copy(), held.root_translation + [0, 0, 0.01])
    with pytest.raises(PhysavatarError, match="another motion"):
        _reuse_sequence(root / "seq", av, n, av.material, other)
    save_npz_atomic(root / "seq" / "sequence.npz", vertices=seq.vertices.astype(np.float32), faces=seq.faces,
                    labels=seq.labels, fps=np.float64(seq.fps * 2))
    with pytest.raises(PhysavatarError, match="fps"):
        _reuse_sequence(root / "seq", av, n)
    save_npz_atomic(root / "seq" / "sequence.npz", vertices=seq.vertices[:, :10].astype(np.float32),
                    faces=seq.faces, labels=seq.labels[:10], fps=np.float64(seq.fps))
    with pytest.raises(PhysavatarError, match="not an animation of this avatar"):
        _reuse_sequence(root / "seq", av, n)
    # ... and one simulated with another material than the avatar's (session 27: reused as its row)
    seq.save(root / "seq", {"command": "animate", "material": random_material(0).to_dict()}, ply=False)
    with pytest.raises(PhysavatarError, match="material"):
        _reuse_sequence(root / "seq", av, n, av.material)


def test_reference_sims_ahead_of_time_give_the_same_rows(result, tiny_capture):
    """`physavatar reference-sims` (what `run` computes beside tracking) = evaluate's own simulations."""
    import json

    from physavatar.errors import PhysavatarError
    from physavatar.stages.evaluate import evaluate, reference_sequences

    m, root = result
    reference_sequences(tiny_capture, root / "refs", rest_shape="template", progress=False)
    _check_random_median(m, root / "refs", tiny_capture)
    # an oracle (fit-physics on the true meshes) that found the true material: its row is the true row
    from physavatar.sim import Material

    true = Material.load(tiny_capture / "ground_truth" / "material.json")
    (root / "oracle").mkdir()
    (root / "oracle" / "material.json").write_text(json.dumps({"material": true.to_dict()}))
    m2 = evaluate(tiny_capture, root / "avatar", root / "out2", n_points=4000, views_spp=4,
                  references=root / "refs", oracle=root / "oracle", views=False, full=False,
                  progress=False)
    assert m2["references"] == str(root / "refs")
    assert "appearance" not in m2 and not (root / "out2" / "views").exists()  # views=False: geometry only
    assert all("full" not in r for r in m2["rows"].values()) and m2["random_draws"]["full_chamfer_x1e3"] is None
    for row in ("true material", "random material", "LBS"):
        assert m2["rows"][row]["garment"]["chamfer_x1e3"] == pytest.approx(
            m["rows"][row]["garment"]["chamfer_x1e3"], rel=1e-4, abs=1e-9), row
    assert m2["rows"]["oracle material"]["garment"]["chamfer_x1e3"] == pytest.approx(
        m["rows"]["true material"]["garment"]["chamfer_x1e3"], rel=1e-4, abs=1e-9)
    assert m2["materials"]["oracle"] == true.to_dict()
    assert "| oracle material |" in (root / "out2" / "report.md").read_text()
    # references made for another random material (another --seed) are refused, by name
    meta_file = root / "refs" / "random-0" / "sequence.json"
    meta = json.loads(meta_file.read_text())
    meta["material"]["density"] *= 1.5
    meta_file.write_text(json.dumps(meta))
    # (session 37: the message names what differs; it said "'random-0' ... uses 'random-0'" before)
    with pytest.raises(PhysavatarError, match=r"random material \(seed 0\) was simulated with another material "
                       r"than this evaluation's \(density .* against .*\)"):
        evaluate(tiny_capture, root / "avatar", root / "out3", n_points=1000, views_spp=4,
                 references=root / "refs", progress=False)


def _least_body_distance(seq_dir) -> float:
    """The least distance [m] of a sequence's garment vertices to its body surface over all frames
    (the body rows of the same sequence, the template's triangles)."""
    from physavatar.data.animated import AnimatedSequence
    from physavatar.geometry import submesh
    from physavatar.geometry.closest import MeshQuery

    seq = AnimatedSequence.load(seq_dir)
    b = seq.labels == 0
    bidx, bf = submesh(seq.faces, b)
    V = seq.vertices.astype(np.float64)
    return min(float(MeshQuery(V[t][bidx], bf).signed_distance(V[t][~b])[0].min()) for t in range(len(V)))


def test_random_draws_get_the_estimates_contact_offset(result, tiny_capture):
    """The random draws are simulated before any fit; they get the thickness the fit uses
    (`reference-sims --contact-offset`, else the template's estimate), so "below random" compares
    materials in one model: with 3 mm every draw keeps its garment at least 3 mm off the body
    (ipctk's d_min: measured on the sequences themselves), the offset is recorded, and draws made
    with another thickness than the avatar's are simulated again, not reused."""
    import json

    from physavatar.sim import Material
    from physavatar.stages.evaluate import evaluate, reference_sequences

    m, root = result
    off = 0.003
    reference_sequences(tiny_capture, root / "refs3", contact_offset=off, rest_shape="template", progress=False)
    info = json.loads((root / "refs3" / "references.json").read_text())
    assert info["contact_offset_m"] == off and info["contact_offset"]["method"] == "given"
    for s in range(5):
        meta = json.loads((root / "refs3" / f"random-{s}" / "sequence.json").read_text())
        assert meta["material"]["contact_offset"] == off
        assert _least_body_distance(root / "refs3" / f"random-{s}") >= off - 2e-5, s
    # the truth keeps the thickness its own file records (none: the tiny capture's simulator had none)
    true = json.loads((root / "refs3" / "true" / "sequence.json").read_text())["material"]
    assert true["contact_offset"] == 0.0
    # the default (the tiny capture's template does not rest on the body at one distance): none
    reference_sequences(tiny_capture, root / "refs0", rest_shape="template", progress=False)
    assert json.loads((root / "refs0" / "references.json").read_text())["contact_offset_m"] == 0.0
    assert _least_body_distance(root / "refs0" / "random-0") < off - 1e-3  # the test can tell them apart
    # an avatar fitted with 3 mm reuses the 3-mm draws
    mat = Material.load(root / "avatar" / "material.json")
    build_avatar(tiny_capture, root / "avatar3", material=dataclasses.replace(mat, contact_offset=off))
    m3 = evaluate(tiny_capture, root / "avatar3", root / "out_off", n_points=4000, references=root / "refs3",
                  views=False, full=False, progress=False)
    assert "references_simulated_again" not in m3 and m3["random_draws"]["contact_offset_mm"] == pytest.approx(3.0)
    assert all(d["contact_offset"] == off for d in m3["random_draws"]["materials"])
    # the offset-free avatar does not reuse them: the five draws are simulated again, without it,
    # and give the rows of an evaluation that simulated them itself
    m0 = evaluate(tiny_capture, root / "avatar", root / "out_off0", n_points=4000, references=root / "refs3",
                  views=False, full=False, progress=False)
    assert sorted(m0["references_simulated_again"]) == sorted(f"random material (seed {s})" for s in range(5))
    np.testing.assert_allclose(m0["random_draws"]["garment_chamfer_x1e3"], m["random_draws"]["garment_chamfer_x1e3"],
                               rtol=1e-4)
    assert m3["random_draws"]["garment_chamfer_x1e3"] != m0["random_draws"]["garment_chamfer_x1e3"]
    # the rest shape is the fit's model too (session 27, Material.rest_shape): an estimate with the
    # equilibrium rest gets draws with it, and draws made with the template rest are not reused
    from physavatar.body import Motion
    from physavatar.data.avatar import Avatar
    from physavatar.stages.evaluate import _reference_materials, _reuse_references

    gt_root = tiny_capture / "ground_truth"
    refs = _reference_materials(gt_root, 0, 5, 0.0, "equilibrium")
    assert [r.material.rest_shape for r in refs[1:]] == ["equilibrium"] * 5 and refs[0].material.rest_shape == "template"
    held = Motion.load(gt_root / "heldout" / "motion.npz")
    rows, stale = _reuse_references(root / "refs0", Avatar.load(root / "avatar"), refs, 4, held)
    assert sorted(stale) == sorted(f"random material (seed {s})" for s in range(5)) and "true material" in rows
    assert all("'template'" in why and "'equilibrium'" in why for why in stale.values())
    # a draw with the equilibrium rest whose garment was not at rest in its start frame was simulated
    # with the template (garment_sim.equilibrium_part), the model an estimate then records (its fit
    # kept the template): its sequence.json records that model, and an estimate with the template
    # reuses it; one whose rest shape was solved, or a folder that recorded "equilibrium" for a draw
    # not at rest (session 28), is simulated again
    import shutil

    from physavatar.stages.animate import simulated_material

    eq = dataclasses.replace(refs[1].material, rest_shape="equilibrium")
    assert simulated_material(eq, {"kind": "equilibrium", "at_rest": False}).rest_shape == "template"
    assert simulated_material(eq, {"kind": "equilibrium", "at_rest": True}) == eq
    assert simulated_material(refs[0].material, {"kind": "template"}) == refs[0].material
    for at_rest, recorded, n_stale in ((False, "template", 0), (True, "equilibrium", 5), (False, "equilibrium", 5)):
        refs_eq = root / f"refs_eq_{at_rest}_{recorded}"
        shutil.copytree(root / "refs0", refs_eq)
        for s in range(5):
            meta_path = refs_eq / f"random-{s}" / "sequence.json"
            meta = json.loads(meta_path.read_text())
            meta["material"]["rest_shape"] = recorded
            meta["rest_shape"] = {"kind": "equilibrium", "at_rest": at_rest}
            meta_path.write_text(json.dumps(meta))
        rows, stale = _reuse_references(refs_eq, Avatar.load(root / "avatar"), _reference_materials(gt_root, 0, 5),
                                        4, held)
        assert len(stale) == n_stale and len(rows) == 6 - n_stale, (at_rest, recorded)
    # ... and an estimate with the equilibrium rest reuses it too: the draw's own material, asked for
    # with the equilibrium rest, is simulated with the template again (session 34: evaluate simulated
    # four of the foreign skirt's draws again, each time to the same template-rest sequence)
    rows, stale = _reuse_references(root / "refs_eq_False_template", Avatar.load(root / "avatar"), refs, 4, held)
    assert not stale and len(rows) == 6
    rows, stale = _reuse_references(root / "refs_eq_True_equilibrium", Avatar.load(root / "avatar"), refs, 4, held)
    assert not stale and len(rows) == 6


def _check_random_median(m, refs, cap):
    """The random row is the median of the documented draws (seeds 0-4): each draw's garment CD
    computed here from the reference-sims sequences (a separate simulation path) with the metric
    itself, and numpy's median of them."""
    from physavatar.data.animated import AnimatedSequence
    from physavatar.geometry import submesh
    from physavatar.metrics import surface_metrics

    d = m["random_draws"]
    assert d["seeds"] == [0, 1, 2, 3, 4]
    assert d["materials"] == [random_material(s).to_dict() for s in range(5)]
    gt = np.load(cap / "ground_truth" / "heldout" / "meshes.npz")["vertices"].astype(np.float64)
    cds = []
    for s in range(5):
        seq = AnimatedSequence.load(refs / f"random-{s}")
        g = seq.labels > 0
        _, gf = submesh(seq.faces, g)
        n = m["heldout_frames"]
        cds.append(np.mean([surface_metrics(seq.vertices[t][g].astype(np.float64), gf, gt[t][g], gf, n_points=4000,
                                            seed=t)["chamfer_x1e3"] for t in range(n)]))
    np.testing.assert_allclose(d["garment_chamfer_x1e3"], cds, rtol=1e-3)
    assert len(set(np.round(cds, 6))) == 5  # five different materials, five different rows
    assert m["rows"]["random material"]["garment"]["chamfer_x1e3"] == pytest.approx(float(np.median(cds)), rel=1e-3)
    assert m["materials"]["random"] == random_material(int(np.argsort(cds)[2])).to_dict()


def test_median_random_row_and_documented_seeds():
    from physavatar.stages.evaluate import (EvaluateConfig, ReferencesConfig, median_random_row, random_draw_row,
                                            _reference_materials, random_seeds)

    assert random_seeds() == [0, 1, 2, 3, 4] and random_seeds(7, 3) == [7, 8, 9]
    assert EvaluateConfig().random_draws == ReferencesConfig().random_draws == 5
    refs = _reference_materials(Path("/nonexistent"), seed=3, draws=3)  # no material.json: no true row
    assert [(r.row, r.folder) for r in refs] == [(random_draw_row(s), f"random-{s}") for s in (3, 4, 5)]
    assert [r.material for r in refs] == [random_material(s) for s in (3, 4, 5)]
    rows = {s: {"garment": {"chamfer_x1e3": cd}, "full": {"chamfer_x1e3": 10 * cd}}
            for s, cd in ((3, 0.5), (1, 0.1), (7, 0.9), (4, 0.3), (0, 2.0))}
    row, audit = median_random_row(rows)
    assert row is rows[3] and audit["median_seed"] == 3 and audit["seeds"] == [0, 1, 3, 4, 7]
    assert audit["garment_chamfer_x1e3"] == [2.0, 0.1, 0.5, 0.3, 0.9] and audit["garment_chamfer_x1e3_median"] == 0.5
    with pytest.raises(ValueError, match="odd"):
        median_random_row({0: rows[3], 1: rows[1]})


def test_heldout_cameras_of_a_capture_without_ground_truth(tmp_path, tiny_capture):
    """`evaluate --holdout CAM` on a capture with no ground_truth/: the tracked meshes rendered from
    the capture's own camera. With the true meshes, texture and light it reproduces the capture's
    images; meshes moved by 3 cm score clearly worse; bad camera names and missing inputs are refused."""
    import json

    from physavatar.errors import PhysavatarError
    from physavatar.stages.evaluate import EvaluateConfig, run

    cap = tmp_path / "cap"
    shutil.copytree(tiny_capture, cap, ignore=shutil.ignore_patterns("ground_truth"))
    gt_dir = tiny_capture / "ground_truth"
    build_avatar(cap, tmp_path / "avatar", material=gt_dir / "material.json")
    shutil.copyfile(gt_dir / "texture_linear.npy", tmp_path / "avatar" / "texture_linear.npy")
    shutil.copyfile(gt_dir / "lighting.json", tmp_path / "avatar" / "light.json")
    gt = np.load(gt_dir / "meshes.npz")
    cam = json.loads((cap / "cameras.json").read_text())[1]["name"]
    scores = {}
    for name, shift in (("true", 0.0), ("moved", 0.03)):
        save_npz_atomic(tmp_path / name / "tracked.npz", vertices=gt["vertices"] + shift, faces=gt["faces"])
        m = run(cap, out=tmp_path / f"eval_{name}", config=EvaluateConfig(holdout=(cam,)), avatar=tmp_path / "avatar",
                tracked=tmp_path / name)
        assert "rows" in m and not m["rows"] and "tracking" not in m  # nothing else without ground truth
        scores[name] = m["heldout_cameras"]
    assert scores["true"]["cameras"] == [cam] and len(scores["true"]["views"]) == 3
    assert scores["true"]["psnr"] > 24, scores["true"]  # 26.6 dB: the capture used more samples
    assert scores["moved"]["psnr"] < scores["true"]["psnr"] - 5, (scores["moved"]["psnr"], scores["true"]["psnr"])
    assert "Held-out cameras of the capture" in (tmp_path / "eval_true" / "report.md").read_text()
    with pytest.raises(PhysavatarError, match="not in the capture"):
        run(cap, out=tmp_path / "e2", config=EvaluateConfig(holdout=("nope",)), avatar=tmp_path / "avatar",
            tracked=tmp_path / "true")
    with pytest.raises(PhysavatarError, match="nothing to evaluate"):
        run(cap, out=tmp_path / "e3", config=EvaluateConfig(), avatar=tmp_path / "avatar")


def test_references_of_another_held_out_motion_are_simulated_again(tmp_path, tiny_capture):
    """evaluate reuses a references folder's rows only when they were simulated on the held-out
    motion it evaluates (session 27: it checked the template, body and materials but not the
    motion, so after ground_truth/heldout/motion.npz changed it scored the old motion's rows).
    The avatar here has the true material: its own simulation and the true row must agree."""
    from physavatar.body import Motion
    from physavatar.stages.evaluate import evaluate, reference_sequences

    cap = tmp_path / "cap"
    shutil.copytree(tiny_capture, cap)
    reference_sequences(cap, tmp_path / "refs", frames=3, random_draws=1, rest_shape="template", progress=False)
    path = cap / "ground_truth" / "heldout" / "motion.npz"
    m = Motion.load(path)
    m.root_translation = m.root_translation + [0.0, 0.01, 0.0]  # the body 1 cm to the side
    m.save(path)
    kw = dict(frames=3, random_draws=1, n_points=1000, views=False, full=False, progress=False)
    got = evaluate(cap, tmp_path / "refs" / "avatar", tmp_path / "out", references=tmp_path / "refs", **kw)
    rows = got["rows"]
    assert rows["true material"]["garment"] == rows["estimated material"]["garment"]
    assert "true material" in got["references_simulated_again"]


def test_the_animate_stage_records_the_motion_evaluate_compares(result, tiny_capture, tmp_path):
    """The key the `animate` stage records (its motion loaded from a file, sliced by --max-frames)
    is the key `evaluate --sequence` computes from the held-out motion: `run`'s own reuse passes,
    and a file with one pose changed does not."""
    from physavatar.body import Motion
    from physavatar.data.avatar import Avatar
    from physavatar.errors import PhysavatarError
    from physavatar.stages.animate import AnimateConfig, run as animate_stage
    from physavatar.stages.evaluate import _reuse_sequence

    _, root = result
    av = Avatar.load(root / "avatar")
    npz = tiny_capture / "ground_truth" / "heldout" / "motion.npz"
    held = Motion.load(npz)
    animate_stage(root / "avatar", out=tmp_path / "seq", config=AnimateConfig(motion=str(npz), max_frames=3),
                  progress=False)
    assert len(_reuse_sequence(tmp_path / "seq", av, 3, av.material, held).vertices) == 3
    changed = held.rotations.copy()
    changed[2, 1] += 0.05
    with pytest.raises(PhysavatarError, match="another motion"):
        _reuse_sequence(tmp_path / "seq", av, 3, av.material, Motion(held.name, held.fps, held.bone_names, changed,
                                                                     held.root_translation))
