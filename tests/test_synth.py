"""Synthetic captures: the tiny preset builds a valid capture whose images agree with its ground truth."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from typer.testing import CliRunner

from physavatar.capture import load_capture, summarize
from physavatar.cli import app
from physavatar.synth import PRESETS, synthesize


@pytest.fixture(scope="module")
def tiny(tiny_capture):
    return tiny_capture


def test_tiny_capture_is_valid(tiny):
    cap = load_capture(tiny, deep=True)
    cfg = PRESETS["tiny"]
    s = summarize(cap)
    assert s["cameras"] == cfg.n_ring + cfg.n_elevated and s["frames"] == cfg.frames
    assert s["garment_vertices"] > 0 and s["boundary_vertices"] > 0 and s["uvs"]
    assert cap.meta["garment_source"] == "simulated"
    from physavatar.sim import Material, preset

    assert Material.load(tiny / "ground_truth" / "material.json") == preset(cfg.material)
    gt = np.load(tiny / "ground_truth" / "meshes.npz")
    assert gt["vertices"].shape == (cfg.frames, len(cap.template.vertices), 3)
    # frame 0 of the ground truth is the template (motions start at rest)
    assert np.abs(gt["vertices"][0] - cap.template.vertices).max() < 1e-5
    held = np.load(tiny / "ground_truth" / "heldout" / "meshes.npz")
    assert held["vertices"].shape[0] == cfg.heldout_frames
    assert (tiny / "ground_truth" / "texture.png").exists()
    # the simulated garment moves, stays attached at its boundary, and never enters the body
    from physavatar.garment_sim import split_template

    g = cap.template.garment_mask
    V = gt["vertices"].astype(np.float64)
    assert np.linalg.norm(V[-1, g] - V[0, g], axis=1).max() > 0.01
    body_ids, body_faces, part = split_template(cap.template.vertices, cap.template.faces,
                                                cap.template.labels, cap.template.boundary)
    from physavatar.geometry import count_intersections

    for t in range(cfg.frames):
        assert count_intersections(V[t, part.vertex_ids], part.faces, V[t, body_ids], body_faces) == 0


def test_masks_agree_with_projected_ground_truth(tiny):
    """Every ground-truth vertex projects inside the mask (dilated by a pixel) of every view."""
    from scipy.ndimage import maximum_filter

    cap = load_capture(tiny)
    gt = np.load(tiny / "ground_truth" / "meshes.npz")["vertices"]
    for f in (0, cap.frames[-1]):
        for cam in cap.cameras:
            m = maximum_filter(cap.mask(cam.name, f), size=3) > 0.0
            uv, z = cam.project(gt[f])
            assert (z > 0).all()
            px = np.round(uv).astype(int)
            inside = (px[:, 0] >= 0) & (px[:, 0] < cam.width) & (px[:, 1] >= 0) & (px[:, 1] < cam.height)
            assert inside.mean() > 0.99
            hit = m[px[inside, 1], px[inside, 0]]
            assert hit.mean() > 0.995, (cam.name, f, hit.mean())
            # and the mask is not the whole image
            assert 0.02 < cap.mask(cam.name, f).mean() < 0.6


def test_images_show_texture_and_shadows(tiny):
    cap = load_capture(tiny)
    img = cap.image(cap.cameras[0].name, 0)
    a = cap.mask(cap.cameras[0].name, 0)
    m = a > 0.99
    assert img[a == 0].max() < 0.02  # black background
    assert img[m].std() > 0.05  # patterned, lit, shadowed: not flat


def test_existing_output_is_refused_and_partial_resumes(tmp_path, tiny):
    r = CliRunner().invoke(app, ["synth", str(tiny), "--preset", "tiny"])
    assert r.exit_code == 2 and "exists" in r.output
    cfg = replace(PRESETS["tiny"], frames=3, heldout_frames=2)
    out = tmp_path / "c"
    synthesize(out, cfg, progress=False)
    a = (out / "images" / "cam00" / "000002.png").read_bytes()
    # simulate an interrupted build: move back to .partial, delete one image, resume
    part = tmp_path / "c.partial"
    out.rename(part)
    (part / "images" / "cam00" / "000002.png").unlink()
    synthesize(out, cfg, progress=False)
    assert (out / "images" / "cam00" / "000002.png").read_bytes() == a  # deterministic
    assert not part.exists()


def test_contact_sheet(tiny, tmp_path):
    r = CliRunner().invoke(app, ["render-capture", str(tiny), "--out", str(tmp_path / "s.png")])
    assert r.exit_code == 0, r.output
    from PIL import Image

    im = np.asarray(Image.open(tmp_path / "s.png"))
    assert im.shape[0] > 96 and im.shape[1] > 2 * 96
