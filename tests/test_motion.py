"""Motions: built-ins, npz round trip, resampling, BVH import with known joint angles."""

import numpy as np
import pytest

from physavatar.body import BUILTIN, BodyModel, Motion, axis_angle_to_matrix, builtin_motion
from physavatar.body.bvh import import_bvh, read_bvh, write_bvh
from physavatar.errors import PhysavatarError


@pytest.fixture(scope="module")
def body():
    return BodyModel(topology="collider")


@pytest.mark.parametrize("name", list(BUILTIN))
def test_builtin_motions_start_at_rest_and_are_smooth(body, name):
    m = builtin_motion(name, body.bone_names, fps=25, duration=3.0)
    assert m.frames == 76
    assert np.abs(m.rotations[0]).max() < 1e-12 and np.abs(m.root_translation[0]).max() < 1e-12
    assert np.abs(m.rotations).max() > 0.05  # it moves
    # smooth: no frame-to-frame jump above 0.35 rad at 25 fps (the jump's crouch is the fastest)
    assert np.abs(np.diff(m.rotations, axis=0)).max() < 0.35
    p = m.pose(body)
    assert np.isfinite(p.vertices).all()
    # the body stays near the floor (no motion sinks it or lifts it by more than a jump)
    assert p.vertices[:, :, 2].min() > -0.05


def test_npz_roundtrip_and_errors(body, tmp_path):
    m = builtin_motion("walk", body.bone_names, duration=1.0)
    m.save(tmp_path / "w.npz")
    r = Motion.load(tmp_path / "w.npz")
    assert r.fps == m.fps and r.bone_names == m.bone_names
    assert np.array_equal(r.rotations, m.rotations)
    np.savez(tmp_path / "bad.npz", fps=25.0, bone_names=np.array(["root"]), rotations=np.zeros((3, 2, 3)),
             root_translation=np.zeros((3, 3)))
    with pytest.raises(PhysavatarError, match="bad.npz"):
        Motion.load(tmp_path / "bad.npz")


def test_resample_keeps_the_motion(body):
    m = builtin_motion("dance", body.bone_names, fps=100, duration=2.0)
    r = m.resample(25)
    assert r.frames == 51
    # every 4th frame of the 100 fps motion is a 25 fps frame
    assert np.abs(axis_angle_to_matrix(r.rotations) - axis_angle_to_matrix(m.rotations[::4])).max() < 1e-9
    assert np.allclose(r.root_translation, m.root_translation[::4])


def _cmu_like_bvh(path, knee_deg, elbow_deg, frames=3):
    """A small CMU-style skeleton: y up, facing +z, left at +x, arms hanging down."""
    names = ["Hips", "LeftHip", "LeftKnee", "LeftAnkle", "RightHip", "RightKnee", "RightAnkle",
             "Chest", "Neck", "Head", "LeftShoulder", "LeftElbow", "LeftWrist", "RightShoulder",
             "RightElbow", "RightWrist"]
    parents = [-1, 0, 1, 2, 0, 4, 5, 0, 7, 8, 7, 10, 11, 7, 13, 14]
    offsets = [[0, 0, 0], [1.7, -1.5, 0], [0, -7.5, 0], [0, -7.5, 0], [-1.7, -1.5, 0], [0, -7.5, 0],
               [0, -7.5, 0], [0, 4, 0], [0, 4, 0], [0, 1.5, 0], [3, 3, 0], [0, -5, 0], [0, -4.5, 0],
               [-3, 3, 0], [0, -5, 0], [0, -4.5, 0]]
    ch = [["Xposition", "Yposition", "Zposition", "Zrotation", "Yrotation", "Xrotation"]] + \
         [["Zrotation", "Yrotation", "Xrotation"]] * (len(names) - 1)
    data = np.zeros((frames, 6 + 3 * (len(names) - 1)))
    data[:, 1] = 17.0
    knee = 6 + 3 * (names.index("LeftKnee") - 1)
    elbow = 6 + 3 * (names.index("LeftElbow") - 1)
    data[1:, knee + 2] = knee_deg  # X rotation: flexes the knee (shin goes back, towards -z)
    data[1:, elbow + 2] = -elbow_deg  # negative X: forearm swings forward (+z)
    write_bvh(path, names, parents, offsets, ch, data, 1 / 30)


