"""Tests of physavatar.render against independent references: ray casting with
``Camera.pixel_rays``, closed-form radiometry of diffuse planes, and finite quantities of the
adjoint. Images are small and spp low; the whole file runs in seconds after Mitsuba's JIT."""

from __future__ import annotations

import os

import numpy as np
import pytest

from physavatar.camera import Camera, intrinsics, look_at
from physavatar.geometry import split_uv_seams
from physavatar.render import (
    Ambient,
    AreaLight,
    EnvMap,
    MeshSpec,
    PointLight,
    SceneSpec,
    SunLight,
    contact_sheet,
    differentiable_scene,
    envmap_directions,
    linear_to_srgb,
    linear_to_srgb8,
    load_scene,
    make_sensor,
    mitsuba,
    read_png,
    render,
    render_views,
    sky_envmap,
    soft_studio,
    srgb_to_linear,
    write_png,
)

ENVMAP_DIR = "/work/shared/data/envmaps"


# -- helpers ------------------------------------------------------------------------------------
def icosphere(subdivisions: int, radius: float, center) -> tuple[np.ndarray, np.ndarray]:
    """Triangulated sphere, faces counter-clockwise seen from outside."""
    t = (1.0 + 5**0.5) / 2.0
    v = [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
         [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]]  # fmt: skip
    f = [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
         [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
         [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]]  # fmt: skip
    verts = [np.array(p, float) / np.linalg.norm(p) for p in v]
    faces = f
    for _ in range(subdivisions):
        cache: dict = {}

        def mid(a, b):
            key = (min(a, b), max(a, b))
            if key not in cache:
                m = verts[a] + verts[b]
                verts.append(m / np.linalg.norm(m))
                cache[key] = len(verts) - 1
            return cache[key]

        new = []
        for a, b, c in faces:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            new += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
        faces = new
    return np.array(verts) * radius + np.asarray(center, float), np.array(faces)


def quad(corners) -> tuple[np.ndarray, np.ndarray]:
    """Two triangles over 4 corners given counter-clockwise seen from the front."""
    return np.asarray(corners, float), np.array([[0, 1, 2], [0, 2, 3]])


def sphere_coverage(camera: Camera, center, radius, n_sub: int) -> np.ndarray:
    """[H, W] fraction of n_sub x n_sub sub-pixel rays per pixel that hit the analytic sphere."""
    cov = np.zeros((camera.height, camera.width))
    Kinv = np.linalg.inv(camera.K)
    R = camera.c2w[:3, :3]
    o = camera.center
    offs = (np.arange(n_sub) + 0.5) / n_sub - 0.5  # pixel (u, v) spans [u - 0.5, u + 0.5]
    u, v = np.meshgrid(np.arange(camera.width, dtype=float), np.arange(camera.height, dtype=float))
    for dy in offs:
        for dx in offs:
            pix = np.stack([u + dx, v + dy, np.ones_like(u)], -1)
            d = pix @ Kinv.T @ R.T
            d /= np.linalg.norm(d, axis=-1, keepdims=True)
            oc = o - np.asarray(center, float)
            b = d @ oc
            disc = b**2 - (oc @ oc - radius**2)
            cov += (disc > 0) & (-b - np.sqrt(np.maximum(disc, 0)) > 0)
    return cov / n_sub**2


def off_centre_camera(width=96, height=64) -> Camera:
    """Non-square image, principal point far from the centre, camera looking past the sphere."""
    K = np.array([[100.0, 0.0, 0.31 * width], [0.0, 100.0, 0.64 * height], [0.0, 0.0, 1.0]])
    return Camera("off", width, height, K, look_at([1.3, -2.6, 1.7], [0.45, 0.2, 0.85]))


SPHERE_C, SPHERE_R = np.array([0.2, 0.15, 1.05]), 0.35


@pytest.fixture(scope="module")
def sphere_render():
    cam = off_centre_camera()
    V, F = icosphere(4, SPHERE_R, SPHERE_C)
    spec = SceneSpec([MeshSpec("ball", V, F, reflectance=(0.6, 0.6, 0.6))], [Ambient(1.0)])
    return cam, render(spec, cam, spp=64, seed=3)


# -- cameras ------------------------------------------------------------------------------------
def test_sensor_rays_match_opencv_pixel_rays():
    """Mitsuba's ray through each pixel centre equals Camera.pixel_rays (OpenCV convention)."""
    mi = mitsuba()
    cam = off_centre_camera(41, 23)
    sensor = make_sensor(cam, spp=1)
    u, v = np.meshgrid(np.arange(cam.width), np.arange(cam.height))
    # Mitsuba's film coordinates put pixel u's centre at u + 0.5; sample_ray takes them / size.
    pos = mi.Point2f(((u + 0.5) / cam.width).ravel(), ((v + 0.5) / cam.height).ravel())
    ray, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5, 0.5))
    d = np.array(ray.d).T.reshape(cam.height, cam.width, 3)
    o = np.array(ray.o).T
    origin, d_ref = cam.pixel_rays()
    assert np.abs(d - d_ref).max() < 2e-6
    # Mitsuba starts each ray on the near plane (z_cam = near_clip = 1e-3), i.e. on the same ray
    off = o.reshape(cam.height, cam.width, 3) - origin
    along = (off * d_ref).sum(-1)
    assert np.abs(off - along[..., None] * d_ref).max() < 1e-5
    np.testing.assert_allclose(along * (d_ref @ cam.w2c[2, :3]), 1e-3, atol=2e-5)


