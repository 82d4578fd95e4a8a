"""Motion import from other skeletons: BVH files in six conventions and an AMASS-style npz, all
written here from one known Anny motion, must come back onto Anny with the joints where the
source's are (scaled to Anny) and the feet on the floor.

Each BVH is forward kinematics of the known motion on a differently shaped Anny body, expressed in
the convention's skeleton: its joint names and hierarchy, its zero pose (T-pose, arms hanging, A-pose
or every bone along its joint's local x), its axes (y-up or z-up, facing anywhere), its units and
its channels (orders, 3 or 6 per joint). Euler angles are written with scipy (an implementation
independent of the importer's), positions are compared in the test's own known axes and scale.
"""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from physavatar.body import BodyModel, BodyShape, Motion, builtin_motion
from physavatar.body.bvh import import_bvh, write_bvh
from physavatar.errors import PhysavatarError

FPS = 10.0
SOURCE_SHAPE = BodyShape(gender=0.3, height=0.75, weight=0.4, proportions=0.6)

# file axes = M @ Anny axes (Anny: x left, y back, z up)
Y_UP_FRONT_Z = np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], float)
Z_UP_FRONT_X = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]], float)
Y_UP_FRONT_NEGX = np.array([[0, 1, 0], [0, 0, 1], [1, 0, 0]], float)


