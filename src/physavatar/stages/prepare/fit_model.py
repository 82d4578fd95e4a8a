"""The body fit's model (:mod:`.body_fit`): the differentiable Anny with the fit's
parameterisation (the moving bones, the fingers' curl), the detector's keypoints on it, and the
extremities the clothing terms leave out."""

from __future__ import annotations

import numpy as np
import torch

from ...body.differentiable import DTYPE, DiffBody
from ...errors import PhysavatarError
from .keypoints import KEYPOINT_WEIGHT, MEDIAPIPE_TO_ANNY

# -- the model's keypoints -----------------------------------------------------------------------

def _keypoint_vertices(rest: np.ndarray, body: DiffBody) -> dict[str, int]:
    """Surface points of the keypoints that are not joints, picked on the rest body (faces -y,
    left at +x, z up)."""
    w = body.weights.numpy()
    names = body.bone_names
    dom = np.array([names[i] for i in w.argmax(1)])
    out = {}
    head = np.flatnonzero(np.char.startswith(dom.astype(str), "head"))
    if len(head):
        out["nose"] = int(head[np.argmin(rest[head, 1])])
        zc = rest[head, 2].mean()
        band = head[np.abs(rest[head, 2] - zc) < 0.04]
        band = band if len(band) else head
        out["ear.L"] = int(band[np.argmax(rest[band, 0])])
        out["ear.R"] = int(band[np.argmin(rest[band, 0])])
    for s in ("L", "R"):
        foot = np.flatnonzero([d == f"foot.{s}" or d.startswith("toe") and d.endswith(s) for d in dom])
        if len(foot):
            low = foot[rest[foot, 2] < rest[foot, 2].min() + 0.03]
            out[f"heel.{s}"] = int(low[np.argmax(rest[low, 1])])
            out[f"toe.{s}"] = int(foot[np.argmin(rest[foot, 1])])
    return out


def _curl_axes(heads: np.ndarray, names: list[str], side: str) -> tuple[list[int], np.ndarray]:
    """The bones of one hand's four fingers (three segments each) and the axis (rest frame) about
    which a turn flexes each finger towards the palm: across the finger, in the palm's plane.

    The palm's normal is that of the plane of the fingers' direction and the thumb's side,
    oriented as a hand is (a right hand's palm faces thumb x fingers, a left hand's
    fingers x thumb; Anny's left is +x)."""
    ix = {n: i for i, n in enumerate(names)}
    wrist = heads[ix[f"wrist.{side}"]]
    base = np.array([heads[ix[f"finger{k}-1.{side}"]] for k in (2, 3, 4, 5)])
    tip = np.array([heads[ix[f"finger{k}-3.{side}"]] for k in (2, 3, 4, 5)])
    d = (tip - base).mean(0)
    thumb = heads[ix[f"finger1-1.{side}"]] - wrist
    n = np.cross(d, thumb) if side == "L" else np.cross(thumb, d)
    n /= np.linalg.norm(n)
    bones, axes = [], []
    for k in (2, 3, 4, 5):
        dk = heads[ix[f"finger{k}-3.{side}"]] - heads[ix[f"finger{k}-1.{side}"]]
        a = np.cross(dk, n)
        a /= np.linalg.norm(a)
        for j in (1, 2, 3):
            bones.append(ix[f"finger{k}-{j}.{side}"])
            axes.append(a)
    return bones, np.array(axes)


# the thumbs' first two joints (fitted with keypoints: body_fit.BodyFitConfig.fit_thumbs)
THUMB_BONES = ("finger1-1.L", "finger1-2.L", "finger1-1.R", "finger1-2.R")


class _Model:
    """The differentiable body with the fit's parameterisation (the moving bones only, the
    thumbs' joints too with ``thumbs``, and with ``curl`` one flexion angle per hand for its four
    fingers, an extra row of ``rot``)."""

    MAX_CURL = 1.4  # [rad] per finger joint: a fist

    def __init__(self, cfg, curl: bool = False, thumbs: bool = False):  # cfg: body_fit.BodyFitConfig
        self.body = DiffBody(cfg.topology)
        names = self.body.bone_names
        bones = tuple(cfg.bones) + tuple(b for b in THUMB_BONES if thumbs and b not in cfg.bones)
        missing = [b for b in bones if b not in names]
        if missing:
            raise PhysavatarError(None, f"body fit: bones {missing} are not Anny bones")
        self.bones = bones
        self.active = torch.as_tensor([names.index(b) for b in bones])
        self.B = len(names)
        self.n_bones = len(bones)
        self.curl = curl
        self.n_params = self.n_bones + int(curl)
        with torch.no_grad():
            v, h = self.body.rest(self.body.p0)
        if curl:
            parts = [_curl_axes(h.numpy(), names, s) for s in ("L", "R")]
            self.curl_bones = [torch.as_tensor(b) for b, _ in parts]
            self.curl_axes = [torch.as_tensor(a, dtype=DTYPE) for _, a in parts]
        kv = _keypoint_vertices(v.numpy(), self.body)
        self.kp_ids, self.kp_src = [], []
        for k, (kind, name) in MEDIAPIPE_TO_ANNY.items():
            if kind == "bone":
                self.kp_ids.append(k)
                self.kp_src.append(("bone", names.index(name)))
            elif name in kv:
                self.kp_ids.append(k)
                self.kp_src.append(("vertex", kv[name]))
        self.kp_weight = np.array([KEYPOINT_WEIGHT.get(k, 1.0) for k in self.kp_ids])

    def full_rotations(self, rot: torch.Tensor) -> torch.Tensor:
        """[T, A, 3] rotations of the moving bones (and the fingers' curl) -> [T, B, 3]."""
        R = torch.zeros(rot.shape[0], self.B, 3, dtype=DTYPE)
        R = R.index_copy(1, self.active, rot[:, :self.n_bones])
        if self.curl:
            for s, (bones, axes) in enumerate(zip(self.curl_bones, self.curl_axes)):
                angle = rot[:, self.n_bones, s].clamp(0.0, self.MAX_CURL)  # flexion only
                R = R.index_copy(1, bones, angle[:, None, None] * axes[None])
        return R

    def pose(self, rot, tau, phen):
        return self.body.pose(self.full_rotations(rot), tau, phen)

    def keypoints(self, V: torch.Tensor, H: torch.Tensor) -> torch.Tensor:
        """[T, K, 3] model positions of the detector's keypoints (order of ``kp_ids``)."""
        cols = [H[:, i] if kind == "bone" else V[:, i] for kind, i in self.kp_src]
        return torch.stack(cols, 1)


def _extremities(body: DiffBody) -> np.ndarray:
    """[V] bool: vertices mostly skinned to the bones below a wrist or a foot (fingers,
    metacarpals, toes), the parts thinner than a clothed mesh of centimetre edges resolves."""
    names, par = body.bone_names, body.parents
    ends = np.zeros(len(names), bool)
    for b in range(len(names)):
        p = par[b]
        ends[b] = p >= 0 and (ends[p] or names[p].startswith(("wrist", "foot")))
    return body.weights.numpy()[:, ends].sum(1) > 0.5