def test_sensor_rejects_non_square_pixels():
    cam = off_centre_camera()
    K = cam.K.copy()
    K[0, 0] *= 1.01
    with pytest.raises(ValueError, match="square pixels"):
        make_sensor(Camera("aniso", cam.width, cam.height, K, cam.w2c))


def test_sphere_silhouette_matches_analytic_projection(sphere_render):
    """(a) mask > 0.5 equals the pixel-centre ray/sphere test up to 1 px, and alpha is the exact
    sub-pixel coverage: a half-pixel shift of the convention would move the centroid by 0.5 px."""
    cam, res = sphere_render
    assert res.rgb.shape == (cam.height, cam.width, 3) and res.alpha.shape == (cam.height, cam.width)
    centre_hit = sphere_coverage(cam, SPHERE_C, SPHERE_R, 1) > 0.5
    mask = res.alpha > 0.5
    # the ellipse lies well inside the image, off its centre
    ys, xs = np.nonzero(centre_hit)
    assert 0 < xs.min() and xs.max() < cam.width - 1 and 0 < ys.min() and ys.max() < cam.height - 1
    assert abs(xs.mean() - (cam.width - 1) / 2) > 5

    def dilate(m):
        p = np.pad(m, 1)
        return np.any([p[1 + dy : 1 + dy + m.shape[0], 1 + dx : 1 + dx + m.shape[1]]
                       for dy in (-1, 0, 1) for dx in (-1, 0, 1)], axis=0)  # fmt: skip

    assert not (mask & ~dilate(centre_hit)).any(), "rendered silhouette extends > 1 px past the sphere"
    assert not (centre_hit & ~dilate(mask)).any(), "rendered silhouette falls > 1 px short of the sphere"
    assert (mask != centre_hit).sum() <= 0.1 * (centre_hit.sum() ** 0.5) * 4  # only a few edge pixels

    cov = sphere_coverage(cam, SPHERE_C, SPHERE_R, 8)
    yy, xx = np.mgrid[: cam.height, : cam.width]
    for w in (cov, res.alpha):
        assert w.sum() > 300
    cx_ref, cy_ref = (xx * cov).sum() / cov.sum(), (yy * cov).sum() / cov.sum()
    cx, cy = (xx * res.alpha).sum() / res.alpha.sum(), (yy * res.alpha).sum() / res.alpha.sum()
    assert abs(cx - cx_ref) < 0.05 and abs(cy - cy_ref) < 0.05
    assert abs(res.alpha.sum() / cov.sum() - 1.0) < 0.01  # the 5120-face mesh is 0.1 % smaller


