"""The projected initial texture (stages/appearance/project.py): texel surface points, visibility,
shading divided out, unseen texels inpainted along the surface.

Checks against independent truths: an affine UV map's exact inverse, a scene rendered here with
a known texture (one quad hiding part of another), and a surface whose UV charts are laid out so
that the UV neighbour of an unseen face is not its surface neighbour.
"""

from __future__ import annotations

import numpy as np
import pytest

from physavatar.camera import Camera, intrinsics, look_at
from physavatar.render import Ambient, MeshSpec, SceneSpec, load_scene, render
from physavatar.stages.appearance.project import (
    Projection,
    TexelPoints,
    bilinear,
    inpaint_faces,
    solve_texture,
)


def grid(n: int, x0: float, x1: float, y0: float, y1: float, z: float, u0: float, u1: float):
    """An n×n-quad planar grid at height z (faces counter-clockwise seen from +z) with the affine
    UV map x -> u in [u0, u1], y -> v in [0.05, 0.95]."""
    xs, ys = np.linspace(x0, x1, n + 1), np.linspace(y0, y1, n + 1)
    X, Y = np.meshgrid(xs, ys)
    V = np.stack([X.ravel(), Y.ravel(), np.full(X.size, z)], 1)
    uv = np.stack([u0 + (X.ravel() - x0) / (x1 - x0) * (u1 - u0), 0.05 + (Y.ravel() - y0) / (y1 - y0) * 0.9], 1)
    F = []
    for j in range(n):
        for i in range(n):
            a, b, c, d = j * (n + 1) + i, j * (n + 1) + i + 1, (j + 1) * (n + 1) + i + 1, (j + 1) * (n + 1) + i
            F += [[a, b, c], [a, c, d]]
    F = np.array(F)
    return V, F, uv[F]


def test_texel_points_invert_an_affine_uv_map():
    V, F, fuv = grid(4, -1.0, 1.0, -1.0, 1.0, 0.0, 0.0, 1.0)
    pts = TexelPoints.of(fuv, 32)
    P = pts.positions(V, F)
    r, c = np.divmod(pts.index, 32)
    u, v = (c + 0.5) / 32, 1 - (r + 0.5) / 32
    # the exact inverse of the grid's UV map
    assert np.allclose(P[:, 0], -1 + 2 * u, atol=1e-9)
    assert np.allclose(P[:, 1], -1 + 2 * (v - 0.05) / 0.9, atol=1e-9)
    assert np.allclose(pts.bary.sum(1), 1) and (pts.bary >= -1e-12).all()
    # bilinear lookups at pixel centres and half-way
    img = np.arange(12.0).reshape(3, 4)
    assert np.allclose(bilinear(img, np.array([[1.0, 1.0], [1.5, 0.5], [3.0, 2.0]])), [5.0, 3.5, 11.0])


def test_an_unseen_face_takes_its_surface_neighbours_colour_not_its_uv_neighbours():
    # Two strips of the same surface: the left one (x < 0) red, the right one blue, the faces at
    # the far right (x > 0.6) unseen. In the atlas the right strip's chart sits beside a third,
    # green chart of another surface; the unseen faces must become blue (their neighbours on the
    # surface), not green (their neighbours in the atlas).
    Va, Fa, uva = grid(8, -1.0, 1.0, -1.0, 1.0, 0.0, 0.05, 0.55)
    Vb, Fb, uvb = grid(2, 3.0, 4.0, -1.0, 1.0, 0.0, 0.6, 0.95)
    V = np.r_[Va, Vb]
    F = np.r_[Fa, Fb + len(Va)]
    fuv = np.r_[uva, uvb]
    pts = TexelPoints.of(fuv, 64)
    P = pts.positions(V, F)
    proj = Projection.empty(pts)
    albedo = np.where((P[:, 0] < 0)[:, None], [0.8, 0.1, 0.1], [0.1, 0.1, 0.8])
    albedo[P[:, 0] > 2.5] = [0.1, 0.8, 0.1]
    seen = ~((P[:, 0] > 0.6) & (P[:, 0] < 2.5))
    E = np.full((len(P), 3), 0.5)  # irradiance; the observed radiance is albedo · E
    proj.num[seen] += albedo[seen] * E[seen] * E[seen]
    proj.den[seen] += E[seen] ** 2
    proj.weight[seen] += 1
    tex, seen_faces = solve_texture(proj, F, prior_views=0.5)
    flat = tex.reshape(-1, 3)[pts.index]
    hidden = ~seen & (P[:, 0] > 0.75)  # texels of faces with no seen texel at all
    assert hidden.sum() > 20 and not seen_faces[pts.face[hidden]].any()
    assert np.allclose(flat[hidden], [0.1, 0.1, 0.8], atol=0.02), flat[hidden].mean(0)
    assert np.allclose(flat[seen], albedo[seen], atol=0.02)
    # inpainting alone: harmonic, so an unknown face between two known colours lies between them
    vals = np.zeros((len(F), 1))
    known = np.zeros(len(F), bool)
    cx = V[F].mean(1)[:, 0]
    known[(cx < -0.7) & (cx > -1.5)] = True
    known[(cx > 0.7) & (cx < 1.5)] = True
    vals[cx > 0.7] = 1.0
    out = inpaint_faces(F, vals, known)
    mid = ~known & (cx > -1.5) & (cx < 1.5)
    assert np.all((out[mid] > 0.0) & (out[mid] < 1.0)), out[mid].ravel()
    assert np.corrcoef(cx[mid], out[mid, 0])[0, 1] > 0.9  # rises from the 0 side to the 1 side
    assert abs(out[mid].mean() - 0.5) < 0.05  # symmetric


