"""The CPU Gaussian rasterizer against its dense PyTorch twin, an analytic splat and finite differences;
mesh-aligned Gaussians against the mesh they come from."""

from __future__ import annotations

import numba
import numpy as np
import pytest
import torch

from physavatar.camera import intrinsics, look_at
from physavatar.splat import expected_depth, longest_edge_index, mesh_to_gaussians, rasterize, rasterize_batch
from physavatar.splat import _gsplat
from physavatar.splat._torch_impl import quat_to_rotmat

F64 = torch.float64
NEAR = 0.1


def random_scene(seed: int, n: int = 300, width: int = 64, height: int = 48):
    """Gaussians in a box larger than the view, plus some straddling the near plane and behind it."""
    rng = np.random.default_rng(seed)
    K = intrinsics(width, height, rng.uniform(40.0, 70.0))
    K[0, 2] += rng.uniform(-3, 3)  # principal point off centre
    direction = rng.normal(size=3)
    eye = 2.5 * direction / np.linalg.norm(direction)
    w2c = look_at(eye, rng.uniform(-0.2, 0.2, 3))
    means = rng.uniform(-1.2, 1.2, (n, 3))
    # 10% close to the camera: camera z in [-0.05, 0.4] with near = 0.1, some off-screen sideways.
    m = n // 10
    cam = np.stack([rng.uniform(-0.3, 0.3, m), rng.uniform(-0.3, 0.3, m), rng.uniform(-0.05, 0.4, m)], 1)
    c2w = np.linalg.inv(w2c)
    means[:m] = cam @ c2w[:3, :3].T + c2w[:3, 3]
    scales = np.exp(rng.uniform(np.log(0.005), np.log(0.2), (n, 3)))
    scales[:m] *= 0.1  # close splats stay small on screen, or they would cover the whole image
    opac = rng.uniform(0.05, 1.0, n)
    opac[rng.random(n) < 0.2] = 1.0  # saturated: exercises the 0.99 clamp
    t = lambda a: torch.tensor(a, dtype=F64)  # noqa: E731
    params = [t(means), t(rng.normal(size=(n, 4))), t(scales), t(opac), t(rng.uniform(0, 1, (n, 3)))]
    return params, t(w2c), t(K), t(rng.uniform(0, 1, 3)), width, height


def render(params, vm, K, bg, w, h, backend):
    return rasterize(*params, vm, K, w, h, bg, near=NEAR, far=100.0, backend=backend)


def loss_and_grads(params, vm, K, bg, w, h, backend, seed=0):
    params = [p.detach().clone().requires_grad_(True) for p in params]
    out = render(params, vm, K, bg, w, h, backend)
    g = torch.Generator().manual_seed(seed)
    wr = torch.randn(h, w, 3, generator=g, dtype=F64)
    wa = torch.randn(h, w, generator=g, dtype=F64)
    wd = torch.randn(h, w, generator=g, dtype=F64)
    loss = (out["rgb"] * wr).sum() + (out["alpha"] * wa).sum() + (out["depth"] * wd).sum()
    return out, torch.autograd.grad(loss, params)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_forward_and_gradients_match_dense_twin(seed):
    scene = random_scene(seed)
    out_n, grads_n = loss_and_grads(*scene, backend="numba")
    out_t, grads_t = loss_and_grads(*scene, backend="torch")
    meta = out_n["meta"]
    # The scene must exercise what it claims to: culled (near plane), off-screen, drawn.
    assert 0 < int(meta["visible"].sum()) < len(meta["visible"])
    assert (meta["depths"] < NEAR).any() and (meta["depths"] > 0).any()
    assert out_n["alpha"].max() > 0.9 and out_n["alpha"].min() < 0.1
    for key in ("rgb", "alpha", "depth"):
        assert (out_n[key] - out_t[key]).abs().max() < 1e-4, key
    for name, gn, gt in zip(("means", "quats", "scales", "opacities", "colors"), grads_n, grads_t):
        assert gt.abs().max() > 0, name
        err = (gn - gt).abs().max() / gt.abs().max()
        assert err < 1e-3, (name, float(err))


