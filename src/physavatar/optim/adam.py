"""Adam on named numpy arrays, with a state that can be checkpointed and resumed exactly."""

from __future__ import annotations

from typing import Mapping

import numpy as np


class Adam:
    """Adam (Kingma & Ba 2015), bias-corrected, on named numpy arrays.

    Each name is one parameter group with its own first and second moments. The learning rate is
    given at every step (a number for all groups, or one per name; each a scalar or an array
    broadcasting against its parameter), so schedules stay with the caller. Updates are
    ``p ← p − lr · m̂ / (√v̂ + ε)`` in float64.

    :meth:`state_dict` is a flat dict of arrays (``adam_t``, ``adam_m_<name>``, ``adam_v_<name>``)
    that fits in an ``.npz`` beside the parameters; :meth:`load_state_dict` restores it, and a run
    continued from it takes the same steps as one that was never interrupted.
    """

    def __init__(self, shapes: Mapping[str, tuple], betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8):
        self.betas = (float(betas[0]), float(betas[1]))
        self.eps = float(eps)
        self.m = {k: np.zeros(s, np.float64) for k, s in shapes.items()}
        self.v = {k: np.zeros(s, np.float64) for k, s in shapes.items()}
        self.t = 0

    def step(self, params: dict[str, np.ndarray], grads: Mapping[str, np.ndarray], lr) -> dict[str, np.ndarray]:
        """One step of the groups named in ``grads``: replaces ``params[name]`` by the updated
        array (others are left alone) and returns ``params``. ``lr``: a number or array for every
        group, or a mapping name -> number or array."""
        self.t += 1
        b1, b2 = self.betas
        for k, g in grads.items():
            self.m[k] = b1 * self.m[k] + (1 - b1) * g
            self.v[k] = b2 * self.v[k] + (1 - b2) * (g * g)
            mh = self.m[k] / (1 - b1 ** self.t)
            vh = self.v[k] / (1 - b2 ** self.t)
            rate = lr[k] if isinstance(lr, Mapping) else lr
            params[k] = params[k] - rate * mh / (np.sqrt(vh) + self.eps)
        return params

    def state_dict(self) -> dict[str, np.ndarray]:
        """The step count and both moments of every group, as arrays (copies)."""
        return {"adam_t": np.int64(self.t), **{f"adam_m_{k}": v.copy() for k, v in self.m.items()},
                **{f"adam_v_{k}": v.copy() for k, v in self.v.items()}}

    def load_state_dict(self, state: Mapping[str, np.ndarray]) -> None:
        """Restore :meth:`state_dict`'s arrays (extra keys, e.g. the rest of a checkpoint, are
        ignored). Raises KeyError for a missing group and ValueError for a moment of another shape."""
        m = {k: np.array(state[f"adam_m_{k}"], np.float64) for k in self.m}
        v = {k: np.array(state[f"adam_v_{k}"], np.float64) for k in self.v}
        for k in self.m:
            if m[k].shape != self.m[k].shape or v[k].shape != self.v[k].shape:
                raise ValueError(f"Adam state of {k!r} has shape {m[k].shape}, the parameter {self.m[k].shape}")
        self.t, self.m, self.v = int(state["adam_t"]), m, v
