"""body.clearance: the motion correction that keeps the parts a garment covers apart, checked with
measures it does not use itself (exact point-triangle distances, the body's winding numbers, the
rotation between the bone's old and new world frames)."""

import numpy as np
import pytest

from physavatar.body import BodyModel, Motion
from physavatar.body.clearance import Clearance, _HAND, _ARM, _TRUNK, part_clearance
from physavatar.body.model import axis_angle_to_matrix, bone_vertex_mask
from physavatar.geometry.closest import MeshQuery
from physavatar.sim.crease import buried_vertices


@pytest.fixture(scope="module")
def body():
    return BodyModel(topology="collider")


def _world(body, rots, bone):
    R = axis_angle_to_matrix(rots)
    X = np.empty_like(R)
    for b in range(rots.shape[1]):
        X[:, b] = R[:, b] if body.parents[b] < 0 else X[:, body.parents[b]] @ R[:, b]
    return X[:, bone]


def test_part_clearance_moves_the_hand_off_the_hip_and_the_thigh_out_of_the_belly(body):
    """A motion that swings the right arm into the hip and pulls the right knee to the chest
    (hip flexed ~120 degrees: Anny's thigh sinks into the belly, as on the CMU walk's frames
    97-110) in frames 33-57 of 90. The correction turns only the right shoulder and hip, within
    its angle bounds, leaves the frames no smoothing window reaches exactly as they were, gives
    the hand the room asked for (exact distances to the body's triangles) and buries fewer body
    vertices inside other parts (winding numbers)."""
    names = body.bone_names
    idx = {n: i for i, n in enumerate(names)}
    T = 90
    t = np.arange(T)
    a = np.clip(1 - np.abs(t - 45) / 12, 0, 1)
    bump = a * a * (3 - 2 * a)
    R = np.zeros((T, len(names), 3))
    R[:, idx["upperarm01.R"], 1] = -0.45 * bump  # the right arm swung in, against the hip
    R[:, idx["upperleg01.R"], 0] = -2.1 * bump  # the knee to the chest
    m = Motion("t", 25.0, names, R, np.zeros((T, 3)))
    thigh = Clearance("thigh", "upperleg01.R", ("upperleg01.R", "upperleg02.R"), _TRUNK, 0.01, np.radians(20.0), 0.06)
    hand = Clearance("hand", "upperarm01.R", _HAND, ("",), 0.03, np.radians(40.0), exclude=_ARM)
    m1, info = part_clearance(m, body, [thigh])
    m2, info_hand = part_clearance(m1, body, [hand])  # the same as both rules in one call, in this order
    info.update(info_hand)

    # only the two bones change, only near the frames that need it, within the bounds
    changed = np.abs(m2.rotations - m.rotations).max(axis=2) > 0
    assert set(np.flatnonzero(changed.any(axis=0))) == {idx["upperleg01.R"], idx["upperarm01.R"]}
    rows = np.flatnonzero(changed.any(axis=1))
    assert rows.min() > 5 and rows.max() < T - 5  # the first and last frames are the motion's own
    np.testing.assert_array_equal(m2.rotations[:6], m.rotations[:6])
    for bone, bound in (("upperleg01.R", 20.0), ("upperarm01.R", 40.0)):
        b = idx[bone]
        D = _world(body, m2.rotations, b) @ np.swapaxes(_world(body, m.rotations, b), 1, 2)
        angle = np.degrees(np.arccos(np.clip((np.trace(D, axis1=1, axis2=2) - 1) / 2, -1, 1)))
        assert angle.max() <= bound + 0.5
    assert np.degrees(info["thigh"]["angle_rad"].max()) > 10  # the hip was turned back

    # the hand: the exact distance to every other part's triangles (the arm itself left out)
    F = np.asarray(body.faces)
    side_arm = bone_vertex_mask(body, [n for n in names if n.startswith(_ARM) and n.endswith(".R")])
    hand_v = np.flatnonzero(bone_vertex_mask(body, [n for n in names if n.startswith(_HAND) and n.endswith(".R")]))
    other_f = F[np.all(~side_arm[F], axis=1)]
    V0, V1 = m1.pose(body).vertices, m2.pose(body).vertices
    need = np.flatnonzero(info["hand"]["distance_before_m"] < 0.03)
    assert len(need)  # not vacuous
    for f in need:
        before = MeshQuery(V0[f], other_f).closest(V0[f][hand_v])[0].min()
        after = MeshQuery(V1[f], other_f).closest(V1[f][hand_v])[0].min()
        assert after > before and after > 0.03 - 0.004  # the room asked for, up to the sampling of the rule

    # the thigh in the belly: fewer body vertices inside another part at the frames of deepest flexion
    V0 = m.pose(body).vertices
    for f in (42, 45, 48):
        assert buried_vertices(V1[f], F).sum() < buried_vertices(V0[f], F).sum()