def test_offscreen_splats_use_clamped_jacobian_and_match_twin():
    """Large splats centred outside the image (beyond 3DGS's 1.3x frustum clamp) reaching into it."""
    rng = np.random.default_rng(11)
    w, h, n = 40, 32, 40
    K = torch.tensor(intrinsics(w, h, 50.0))
    tan_x = 0.5 * w / float(K[0, 0])
    z = rng.uniform(1.5, 3.0, n)
    side = rng.choice([-1.0, 1.0], n)
    x = side * rng.uniform(1.35, 1.7, n) * tan_x * z  # tx / tz beyond the clamp limit
    y = rng.uniform(-0.5, 0.5, n) * z * 0.5
    params = [
        torch.tensor(np.stack([x, y, z], 1), dtype=F64),
        torch.tensor(rng.normal(size=(n, 4)), dtype=F64),
        torch.tensor(rng.uniform(0.2, 0.5, (n, 3)), dtype=F64),
        torch.tensor(rng.uniform(0.3, 1.0, n), dtype=F64),
        torch.tensor(rng.uniform(0, 1, (n, 3)), dtype=F64),
    ]
    scene = (params, torch.eye(4, dtype=F64), K, torch.zeros(3, dtype=F64), w, h)
    out_n, grads_n = loss_and_grads(*scene, backend="numba")
    _, grads_t = loss_and_grads(*scene, backend="torch")
    assert int(out_n["meta"]["visible"].sum()) > 10  # they do reach the image
    for name, gn, gt in zip(("means", "quats", "scales", "opacities", "colors"), grads_n, grads_t):
        assert (gn - gt).abs().max() / gt.abs().max() < 1e-3, name


def test_gradients_match_finite_differences():
    params, vm, K, bg, w, h = random_scene(7, n=24, width=24, height=20)
    _, grads = loss_and_grads(params, vm, K, bg, w, h, "numba", seed=3)

    def loss(ps):
        out = render(ps, vm, K, bg, w, h, "numba")
        g = torch.Generator().manual_seed(3)
        wr = torch.randn(h, w, 3, generator=g, dtype=F64)
        wa = torch.randn(h, w, generator=g, dtype=F64)
        wd = torch.randn(h, w, generator=g, dtype=F64)
        return float((out["rgb"] * wr).sum() + (out["alpha"] * wa).sum() + (out["depth"] * wd).sum())

    rng = np.random.default_rng(0)
    eps = 1e-6
    for i, name in enumerate(("means", "quats", "scales", "opacities", "colors")):
        flat_grad = grads[i].reshape(-1)
        # Probe the entries with the largest gradients (the ones that matter) plus random ones.
        idx = set(torch.topk(flat_grad.abs(), 4).indices.tolist()) | set(rng.integers(0, flat_grad.numel(), 3).tolist())
        for j in idx:
            plus = [p.clone() for p in params]
            minus = [p.clone() for p in params]
            plus[i].view(-1)[j] += eps
            minus[i].view(-1)[j] -= eps
            fd = (loss(plus) - loss(minus)) / (2 * eps)
            assert abs(fd - float(flat_grad[j])) <= 1e-5 * max(1.0, abs(fd)), (name, j, fd, float(flat_grad[j]))


@pytest.mark.parametrize("sigma_px", [0.35, 1.0])
def test_antialiased_low_pass_conserves_splat_mass(sigma_px):
    """A flat Gaussian facing the camera: the summed alpha (its mass in px) is o 2 pi sigma² with
    the compensated low-pass, o 2 pi (sigma² + 0.3) with the plain one (3DGS), analytically."""
    w, h, z, o = 31, 29, 2.0, 0.9
    K = torch.tensor(intrinsics(w, h, 40.0))
    s = sigma_px * z / float(K[0, 0])
    args = (torch.tensor([[0.003, -0.002, z]], dtype=F64), torch.tensor([[1.0, 0, 0, 0]], dtype=F64),
            torch.tensor([[s, s, 1e-5]], dtype=F64), torch.tensor([o], dtype=F64), torch.ones(1, 3, dtype=F64),
            torch.eye(4, dtype=F64), K, w, h)
    for antialiased, var in ((True, sigma_px**2), (False, sigma_px**2 + 0.3)):
        mass = float(rasterize(*args, backend="numba", antialiased=antialiased)["alpha"].sum())
        # the 3-sigma cutoff and the 1/255 alpha floor drop a little of the tail
        assert mass == pytest.approx(o * 2 * np.pi * var, rel=0.03), antialiased
        twin = float(rasterize(*args, backend="torch", antialiased=antialiased)["alpha"].sum())
        assert twin == pytest.approx(mass, abs=1e-9)