def test_mask_is_zero_outside_and_one_inside(sphere_render):
    """(d) alpha is exactly 0 where no part of a pixel sees the sphere and 1 where all of it does."""
    cam, res = sphere_render
    cov = sphere_coverage(cam, SPHERE_C, SPHERE_R, 4)
    pad = 1  # stay a pixel away from the edge, where sub-pixel sampling decides
    inside = cov == 1.0
    outside = cov == 0.0
    for _ in range(pad):
        inside = inside & np.roll(inside, 1, 0) & np.roll(inside, -1, 0) & np.roll(inside, 1, 1) & np.roll(inside, -1, 1)
        outside = outside & np.roll(outside, 1, 0) & np.roll(outside, -1, 0) & np.roll(outside, 1, 1) & np.roll(outside, -1, 1)
    assert inside.sum() > 200 and outside.sum() > 2000
    assert np.all(res.alpha[inside] == 1.0)
    assert np.all(res.alpha[outside] == 0.0)
    assert np.all(res.rgb[outside] == 0.0)  # the ambient emitter is not seen as background
    edge = ~inside & ~outside
    assert ((res.alpha[edge] > 0) & (res.alpha[edge] < 1)).any()  # anti-aliased, not binary
    assert res.alpha.min() >= 0.0 and res.alpha.max() <= 1.0


def test_light_panel_in_view_stays_out_of_rgb_and_mask():
    V, F = quad([[-0.5, 0, 0.5], [0.5, 0, 0.5], [0.5, 0, 1.5], [-0.5, 0, 1.5]])
    cam = Camera("c", 48, 32, intrinsics(48, 32, 60), look_at([0, -3, 1], [0, 0, 1]))
    panel = AreaLight(center=(0.0, -1.5, 1.0), target=(0.0, -3.0, 1.0), size=(0.3, 0.3), radiance=50.0)
    res = render(SceneSpec([MeshSpec("card", V, F)], [panel]), cam, spp=4)
    covered = res.alpha > 0
    # the panel faces the camera from between it and the card: invisible, but it blocks no
    # camera ray, and it does not light the card (it emits towards the camera only)
    assert covered[16, 24] and res.alpha.sum() > 60
    assert np.all(res.rgb[~covered] == 0.0)
    assert np.all(res.rgb < 1e-6)


# -- materials ----------------------------------------------------------------------------------
def front_camera(width=40, height=40) -> Camera:
    """Looks along +y at the plane y = 0, image right = +x, image up = +z."""
    return Camera("front", width, height, intrinsics(width, height, 30.0), look_at([0, -4, 1], [0, 0, 1]))


PLANE = quad([[-1, 0, 0], [1, 0, 0], [1, 0, 2], [-1, 0, 2]])  # faces -y, towards front_camera


def test_textured_plane_shows_checker_times_ambient():
    """(b) A one-sided diffuse plane of reflectance ρ under constant radiance L sees the whole
    hemisphere: outgoing radiance ∫ (ρ/π) L cosθ dω = ρ L. The 2x2 checker's top-left texel
    (row 0) must appear top-left (UV v up, OBJ convention)."""
    V, F = PLANE
    uv = (V[:, [0, 2]] - [-1, 0]) / 2.0  # u along +x, v along +z
    colors = np.array([[[0.9, 0.1, 0.1], [0.1, 0.8, 0.1]], [[0.1, 0.1, 0.7], [0.6, 0.6, 0.6]]], np.float32)
    # 4x4 texels per checker cell, so bilinear filtering is constant over the sampled patches
    texture = np.kron(colors, np.ones((4, 4, 1), np.float32))
    L = np.array([0.8, 1.0, 1.2])
    cam = front_camera()
    res = render(SceneSpec([MeshSpec("plane", V, F, uvs=uv, texture=texture)], [Ambient(tuple(L))]), cam, spp=32)
    # plane x in [-1, 1] at distance 4, fov 30°: it spans ~ +-14.9 px about the centre
    uvw, _ = cam.project(np.array([[-0.5, 0, 1.5], [0.5, 0, 1.5], [-0.5, 0, 0.5], [0.5, 0, 0.5]]))
    for (u, v), rho in zip(uvw, [colors[0, 0], colors[0, 1], colors[1, 0], colors[1, 1]]):
        patch = res.rgb[int(round(v)) - 3 : int(round(v)) + 4, int(round(u)) - 3 : int(round(u)) + 4]
        np.testing.assert_allclose(patch.reshape(-1, 3).mean(0), rho * L, rtol=0.03, atol=0.003)


