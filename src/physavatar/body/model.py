"""The Anny body model, wrapped: shape (phenotype) + per-bone pose -> posed mesh, joints, bones.

Anny (NAVER, Apache-2.0; MakeHuman CC0 assets) ships its data in the wheel and builds offline.
Its first build takes about a minute and is cached by Anny itself on disk (``ANNY_CACHE_DIR``,
default ``~/.cache/anny``); in-process we keep one model per topology.

Pose convention: each bone's rotation is an axis-angle vector in *world-aligned* axes, applied
about the bone's head and composed down the hierarchy (forward kinematics in ``world_bone_poses``):
a bone's world rotation relative to rest is ``R_root ... R_parent R_bone``. This is the BVH
convention for skeletons whose rest frames are world-aligned, so motion capture maps directly.
The root additionally translates: ``v -> R_root (v - h_root) + h_root + t``.

World placement: z up, metres, the body facing -y (its left side at +x), and the rest body's
lowest point on the floor z = 0 (the floor offset depends on the shape).
"""

from __future__ import annotations

import contextlib
import functools
import os
import sys
import threading
import warnings
from dataclasses import dataclass

import numpy as np
import torch

# Anny's own names for its topologies; ours are shorter and say what they are for.
TOPOLOGIES = {
    "full": "anny",  # 13,718 vertices: eyes, no tongue, full detail
    "notoes": "notoes",  # 12,272 vertices: no toes
    "collider": "notoes_collapse10pc",  # 1,229 vertices: the decimated collision body
    "coarse": "notoes_collapse5pc",  # 615 vertices
    "tiny": "notoes_collapse3pc",  # 369 vertices
}

PHENOTYPES = ("gender", "age", "muscle", "weight", "height", "proportions")

_lock = threading.Lock()


def _import_anny():
    """Import anny without losing sys.stdout.

    anny.utils.warp_mesh_utils swaps sys.stdout for sys.stderr while it initialises Warp and
    then sets it to sys.__stdout__, not back to what it was: under a redirected stdout (typer's
    CliRunner, rich's live display, a caller's capture) the replaced stream was dropped, and a
    dropped text wrapper closes the buffer under it. Import it once here and restore stdout.
    """
    saved_stdout = sys.stdout
    try:
        import anny
        import anny.utils.warp_mesh_utils  # noqa: F401
    finally:
        sys.stdout = saved_stdout
    return anny


