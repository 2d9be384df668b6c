"""The bf16 autocast path of the training step (what runs on CUDA), exercised with CPU autocast."""

from __future__ import annotations

import dataclasses

import torch
from torch.utils.data import default_collate

from vnc_warp.training.config import named_config
from vnc_warp.training.losses import cvae_loss, gradient_queries
from vnc_warp.training.model import build_model
from vnc_warp.training.synthetic import EllipsoidTrajectories


def test_bf16_autocast_step_keeps_sdf_in_float32():
    """Under bf16 autocast the latents are bf16 but the predicted SDF is float32 and equals the float32
    head applied to the bf16 features; the loss with the eikonal double backward gives finite gradients
    to every trainable parameter."""
    torch.manual_seed(0)
    cfg = named_config("tiny")
    model = build_model(cfg.model)
    torch.nn.init.normal_(model.decoder.queries.head.weight, std=0.1)  # a zero head would hide the dtype
    batch = default_collate([EllipsoidTrajectories(num_shapes=1, num_stages=4, num_on_surface=16)[i] for i in range(4)])
    loss_cfg = dataclasses.replace(cfg.loss, eikonal_queries=32, surface_weight=1.0, normal_weight=0.05)
    grad_q = gradient_queries(batch, loss_cfg)
    features = []

    def keep(module, inputs, output):
        features.append(output)

    hook = model.decoder.queries.norm.register_forward_hook(keep)
    with torch.autocast(device_type="cpu", dtype=torch.bfloat16):
        out = model(batch["surface"], batch["queries"], batch["t"], eikonal_queries=grad_q.points)
    hook.remove()
    assert out["z"].dtype == torch.bfloat16
    assert out["tsdf"].dtype == torch.float32 and out["eikonal_tsdf"].dtype == torch.float32
    head = model.decoder.queries.head
    expected = (features[0].float() @ head.weight.T + head.bias).squeeze(-1)  # the first call: the tsdf queries
    torch.testing.assert_close(out["tsdf"], expected.detach(), rtol=1e-5, atol=1e-6)
    terms = cvae_loss(out, batch, loss_cfg, step=100, gradient=grad_q)
    assert all(torch.isfinite(terms[k]) for k in ("tsdf", "kl", "eik", "surf", "normal"))
    terms["loss"].backward()
    grads = [p.grad for p in model.parameters() if p.requires_grad]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