def test_antialiased_gradients_match_finite_differences():
    params, vm, K, bg, w, h = random_scene(5, n=20, width=22, height=18)
    g = torch.Generator().manual_seed(1)
    wr, wa = torch.randn(h, w, 3, generator=g, dtype=F64), torch.randn(h, w, generator=g, dtype=F64)

    def loss(ps):
        out = rasterize(*ps, vm, K, w, h, bg, near=NEAR, far=100.0, backend="numba", antialiased=True)
        return (out["rgb"] * wr).sum() + (out["alpha"] * wa).sum()

    ps = [p.detach().clone().requires_grad_(True) for p in params]
    grads = torch.autograd.grad(loss(ps), ps)
    eps = 1e-6
    for i, name in ((0, "means"), (1, "quats"), (2, "scales"), (3, "opacities")):
        flat = grads[i].reshape(-1)
        for j in torch.topk(flat.abs(), 3).indices.tolist():
            plus = [p.detach().clone() for p in params]
            minus = [p.detach().clone() for p in params]
            plus[i].view(-1)[j] += eps
            minus[i].view(-1)[j] -= eps
            fd = float(loss(plus) - loss(minus)) / (2 * eps)
            assert abs(fd - float(flat[j])) <= 1e-5 * max(1.0, abs(fd)), (name, j, fd, float(flat[j]))


def test_single_splat_matches_analytic_gaussian():
    """An isotropic Gaussian facing the camera: alpha = o exp(-d^2 / (2 (sigma_px^2 + 0.3)))."""
    w, h, z, s, o = 41, 33, 2.0, 0.02, 0.8
    K = torch.tensor(intrinsics(w, h, 30.0))
    f = float(K[0, 0])
    vm = torch.eye(4, dtype=F64)
    out = rasterize(
        torch.tensor([[0.0, 0.0, z]], dtype=F64), torch.tensor([[1.0, 0, 0, 0]], dtype=F64),
        torch.full((1, 3), s, dtype=F64), torch.tensor([o], dtype=F64), torch.tensor([[1.0, 0.5, 0.25]], dtype=F64),
        vm, K, w, h, backend="numba",
    )
    var = (f * s / z) ** 2 + 0.3
    v, u = np.mgrid[0:h, 0:w]
    d2 = (u - float(K[0, 2])) ** 2 + (v - float(K[1, 2])) ** 2
    ref = o * np.exp(-0.5 * d2 / var)
    ref[(d2 / var > 9.0) | (ref < 1 / 255)] = 0.0  # 3-sigma ellipse and the 1/255 floor
    np.testing.assert_allclose(out["alpha"].numpy(), ref, atol=1e-12)
    np.testing.assert_allclose(out["rgb"][..., 1].numpy(), 0.5 * ref, atol=1e-12)
    np.testing.assert_allclose(out["depth"].numpy(), z * ref, atol=1e-12)
    covered = out["alpha"] > 0
    assert torch.allclose(expected_depth(out)[covered], torch.tensor(z, dtype=F64))


