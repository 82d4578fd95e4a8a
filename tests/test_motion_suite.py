"""The motion suite's hands-on-hips stress pose (benchmarks/motion_suite.py): an akimbo pose whose
hands are pressed to the waist while the forearms stay clear of it, checked on the posed body."""

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import motion_suite as ms  # noqa: E402
from physavatar.body import BodyModel  # noqa: E402


@pytest.fixture(scope="module")
def body():
    return BodyModel(topology="collider")


def test_akimbo_rotations_put_the_wrist_where_asked(body):
    """Forward kinematics of the rotations (Anny's, not ours) reaches the asked wrist position,
    with the arm's bone lengths kept and the elbow out to the side of the shoulder."""
    names = body.bone_names
    J0 = body.pose(*body.rest_pose()).joints[0]
    target = J0[names.index("root")] + [0.16, 0.04, 0.13]
    R = ms._pose_arms(body, ms._akimbo_rotations(body, target))
    J = body.pose(R, np.zeros((1, 3))).joints[0]
    j = {n: J[names.index(n)] for n in ("upperarm01.L", "lowerarm01.L", "wrist.L", "wrist.R")}
    np.testing.assert_allclose(j["wrist.L"], target, atol=1e-6)
    np.testing.assert_allclose(j["wrist.R"], target * [-1, 1, 1], atol=2e-3)  # mirror (Anny ~symmetric)
    assert j["lowerarm01.L"][0] - j["upperarm01.L"][0] > 0.15  # elbow out
    assert j["lowerarm01.L"][2] < j["upperarm01.L"][2]  # and below the shoulder


def test_hands_pressed_to_the_waist_forearms_clear(body):
    R = ms._pose_arms(body, ms._hands_on_hips_pose(body))
    gaps = ms.hand_trunk_gaps(body, R, np.zeros((1, 3)))
    assert abs(gaps["hand"][0] - ms.HANDS_ON_HIPS_GAP) < 2e-4
    assert gaps["lowerarm"][0] > 0.03  # a cloth layer needs ~2 mm; the straight-arm pose left 0.4 mm