def _conventions():
    """name -> (joints [(name, parent, anchor)], zero pose, M, units per metre, root channels,
    joint channels, local-x frames?, end-site tips {joint: anchor})."""
    S = {"L": "Left", "R": "Right"}
    cmu = [("Hips", None, "root")]
    for s in "LR":
        cmu += [(f"{s}HipJoint", "Hips", f"pelvis.{s}"), (f"{S[s]}Hip", f"{s}HipJoint", f"upperleg01.{s}"),
                (f"{S[s]}Knee", f"{S[s]}Hip", f"lowerleg01.{s}"), (f"{S[s]}Ankle", f"{S[s]}Knee", f"foot.{s}"),
                (f"{S[s]}Toe", f"{S[s]}Ankle", f"toes.{s}")]
    cmu += [("lowerback", "Hips", "spine05"), ("Chest", "lowerback", "spine03"), ("Chest2", "Chest", "spine01"),
            ("lowerneck", "Chest2", "neck01"), ("Neck", "lowerneck", "neck02"), ("Head", "Neck", "head")]
    for s in "LR":
        lo = s.lower()
        cmu += [(f"{S[s]}Collar", "Chest2", f"clavicle.{s}"), (f"{S[s]}Shoulder", f"{S[s]}Collar", f"upperarm01.{s}"),
                (f"{S[s]}Elbow", f"{S[s]}Shoulder", f"lowerarm01.{s}"), (f"{S[s]}Wrist", f"{S[s]}Elbow", f"wrist.{s}"),
                (f"{lo}hand", f"{S[s]}Wrist", f"wrist.{s}"), (f"{s}Fingers", f"{lo}hand", f"knuckle.{s}")]

    mx = [("mixamorig:Hips", None, "root"), ("mixamorig:Spine", "mixamorig:Hips", "spine04"),
          ("mixamorig:Spine1", "mixamorig:Spine", "spine03"), ("mixamorig:Spine2", "mixamorig:Spine1", "spine01"),
          ("mixamorig:Neck", "mixamorig:Spine2", "neck01"), ("mixamorig:Head", "mixamorig:Neck", "head"),
          ("mixamorig:HeadTop_End", "mixamorig:Head", "headtop")]
    for s in "LR":
        p = f"mixamorig:{S[s]}"
        mx += [(f"{p}Shoulder", "mixamorig:Spine2", f"clavicle.{s}"), (f"{p}Arm", f"{p}Shoulder", f"upperarm01.{s}"),
               (f"{p}ForeArm", f"{p}Arm", f"lowerarm01.{s}"), (f"{p}Hand", f"{p}ForeArm", f"wrist.{s}"),
               (f"{p}HandMiddle1", f"{p}Hand", f"knuckle.{s}"),
               (f"{p}UpLeg", "mixamorig:Hips", f"upperleg01.{s}"), (f"{p}Leg", f"{p}UpLeg", f"lowerleg01.{s}"),
               (f"{p}Foot", f"{p}Leg", f"foot.{s}"), (f"{p}ToeBase", f"{p}Foot", f"toes.{s}")]

    bp = [("Bip01", None, "root"), ("Bip01 Pelvis", "Bip01", "root"), ("Bip01 Spine", "Bip01 Pelvis", "spine04")]
    for s in "LR":
        bp += [(f"Bip01 {s} Thigh", "Bip01 Spine", f"upperleg01.{s}"), (f"Bip01 {s} Calf", f"Bip01 {s} Thigh", f"lowerleg01.{s}"),
               (f"Bip01 {s} Foot", f"Bip01 {s} Calf", f"foot.{s}"), (f"Bip01 {s} Toe0", f"Bip01 {s} Foot", f"toes.{s}")]
    bp += [("Bip01 Spine1", "Bip01 Spine", "spine03"), ("Bip01 Spine2", "Bip01 Spine1", "spine01"),
           ("Bip01 Neck", "Bip01 Spine2", "neck01"), ("Bip01 Head", "Bip01 Neck", "head")]
    for s in "LR":  # 3ds Max biped: the clavicles hang from the neck
        bp += [(f"Bip01 {s} Clavicle", "Bip01 Neck", f"clavicle.{s}"), (f"Bip01 {s} UpperArm", f"Bip01 {s} Clavicle", f"upperarm01.{s}"),
               (f"Bip01 {s} Forearm", f"Bip01 {s} UpperArm", f"lowerarm01.{s}"), (f"Bip01 {s} Hand", f"Bip01 {s} Forearm", f"wrist.{s}"),
               (f"Bip01 {s} Finger2", f"Bip01 {s} Hand", f"knuckle.{s}")]

    lx = [("Reference", None, "ground"), ("Hips", "Reference", "root")]
    for s in "LR":
        lx += [(f"UpperLeg_{s}", "Hips", f"upperleg01.{s}"), (f"LowerLeg_{s}", f"UpperLeg_{s}", f"lowerleg01.{s}"),
               (f"Foot_{s}", f"LowerLeg_{s}", f"foot.{s}"), (f"Toe_{s}", f"Foot_{s}", f"toes.{s}")]
    lx += [("Spine", "Hips", "spine03"), ("Chest", "Spine", "spine01"), ("Neck", "Chest", "neck01"), ("Head", "Neck", "head")]
    for s in "LR":
        lx += [(f"Shoulder_{s}", "Chest", f"clavicle.{s}"), (f"UpperArm_{s}", f"Shoulder_{s}", f"upperarm01.{s}"),
               (f"LowerArm_{s}", f"UpperArm_{s}", f"lowerarm01.{s}"), (f"Hand_{s}", f"LowerArm_{s}", f"wrist.{s}")]
    assert len(lx) == 22

    sm = [("Pelvis", None, "root")]
    for s in "LR":
        sm += [(f"{s}_Hip", "Pelvis", f"upperleg01.{s}"), (f"{s}_Knee", f"{s}_Hip", f"lowerleg01.{s}"),
               (f"{s}_Ankle", f"{s}_Knee", f"foot.{s}"), (f"{s}_Foot", f"{s}_Ankle", f"toes.{s}")]
    sm += [("Spine1", "Pelvis", "spine04"), ("Spine2", "Spine1", "spine03"), ("Spine3", "Spine2", "spine01"),
           ("Neck", "Spine3", "neck01"), ("Head", "Neck", "head")]
    for s in "LR":
        sm += [(f"{s}_Collar", "Spine3", f"clavicle.{s}"), (f"{s}_Shoulder", f"{s}_Collar", f"upperarm01.{s}"),
               (f"{s}_Elbow", f"{s}_Shoulder", f"lowerarm01.{s}"), (f"{s}_Wrist", f"{s}_Elbow", f"wrist.{s}"),
               (f"{s}_Hand", f"{s}_Wrist", f"knuckle.{s}")]

    bl = [("hips", None, "root")]  # Blender-style names with .L/.R, A-pose zero pose, z-up
    for s in "LR":
        bl += [(f"thigh.{s}", "hips", f"upperleg01.{s}"), (f"shin.{s}", f"thigh.{s}", f"lowerleg01.{s}"),
               (f"foot.{s}", f"shin.{s}", f"foot.{s}"), (f"toe.{s}", f"foot.{s}", f"toes.{s}")]
    bl += [("spine", "hips", "spine03"), ("chest", "spine", "spine01"), ("neck", "chest", "neck01"), ("head", "neck", "head")]
    for s in "LR":
        bl += [(f"shoulder.{s}", "chest", f"clavicle.{s}"), (f"upper_arm.{s}", f"shoulder.{s}", f"upperarm01.{s}"),
               (f"forearm.{s}", f"upper_arm.{s}", f"lowerarm01.{s}"), (f"hand.{s}", f"forearm.{s}", f"wrist.{s}")]

    pos_zyx = ["Xposition", "Yposition", "Zposition", "Zrotation", "Yrotation", "Xrotation"]
    return {
        "cmu": (cmu, "down", Y_UP_FRONT_Z, 1 / 0.056, pos_zyx, ["Zrotation", "Yrotation", "Xrotation"], False, {"Head": "headtop"}),
        "mixamo": (mx, "T", Y_UP_FRONT_Z, 100.0, ["Xposition", "Yposition", "Zposition", "Zrotation", "Xrotation", "Yrotation"],
                   ["Zrotation", "Xrotation", "Yrotation"], False, {}),
        "biped": (bp, "T", Z_UP_FRONT_X, 1 / 0.0254, ["Xposition", "Yposition", "Zposition", "Zrotation", "Xrotation", "Yrotation"],
                  ["Zrotation", "Xrotation", "Yrotation"], False, {"Bip01 Head": "headtop"}),
        "ground_root_local_x": (lx, "A", Y_UP_FRONT_NEGX, 1000.0, ["Xposition", "Yposition", "Zposition", "Xrotation", "Yrotation", "Zrotation"],
                                ["Xposition", "Yposition", "Zposition", "Xrotation", "Yrotation", "Zrotation"], True,
                                {"Head": "headtop", "Hand_L": "knuckle.L", "Hand_R": "knuckle.R"}),
        "blender_a_pose": (bl, "A", np.eye(3), 1.0, ["Xposition", "Yposition", "Zposition", "Xrotation", "Yrotation", "Zrotation"],
                           ["Xrotation", "Yrotation", "Zrotation"], False, {"head": "headtop", "hand.L": "knuckle.L", "hand.R": "knuckle.R"}),
        "smpl_names": (sm, "T", Y_UP_FRONT_Z, 1.0, pos_zyx, ["Zrotation", "Yrotation", "Xrotation"], False, {"Head": "headtop"}),
    }