def test_one_sided_back_is_black_and_twosided_is_lit():
    V, F = PLANE
    back = Camera("back", 24, 24, intrinsics(24, 24, 30.0), look_at([0, 4, 1], [0, 0, 1]))
    one = render(SceneSpec([MeshSpec("p", V, F, reflectance=(0.5, 0.5, 0.5))], [Ambient(1.0)]), back, spp=8)
    two = render(SceneSpec([MeshSpec("p", V, F, reflectance=(0.5, 0.5, 0.5), twosided=True)], [Ambient(1.0)]), back, spp=16)
    assert one.alpha[12, 12] == 1.0 and one.rgb[8:16, 8:16].max() == 0.0
    np.testing.assert_allclose(two.rgb[8:16, 8:16].mean(), 0.5, rtol=0.03)


def test_vertex_colors_and_two_meshes():
    """(c) Per-vertex colours interpolate linearly over a triangle, so a colour that is an
    affine function of position is reproduced exactly at every surface point; a second mesh
    with a constant reflectance renders beside it in the same scene."""
    V, F = quad([[-1, 0, 0], [0, 0, 0], [0, 0, 2], [-1, 0, 2]])
    A = np.array([[0.4, 0.0, 0.1], [0.0, 0.0, 0.2], [0.0, 0.3, 0.0]])  # colour = c0 + (x, y, z) A
    c0 = np.array([0.5, 0.2, 0.3])

    def colour(p):
        return c0 + p @ A

    V2, F2 = quad([[0.2, 0, 0], [1, 0, 0], [1, 0, 2], [0.2, 0, 2]])
    L = 1.5
    cam = front_camera(48, 40)
    spec = SceneSpec(
        [MeshSpec("body", V, F, colors=colour(V)), MeshSpec("garment", V2, F2, reflectance=(0.1, 0.3, 0.5))],
        [Ambient(L)],
    )
    res = render(spec, cam, spp=64)
    o, d = cam.pixel_rays()
    t = -o[1] / d[..., 1]  # ray parameter where each pixel-centre ray meets the plane y = 0
    hit = o + t[..., None] * d
    on_body = (hit[..., 0] < -0.1) & (hit[..., 0] > -0.9) & (hit[..., 2] > 0.1) & (hit[..., 2] < 1.9)
    on_garment = (hit[..., 0] > 0.3) & (hit[..., 0] < 0.9) & (hit[..., 2] > 0.1) & (hit[..., 2] < 1.9)
    assert on_body.sum() > 100 and on_garment.sum() > 80
    expected = L * colour(hit[on_body])
    err = res.rgb[on_body] - expected
    assert np.abs(err.mean(0)).max() < 0.01  # unbiased
    # noise-free part: the colour gradient across the patch is reproduced (fit slope in x and z)
    X = np.column_stack([np.ones(on_body.sum()), hit[on_body][:, 0], hit[on_body][:, 2]])
    coef, *_ = np.linalg.lstsq(X, res.rgb[on_body], rcond=None)
    np.testing.assert_allclose(coef[1], L * A[0], atol=0.03)
    np.testing.assert_allclose(coef[2], L * A[2], atol=0.03)
    np.testing.assert_allclose(res.rgb[on_garment].mean(0), L * np.array([0.1, 0.3, 0.5]), rtol=0.03)
    # the gap between the two meshes (x in (0, 0.2)) is background
    gap = (hit[..., 0] > 0.05) & (hit[..., 0] < 0.15) & (hit[..., 2] > 0.2) & (hit[..., 2] < 1.8)
    assert gap.any() and np.all(res.alpha[gap] == 0.0)