def test_with_part_clearance_is_what_simulate_and_animate_apply(body):
    """`--part-clearance` (body.load.with_part_clearance): only motion capture is corrected, only
    when asked; the summary it records in config.json counts the frames in which the hip was
    turned, as measured from the rotations themselves, and the line the CLI prints names the rule."""
    from physavatar.body.load import describe_part_clearance, with_part_clearance

    names = body.bone_names
    idx = {n: i for i, n in enumerate(names)}
    T = 40
    a = np.clip(1 - np.abs(np.arange(T) - 20) / 10, 0, 1)
    R = np.zeros((T, len(names), 3))
    R[:, idx["upperleg01.R"], 0] = -2.1 * a * a * (3 - 2 * a)  # the knee to the chest
    m = Motion("t", 25.0, names, R, np.zeros((T, 3)))
    assert with_part_clearance(m, "walk", body, True) == (m, None)  # a built-in motion: made for Anny
    assert with_part_clearance(m, "clip.bvh", body, False) == (m, None)
    m2, summary = with_part_clearance(m, "clip.bvh", body, True)
    assert set(summary) >= {"thigh-belly.R"} and "thigh-belly.L" not in summary
    b = idx["upperleg01.R"]
    turned = np.linalg.norm(m2.rotations[:, b] - m.rotations[:, b], axis=1) > 1e-3
    s = summary["thigh-belly.R"]
    assert abs(s["frames_turned"] - turned.sum()) <= 2 and 5 < s["max_angle_deg"] <= 35.0 + 0.5
    assert s["min_distance_after_m"] > s["min_distance_before_m"]
    assert describe_part_clearance(summary).startswith("part clearance: thigh-belly.R in ")
    assert describe_part_clearance(None) is None
    # on by default for motion capture since session 27 (docs/motions.md), off only when asked
    from physavatar.stages.animate import AnimateConfig
    from physavatar.stages.simulate import SimulateConfig
    assert SimulateConfig().part_clearance and AnimateConfig().part_clearance


def _winding(V, F, ids):
    """The body's generalised winding number at its vertices ``ids``, each leaving out its own
    triangles (van Oosterom and Strackee's solid angle, numpy: not the numba kernel the rule uses)."""
    out = np.empty(len(ids))
    for k, i in enumerate(ids):
        f = F[~np.any(F == i, axis=1)]
        a, b, c = (V[f[:, j]] - V[i] for j in range(3))
        la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
        num = np.einsum("ij,ij->i", a, np.cross(b, c))
        den = la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", b, c) * la + np.einsum("ij,ij->i", c, a) * lb
        out[k] = np.sum(2 * np.arctan2(num, den)) / (4 * np.pi)
    return out


def _flexion(joints, b, parent, child):
    u, w = joints[:, b] - joints[:, parent], joints[:, child] - joints[:, b]
    return np.arccos(np.clip(np.einsum("ij,ij->i", u, w) / np.linalg.norm(u, axis=1) / np.linalg.norm(w, axis=1), -1, 1))


