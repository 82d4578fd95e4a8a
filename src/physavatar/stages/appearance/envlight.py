"""The ``env`` light model: a smooth environment map fitted together with the albedo, in closed
form, before the projected texture is made.

A diffuse surface shows I = T · E, and the irradiance E is linear in the environment's radiance:
with the environment written as a sum of K fixed basis maps B_k with RGB weights l_k ≥ 0
(a constant map and K-1 smooth lobes exp(κ (d·d_k − 1)) about directions d_k spread over the
sphere), E = Σ_k l_k E_k, E_k the render of a white avatar under B_k alone (shadows and the
bounce included). Over the texel observations of a few training views (the visibility and
occlusion-edge tests of :class:`~.project.Projection`), the albedo and the light are fitted by
alternating least squares, per channel:

    T_x = Σ_v w I E / Σ_v w E²                    (the light fixed: the projection's division)
    l   = argmin_{l ≥ 0} Σ_{x,v} w (I − T_x Σ_k l_k E_k)²   (the albedo fixed: non-negative LS)

A texel seen in one frame only can match any light; what fixes the light is the same texel seen
in frames where the body turned (its shading changes, its albedo does not). The ambient model
(one constant) is the K = 1 case; the lobes take the directional part of the lights (a key light
on one side, a rim light behind) that the ambient model bakes into the texture.

The environment starts at ``ambient_init`` (the ambient model's start), so texture and light keep
the ambient model's overall scale. Libraries: Mitsuba renders the basis irradiances (the renderer
the fit and ``evaluate`` use), ``scipy.optimize.nnls`` solves the light.
"""

from __future__ import annotations

import numpy as np

from ...render.lights import envmap_directions

ENV_SHAPE = (16, 32)  # rows, columns of the fitted equirectangular map


def fibonacci_directions(n: int) -> np.ndarray:
    """[n, 3] unit directions spread evenly over the sphere (a Fibonacci lattice)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = np.pi * (1.0 + 5.0 ** 0.5) * i
    r = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)


def env_basis(lobes: int, shape: tuple[int, int] = ENV_SHAPE, sharpness: float = 4.0) -> np.ndarray:
    """[K, H, W] basis maps: a constant map, then ``lobes`` smooth lobes exp(κ (d·d_k − 1))."""
    d = envmap_directions(*shape)
    out = [np.ones(shape)]
    for dk in fibonacci_directions(lobes) if lobes > 0 else []:
        out.append(np.exp(sharpness * (d @ dk - 1.0)))
    return np.stack(out).astype(np.float32)


def env_image(basis: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """[H, W, 3] map Σ_k weights[k] · basis[k] (weights [K, 3])."""
    return np.einsum("khw,kc->hwc", basis, weights).astype(np.float32)


def alternate(I: np.ndarray, E: np.ndarray, w: np.ndarray, texel: np.ndarray, l0: np.ndarray,
              iterations: int = 20, max_rows: int = 60000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Alternating least squares of I ≈ T[texel] · Σ_k l_k E_k (module docstring).

    Args:
        I: [n, 3] observed linear colours; E: [n, K, 3] basis irradiances at the same samples;
        w: [n] weights; texel: [n] texel id of each sample; l0: [K, 3] starting weights.
    Returns:
        l [K, 3] non-negative light weights; T [max(texel)+1, 3] the albedo of each texel (0 where
        it has no sample).
    """
    from scipy.optimize import nnls

    l = np.asarray(l0, np.float64).copy()
    m = int(texel.max()) + 1 if len(texel) else 0
    rng = np.random.default_rng(seed)
    rows = rng.choice(len(I), min(len(I), max_rows), replace=False) if len(I) else np.zeros(0, int)
    sw = np.sqrt(w[rows])
    T = np.zeros((m, 3))
    for _ in range(iterations):
        Eo = np.einsum("nkc,kc->nc", E, l)
        for c in range(3):
            num = np.bincount(texel, weights=w * I[:, c] * Eo[:, c], minlength=m)
            den = np.bincount(texel, weights=w * Eo[:, c] ** 2, minlength=m)
            T[:, c] = np.where(den > 0, num / np.maximum(den, 1e-20), 0.0)
        for c in range(3):
            A = sw[:, None] * T[texel[rows], c][:, None] * E[rows, :, c]
            l[:, c] = nnls(A, sw * I[rows, c], maxiter=50 * A.shape[1])[0]
    return l, T