def test_split_uv_seams():
    rng = np.random.default_rng(0)
    V = rng.normal(size=(6, 3))
    F = np.array([[0, 1, 2], [0, 2, 3], [3, 2, 4], [4, 2, 5]])
    # one UV chart per pair of faces: vertices 2 and 3 (shared across the seam) get two UVs
    uv_vals = rng.uniform(size=(F.size, 2))
    corner_uv = uv_vals.reshape(-1, 3, 2).copy()
    for (fa, ka), (fb, kb) in [((0, 0), (1, 0)), ((0, 2), (1, 1)), ((2, 1), (3, 1)), ((2, 2), (3, 0))]:
        corner_uv[fb, kb] = corner_uv[fa, ka]  # same chart: shared vertices share their UV
    s = split_uv_seams(V, F, corner_uv)
    # distinct (vertex, uv) pairs: chart A has vertices 0,1,2,3; chart B has 2,3,4,5 -> 8
    assert len(s.vertices) == 8
    np.testing.assert_array_equal(s.vertices[s.faces], V[F])
    np.testing.assert_array_equal(s.uvs[s.faces], corner_uv)
    np.testing.assert_array_equal(s.vertices, V[s.vertex_map])
    # the OBJ layout (uv table + uv indices) gives the same split
    table, idx = np.unique(corner_uv.reshape(-1, 2), axis=0, return_inverse=True)
    s2 = split_uv_seams(V, F, table, idx.reshape(F.shape))
    np.testing.assert_array_equal(s2.vertices[s2.faces], V[F])
    np.testing.assert_array_equal(s2.uvs[s2.faces], corner_uv)
    assert len(s2.vertices) == 8
    # without seams the vertex order is kept
    per_vertex_uv = rng.uniform(size=(6, 2))
    s3 = split_uv_seams(V, F, per_vertex_uv[F])
    np.testing.assert_array_equal(s3.vertex_map, np.arange(6))
    np.testing.assert_array_equal(s3.faces, F)


# -- lights -------------------------------------------------------------------------------------
def floor_scene(light, rho=0.5):
    V, F = quad([[-3, -3, 0], [3, -3, 0], [3, 3, 0], [-3, 3, 0]])  # faces +z
    return SceneSpec([MeshSpec("floor", V, F, reflectance=(rho, rho, rho))], [light], max_depth=2)


def top_camera(n=24) -> Camera:
    return Camera("top", n, n, intrinsics(n, n, 40.0), look_at([0, 0, 3], [0, 0, 0], up=(0, 1, 0)))


def floor_hits(cam, dx=0.0, dy=0.0):
    """[H, W, 3] points where rays through pixel centres (+ (dx, dy) px) meet z = 0."""
    u, v = np.meshgrid(np.arange(cam.width) + dx, np.arange(cam.height) + dy)
    d = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(cam.K).T @ cam.c2w[:3, :3].T
    o = cam.center
    return o + (-o[2] / d[..., 2])[..., None] * d


def test_point_and_sun_light_radiometry():
    """Diffuse radiance is ρ/π · E with irradiance E = I cosθ / r² (point) or E_sun cosθ (sun).
    Delta lights have no sampling noise, so the match is per pixel."""
    rho, cam = 0.5, top_camera()
    P, I = np.array([0.3, -0.2, 1.0]), 2.0
    res = render(floor_scene(PointLight(tuple(P), I), rho), cam, spp=64)
    # irradiance changes by several % across a pixel's footprint: average 4x4 sub-pixel points
    expected = 0.0
    for dy in (-0.375, -0.125, 0.125, 0.375):
        for dx in (-0.375, -0.125, 0.125, 0.375):
            r = P - floor_hits(cam, dx, dy)
            dist = np.linalg.norm(r, axis=-1)
            expected = expected + rho / np.pi * I * (r[..., 2] / dist) / dist**2 / 16
    np.testing.assert_allclose(res.rgb[..., 1], expected, rtol=0.02)

    to_sun, E = np.array([0.3, -0.5, 0.8]), 3.0
    res = render(floor_scene(SunLight(tuple(to_sun), E), rho), cam, spp=4)
    np.testing.assert_allclose(res.rgb, rho / np.pi * E * to_sun[2] / np.linalg.norm(to_sun), rtol=1e-3)