def _turn(a, b):
    """Smallest rotation taking direction a onto b (Rodrigues)."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    v, c = np.cross(a, b), float(np.dot(a, b))
    s = np.linalg.norm(v)
    if s < 1e-12:
        return np.eye(3)
    k = v / s
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * K + (1 - c) * K @ K


def _posture(body, kind):
    """[B, 3] local rotations putting Anny's arms in the convention's zero pose."""
    n = body.bone_names.index
    J = body.rest_joints
    rot = np.zeros((len(body.bone_names), 3))
    if kind == "A":
        return rot
    for s, sign in (("L", 1.0), ("R", -1.0)):
        target = np.array([sign, 0, 0]) if kind == "T" else np.array([0, 0, -1.0])
        R1 = _turn(J[n(f"lowerarm01.{s}")] - J[n(f"upperarm01.{s}")], target)
        R2 = _turn(R1 @ (J[n(f"wrist.{s}")] - J[n(f"lowerarm01.{s}")]), target)
        rot[n(f"upperarm01.{s}")] = Rotation.from_matrix(R1).as_rotvec()
        rot[n(f"lowerarm01.{s}")] = Rotation.from_matrix(R1.T @ R2 @ R1).as_rotvec()
    return rot


def known_motion(names, fps=FPS, duration=3.0):
    """The built-in dance plus feet, wrists, a forearm twist and walking forward (-y)."""
    m = builtin_motion("dance", names, fps, duration)
    R, tr = m.rotations.copy(), m.root_translation.copy()
    t = np.arange(m.frames) / fps
    e = np.clip(t / 0.5, 0, 1)
    n = names.index
    R[:, n("foot.L"), 0] = -0.35 * np.sin(2.1 * t) * e
    R[:, n("foot.R"), 0] = 0.25 * np.sin(1.7 * t) * e
    R[:, n("wrist.L")] = np.stack([0.4 * np.sin(2 * t), 0.2 * np.ones_like(t), 0.3 * np.cos(t)], -1) * e[:, None]
    R[:, n("wrist.R")] = np.stack([-0.3 * np.sin(3 * t), 0 * t, -0.25 * np.ones_like(t)], -1) * e[:, None]
    R[:, n("clavicle.L"), 1] = -0.15 * np.sin(2 * t) * e
    tr[:, 1] -= 0.3 * t * e  # walk forward
    return Motion("known", fps, names, R, tr)


def _pose_points(body, rot, tr):
    """Per frame: world rotations X [T, B, 3, 3] and named points (bone heads, toes, knuckles, head top)."""
    W = body.world_bone_poses(rot, tr)
    X = W[:, :, :3, :3] @ np.swapaxes(body.rest_bone_axes, -1, -2)[None]
    H = W[:, :, :3, 3] + np.array([0, 0, body.floor_offset])
    n = body.bone_names.index
    pts = {b: H[:, i] for i, b in enumerate(body.bone_names)}
    for s in "LR":
        pts[f"toes.{s}"] = np.mean([H[:, n(f"toe{k}-1.{s}")] for k in range(1, 6)], axis=0)
        pts[f"knuckle.{s}"] = H[:, n(f"finger3-1.{s}")]
    pts["headtop"] = H[:, n("head")] + 0.15 * np.einsum("tij,j->ti", W[:, n("head"), :3, :3], [0, 1.0, 0])
    pts["ground"] = np.zeros_like(H[:, 0])
    return X, pts


def _carrier(anchor):
    """The Anny bone a source joint turns with."""
    base, _, side = anchor.partition(".")
    base = {"toes": "foot", "knuckle": "wrist", "headtop": "head"}.get(base, base)
    return f"{base}.{side}" if side else base


def write_convention(path, conv, src_body, motion):
    """Write the known motion as a BVH file in one convention; returns the source joint positions
    [T, J, 3] in metres and Anny axes, and the joint list."""
    joints, zero, M, units, root_ch, joint_ch, local_x, tips = conv
    names = [j[0] for j in joints]
    parents = [-1 if p is None else names.index(p) for _, p, _ in joints]
    Xt, pts = _pose_points(src_body, motion.rotations, motion.root_translation)
    q = _posture(src_body, zero)[None]
    Xq, ref = _pose_points(src_body, q, np.zeros((1, 3)))
    bi = src_body.bone_names.index
    J, T = len(joints), motion.frames
    P = np.stack([pts[a] for _, _, a in joints], 1)  # [T, J, 3] metres, Anny axes
    Pref = np.stack([ref[a][0] for _, _, a in joints], 0)
    Pf, Preff = P @ M.T * units, Pref @ M.T * units  # file axes and units
    kids = {j: [k for k in range(J) if parents[k] == j] for j in range(J)}
    O = np.broadcast_to(np.eye(3), (J, 3, 3)).copy()
    if local_x:  # each joint's frame has x along its first child (leaves: their parent's frame)
        for j in range(J):
            if joints[j][2] == "ground":
                continue
            if kids[j] and np.linalg.norm(Preff[kids[j][0]] - Preff[j]) > 1e-9:
                x = Preff[kids[j][0]] - Preff[j]
                O[j] = _turn(np.array([1.0, 0, 0]), x)
            elif parents[j] >= 0:
                O[j] = O[parents[j]]
    G = np.empty((T, J, 3, 3))
    for j, (_, _, a) in enumerate(joints):
        if a == "ground":
            G[:, j] = np.eye(3)
            continue
        b = bi(_carrier(a))
        G[:, j] = M @ Xt[:, b] @ Xq[0, b].T @ M.T @ O[j]
    offsets = np.zeros((J, 3))
    for j in range(J):
        if parents[j] >= 0:
            offsets[j] = O[parents[j]].T @ (Preff[j] - Preff[parents[j]])
    cols = []
    for j in range(J):
        ch = root_ch if parents[j] < 0 else joint_ch
        L = G[:, j] if parents[j] < 0 else np.swapaxes(G[:, parents[j]], -1, -2) @ G[:, j]
        rot_order = "".join(c[0] for c in ch if c.endswith("rotation"))
        eul = Rotation.from_matrix(L).as_euler(rot_order.upper(), degrees=True)
        pos = Pf[:, j] if parents[j] < 0 else np.tile(offsets[j], (T, 1))
        if parents[j] >= 0 and parents[parents[j]] < 0 and joints[parents[j]][2] == "ground":
            pos = Pf[:, j]  # the hips below a ground root: their position channels carry the motion
        for c in ch:
            cols.append(pos[:, "XYZ".index(c[0])] if c.endswith("position") else eul[:, rot_order.index(c[0])])
    data = np.stack(cols, 1)
    end = {}
    for j, (nm, _, _) in enumerate(joints):
        if not kids[j] and nm in tips:
            end[j] = O[j].T @ (M @ (ref[tips[nm]][0] - ref[joints[j][2]][0]) * units)
    write_bvh(path, names, parents, offsets, [root_ch if p < 0 else joint_ch for p in parents], data, 1 / FPS, end)
    return P, joints


@pytest.fixture(scope="module")
def bodies():
    return BodyModel(topology="collider"), BodyModel(SOURCE_SHAPE, topology="collider")


def _leg(body):
    n, J = body.bone_names.index, body.rest_joints
    return np.mean([np.linalg.norm(J[n(f"upperleg01.{s}")] - J[n(f"lowerleg01.{s}")]) +
                    np.linalg.norm(J[n(f"lowerleg01.{s}")] - J[n(f"foot.{s}")]) for s in "LR"])


@pytest.mark.parametrize("name", list(_conventions()))
def test_bvh_conventions_retarget_onto_anny(bodies, tmp_path, name, record_property):
    body, src_body = bodies
    known = known_motion(src_body.bone_names)
    P, joints = write_convention(tmp_path / f"{name}.bvh", _conventions()[name], src_body, known)
    m = import_bvh(tmp_path / f"{name}.bvh", body)
    assert m.frames == known.frames and abs(m.fps - FPS) < 1e-6
    s = _leg(body) / _leg(src_body)
    _, got = _pose_points(body, m.rotations, m.root_translation)
    sel = [j for j, (_, _, a) in enumerate(joints) if a in body.bone_names]
    A = np.stack([got[joints[j][2]] for j in sel], 1)
    B = P[:, sel] * s
    d = (A - B).reshape(-1, 3)
    d -= d.mean(0)  # one translation for the clip: the importer places it (first frame, floor)
    err = np.linalg.norm(d, axis=1)
    record_property("mean_joint_error_m", float(err.mean()))
    print(f"{name}: mean joint error {100 * err.mean():.2f} cm, max {100 * err.max():.2f} cm, scale {m.meta['scale_m_per_unit']:.4f}")
    assert err.mean() < 0.03
    # the feet on the floor: Anny's lowest point per frame follows the source's (scaled; the
    # known motion tips the feet, so the source itself dips its toes up to 7 cm below the floor)
    low = body.pose(m.rotations, m.root_translation).vertices[..., 2].min(1)
    src_low = src_body.pose(known.rotations, known.root_translation).vertices[..., 2].min(1) * s
    assert abs(low.min() - src_low.min()) < 0.015
    assert np.abs(low - src_low).max() < 0.03


@pytest.mark.parametrize("name", list(_conventions()))
def test_structure_alone_maps_unnamed_skeletons(bodies, tmp_path, name, record_property):
    """The same files with every joint renamed j00, j01, …: the map comes from the skeleton's
    shape. The biped hangs its clavicles from the neck, which the shape reads as the chest, so
    its bound is looser (measured 4.4 cm; the names fix it)."""
    body, src_body = bodies
    joints, *rest = _conventions()[name]
    names = [n for n, _, _ in joints]
    odd = [(f"j{k:02d}", None if p is None else f"j{names.index(p):02d}", a) for k, (n, p, a) in enumerate(joints)]
    known = known_motion(src_body.bone_names, duration=1.5)
    P, _ = write_convention(tmp_path / "odd.bvh", (odd, *rest), src_body, known)
    m = import_bvh(tmp_path / "odd.bvh", body)
    s = _leg(body) / _leg(src_body)
    _, got = _pose_points(body, m.rotations, m.root_translation)
    sel = [j for j, (_, _, a) in enumerate(odd) if a in body.bone_names]
    d = (np.stack([got[odd[j][2]] for j in sel], 1) - P[:, sel] * s).reshape(-1, 3)
    err = np.linalg.norm(d - d.mean(0), axis=1).mean()
    record_property("mean_joint_error_m", float(err))
    print(f"{name} without names: mean joint error {100 * err:.2f} cm")
    assert err < (0.05 if name == "biped" else 0.03)
    for j, (_, _, a) in enumerate(joints):  # the legs' sides come out right
        if a.startswith("upperleg01"):
            assert m.meta["mapped_joints"].get(odd[j][0]) == a


# -- AMASS / SMPL ------------------------------------------------------------------------------

_QZ = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # SMPL's y-up body upright in AMASS's z-up world


def _write_amass(path, body, motion, width=156, fps_key="mocap_framerate"):
    """The known Anny motion as SMPL axis-angles: each SMPL joint turns with its Anny bone, from
    SMPL's T-pose rest (the module's neutral offsets) instead of Anny's A-pose."""
    from physavatar.body.amass import SMPL_NAMES, SMPL_OFFSETS, SMPL_PARENTS, SMPL_PELVIS, SMPL_TO_ANNY

    X, pts = _pose_points(body, motion.rotations, motion.root_translation)
    bi = body.bone_names.index
    rest = np.zeros((24, 3))
    for j, p in enumerate(SMPL_PARENTS):
        if p >= 0:
            rest[j] = rest[p] + _QZ @ SMPL_OFFSETS[j]
    anchor = dict(SMPL_TO_ANNY)
    anchor.update({"L_Foot": "toes.L", "R_Foot": "toes.R", "L_Hand": "knuckle.L", "R_Hand": "knuckle.R"})
    _, ref = _pose_points(body, np.zeros((1, len(body.bone_names), 3)), np.zeros((1, 3)))
    T = motion.frames
    G = np.empty((T, 24, 3, 3))
    for j, nm in enumerate(SMPL_NAMES):
        kids = [k for k in range(24) if SMPL_PARENTS[k] == j]
        if nm not in SMPL_TO_ANNY:
            G[:, j] = G[:, SMPL_PARENTS[j]]
            continue
        a = [ref[anchor[SMPL_NAMES[k]]][0] - ref[anchor[nm]][0] for k in kids]
        s = [rest[k] - rest[j] for k in kids]
        if not kids:  # the head: SMPL's up against Anny's head axis
            a, s = [body.rest_bone_axes[bi("head")][:, 1]], [np.array([0, 0, 1.0])]
        K = _turn(s[0], a[0]) if len(a) == 1 else Rotation.align_vectors(np.array(a), np.array(s))[0].as_matrix()
        G[:, j] = X[:, bi(SMPL_TO_ANNY[nm])] @ K
    poses = np.zeros((T, width))
    for j in range(22):
        p = SMPL_PARENTS[j]
        L = G[:, j] @ _QZ if p < 0 else _QZ.T @ np.swapaxes(G[:, p], -1, -2) @ G[:, j] @ _QZ
        poses[:, 3 * j:3 * j + 3] = Rotation.from_matrix(L).as_rotvec()
    smpl_leg = np.mean([np.linalg.norm(SMPL_OFFSETS[k]) + np.linalg.norm(SMPL_OFFSETS[k + 3]) for k in (4, 5)])
    pelvis = pts["root"] * smpl_leg / _leg(body)
    np.savez(path, poses=poses, trans=pelvis - SMPL_PELVIS, betas=np.zeros(16), gender=np.array("neutral"),
             **{fps_key: np.array(motion.fps)})


