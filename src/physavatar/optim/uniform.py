"""Adam with one second-moment normaliser per tensor (torch): steps keep the gradient's relative sizes."""

from __future__ import annotations

import torch


class AdamUniform(torch.optim.Optimizer):
    """Adam whose second moment is normalised by one value for the whole tensor, not per entry
    (Nicolet et al. 2021, ``largesteps.optimize.AdamUniform``, uses the maximum).

    Per-entry Adam moves every entry about one step size per iteration however weak its
    gradient, so vertices whose gradient is only noise (hidden or low-contrast) wander as far as
    the well-observed ones. With one normaliser the update keeps the gradient's relative sizes:
    the best-observed vertex moves about a step, a vertex with a hundredth of its gradient a
    hundredth of that.

    ``quantile`` < 1: rows (vertices) whose RMS gradient is above that quantile over rows take
    per-row Adam steps, the others steps proportional to their gradient; with the maximum a few
    vertices on high-contrast edges set the scale and hold everything else still
    (docs/tracking.md has the measurements behind the default).
    """

    def __init__(self, params, lr: float = 1e-3, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8,
                 quantile: float = 1.0):
        super().__init__(params, dict(lr=lr, betas=betas, eps=eps, quantile=quantile))

    @torch.no_grad()
    def step(self, closure=None):
        for group in self.param_groups:
            b1, b2 = group["betas"]
            for p in group["params"]:
                if p.grad is None:
                    continue
                st = self.state[p]
                if not st:
                    st["step"] = 0
                    st["m"] = torch.zeros_like(p)
                    st["v"] = torch.zeros_like(p)
                st["step"] += 1
                st["m"].mul_(b1).add_(p.grad, alpha=1 - b1)
                st["v"].mul_(b2).addcmul_(p.grad, p.grad, value=1 - b2)
                m = st["m"] / (1 - b1 ** st["step"])
                v = st["v"] / (1 - b2 ** st["step"])
                # per row (vertex) RMS gradient; the normaliser is at least its quantile over rows
                rms = v.reshape(len(v), -1).sum(1).sqrt()
                floor = rms.max() if group["quantile"] >= 1 else torch.quantile(rms, group["quantile"])
                denom = torch.maximum(rms, floor).reshape((-1,) + (1,) * (v.ndim - 1))
                p.sub_(group["lr"] * m / (denom + group["eps"]))