def test_area_light_radiometry():
    """Below the centre of a parallel square panel (half side a, height h) the form factor is
    4 · (1/2π)(2 · X/√(1+X²) · atan(X/√(1+X²))) with X = a/h; radiance out is ρ · Le · F."""
    rho, a, h, Le = 0.5, 0.4, 1.0, 4.0
    res = render(floor_scene(AreaLight((0, 0, h), (0, 0, 0), (2 * a, 2 * a), Le), rho), top_camera(), spp=64)
    X = a / h
    F = 4.0 / (2 * np.pi) * 2 * X / np.sqrt(1 + X**2) * np.arctan(X / np.sqrt(1 + X**2))
    np.testing.assert_allclose(res.rgb[10:14, 10:14].mean(), rho * Le * F, rtol=0.03)


def test_envmap_orientation():
    """An environment map that stores each texel's own direction returns, for a viewing direction
    w, (about) w itself: row 0 = +z, centre column = +x, quarter column = +y."""
    mi = mitsuba()
    H, W = 64, 128
    dirs = envmap_directions(H, W)
    emitter = mi.load_dict({"type": "scene", "env": EnvMap(dirs * 0.5 + 0.5).to_dict()}).environment()
    ws = np.array([[1, 0, 0], [0, 1, 0], [0, -1, 0], [-0.6, 0, 0.8], [0.48, 0.6, -0.64]], float)
    si = mi.SurfaceInteraction3f()
    si.wi = mi.Vector3f(-ws.T)  # wi points back along the viewing ray
    got = np.array(emitter.eval(si)) * 2 - 1
    np.testing.assert_allclose(got.T, ws, atol=0.04)  # bilinear lookup: within a texel


def test_sky_and_hdr_envmaps_light_from_above():
    """Under a sky (bright above, dark ground) a floor facing up is much brighter than a
    ceiling facing down; the same holds for a real HDRI when the shared data is present."""
    cam = top_camera(16)
    up = render(floor_scene(EnvMap(sky_envmap(32, 64)), 0.5), cam, spp=16).rgb.mean()
    V, F = quad([[-3, 3, 0], [3, 3, 0], [3, -3, 0], [-3, -3, 0]])  # faces -z
    below = Camera("below", 16, 16, intrinsics(16, 16, 40.0), look_at([0, 0, -3], [0, 0, 0], up=(0, 1, 0)))
    spec = SceneSpec([MeshSpec("ceiling", V, F, reflectance=(0.5, 0.5, 0.5))], [EnvMap(sky_envmap(32, 64))], max_depth=2)
    down = render(spec, below, spp=16).rgb.mean()
    assert up > 3 * down > 0
    path = os.path.join(ENVMAP_DIR, "studio_small_03_1k.hdr")
    if os.path.exists(path):
        res = render(floor_scene(EnvMap(path), 0.5), cam, spp=4)
        assert np.isfinite(res.rgb).all() and res.rgb.mean() > 0


def test_soft_studio_casts_a_soft_shadow():
    """A box above the floor darkens the floor under it (shadow of the key panel) without
    making it black (ambient), and the shadow edge is soft: no hard step across it."""
    V, F = quad([[-3, -3, 0], [3, -3, 0], [3, 3, 0], [-3, 3, 0]])
    Vb, Fb = icosphere(2, 0.3, (0.0, 0.0, 0.6))
    lights = soft_studio(target=(0, 0, 0.5), ambient=0.3)
    spec = SceneSpec([MeshSpec("floor", V, F), MeshSpec("ball", Vb, Fb)], lights)
    cam = Camera("c", 64, 48, intrinsics(64, 48, 50.0), look_at([0, 2.5, 2.5], [0, -0.3, 0]))
    res = render(spec, cam, spp=32)
    uv, _ = cam.project(np.array([[0.0, 0.45, 0.0], [1.6, 0.45, 0.0]]))  # behind the ball / far away
    shadow = res.rgb[int(uv[0, 1]) - 1 : int(uv[0, 1]) + 2, int(uv[0, 0]) - 1 : int(uv[0, 0]) + 2].mean()
    lit = res.rgb[int(uv[1, 1]) - 1 : int(uv[1, 1]) + 2, int(uv[1, 0]) - 1 : int(uv[1, 0]) + 2].mean()
    assert 0.1 * lit < shadow < 0.85 * lit


