"""The ``env`` light model (stages/appearance/envlight.py): the alternating least squares recovers a
light and an albedo it did not start from; the renderer's environment swap is the same map a fresh
scene renders; a fitted map survives light.json."""

from __future__ import annotations

import numpy as np

from physavatar.camera import Camera, intrinsics, look_at
from physavatar.render import EnvMap, MeshSpec, SceneSpec, load_scene, render
from physavatar.render.lights import envmap_directions, load_lights, save_lights
from physavatar.stages.appearance.envlight import alternate, env_basis, env_views, fibonacci_directions


def test_alternating_least_squares_recovers_light_and_albedo():
    # I = T[texel] * sum_k l_k E_k, each texel seen in 4 "frames" with different basis irradiances;
    # the start is the constant light alone (the ambient model). Only T*l is determined: the
    # product must be recovered, and l up to one factor per channel.
    rng = np.random.default_rng(1)
    n_tex, K, frames = 300, 5, 4
    T = rng.uniform(0.1, 0.9, (n_tex, 3))
    l_true = rng.uniform(0.0, 1.0, (K, 3))
    l_true[2] = 0.0  # one lobe unlit: non-negativity must keep it at 0
    texel = np.repeat(np.arange(n_tex), frames)
    E = rng.uniform(0.0, 1.0, (len(texel), K, 3))
    I = T[texel] * np.einsum("nkc,kc->nc", E, l_true)
    w = np.ones(len(texel))
    l0 = np.zeros((K, 3))
    l0[0] = 1.0
    l, T_fit = alternate(I, E, w, texel, l0, iterations=200)
    ratio = l / l_true.clip(1e-12)
    c = ratio[[0, 1, 3, 4]].mean(0)
    np.testing.assert_allclose(ratio[[0, 1, 3, 4]], np.broadcast_to(c, (4, 3)), rtol=2e-2)
    assert np.all(l[2] < 1e-3 * l.max())
    np.testing.assert_allclose(T_fit * c, T, rtol=2e-2)
    # the images are reproduced
    assert np.abs(I - T_fit[texel] * np.einsum("nkc,kc->nc", E, l)).max() < 1e-2 * np.abs(I).max()


def test_basis_and_views():
    d = fibonacci_directions(12)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    assert abs(d.mean(0)).max() < 0.1  # spread over the whole sphere
    B = env_basis(12)
    assert B.shape == (13, 16, 32) and np.allclose(B[0], 1.0)
    # each lobe peaks at its own direction (the texel nearest to it)
    dirs = envmap_directions(16, 32).reshape(-1, 3)
    for k in range(1, 13):
        assert np.dot(dirs[B[k].argmax()], d[k - 1]) > 0.95
    v = env_views(10, 4, 12)
    assert len(v) == 12 and v[0] == (0, 0) and v[-1][0] == 9 and {c for _, c in v} == {0, 1, 2, 3}


def _sphere():
    import trimesh

    s = trimesh.creation.icosphere(3, radius=0.5)
    return np.asarray(s.vertices), np.asarray(s.faces)


def test_renderer_env_swap_matches_a_fresh_scene():
    """InverseRenderer.set_envmap pads the map as Mitsuba does: rendering after the swap equals
    rendering a scene built with that map (a lobe from one side, so a wrong column shift or
    orientation shows)."""
    from physavatar.render.avatar import AvatarMeshes
    from physavatar.stages.appearance.scene import InverseRenderer

    V, F = _sphere()
    uv = np.zeros((len(F), 3, 2)) + 0.5
    cam = Camera("c", 48, 48, intrinsics(48, 48, 40.0), look_at(np.array([0.0, -3.0, 0.3]), np.zeros(3)))
    lobe = np.repeat(env_basis(12)[4][..., None], 3, -1) * np.array([1.0, 0.6, 0.3], np.float32)
    tex = np.full((8, 8, 3), 0.7, np.float32)
    meshes = AvatarMeshes.build(V, F, uv, np.zeros(len(V), int))
    r = InverseRenderer(meshes, V, tex, [EnvMap(np.ones_like(lobe))])
    r.set_envmap(lobe)
    swapped = r.render(cam, tex, spp=64, seed=3).rgb
    fresh = render(load_scene(SceneSpec(meshes=meshes.specs(V, tex), lights=[EnvMap(lobe)])), cam, spp=64, seed=3).rgb
    assert swapped.max() > 0.05
    np.testing.assert_allclose(swapped, fresh, atol=2e-3)
    uniform = render(load_scene(SceneSpec(meshes=meshes.specs(V, tex), lights=[EnvMap(np.ones_like(lobe))])), cam,
                     spp=64, seed=3).rgb
    assert np.abs(swapped - uniform).mean() > 0.05


def test_a_fitted_environment_map_survives_light_json(tmp_path):
    img = np.random.default_rng(0).uniform(0, 2, (16, 32, 3)).astype(np.float32)
    save_lights(tmp_path / "light.json", [EnvMap(img)])
    (back,) = load_lights(tmp_path / "light.json")
    assert isinstance(back, EnvMap) and back.image.shape == (16, 32, 3)
    np.testing.assert_allclose(back.image, img, atol=1e-6)
