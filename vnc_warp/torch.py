"""VNC-soft as a PyTorch op: Eq. (3) with gradients w.r.t. vertex positions.

``vnc_soft(verts, mesh, tau)`` checks its inputs and calls a private ``torch.autograd.Function`` whose
forward runs the Warp kernels on the tensor's device (CPU or CUDA, zero-copy through ``wp.from_torch``)
under a ``wp.Tape``, and whose backward replays that tape. It answers per row of ``verts``, exactly as
:func:`vnc_warp.vnc_soft` answers per vertex of a trimesh or a file: vertices at one position (texture seams)
are merged into one vertex of the surface and every row gets its vertex's value.
"""

from __future__ import annotations

import numpy as np
import torch
import warp as wp

from ._device import get_device
from .mesh import Mesh, MeshInput, from_arrays, mesh_input
from .operators import _vnc_soft, _warn_if_degenerate

__all__ = ["vnc_soft"]


class _VncSoft(torch.autograd.Function):
    @staticmethod
    def forward(ctx, verts: torch.Tensor, mesh: Mesh, tau, kappa: float):
        device = get_device(verts.device)
        x = wp.from_torch(verts.detach().contiguous(), dtype=wp.vec3, requires_grad=True)
        tape = wp.Tape()
        with tape:
            H, n = _vnc_soft(mesh, tau, kappa=kappa, device=device, positions=x, tape=tape, strategy="auto")
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
        verts: (V_in, 3) float32 or float64 vertex positions, on CPU or CUDA; gradients flow to it.
        mesh: the connectivity, any of: a :class:`~vnc_warp.Mesh` (``verts`` has a row per mesh vertex, or a row
            per vertex of the input it was loaded from, ``mesh.source_index``); a ``trimesh.Trimesh``, a
            ``(V, F)`` pair or a path whose vertices are the rows of ``verts``; or (F, 3) integer faces indexing
            the rows of ``verts`` (checked for manifoldness and winding). Reuse a Mesh across calls: building one
            from faces costs a sort of the edges.
        tau: scale (mesh units), a float or one value per row of ``verts`` (a tensor or array; not differentiated).
        kappa: cut-off ratio, ``sigma = tau / kappa``.

    Returns:
        ``(H, n)``: (V_in,) curvature and (V_in, 3) unit normals, float32, on ``verts.device``, one row per row of
        ``verts``. Rows at one position (a texture seam) are one vertex of the surface: they get its value, and the
        gradient of that vertex split equally among them; a row no face uses gets NaN.
    """
    _check_verts(verts)
    return _vnc_soft_input(verts, _connectivity(verts, mesh), tau, kappa=kappa)


def _check_verts(verts) -> None:
    if not isinstance(verts, torch.Tensor):
        raise TypeError(f"verts must be a torch.Tensor, got {type(verts).__name__}")
    if verts.ndim != 2 or verts.shape[1] != 3:
        raise ValueError(f"verts must have shape (V, 3), got {tuple(verts.shape)}")
    if verts.dtype not in (torch.float32, torch.float64):
        raise TypeError(f"verts must be float32 or float64 (Warp kernels run in float32), got {verts.dtype}")
    if not torch.isfinite(verts).all():
        raise ValueError("verts contain NaN or infinite values")


def _connectivity(verts: torch.Tensor, mesh) -> MeshInput:
    """The :class:`MeshInput` that answers per row of ``verts``."""
    rows = verts.shape[0]
    if isinstance(mesh, Mesh):
        if rows == mesh.num_vertices:
            return MeshInput(mesh, None, "torch", verts.device)
        if mesh.source_index is not None and rows == mesh.source_index.size:
            return MeshInput(mesh, mesh.source_index, "torch", verts.device)
        raise ValueError(f"verts has {rows} rows but the mesh has {mesh.num_vertices} vertices"
                         + ("" if mesh.source_index is None else f" (its input had {mesh.source_index.size})"))
    faces = mesh
    if isinstance(faces, (torch.Tensor, np.ndarray)) and faces.ndim == 2 and faces.shape[1] == 3 and not (
            faces.dtype.is_floating_point if isinstance(faces, torch.Tensor) else np.issubdtype(faces.dtype, np.floating)):
        built = from_arrays(verts.detach(), faces, name="faces")
        return MeshInput(built, built.source_index, "torch", verts.device)
    src = mesh_input(mesh)
    if src.num_input_vertices != rows:
        raise ValueError(f"verts has {rows} rows but the mesh given for its connectivity has "
                         f"{src.num_input_vertices} vertices")
    return MeshInput(src.mesh, src.index, "torch", verts.device)


def _vnc_soft_input(verts: torch.Tensor, src: MeshInput, tau, *, kappa: float, device=None):
    """VNC-soft of the rows of ``verts`` on the surface of ``src`` (whose map answers per row)."""
    _check_verts(verts)
    if device is not None and get_device(device) != get_device(verts.device):
        raise ValueError(f"device={device} differs from the tensor's device {verts.device}; move the tensor")
    if src.num_input_vertices != verts.shape[0]:
        raise ValueError(f"verts has {verts.shape[0]} rows, the mesh {src.num_input_vertices} vertices")
    x = verts
    idx = None
    if src.index is not None:
        # one position per vertex of the surface: the mean of its rows (equal on a seam), so its gradient is
        # shared equally by them
        idx = torch.as_tensor(src.index, device=verts.device)
        used = idx >= 0
        V = src.mesh.num_vertices
        x = torch.zeros(V, 3, dtype=verts.dtype, device=verts.device).index_add(0, idx[used], verts[used])
        x = x / torch.bincount(idx[used], minlength=V).clamp(min=1).to(verts.dtype)[:, None]
    # relative to the centre, in the input's precision, before float32: a mesh far from the origin keeps its digits
    centre = 0.5 * (x.detach().amin(0) + x.detach().amax(0))
    x = (x - centre).to(torch.float32)
    if isinstance(tau, torch.Tensor) and tau.ndim > 0 and tau.device != verts.device:
        raise ValueError(f"tau is on {tau.device}, verts on {verts.device}")
    tau = src.to_mesh_vertices(tau.detach().cpu().numpy() if isinstance(tau, torch.Tensor) else tau, "tau")
    H, n = _VncSoft.apply(x, src.mesh, tau, float(kappa))
    if not verts.is_cuda:
        _warn_if_degenerate("vnc_soft", src, tau, kappa, wp.from_torch(n.detach(), dtype=wp.vec3))
    if idx is None:
        return H, n
    pick = idx.clamp(min=0)
    H, n = H[pick], n[pick]
    if not bool(used.all()):
        H = torch.where(used, H, torch.full_like(H, float("nan")))
        n = torch.where(used[:, None], n, torch.full_like(n, float("nan")))
    return H, n