def test_bvh_import_reproduces_joint_angles(body, tmp_path):
    _cmu_like_bvh(tmp_path / "m.bvh", knee_deg=40.0, elbow_deg=70.0)
    b = read_bvh(tmp_path / "m.bvh")
    assert b.data.shape == (3, 6 + 45) and abs(b.fps - 30) < 1e-3
    m = import_bvh(tmp_path / "m.bvh", body)
    p = m.pose(body)
    J = p.joints
    n = body.bone_names.index
    hip, knee, ankle = n("upperleg01.L"), n("lowerleg01.L"), n("foot.L")
    sh, el, wr = n("upperarm01.L"), n("lowerarm01.L"), n("wrist.L")

    def angle(a, b, c, t):
        u, v = J[t, b] - J[t, a], J[t, c] - J[t, b]
        # clipped: straight limbs give a cosine a rounding error above 1 on some CPUs (then NaN)
        return np.degrees(np.arccos(np.clip(np.dot(u, v) / np.linalg.norm(u) / np.linalg.norm(v), -1.0, 1.0)))

    # frame 0: the BVH rest (straight legs, arms hanging straight down) is reproduced
    assert angle(hip, knee, ankle, 0) < 3.0
    assert angle(sh, el, wr, 0) < 3.0
    upper = J[0, el] - J[0, sh]
    assert upper[2] / np.linalg.norm(upper) < -0.97  # upper arm hangs down
    # frame 1: knee flexed by 40 degrees, shin going backwards (+y in Anny: the body faces -y)
    assert abs(angle(hip, knee, ankle, 1) - 40.0) < 3.0
    assert (J[1, ankle] - J[1, knee])[1] > 0.1 * np.linalg.norm(J[1, ankle] - J[1, knee])
    # elbow flexed by 70 degrees, forearm going forwards (-y)
    assert abs(angle(sh, el, wr, 1) - 70.0) < 3.0
    assert (J[1, wr] - J[1, el])[1] < 0
    # standing on the floor, at the origin
    assert abs(p.vertices[0, :, 2].min()) < 0.05
    assert np.abs(m.root_translation[:, :2]).max() < 1e-9


def test_bvh_mapping_override_and_errors(body, tmp_path):
    _cmu_like_bvh(tmp_path / "m.bvh", 40.0, 0.0)
    m = import_bvh(tmp_path / "m.bvh", body, mapping={"LeftKnee": ""})  # un-map the knee
    p = m.pose(body)
    n = body.bone_names.index
    d = p.joints[1, n("foot.L")] - p.joints[1, n("lowerleg01.L")]
    assert d[2] / np.linalg.norm(d) < -0.99  # the knee no longer bends
    with pytest.raises(PhysavatarError, match="unknown Anny bones"):
        import_bvh(tmp_path / "m.bvh", body, mapping={"LeftKnee": "no_such_bone"})
    (tmp_path / "bad.bvh").write_text("HIERARCHY\nROOT Hips\n{\nOFFSET 0 0\n")
    with pytest.raises(PhysavatarError, match="bad.bvh"):
        read_bvh(tmp_path / "bad.bvh")


def test_real_cmu_bvh_imports(body):
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "shared" / "data" / "motions" / "cmu_131_01.bvh"
    if not path.exists():
        pytest.skip("shared CMU data not present")
    m = import_bvh(path, body).resample(25)
    assert m.frames > 100 and abs(m.meta["scale_m_per_unit"] - 0.056) < 0.01  # CMU: ~0.056 m/unit
    p = m.slice(0, 60).pose(body)
    assert np.isfinite(p.vertices).all()
    z = p.vertices[..., 2]
    assert abs(z.min(1)).max() < 0.12  # feet near the floor throughout
    assert 1.5 < (z.max(1) - z.min(1)).mean() < 1.9  # a person-sized person


def test_arm_clearance_raises_only_the_arms_and_only_where_the_hands_come_too_close(body):
    """The built-in walk swings the hands past the hips (12-18 cm from the trunk); asking for 1 cm
    more room than the median raises the upper arms in the frames that lack it (checked with an
    independent, denser surface sampling) and changes no other bone and no frame far from it."""
    from scipy.spatial import cKDTree

    from physavatar.body import builtin_motion
    from physavatar.body.motion import _TRUNK_PARTS, arm_clearance
    from physavatar.body.model import bone_vertex_mask

    walk = builtin_motion("walk", body.bone_names, 25.0, 1.2)
    _, before = arm_clearance(walk, body, clearance=0.0)  # measures only
    c = float(np.median(before["L"]["distance_before_m"])) + 0.01
    m, info = arm_clearance(walk, body, clearance=c)
    names = body.bone_names
    arm_bones = [names.index("upperarm01.L"), names.index("upperarm01.R")]
    other = np.setdiff1d(np.arange(len(names)), arm_bones)
    np.testing.assert_array_equal(m.rotations[:, other], walk.rotations[:, other])
    F = np.asarray(body.faces)
    trunk = bone_vertex_mask(body, _TRUNK_PARTS)
    tf = F[np.all(trunk[F], axis=1)]
    bary = np.random.default_rng(7).dirichlet([1.0, 1.0, 1.0], size=(len(tf), 40))
    V = body.pose(m.rotations, m.root_translation).vertices
    raised_any = False
    for side in ("L", "R"):
        d = info[side]
        need = d["distance_before_m"] < c
        raised_any |= bool(need.any())
        assert np.all(d["angle_rad"][need] > 0) and np.all(d["angle_rad"] <= np.radians(40.0) + 1e-9)
        hand = bone_vertex_mask(body, [n for n in names if n.startswith(("hand", "finger", "lowerarm"))
                                       and n.endswith("." + side)])
        for t in np.flatnonzero(need):
            P = np.einsum("fsk,fkd->fsd", bary, V[t][tf]).reshape(-1, 3)
            assert cKDTree(P).query(V[t][hand])[0].min() > c - 0.005  # the room asked for, up to sampling
        far = d["angle_rad"] < 1e-12
        i = names.index(f"upperarm01.{side}")
        np.testing.assert_allclose(m.rotations[far, i], walk.rotations[far, i], atol=1e-9)
    assert raised_any  # the check is not vacuous
