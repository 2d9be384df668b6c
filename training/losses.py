"""The C-VAE objective of Sec. 3.3: L = L_tsdf + beta_kl L_kl + lambda_eik L_eik.

Weights and the beta_kl curriculum come from :class:`~vnc_warp.training.config.LossConfig`.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from .config import LossConfig

__all__ = ["tsdf_loss", "eikonal_loss", "kl_weight_at", "select_eikonal_queries", "cvae_loss"]


def tsdf_loss(pred: torch.Tensor, target: torch.Tensor, *, kind: str = "l1") -> torch.Tensor:
    """L_tsdf: mean L1 (``"l1"``) or squared (``"mse"``) error of the truncated SDF.

    Args:
        pred: (B, Q) predicted SDF, normalised units.
        target: (B, Q) truncated ground-truth SDF, same units.

    Returns:
        () float32.
    """
    if pred.shape != target.shape:
        raise ValueError(f"tsdf_loss: pred {tuple(pred.shape)} and target {tuple(target.shape)} differ")
    if kind == "l1":
        return F.l1_loss(pred.float(), target.float())
    if kind == "mse":
        return F.mse_loss(pred.float(), target.float())
    raise ValueError(f"tsdf_loss: kind must be 'l1' or 'mse', got {kind!r}")


def eikonal_loss(sdf: torch.Tensor, queries: torch.Tensor, near: torch.Tensor) -> torch.Tensor:
    """L_eik = mean over near-surface queries of (|grad_x f(x)| - 1)^2.

    The gradient is taken with ``torch.autograd.grad(..., create_graph=True)`` so the loss can be
    back-propagated to the network.

    Args:
        sdf: (B, Q) predicted SDF, computed from ``queries``.
        queries: (B, Q, 3) query points with ``requires_grad=True``.
        near: (B, Q) bool, the queries the term applies to.

    Returns:
        () float32; 0 (still attached to the graph) when no query is near.
    """
    if not queries.requires_grad:
        raise ValueError("eikonal_loss: queries must require grad "
                         "(set queries.requires_grad_(True) before the forward)")
    if sdf.shape != queries.shape[:-1] or near.shape != sdf.shape:
        raise ValueError(f"eikonal_loss: sdf {tuple(sdf.shape)}, queries {tuple(queries.shape)} and "
                         f"near {tuple(near.shape)} do not match")
    (grad,) = torch.autograd.grad(sdf, queries, grad_outputs=torch.ones_like(sdf), create_graph=True)
    norm = torch.sqrt(grad.float().square().sum(-1) + 1e-12)
    mask = near.to(norm.dtype)
    return ((norm - 1.0).square() * mask).sum() / mask.sum().clamp(min=1.0)


def kl_weight_at(step: int, config: LossConfig) -> float:
    """beta_kl at optimiser step ``step`` (the C-VAE-I curriculum when ``kl_schedule="linear"``)."""
    if config.kl_schedule == "constant":
        return config.kl_weight
    if config.kl_warmup_steps == 0:
        frac = 1.0 if step >= config.kl_warmup_start else 0.0
    else:
        frac = min(max((step - config.kl_warmup_start) / config.kl_warmup_steps, 0.0), 1.0)
    return config.kl_weight_start + frac * (config.kl_weight - config.kl_weight_start)


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


def cvae_loss(out: dict[str, torch.Tensor], batch: dict[str, torch.Tensor], config: LossConfig, *, step: int,
              eikonal_queries: torch.Tensor | None = None, eikonal_near: torch.Tensor | None = None
              ) -> dict[str, torch.Tensor]:
    """The full objective for one batch.

    Args:
        out: model output, ``{"tsdf": (B, Q), "kl": (B,)}`` and, for the eikonal term, ``"eikonal_tsdf"`` (B, E).
        batch: ``{"tsdf": (B, Q), ...}`` on the model's device.
        config: weights.
        step: optimiser step, for the beta_kl schedule.
        eikonal_queries: (B, E, 3) the points ``out["eikonal_tsdf"]`` was decoded at (with grad).
        eikonal_near: (B, E) bool mask of those points the eikonal term applies to.

    Returns:
        ``{"loss", "tsdf", "kl", "eik", "beta_kl"}``, () float32 tensors; ``loss`` carries the graph.
    """
    l_tsdf = tsdf_loss(out["tsdf"], batch["tsdf"], kind=config.tsdf)
    l_kl = out["kl"].float().mean()
    beta = kl_weight_at(step, config)
    if config.eikonal_weight > 0:
        if eikonal_queries is None or eikonal_near is None or "eikonal_tsdf" not in out:
            raise ValueError("cvae_loss: eikonal_weight > 0 needs eikonal_queries, eikonal_near "
                             "and out['eikonal_tsdf']")
        l_eik = eikonal_loss(out["eikonal_tsdf"], eikonal_queries, eikonal_near)
    else:
        l_eik = torch.zeros((), device=l_tsdf.device)
    loss = l_tsdf + beta * l_kl + config.eikonal_weight * l_eik
    return {"loss": loss, "tsdf": l_tsdf, "kl": l_kl, "eik": l_eik,
            "beta_kl": torch.tensor(beta, device=l_tsdf.device)}