@pytest.mark.parametrize("width,fps_key", [(156, "mocap_framerate"), (165, "mocap_frame_rate"), (72, "mocap_framerate")])
def test_amass_roundtrip(bodies, tmp_path, width, fps_key, record_property):
    from physavatar.body.load import load_motion

    body = bodies[0]
    known = known_motion(body.bone_names)
    f = tmp_path / "amass.npz"
    _write_amass(f, body, known, width, fps_key)
    m = load_motion(str(f), fps=FPS, body=body)
    assert m.meta["model"].startswith({156: "SMPL-H", 165: "SMPL-X", 72: "SMPL "}[width])
    from physavatar.body.amass import SMPL_TO_ANNY

    bones = list(SMPL_TO_ANNY.values())
    _, want = _pose_points(body, known.rotations, known.root_translation)
    _, got = _pose_points(body, m.rotations, m.root_translation)
    d = np.stack([got[b] - want[b] for b in bones], 1).reshape(-1, 3)
    d -= d.mean(0)
    err = np.linalg.norm(d, axis=1)
    record_property("mean_joint_error_m", float(err.mean()))
    print(f"AMASS {width}: mean joint error {100 * err.mean():.2f} cm, max {100 * err.max():.2f} cm")
    assert err.mean() < 0.03
    low = body.pose(m.rotations, m.root_translation).vertices[..., 2].min(1)
    low0 = body.pose(known.rotations, known.root_translation).vertices[..., 2].min(1)
    assert np.abs(low - low0).max() < 0.03 and abs(low.min() - low0.min()) < 0.015
    # AMASS keeps its heading: the known motion walks towards -y
    assert m.root_translation[-1, 1] - m.root_translation[0, 1] < -0.5