# -- rendering API --------------------------------------------------------------------------------
def test_render_is_deterministic_and_seed_dependent():
    V, F = icosphere(2, 0.5, (0, 0, 1))
    spec = SceneSpec([MeshSpec("ball", V, F)], soft_studio())
    scene = load_scene(spec)
    cam = front_camera(24, 16)
    a = render(scene, cam, spp=4, seed=7)
    b = render(scene, cam, spp=4, seed=7)
    c = render(scene, cam, spp=4, seed=8)
    np.testing.assert_array_equal(a.rgb, b.rgb)
    np.testing.assert_array_equal(a.alpha, b.alpha)
    assert not np.array_equal(a.rgb, c.rgb)
    views = render_views(scene, [cam, front_camera(20, 12)], spp=4, seed=7)
    assert views[1].rgb.shape == (12, 20, 3)
    np.testing.assert_array_equal(views[0].rgb, a.rgb)


def test_gradient_wrt_ambient_radiance():
    """d/dL of mean((ρ L α - T)²) for a target rendered brighter is negative, finite, and
    equals the closed form 2 (L - L_t) Σ (ρ α)² / N per channel for this unshadowed plane."""
    import drjit as dr

    mi = mitsuba()
    V, F = PLANE
    rho = np.array([0.5, 0.4, 0.3])
    spec = SceneSpec([MeshSpec("plane", V, F, reflectance=tuple(rho))], [Ambient(0.5)], max_depth=2)
    cam = front_camera(24, 24)
    L_target = 1.0
    target = render(SceneSpec(spec.meshes, [Ambient(L_target)], max_depth=2), cam, spp=16, seed=1)
    scene, params, keys = differentiable_scene(spec)
    assert keys.ambient == "ambient.radiance.value" and keys.reflectance["plane"] == "plane.bsdf.reflectance.value"
    key = keys.ambient
    dr.enable_grad(params[key])
    params.update()
    img = mi.render(scene, params, sensor=make_sensor(cam, 16), spp=16, seed=0)
    tgt = mi.TensorXf(np.concatenate([target.rgb, target.alpha[..., None]], -1))
    loss = dr.mean(dr.square(img - tgt), axis=None)
    dr.backward(loss)
    g = np.array(dr.grad(params[key])).ravel()
    assert np.isfinite(g).all() and np.all(g < 0)
    alpha = target.alpha
    N = alpha.size * 4
    expected = 2 * (0.5 - L_target) * (rho[None, :] ** 2 * (alpha**2).reshape(-1, 1)).sum(0) / N
    np.testing.assert_allclose(g, expected, rtol=0.1)


def test_texture_gradient_key_exists_and_is_finite():
    import drjit as dr

    mi = mitsuba()
    V, F = PLANE
    uv = (V[:, [0, 2]] - [-1, 0]) / 2.0
    tex = np.full((4, 4, 3), 0.3, np.float32)
    spec = SceneSpec([MeshSpec("garment", V, F, uvs=uv, texture=tex, twosided=True)], [Ambient(1.0)])
    scene, params, keys = differentiable_scene(spec)
    key = keys.reflectance["garment"]
    assert key == "garment.bsdf.brdf_0.reflectance.data"
    dr.enable_grad(params[key])
    params.update()
    img = mi.render(scene, params, sensor=make_sensor(front_camera(16, 16), 4), spp=4, seed=0)
    dr.backward(dr.mean(img[..., :3], axis=None))  # brighter texture -> brighter image
    g = np.array(dr.grad(params[key]))
    assert g.shape == (4, 4, 3) and np.isfinite(g).all() and g.sum() > 0


