"""Multi-scale analysis (paper Sec. 3.1): VNC-Scale curves, the global mean curve, VNC-AUC (Eq. 4)
and adaptive per-vertex scales (Eq. 6).

:func:`scale_curve` and :func:`default_scales` take the mesh as the user holds it (see
:func:`vnc_warp.mesh.mesh_input`); a :class:`ScaleCurve` remembers how, and :func:`vnc_auc` and
:func:`adaptive_scale` answer the same way: Warp arrays per mesh vertex for a :class:`~vnc_warp.Mesh`, NumPy
arrays per input vertex for a trimesh, ``(V, F)`` pair or path, torch tensors for tensors."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import warp as wp

from vnc_warp.kernels import vnc as _k

from . import _pairs
from ._device import get_device
from .mesh import Mesh, MeshInput, mesh_input
from .operators import (_ball_sources, _check_values, _degenerate_reason, _edge_fields, _host_bounds, _midpoint_bvh,
                        _mesh_only, _positions, _segment_bvh, _soft_sources, _warn_once)

__all__ = ["ScaleCurve", "default_scales", "scale_curve", "vnc_auc", "adaptive_scale"]


@dataclass
class ScaleCurve:
    """VNC-Scale curves of every vertex and the global mean curve.

    Attributes:
        taus: (S,) float64 ascending scales (mesh units).
        H: ``H[s, k] = H(v_k, taus[s])``: a (S, V) float32 ``wp.array2d`` for a :class:`~vnc_warp.Mesh`, a (S, V_in)
            NumPy array or torch tensor (one column per input vertex) for the other inputs.
        mean: (S,) float32: the global mean curve ``mean_k H(v_k, tau)`` over the mesh's vertices, in the kind of
            ``H``.
        variant: "soft" (Eq. 3) or "hard" (Eq. 2).
    """

    taus: np.ndarray
    H: Any
    mean: Any
    variant: str
    _H: wp.array = field(default=None, repr=False)
    _mean: wp.array = field(default=None, repr=False)
    _input: MeshInput | None = field(default=None, repr=False)

    def __post_init__(self):
        if self._H is None:  # made from Warp arrays by hand
            self._H, self._mean = self.H, self.mean

    @property
    def device(self):
        return self._H.device

    def _result(self, values: wp.array):
        """A per-vertex result of this curve, answered the way its mesh was given."""
        return values if self._input is None else self._input.per_vertex(values)


def default_scales(mesh, num: int = 16, *, lo: float = 2.0, hi: float = 0.25) -> np.ndarray:
    """The default scale range, from the mesh alone (never from absolute units).

    ``tau_min = lo x mean edge length`` (a neighbourhood of a few rings, so every vertex sees edges) and
    ``tau_max = hi x bounding-box diagonal`` (the shape's large-scale structure), ``num`` scales spaced
    geometrically between them. ``mesh``: a :class:`~vnc_warp.Mesh`, trimesh, ``(V, F)`` pair or path. Returns
    (num,) float64.
    """
    mesh = mesh_input(mesh).mesh
    if num < 2:
        raise ValueError(f"need at least 2 scales, got {num}")
    t0 = lo * mesh.mean_edge_length
    t1 = hi * mesh.bbox_diagonal
    if not t1 > t0:
        t1 = 4.0 * t0
    return np.geomspace(t0, t1, num)


def _check_taus(taus) -> np.ndarray:
    t = np.asarray(taus, dtype=np.float64).reshape(-1)
    if t.size < 2:
        raise ValueError(f"need at least 2 scales, got {t.size}")
    if not np.isfinite(t).all() or (t <= 0).any():
        raise ValueError("scales must be positive and finite")
    if (np.diff(t) <= 0).any():
        raise ValueError("scales must be strictly ascending")
    return t


def scale_curve(mesh, taus=None, variant: str = "soft", *, kappa: float | None = 6.0, device=None,
                positions: wp.array | None = None, strategy: str = "auto") -> ScaleCurve:
    """VNC-Scale curves ``C(v_k) = H(v_k, tau)`` at every scale, in one neighbour traversal.

    Each traversal visits the pairs within the largest scale once and adds every pair to all the scales that
    reach it, 16 scales at a time in registers (more than 16 scales take one traversal per 16).

    Args:
        mesh: a :class:`~vnc_warp.Mesh`, a ``trimesh.Trimesh``, a ``(V, F)`` pair (NumPy or torch) or a path.
        taus: (S,) ascending scales (mesh units); default :func:`default_scales`.
        variant: "soft" (Eq. 3, ``sigma = tau / kappa``) or "hard" (Eq. 2, radius ``tau``).
        kappa: cut-off ratio (``None`` allowed for "hard": unweighted).
        device: Warp device (defaults to ``positions.device`` when positions are given, a tensor's device, or the
            preferred device).
        positions: (V,) vec3 ``wp.array`` overriding a :class:`~vnc_warp.Mesh`'s vertices (e.g. a flow iterate on
            the GPU).
        strategy: "auto", "grid", "dense" or "bvh" (see :func:`vnc_warp.vnc_soft`); "auto" decides per
            traversal from its largest scale.

    Returns:
        A :class:`ScaleCurve` with ``H`` of shape (S, V) (Warp, for a Mesh) or (S, V_in) (NumPy or torch) and the
        global mean curve.
    """
    src = mesh_input(mesh)
    _mesh_only(src, "scale_curve", positions=positions)
    if device is None and positions is None:
        device = src.device
    curve = _scale_curve(src.mesh, taus, variant, kappa=kappa, device=device, positions=positions,
                         strategy=strategy)
    if positions is None:
        _warn_zero_rows(src, curve, kappa)
    if src.kind == "warp":
        return curve
    return ScaleCurve(curve.taus, src.per_vertex(curve.H, axis=1), src.per_point(curve.mean), variant, curve.H,
                      curve.mean, src)


def _warn_zero_rows(src: MeshInput, curve: ScaleCurve, kappa) -> None:
    """Warn once when the curve's smallest scales gave 0 at every vertex for want of anything in reach (read where
    it costs nothing: on the CPU, or for results going to the host anyway)."""
    if curve.device.is_cuda and src.kind == "warp":
        return
    H = curve.H.numpy()
    zero = ~H.any(axis=1)
    if not zero.any() or zero.all():  # all zero: a flat surface, no degenerate scale
        return
    rows = np.nonzero(zero)[0]
    reason = _degenerate_reason(src.mesh, float(curve.taus[rows[-1]]), kappa, soft=curve.variant == "soft")
    if reason is not None:
        listed = ", ".join(map(str, rows[:6])) + (", ..." if rows.size > 6 else "")
        _warn_once("scale_curve", reason[0], f"scale_curve on {src.mesh.name}: {rows.size} of {zero.size} scales "
                                             f"(taus[{listed}]) gave H = 0 at every vertex: {reason[1]}")


def _scale_curve(mesh: Mesh, taus, variant: str, *, kappa, device, positions, strategy: str) -> ScaleCurve:
    """:func:`scale_curve` on a :class:`Mesh`: Warp arrays per mesh vertex."""
    device = positions.device if positions is not None else get_device(device)
    t = _check_taus(default_scales(mesh) if taus is None else taus)
    if variant not in ("soft", "hard"):
        raise ValueError(f"variant must be 'soft' or 'hard', got {variant!r}")
    if variant == "soft" and not (kappa is not None and kappa > 0):
        raise ValueError(f"VNC-soft needs a positive kappa, got {kappa}")
    if variant == "hard" and kappa is not None and not kappa > 0:
        raise ValueError(f"kappa must be positive or None, got {kappa}")
    _pairs.check_strategy(strategy)
    S, V = t.size, mesh.num_vertices
    x = _positions(mesh, positions, device)
    pool = _pairs.Pool(device, f"scale_curve/{variant}")
    f = _edge_fields(mesh, x, pool=pool)
    taus_wp = wp.array(t.astype(np.float32), dtype=wp.float32, device=device)
    H = wp.empty((S, V), dtype=wp.float32, device=device)
    if strategy == "bvh":
        _check_values(mesh, x, taus_wp)
        _scale_curve_bvh(x, f, taus_wp, variant, kappa, H)
    else:
        _scale_curve_cells(mesh, x, f, t, taus_wp, variant, kappa, strategy, H, pool)
    mean = wp.zeros(S, dtype=wp.float32, device=device)
    stride = min(V, 256)
    wp.launch(_k.column_mean, dim=(S, stride), inputs=[H, stride, 1.0 / V], outputs=[mean], device=device)
    return ScaleCurve(t, H, mean, variant)


def _scale_curve_bvh(x, f, taus_wp, variant, kappa, H):
    device = x.device
    S, V = H.shape
    num = wp.zeros((S, V), dtype=wp.float32, device=device)
    den = wp.zeros((S, V), dtype=wp.float32, device=device)
    if variant == "soft":
        bvh = _midpoint_bvh(f)
        wp.launch(_k.soft_multiscale, dim=V, inputs=[x, taus_wp, float(kappa), bvh.id, f.mid, f.length, f.angle],
                  outputs=[num, den], device=device)
    else:
        bvh = _segment_bvh(x, f)
        k = 1.0e-6 if kappa is None else float(kappa)  # sigma = tau / 1e-6: w = 1 to float precision
        wp.launch(_k.ball_multiscale, dim=V, inputs=[x, taus_wp, k, bvh.id, x, f.edges, f.mid, f.angle],
                  outputs=[num, den], device=device)
    wp.launch(_k.ratio2d, dim=(S, V), inputs=[num, den], outputs=[H], device=device)


def _scale_curve_cells(mesh, x, f, t, taus_wp, variant, kappa, strategy, H, pool):
    device = x.device
    S, V = H.shape
    E = f.mid.shape[0]
    soft = variant == "soft"
    b = _host_bounds(mesh, x, (float(t[-1]), float(t[-1])), lengths=not soft) or _pairs.bounds(
        x, wp.full(V, np.float32(t[-1]), dtype=wp.float32, device=device), None if soft else f.length)
    pad = 0.0 if soft else 0.5 * b.lmax
    k = 0.0 if kappa is None else float(kappa)  # kappa = 0: unweighted scales
    # 32 sums per scale chunk and thread: fewer splits than a single-scale traversal
    splits = min(_pairs.launch_shape(device, V)[1], 4)
    for offset in range(0, S, 16):
        tmax = float(t[min(offset + 16, S) - 1])
        concrete = _pairs.resolve(strategy, device, b, tmax + pad, V, E)
        radius = pool.empty(V, wp.float32)
        radius.fill_(np.float32(tmax))
        chunk = replace(b, rmax=tmax, rmean=tmax)
        if soft:
            plans = [_pairs.plan(x, radius, f.mid, chunk, concrete, tmax, splits=splits, cache=mesh._cache, pool=pool)]
        else:
            plans = _pairs.ball_plans(x, radius, f.mid, f.length, chunk, concrete, splits=splits, cache=mesh._cache,
                                      pool=pool)
        groups = plans[0][1]
        rows = 16 * len(plans) * groups.splits
        part_num = pool.empty((rows, groups.padded), wp.float32)
        part_den = pool.empty((rows, groups.padded), wp.float32)
        if not soft:  # every traversal reads the edges in one sorted order (ball_plans)
            seg_m, seg_h, val = _ball_sources(plans[0][0], x, f, device, pool)
        for i, (cells, grp) in enumerate(plans):
            if soft:
                pos, val = _soft_sources(cells, f, device, pool)
                wp.launch(_k.soft_cells_multiscale, dim=grp.dim,
                          inputs=[x, taus_wp, offset, k, *grp.args(cells), pos, val],
                          outputs=[part_num, part_den], device=device)
            else:
                wp.launch(_k.ball_cells_multiscale, dim=grp.dim,
                          inputs=[x, taus_wp, offset, k, *grp.args(cells), seg_m, seg_h, val, grp.splits,
                                  i * grp.splits],
                          outputs=[part_num, part_den], device=device)
        wp.launch(_k.reduce_multiscale, dim=(min(16, S - offset), V), inputs=[groups.order, part_num, part_den, offset],
                  outputs=[H], device=device)


def _curve_taus(curve: ScaleCurve, taus) -> wp.array:
    t = curve.taus if taus is None else _check_taus(taus)
    if t.size != curve._H.shape[0]:
        raise ValueError(f"{t.size} scales given for a curve sampled at {curve._H.shape[0]}")
    return wp.array(t.astype(np.float32), dtype=wp.float32, device=curve.device)


def vnc_auc(curve: ScaleCurve, taus=None) -> wp.array:
    """Eq. (4) at ``tau_max``: per-vertex total complexity ``s(v_k) = int |H(v_k, x) - mean(x)| dx``.

    Trapezoid rule over the sampled scales; units of the scales (mesh units). Returns (V,) float32 per vertex,
    in the kind of the curve's mesh (a Warp array for a :class:`~vnc_warp.Mesh`, NumPy or torch per input vertex
    otherwise).
    """
    V = curve._H.shape[1]
    out = wp.empty(V, dtype=wp.float32, device=curve.device)
    wp.launch(_k.scale_auc, dim=V, inputs=[curve._H, curve._mean, _curve_taus(curve, taus)], outputs=[out],
              device=curve.device)
    return curve._result(out)


def adaptive_scale(curve: ScaleCurve, taus=None, phi: float = 0.0) -> wp.array:
    """Eq. (6): per-vertex adaptive scale ``tau_adpt`` where the running VNC-AUC reaches ``phi``.

    Complex vertices reach the information budget ``phi`` (mesh units, like Eq. (4)) at small scales,
    flat ones late; a vertex that never reaches it gets ``tau_max``. Returns (V,) float32 per vertex, in the kind
    of the curve's mesh (as :func:`vnc_auc`).
    """
    if not np.isfinite(phi) or phi < 0:
        raise ValueError(f"phi must be finite and non-negative, got {phi}")
    V = curve._H.shape[1]
    out = wp.empty(V, dtype=wp.float32, device=curve.device)
    wp.launch(_k.adaptive_scale, dim=V, inputs=[curve._H, curve._mean, _curve_taus(curve, taus), float(phi)],
              outputs=[out], device=curve.device)
    return curve._result(out)
