"""Optimizers shared by the stages.

- ``adam``: :class:`Adam` on named numpy arrays with a checkpointable state (appearance's
  inverse rendering, the finite-difference physics fit);
- ``uniform``: :class:`AdamUniform`, a torch optimizer whose step keeps the gradient's relative
  sizes across a tensor (tracking's vertices); imported from its module so that the numpy
  optimizers do not load torch;
- ``lm``: :func:`lm_step`, the box-constrained Levenberg–Marquardt step (the exact-gradient physics fit).
"""

from .adam import Adam
from .lm import lm_step

__all__ = ["Adam", "lm_step"]