def test_amass_zero_pose_is_an_upright_t_pose_facing_minus_y(bodies, tmp_path):
    """Zero body rotations with the root turned upright (AMASS z-up) put Anny in SMPL's rest pose:
    a T-pose, legs straight down, toes towards -y: the rest offsets and axes are SMPL's."""
    from physavatar.body.amass import import_amass

    body = bodies[0]
    poses = np.zeros((3, 156))
    poses[:, 0] = np.pi / 2
    np.savez(tmp_path / "t.npz", poses=poses, trans=np.zeros((3, 3)), mocap_framerate=np.array(30.0))
    m = import_amass(tmp_path / "t.npz", body)
    _, p = _pose_points(body, m.rotations, m.root_translation)
    for s, sign in (("L", 1), ("R", -1)):
        arm = p[f"wrist.{s}"][0] - p[f"upperarm01.{s}"][0]
        assert sign * arm[0] / np.linalg.norm(arm) > 0.97  # out sideways, level
        leg = p[f"foot.{s}"][0] - p[f"upperleg01.{s}"][0]
        assert leg[2] / np.linalg.norm(leg) < -0.97
        toe = p[f"toes.{s}"][0] - p[f"foot.{s}"][0]
        assert toe[1] < -0.5 * np.linalg.norm(toe)
    assert abs(body.pose(m.rotations, m.root_translation).vertices[0, :, 2].min()) < 0.02
    # the same through the CLI: 'motion import' writes the project's motion file
    from typer.testing import CliRunner

    from physavatar.cli import app

    r = CliRunner().invoke(app, ["motion", "import", str(tmp_path / "t.npz"), "--out", str(tmp_path / "m.npz")])
    assert r.exit_code == 0, r.output
    saved = Motion.load(tmp_path / "m.npz")
    assert saved.fps == 30.0 and np.allclose(saved.rotations, m.rotations, atol=1e-9)


