"""Appearance stage (PhysAvatar Sec. 3.3): UV atlas, initial texture, inverse rendering, relighting.

Every check compares against something independent: the synthetic capture's true texture and
lights, point-in-triangle tests done here in numpy, or the loss at a perturbed light.
"""

from __future__ import annotations

import numpy as np
import pytest

from physavatar.capture import load_capture
from physavatar.render import Ambient, AreaLight
from physavatar.render.avatar import AvatarMeshes
from physavatar.stages.appearance import AppearanceConfig
from physavatar.stages.appearance.data import load_appearance_data
from physavatar.stages.appearance.evaluation import baked_shading, covered_texels, texture_psnr
from physavatar.stages.appearance.fit import fit_appearance
from physavatar.stages.appearance.scene import InverseRenderer, initial_lights
from physavatar.stages.appearance.texture import splat_face_colors, uv_atlas
from physavatar.stages.relight import relight
from physavatar.synth import PRESETS, synthesize


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    out = tmp_path_factory.mktemp("appearance") / "tiny"
    synthesize(out, PRESETS["tiny"], progress=False)
    return load_capture(out)


def _signed_areas(uv: np.ndarray) -> np.ndarray:
    a, b, c = uv[:, 0], uv[:, 1], uv[:, 2]
    return 0.5 * ((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1]))


def test_xatlas_uvs_are_a_valid_atlas(tiny):
    t = tiny.template
    uv = uv_atlas(t.vertices, t.faces, texture_size=256)
    assert uv.shape == (len(t.faces), 3, 2)
    assert uv.min() >= 0.0 and uv.max() <= 1.0
    area = _signed_areas(uv)
    # Counter-clockwise faces stay counter-clockwise in UV: no chart is mirrored or folded.
    assert (area > 0).all(), f"{(area <= 0).sum()} flipped or degenerate UV triangles"
    assert area.sum() <= 1.0
    # Non-overlapping: every texel centre lies in at most one UV triangle (exact barycentric test
    # here, independent of the PIL rasterizer the stage uses).
    n = 128
    c = (np.arange(n) + 0.5) / n
    P = np.stack(np.meshgrid(c, 1.0 - c), -1).reshape(-1, 2)
    hits = np.zeros(len(P), np.int64)
    for tri in uv:
        lo, hi = tri.min(0), tri.max(0)
        idx = np.flatnonzero((P[:, 0] >= lo[0]) & (P[:, 0] <= hi[0]) & (P[:, 1] >= lo[1]) & (P[:, 1] <= hi[1]))
        if len(idx):
            hits[idx[_inside(P[idx], tri, eps=-1e-9)]] += 1
    assert hits.max() <= 1
    assert (hits > 0).mean() > 0.3  # and the charts actually use the atlas


def _inside(p: np.ndarray, tri: np.ndarray, eps: float = 0.0) -> np.ndarray:
    """Strictly-inside test (by ``-eps`` margin in barycentric coordinates)."""
    a, b, c = tri
    m = np.array([b - a, c - a]).T
    lam = np.linalg.solve(m, (p - a).T).T
    l0 = 1 - lam.sum(1)
    return (lam[:, 0] > -eps) & (lam[:, 1] > -eps) & (l0 > -eps)


def test_splatting_puts_each_face_colour_in_its_texels(tiny):
    # on a non-overlapping atlas (the capture's own body UVs may share texels between mirrored
    # halves, where "this face's texels" is ambiguous)
    t = tiny.template
    n = 128
    face_uvs = uv_atlas(t.vertices, t.faces, texture_size=n)
    rng = np.random.default_rng(1)
    colors = rng.random((len(t.faces), 3))
    tex = splat_face_colors(face_uvs, colors, n)
    c = (np.arange(n) + 0.5) / n
    P = np.stack(np.meshgrid(c, 1.0 - c), -1)  # texel centres, row 0 = v 1
    checked = 0
    for f in rng.choice(len(t.faces), 200, replace=False):
        tri = face_uvs[f]
        lo, hi = np.floor(tri.min(0) * n).astype(int), np.ceil(tri.max(0) * n).astype(int)
        rows = slice(n - hi[1], n - lo[1])
        cols = slice(lo[0], hi[0])
        pts = P[rows, cols].reshape(-1, 2)
        inside = _inside(pts, tri, eps=-0.02)  # well inside: texels shared with neighbours excluded
        got = tex[rows, cols].reshape(-1, 3)[inside]
        np.testing.assert_allclose(got, np.broadcast_to(colors[f], got.shape).astype(np.float32), atol=1e-6)
        checked += inside.sum()
    assert checked > 100
    # empty texels are filled by dilation: every texel holds some face's colour
    palette = {tuple(c) for c in colors.astype(np.float32)}
    assert all(tuple(c) in palette for c in np.unique(tex.reshape(-1, 3), axis=0))


