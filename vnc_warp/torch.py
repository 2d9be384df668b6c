"""VNC-soft as a PyTorch op: Eq. (3) with gradients w.r.t. vertex positions.

``vnc_soft(verts, mesh, tau)`` checks its inputs and calls a private ``torch.autograd.Function`` whose
forward runs the Warp kernels on the tensor's device (CPU or CUDA, zero-copy through ``wp.from_torch``)
under a ``wp.Tape``, and whose backward replays that tape.
"""

from __future__ import annotations

import numpy as np
import torch
import warp as wp

from ._device import get_device
from .mesh import Mesh, from_arrays
from .operators import vnc_soft as _vnc_soft_wp

__all__ = ["vnc_soft"]


class _VncSoft(torch.autograd.Function):
    @staticmethod
    def forward(ctx, verts: torch.Tensor, mesh: Mesh, tau, kappa: float):
        device = get_device(verts.device)
        x = wp.from_torch(verts.detach().contiguous(), dtype=wp.vec3, requires_grad=True)
        tape = wp.Tape()
        with tape:
            H, n = _vnc_soft_wp(mesh, tau, kappa=kappa, device=device, positions=x, tape=tape)
        ctx.tape, ctx.x, ctx.H, ctx.n = tape, x, H, n
        return wp.to_torch(H).clone(), wp.to_torch(n).clone()

    @staticmethod
    def backward(ctx, grad_H: torch.Tensor, grad_n: torch.Tensor):
        tape = ctx.tape
        gH = wp.from_torch(grad_H.contiguous().to(torch.float32))
        gn = wp.from_torch(grad_n.contiguous().to(torch.float32), dtype=wp.vec3)
        tape.backward(grads={ctx.H: gH, ctx.n: gn})
        grad = wp.to_torch(ctx.x.grad).clone()
        tape.zero()
        return grad, None, None, None


def vnc_soft(verts: torch.Tensor, mesh, tau, *, kappa: float = 6.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Differentiable VNC-soft (Eq. 3) on a batch-free mesh.

    Args:
        verts: (V, 3) float32 vertex positions, on CPU or CUDA; gradients flow to it.
        mesh: a :class:`~vnc_warp.Mesh` with V vertices giving the connectivity, or (F, 3) integer faces
            (checked for manifoldness and winding; vertices are not merged or reordered).
        tau: scale (mesh units), a float or a (V,) tensor/array of per-vertex scales (not differentiated).
        kappa: cut-off ratio, ``sigma = tau / kappa``.

    Returns:
        ``(H, n)``: (V,) float32 curvature and (V, 3) float32 unit normals, on ``verts.device``.
    """
    if not isinstance(verts, torch.Tensor):
        raise TypeError(f"verts must be a torch.Tensor, got {type(verts).__name__}")
    if verts.ndim != 2 or verts.shape[1] != 3:
        raise ValueError(f"verts must have shape (V, 3), got {tuple(verts.shape)}")
    if verts.dtype != torch.float32:
        raise TypeError(f"verts must be float32 (Warp kernels run in float32), got {verts.dtype}")
    if not torch.isfinite(verts).all():
        raise ValueError("verts contain NaN or infinite values")
    if not isinstance(mesh, Mesh):
        faces = mesh.detach().cpu().numpy() if isinstance(mesh, torch.Tensor) else np.asarray(mesh)
        mesh = from_arrays(verts.detach().cpu().numpy(), faces, name="faces", merge=False)
    if mesh.num_vertices != verts.shape[0]:
        raise ValueError(f"verts has {verts.shape[0]} rows but the mesh has {mesh.num_vertices} vertices "
                         "(unreferenced vertices are not allowed)")
    if isinstance(tau, torch.Tensor):
        if tau.device != verts.device and tau.ndim > 0:
            raise ValueError(f"tau is on {tau.device}, verts on {verts.device}")
        tau = tau.detach().cpu().numpy()
    return _VncSoft.apply(verts, mesh, tau, float(kappa))
