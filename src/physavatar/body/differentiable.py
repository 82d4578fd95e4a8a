"""A differentiable Anny body in torch, for fitting shape and pose to observations.

Posing follows the convention of :mod:`physavatar.body.model` exactly (world-aligned axis-angle
per bone composed down the hierarchy, root translation, rest body on the floor), so fitted
rotations go into ``body.npz`` unchanged. What differs is speed and gradients:

- Forward kinematics runs level by level over the hierarchy (about a dozen batched steps instead
  of one step per bone), and linear blend skinning is one matrix product: a frame costs
  milliseconds, forward and backward.
- Shape: Anny's phenotype blend (age/gender/... targets) is evaluated by Anny itself at a
  linearisation point, and around it the rest vertices and bone heads are linear in the six
  phenotypes (Jacobian by central differences: 12 Anny evaluations). A fit re-linearises when
  the shape has moved (:meth:`DiffBody.relinearize`); Anny's blend is piecewise linear in each
  phenotype, so the model is exact within a piece.

The floor offset (which puts the rest body of a shape on z = 0) is not differentiated: it only
shifts the whole body vertically, which the root translation absorbs (``floor_offset`` gives the
value to subtract at the end).
"""

from __future__ import annotations

import numpy as np
import torch

from .model import PHENOTYPES, BodyModel, BodyShape, _anny, _floor_offset, one_thread

DTYPE = torch.float64


def axis_angle_to_matrix_t(r: torch.Tensor) -> torch.Tensor:
    """[..., 3] axis-angle -> [..., 3, 3] (Rodrigues, smooth at zero)."""
    theta2 = (r * r).sum(-1, keepdim=True)[..., None]
    theta = torch.sqrt(theta2 + 1e-24)
    K = torch.zeros(r.shape[:-1] + (3, 3), dtype=r.dtype)
    K[..., 0, 1], K[..., 0, 2] = -r[..., 2], r[..., 1]
    K[..., 1, 0], K[..., 1, 2] = r[..., 2], -r[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -r[..., 1], r[..., 0]
    small = theta2 < 1e-12
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / (theta2 + 1e-30))
    eye = torch.eye(3, dtype=r.dtype).expand(K.shape)
    return eye + a * K + b * (K @ K)


