"""benchmarks/prepare_body_parts.py's measurements on bodies with known answers (session 34)."""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from physavatar.body.model import BodyShape  # noqa: E402
from physavatar.capture import BodyPoses  # noqa: E402
from prepare_body_parts import GROUPS, body_errors, mix  # noqa: E402


def poses(shape=0.5, turn=0.0, shift=(0.0, 0.0, 0.0)):
    """Anny's collider at rest over two frames, the left thigh turned by ``turn`` rad about x,
    moved by ``shift`` [m]."""
    from physavatar.body import BodyModel

    names = BodyModel(BodyShape.from_array(np.full(6, shape)), topology="collider").bone_names
    rot = np.zeros((2, len(names), 3))
    rot[:, names.index("upperleg01.L"), 0] = turn
    return BodyPoses(BodyShape.from_array(np.full(6, shape)), list(names), rot, np.tile(shift, (2, 1)), "collider")


def test_body_errors_of_a_pure_shift_are_the_shift_everywhere():
    true = poses()
    e = body_errors(true, poses(shift=(0.01, 0.0, 0.0)))
    assert np.allclose(e["mean_mm_per_frame"], 10.0, atol=1e-3) and abs(e["frame0_mean_mm"] - 10.0) < 1e-3
    for r in e["frame0_by_region"].values():
        assert abs(r["frame0_mean_mm"] - 10.0) < 0.01 and np.allclose(r["frame0_mean_offset_mm"], [10, 0, 0], atol=0.06)
    assert body_errors(true, true)["mean_mm"] == 0.0


def test_mix_takes_exactly_the_parts_asked_from_the_truth():
    fit, true = poses(shape=0.45, turn=0.3, shift=(0.02, 0, 0)), poses()
    legs = mix(fit, true, bones=GROUPS["legs"])
    assert np.abs(legs.rotations).max() == 0.0 and legs.shape == fit.shape
    assert np.array_equal(legs.root_translation, fit.root_translation)
    e = body_errors(true, mix(fit, true, shape=True, translation=True, bones=tuple(true.bone_names)))
    assert e["mean_mm"] == 0.0
    # the turned thigh moves the thighs and lower legs, not the head
    r = body_errors(true, mix(fit, true, shape=True, translation=True))["frame0_by_region"]
    assert r["head/neck"]["frame0_mean_mm"] < 1e-6 and r["lower legs/feet"]["frame0_mean_mm"] > 50