# -- bad input and the CLI ---------------------------------------------------------------------

def test_bad_input_one_clear_line(bodies, tmp_path):
    body = bodies[0]
    names = ["Root", "Spine", "Neck", "Head", "LeftArm", "LeftForeArm", "RightArm", "RightForeArm"]
    parents = [-1, 0, 1, 2, 1, 4, 1, 6]
    offs = [[0, 0, 0], [0, 10, 0], [0, 10, 0], [0, 5, 0], [5, 0, 0], [10, 0, 0], [-5, 0, 0], [-10, 0, 0]]
    ch = [["Xposition", "Yposition", "Zposition", "Zrotation", "Xrotation", "Yrotation"]] + [["Zrotation", "Xrotation", "Yrotation"]] * 7
    write_bvh(tmp_path / "nolegs.bvh", names, parents, offs, ch, np.zeros((2, 6 + 21)), 1 / 30)
    with pytest.raises(PhysavatarError, match=r"nolegs\.bvh: cannot find the (hips|left leg)"):
        import_bvh(tmp_path / "nolegs.bvh", body)
    np.savez(tmp_path / "short.npz", poses=np.zeros((4, 30)), trans=np.zeros((4, 3)), mocap_framerate=np.array(60.0))
    np.savez(tmp_path / "nofps.npz", poses=np.zeros((4, 72)), trans=np.zeros((4, 3)))
    from physavatar.body.load import load_motion

    with pytest.raises(PhysavatarError, match=r"short\.npz: 'poses' must be"):
        load_motion(str(tmp_path / "short.npz"), body=body)
    with pytest.raises(PhysavatarError, match=r"nofps\.npz: no frame rate"):
        load_motion(str(tmp_path / "nofps.npz"), body=body)
    # a mapping naming a joint the file lacks, and the same through the CLI: one line, exit 2
    from typer.testing import CliRunner

    from physavatar.cli import app

    (tmp_path / "map.json").write_text('{"NoSuchJoint": "root"}')
    r = CliRunner().invoke(app, ["motion", "import", str(tmp_path / "nolegs.bvh"), "--out", str(tmp_path / "o.npz")])
    assert r.exit_code == 2 and "nolegs.bvh" in r.output and "Traceback" not in r.output
    assert len([ln for ln in r.output.splitlines() if ln.strip()]) == 1


