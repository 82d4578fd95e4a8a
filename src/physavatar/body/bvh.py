"""BVH motion capture: reading, forward kinematics, writing, and import onto Anny.

BVH (Biovision hierarchy) joints rotate their subtree about the joint with Euler channels
(``R = R_c0 R_c1 R_c2`` in the file's channel order) in the joint's zero-pose frame; a joint may
also carry position channels (3 or 6 channels per joint), which replace its offset. Import:

1. forward kinematics: every joint's global rotation since the zero pose and position per frame;
2. the joint map (:mod:`physavatar.body.skeleton_map`: names and structure, ``--mapping``
   overrides), checked to have the hips and both legs;
3. retargeting onto Anny (:mod:`physavatar.body.retarget`: axes and scale from the skeleton,
   any zero pose: T, A, arms down or bones along a local axis).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import PhysavatarError
from .model import BodyModel, axis_angle_to_matrix
from .motion import Motion


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


_SPACE = "\ue000"  # stands for a space inside a joint name while the file is split into words


def _parse_bvh(text: str) -> BvhFile:
    # joint names may hold spaces ("Bip01 L Thigh"): the rest of a ROOT/JOINT line is the name
    text = re.sub(r"(?m)^(\s*(?:ROOT|JOINT))[ \t]+([^\n{]*?)[ \t]*(\{?)[ \t]*$",
                  lambda m: " ".join([m.group(1), re.sub(r"[ \t]", _SPACE, m.group(2)), m.group(3)]), text)
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
            names.append(tokens[i + 1].replace(_SPACE, " "))
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
    if n_frames < 1:
        raise ValueError("no frames")
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


def zero_pose(b: BvhFile) -> np.ndarray:
    """[J, 3] joint positions with every rotation channel zero (position channels of non-root
    joints at their first-frame values, the root at its offset)."""
    sk = b.skeleton
    P = np.zeros((len(sk.names), 3))
    col = 0
    for j, p in enumerate(sk.parents):
        off = np.array(sk.offsets[j], dtype=float)
        for c in sk.channels[j]:
            if c.endswith("position") and p >= 0:
                off["XYZ".index(c[0])] = b.data[0, col]
            col += 1
        P[j] = off + (P[p] if p >= 0 else 0)
    return P


def load_mapping(mapping) -> dict[str, str] | None:
    """A mapping dict, or read from a JSON file ``{joint: anny_bone}``."""
    if mapping is None or isinstance(mapping, dict):
        return mapping
    from ..files import read_json

    m = read_json(mapping)
    if not isinstance(m, dict) or not all(isinstance(k, str) and isinstance(v, str) for k, v in m.items()):
        raise PhysavatarError(mapping, 'a joint mapping must be a JSON object {"joint": "anny_bone", ...}')
    return m


def map_bvh(b: BvhFile, body: BodyModel, mapping=None, path=None):
    """The joint map of a BVH file (names + structure, ``mapping`` overrides), checked."""
    from .retarget import check_map
    from .skeleton_map import map_skeleton

    sk = b.skeleton
    anny = dict(zip(body.bone_names, body.rest_joints))
    try:
        sm = map_skeleton(sk.names, sk.parents, zero_pose(b), anny, load_mapping(mapping),
                          first_frame=bvh_global(b)[1][0])
    except KeyError as e:
        raise PhysavatarError(path, str(e.args[0])) from None
    check_map(sm, body, path)
    return sm


def bvh_source(b: BvhFile):
    """The file as a :class:`~physavatar.body.retarget.SourceMotion`."""
    from .retarget import SourceMotion

    G, P = bvh_global(b)
    return SourceMotion(list(b.skeleton.names), np.asarray(b.skeleton.parents), zero_pose(b), G, P, b.fps,
                        dict(b.skeleton.end_sites))


def import_bvh(path: str | Path, body: BodyModel | None = None, mapping: dict[str, str] | str | Path | None = None,
               name: str | None = None) -> Motion:
    """Read a BVH file and retarget it to Anny (see module doc). Keeps the file's fps.

    Args:
        path: the .bvh file.
        body: the Anny body to retarget to (default shape if None).
        mapping: overrides of the automatic joint map: a dict or a JSON file of
            ``{bvh_joint: anny_bone}`` (an empty string un-maps a joint).
    """
    from .retarget import retarget

    path = Path(path)
    b = read_bvh(path)
    body = body or BodyModel()
    sm = map_bvh(b, body, mapping, path)
    return retarget(bvh_source(b), body, sm, path=path, name=name or path.stem, meta={"source": str(path)})


def write_bvh(path: str | Path, names, parents, offsets, channels_per_joint, data, frame_time,
              end_sites: dict[int, np.ndarray] | None = None) -> None:
    """Write a BVH file (used by tests and for exporting simple skeletons). ``data`` [T, channels]
    has each joint's channels in the order of ``names`` (written in the hierarchy's order, as BVH
    requires). A leaf's end site is ``end_sites[j]`` or, by default, a third of its own offset
    further along it."""
    from ..files import write_text_atomic

    children = {j: [k for k in range(len(names)) if parents[k] == j] for j in range(len(names))}
    lines = ["HIERARCHY"]
    start = np.cumsum([0] + [len(c) for c in channels_per_joint])
    order: list[int] = []

    def emit(j, depth):
        order.append(j)
        ind = "  " * depth
        lines.append(f"{ind}{'ROOT' if parents[j] < 0 else 'JOINT'} {names[j]}")
        lines.append(f"{ind}{{")
        lines.append(f"{ind}  OFFSET {' '.join(f'{x:.6f}' for x in offsets[j])}")
        ch = channels_per_joint[j]
        lines.append(f"{ind}  CHANNELS {len(ch)} {' '.join(ch)}")
        if not children[j]:
            e = (end_sites or {}).get(j)
            e = np.asarray(offsets[j], float) / 3 if e is None else np.asarray(e, float)
            lines.extend([f"{ind}  End Site", f"{ind}  {{", f"{ind}    OFFSET {' '.join(f'{x:.6f}' for x in e)}",
                          f"{ind}  }}"])
        for k in children[j]:
            emit(k, depth + 1)
        lines.append(f"{ind}}}")

    for r in [j for j in range(len(names)) if parents[j] < 0]:
        emit(r, 0)
    cols = [c for j in order for c in range(start[j], start[j + 1])]
    lines += ["MOTION", f"Frames: {len(data)}", f"Frame Time: {frame_time:.7f}"]
    lines += [" ".join(f"{x:.6f}" for x in row) for row in np.asarray(data)[:, cols]]
    write_text_atomic(path, "\n".join(lines) + "\n")