class DiffBody:
    """Anny at one topology with a linearised shape and batched, differentiable posing.

    Args:
        topology: Anny topology (``physavatar.body.TOPOLOGIES``).
        shape: the linearisation point (phenotypes in [0, 1]).
    """

    def __init__(self, topology: str = "collider", shape: BodyShape | None = None):
        self.topology = topology
        model = _anny(topology)
        self.bone_names = list(model.bone_labels)
        self.parents = np.asarray(model.bone_parents, dtype=np.int64)
        self.faces = model.get_triangular_faces().numpy().astype(np.int64)
        # dense skinning weights, as BodyModel.skinning_weights (clamped, rows summing to one)
        w = torch.zeros(model.vertex_bone_weights.shape[0], len(self.bone_names), dtype=DTYPE)
        w.scatter_add_(1, model.vertex_bone_indices.long(), model.vertex_bone_weights.to(DTYPE))
        w.clamp_(min=0.0)
        self.weights = w / w.sum(1, keepdim=True)  # [V, B]
        # Hierarchy levels: bones of one depth are posed together.
        depth = np.zeros(len(self.parents), int)
        for b in range(1, len(self.parents)):
            depth[b] = depth[self.parents[b]] + 1
        self.levels = [torch.as_tensor(np.flatnonzero(depth == d)) for d in range(depth.max() + 1)]
        self.relinearize(shape or BodyShape())

    # -- shape --------------------------------------------------------------------------------
    def _rest(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        model = _anny(self.topology)
        with torch.no_grad(), one_thread():
            out = model(None, phenotype_kwargs=torch.as_tensor(p[None], dtype=DTYPE))
        return out["rest_vertices"][0].numpy(), out["rest_bone_poses"][0, :, :3, 3].numpy()

    def relinearize(self, shape: BodyShape, step: float = 0.02) -> None:
        """Evaluate Anny at ``shape`` and the Jacobian of rest vertices and heads around it
        (one-sided differences, towards the middle of [0, 1])."""
        p0 = shape.as_array()
        self.p0 = torch.as_tensor(p0, dtype=DTYPE)
        v0, h0 = self._rest(p0)
        Jv, Jh = [], []
        for i in range(len(PHENOTYPES)):
            d = step if p0[i] <= 0.5 else -step
            p = p0.copy()
            p[i] += d
            v, h = self._rest(p)
            Jv.append((v - v0) / d)
            Jh.append((h - h0) / d)
        self.v0 = torch.as_tensor(v0, dtype=DTYPE)
        self.h0 = torch.as_tensor(h0, dtype=DTYPE)
        self.Jv = torch.as_tensor(np.stack(Jv), dtype=DTYPE)  # [6, V, 3]
        self.Jh = torch.as_tensor(np.stack(Jh), dtype=DTYPE)  # [6, B, 3]

    def rest(self, phen: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Rest vertices [V, 3] and bone heads [B, 3] (Anny's frame, before the floor offset)."""
        d = phen - self.p0
        return self.v0 + torch.einsum("i,ivk->vk", d, self.Jv), self.h0 + torch.einsum("i,ibk->bk", d, self.Jh)

    @staticmethod
    def floor_offset(shape: BodyShape) -> float:
        return _floor_offset(shape)

    # -- posing -------------------------------------------------------------------------------
    def forward_kinematics(self, rotations: torch.Tensor, translation: torch.Tensor, heads: torch.Tensor):
        """World rotations X [T, B, 3, 3] and posed heads [T, B, 3] (Anny frame + translation)."""
        T, B = rotations.shape[:2]
        R = axis_angle_to_matrix_t(rotations)
        par = torch.as_tensor(self.parents)
        X = [None] * len(self.levels)
        H = [None] * len(self.levels)
        Xall = torch.zeros(T, B, 3, 3, dtype=DTYPE)
        Hall = torch.zeros(T, B, 3, dtype=DTYPE)
        for d, idx in enumerate(self.levels):
            if d == 0:
                Xd = R[:, idx]
                Hd = heads[idx][None] + translation[:, None]
            else:
                p = par[idx]
                Xp, Hp = Xall[:, p], Hall[:, p]
                Xd = Xp @ R[:, idx]
                Hd = Hp + torch.einsum("tbij,bj->tbi", Xp, heads[idx] - heads[p])
            X[d], H[d] = Xd, Hd
            Xall = Xall.index_copy(1, idx, Xd)
            Hall = Hall.index_copy(1, idx, Hd)
        return Xall, Hall

    def pose(self, rotations: torch.Tensor, translation: torch.Tensor, phen: torch.Tensor):
        """Posed vertices [T, V, 3] and bone heads [T, B, 3] in Anny's frame plus ``translation``
        (add :meth:`floor_offset` in z for the world)."""
        v_rest, h_rest = self.rest(phen)
        X, H = self.forward_kinematics(rotations, translation, h_rest)
        # transform of bone b: x -> X_b (x - h_b) + H_b
        Tb = H - torch.einsum("tbij,bj->tbi", X, h_rest)  # [T, B, 3]
        A = torch.cat([X.reshape(*X.shape[:2], 9), Tb], -1)  # [T, B, 12]
        M = torch.einsum("vb,tbk->tvk", self.weights, A)  # [T, V, 12]
        Rv = M[..., :9].reshape(*M.shape[:2], 3, 3)
        V = torch.einsum("tvij,vj->tvi", Rv, v_rest) + M[..., 9:]
        return V, H

    def check_against_anny(self, shape: BodyShape, rotations: np.ndarray, translation: np.ndarray) -> float:
        """Largest vertex difference [m] to :class:`BodyModel` posing (for tests)."""
        ref = BodyModel(shape, topology=self.topology).pose(rotations, translation)
        self.relinearize(shape)
        with torch.no_grad():
            V, _ = self.pose(torch.as_tensor(rotations), torch.as_tensor(translation, dtype=DTYPE),
                             torch.as_tensor(shape.as_array()))
        V = V.numpy() + [0.0, 0.0, _floor_offset(shape)]
        return float(np.abs(V - ref.vertices).max())