def test_knee_collapse_opens_the_knee_until_no_vertex_is_buried(body):
    """`knee-collapse` (session 29): a knee flexed to 120 degrees in frames 28-52 of 80 folds the
    calf into the back of the thigh (linear blend skinning; the CMU hop's written frame 164). The
    rule turns only the knee, about the axis normal to thigh and calf, so the knee's flexion
    (the angle between the bones, from the posed joints) drops by the angle it reports (at most
    by it; by 97 % of it at least where the knee is bent more than 30 degrees);
    afterwards no vertex of the leg is inside another part (winding numbers computed here), where
    before some were; the opening is at most 3 degrees more than the smallest that clears the
    deepest frame (found here by a 1-degree scan)."""
    names = body.bone_names
    idx = {n: i for i, n in enumerate(names)}
    b, thigh, calf = idx["lowerleg01.L"], idx["upperleg02.L"], idx["lowerleg02.L"]
    T = 80
    a = np.clip(1 - np.abs(np.arange(T) - 40) / 12, 0, 1)
    R = np.zeros((T, len(names), 3))
    R[:, b, 0] = 2.1 * a * a * (3 - 2 * a)  # the heel to the buttock
    m = Motion("t", 25.0, names, R, np.zeros((T, 3)))
    from physavatar.body.clearance import knee_collapse_rules

    rule = knee_collapse_rules()[0]
    assert rule.name == "knee-collapse.L"
    m2, info = part_clearance(m, body, [rule])
    angle = info["knee-collapse.L"]["angle_rad"]

    changed = np.abs(m2.rotations - m.rotations).max(axis=2) > 0
    assert set(np.flatnonzero(changed.any(axis=0))) == {b}
    np.testing.assert_array_equal(m2.rotations[:6], m.rotations[:6])
    P0, P1 = m.pose(body), m2.pose(body)
    flex = _flexion(P0.joints, b, thigh, calf)
    drop = flex - _flexion(P1.joints, b, thigh, calf)
    # a turn by theta changes the angle between the bones by at most theta, by theta when its axis is
    # normal to both (the hinge's own axis, well defined where the knee is bent; the rule averages
    # the axes of the frames around)
    bent = flex > np.radians(30.0)
    assert np.all(drop <= angle + 1e-9) and np.all(drop[bent] >= 0.97 * angle[bent]) and angle.max() > 0

    F = np.asarray(body.faces)
    leg = np.flatnonzero(bone_vertex_mask(body, [n for n in names if n.startswith(("upperleg", "lowerleg")) and n.endswith(".L")]))
    deep = int(np.argmax(R[:, b, 0]))
    need = [f for f in (deep - 1, deep, deep + 1) if (_winding(P0.vertices[f], F, leg) > 1).any()]
    assert len(need) == 3  # not vacuous: the knee folds into itself there
    for f in need:
        assert not (_winding(P1.vertices[f], F, leg) > 1).any()
    # the smallest opening that clears the deepest frame, turning the knee as a hinge
    X = _world(body, m.rotations[deep:deep + 1], idx["upperleg02.L"])
    from physavatar.body.motion import turn_bone
    from physavatar.body.clearance import _opening_axis
    ax = _opening_axis(P0.joints[deep:deep + 1], b, thigh, calf)
    for deg in range(0, 31):
        r = turn_bone(m.rotations[deep:deep + 1], b, X, ax * np.radians(deg), np.array([0]))
        if not (_winding(Motion("t", 25.0, names, r, np.zeros((1, 3))).pose(body).vertices[0], F, leg) > 1).any():
            break
    assert 0 < deg < 25 and np.degrees(angle[deep]) <= deg + 3


def test_knee_collapse_option_is_the_rule_after_the_default_ones(body):
    """`--knee-collapse` (simulate, animate; body.load.with_part_clearance): off by default; on, the
    motion is the default rules' result with body.clearance.knee_collapse_rules applied after them
    (what benchmarks/motion_suite.py --knee-collapse measured), and its summary names the knee."""
    from physavatar.body.clearance import default_rules, knee_collapse_rules
    from physavatar.body.load import describe_part_clearance, with_part_clearance
    from physavatar.stages.animate import AnimateConfig
    from physavatar.stages.simulate import SimulateConfig

    # auto by default since session 33 (None); True / False: --knee-collapse / --no-knee-collapse
    assert SimulateConfig().knee_collapse is None and AnimateConfig().knee_collapse is None
    idx = {n: i for i, n in enumerate(body.bone_names)}
    T = 40
    a = np.clip(1 - np.abs(np.arange(T) - 20) / 8, 0, 1)
    R = np.zeros((T, len(idx), 3))
    R[:, idx["lowerleg01.L"], 0] = 2.1 * a * a * (3 - 2 * a)  # the heel to the buttock
    m = Motion("t", 25.0, body.bone_names, R, np.zeros((T, 3)))
    assert with_part_clearance(m, "walk", body, True, knee_collapse=True) == (m, None)  # not motion capture
    m2, summary = with_part_clearance(m, "clip.bvh", body, True, knee_collapse=True)
    ref = part_clearance(part_clearance(m, body, default_rules())[0], body, knee_collapse_rules())[0]
    np.testing.assert_array_equal(m2.rotations, ref.rotations)
    assert "knee-collapse.L" in summary and summary["knee-collapse.L"]["max_angle_deg"] > 1.0
    assert "knee-collapse.L" in describe_part_clearance(summary)
    m0, _ = with_part_clearance(m, "clip.bvh", body, True, knee_collapse=False)  # no collapse rule
    assert not np.array_equal(m0.rotations, m2.rotations)
    np.testing.assert_array_equal(m0.rotations, part_clearance(m, body, default_rules())[0].rotations)
    # the default, auto: this knee crosses deeply (the heel to the buttock), so it is opened as with the flag
    m1, s1 = with_part_clearance(m, "clip.bvh", body, True)
    np.testing.assert_array_equal(m1.rotations, m2.rotations)
    assert s1["knee-collapse.L"]["windows"][0]["opened"]
    assert with_part_clearance(m, "clip.bvh", body, False) == (m, None)  # auto follows --part-clearance