def _tiny_renderer(tiny, lights, texture_size=64):
    data = load_appearance_data(tiny, None, "gt", texture_size)
    t = data.template
    gt_tex = np.load(tiny.root / "ground_truth" / "texture_linear.npy")
    meshes = AvatarMeshes.build(t.vertices, t.faces, t.face_uvs, t.labels)
    return data, gt_tex, InverseRenderer(meshes, data.vertices[0], gt_tex, lights, max_depth=3)


def test_ambient_gradient_has_the_right_sign(tiny):
    # Target: the true texture under the true studio lights; the loss must pull a too-bright
    # ambient down and a too-dark one up, and agree with a central difference of the loss.
    cfg = AppearanceConfig(light="studio")
    lights = initial_lights(cfg, tiny)
    assert isinstance(lights[0], Ambient) and isinstance(lights[1], AreaLight)
    data, gt_tex, r = _tiny_renderer(tiny, lights)
    cam = data.cameras[0]
    true_amb = np.full(3, 0.3)
    key = np.full(3, 3.0)
    r.set_vertices(data.vertices[0])
    target = r.render(cam, gt_tex, true_amb, key, spp=64, seed=5).rgb
    mask = r.render(cam, gt_tex, true_amb, key, spp=4).alpha > 0.99
    for amb, sign in ((0.6, 1.0), (0.1, -1.0)):
        a = np.full(3, amb)
        _, _, gA, gK = r.loss_and_grads(cam, target, mask, gt_tex, a, key, spp=32, seed=1)
        assert (np.sign(gA) == sign).all(), (amb, gA)
        h = 0.02
        lp = r.loss_and_grads(cam, target, mask, gt_tex, a + h, key, spp=32, seed=1)[0]
        lm = r.loss_and_grads(cam, target, mask, gt_tex, a - h, key, spp=32, seed=1)[0]
        fd = (lp - lm) / (2 * h)
        assert gA.sum() == pytest.approx(fd, rel=0.2)


@pytest.mark.parametrize("light", ["studio"])
def test_short_fit_reduces_loss_and_moves_texture_to_truth(tiny, tmp_path, light):
    # the paper's schedule from the paper's T_0 (per-face colours): the Adam fit itself is tested
    cfg = AppearanceConfig(light=light, iterations=40, texture_size=64, spp=4, final_spp=8, lr=0.03,
                           lr_decay_every=20, checkpoint_every=20, init_frame_stride=2, init="faces")
    res = fit_appearance(tiny, tmp_path / "fit", cfg, meshes="gt", progress=False)
    loss = np.array([r["loss"] for r in res.log])
    assert loss[-10:].mean() < 0.8 * loss[:10].mean()
    gt = np.load(tiny.root / "ground_truth" / "texture_linear.npy")
    cov = covered_texels(res.face_uvs, gt.shape[0], res.face_pixels > 0)
    p0 = texture_psnr(res.texture_init, gt, cov, align_scale=True)
    p1 = texture_psnr(res.texture, gt, cov, align_scale=True)
    assert p1 > p0 + 0.5, (p0, p1)
    # the shading baked into T_0 (per-face texture/albedo ratios spread by light and shadow)
    # is largely removed when the renderer models the studio's key light
    b0 = baked_shading(res.texture_init, gt, res.face_uvs, res.face_pixels > 0)
    b1 = baked_shading(res.texture, gt, res.face_uvs, res.face_pixels > 0)
    assert b1 < 0.75 * b0, (b0, b1)
    for name in ("texture.png", "texture_linear.npy", "light.json", "fit_log.csv", "loss.png", "config.json",
                 "preview.png", "atlas.npz"):
        assert (tmp_path / "fit" / name).is_file(), name
    # resume: the same config with more iterations continues from the checkpoint
    more = fit_appearance(tiny, tmp_path / "fit", AppearanceConfig(**{**cfg.to_dict(), "iterations": 42}),
                          meshes="gt", progress=False)
    assert len(more.log) == 42 and [r["iteration"] for r in more.log[:40]] == list(range(40))
    # ... but a checkpoint fitted to other meshes (another tracking run in the same folder) is
    # fitted again, not resumed: its first 40 steps see the moved meshes, not the old log
    from dataclasses import replace

    from physavatar.stages.appearance.data import load_appearance_data

    data = load_appearance_data(tiny, None, "gt", cfg.texture_size)
    moved = replace(data, vertices=np.asarray(data.vertices) + np.array([0.0, 0.0, 0.01], np.float32))
    other = fit_appearance(tiny, tmp_path / "fit", AppearanceConfig(**{**cfg.to_dict(), "iterations": 42}),
                           data=moved, progress=False)
    assert len(other.log) == 42
    assert [r["loss"] for r in other.log[:40]] != [r["loss"] for r in more.log[:40]]


