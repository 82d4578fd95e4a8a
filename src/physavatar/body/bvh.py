"""BVH motion capture import, retargeted to the Anny skeleton.

BVH (Biovision hierarchy) joints rotate their subtree about the joint, with Euler channels in
the joint's rest frame, which in CMU / Mixamo-style files is aligned with the world. Anny's
``local-ref`` pose convention is the same (world-aligned axes), so retargeting is:

1. Forward kinematics in the BVH file: global rotation ``G_j`` (relative to the BVH rest) of
   every joint per frame.
2. Change of axes ``C``: BVH files are usually y-up; Anny is z-up, facing -y, left at +x. ``C``
   is found from the BVH rest skeleton itself (up = hips -> head, left = right hip -> left hip),
   so files facing any direction import upright and facing the camera convention.
3. Rest-pose alignment ``S_b``: the BVH rest pose (CMU: arms hanging down; Mixamo: T-pose)
   differs from Anny's (A-pose). For each mapped bone, ``S_b`` is the smallest rotation taking
   Anny's rest bone direction onto the BVH rest direction of the same segment, so the world
   rotation of bone ``b`` is ``X_b = C G_j Cᵀ S_b``.
4. Unmapped Anny bones inherit their parent's world rotation; local rotations are
   ``D_b = X_parent(b)ᵀ X_b``, stored as axis-angle.
5. The root translation is the hips' trajectory, scaled by the ratio of leg lengths (Anny's hip
   to ankle over the file's), made relative to the first frame horizontally.

The joint-name mapping (``DEFAULT_MAP``) covers the CMU (cgspeed/bvh11 names) and Mixamo
conventions and can be overridden with a JSON file ``{"BVHJointName": "anny_bone", ...}``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import PhysavatarError
from .model import BodyModel, axis_angle_to_matrix, matrix_to_axis_angle
from .motion import Motion

# BVH joint name -> Anny bone. Joints that are not listed do not drive a bone (their rotation
# still moves their children through the BVH forward kinematics).
DEFAULT_MAP: dict[str, str] = {
    # CMU (cgspeed / bvh11 conversions)
    "Hips": "root",
    "LHipJoint": "pelvis.L", "RHipJoint": "pelvis.R",
    "LeftHip": "upperleg01.L", "RightHip": "upperleg01.R",
    "LeftUpLeg": "upperleg01.L", "RightUpLeg": "upperleg01.R",
    "LeftKnee": "lowerleg01.L", "RightKnee": "lowerleg01.R",
    "LeftLeg": "lowerleg01.L", "RightLeg": "lowerleg01.R",
    "LeftAnkle": "foot.L", "RightAnkle": "foot.R",
    "LeftFoot": "foot.L", "RightFoot": "foot.R",
    "lowerback": "spine05", "LowerBack": "spine05",
    "Chest": "spine03", "Spine": "spine03",
    "Chest2": "spine01", "Spine1": "spine01",
    "lowerneck": "neck01", "Neck": "neck02", "Neck1": "neck03", "Head": "head",
    "LeftCollar": "clavicle.L", "RightCollar": "clavicle.R",
    "LeftShoulder": "upperarm01.L", "RightShoulder": "upperarm01.R",
    "LeftArm": "upperarm01.L", "RightArm": "upperarm01.R",
    "LeftElbow": "lowerarm01.L", "RightElbow": "lowerarm01.R",
    "LeftForeArm": "lowerarm01.L", "RightForeArm": "lowerarm01.R",
    "LeftWrist": "wrist.L", "RightWrist": "wrist.R",
    "LeftHand": "wrist.L", "RightHand": "wrist.R",
    # Mixamo ("mixamorig:" prefixes are stripped before lookup)
    "Spine2": "spine01",
}
# CMU names where "LeftShoulder" is the clavicle (Mixamo, cgspeed "LeftShoulder/LeftArm" files):
# resolved in _resolve_map by looking at whether "LeftArm" exists.

_LEFT_HIP = ("LeftHip", "LeftUpLeg", "LHipJoint")
_RIGHT_HIP = ("RightHip", "RightUpLeg", "RHipJoint")
_HEAD = ("Head", "Neck1", "Neck")
_ANKLE = ("LeftAnkle", "LeftFoot")


@dataclass
class BvhSkeleton:
    names: list[str]
    parents: np.ndarray  # [J]
    offsets: np.ndarray  # [J, 3] in file units
    channels: list[list[str]]
    end_sites: dict[int, np.ndarray]  # joint index -> end-site offset


@dataclass
class BvhFile:
    skeleton: BvhSkeleton
    frame_time: float
    data: np.ndarray  # [T, n_channels]

    @property
    def fps(self) -> float:
        return 1.0 / self.frame_time


def read_bvh(path: str | Path) -> BvhFile:
    path = Path(path)
    if not path.is_file():
        raise PhysavatarError(path, "file not found")
    try:
        text = path.read_text(errors="strict")
        return _parse_bvh(text)
    except PhysavatarError:
        raise
    except Exception as e:
        raise PhysavatarError(path, f"not a readable BVH file ({type(e).__name__}: {e})") from None


def _parse_bvh(text: str) -> BvhFile:
    tokens = text.split()
    if not tokens or tokens[0] != "HIERARCHY":
        raise ValueError("missing HIERARCHY")
    names, parents, offsets, channels, end_sites = [], [], [], [], {}
    stack: list[int] = []
    i = 1
    pending_end = False
    while i < len(tokens) and tokens[i] != "MOTION":
        tok = tokens[i]
        if tok in ("ROOT", "JOINT"):
            names.append(tokens[i + 1])
            parents.append(stack[-1] if stack else -1)
            offsets.append(np.zeros(3))
            channels.append([])
            i += 2
        elif tok == "End":
            pending_end = True
            i += 2
        elif tok == "{":
            stack.append(-2 if pending_end else len(names) - 1)
            i += 1
        elif tok == "}":
            stack.pop()
            pending_end = False
            i += 1
        elif tok == "OFFSET":
            off = np.array([float(x) for x in tokens[i + 1:i + 4]])
            if stack and stack[-1] == -2:
                # the end site belongs to the innermost joint still open
                owner = [s for s in stack if s >= 0][-1]
                end_sites[owner] = off
            else:
                offsets[-1] = off
            i += 4
        elif tok == "CHANNELS":
            n = int(tokens[i + 1])
            channels[-1] = tokens[i + 2:i + 2 + n]
            i += 2 + n
        else:
            raise ValueError(f"unexpected token {tok!r} in HIERARCHY")
    if i >= len(tokens):
        raise ValueError("missing MOTION section")
    if not names:
        raise ValueError("no joints")
    m = re.search(r"Frames:\s*(\d+)\s+Frame\s+Time:\s*([0-9.eE+-]+)", " ".join(tokens[i:i + 6]))
    if not m:
        raise ValueError("missing 'Frames:' / 'Frame Time:'")
    n_frames, frame_time = int(m.group(1)), float(m.group(2))
    if frame_time <= 0:
        raise ValueError(f"frame time must be positive, got {frame_time}")
    values = tokens[i + 6:]
    n_ch = sum(len(c) for c in channels)
    if len(values) < n_frames * n_ch:
        raise ValueError(f"expected {n_frames} frames of {n_ch} channels, found {len(values)} numbers")
    data = np.array(values[: n_frames * n_ch], dtype=np.float64).reshape(n_frames, n_ch)
    if not np.isfinite(data).all():
        raise ValueError("motion data contains NaN or infinite values")
    sk = BvhSkeleton(names, np.array(parents), np.array(offsets), channels, end_sites)
    return BvhFile(sk, frame_time, data)


def _euler_to_matrix(angles_deg: np.ndarray, order: list[str]) -> np.ndarray:
    """[T, 3] angles in channel order -> [T, 3, 3]; R = R_c0 R_c1 R_c2 (BVH convention)."""
    T = angles_deg.shape[0]
    R = np.broadcast_to(np.eye(3), (T, 3, 3)).copy()
    for k, axis in enumerate(order):
        v = np.zeros((T, 3))
        v[:, "XYZ".index(axis)] = np.radians(angles_deg[:, k])
        R = R @ axis_angle_to_matrix(v)
    return R


def bvh_global(b: BvhFile) -> tuple[np.ndarray, np.ndarray]:
    """Forward kinematics: global rotations [T, J, 3, 3] and positions [T, J, 3] (file units)."""
    sk = b.skeleton
    T, J = b.data.shape[0], len(sk.names)
    G = np.zeros((T, J, 3, 3))
    P = np.zeros((T, J, 3))
    col = 0
    for j in range(J):
        ch = sk.channels[j]
        pos = np.tile(sk.offsets[j], (T, 1))
        rot_ch, rot_cols = [], []
        for c in ch:
            if c.endswith("position"):
                pos[:, "XYZ".index(c[0])] = b.data[:, col]
            else:
                rot_ch.append(c[0])
                rot_cols.append(col)
            col += 1
        Rl = _euler_to_matrix(b.data[:, rot_cols], rot_ch) if rot_ch else np.broadcast_to(np.eye(3), (T, 3, 3))
        p = sk.parents[j]
        if p < 0:
            G[:, j] = Rl
            P[:, j] = pos
        else:
            G[:, j] = G[:, p] @ Rl
            P[:, j] = P[:, p] + np.einsum("tij,tj->ti", G[:, p], pos)
    return G, P


def _rest_positions(sk: BvhSkeleton) -> np.ndarray:
    P = np.zeros((len(sk.names), 3))
    for j, p in enumerate(sk.parents):
        P[j] = sk.offsets[j] + (P[p] if p >= 0 else 0)
    return P


def _min_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation taking direction a onto direction b."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    v = np.cross(a, b)
    s, c = np.linalg.norm(v), float(np.dot(a, b))
    if s < 1e-9:
        if c > 0:
            return np.eye(3)
        perp = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])
        return axis_angle_to_matrix(np.pi * perp / np.linalg.norm(perp))
    return axis_angle_to_matrix(v / s * np.arctan2(s, c))


def _find(names, candidates):
    for c in candidates:
        if c in names:
            return names.index(c)
    return None


def _strip(name: str) -> str:
    return name.split(":")[-1]


def resolve_map(sk: BvhSkeleton, mapping: dict[str, str] | None) -> dict[int, str]:
    names = [_strip(n) for n in sk.names]
    base = dict(DEFAULT_MAP)
    if "LeftArm" in names:  # Mixamo-style: LeftShoulder is the clavicle, LeftArm the upper arm
        base["LeftShoulder"], base["RightShoulder"] = "clavicle.L", "clavicle.R"
    if mapping:
        base.update(mapping)
    return {j: base[n] for j, n in enumerate(names) if n in base and base[n]}


def import_bvh(path: str | Path, body: BodyModel | None = None, mapping: dict[str, str] | str | Path | None = None,
               name: str | None = None) -> Motion:
    """Read a BVH file and retarget it to Anny (see module doc). Keeps the file's fps.

    Args:
        path: the .bvh file.
        body: the Anny body to retarget to (default shape if None).
        mapping: overrides of ``DEFAULT_MAP``: a dict or a JSON file of ``{bvh_joint: anny_bone}``
            (an empty string un-maps a joint).
    """
    path = Path(path)
    b = read_bvh(path)
    if isinstance(mapping, (str, Path)):
        from ..files import read_json

        mapping = read_json(mapping)
    body = body or BodyModel()
    sk = b.skeleton
    names = [_strip(n) for n in sk.names]
    jmap = resolve_map(sk, mapping)
    anny_names = body.bone_names
    bad = sorted({v for v in jmap.values() if v not in anny_names})
    if bad:
        raise PhysavatarError(path, f"joint mapping names unknown Anny bones {bad}")
    if 0 not in jmap:
        raise PhysavatarError(path, f"the root joint {sk.names[0]!r} must map to Anny's 'root'")

    rest = _rest_positions(sk)
    lh, rh, hd = _find(names, _LEFT_HIP), _find(names, _RIGHT_HIP), _find(names, _HEAD)
    if lh is None or rh is None or hd is None:
        raise PhysavatarError(path, "cannot find hips and head joints to orient the skeleton "
                              "(expected e.g. LeftHip/LeftUpLeg, RightHip/RightUpLeg, Head)")
    up = rest[hd] - rest[0]
    up /= np.linalg.norm(up)
    left = rest[lh] - rest[rh]
    if np.linalg.norm(left) < 1e-9:  # hip joints at the hips (zero offsets): use their children
        kids_l = [k for k in range(len(names)) if sk.parents[k] == lh]
        kids_r = [k for k in range(len(names)) if sk.parents[k] == rh]
        left = rest[kids_l[0]] - rest[kids_r[0]]
    left -= np.dot(left, up) * up
    left /= np.linalg.norm(left)
    fwd = np.cross(left, up)
    # C maps file axes to Anny's: up -> +z, left -> +x, forward -> -y.
    C = np.stack([left, -fwd, up])  # rows: Anny axes in file coordinates

    G, P = bvh_global(b)
    T = G.shape[0]
    anny_rest = body.rest_joints
    aidx = {n: i for i, n in enumerate(anny_names)}

    # Per mapped joint: rest alignment S_b from the segment to its nearest mapped descendant.
    children = {j: [k for k in range(len(names)) if sk.parents[k] == j] for j in range(len(names))}
    S: dict[int, np.ndarray] = {}
    order = list(range(len(names)))  # BVH joints are listed parents-first
    for j in order:
        if j not in jmap or j == 0:
            continue
        bj = aidx[jmap[j]]
        target = _nearest_mapped_descendant(j, children, jmap, rest, aidx, anny_rest, body)
        if target is None:
            # a leaf: inherit the nearest mapped ancestor's alignment
            p = sk.parents[j]
            while p >= 0 and p not in S:
                p = sk.parents[p]
            S[j] = S.get(p, np.eye(3))
            continue
        k = target
        a = anny_rest[aidx[jmap[k]]] - anny_rest[bj]
        r = C @ (rest[k] - rest[j])
        S[j] = _min_rotation(a, r)
    S[0] = np.eye(3)

    # World rotations of mapped Anny bones; unmapped bones inherit their parent's.
    X = np.zeros((T, len(anny_names), 3, 3))
    mapped = {aidx[v]: j for j, v in jmap.items()}
    parents = body.parents
    for bidx in range(len(anny_names)):  # Anny bones are listed parents-first
        if bidx in mapped:
            j = mapped[bidx]
            X[:, bidx] = C @ G[:, j] @ C.T @ S[j]
        elif parents[bidx] >= 0:
            X[:, bidx] = X[:, parents[bidx]]
        else:
            X[:, bidx] = np.eye(3)
    D = X.copy()
    for bidx in range(1, len(anny_names)):
        D[:, bidx] = np.swapaxes(X[:, parents[bidx]], -1, -2) @ X[:, bidx]
    rot = matrix_to_axis_angle(D.reshape(-1, 3, 3)).reshape(T, len(anny_names), 3)

    # Root translation: scale by leg length, relative to the first frame horizontally.
    ank = _find(names, _ANKLE)
    file_leg = rest[lh if ank is None else ank] - rest[lh]
    la = anny_rest[aidx["upperleg01.L"]] - anny_rest[aidx["foot.L"]]
    scale = float(np.linalg.norm(la) / max(np.linalg.norm(file_leg), 1e-9)) if ank is not None else 0.056
    hips = (P[:, 0] @ C.T) * scale
    tr = hips - hips[0]
    # Vertical: the hips' height above the ankles in the first frame (feet assumed on the
    # floor there), relative to that height when standing in the file's rest pose, so standing
    # straight puts Anny's rest body on the floor whatever the two pelvis proportions.
    if ank is not None:
        feet = [k for k in (ank, _find(names, ("RightAnkle", "RightFoot"))) if k is not None]
        floor0 = min(float((P[0, k] @ C.T)[2]) for k in feet)
        rest_h = float(C[2] @ (rest[0] - rest[ank]))
        tr[:, 2] = ((P[:, 0] @ C.T)[:, 2] - floor0 - rest_h) * scale
    return Motion(name or path.stem, b.fps, anny_names, rot, tr,
                  {"source": str(path), "scale_m_per_unit": scale, "mapped_joints": {sk.names[j]: v for j, v in jmap.items()}})


def _nearest_mapped_descendant(j, children, jmap, rest, aidx, anny_rest, body):
    """The mapped descendant of BVH joint j at the smallest depth with a non-zero rest offset
    whose Anny bone descends from j's; ties broken by alignment with Anny's rest bone axis."""
    bj = aidx[jmap[j]]
    anny_parents = body.parents

    def anny_descends(c):
        p = anny_parents[c]
        while p >= 0:
            if p == bj:
                return True
            p = anny_parents[p]
        return False

    frontier = list(children[j])
    while frontier:
        cands = [k for k in frontier if k in jmap and np.linalg.norm(rest[k] - rest[j]) > 1e-6
                 and anny_descends(aidx[jmap[k]])]
        if cands:
            axis = body.rest_bone_axes[bj][:, 1]  # Anny bones point along their local y
            def score(k):
                d = anny_rest[aidx[jmap[k]]] - anny_rest[bj]
                return -np.dot(d / max(np.linalg.norm(d), 1e-12), axis)
            return min(cands, key=score)
        frontier = [c for k in frontier for c in children[k]]
    return None


def write_bvh(path: str | Path, names, parents, offsets, channels_per_joint, data, frame_time) -> None:
    """Write a BVH file (used by tests and for exporting simple skeletons)."""
    from ..files import write_text_atomic

    children = {j: [k for k in range(len(names)) if parents[k] == j] for j in range(len(names))}
    lines = ["HIERARCHY"]

    def emit(j, depth):
        ind = "  " * depth
        lines.append(f"{ind}{'ROOT' if parents[j] < 0 else 'JOINT'} {names[j]}")
        lines.append(f"{ind}{{")
        lines.append(f"{ind}  OFFSET {' '.join(f'{x:.6f}' for x in offsets[j])}")
        ch = channels_per_joint[j]
        lines.append(f"{ind}  CHANNELS {len(ch)} {' '.join(ch)}")
        if not children[j]:
            lines.extend([f"{ind}  End Site", f"{ind}  {{", f"{ind}    OFFSET 0 0.1 0", f"{ind}  }}"])
        for k in children[j]:
            emit(k, depth + 1)
        lines.append(f"{ind}}}")

    emit(0, 0)
    lines += ["MOTION", f"Frames: {len(data)}", f"Frame Time: {frame_time:.7f}"]
    lines += [" ".join(f"{x:.6f}" for x in row) for row in np.asarray(data)]
    write_text_atomic(path, "\n".join(lines) + "\n")
