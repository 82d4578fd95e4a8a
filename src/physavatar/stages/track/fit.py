"""One frame's photometric fit: the loss of Eq. 4 rendered into every training view, minimised
coarse to fine over the image pyramid with Adam and early stopping on a loss plateau."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import torch

from ...geometry import mesh_edges
from ...optim.uniform import AdamUniform
from .config import LossConfig, TrackConfig
from .gaussians import MeshGaussians
from .losses import AnchorLoss, CollisionLoss, IsometryLoss, NormalLoss, linear_to_srgb, ssim
from .views import View


class SmoothedSolve(torch.autograd.Function):
    """x = M^-1 u for the fixed SPD matrix M = I + λ L (L the graph Laplacian of the mesh).

    The "large steps" reparametrization (Nicolet et al. 2021): Adam updates u, and the vertices
    move by M^-1 of it, a smooth field. Photometric gradients per vertex are noisy (each sees a
    few pixels of texture); through M^-1 they act on whole neighbourhoods, so a limb that moved
    several pixels between frames is followed in tens of steps instead of being torn apart.
    M's rows sum to one (L 1 = 0): a uniform shift of u is the same shift of x, so step sizes
    keep their meaning in metres. M is symmetric, so the backward pass is the same solve.
    """

    @staticmethod
    def forward(ctx, u, solve):
        ctx.solve = solve
        return torch.from_numpy(solve(u.detach().double().numpy())).to(u.dtype)

    @staticmethod
    def backward(ctx, g):
        return torch.from_numpy(ctx.solve(g.double().numpy())).to(g.dtype), None


def smoothing_solver(n_vertices: int, faces: np.ndarray, lam: float):
    """A function [V, 3] -> [V, 3] applying (I + lam L)^-1 (sparse LU, factorized once)."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    e = mesh_edges(np.asarray(faces))
    A = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n_vertices, n_vertices))
    A = (A + A.T).tocsr()
    L = sp.diags(np.asarray(A.sum(1)).ravel()) - A
    lu = splu((sp.identity(n_vertices) + lam * L).tocsc())
    return lambda b: lu.solve(np.ascontiguousarray(b))


@dataclass
class FrameResult:
    """One fitted frame: vertices [V, 3] float32, the Gaussians' colours, iterations over all
    levels and the final loss terms at the finest level."""

    vertices: np.ndarray
    colors: np.ndarray
    iterations: int
    terms: dict = field(default_factory=dict)


def _loss_terms(model: MeshGaussians, vertices, colors, log_scales, opacity_logits, views: list[View],
                cfg: LossConfig, iso: IsometryLoss | None, normal: NormalLoss | None,
                collision: CollisionLoss | None = None, anchor: AnchorLoss | None = None) -> dict:
    preds, alphas = [], []
    splats = model.splats(vertices, colors, log_scales, opacity_logits)
    for v in views:
        out = model.rasterize(splats, v.camera)
        preds.append(linear_to_srgb(out["rgb"]))
        alphas.append(out["alpha"])
    pred = torch.stack(preds)
    target = torch.stack([v.image for v in views])
    l1 = (pred - target).abs().mean()
    s = ssim(pred, target)
    terms = {"l1": l1, "ssim": s}
    render = cfg.l1_weight * l1 + (1 - cfg.l1_weight) * (1 - s)
    if cfg.mask_weight > 0:
        m = (torch.stack(alphas) - torch.stack([v.mask for v in views])).abs().mean()
        terms["mask"] = m
        render = render + cfg.mask_weight * m
    terms["render"] = render
    loss = render
    for name, term, weight in (("iso", iso, cfg.iso_weight), ("normal", normal, cfg.normal_weight),
                               ("collision", collision, cfg.collision_weight), ("anchor", anchor, cfg.anchor_weight)):
        if term is not None:
            terms[name] = term(vertices)
            loss = loss + weight * terms[name]
    terms["loss"] = loss
    return terms