def fit_env_light(data, cfg, renderer, points, views, advance=None) -> tuple[np.ndarray, dict]:
    """The fitted environment map [H, W, 3] and a summary, from the (frame index, camera index)
    ``views`` (module docstring). ``renderer``: the fit's :class:`~.scene.InverseRenderer` with an
    environment map; ``points``: the atlas's :class:`~.project.TexelPoints`. Leaves the
    renderer's environment at the fitted map."""
    from .data import load_target
    from .initial import twosided_faces
    from .project import Occlusion, Projection, bilinear

    t = data.template
    basis = env_basis(cfg.env_lobes)
    K = len(basis)
    white = np.ones((cfg.texture_size, cfg.texture_size, 3), np.float32)
    two = twosided_faces(t)
    probe = Projection.empty(points)
    Is, Es, ws, xs = [], [], [], []
    for ti, ci in views:
        V = data.vertices[ti]
        cam = data.cameras[ci]
        renderer.set_vertices(V, tag=ti)
        image, mask = load_target(data.capture, cam, data.frames[ti], 1.0, cfg.erode_px)
        Ek = []
        for k in range(K):
            renderer.set_envmap(np.repeat(basis[k][..., None], 3, -1))
            Ek.append(renderer.render(cam, white, spp=cfg.env_spp, seed=3000 + 131 * ti + 7 * ci + k))
        allowed = mask & (Ek[0].alpha > 0.99)
        idx, xy, cos = probe.observe(cam, V, t.faces, allowed, occlusion=Occlusion(V, t.faces), twosided=two)
        Is.append(bilinear(image, xy).astype(np.float32))
        Es.append(np.stack([bilinear(e.rgb, xy) for e in Ek], 1).astype(np.float32))
        ws.append(cos.astype(np.float32))
        xs.append(idx)
        if advance is not None:
            advance()
    I, E, w, texel = np.concatenate(Is), np.concatenate(Es), np.concatenate(ws), np.concatenate(xs)
    l0 = np.zeros((K, 3))
    l0[0] = cfg.ambient_init
    l, _ = alternate(I.astype(np.float64), E.astype(np.float64), w.astype(np.float64), texel, l0, seed=cfg.seed)
    img = env_image(basis, l)
    renderer.set_envmap(img)
    return img, {"weights": l.tolist(), "samples": int(len(I)), "views": len(views), "lobes": cfg.env_lobes}


def env_views(n_frames: int, n_cams: int, n: int) -> list[tuple[int, int]]:
    """``n`` (frame index, camera index) views: frames spread evenly over the sequence, cameras
    in turn (the light is fixed by the body turning between frames)."""
    frames = np.linspace(0, n_frames - 1, n).round().astype(int)
    return [(int(f), j % n_cams) for j, f in enumerate(frames)]


def fitted_env_light(data, cfg, out, renderer, points, progress=None) -> tuple[np.ndarray, dict]:
    """:func:`fit_env_light`, read back from ``out/env_light.npz`` when it was made with the same
    settings from the same data (:attr:`AppearanceData.key`; a resumed fit), else computed and
    written there."""
    import json

    from ...files import load_npz, save_npz_atomic
    from ...progress import resolve

    key = json.dumps({"lobes": cfg.env_lobes, "views": cfg.env_views, "spp": cfg.env_spp, "erode_px": cfg.erode_px,
                      "ambient_init": cfg.ambient_init, "seed": cfg.seed, "meshes": data.source, "data": data.key,
                      "frames": data.frames, "cameras": [c.name for c in data.cameras],
                      "texture_size": cfg.texture_size})
    path = out / "env_light.npz"
    z = load_npz(path) if path.is_file() else {}
    if str(z.get("key", "")) == key:
        img = np.asarray(z["image"], np.float32)
        renderer.set_envmap(img)
        return img, json.loads(str(z["info"]))
    views = env_views(len(data.frames), len(data.cameras), cfg.env_views)
    with resolve(progress).task("appearance: environment light", total=len(views)) as task:
        img, info = fit_env_light(data, cfg, renderer, points, views, advance=task.advance)
    save_npz_atomic(path, image=img, key=np.array(key), info=np.array(json.dumps(info)))
    return img, info