@contextlib.contextmanager
def one_thread():
    """Anny's forward pass on one torch thread. Its blend-shape and skinning sums then add up in
    one order whatever the machine's core count, so the body, and everything built on it (a
    garment's mesh: the dress at 5 cm had 556 vertices on one thread and 557 on two), is the
    same bit for bit on every machine."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(n)


@functools.lru_cache(maxsize=None)
def _anny(topology: str):
    """One Anny module per topology (Anny caches the built data on disk; this caches it in RAM)."""
    if topology not in TOPOLOGIES:
        raise ValueError(f"unknown body topology {topology!r}; choose from {sorted(TOPOLOGIES)}")
    with _lock, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        os.environ.setdefault("WARP_LOG_LEVEL", "error")
        anny = _import_anny()

        # Dense LBS in torch: deterministic and needs no Warp kernel compilation.
        model = anny.Anny(topology=TOPOLOGIES[topology], skinning_method="lbs")
    model = model.to(torch.float64)
    model.eval()
    return model


@dataclass(frozen=True)
class BodyShape:
    """Anny phenotype parameters, each in [0, 1] (0.5 is the average adult)."""

    gender: float = 0.5
    age: float = 0.5
    muscle: float = 0.5
    weight: float = 0.5
    height: float = 0.5
    proportions: float = 0.5

    def __post_init__(self):
        for k in PHENOTYPES:
            v = float(getattr(self, k))
            if not np.isfinite(v) or not 0.0 <= v <= 1.0:
                raise ValueError(f"body shape parameter {k} = {v} must be in [0, 1]")

    def as_array(self) -> np.ndarray:
        return np.array([getattr(self, k) for k in PHENOTYPES], dtype=np.float64)

    @staticmethod
    def from_array(a) -> "BodyShape":
        a = np.asarray(a, dtype=np.float64).reshape(-1)
        if a.shape != (len(PHENOTYPES),):
            raise ValueError(f"body shape needs {len(PHENOTYPES)} values {PHENOTYPES}, got {a.shape}")
        return BodyShape(*map(float, a))

    def to_dict(self) -> dict:
        return {k: float(getattr(self, k)) for k in PHENOTYPES}


@dataclass
class PosedBody:
    """A posed body sequence.

    Attributes:
        vertices: [T, V, 3] world positions.
        joints: [T, B, 3] bone head positions.
        bone_transforms: [T, B, 4, 4] rest-to-posed transform of each bone (for skinning).
    """

    vertices: np.ndarray
    joints: np.ndarray
    bone_transforms: np.ndarray


def axis_angle_to_matrix(rotvec: np.ndarray) -> np.ndarray:
    """[..., 3] axis-angle (radians) -> [..., 3, 3] rotation matrices (Rodrigues)."""
    rotvec = np.asarray(rotvec, dtype=np.float64)
    theta = np.linalg.norm(rotvec, axis=-1, keepdims=True)[..., None]
    small = theta < 1e-12
    k = rotvec / np.where(theta[..., 0] < 1e-12, 1.0, theta[..., 0])
    K = np.zeros(rotvec.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2] = -k[..., 2], k[..., 1]
    K[..., 1, 0], K[..., 1, 2] = k[..., 2], -k[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -k[..., 1], k[..., 0]
    eye = np.broadcast_to(np.eye(3), K.shape)
    R = eye + np.sin(theta) * K + (1 - np.cos(theta)) * (K @ K)
    return np.where(small, eye, R)


def matrix_to_axis_angle(R: np.ndarray) -> np.ndarray:
    """[..., 3, 3] rotation matrices -> [..., 3] axis-angle, robust near 0 and pi."""
    import roma

    t = torch.as_tensor(np.asarray(R, dtype=np.float64))
    return roma.rotmat_to_rotvec(t).numpy()


class BodyModel:
    """Anny at one topology and one shape.

    Args:
        shape: phenotype parameters.
        topology: one of ``TOPOLOGIES`` (``"full"`` for rendering and templates, ``"collider"``
            for contact).
    """

    def __init__(self, shape: BodyShape | None = None, topology: str = "full"):
        self.shape = shape or BodyShape()
        self.topology = topology
        self._model = _anny(topology)
        self._phen = torch.as_tensor(self.shape.as_array()[None], dtype=torch.float64)
        with torch.no_grad(), one_thread():
            rest = self._model(None, phenotype_kwargs=self._phen)
        self._rest_bone_poses = rest["rest_bone_poses"]  # [1, B, 4, 4]
        self.floor_offset = _floor_offset(self.shape)
        off = np.array([0.0, 0.0, self.floor_offset])
        self.rest_vertices = rest["rest_vertices"][0].numpy() + off
        self.rest_joints = rest["rest_bone_heads"][0].numpy() + off
        self.faces = self._model.get_triangular_faces().numpy().astype(np.int64)
        par = self.parents
        if not all(par[b] < b for b in range(1, len(par))) or par[0] != -1:
            raise RuntimeError("Anny's bones are expected in parents-first order")

    # -- skeleton -----------------------------------------------------------------------------
    @property
    def bone_names(self) -> list[str]:
        return list(self._model.bone_labels)

    @property
    def parents(self) -> np.ndarray:
        """[B] parent index of each bone (-1 for the root)."""
        return np.asarray(self._model.bone_parents, dtype=np.int64)

    @property
    def rest_bone_axes(self) -> np.ndarray:
        """[B, 3, 3] rest orientation of each bone (columns: bone axes in world)."""
        return self._rest_bone_poses[0, :, :3, :3].numpy()

    @functools.cached_property
    def skinning_weights(self) -> np.ndarray:
        """[V, B] dense linear-blend-skinning weights (non-negative, rows sum to one)."""
        w = self._model.vertex_bone_weights.to(torch.float64)
        idx = self._model.vertex_bone_indices.long()
        dense = torch.zeros(w.shape[0], len(self.bone_names), dtype=torch.float64)
        dense.scatter_add_(1, idx, w)
        # The decimated topologies carry weights transferred by Anny with round-off negatives
        # (~1e-10); clamp and renormalize so the weights are a partition of unity.
        dense.clamp_(min=0.0)
        dense /= dense.sum(1, keepdim=True)
        return dense.numpy()

    # -- posing -------------------------------------------------------------------------------
    def world_bone_poses(self, rotations: np.ndarray, root_translation: np.ndarray) -> np.ndarray:
        """Forward kinematics in our convention -> posed bone poses W [T, B, 4, 4].

        A bone's world rotation relative to rest is X_b = X_parent R_b (world-aligned local
        rotations, BVH-style), its head goes where its parent's transform takes it, and the
        root's head moves by the root translation. W_b = [X_b R_rest_b | posed head]. Anny's
        own 'local-ref' deltas would give its *reference* pose for zero rotations, which
        differs from the rest pose by about a centimetre, so we pass world poses instead.
        """
        rotations = np.asarray(rotations, dtype=np.float64)
        T, B = rotations.shape[:2]
        Rl = axis_angle_to_matrix(rotations)
        P = self._rest_bone_poses[0].numpy()
        h = P[:, :3, 3]
        par = self.parents
        X = np.empty((T, B, 3, 3))
        head = np.empty((T, B, 3))
        for b in range(B):  # parents come first (checked in __init__)
            p = par[b]
            if p < 0:
                X[:, b] = Rl[:, b]
                head[:, b] = h[b] + root_translation
            else:
                X[:, b] = X[:, p] @ Rl[:, b]
                head[:, b] = head[:, p] + np.einsum("tij,j->ti", X[:, p], h[b] - h[p])
        W = np.zeros((T, B, 4, 4))
        W[:, :, :3, :3] = X @ P[:, :3, :3]
        W[:, :, :3, 3] = head
        W[:, :, 3, 3] = 1.0
        return W

    def pose(self, rotations: np.ndarray, root_translation: np.ndarray, chunk: int = 32) -> PosedBody:
        """Pose the body for a sequence of frames.

        Args:
            rotations: [T, B, 3] per-bone axis-angle in world-aligned axes (see module doc).
            root_translation: [T, 3] metres, added to the root (0 = standing at the origin).
        Returns:
            PosedBody with vertices [T, V, 3], joints [T, B, 3], bone_transforms [T, B, 4, 4].
        """
        rotations = np.asarray(rotations, dtype=np.float64)
        root_translation = np.asarray(root_translation, dtype=np.float64)
        B = len(self.bone_names)
        if rotations.ndim != 3 or rotations.shape[1:] != (B, 3):
            raise ValueError(f"rotations must have shape [T, {B}, 3], got {rotations.shape}")
        if root_translation.shape != (rotations.shape[0], 3):
            raise ValueError(f"root_translation must have shape [{rotations.shape[0]}, 3], got {root_translation.shape}")
        off = np.array([0.0, 0.0, self.floor_offset])
        verts, joints, transforms = [], [], []
        with torch.no_grad(), one_thread():
            for s in range(0, rotations.shape[0], chunk):
                W = torch.as_tensor(self.world_bone_poses(rotations[s:s + chunk], root_translation[s:s + chunk]))
                out = self._model(W, phenotype_kwargs=self._phen.expand(W.shape[0], -1),
                                  pose_parameterization="world")
                D = W
                verts.append(out["vertices"].numpy() + off)
                joints.append(out["bone_poses"][:, :, :3, 3].numpy() + off)
                rest = self._rest_bone_poses.expand(D.shape[0], -1, -1, -1)
                Tb = out["bone_poses"] @ torch.linalg.inv(rest)
                Tb = Tb.numpy().copy()
                # Express in our floor-offset world: T' = S T S^-1 with S a z translation.
                Tb[:, :, :3, 3] += off - np.einsum("tbij,j->tbi", Tb[:, :, :3, :3], off)
                transforms.append(Tb)
        return PosedBody(np.concatenate(verts), np.concatenate(joints), np.concatenate(transforms))

    def rest_pose(self, frames: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """Zero rotations [frames, B, 3] and translations [frames, 3]."""
        return np.zeros((frames, len(self.bone_names), 3)), np.zeros((frames, 3))


@functools.lru_cache(maxsize=64)
def _floor_offset(shape: BodyShape) -> float:
    """Height that puts the rest body of this shape on the floor (from the full topology, so
    every topology of one shape shares the same world frame)."""
    model = _anny("full")
    phen = torch.as_tensor(shape.as_array()[None], dtype=torch.float64)
    with torch.no_grad(), one_thread():
        rest = model(None, phenotype_kwargs=phen)
    return float(-rest["rest_vertices"][0, :, 2].min())


def linear_blend_skinning(rest_points: np.ndarray, weights: np.ndarray, bone_transforms: np.ndarray) -> np.ndarray:
    """Skin points with given weights.

    Args:
        rest_points: [N, 3]; weights: [N, B]; bone_transforms: [T, B, 4, 4].
    Returns:
        [T, N, 3].
    """
    A = np.einsum("nb,tbij->tnij", weights, bone_transforms[:, :, :3, :])
    return np.einsum("tnij,nj->tni", A[..., :3], rest_points) + A[..., 3]


def bone_vertex_mask(body: BodyModel, prefixes) -> np.ndarray:
    """[V] bool: vertices whose dominant skinning bone starts with one of ``prefixes``."""
    names = body.bone_names
    dom = np.argmax(body.skinning_weights, axis=1)
    sel = np.array([any(n.startswith(p) for p in prefixes) for n in names])
    return sel[dom]
