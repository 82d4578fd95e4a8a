"""Skinning-weight transfer (paper A.2): closest-point where it is trustworthy, inpainting elsewhere."""

import numpy as np
import pytest

from physavatar.body import BodyModel
from physavatar.body.transfer import cotangent_laplacian, inpaint_weights, transfer_skinning_weights


@pytest.fixture(scope="module")
def bodies():
    return BodyModel(topology="collider"), BodyModel(topology="coarse")


def test_cotangent_laplacian_is_exact_on_linear_functions():
    # on a flat grid, L applied to a linear function vanishes at interior vertices
    n = 6
    u, v = np.meshgrid(np.arange(n), np.arange(n))
    V = np.stack([u.ravel(), v.ravel(), np.zeros(n * n)], 1).astype(float)
    F = []
    for i in range(n - 1):
        for j in range(n - 1):
            a = i * n + j
            F += [[a, a + 1, a + n + 1], [a, a + n + 1, a + n]]
    L, M = cotangent_laplacian(V, np.array(F))
    f = 2.0 * V[:, 0] - 3.0 * V[:, 1] + 1.0
    interior = (u.ravel() > 0) & (u.ravel() < n - 1) & (v.ravel() > 0) & (v.ravel() < n - 1)
    assert np.abs((L @ f)[interior]).max() < 1e-10
    assert abs(M.diagonal().sum() - (n - 1) ** 2) < 1e-9  # total area


def test_transfer_from_anny_to_another_topology(bodies):
    """The decimated body gets weights close to Anny's own for it, from the finer body."""
    col, coarse = bodies
    W, matched = transfer_skinning_weights(coarse.rest_vertices, coarse.faces, col.rest_vertices, col.faces,
                                           col.skinning_weights)
    assert matched.mean() > 0.9
    assert np.allclose(W.sum(1), 1) and (W >= 0).all()
    err = np.abs(W - coarse.skinning_weights).sum(1)  # L1 per vertex, in [0, 2]
    assert np.median(err) < 0.3


def test_inpainting_recovers_hidden_weights(bodies):
    col, _ = bodies
    truth = col.skinning_weights
    rng = np.random.default_rng(0)
    # hide a 10 cm ball of vertices around the left shoulder and everything within 2 cm of a random set
    c = col.rest_joints[col.bone_names.index("upperarm01.L")]
    hidden = np.linalg.norm(col.rest_vertices - c, axis=1) < 0.10
    hidden |= rng.random(len(hidden)) < 0.1
    W = truth.copy()
    W[hidden] = 0.0
    out = inpaint_weights(col.rest_vertices, col.faces, W, ~hidden)
    assert np.allclose(out[~hidden], truth[~hidden])
    err = np.abs(out[hidden] - truth[hidden]).sum(1)
    uniform = np.abs(1.0 / truth.shape[1] - truth[hidden]).sum(1)
    assert err.mean() < 0.35 and err.mean() < 0.3 * uniform.mean()
    # skinning with the inpainted weights moves the hidden vertices like the true weights do
    R, t = col.rest_pose(1)
    R[0, col.bone_names.index("upperarm01.L")] = [0.0, 0.6, 0.0]
    p = col.pose(R, t)
    from physavatar.body import linear_blend_skinning

    v_in = linear_blend_skinning(col.rest_vertices, out, p.bone_transforms)[0]
    assert np.linalg.norm(v_in[hidden] - p.vertices[0, hidden], axis=1).mean() < 0.02
