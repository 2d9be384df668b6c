"""VNC-soft and VNC-hard as PyTorch ops: Eqs. (3) and (2) with gradients with respect to the vertex positions.

``vnc_soft(verts, mesh, tau)`` and ``vnc_hard(verts, mesh, tau)`` check their inputs and call a private
``torch.autograd.Function`` that runs the Warp kernels on the tensor's device (CPU or CUDA, zero-copy through
``wp.from_torch``) on the :class:`~vnc_warp.Engine` of the mesh. They answer per row of ``verts``, exactly as
:func:`vnc_warp.vnc_soft` answers per vertex of a trimesh or a file: vertices at one position (texture seams) are
merged into one vertex of the surface and every row gets its vertex's value.

VNC-soft goes through the engine's plan for positions on the device: forward and backward are each replayed from a
captured graph once the shapes repeat, and read nothing back (on CUDA, invalid positions are caught by the engine's
check on the device: see :mod:`vnc_warp._engine`). VNC-hard reads the bounds of its edges each call (their pieces
depend on the edge lengths) and differentiates every chord with respect to the ball's centre and the edge's ends.
"""

from __future__ import annotations

import math
import weakref

import numpy as np
import torch
import warp as wp

from ._checks import warn_if_degenerate
from ._device import get_device
from ._engine import Engine, engine
from .mesh import Mesh, MeshInput, from_arrays, mesh_input
from .tuning import Tuning

__all__ = ["vnc_soft", "vnc_hard"]


# torch views of Warp arrays the op reads or writes on every call (a plan's positions, the engine's upstream gradients,
# a graph's outputs), made once per array: ``wp.to_torch`` costs more host time than a replayed call's graph
_VIEWS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _view(owner, name: str, arr: wp.array) -> torch.Tensor:
    """The torch view of ``owner``'s Warp array ``arr`` (kept per owner and name while it is the same array)."""
    views = _VIEWS.get(owner)
    if views is None:
        views = _VIEWS[owner] = {}
    hit = views.get(name)
    if hit is None or hit[0] is not arr:
        hit = views[name] = (arr, wp.to_torch(arr, requires_grad=False))
    return hit[1]


def _owned(owner, name: str, arr: wp.array, owned: bool) -> torch.Tensor:
    """``arr`` as a tensor of the caller's own: wrapped when it is the caller's already, else a copy of a graph's
    output (a later replay of that graph writes into the array)."""
    return wp.to_torch(arr, requires_grad=False) if owned else _view(owner, name, arr).clone()


class _Held:
    """The (V, 24) state of a forward pass for its backward pass ((V, 9) where the backward pass adds the vertices'
    part itself, ``Tuning.vertex_scatter``; :meth:`Engine.hold`): a view of the graph's output
    until the engine's next VNC-soft call, then a copy of it; None once a backward pass has read what the forward
    pass left on the device (that pass may run again, ``retain_graph``: it then prepares the state again)."""

    __slots__ = ("state", "__weakref__")

    def __init__(self, state: torch.Tensor):
        self.state = state

    def save(self) -> None:
        self.state = self.state.clone()

    def release(self) -> None:
        self.state = None


def _centred(x: torch.Tensor, centre: torch.Tensor) -> wp.array:
    return wp.from_torch((x - centre).to(torch.float32).contiguous(), dtype=wp.vec3, requires_grad=False)


class _VncSoft(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: torch.Tensor, centre: torch.Tensor, eng: Engine, tau, kappa: float):
        # relative to the centre, in the input's precision, then float32: written straight into the positions the
        # plan's graph reads when the plan exists (one torch op, no Warp array made), else into an array of our own
        # a forward pass that no backward pass follows leaves out the moments of the vertex adjoint
        grad = ctx.needs_input_grad[0]
        plan = eng.soft_plan(tau, kappa)
        if plan is not None:
            torch.sub(x, centre, out=_view(plan, "x", plan.x))
            state, token, owned = eng.soft_state(plan, tau, kappa, grad=grad, copy=False)
        else:
            state, token, owned = eng.soft_state(_centred(x, centre), tau, kappa, grad=grad, copy=False)
        if owned or token is None:  # the caller's own, or no backward pass follows: one tensor for H and n
            out = state = _owned(eng, f"state{state.shape[1]}", state, owned)
        else:
            # H and n are copied out of the graph's output, the moments only when a VNC-soft call is about to write
            # over them before the backward pass (which reads them on the device): a (V, 24) copy per call cost
            # more host time than the rest of a replayed call on the CPU (torch's threaded copy)
            state = _view(eng, f"state{state.shape[1]}", state)
            out = state[:, :4].clone()
        ctx.held = _Held(state)
        if not owned and token is not None:
            eng.hold(token, ctx.held)
        ctx.save_for_backward(x, centre)
        ctx.eng, ctx.tau, ctx.kappa, ctx.token = eng, tau, kappa, token
        return out[:, 0], out[:, 1:4]

    @staticmethod
    def backward(ctx, grad_H: torch.Tensor, grad_n: torch.Tensor):
        eng = ctx.eng
        x, centre = ctx.saved_tensors
        torch.cat([grad_H.reshape(-1, 1), grad_n], dim=1, out=_view(eng, "grads", eng.soft_grads))

        def state():
            held = ctx.held
            if held.state is None:  # read on the device by an earlier backward pass, and overwritten since
                return eng.soft_state(_centred(x, centre), ctx.tau, ctx.kappa)[0]
            return wp.from_torch(held.state, requires_grad=False)

        gx, owned = eng.soft_gradient(lambda: _centred(x, centre), ctx.tau, ctx.kappa, state, None, ctx.token,
                                      copy=False)
        gx = _owned(eng, "grad", gx, owned)
        return gx.to(x.dtype), None, None, None, None


