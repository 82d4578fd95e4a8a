"""The body between two frames skinned from the poses (body.between.PoseBetween): a turning
body part keeps its shape along the arc, where the vertex-by-vertex chord cuts inside it; the
frames themselves are met bit for bit (sim.simulate.between_bodies)."""

import numpy as np
import pytest

from physavatar.body import BodyModel, axis_angle_to_matrix
from physavatar.body.between import PoseBetween
from physavatar.sim.simulate import between_bodies

S = np.array([0.25, 0.5, 0.75])


@pytest.fixture(scope="module")
def body():
    return BodyModel(topology="collider")


def test_a_spinning_body_keeps_every_vertex_at_its_radius_in_between(body):
    """The root turned by 0.6 rad about z in one frame (2 turns/s at 25 fps is 0.5 rad): the
    in-between bodies are the rest body turned by s·0.6 about the vertical through the root
    (analytic: Rodrigues), every vertex at its radius; the chord between the two frames
    shrinks the radius by r (1 − cos(θ/2)) half-way (1.7 cm at r = 0.4 m)."""
    theta = 0.6
    rot = np.zeros((2, len(body.bone_names), 3))
    rot[1, 0] = [0.0, 0.0, theta]
    tr = np.zeros((2, 3))
    frames = body.pose(rot, tr)
    pivot = frames.joints[0, 0]
    between = PoseBetween(body, rot, tr)
    B = between(1, S)
    radius = lambda V: np.linalg.norm((V - pivot)[:, :2], axis=1)  # noqa: E731
    r = radius(frames.vertices[0])
    for k, s in enumerate(S):
        expected = pivot + (frames.vertices[0] - pivot) @ axis_angle_to_matrix(np.array([0, 0, s * theta])).T
        np.testing.assert_allclose(B[k], expected, atol=1e-9)
        np.testing.assert_allclose(radius(B[k]), r, atol=1e-9)
    chord = 0.5 * (frames.vertices[0] + frames.vertices[1])
    np.testing.assert_allclose(radius(chord), r * np.cos(theta / 2), atol=1e-9)
    assert (r - radius(chord)).max() > 0.015  # the chord's 1.7 cm, gone


def test_a_fast_knee_flex_turns_the_shank_about_the_knee_in_between(body):
    """The left knee flexed by 1.2 rad in one frame: the vertices the shank and foot alone carry
    turn rigidly about the knee's axis in between, by s·1.2, at their distance from the axis;
    the chord brings them closer to it by r (1 − cos 0.6) half-way, into the crease."""
    names = body.bone_names
    knee = names.index("lowerleg01.L")
    below = np.zeros(len(names), bool)
    for b in range(len(names)):  # the knee's subtree (parents come first)
        below[b] = b == knee or (body.parents[b] >= 0 and below[body.parents[b]])
    rigid = body.skinning_weights[:, below].sum(1) > 1 - 1e-12
    assert rigid.sum() > 20
    rot = np.zeros((2, len(names), 3))
    rot[1, knee] = [1.2, 0.0, 0.0]
    tr = np.zeros((2, 3))
    frames = body.pose(rot, tr)
    joint = frames.joints[0, knee]
    B = PoseBetween(body, rot, tr)(1, S)
    radius = lambda V: np.linalg.norm((V - joint)[:, 1:], axis=1)  # from the knee's axis (x)  # noqa: E731
    r = radius(frames.vertices[0, rigid])
    for k, s in enumerate(S):
        expected = joint + (frames.vertices[0, rigid] - joint) @ axis_angle_to_matrix(np.array([1.2 * s, 0, 0])).T
        np.testing.assert_allclose(B[k, rigid], expected, atol=1e-9)
        np.testing.assert_allclose(radius(B[k, rigid]), r, atol=1e-9)
    chord = 0.5 * (frames.vertices[0, rigid] + frames.vertices[1, rigid])
    np.testing.assert_allclose(radius(chord), r * np.cos(0.6), atol=1e-9)
    assert (r - radius(chord)).max() > 0.08  # the foot, 8 cm into the crease half-way


def test_the_frames_are_met_bit_for_bit_and_corrections_blended(body):
    """s = 0 and 1 of PoseBetween are the frames to round-off; the in-between sequence the
    simulator steps through starts and ends at the given frames exactly, and a correction made
    to a frame after skinning (an uncollapsed vertex, a clearance) is blended in linearly."""
    rng = np.random.default_rng(0)
    rot = rng.normal(0, 0.3, (3, len(body.bone_names), 3))
    tr = rng.normal(0, 0.1, (3, 3))
    frames = body.pose(rot, tr).vertices
    between = PoseBetween(body, rot, tr)
    ends = between(2, [0.0, 1.0])
    np.testing.assert_allclose(ends, frames[1:3], atol=1e-12)
    given1 = frames[2].copy()
    given1[:10] += 0.003  # a correction after skinning
    n = 4
    B = between_bodies(between, 2, n, frames[1], given1)
    assert B.shape == (n + 1,) + frames[1].shape
    assert np.array_equal(B[0], frames[1]) and np.array_equal(B[-1], given1)
    skinned = between(2, np.arange(n + 1) / n)
    for k in range(1, n):
        w = k / n
        np.testing.assert_allclose(B[k] - skinned[k], (1 - w) * (frames[1] - skinned[0]) + w * (given1 - skinned[-1]),
                                   atol=1e-12)
    assert np.abs(B[1:-1, :10] - skinned[1:-1, :10]).max() > 0.0005  # the correction, blended
    assert np.abs(B[1:-1] - ((1 - np.arange(1, n) / n)[:, None, None] * frames[1]
                             + (np.arange(1, n) / n)[:, None, None] * given1)).max() > 1e-3  # not the chord


def test_poses_must_match_the_body(body):
    with pytest.raises(ValueError, match="rotations"):
        PoseBetween(body, np.zeros((2, 3, 3)), np.zeros((2, 3)))
    with pytest.raises(IndexError):
        PoseBetween(body, *body.rest_pose(2))(0, [0.5])


def test_simulate_poses_the_in_betweens_from_the_motion_it_simulates(body, tmp_path):
    """`simulate --motion` (stages.simulate._on_motion) hands the simulator the poses of its
    collider sequence, warm-up transition included: s = 0 and 1 of every frame are its frames."""
    from physavatar.body import Motion, builtin_motion
    from physavatar.data.material import resolve_material
    from physavatar.sim import SimSettings
    from physavatar.stages import simulate as stage

    twist = builtin_motion("twist", body.bone_names, 25.0, 1.0)
    Motion("clip", 25.0, twist.bone_names, twist.rotations[12:16], twist.root_translation[12:16]).save(tmp_path / "c.npz")
    cfg = stage.SimulateConfig(warmup=0.2, edge_length=0.05, preview=False)
    _, bodies, _, n_warm, *_, between = stage._on_motion("skirt", str(tmp_path / "c.npz"), 25.0, cfg,
                                                         resolve_material("cotton"), SimSettings(), None)
    assert n_warm == 5 and len(between) == len(bodies) == 9
    for f in range(1, len(bodies)):
        np.testing.assert_allclose(between(f, [0.0, 1.0]), bodies[f - 1:f + 1], atol=1e-12)


def test_the_skinned_in_betweens_are_the_default():
    """On by default since session 31 (simulate, animate and the animate function evaluate calls);
    --linear-between turns them off."""
    import inspect

    from physavatar.stages.animate import AnimateConfig, animate
    from physavatar.stages.simulate import SimulateConfig

    assert SimulateConfig().skinned_between and AnimateConfig().skinned_between
    assert inspect.signature(animate).parameters["skinned_between"].default is True