def test_a_rerun_reuses_no_initial_texture_or_checkpoint_of_other_images_or_cameras(tiny, tmp_path):
    """T_0 (atlas.npz) and the checkpoint are read back only when made from the same data (session
    27: T_0 was keyed on the settings, the frame ids and the camera names, and the checkpoint on
    the meshes and T_0, so after an image was replaced or a camera moved a rerun read back both
    and printed the old fit): each rerun equals a fresh fit of the changed data."""
    import json
    import shutil
    from dataclasses import replace

    cap = tmp_path / "cap"
    shutil.copytree(tiny.root, cap)
    cfg = AppearanceConfig(light="studio", iterations=2, texture_size=64, spp=2, final_spp=2, checkpoint_every=1,
                           init_frame_stride=2, init="faces")
    first = fit_appearance(cap, tmp_path / "fit", cfg, meshes="gt", progress=False)
    shutil.copyfile(cap / "images" / "cam00" / "000002.png", cap / "images" / "cam00" / "000000.png")
    again = fit_appearance(cap, tmp_path / "fit", cfg, meshes="gt", progress=False)
    fresh = fit_appearance(cap, tmp_path / "fresh", cfg, meshes="gt", progress=False)
    np.testing.assert_array_equal(again.texture_init, fresh.texture_init)
    assert np.abs(again.texture_init - first.texture_init).max() > 0.01
    assert [r["loss"] for r in again.log] != [r["loss"] for r in first.log]  # fitted, not read back
    cams = json.loads((cap / "cameras.json").read_text())
    cams[0]["w2c"][0][3] += 0.05
    (cap / "cameras.json").write_text(json.dumps(cams))
    moved = fit_appearance(cap, tmp_path / "fit", replace(cfg, iterations=1), meshes="gt", progress=False)
    np.testing.assert_array_equal(moved.texture_init, fit_appearance(cap, tmp_path / "fresh2", replace(cfg, iterations=1), meshes="gt",
                                                                     progress=False).texture_init)
    assert [r["loss"] for r in moved.log] != [r["loss"] for r in again.log[:1]]


def test_projected_texture_is_closer_to_the_true_albedo_than_face_colours(tiny, tmp_path):
    # T_0 alone (no Adam steps) on the true meshes under the studio's known lights: the projected
    # texture (texels looked up where they are, shading divided out) against the paper's per-face
    # colours, both scored on the true albedo texture over the texels some view saw.
    common = dict(light="studio", iterations=0, texture_size=64, final_spp=4, init_frame_stride=2, project_views=12,
                  project_spp=8)
    faces = fit_appearance(tiny, tmp_path / "faces", AppearanceConfig(init="faces", **common), meshes="gt",
                           progress=False)
    proj = fit_appearance(tiny, tmp_path / "proj", AppearanceConfig(init="project", **common), meshes="gt",
                          progress=False)
    gt = np.load(tiny.root / "ground_truth" / "texture_linear.npy")
    cov = covered_texels(proj.face_uvs, gt.shape[0], (proj.face_pixels > 0) & (faces.face_pixels > 0))
    p_faces = texture_psnr(faces.texture, gt, cov)
    p_proj = texture_psnr(proj.texture, gt, cov)
    assert p_proj > p_faces + 2.0, (p_faces, p_proj)
    seen = (proj.face_pixels > 0) & (faces.face_pixels > 0)
    assert baked_shading(proj.texture, gt, proj.face_uvs, seen) < baked_shading(faces.texture, gt, faces.face_uvs, seen)