def test_mapping_used_in_every_step_and_inspect_cli(bodies, tmp_path):
    """Joints with names that say nothing are mapped from the skeleton's shape; a complete
    --mapping is used in every step (orientation, alignment, scale, floor); 'motion inspect' shows
    the map and why."""
    body, src_body = bodies
    joints, *rest = _conventions()["ground_root_local_x"]
    odd = [(f"j{k:02d}", None if p is None else f"j{[n for n, _, _ in joints].index(p):02d}", a)
           for k, (n, p, a) in enumerate(joints)]
    known = known_motion(src_body.bone_names, duration=1.5)
    P, _ = write_convention(tmp_path / "odd.bvh", (odd, *rest), src_body, known)
    s = _leg(body) / _leg(src_body)
    sel = [j for j, (_, _, a) in enumerate(odd) if a in body.bone_names]

    def error(m):
        _, got = _pose_points(body, m.rotations, m.root_translation)
        d = (np.stack([got[odd[j][2]] for j in sel], 1) - P[:, sel] * s).reshape(-1, 3)
        return np.linalg.norm(d - d.mean(0), axis=1).mean()

    # names that say nothing: the map comes from the skeleton's shape (mirror legs and arms, lengths)
    m = import_bvh(tmp_path / "odd.bvh", body)
    assert m.meta["mapped_joints"]["j01"] == "root" and "structure" in m.meta["mapping_why"]["j01"]
    assert m.meta["mapped_joints"]["j02"] == "upperleg01.L" and m.meta["mapped_joints"]["j06"] == "upperleg01.R"
    assert error(m) < 0.03
    mapping = {f"j{k:02d}": a for k, (_, _, a) in enumerate(joints) if a in body.bone_names}
    import json

    (tmp_path / "map.json").write_text(json.dumps(mapping))
    m = import_bvh(tmp_path / "odd.bvh", body, mapping=tmp_path / "map.json")
    assert error(m) < 0.03
    assert m.meta["mapping_why"]["j01"] == "mapping file: root"
    # the mapping is used in every step: mapping the legs crosswise turns the body round
    swap = {k: (v[:-1] + {"L": "R", "R": "L"}[v[-1]] if v.endswith((".L", ".R")) else v) for k, v in mapping.items()}
    (tmp_path / "swap.json").write_text(json.dumps(swap))
    m2 = import_bvh(tmp_path / "odd.bvh", body, mapping=tmp_path / "swap.json")
    assert np.allclose(np.asarray(m2.meta["axes"])[2], np.asarray(m.meta["axes"])[2])  # still upright
    assert np.allclose(np.asarray(m2.meta["axes"])[0], -np.asarray(m.meta["axes"])[0])  # left and right swapped

    from typer.testing import CliRunner

    from physavatar.cli import app

    write_convention(tmp_path / "mixamo.bvh", _conventions()["mixamo"], src_body, known)
    r = CliRunner().invoke(app, ["motion", "inspect", str(tmp_path / "mixamo.bvh"), "--out", str(tmp_path / "p.png"),
                                 "--frames", "2"], env={"COLUMNS": "240"})
    assert r.exit_code == 0, r.output
    for text in ("mixamorig:LeftUpLeg", "upperleg01.L", "an upper arm", "clavicle.L", "the file's up is +y",
                 "its forward +z", "m per file unit"):
        assert text in r.output, text
    assert (tmp_path / "p.png").stat().st_size > 1000


def test_bvh_reader_keeps_names_with_spaces_and_reads_crlf(tmp_path):
    from physavatar.body.bvh import read_bvh

    text = ("HIERARCHY\r\nROOT Bip01\r\n{\r\n OFFSET 0 0 0\r\n CHANNELS 6 Xposition Yposition Zposition Zrotation "
            "Xrotation Yrotation\r\n JOINT Bip01 L Thigh {\r\n  OFFSET 1 -2 0\r\n  CHANNELS 3 Zrotation Xrotation "
            "Yrotation\r\n  End Site\r\n  {\r\n   OFFSET 0 -4 0\r\n  }\r\n }\r\n}\r\nMOTION\r\nFrames: 2\r\n"
            "Frame Time: 0.0333333\r\n0 1 0 0 0 0 0 0 0\r\n0 1 0 0 0 0 0 0 90\r\n")
    (tmp_path / "s.bvh").write_bytes(text.encode())
    b = read_bvh(tmp_path / "s.bvh")
    assert b.skeleton.names == ["Bip01", "Bip01 L Thigh"] and b.data.shape == (2, 9)
    assert np.allclose(b.skeleton.end_sites[1], [0, -4, 0])


def _write_cmu_still(path):
    """CMU's own offsets (131_01: collars at the neck base, shoulders 26 deg above it), standing
    still in the zero pose for three frames, y up; returns the skeleton [(name, parent, offset)]."""
    sk = [("Hips", None, (0, 0, 0)), ("lowerback", "Hips", (0, 0, 0)), ("Chest", "lowerback", (-0.023, 1.987, 0.003)),
          ("Chest2", "Chest", (-0.007, 1.990, -0.005)), ("lowerneck", "Chest2", (0, 0, 0)),
          ("Neck", "lowerneck", (0.001, 1.610, 0.107)), ("Head", "Neck", (-0.011, 1.599, 0.013))]
    for s, S, x in (("L", "Left", 1.0), ("R", "Right", -1.0)):
        sk += [(f"{s}HipJoint", "Hips", (0, 0, 0)), (f"{S}Hip", f"{s}HipJoint", (x * 1.248, -1.643, 0.717)),
               (f"{S}Knee", f"{S}Hip", (x * 2.493, -6.850, 0)), (f"{S}Ankle", f"{S}Knee", (x * 2.368, -6.505, 0)),
               (f"{S}Toe", f"{S}Ankle", (x * 0.148, -0.407, 2.214)),
               (f"{S}Collar", "Chest2", (0, 0, 0)), (f"{S}Shoulder", f"{S}Collar", (x * 3.054, 1.471, -0.017)),
               (f"{S}Elbow", f"{S}Shoulder", (0, -4.251, 0)), (f"{S}Wrist", f"{S}Elbow", (0, -3.276, 0))]
    names = [j[0] for j in sk]
    parents = [-1 if p is None else names.index(p) for _, p, _ in sk]
    channels = [["Xposition", "Yposition", "Zposition", "Zrotation", "Yrotation", "Xrotation"] if p < 0 else
                ["Zrotation", "Yrotation", "Xrotation"] for p in parents]
    data = np.zeros((3, sum(len(c) for c in channels)))
    data[:, 1] = 17.0  # the hips 17 units (~0.95 m) above the floor, y up
    write_bvh(path, names, parents, np.array([o for _, _, o in sk], float), channels, data, 1 / 120)
    return sk