def test_opaque_stack_terminates_and_hides_what_is_behind():
    """Opaque splats in front: alpha 0.99 each, compositing stops once T would drop below 1e-4."""
    w, h = 16, 16
    K = torch.tensor(intrinsics(w, h, 40.0))
    n = 4
    means = torch.tensor([[0.0, 0.0, 1.0 + 0.1 * i] for i in range(n)], dtype=F64)
    colors = torch.eye(3, dtype=F64)[[0, 1, 2, 2]]
    out = rasterize(means, torch.tensor([[1.0, 0, 0, 0]] * n, dtype=F64), torch.full((n, 3), 0.5, dtype=F64),
                    torch.ones(n, dtype=F64), colors, torch.eye(4, dtype=F64), K, w, h, backend="numba")
    c = out["rgb"][h // 2, w // 2]
    # Pixel near the centre: G ~ 1, so alpha = 0.99 for each splat. Splat 3 would give T = 1e-6 < 1e-4: dropped.
    assert torch.allclose(c, torch.tensor([0.99, 0.0099, 0.000099], dtype=F64), atol=1e-4)
    assert abs(float(out["alpha"][h // 2, w // 2]) - (1 - 1e-6)) < 1e-4


def test_feature_channels_and_background_gradient_match_twin():
    params, vm, K, _, w, h = random_scene(5, n=120)
    g = torch.Generator().manual_seed(5)
    params[4] = torch.rand(120, 5, generator=g, dtype=F64)  # 5 feature channels instead of RGB
    wr = torch.randn(h, w, 5, generator=g, dtype=F64)
    res = {}
    for backend in ("numba", "torch"):
        ps = [p.clone().requires_grad_(True) for p in params]
        bg = torch.rand(5, generator=torch.Generator().manual_seed(1), dtype=F64).requires_grad_(True)
        out = rasterize(*ps, vm, K, w, h, bg, near=NEAR, backend=backend)
        res[backend] = (out["rgb"].detach(), torch.autograd.grad((out["rgb"] * wr).sum(), [ps[4], bg, ps[0]]))
    assert (res["numba"][0] - res["torch"][0]).abs().max() < 1e-4
    for gn, gt in zip(res["numba"][1], res["torch"][1]):
        assert (gn - gt).abs().max() <= 1e-3 * gt.abs().max()


def test_thread_count_does_not_change_results():
    scene = random_scene(3, n=200)
    before = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        out1, g1 = loss_and_grads(*scene, backend="numba")
        numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
        out2, g2 = loss_and_grads(*scene, backend="numba")
    finally:
        numba.set_num_threads(before)
    assert torch.equal(out1["rgb"], out2["rgb"])
    for a, b in zip(g1, g2):
        assert torch.equal(a, b)


def test_float32_inputs_batch_and_auto_backend():
    params, vm, K, bg, w, h = random_scene(4, n=150)
    p32 = [p.float() for p in params]
    auto = rasterize(*p32, vm.float(), K.float(), w, h, bg.float(), near=NEAR)  # auto -> numba on CPU
    assert auto["meta"]["backend"] == ("gsplat" if _gsplat.available() else "numba")
    out32 = rasterize(*p32, vm.float(), K.float(), w, h, bg.float(), near=NEAR, backend="numba")
    assert out32["rgb"].dtype == torch.float32
    ref = render(params, vm, K, bg, w, h, "torch")
    assert (out32["rgb"].double() - ref["rgb"]).abs().mean() < 1e-5
    vms = torch.stack([vm, torch.tensor(look_at([0.3, -2.5, 0.4], [0, 0, 0]))])
    batch = rasterize_batch(*params, vms, torch.stack([K, K]), w, h, torch.stack([bg, bg]), near=NEAR, backend="numba")
    assert batch["rgb"].shape == (2, h, w, 3)
    assert torch.equal(batch["rgb"][0], render(params, vm, K, bg, w, h, "numba")["rgb"])


# -- mesh-aligned Gaussians ---------------------------------------------------------------------


def wavy_grid(n=5, seed=0):
    rng = np.random.default_rng(seed)
    u, v = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n))
    verts = np.stack([u + 0.05 * rng.normal(size=u.shape), v + 0.05 * rng.normal(size=u.shape),
                      0.2 * np.sin(3 * u) * np.cos(2 * v)], -1).reshape(-1, 3)
    faces = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, i * n + j + 1, (i + 1) * n + j, (i + 1) * n + j + 1
            faces += [[a, b, d], [a, d, c]]
    return torch.tensor(verts, dtype=F64), torch.tensor(faces)


def test_mesh_gaussians_sit_on_faces():
    verts, faces = wavy_grid()
    log_scales = torch.log(torch.rand(faces.shape[0], 2, dtype=F64) * 0.01 + 0.001)
    means, quats, scales = mesh_to_gaussians(verts, faces, log_scales)
    V, Fc = verts.numpy(), faces.numpy()
    tri = V[Fc]
    np.testing.assert_allclose(means.numpy(), tri.mean(1), atol=1e-14)
    R = quat_to_rotmat(quats).numpy()
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    np.testing.assert_allclose(R[:, :, 2], normal, atol=1e-12)
    # x axis along the longest edge of each face
    edges = np.roll(tri, -1, axis=1) - tri
    k = np.linalg.norm(edges, axis=2).argmax(1)
    e = edges[np.arange(len(k)), k]
    np.testing.assert_allclose(R[:, :, 0], e / np.linalg.norm(e, axis=1, keepdims=True), atol=1e-12)
    np.testing.assert_allclose(np.einsum("fij,fik->fjk", R, R), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(scales[:, :2].numpy(), np.exp(log_scales.numpy()))
    assert torch.all(scales[:, 2] == 1e-4)
    # The edge choice stays fixed when the mesh deforms.
    k0 = longest_edge_index(verts, faces)
    moved = verts * torch.tensor([1.0, 3.0, 1.0], dtype=F64)
    _, q1, _ = mesh_to_gaussians(moved, faces, log_scales, edge_index=k0)
    R1 = quat_to_rotmat(q1).numpy()
    tri1 = moved.numpy()[Fc]
    e1 = (np.roll(tri1, -1, axis=1) - tri1)[np.arange(len(k)), k0.numpy()]
    np.testing.assert_allclose(R1[:, :, 0], e1 / np.linalg.norm(e1, axis=1, keepdims=True), atol=1e-12)


def test_mesh_gaussians_vertex_gradient_matches_finite_differences():
    verts, faces = wavy_grid(4, seed=1)
    log_scales = torch.full((faces.shape[0], 2), -4.0, dtype=F64)
    k0 = longest_edge_index(verts, faces)
    g = torch.Generator().manual_seed(0)
    wm, wq, ws = (torch.randn(faces.shape[0], d, generator=g, dtype=F64) for d in (3, 4, 3))

    def loss(v):
        m, q, s = mesh_to_gaussians(v, faces, log_scales, edge_index=k0)
        return (m * wm).sum() + (q * wq).sum() + (s * ws).sum()

    v = verts.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(loss(v), v)
    fd = torch.zeros_like(verts)
    eps = 1e-6
    for i in range(verts.numel()):
        d = torch.zeros_like(verts).view(-1)
        d[i] = eps
        d = d.view_as(verts)
        fd.view(-1)[i] = (loss(verts + d) - loss(verts - d)) / (2 * eps)
    assert fd.abs().max() > 0.1
    torch.testing.assert_close(grad, fd, rtol=1e-6, atol=1e-7)


def test_rendered_mesh_gaussians_vertex_gradient_matches_finite_differences():
    """Photometric gradients reach the mesh: rasterizer backward composed with mesh_to_gaussians."""
    verts, faces = wavy_grid(4, seed=2)
    verts = verts - verts.mean(0)
    nf = faces.shape[0]
    log_scales = torch.full((nf, 2), np.log(0.12), dtype=F64)
    k0 = longest_edge_index(verts, faces)
    g = torch.Generator().manual_seed(4)
    colors = torch.rand(nf, 3, generator=g, dtype=F64)
    opac = torch.full((nf,), 0.7, dtype=F64)
    w, h = 32, 24
    K = torch.tensor(intrinsics(w, h, 50.0))
    vm = torch.tensor(look_at([0.4, -0.6, 1.8], [0.0, 0.0, 0.0]))
    wr = torch.randn(h, w, 3, generator=g, dtype=F64)

    def loss(v):
        m, q, s = mesh_to_gaussians(v, faces, log_scales, edge_index=k0)
        out = rasterize(m, q, s, opac, colors, vm, K, w, h, backend="numba")
        return (out["rgb"] * wr).sum() + out["depth"].sum()

    v = verts.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(loss(v), v)
    eps = 1e-6
    for i in torch.topk(grad.abs().view(-1), 6).indices.tolist():
        d = torch.zeros(verts.numel(), dtype=F64)
        d[i] = eps
        d = d.view_as(verts)
        fd = float(loss(verts + d) - loss(verts - d)) / (2 * eps)
        assert abs(fd - float(grad.view(-1)[i])) <= 1e-5 * max(1.0, abs(fd)), (i, fd, float(grad.view(-1)[i]))


def test_tracker_backend_option_resolves_and_refuses_what_cannot_run():
    """``track --splat-backend``: "auto" is the numba kernels on a CPU machine (gsplat with CUDA),
    and asking for gsplat where it cannot run is one clear message, not a CUDA traceback."""
    from physavatar.errors import PhysavatarError
    from physavatar.stages.base import apply_options
    from physavatar.stages.track import TrackConfig
    from physavatar.stages.track.gaussians import MeshGaussians

    verts, faces = wavy_grid()
    model = MeshGaussians.init(verts.float().numpy(), faces.numpy(), backend=TrackConfig().splat_backend)
    assert model.backend == ("gsplat" if _gsplat.available() else "numba")
    cfg = apply_options(TrackConfig(), {"splat_backend": "torch"})
    assert cfg.splat_backend == "torch"
    with pytest.raises(PhysavatarError, match="--splat-backend: 'cuda' is not auto, numba, gsplat or torch"):
        apply_options(TrackConfig(), {"splat_backend": "cuda"})
    if not _gsplat.available():
        with pytest.raises(PhysavatarError, match="--splat-backend: gsplat needs a CUDA device"):
            apply_options(TrackConfig(), {"splat_backend": "gsplat"})