@pytest.mark.parametrize("size", [48])
def test_an_occluded_texel_does_not_take_the_occluders_colour(size):
    # A green quad, half hidden behind a red strip nearer the camera. Rendered here with Mitsuba
    # (image: the true textures; irradiance: a white texture, same samples), projected back.
    Vb, Fb, uvb = grid(6, -1.0, 1.0, -1.0, 1.0, 0.0, 0.02, 0.48)
    Vf, Ff, uvf = grid(2, -0.3, 0.3, -1.5, 1.5, 0.6, 0.52, 0.98)
    V = np.r_[Vb, Vf]
    F = np.r_[Fb, Ff + len(Vb)]
    fuv = np.r_[uvb, uvf]
    tex_true = np.zeros((size, size, 3), np.float32)
    tex_true[:, : size // 2] = [0.1, 0.6, 0.1]
    tex_true[:, size // 2:] = [0.7, 0.1, 0.1]
    from physavatar.geometry import split_uv_seams

    sm = split_uv_seams(V, F, fuv)
    cam = Camera("c", 64, 64, intrinsics(64, 64, 50.0), look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0)))

    def shot(tex):
        spec = SceneSpec(meshes=[MeshSpec("m", sm.vertices, sm.faces, uvs=sm.uvs, texture=tex, twosided=True)],
                         lights=[Ambient(1.0)], max_depth=2)
        return render(load_scene(spec), cam, spp=64, seed=3)

    img, E = shot(tex_true), shot(np.ones_like(tex_true))
    pts = TexelPoints.of(fuv, size)
    proj = Projection.empty(pts)
    seen = proj.add_view(cam, V, F, img.rgb, E.alpha > 0.99, E.rgb, twosided=np.ones(len(F), bool))
    P = pts.positions(V, F)
    back = pts.face < len(Fb)
    # behind the strip: the back quad's texels whose ray to the camera crosses |x| < 0.3 at z = 0.6
    xs = P[:, 0] * (3.0 - 0.6) / 3.0
    behind = back & (np.abs(xs) < 0.28) & (np.abs(P[:, 1]) < 0.9)
    clear = back & (np.abs(xs) > 0.4) & (np.abs(P[:, 0]) < 0.85) & (np.abs(P[:, 1]) < 0.85)
    assert behind.sum() > 20 and clear.sum() > 20
    assert not seen[behind].any()
    assert seen[clear].all()
    tex, _ = solve_texture(proj, F)
    flat = tex.reshape(-1, 3)[pts.index]
    assert np.allclose(flat[clear], [0.1, 0.6, 0.1], atol=0.03), flat[clear].mean(0)
    # the hidden band is inpainted from the visible green around it, never red
    assert np.allclose(flat[behind], [0.1, 0.6, 0.1], atol=0.05), flat[behind].mean(0)
    front = ~back & (np.abs(P[:, 1]) < 0.9)
    # the strip's outline pixels mix red and green: they are dropped (depth edge), not averaged
    assert not seen[front & (np.abs(P[:, 0]) > 0.29)].any()
    assert np.allclose(flat[front], [0.7, 0.1, 0.1], atol=0.03), flat[front].mean(0)


def test_small_captures_are_fitted_at_full_resolution():
    from physavatar.stages.appearance.config import AppearanceConfig, fit_scale, quick_preset

    q = quick_preset(AppearanceConfig())
    assert q.scale == 0.5
    assert fit_scale(q, 512, 512) == 0.5  # 256 px images: as asked
    assert fit_scale(q, 256, 256) == 1.0  # never below min_size (256 px)
    assert fit_scale(q, 384, 288) == pytest.approx(256 / 384)
    assert fit_scale(AppearanceConfig(scale=1.0), 2048, 2048) == 1.0
