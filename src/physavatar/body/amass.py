"""AMASS / SMPL-family motions (``.npz``) retargeted onto Anny, with no SMPL model file.

An AMASS file holds ``poses`` ([T, 3·J] axis-angle: the root's global orientation, then each joint
relative to its parent, in the SMPL kinematic tree's order), ``trans`` ([T, 3] metres) and
``mocap_framerate`` (``mocap_frame_rate`` in the SMPL-X release). The width tells the body model:
72 = SMPL (24 joints), 156 = SMPL-H (52: 22 body + 2·15 finger joints), 165 = SMPL-X (55: 22 body,
jaw, two eyes, 2·15 fingers), 66 = the 22 body joints alone; files split as ``root_orient`` +
``pose_body`` are read too. Only the 22 body joints drive Anny (fingers and face are left alone).

The rotations are relative to SMPL's rest pose, so retargeting needs SMPL's rest *directions*
(a T-pose: arms out, legs straight), not Anny's (an A-pose with bent elbows): using Anny's own
rest would put every arm motion off by the 45° between the two rest poses. ``SMPL_OFFSETS`` is the
rest skeleton of the gender-neutral SMPL model with zero shape (Loper et al., "SMPL: A Skinned
Multi-Person Linear Model", SIGGRAPH Asia 2015; joints = J_regressor · v_template), as tabulated
in PHC's ``smpl_humanoid.xml`` (Luo et al., "Perpetual Humanoid Control", ICCV 2023), rewritten
in SMPL's own axes (y up, x left, z forward) and rounded to 0.1 mm. Bone *lengths* come from Anny
(rotations are transferred, not positions); ``trans`` is scaled by Anny's leg length over this
skeleton's, as the shape (``betas``) cannot be used without the model.

AMASS's world is z-up: the root orientation of a standing subject turns SMPL's y-up body upright
in z. The world's up axis is checked from the motion itself (the mean pelvis-to-head direction,
snapped to an axis) so y-up exports of SMPL motions import upright too. Zero rotations with
``root_orient = (π/2, 0, 0)`` put the SMPL body upright facing −y, which is Anny's own facing,
so the motion keeps AMASS's heading.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import PhysavatarError
from .model import BodyModel, axis_angle_to_matrix
from .motion import Motion

SMPL_NAMES = ["Pelvis", "L_Hip", "R_Hip", "Spine1", "L_Knee", "R_Knee", "Spine2", "L_Ankle", "R_Ankle", "Spine3",
              "L_Foot", "R_Foot", "Neck", "L_Collar", "R_Collar", "Head", "L_Shoulder", "R_Shoulder", "L_Elbow",
              "R_Elbow", "L_Wrist", "R_Wrist", "L_Hand", "R_Hand"]
SMPL_PARENTS = np.array([-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21])
# Rest offset of each joint from its parent [m], SMPL axes (y up, x = the body's left, z forward).
SMPL_OFFSETS = np.array([
    [0.0, 0.0, 0.0],
    [0.0695, -0.0914, -0.0068], [-0.0677, -0.0905, -0.0043], [-0.0025, 0.1090, -0.0267],
    [0.0343, -0.3752, -0.0045], [-0.0383, -0.3826, -0.0089], [0.0055, 0.1352, 0.0011],
    [-0.0136, -0.3980, -0.0437], [0.0158, -0.3984, -0.0423], [0.0015, 0.0529, 0.0254],
    [0.0264, -0.0558, 0.1193], [-0.0254, -0.0481, 0.1233], [-0.0028, 0.2139, -0.0429],
    [0.0788, 0.1217, -0.0341], [-0.0818, 0.1188, -0.0386], [0.0052, 0.0650, 0.0513],
    [0.0910, 0.0305, -0.0089], [-0.0960, 0.0326, -0.0091], [0.2596, -0.0128, -0.0275],
    [-0.2537, -0.0133, -0.0214], [0.2492, 0.0090, -0.0012], [-0.2553, 0.0078, -0.0056],
    [0.0840, -0.0082, -0.0149], [-0.0846, -0.0061, -0.0103],
])
SMPL_PELVIS = np.array([-0.0018, -0.2233, 0.0282])  # the pelvis joint in the template's frame [m]

# SMPL joint -> Anny bone (the SMPL foot joint is the ball of the foot and the hand joint the
# knuckles: they give the direction of Anny's foot and hand, and drive nothing themselves).
SMPL_TO_ANNY = {
    "Pelvis": "root", "L_Hip": "upperleg01.L", "R_Hip": "upperleg01.R", "Spine1": "spine03",
    "L_Knee": "lowerleg01.L", "R_Knee": "lowerleg01.R", "Spine2": "spine02", "L_Ankle": "foot.L",
    "R_Ankle": "foot.R", "Spine3": "spine01", "Neck": "neck01", "L_Collar": "clavicle.L", "R_Collar": "clavicle.R",
    "Head": "head", "L_Shoulder": "upperarm01.L", "R_Shoulder": "upperarm01.R", "L_Elbow": "lowerarm01.L",
    "R_Elbow": "lowerarm01.R", "L_Wrist": "wrist.L", "R_Wrist": "wrist.R",
}
MODELS = {72: "SMPL", 156: "SMPL-H", 165: "SMPL-X", 66: "SMPL body joints"}
_FPS_KEYS = ("mocap_framerate", "mocap_frame_rate", "frame_rate", "fps")


def is_amass(keys) -> bool:
    """Whether an npz's keys are an AMASS/SMPL motion (not the project's own motion format)."""
    keys = set(keys)
    return "rotations" not in keys and ("poses" in keys or {"root_orient", "pose_body"} <= keys)


def read_amass(path: str | Path) -> dict:
    """{poses [T, 24, 3], trans [T, 3], fps, model}: the body joints of an AMASS-style file (SMPL
    hand joints zero when the file has finger joints instead)."""
    path = Path(path)
    if not path.is_file():
        raise PhysavatarError(path, "file not found")
    try:
        with np.load(path, allow_pickle=False) as z:
            keys = set(z.files)
            if "poses" in keys:
                poses = np.asarray(z["poses"], dtype=np.float64)
            elif {"root_orient", "pose_body"} <= keys:
                poses = np.concatenate([z["root_orient"], z["pose_body"]], axis=-1).astype(np.float64)
            else:
                raise PhysavatarError(path, "an AMASS motion needs 'poses' (or 'root_orient' and 'pose_body')")
            if "trans" not in keys:
                raise PhysavatarError(path, "an AMASS motion needs 'trans' (root translation per frame)")
            trans = np.asarray(z["trans"], dtype=np.float64)
            fk = next((k for k in _FPS_KEYS if k in keys), None)
            if fk is None:
                raise PhysavatarError(path, f"no frame rate: expected one of {list(_FPS_KEYS)}")
            fps = float(np.asarray(z[fk]).reshape(-1)[0])
    except PhysavatarError:
        raise
    except Exception as e:
        raise PhysavatarError(path, f"not a readable AMASS .npz file ({type(e).__name__}: {e})") from None
    if poses.ndim == 3:
        poses = poses.reshape(len(poses), -1)
    if poses.ndim != 2 or poses.shape[1] % 3 or poses.shape[1] < 66:
        raise PhysavatarError(path, f"'poses' must be [frames, 3 x joints] with at least the 22 SMPL body joints "
                              f"(66 values), got shape {poses.shape}")
    n = poses.shape[1]
    model = MODELS.get(n, f"{n // 3} joints (read as SMPL's first 22)")
    if trans.shape != (len(poses), 3):
        raise PhysavatarError(path, f"'trans' must be [{len(poses)}, 3], got {trans.shape}")
    if not (np.isfinite(poses).all() and np.isfinite(trans).all()):
        raise PhysavatarError(path, "'poses' or 'trans' contains NaN or infinite values")
    if not (np.isfinite(fps) and fps > 0):
        raise PhysavatarError(path, f"the frame rate must be positive, got {fps}")
    aa = np.zeros((len(poses), 24, 3))
    keep = 24 if n == 72 else 22
    aa[:, :keep] = poses[:, : 3 * keep].reshape(len(poses), keep, 3)
    return {"poses": aa, "trans": trans, "fps": fps, "model": f"{model} ({n} values per frame)"}


def smpl_forward(poses: np.ndarray, trans: np.ndarray):
    """SMPL skeleton forward kinematics in the file's world: global rotations [T, 24, 3, 3] (from
    SMPL's rest axes) and joint positions [T, 24, 3] (trans + the template pelvis at the root)."""
    T = len(poses)
    L = axis_angle_to_matrix(poses)
    G = np.empty((T, 24, 3, 3))
    P = np.empty((T, 24, 3))
    for j, p in enumerate(SMPL_PARENTS):
        if p < 0:
            G[:, j] = L[:, j]
            P[:, j] = trans + SMPL_PELVIS
        else:
            G[:, j] = G[:, p] @ L[:, j]
            P[:, j] = P[:, p] + G[:, p] @ SMPL_OFFSETS[j]
    return G, P