def test_knee_collapse_auto_opens_a_deep_crossing_and_leaves_a_grazing_one(body):
    """`--knee-collapse` auto (session 33): the knee opened only in windows of frames where calf and
    thigh cross deeper than the room the cloth's contact needs (KNEE_ROOM = d̂ + cotton's contact
    offset = 1 mm). One knee bend in 80 frames folds the calf 10 mm into the thigh (frames 14-16),
    a second, 50 frames later, grazes (frame 60: one thigh vertex inside the calf). Checked with the
    winding numbers computed here and the hinge axis from the posed joints: the deep window is
    opened until no leg vertex is buried; the grazing one is left bit-identical (every frame from
    41 on: the deep window's smoothing ends before), its vertex still buried, though the full rule
    (``min_depth`` 0) does open it; the reported opening is bracketed by turns 0.02 degrees either
    side of it (buried, clear), and the depth is that opening times the buried vertex's distance
    from the hinge axis, below 1 mm."""
    from physavatar.body.clearance import KNEE_ROOM, knee_collapse_rules
    from physavatar.body.motion import turn_bone
    from physavatar.data.material import resolve_material
    from physavatar.sim import SimSettings

    assert KNEE_ROOM == SimSettings().dhat + resolve_material("cotton", option="--material").contact_offset
    names = body.bone_names
    idx = {n: i for i, n in enumerate(names)}
    b, thigh, calf = idx["lowerleg01.L"], idx["upperleg02.L"], idx["lowerleg02.L"]
    T, t = 80, np.arange(80)

    def bump(centre, peak_deg):
        a = np.clip(1 - np.abs(t - centre) / 8, 0, 1)
        return np.radians(peak_deg) * a * a * (3 - 2 * a)

    R = np.zeros((T, len(names), 3))
    R[:, b, 0] = bump(15, 110.0) + bump(60, 102.6)
    m = Motion("t", 25.0, names, R, np.zeros((T, 3)))
    m2, info = part_clearance(m, body, knee_collapse_rules(KNEE_ROOM)[:1])
    deep, graze = info["knee-collapse.L"]["windows"]
    assert list(deep["frames"]) == [14, 15, 16] and deep["opened"]
    assert list(graze["frames"]) == [60] and not graze["opened"]
    np.testing.assert_array_equal(m2.rotations[41:], m.rotations[41:])
    assert not np.array_equal(m2.rotations[14:17], m.rotations[14:17])
    full = part_clearance(m, body, knee_collapse_rules()[:1])[0]
    assert not np.array_equal(full.rotations[60], m.rotations[60])

    F = np.asarray(body.faces)
    leg = np.flatnonzero(bone_vertex_mask(body, [n for n in names if n.startswith(("upperleg", "lowerleg")) and n.endswith(".L")]))
    P0, P1 = m.pose(body), m2.pose(body)
    for f in (14, 15, 16):
        assert (_winding(P0.vertices[f], F, leg) > 1).any() and not (_winding(P1.vertices[f], F, leg) > 1).any()
    bur = leg[_winding(P0.vertices[60], F, leg) > 1]
    assert len(bur) == 1 and (_winding(P1.vertices[60], F, leg) > 1).any()

    # the hinge axis: normal to the thigh's and the calf's directions (posed joints)
    J = P0.joints[60]
    axis = np.cross(J[calf] - J[b], J[b] - J[thigh])
    axis /= np.linalg.norm(axis)
    theta = graze["opening_rad"][0]
    X = _world(body, m.rotations[60:61], thigh)
    for dth, buried in ((-0.02, True), (0.02, False)):
        r = turn_bone(m.rotations[60:61], b, X, axis[None] * (theta + np.radians(dth)), np.array([0]))
        V = Motion("t", 25.0, names, r, np.zeros((1, 3))).pose(body).vertices[0]
        assert (_winding(V, F, leg) > 1).any() == buried
    v = P0.vertices[60][bur[0]] - J[b]
    reach = np.linalg.norm(v - (v @ axis) * axis)
    assert graze["depth_m"][0] == pytest.approx(theta * reach, rel=1e-6) and 0.3e-3 < graze["depth_m"][0] < KNEE_ROOM
    assert deep["depth_m"].max() > 5 * KNEE_ROOM
