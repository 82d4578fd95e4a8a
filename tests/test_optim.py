"""physavatar.optim against independent references: torch's Adam, an uninterrupted run, and
linear least squares solved in closed form."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from physavatar.optim import Adam, lm_step
from physavatar.optim.uniform import AdamUniform

# an ill-conditioned convex quadratic f(x) = ½ (x − c)ᵀ A (x − c)
_rng = np.random.default_rng(7)
_Q = np.linalg.qr(_rng.standard_normal((5, 5)))[0]
A = _Q @ np.diag([100.0, 10.0, 1.0, 0.3, 0.01]) @ _Q.T
C = _rng.standard_normal(5)


def grad(x):
    return A @ (x - C)


def test_adam_takes_torch_adams_steps():
    x0 = np.linspace(-1.0, 1.0, 5)
    lr = 0.05
    xt = torch.tensor(x0, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.Adam([xt], lr=lr, betas=(0.9, 0.999), eps=1e-8)
    adam = Adam({"x": x0.shape})
    params = {"x": x0.copy()}
    for _ in range(200):
        opt.zero_grad()
        xt.grad = torch.from_numpy(grad(xt.detach().numpy()))
        opt.step()
        adam.step(params, {"x": grad(params["x"])}, lr)
        np.testing.assert_allclose(params["x"], xt.detach().numpy(), rtol=1e-9, atol=1e-12)
    assert np.linalg.norm(params["x"] - C) < np.linalg.norm(x0 - C)  # and it descends


def test_adam_groups_are_independent_and_take_their_own_rates():
    """Two named groups with different rates step like two separate optimizers; a group without
    a gradient in a step is left alone."""
    a, b = Adam({"u": (5,), "w": (2, 3)}), Adam({"u": (5,)})
    c = Adam({"w": (2, 3)})
    p = {"u": np.zeros(5), "w": np.ones((2, 3))}
    pu, pw = {"u": np.zeros(5)}, {"w": np.ones((2, 3))}
    for k in range(5):
        gu, gw = grad(p["u"]), np.full((2, 3), (-1.0) ** k) * np.arange(6).reshape(2, 3)
        a.step(p, {"u": gu, "w": gw}, {"u": 0.1, "w": np.array([0.01, 0.02, 0.03])})
        b.step(pu, {"u": grad(pu["u"])}, 0.1)
        c.step(pw, {"w": gw}, np.array([0.01, 0.02, 0.03]))
    np.testing.assert_array_equal(p["u"], pu["u"])
    np.testing.assert_array_equal(p["w"], pw["w"])
    frozen = p["w"].copy()
    a.step(p, {"u": grad(p["u"])}, {"u": 0.1, "w": 0.5})
    np.testing.assert_array_equal(p["w"], frozen)


def test_adam_continued_from_its_state_dict_equals_an_uninterrupted_run(tmp_path):
    def run(n, adam, x):
        for _ in range(n):
            adam.step(x, {"x": grad(x["x"])}, 0.03)
        return x

    whole_adam = Adam({"x": (5,)})
    whole = run(60, whole_adam, {"x": np.zeros(5)})

    first = Adam({"x": (5,)})
    x = run(25, first, {"x": np.zeros(5)})
    np.savez(tmp_path / "ckpt.npz", x=x["x"], **first.state_dict())
    first.step(x, {"x": np.ones(5)}, 1.0)  # the saved state is a copy: later steps do not change it
    z = dict(np.load(tmp_path / "ckpt.npz"))
    resumed = Adam({"x": (5,)})
    resumed.load_state_dict(z)
    assert resumed.t == 25
    rest = run(35, resumed, {"x": z["x"]})
    np.testing.assert_array_equal(rest["x"], whole["x"])
    for k, v in whole_adam.state_dict().items():
        np.testing.assert_array_equal(resumed.state_dict()[k], v)

    with pytest.raises(ValueError):
        Adam({"x": (4,)}).load_state_dict(z)
    with pytest.raises(KeyError):
        Adam({"y": (5,)}).load_state_dict(z)


def test_adam_uniform_with_quantile_zero_is_per_row_adam():
    """quantile 0: every row's normaliser is its own RMS, i.e. row-wise Adam; on a single column
    that is per-entry Adam, which torch's Adam computes independently."""
    x0 = torch.linspace(-1.0, 1.0, 5, dtype=torch.float64).reshape(5, 1)
    xu, xa = x0.clone().requires_grad_(True), x0.clone().requires_grad_(True)
    ou, oa = AdamUniform([xu], lr=0.05, quantile=0.0), torch.optim.Adam([xa], lr=0.05)
    for _ in range(50):
        for x, o in ((xu, ou), (xa, oa)):
            o.zero_grad()
            x.grad = torch.from_numpy(grad(x.detach().numpy().ravel())).reshape(5, 1)
            o.step()
    torch.testing.assert_close(xu, xa, rtol=1e-9, atol=1e-9)


def test_lm_step_solves_a_linear_least_squares_problem_in_one_step():
    """r(θ) = Jθ − b is linear: with λ → 0 and a box that does not bind, one step lands on the
    least-squares solution, and the predicted decrease is the actual one."""
    rng = np.random.default_rng(1)
    J = rng.standard_normal((30, 3)) * [10.0, 1.0, 0.1]
    x_star = np.array([0.3, -0.2, 0.1])
    b = J @ x_star + 0.01 * rng.standard_normal(30)
    theta = np.zeros(3)
    res = J @ theta - b
    lo, hi = np.full(3, -10.0), np.full(3, 10.0)
    new, predicted = lm_step(J, res, theta, lo, hi, lam=1e-12, radius=10.0)
    ls = np.linalg.lstsq(J, b, rcond=None)[0]
    np.testing.assert_allclose(new, ls, rtol=1e-7, atol=1e-9)
    after = J @ new - b
    assert predicted == pytest.approx(res @ res - after @ after, rel=1e-9)


def test_lm_step_respects_bounds_and_radius():
    rng = np.random.default_rng(2)
    J = rng.standard_normal((20, 2))
    b = J @ np.array([3.0, -3.0])
    theta = np.array([0.0, -0.9])
    lo, hi = np.array([-1.0, -1.0]), np.array([1.0, 1.0])
    for radius in (0.05, 0.5, 5.0):
        new, predicted = lm_step(J, J @ theta - b, theta, lo, hi, lam=1e-3, radius=radius)
        assert np.all(new >= lo) and np.all(new <= hi)
        assert np.max(np.abs(new - theta)) <= radius + 1e-12
        assert predicted > 0
    # a parameter on its bound with the minimum beyond it stays there, the other one still moves
    theta = np.array([0.0, -1.0])
    new, _ = lm_step(J, J @ theta - b, theta, lo, hi, lam=1e-3, radius=0.5)
    assert new[1] == -1.0 and new[0] > 0.0