class _VncHard(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: torch.Tensor, eng: Engine, tau, kappa):
        xw = wp.from_torch(x.detach(), dtype=wp.vec3)
        outs = eng.hard_state(xw, tau, kappa)
        ctx.eng, ctx.outs, ctx.x = eng, outs, x
        return wp.to_torch(outs[3]), wp.to_torch(outs[4])

    @staticmethod
    def backward(ctx, grad_H: torch.Tensor, grad_n: torch.Tensor):
        gH = wp.from_torch(grad_H.to(torch.float32).contiguous())
        gn = wp.from_torch(grad_n.to(torch.float32).contiguous(), dtype=wp.vec3)
        return wp.to_torch(ctx.eng.hard_gradient(ctx.outs, gH, gn)), None, None, None


def vnc_soft(verts: torch.Tensor, mesh, tau, *, kappa: float = 6.0,
             tuning: Tuning | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Differentiable VNC-soft (Eq. 3) on a batch-free mesh.

    Args:
        verts: (V_in, 3) float32 or float64 vertex positions, on CPU or CUDA; gradients flow to it.
        mesh: the connectivity, any of: a :class:`~vnc_warp.Mesh` (``verts`` has a row per mesh vertex, or a row
            per vertex of the input it was loaded from, ``mesh.source_index``); a ``trimesh.Trimesh``, a
            ``(V, F)`` pair or a path whose vertices are the rows of ``verts``; or (F, 3) integer faces indexing
            the rows of ``verts`` (checked for manifoldness and winding). Reuse a Mesh across calls: it keeps its
            engine (plans, captured graphs); building one from faces costs a sort of the edges.
        tau: scale (mesh units), a float or one value per row of ``verts`` (a tensor on ``verts``' device or an
            array; not differentiated).
        kappa: cut-off ratio, ``sigma = tau / kappa``.
        tuning: the engine's knobs (:class:`~vnc_warp.tuning.Tuning`).

    Returns:
        ``(H, n)``: (V_in,) curvature and (V_in, 3) unit normals, float32, on ``verts.device``, one row per row of
        ``verts``. Rows at one position (a texture seam) are one vertex of the surface: they get its value, and the
        gradient of that vertex split equally among them; a row no face uses gets NaN.
    """
    _check_verts(verts)
    return _apply(verts, _connectivity(verts, mesh), tau, kappa, tuning, soft=True)


def vnc_hard(verts: torch.Tensor, mesh, tau, *, kappa: float | None = 6.0,
             tuning: Tuning | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Differentiable VNC-hard (Eq. 2) on a batch-free mesh: balls of radius ``tau`` at the vertices, exact chords.

    The gradient holds every term of Eq. (2): the chord of each edge in each ball (with respect to the ball's centre
    and both ends of the edge), the Gaussian weight at the edge's midpoint, and the edge's dihedral angle and normal.

    Args:
        verts: (V_in, 3) float32 or float64 vertex positions, on CPU or CUDA; gradients flow to it.
        mesh: the connectivity, as for :func:`vnc_soft`.
        tau: ball radius (mesh units), a float or one value per row of ``verts`` (not differentiated).
        kappa: ``sigma = tau / kappa`` of the Gaussian weight, or None for ``w = 1``.
        tuning: the engine's knobs (:class:`~vnc_warp.tuning.Tuning`).

    Returns:
        ``(H, n)`` as for :func:`vnc_soft`.
    """
    _check_verts(verts)
    return _apply(verts, _connectivity(verts, mesh), tau, kappa, tuning, soft=False)


def _check_verts(verts) -> None:
    if not isinstance(verts, torch.Tensor):
        raise TypeError(f"verts must be a torch.Tensor, got {type(verts).__name__}")
    if verts.ndim != 2 or verts.shape[1] != 3:
        raise ValueError(f"verts must have shape (V, 3), got {tuple(verts.shape)}")
    if verts.dtype not in (torch.float32, torch.float64):
        raise TypeError(f"verts must be float32 or float64 (Warp kernels run in float32), got {verts.dtype}")
    # NaN and infinite values are refused in _apply (on CUDA that would wait for the device: the engine checks the
    # positions there instead)


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


def vnc_soft_input(verts: torch.Tensor, src: MeshInput, tau, *, kappa: float, device=None,
                   tuning: Tuning | None = None):
    """VNC-soft of the rows of ``verts`` on the surface of ``src`` (whose map answers per row): the torch op behind
    :func:`vnc_soft` and :func:`vnc_warp.vnc_soft` given tensors."""
    _check_verts(verts)
    if device is not None and get_device(device) != get_device(verts.device):
        raise ValueError(f"device={device} differs from the tensor's device {verts.device}; move the tensor")
    return _apply(verts, src, tau, kappa, tuning, soft=True)


def _mesh_tau(verts: torch.Tensor, src: MeshInput, tau):
    """``tau`` per mesh vertex: a scalar as it is, a tensor on ``verts``' device as a float32 ``wp.array`` (never
    read back), anything else as a host array."""
    if isinstance(tau, torch.Tensor) and tau.ndim > 0:
        if tau.device != verts.device:
            raise ValueError(f"tau is on {tau.device}, verts on {verts.device}")
        t = tau.detach().to(torch.float32)
        if src.index is not None:
            if t.shape != (src.index.size,):
                raise ValueError(f"tau: expected a scalar or one value per vertex ({src.index.size},), got shape "
                                 f"{tuple(t.shape)}")
            valid = np.nonzero(src.index >= 0)[0]
            _, first = np.unique(src.index[valid], return_index=True)
            t = t[torch.as_tensor(valid[first], device=t.device)]
        elif t.shape != (src.mesh.num_vertices,):
            raise ValueError(f"tau: expected a scalar or one value per vertex ({src.mesh.num_vertices},), got shape "
                             f"{tuple(t.shape)}")
        return wp.from_torch(t.contiguous())
    if isinstance(tau, torch.Tensor):
        tau = float(tau)
    return src.to_mesh_vertices(tau, "tau")


def _apply(verts: torch.Tensor, src: MeshInput, tau, kappa, tuning: Tuning | None, *, soft: bool):
    """VNC-soft (``soft``) or VNC-hard on the merged vertices of ``verts``, answered per row."""
    if src.num_input_vertices != verts.shape[0]:
        raise ValueError(f"verts has {verts.shape[0]} rows, the mesh {src.num_input_vertices} vertices")
    x = verts
    idx = None
    fast = soft and src.index is None  # checked finite below, from the box of the vertices
    if not fast and not verts.is_cuda and not torch.isfinite(verts).all():
        raise ValueError("verts contain NaN or infinite values")
    if src.index is not None:
        # one position per vertex of the surface: the mean of its rows (equal on a seam), so its gradient is
        # shared equally by them
        idx = torch.as_tensor(src.index, device=verts.device)
        used = idx >= 0
        V = src.mesh.num_vertices
        x = torch.zeros(V, 3, dtype=verts.dtype, device=verts.device).index_add(0, idx[used], verts[used])
        x = x / torch.bincount(idx[used], minlength=V).clamp(min=1).to(verts.dtype)[:, None]
    mesh_tau = _mesh_tau(verts, src, tau)
    eng = engine(src.mesh, get_device(verts.device), tuning=tuning)
    if soft:
        # the centre of the box, in the input's precision: the op works relative to it, so that a mesh far from the
        # origin keeps its digits in float32 (not differentiated: VNC does not depend on it)
        xd = x.detach()
        # one reduction on CUDA; torch's CPU aminmax along a dim takes milliseconds on a small tensor
        lo, hi = torch.aminmax(xd, dim=0) if xd.is_cuda else (xd.amin(0), xd.amax(0))
        centre = torch.lerp(lo, hi, 0.5)
        # on the CPU reading 3 numbers is free; amin/amax propagate NaN and inf (on CUDA the engine checks instead)
        if fast and not verts.is_cuda and not all(map(math.isfinite, centre.tolist())):
            raise ValueError("verts contain NaN or infinite values")
        H, n = _VncSoft.apply(x, centre, eng, mesh_tau, float(kappa))
    else:
        centre = 0.5 * (x.detach().amin(0) + x.detach().amax(0))
        x = (x - centre).to(torch.float32).contiguous()
        H, n = _VncHard.apply(x, eng, mesh_tau, None if kappa is None else float(kappa))
    if not verts.is_cuda:
        warn_if_degenerate("vnc_soft" if soft else "vnc_hard", src,
                           mesh_tau.numpy() if isinstance(mesh_tau, wp.array) else mesh_tau, kappa, n, soft=soft)
    if idx is None:
        return H, n
    pick = idx.clamp(min=0)
    H, n = H[pick], n[pick]
    if (src.index < 0).any():
        H = torch.where(used, H, torch.full_like(H, float("nan")))
        n = torch.where(used[:, None], n, torch.full_like(n, float("nan")))
    return H, n