def test_relight_matches_the_capture_under_its_own_lights(tiny):
    # The true texture relit with the capture's own lights reproduces the capture's image.
    from physavatar.render import srgb_to_linear
    from physavatar.render.lights import load_lights

    lights = load_lights(tiny.root / "ground_truth" / "lighting.json")
    gt_tex = np.load(tiny.root / "ground_truth" / "texture_linear.npy")
    V = np.load(tiny.root / "ground_truth" / "meshes.npz")["vertices"][2]
    t = tiny.template
    cam = tiny.cameras[1]
    res = relight(V, t.faces, t.face_uvs, gt_tex, cam, lights, labels=t.labels, spp=64)
    img = srgb_to_linear(tiny.image(cam.name, 2))
    m = tiny.mask(cam.name, 2) > 0.99
    err = np.abs(res.rgb[m] - img[m]).mean()
    assert err < 0.02, err
    # named lights render the same silhouette with different shading
    sky = relight(V, t.faces, t.face_uvs, gt_tex, cam, "sky", labels=t.labels, spp=16)
    assert sky.alpha[m].mean() > 0.95
    assert np.abs(sky.rgb[m] - img[m]).mean() > 0.02


def test_cli_fit_appearance_and_relight(tiny, tmp_path):
    import json

    from PIL import Image
    from typer.testing import CliRunner

    from physavatar.cli import app

    runner = CliRunner()
    out = tmp_path / "app"
    r = runner.invoke(app, ["fit-appearance", str(tiny.root), "--meshes", "gt", "--out", str(out), "--iterations", "3",
                            "--texture-size", "32", "--final-spp", "4", "--light", "ambient"])
    assert r.exit_code == 0, r.output
    light = json.loads((out / "light.json").read_text())
    assert light["lights"][0]["type"] == "Ambient" and light["model"] == "ambient"
    assert np.load(out / "texture_linear.npy").shape == (32, 32, 3)
    png = tmp_path / "relit.png"
    r = runner.invoke(app, ["relight", str(tiny.root), "--texture", str(out), "--light", "sun", "--frame", "1",
                            "--out", str(png), "--spp", "4"])
    assert r.exit_code == 0, r.output
    assert Image.open(png).size[0] > tiny.cameras[0].width
    # bad input: one line and exit code 2
    r = runner.invoke(app, ["fit-appearance", str(tiny.root), "--out", str(tmp_path / "x")])
    assert r.exit_code == 2 and "--tracked" in r.output
    r = runner.invoke(app, ["relight", str(tiny.root), "--texture", str(out), "--light", "nope", "--out", str(png)])
    assert r.exit_code == 2


def test_run_settings_keep_the_projected_texture_and_the_old_rate_adds_grain(tiny, tmp_path):
    # Each Adam step renders one random view at a few spp, so most of a texel's gradient is noise,
    # and Adam (normalised per texel) moves every texel about one rate per step whatever its
    # signal: at run's old rate (0.02) that random walk left a texel-scale grain everywhere
    # (docs/appearance.md: foreign print top 31.0 -> 28.0 dB on held-out cameras). On the true
    # meshes against the true albedo (gain-aligned PSNR over the texels some view saw): with run's
    # settings the steps keep T_0's accuracy; at the old rate, all else equal, they lose it.
    from dataclasses import replace

    from physavatar.stages.appearance import pipeline_config

    run = pipeline_config(quick=True)
    assert run.light == "env" and run.lr <= 0.005
    small = {"texture_size": 64, "final_spp": 2, "project_views": 8, "env_views": 4, "iterations": 60}  # smaller budget
    gt = np.load(tiny.root / "ground_truth" / "texture_linear.npy")
    scores = {}
    for lr in (run.lr, 0.02):
        res = fit_appearance(tiny, tmp_path / f"lr{lr}", replace(run, lr=lr, **small), meshes="gt", progress=False)
        cov = covered_texels(res.face_uvs, gt.shape[0], res.face_pixels > 0)
        scores[lr] = (texture_psnr(res.texture_init, gt, cov, align_scale=True),
                      texture_psnr(res.texture, gt, cov, align_scale=True))
    (new0, new1), (old0, old1) = scores[run.lr], scores[0.02]
    assert new0 == pytest.approx(old0, abs=1e-4)  # the same T_0: the rate acts on the steps only
    assert new1 > new0 - 0.1, scores
    assert old1 < old0 - 0.25, scores