def amass_source(data: dict):
    """The motion as a :class:`~physavatar.body.retarget.SourceMotion` whose zero pose is SMPL's
    T-pose stood upright in the file's world."""
    from .retarget import SourceMotion, rotation_between

    G, P = smpl_forward(data["poses"], data["trans"])
    head_dir = (P[:, 15] - P[:, 0]).mean(0)
    k = int(np.argmax(np.abs(head_dir)))
    up = np.eye(3)[k] * np.sign(head_dir[k])
    Q = rotation_between(np.array([0.0, 1.0, 0.0]), up)  # SMPL's y-up rest -> upright in the world
    rest = np.zeros((24, 3))
    for j, p in enumerate(SMPL_PARENTS):
        if p >= 0:
            rest[j] = rest[p] + Q @ SMPL_OFFSETS[j]
    axes = rotation_between(up, np.array([0.0, 0.0, 1.0]))  # the world's up onto Anny's; heading kept
    return SourceMotion(list(SMPL_NAMES), SMPL_PARENTS.copy(), rest, G @ Q.T, P, data["fps"], {}, up, axes)


def amass_map(mapping: dict[str, str] | None = None):
    """The SMPL -> Anny joint correspondence as a SkeletonMap (``mapping`` overrides by SMPL name)."""
    from .skeleton_map import SkeletonMap, _apply_explicit

    sm = SkeletonMap(list(SMPL_NAMES))
    for j, n in enumerate(SMPL_NAMES):
        if n in SMPL_TO_ANNY:
            sm.bones[j] = SMPL_TO_ANNY[n]
            sm.why[j] = f"SMPL joint {n}: Anny's {SMPL_TO_ANNY[n]} by correspondence"
        else:
            sm.why[j] = f"SMPL joint {n}: gives the direction of its parent's far end"
    if mapping:
        try:
            _apply_explicit(sm, mapping)
        except KeyError as e:
            raise PhysavatarError(None, str(e.args[0])) from None
    return sm


def import_amass(path: str | Path, body: BodyModel | None = None, mapping=None, name: str | None = None) -> Motion:
    """Read an AMASS-style ``.npz`` and retarget it onto Anny at the file's frame rate."""
    from .bvh import load_mapping
    from .retarget import retarget

    path = Path(path)
    data = read_amass(path)
    body = body or BodyModel()
    try:
        sm = amass_map(load_mapping(mapping))
    except PhysavatarError as e:
        raise PhysavatarError(path, e.problem) from None
    return retarget(amass_source(data), body, sm, path=path, name=name or path.stem,
                    meta={"source": str(path), "model": data["model"]})