# -- images ----------------------------------------------------------------------------------------
def test_srgb_round_trip_and_reference_values():
    x = np.linspace(0, 1, 101)
    np.testing.assert_allclose(srgb_to_linear(linear_to_srgb(x)), x, atol=1e-12)
    # IEC 61966-2-1: linear 0.5 -> 0.7354, 0.0031308 is the knee, 0.18 (mid grey) -> 0.4614
    np.testing.assert_allclose(linear_to_srgb([0.5, 0.18, 0.0031308]), [0.735357, 0.461356, 0.0404482], atol=1e-5)
    assert linear_to_srgb8(np.array([[[0.0, 1.0, 2.0]]])).tolist() == [[[0, 255, 255]]]


def test_write_png_is_atomic_and_round_trips(tmp_path):
    img = (np.arange(5 * 7 * 3) % 256).astype(np.uint8).reshape(5, 7, 3)
    p = write_png(tmp_path / "sub" / "a.png", img)
    np.testing.assert_array_equal(read_png(p), img)
    write_png(p, img[..., 0])  # overwrite in place
    np.testing.assert_array_equal(read_png(p), img[..., 0])
    assert sorted(os.listdir(tmp_path / "sub")) == ["a.png"]  # no temporary files left behind
    with pytest.raises(TypeError):
        write_png(tmp_path / "b.png", img.astype(np.float32))


def test_contact_sheet_layout():
    imgs = [np.full((10, 40, 3), 40 * (i + 1), np.uint8) for i in range(5)]
    sheet = contact_sheet(imgs, [f"cam{i:02d}" for i in range(5)], pad=2, label_height=12)
    # 3 columns x 2 rows of (12 + 10) x 40 cells with 2 px padding
    assert sheet.shape == (2 + 2 * (22 + 2), 2 + 3 * (40 + 2), 3) and sheet.dtype == np.uint8
    for i in range(5):
        r, c = divmod(i, 3)
        y0, x0 = 2 + r * 24 + 12, 2 + c * 42
        assert np.all(sheet[y0 : y0 + 10, x0 : x0 + 40] == 40 * (i + 1))
        label = sheet[y0 - 12 : y0, x0 : x0 + 40]
        assert (label > 150).sum() > 10  # light text drawn in the label strip
    assert np.all(sheet[2 + 24 + 12 :, 2 + 2 * 42 :] == 32)  # the sixth cell is empty


def test_param_keys_name_every_light_and_material():
    """Every key ParamKeys promises exists in mi.traverse (differentiable_scene checks it)."""
    V, F = PLANE
    uv = (V[:, [0, 2]] - [-1, 0]) / 2.0
    spec = SceneSpec(
        [
            MeshSpec("body", V, F, colors=np.full((4, 3), 0.5)),
            MeshSpec("garment", V + [0, -0.1, 0], F, uvs=uv, texture=np.full((2, 2, 3), 0.5)),
            MeshSpec("shoe", V + [0, -0.2, 0], F, reflectance=(0.2, 0.2, 0.2), twosided=True),
        ],
        [EnvMap(sky_envmap(8, 16)), AreaLight((0, -2, 2), (0, 0, 1)), PointLight((0, -1, 3)), SunLight()],
    )
    _, params, keys = differentiable_scene(spec)
    assert keys.reflectance == {
        "body": "body.vertex_color",
        "garment": "garment.bsdf.reflectance.data",
        "shoe": "shoe.bsdf.brdf_0.reflectance.value",
    }
    assert keys.ambient == "envmap.scale"
    assert set(keys.emitters) == {"envmap", "area", "point", "sun"}
    assert all(k in params for k in keys.emitters.values())
    with pytest.raises(ValueError, match="unique"):
        SceneSpec([MeshSpec("a", V, F), MeshSpec("a", V, F)])
    with pytest.raises(ValueError, match="at most one"):
        SceneSpec([], [Ambient(1.0), EnvMap(sky_envmap(8, 16))])