def test_cmu_pelvis_joints_keep_anny_hips_and_the_thighs_apart(bodies, tmp_path):
    """The CMU skeleton's hip joints hang from a root at their own height: ``LHipJoint`` (offset 0)
    runs 50° down and forwards to ``LeftHip`` (the offsets below are CMU's own), where Anny's
    pelvis.L runs sideways. Standing still in the file's zero pose (the calibration pose), Anny's
    pelvis must keep its rest shape: the hip joints exactly Anny's rest distances apart and
    from the root, the thighs aimed along the file's (CMU's 20° splay), no leg through the other.
    Aimed at the file's hip joints, the pelvis sides swung the hip joints 8 cm down and together
    (0.204 -> 0.115 m) and the thighs crossed (CMU 131_01 in most frames)."""
    import ipctk

    from physavatar.body.model import bone_vertex_mask

    body = bodies[0]
    sk = _write_cmu_still(tmp_path / "cmu.bvh")
    names = [j[0] for j in sk]
    m = import_bvh(tmp_path / "cmu.bvh", body)
    assert m.meta["mapped_joints"]["LHipJoint"] == "pelvis.L"
    J = body.pose(m.rotations, m.root_translation).joints
    n, R = body.bone_names.index, body.rest_joints
    for a, b in (("upperleg01.L", "upperleg01.R"), ("root", "upperleg01.L"), ("root", "upperleg01.R")):
        np.testing.assert_allclose(np.linalg.norm(J[:, n(a)] - J[:, n(b)], axis=1),
                                   np.linalg.norm(R[n(a)] - R[n(b)]), atol=1e-6)
    C = np.array(m.meta["axes"])  # file axes -> Anny's (y up, facing +z: Anny's x, -z, y)
    for s, S in (("L", "Left"), ("R", "Right")):
        want = C @ np.array(sk[names.index(f"{S}Knee")][2])
        got = J[0, n(f"lowerleg01.{s}")] - J[0, n(f"upperleg01.{s}")]
        assert np.degrees(np.arccos(np.dot(want, got) / np.linalg.norm(want) / np.linalg.norm(got))) < 1.0
    # no thigh or shin through the other leg's (ipctk's exact edge-triangle test, the legs only)
    F = np.asarray(body.faces)
    legs = [bone_vertex_mask(body, [b for b in body.bone_names if b.startswith(("upperleg", "lowerleg")) and b.endswith(s)])
            for s in (".L", ".R")]
    ids = np.r_[np.flatnonzero(legs[0]), np.flatnonzero(legs[1])]
    local = np.full(len(legs[0]), -1)
    local[ids] = np.arange(len(ids))
    Fl = local[np.vstack([F[leg[F].all(1)] for leg in legs])].astype(np.int32)
    V = body.pose(m.rotations, m.root_translation).vertices
    mesh = ipctk.CollisionMesh(V[0][ids], ipctk.edges(Fl), Fl)
    mesh.can_collide = ipctk.make_vertex_patches_filter(np.r_[np.zeros(legs[0].sum()), np.ones(legs[1].sum())].astype(np.int32))
    assert not ipctk.has_intersections(mesh, V[0][ids])


def test_cmu_collars_keep_anny_rest_shoulders(bodies, tmp_path):
    """CMU's collar joints sit at the neck base, its shoulders 26 deg above them; Anny's clavicle
    runs 10 deg down from beside the sternum. A collar's direction in a zero pose says where the
    skeleton puts its collar joint as much as a pose: the collars are calibrated on the clip's
    average collar pose, which is Anny's rest. Standing still, Anny's shoulders stay at rest on
    the chest (aimed at the file's collars they rose 8.7 cm: a shrug in every frame of the CMU clips), and
    the arms still hang along the file's."""
    body = bodies[0]
    sk = _write_cmu_still(tmp_path / "cmu.bvh")
    m = import_bvh(tmp_path / "cmu.bvh", body)
    assert m.meta["mapped_joints"]["LeftCollar"] == "clavicle.L"
    J = body.pose(m.rotations, m.root_translation).joints
    n, R = body.bone_names.index, body.rest_joints
    names = [j[0] for j in sk]
    C = np.array(m.meta["axes"])
    X, _ = _pose_points(body, m.rotations, m.root_translation)
    for s, S in (("L", "Left"), ("R", "Right")):
        # the shoulder where Anny's rest puts it on the chest (spine01, Anny's collars' parent)
        rel = np.einsum("tji,tj->ti", X[:, n("spine01")], J[:, n(f"upperarm01.{s}")] - J[:, n("spine01")])
        assert np.abs(rel - (R[n(f"upperarm01.{s}")] - R[n("spine01")])).max() < 0.01
        want = C @ np.array(sk[names.index(f"{S}Elbow")][2])
        got = J[0, n(f"lowerarm01.{s}")] - J[0, n(f"upperarm01.{s}")]
        assert np.degrees(np.arccos(np.dot(want, got) / np.linalg.norm(want) / np.linalg.norm(got))) < 1.0