def fit_frame(model: MeshGaussians, vertices: np.ndarray, pyramid: list[list[View]], cfg: TrackConfig,
              first: bool, iso: IsometryLoss | None = None, normal: NormalLoss | None = None,
              solve=None, collision: CollisionLoss | None = None, anchor: AnchorLoss | None = None,
              refine_first: bool = False) -> FrameResult:
    """Fit one frame over the pyramid (coarse to fine).

    ``first``: optimize colours, log-scales and opacity logits of ``model`` in place (vertices
    fixed); otherwise optimize ``vertices`` and colours, leaving scales and opacities alone.
    ``refine_first`` (with ``first`` False): frame 1's vertex fit after its colour fit
    (``fit.first_vertex_iters`` per level; colours as on later frames).
    Returns the fitted vertices and colours (also left in ``model.colors``).
    """
    fit = cfg.fit
    # with colours fixed after frame 1, later frames weigh the silhouette by mask_weight_track
    loss_cfg = cfg.loss if first else replace(cfg.loss, mask_weight=cfg.loss.mask_weight_track)
    V0 = torch.from_numpy(np.asarray(vertices, np.float32)).clone()
    U = torch.zeros_like(V0)  # the smoothed offset's parameter (x = V0 + M^-1 U)

    def current():
        if first:
            return V0
        return V0 + (SmoothedSolve.apply(U, solve) if solve is not None else U)

    colors = model.colors.clone().requires_grad_(True)
    if first:
        log_scales = model.log_scales.clone().requires_grad_(True)
        opac = model.opacity_logits.clone().requires_grad_(True)
        groups = [(colors, fit.lr_colors), (log_scales, fit.lr_scales), (opac, fit.lr_opacity)]
        iso = normal = collision = anchor = None  # vertices are fixed: these terms are constants
    else:
        log_scales, opac = model.log_scales, model.opacity_logits
        U.requires_grad_(True)
        groups = [(colors, fit.lr_colors_track), (U, fit.lr_vertices)]
    n_levels = [fit.iters_first] * len(pyramid) if first else [fit.first_vertex_iters] * len(pyramid) if refine_first \
        else (list(fit.level_iters) if fit.level_iters is not None else [fit.iters] * len(pyramid))
    finest_px = pyramid[-1][0].camera.width
    total_iters = 0
    terms = {}
    for views, n_max in zip(pyramid, n_levels):
        # larger pixels, larger vertex steps: keep the step a fixed fraction of a pixel
        px_ratio = finest_px / views[0].camera.width
        lrs = [lr * (px_ratio if p is U else 1.0) for p, lr in groups]
        decay = fit.lr_decay ** (1.0 / max(n_max - 1, 1))
        opts = []
        for (p, _), lr in zip(groups, lrs):
            kind = AdamUniform if (p is U and fit.vertex_optimizer == "uniform") else torch.optim.Adam
            opts.append(kind([p], lr=lr, quantile=fit.uniform_quantile) if kind is AdamUniform else kind([p], lr=lr))
        scheds = [torch.optim.lr_scheduler.ExponentialLR(o, decay) for o in opts]
        history: list[float] = []
        for it in range(n_max):
            for o in opts:
                o.zero_grad(set_to_none=True)
            terms = _loss_terms(model, current(), colors, log_scales, opac, views, loss_cfg, iso, normal, collision, anchor)
            terms["loss"].backward()
            for o, sc in zip(opts, scheds):
                o.step()
                sc.step()
            with torch.no_grad():
                colors.clamp_(0.0, 1.0)
            history.append(float(terms["loss"].detach()))
            total_iters += 1
            k = fit.check_every
            if it + 1 >= max(fit.min_iters, 2 * k) and (it + 1) % k == 0:
                prev, last = np.mean(history[-2 * k:-k]), np.mean(history[-k:])
                if prev - last < fit.plateau_tol * abs(prev):
                    break
    with torch.no_grad():
        V = current().detach()
        final = _loss_terms(model, V, colors.detach(), log_scales.detach(), opac.detach(),
                            pyramid[-1], loss_cfg, iso, normal, collision, anchor)
    model.colors = colors.detach().clone()
    if first:
        model.log_scales = log_scales.detach().clone()
        model.opacity_logits = opac.detach().clone()
    return FrameResult(V.numpy().astype(np.float32), model.colors.numpy().astype(np.float32),
                       total_iters, {k: float(v) for k, v in final.items()})

