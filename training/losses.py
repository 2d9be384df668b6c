"""The C-VAE objective of Sec. 3.3: L = L_tsdf + beta_kl L_kl + lambda_eik L_eik, with thicker supervision.

Besides the paper's three terms, two optional ones act at points on the item's own surface (as in VecSetX):
L_surf = mean |f(p)| (the zero level set passes through the surface) and L_normal = mean (1 - cos(grad f(p),
n(p))) (its orientation follows the surface's). beta_kl follows a curriculum over steps and, for C-VAE-I, over
the normalized time t: :func:`kl_weights`. Weights come from :class:`~vnc_warp.training.config.LossConfig`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from .config import LossConfig
from .model import DiagonalGaussian

__all__ = ["tsdf_loss", "eikonal_loss", "kl_weight_at", "kl_prior_logvar", "select_eikonal_queries", "GradientQueries",
           "gradient_queries", "cvae_loss"]


def tsdf_loss(pred: torch.Tensor, target: torch.Tensor, *, kind: str = "l1", near: torch.Tensor | None = None,
              near_weight: float = 1.0) -> torch.Tensor:
    """L_tsdf: mean L1 (``"l1"``) or squared (``"mse"``) error of the truncated SDF.

    Args:
        pred: (B, Q) predicted SDF, normalised units.
        target: (B, Q) truncated ground-truth SDF, same units.
        kind: ``"l1"`` or ``"mse"``.
        near: (B, Q) bool, queries drawn near the surface; with ``near_weight`` != 1 the mean is weighted,
            ``sum w |e| / sum w`` with w = ``near_weight`` there and 1 elsewhere.
        near_weight: weight of the near-surface queries.

    Returns:
        () float32.
    """
    if pred.shape != target.shape:
        raise ValueError(f"tsdf_loss: pred {tuple(pred.shape)} and target {tuple(target.shape)} differ")
    if kind not in ("l1", "mse"):
        raise ValueError(f"tsdf_loss: kind must be 'l1' or 'mse', got {kind!r}")
    err = pred.float() - target.float()
    err = err.abs() if kind == "l1" else err.square()
    if near is None or near_weight == 1.0:
        return err.mean()
    if near.shape != err.shape:
        raise ValueError(f"tsdf_loss: near {tuple(near.shape)} does not match pred {tuple(pred.shape)}")
    w = torch.where(near, near_weight, 1.0).to(err.dtype)
    return (w * err).sum() / w.sum()


def _input_gradient(sdf: torch.Tensor, queries: torch.Tensor) -> torch.Tensor:
    """grad_x f at every query, (B, Q, 3) float32, kept in the graph (``create_graph``)."""
    if not queries.requires_grad:
        raise ValueError("the gradient terms need queries that require grad "
                         "(set queries.requires_grad_(True) before the forward)")
    (grad,) = torch.autograd.grad(sdf, queries, grad_outputs=torch.ones_like(sdf), create_graph=True)
    return grad.float()


def eikonal_loss(sdf: torch.Tensor, queries: torch.Tensor, near: torch.Tensor, *,
                 grad: torch.Tensor | None = None) -> torch.Tensor:
    """L_eik = mean over near-surface queries of (|grad_x f(x)| - 1)^2.

    The gradient is taken with ``torch.autograd.grad(..., create_graph=True)`` so the loss can be
    back-propagated to the network.

    Args:
        sdf: (B, Q) predicted SDF, computed from ``queries``.
        queries: (B, Q, 3) query points with ``requires_grad=True``.
        near: (B, Q) bool, the queries the term applies to.
        grad: (B, Q, 3) the gradient, when the caller has it already.

    Returns:
        () float32; 0 (still attached to the graph) when no query is near.
    """
    if sdf.shape != queries.shape[:-1] or near.shape != sdf.shape:
        raise ValueError(f"eikonal_loss: sdf {tuple(sdf.shape)}, queries {tuple(queries.shape)} and "
                         f"near {tuple(near.shape)} do not match")
    grad = _input_gradient(sdf, queries) if grad is None else grad
    norm = torch.sqrt(grad.square().sum(-1) + 1e-12)
    mask = near.to(norm.dtype)
    return ((norm - 1.0).square() * mask).sum() / mask.sum().clamp(min=1.0)


def kl_weight_at(step: int, config: LossConfig) -> float:
    """beta_kl at optimiser step ``step`` (the curriculum over steps when ``kl_schedule="linear"``)."""
    if config.kl_schedule == "constant":
        return config.kl_weight
    if config.kl_warmup_steps == 0:
        frac = 1.0 if step >= config.kl_warmup_start else 0.0
    else:
        frac = min(max((step - config.kl_warmup_start) / config.kl_warmup_steps, 0.0), 1.0)
    return config.kl_weight_start + frac * (config.kl_weight - config.kl_weight_start)


def kl_prior_logvar(t: torch.Tensor, config: LossConfig) -> torch.Tensor:
    """The temporal part of the beta_kl curriculum: per-item log-variance of the KL's prior N(0, s(t)^2 I).

    ``s(t)^2 = kl_time_ratio ** -(1 - t)``: the prior is N(0, I) at t = 1 and contracts geometrically toward
    t = 0, where its pull on a code's mean is ``kl_time_ratio`` times that at t = 1. The codes of the base
    shapes gather at the origin and the detailed ones keep the periphery: the radial latent structure of
    Sec. 3.3. Unlike a heavier weight on N(0, I), the contracted prior also asks for a proportionally smaller
    posterior spread, so the noise relative to the code stays that of t = 1 (a heavier N(0, I) term would
    widen the posterior of t -> 0 and let training and inference decode different codes there).
    ``kl_time_ratio = 1``: the plain, t-independent KL.

    Args:
        t: (B,) normalized time of each item (Eq. (7)).
        config: the loss settings.

    Returns:
        (B,) float32 ``log s(t)^2``.
    """
    return -(1.0 - t.float()).clamp(0.0, 1.0) * math.log(config.kl_time_ratio)


def select_eikonal_queries(queries: torch.Tensor, near: torch.Tensor, count: int) -> tuple[torch.Tensor, torch.Tensor]:
    """A random subset of ``count`` queries per item, near-surface ones first.

    Args:
        queries: (B, Q, 3).
        near: (B, Q) bool.
        count: E <= Q queries per item (random order from the global torch RNG).

    Returns:
        ``(points, mask)``: (B, E, 3) detached copies with ``requires_grad=True`` and (B, E) bool,
        True where the chosen query is near the surface (fewer than E near queries leave False).
    """
    count = min(count, queries.shape[1])
    score = near.float() + 0.5 * torch.rand(near.shape, device=near.device)
    idx = score.topk(count, dim=1).indices
    points = torch.gather(queries, 1, idx.unsqueeze(-1).expand(-1, -1, 3)).detach().requires_grad_(True)
    return points, torch.gather(near, 1, idx)


@dataclass
class GradientQueries:
    """The points at which the decoder is differentiated with respect to its input.

    Attributes:
        points: (B, E + S, 3) ``requires_grad``: E near-surface queries, then S points on the item's surface.
        near: (B, E + S) bool, where L_eik applies (the near queries and every surface point).
        normals: (B, S, 3) unit normals at the surface points (S may be 0).
    """

    points: torch.Tensor
    near: torch.Tensor
    normals: torch.Tensor

    @property
    def num_surface(self) -> int:
        return self.normals.shape[1]


def gradient_queries(batch: dict[str, torch.Tensor], config: LossConfig) -> GradientQueries | None:
    """The points of L_eik, L_surf and L_normal for one batch; None when all three weights are 0.

    Args:
        batch: ``queries`` (B, Q, 3), ``near`` (B, Q) and, for L_surf and L_normal, ``on_surface`` (B, S, 6):
            points and unit normals on each item's own surface (``data.num_on_surface`` per item).
        config: the loss settings.

    Raises:
        ValueError: a surface term is on but the batch has no ``on_surface`` points.
    """
    surface_terms = config.surface_weight > 0 or config.normal_weight > 0
    if config.eikonal_weight <= 0 and not surface_terms:
        return None
    pts, near = select_eikonal_queries(batch["queries"], batch["near"], config.eikonal_queries)
    normals = pts.new_zeros(pts.shape[0], 0, 3)
    if surface_terms:
        on = batch.get("on_surface")
        if on is None:
            raise ValueError("loss.surface_weight / loss.normal_weight need dataset items with 'on_surface' "
                             "(points and normals on the item's own surface): set data.num_on_surface > 0")
        pts = torch.cat([pts.detach(), on[..., :3].to(pts.dtype)], dim=1).requires_grad_(True)
        near = torch.cat([near, torch.ones(on.shape[:2], dtype=torch.bool, device=near.device)], dim=1)
        normals = on[..., 3:].float()
    return GradientQueries(pts, near, normals)


def cvae_loss(out: dict[str, torch.Tensor], batch: dict[str, torch.Tensor], config: LossConfig, *, step: int,
              gradient: GradientQueries | None = None) -> dict[str, torch.Tensor]:
    """The full objective for one batch.

    Args:
        out: model output, ``{"tsdf": (B, Q), "mean", "logvar": (B, M, C)}`` (the posterior) and, for the
            gradient terms, ``"eikonal_tsdf"`` (B, E + S): the SDF at ``gradient.points``.
        batch: ``{"tsdf": (B, Q), "near": (B, Q), "t": (B,), ...}`` on the model's device.
        config: weights.
        step: optimiser step, for the beta_kl curriculum.
        gradient: the points ``out["eikonal_tsdf"]`` was decoded at (:func:`gradient_queries`).

    Returns:
        ``{"loss", "tsdf", "kl", "eik", "surf", "normal", "beta_kl"}``, () float32 tensors (``kl`` against the
        temporal prior of :func:`kl_prior_logvar`); ``loss`` carries the graph.
    """
    l_tsdf = tsdf_loss(out["tsdf"], batch["tsdf"], kind=config.tsdf, near=batch["near"],
                       near_weight=config.near_weight)
    kl = DiagonalGaussian(out["mean"], out["logvar"]).kl(kl_prior_logvar(batch["t"].to(l_tsdf.device), config))
    beta = kl_weight_at(step, config)
    zero = torch.zeros((), device=l_tsdf.device)
    l_eik = l_surf = l_normal = zero
    if gradient is not None:
        if "eikonal_tsdf" not in out:
            raise ValueError("cvae_loss: the gradient terms need out['eikonal_tsdf'], the SDF at gradient.points")
        sdf = out["eikonal_tsdf"]
        grad = _input_gradient(sdf, gradient.points)
        l_eik = eikonal_loss(sdf, gradient.points, gradient.near, grad=grad)
        s = gradient.num_surface
        if s:
            l_surf = sdf[:, -s:].float().abs().mean()
            l_normal = (1.0 - F.cosine_similarity(grad[:, -s:], gradient.normals, dim=-1, eps=1e-8)).mean()
    elif config.eikonal_weight > 0 or config.surface_weight > 0 or config.normal_weight > 0:
        raise ValueError("cvae_loss: eikonal/surface/normal weights > 0 need gradient queries "
                         "(losses.gradient_queries) and out['eikonal_tsdf']")
    loss = (l_tsdf + beta * kl.mean() + config.eikonal_weight * l_eik + config.surface_weight * l_surf
            + config.normal_weight * l_normal)
    return {"loss": loss, "tsdf": l_tsdf, "kl": kl.mean(), "eik": l_eik, "surf": l_surf, "normal": l_normal,
            "beta_kl": torch.full((), beta, device=l_tsdf.device)}
