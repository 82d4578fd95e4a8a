"""The Anny wrapper: rest pose, rigid root motion, skinning weights, LBS consistency, collider."""

import numpy as np
import pytest

from physavatar.body import BodyModel, BodyShape, axis_angle_to_matrix, linear_blend_skinning


@pytest.fixture(scope="module")
def body():
    return BodyModel(topology="collider")


def test_rest_pose_gives_rest_mesh(body):
    R, t = body.rest_pose(2)
    p = body.pose(R, t)
    assert np.abs(p.vertices - body.rest_vertices).max() < 1e-9
    assert np.abs(p.joints - body.rest_joints).max() < 1e-9
    assert np.allclose(p.bone_transforms, np.eye(4), atol=1e-9)
    assert abs(body.rest_vertices[:, 2].min()) < 0.01  # standing on the floor (collider ~ full body)


def test_root_transform_moves_every_vertex_rigidly(body):
    rng = np.random.default_rng(0)
    R, t = body.rest_pose(3)
    R[:, 0] = rng.normal(size=(3, 3)) * 0.7
    t[:] = rng.normal(size=(3, 3)) * 0.3
    p = body.pose(R, t)
    h = body.rest_joints[0]
    for k in range(3):
        Rm = axis_angle_to_matrix(R[k, 0])
        expect = (body.rest_vertices - h) @ Rm.T + h + t[k]
        assert np.abs(p.vertices[k] - expect).max() < 1e-9
        # distances between vertices are preserved
        i, j = rng.integers(0, len(body.rest_vertices), (2, 50))
        d0 = np.linalg.norm(body.rest_vertices[i] - body.rest_vertices[j], axis=1)
        d1 = np.linalg.norm(p.vertices[k, i] - p.vertices[k, j], axis=1)
        assert np.abs(d0 - d1).max() < 1e-9


def test_skinning_weights_are_a_partition_of_unity(body):
    W = body.skinning_weights
    assert W.shape == (len(body.rest_vertices), len(body.bone_names))
    assert (W >= 0).all()
    assert np.abs(W.sum(1) - 1).max() < 1e-6


def test_exported_weights_and_transforms_reproduce_the_pose(body):
    """Skinning with our weights and bone transforms (an independent LBS) gives Anny's vertices."""
    rng = np.random.default_rng(1)
    R, t = body.rest_pose(2)
    R += rng.normal(size=R.shape) * 0.2
    p = body.pose(R, t)
    v = linear_blend_skinning(body.rest_vertices, body.skinning_weights, p.bone_transforms)
    assert np.abs(v - p.vertices).max() < 1e-6


def test_elbow_rotation_bends_the_forearm_about_the_elbow(body):
    names = body.bone_names
    R, t = body.rest_pose(1)
    e = names.index("lowerarm01.L")
    R[0, e] = [0.0, 0.0, 0.5]
    p = body.pose(R, t)
    J0, J1 = body.rest_joints, p.joints[0]
    w = names.index("wrist.L")
    # the elbow stays, the wrist rotates about it by 0.5 rad about z
    assert np.allclose(J1[e], J0[e], atol=1e-9)
    Rz = axis_angle_to_matrix(np.array([0, 0, 0.5]))
    assert np.allclose(J1[w] - J1[e], Rz @ (J0[w] - J0[e]), atol=1e-9)


def test_collider_follows_the_full_body():
    """The decimated collider, posed the same way, stays on the full body's surface."""
    from scipy.spatial import cKDTree

    full, col = BodyModel(topology="full"), BodyModel(topology="collider")
    rng = np.random.default_rng(2)
    R, t = full.rest_pose(1)
    for b in ("upperarm01.L", "upperleg01.R", "spine03"):
        R[0, full.bone_names.index(b)] = rng.normal(size=3) * 0.4
    t[0] = [0.1, -0.2, 0.05]
    pf, pc = full.pose(R, t), col.pose(R, t)
    d, _ = cKDTree(pf.vertices[0]).query(pc.vertices[0])
    assert np.median(d) < 0.01 and np.percentile(d, 99) < 0.04


def test_shape_changes_height():
    tall = BodyModel(BodyShape(height=0.9), topology="collider")
    short = BodyModel(BodyShape(height=0.1), topology="collider")
    h = lambda b: b.rest_vertices[:, 2].max() - b.rest_vertices[:, 2].min()
    assert h(tall) > h(short) + 0.1
    with pytest.raises(ValueError):
        BodyShape(height=1.5)


def test_loading_anny_keeps_a_redirected_stdout():
    # anny's Warp module sets sys.stdout = sys.__stdout__ on import; under typer's CliRunner
    # that dropped (and closed) the runner's capture stream. A fresh interpreter, so anny is
    # imported for the first time under the redirect.
    import subprocess
    import sys

    code = ("import io, sys\n"
            "from physavatar.body.model import _import_anny\n"
            "buf = io.StringIO(); sys.stdout = buf\n"
            "_import_anny()\n"
            "print('captured')\n"
            "sys.__stdout__.write(f'same={sys.stdout is buf} closed={buf.closed} text={buf.getvalue()!r}')\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.endswith("same=True closed=False text='captured\\n'"), r.stdout
