"""The VNC operator (paper Sec. 3.1): VNC-soft (Eq. 3), VNC-hard (Eq. 2) and the integrated measure (Eq. 1).

Every operator takes the mesh as the user holds it: a :class:`~vnc_warp.Mesh` (results are Warp arrays on the
device that computed them; ``.numpy()`` gives NumPy), a ``trimesh.Trimesh``, a ``(V, F)`` pair or a path (NumPy
arrays, one row per input vertex), or a ``(V, F)`` pair of torch tensors (tensors on ``V``'s device); see
:func:`vnc_warp.mesh.mesh_input`. Vertices at one position are merged for the topology and answered per input
vertex. Scales are in the mesh's own units; :func:`vnc_warp.default_scales` derives a range from the mesh. The
kernels run on coordinates relative to the mesh's centre (:attr:`~vnc_warp.Mesh.local_vertices`), so a result does
not depend on where the mesh sits. A call whose every vertex has nothing in reach (a scale below the distance to
the nearest edge midpoint, or a ``kappa`` so large that every Gaussian weight underflows) warns once, saying which.

Each call runs on the :class:`~vnc_warp.Engine` of its mesh and device (``vw.engine``), which keeps what repeated
calls share and replays a repeated call from a captured graph; ``tuning=`` picks an engine with other knobs
(:class:`~vnc_warp.tuning.Tuning`). ``strategy=`` ("auto", "grid", "dense" or "bvh") is how the pairs within the
cut-off are found (see ``vnc_warp/_plan.py``); all strategies sum over the same pairs, and :func:`choose_strategy`
tells which one "auto" takes.

Differentiation: :func:`vnc_soft` records itself on a ``wp.Tape`` passed as ``tape=`` (with the vertex positions
given as a ``wp.array`` that ``requires_grad``); :mod:`vnc_warp.torch` makes VNC-soft and VNC-hard
``torch.autograd.Function``\\ s.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from . import _plan
from ._checks import DegenerateResultWarning, host_values, mesh_only, warn_if_degenerate
from ._checks import per_point as _per_point  # noqa: F401  (vnc_warp.flow checks its per-vertex values with it)
from ._engine import EdgeFields, engine_of
from .mesh import Mesh, MeshInput, mesh_input
from .tuning import Tuning

__all__ = ["EdgeFields", "edge_fields", "vnc_soft", "vnc_hard", "integrated_mean_curvature", "choose_strategy",
           "STRATEGIES", "DegenerateResultWarning"]

STRATEGIES = _plan.STRATEGIES


def edge_fields(mesh: Mesh, *, positions: wp.array | None = None, device=None, requires_grad: bool = False,
                tuning: Tuning | None = None) -> EdgeFields:
    """Midpoints, lengths, signed dihedral angles and normals of the interior edges of a :class:`Mesh`.

    Launched as a differentiable kernel: inside a ``wp.Tape`` it is recorded like any Warp launch. Without
    ``positions`` the midpoints are relative to ``mesh.origin`` (the operators' frame, ``mesh.local_vertices``).
    Returns new arrays.
    """
    eng = engine_of(MeshInput(mesh, None, "warp"), device, positions, tuning)
    return eng.fields(eng.positions(positions), requires_grad=requires_grad)


def vnc_soft(
    mesh,
    tau,
    *,
    kappa: float = 6.0,
    device=None,
    positions: wp.array | None = None,
    tape: wp.Tape | None = None,
    strategy: str = "auto",
    tuning: Tuning | None = None,
):
    """VNC-soft, Eq. (3): Gaussian-weighted normalized mean curvature and averaged normal per vertex.

    ``H(v_k) = sum_j alpha_j delta_j w_kj L_j / (2 sum_j w_kj L_j)`` with ``w_kj = exp(-|v_k - m_j|^2 / 2 sigma^2)``,
    ``sigma = tau / kappa``; the normal is ``sum_j w_kj L_j n_j`` normalized. Sums run over interior edges whose
    midpoint lies within the cut-off ``r = kappa * sigma = tau``; the weight dropped beyond it is below
    ``exp(-kappa^2 / 2)`` per edge.

    Args:
        mesh: a :class:`~vnc_warp.Mesh`, a ``trimesh.Trimesh``, a ``(V, F)`` pair (NumPy or torch) or a path
            (see :func:`vnc_warp.mesh.mesh_input`). With a torch ``V`` the call is differentiable through
            :func:`vnc_warp.torch.vnc_soft`.
        tau: observation scale (mesh units): a scalar or one value per vertex (of the input).
        kappa: ratio of cut-off radius to Gaussian width (the paper uses 6).
        device: Warp device; defaults to ``positions.device``, a tensor's device, or the preferred device.
        positions: (V,) vec3 ``wp.array`` overriding the vertex positions of a :class:`~vnc_warp.Mesh` (a flow
            step): planned once and replayed while only the positions move (see :mod:`vnc_warp._engine`).
        tape: a ``wp.Tape`` to record on; pass the tape you are inside to differentiate through this call (with
            ``positions`` that require gradients).
        strategy: how pairs within the cut-off are found: "auto", "grid", "dense" or "bvh" (same result; the
            backward pass visits the same pairs as the forward).
        tuning: the engine's knobs (:class:`~vnc_warp.tuning.Tuning`; default :data:`~vnc_warp.tuning.DEFAULT`).

    Returns:
        ``(H, n)``: dimensionless curvature (positive on convex regions) and unit normals, per vertex: (V,) float32
        and (V,) vec3 Warp arrays for a Mesh, (V_in,) and (V_in, 3) NumPy arrays for a trimesh, pair or path, torch
        tensors for tensors. A vertex with no edge in reach gets ``H = 0`` and ``n = 0``; a vertex no face uses,
        NaN.
    """
    src = mesh_input(mesh)
    mesh_only(src, "vnc_soft", positions=positions, tape=tape)
    if src.kind == "torch":
        from .torch import vnc_soft_input

        return vnc_soft_input(mesh[0], src, tau, kappa=kappa, device=device, tuning=tuning)
    tau = src.to_mesh_vertices(tau, "tau")
    H, n = engine_of(src, device, positions, tuning).vnc_soft(tau, kappa=kappa, positions=positions, tape=tape,
                                                           strategy=strategy)
    if positions is None:
        warn_if_degenerate("vnc_soft", src, tau, kappa, n)
    return src.per_vertex(H), src.per_vertex(n)


def vnc_hard(mesh, tau, *, kappa: float | None = 6.0, device=None, strategy: str = "auto",
             tuning: Tuning | None = None):
    """VNC-hard, Eq. (2): exact edge/ball intersections, normalized by the weighted intersected length.

    ``H(v_k, r) = sum_j alpha_j delta_j w_kj l_j / (2 sum_j w_kj l_j)`` over the edges crossing the ball of
    radius ``r = tau`` around ``v_k``, ``l_j`` the length of edge ``j`` inside the ball and
    ``w_kj = exp(-|v_k - m_j|^2 / 2 sigma^2)`` with ``sigma = tau / kappa``; ``kappa=None`` means ``w = 1``.
    The normal weights the edges' area-weighted normals by ``w_kj l_j``. Differentiable through
    :func:`vnc_warp.torch.vnc_hard`.

    Args:
        mesh: a :class:`~vnc_warp.Mesh`, a ``trimesh.Trimesh``, a ``(V, F)`` pair (NumPy or torch) or a path.
        tau: ball radius (mesh units): a scalar or one value per vertex (of the input).
        kappa: radius-to-sigma ratio, or None for the unweighted operator.
        device: Warp device (default: a tensor's device, else the preferred device).
        strategy: "auto", "grid", "dense" or "bvh" (see :func:`vnc_soft`).
        tuning: the engine's knobs (:class:`~vnc_warp.tuning.Tuning`).

    Returns:
        ``(H, n)`` per vertex, as for :func:`vnc_soft`: Warp arrays for a Mesh, NumPy arrays (one row per input
        vertex) for a trimesh, pair or path, torch tensors for tensors.
    """
    src = mesh_input(mesh)
    tau = src.to_mesh_vertices(tau, "tau")
    H, n = engine_of(src, device, None, tuning).vnc_hard(tau, kappa=kappa, strategy=strategy)
    warn_if_degenerate("vnc_hard", src, tau, kappa, n, soft=False)
    return src.per_vertex(H), src.per_vertex(n)


def integrated_mean_curvature(mesh, radius, points=None, *, device=None, strategy: str = "auto",
                              tuning: Tuning | None = None):
    """Eq. (1): integrated discrete mean curvature in balls, ``1/2 sum_j alpha_j delta_j l_j``.

    The normal-cycle measure of Cohen-Steiner and Morvan, equal to trimesh's
    ``curvature.discrete_mean_curvature_measure(mesh, points, radius)``.

    Args:
        mesh: a :class:`~vnc_warp.Mesh`, a ``trimesh.Trimesh``, a ``(V, F)`` pair (NumPy or torch) or a path.
        radius: ball radius (mesh units), a scalar, or one value per point (per input vertex without ``points``).
        points: (P, 3) ball centres (NumPy, torch or a list); defaults to the vertices.
        device: Warp device (default: a tensor's device, else the preferred device).
        strategy: "auto", "grid", "dense" or "bvh" (see :func:`vnc_soft`).
        tuning: the engine's knobs (:class:`~vnc_warp.tuning.Tuning`).

    Returns:
        In mesh units (length x angle): per vertex as for :func:`vnc_soft` (a (V,) float32 Warp array for a Mesh,
        NumPy for a trimesh, pair or path, torch for tensors), or one value per point in the same kind.
    """
    src = mesh_input(mesh)
    eng = engine_of(src, device, None, tuning)
    if points is None:
        return src.per_vertex(eng.integrated(src.to_mesh_vertices(radius, "radius"), strategy=strategy))
    pts = np.asarray(host_values(points), dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must be (P, 3), got {pts.shape}")
    pts = pts - src.mesh.origin  # the kernels run on coordinates relative to the mesh's centre
    if not np.isfinite(pts).all():
        raise ValueError("points contain NaN or infinite coordinates")
    return src.per_point(eng.integrated(radius, pts.astype(np.float32), strategy=strategy))


def choose_strategy(mesh: Mesh, tau, *, variant: str = "soft", device=None, positions: wp.array | None = None,
                    tuning: Tuning | None = None) -> str:
    """The traversal ``strategy="auto"`` takes for this call of :func:`vnc_soft` ("soft") or :func:`vnc_hard` /
    :func:`integrated_mean_curvature` ("hard"): "grid" or "dense".

    ``tau`` may be a scalar or a (V,) array, as for the operators; for a scale curve pass its largest scale.
    """
    eng = engine_of(MeshInput(mesh, None, "warp"), device, positions, tuning)
    return eng.choose_strategy(tau, variant=variant, positions=positions)
