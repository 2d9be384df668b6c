"""The VNC operator (paper Sec. 3.1): VNC-soft (Eq. 3), VNC-hard (Eq. 2) and the integrated measure (Eq. 1).

Every operator takes the mesh as the user holds it: a :class:`~vnc_warp.Mesh` (results are Warp arrays on the
device that computed them; ``.numpy()`` gives NumPy), a ``trimesh.Trimesh``, a ``(V, F)`` pair or a path (NumPy
arrays, one row per input vertex), or a ``(V, F)`` pair of torch tensors (tensors on ``V``'s device); see
:func:`vnc_warp.mesh.mesh_input`. Vertices at one position are merged for the topology and answered per input
vertex. Scales are in the mesh's own units; :func:`vnc_warp.default_scales` derives a range from the mesh. The
kernels run on coordinates relative to the mesh's centre (:attr:`~vnc_warp.Mesh.local_vertices`), so a result does
not depend on where the mesh sits. A call whose every vertex has nothing in reach (a scale below the distance to
the nearest edge midpoint, or a ``kappa`` so large that every Gaussian weight underflows) warns once, saying which.

Differentiation: :func:`vnc_soft` records itself on a ``wp.Tape`` passed as ``tape=`` (with the vertex
positions given as a ``wp.array`` that ``requires_grad``); :mod:`vnc_warp.torch` wraps the same
computation as a ``torch.autograd.Function``.

Speed: every operator takes ``strategy=`` ("auto", "grid", "dense" or "bvh"), the way the pairs within
the cut-off are found (see ``vnc_warp/_pairs.py``). All strategies sum over the same pairs; "auto" picks
per call from the scale and the mesh's extent, so that no scale falls off a cliff: a uniform grid with
warp-coherent traversal while the balls are small, an all-pairs traversal when they cover most of the
mesh. :func:`choose_strategy` tells which one it picks. A call on the mesh's own vertices with a scale given on the
host is replayed from a captured graph from its third time on (:mod:`vnc_warp._replay`); it returns new arrays
every time.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import warp as wp

from vnc_warp.kernels import vnc as _k

from . import _pairs, _replay
from ._device import get_device
from .mesh import Mesh, MeshError, MeshInput, mesh_input

__all__ = ["EdgeFields", "edge_fields", "vnc_soft", "vnc_hard", "integrated_mean_curvature", "choose_strategy",
           "STRATEGIES", "DegenerateResultWarning"]

STRATEGIES = _pairs.STRATEGIES


@dataclass
class EdgeFields:
    """Per-interior-edge quantities on one device (Sec. 3.1).

    Attributes:
        edges: (Ei,) vec4i ``(a, b, c0, c1)``.
        mid: (Ei,) vec3 midpoints.
        length: (Ei,) float32 full edge lengths ``L_j``.
        angle: (Ei,) float32 signed dihedral angles ``alpha_j * delta_j`` (radians).
        normal: (Ei,) vec3 unit area-weighted normals of the two faces.
    """

    edges: wp.array
    mid: wp.array
    length: wp.array
    angle: wp.array
    normal: wp.array


def _edge_array(mesh: Mesh, device) -> wp.array:
    key = ("edges", str(device))
    arr = mesh._cache.get(key)
    if arr is None:
        if mesh.topology.num_interior == 0:
            raise MeshError(f"{mesh.name}: no interior edges (every edge has a single face); VNC is undefined")
        arr = wp.array(mesh.topology.interior, dtype=wp.vec4i, device=device)
        mesh._cache[key] = arr
    return arr


def _mesh_vertices(mesh: Mesh, device) -> wp.array:
    """The mesh's vertices on ``device``, relative to its centre (``mesh.local_vertices``), copied once per vertex
    array (a Mesh's arrays are treated as immutable); read-only for every caller."""
    return mesh._memo(("vertices", str(device)), lambda: wp.array(mesh.local_vertices, dtype=wp.vec3, device=device))


def _own_vertices(mesh: Mesh, x: wp.array) -> bool:
    """Whether ``x`` is the mesh's own vertex array on its device (:func:`_mesh_vertices`), whose derived arrays
    may be kept with the mesh."""
    kept = mesh._cache.get(("vertices", str(x.device)), (None, None))
    return kept[0] is mesh.vertices and x is kept[1]


def _host_bounds(mesh: Mesh, x: wp.array, radius_stats, lengths: bool = False) -> _pairs.Bounds | None:
    """The :class:`~vnc_warp._pairs.Bounds` of a call, from the host when ``x`` is the mesh's own vertices and the radii
    came from the host (``radius_stats = (max, mean)``), else None. Without a read from the device the launches that
    follow are queued while the device still works on earlier ones."""
    if radius_stats is None or not _own_vertices(mesh, x):
        return None
    lo, hi = mesh._memo("bbox", lambda: (mesh.local_vertices.min(0).astype(np.float64),
                                         mesh.local_vertices.max(0).astype(np.float64)))
    lmax = lmean = 0.0
    if lengths:
        L = _interior_lengths(mesh)
        # float32 lengths on the device may round up past the host's: one part in 1e6 of slack
        lmax = float(L[-1]) * (1.0 + 1e-6)
        lmean = mesh._memo("interior_length_mean", lambda: float(L.mean(dtype=np.float64)))
    return _pairs.Bounds(lo, hi, float(radius_stats[0]), float(radius_stats[1]), lmax, lmean)


def _interior_lengths(mesh: Mesh) -> np.ndarray:
    """The interior edges' lengths on the host, sorted (once per vertex array)."""
    def lengths():
        e = mesh.topology.interior
        v = mesh.local_vertices
        return np.sort(np.linalg.norm(v[e[:, 1]] - v[e[:, 0]], axis=1).astype(np.float32))

    return mesh._memo("interior_lengths_sorted", lengths)


def _tier_sizes(mesh: Mesh):
    """``size(lo, hi)``: how many interior edges of the mesh's own vertices have ``lo < length <= hi``."""
    L = _interior_lengths(mesh)
    # float32 lengths on the device can differ in the last bit: count a tier generously (the count only decides
    # how a tier is traversed, never which edges are in it)
    # (the bounds as float32: a float64 one would convert all of L for every search)
    return lambda lo, hi: int(np.searchsorted(L, np.float32(min(hi * (1 + 1e-6), 3e38)), "right")
                              - np.searchsorted(L, np.float32(lo * (1 - 1e-6)), "right"))


def _radius_stats(value):
    """``(max, mean)`` of a scalar or host array of radii (None for a ``wp.array``: its values are on the device)."""
    if isinstance(value, wp.array):
        return None
    arr = np.asarray(value.detach().cpu().numpy() if hasattr(value, "detach") else value, dtype=np.float32)
    return float(arr.max()), float(arr.astype(np.float64).mean())


def _positions(mesh: Mesh, positions, device) -> wp.array:
    if positions is None:
        return _mesh_vertices(mesh, device)
    if not isinstance(positions, wp.array) or positions.dtype != wp.vec3:
        raise TypeError("positions must be a wp.array of wp.vec3")
    if positions.shape[0] != mesh.num_vertices:
        raise ValueError(f"positions has {positions.shape[0]} rows, the mesh {mesh.num_vertices} vertices")
    if positions.device != device:
        raise ValueError(f"positions live on {positions.device}, the computation on {device}")
    return positions


def _check_values(mesh: Mesh, x: wp.array, radius: wp.array) -> None:
    """Refuse NaN or infinite positions and scales that are not positive and finite, given on the device (the grid
    and dense traversals check them while reading their bounds, :func:`vnc_warp._pairs.bounds`; the BVH one
    calls this). A mesh's own vertices were checked when it was made."""
    if not _own_vertices(mesh, x) or isinstance(radius, wp.array):
        _pairs.bounds(x, radius)


def _per_point(value, count: int, device, what: str, pool: _pairs.Pool | None = None) -> wp.array:
    """A positive, finite scalar or (count,) array as a float32 wp.array on ``device`` (a scalar's array from
    ``pool``, when given)."""
    if isinstance(value, wp.array):
        if value.shape != (count,) or value.dtype != wp.float32:
            raise ValueError(f"{what}: expected a ({count},) float32 array, got {value.shape} {value.dtype}")
        return value if value.device == device else value.to(device)
    arr = np.asarray(value.detach().cpu().numpy() if hasattr(value, "detach") else value, dtype=np.float64)
    if arr.ndim == 0:
        v = _host_scalar(arr, what)
        if pool is not None:
            arr = pool.empty(count, wp.float32)
            arr.fill_(np.float32(v))
            return arr
        return wp.full(count, np.float32(v), dtype=wp.float32, device=device)
    if arr.shape != (count,):
        raise ValueError(f"{what}: expected a scalar or shape ({count},), got {arr.shape}")
    bad = np.nonzero(~np.isfinite(arr) | (arr <= 0.0))[0]
    if bad.size:
        raise ValueError(f"{what} must be positive and finite; {bad.size} value(s) are not, e.g. index {int(bad[0])}: {arr[bad[0]]}")
    return wp.array(arr.astype(np.float32), dtype=wp.float32, device=device)


def edge_fields(mesh: Mesh, *, positions: wp.array | None = None, device=None, requires_grad: bool = False) -> EdgeFields:
    """Midpoints, lengths, signed dihedral angles and normals of the interior edges of a :class:`Mesh`.

    Launched as a differentiable kernel: inside a ``wp.Tape`` it is recorded like any Warp launch. Without
    ``positions`` the midpoints are relative to ``mesh.origin`` (the operators' frame, ``mesh.local_vertices``).
    """
    device = positions.device if positions is not None else get_device(device)
    return _edge_fields(mesh, _positions(mesh, positions, device), requires_grad)


def _edge_fields(mesh: Mesh, x: wp.array, requires_grad: bool = False, pool: _pairs.Pool | None = None,
                 keep: bool = False) -> EdgeFields:
    """The edge fields of positions ``x`` (scratch from ``pool`` unless they need gradients). ``keep``: when ``x`` is
    the mesh's own vertex array (:func:`_own_vertices`) and no gradient is wanted, computed once and kept with the
    mesh; the caller then only reads them."""
    device = x.device
    if keep and not (requires_grad or x.requires_grad) and _own_vertices(mesh, x):
        name = ("edge_fields", str(device))
        # arrays made while a graph is captured only hold their values once it runs: none is kept then
        kept = mesh._kept(name) if device.is_capturing else mesh._memo(name, lambda: _edge_fields(mesh, x))
        if kept is not None:
            return kept
    edges = _edge_array(mesh, device)
    ne = edges.shape[0]
    rg = requires_grad or x.requires_grad
    if rg:
        pool = None

    def new(dtype):
        return pool.empty(ne, dtype) if pool is not None else wp.empty(ne, dtype=dtype, device=device, requires_grad=rg)

    f = EdgeFields(edges, new(wp.vec3), new(wp.float32), new(wp.float32), new(wp.vec3))
    wp.launch(_k.edge_geometry, dim=ne, inputs=[x, edges], outputs=[f.mid, f.length, f.angle, f.normal], device=device)
    return f


def _midpoint_bvh(f: EdgeFields) -> wp.Bvh:
    ne = f.mid.shape[0]
    lowers = wp.empty(ne, dtype=wp.vec3, device=f.mid.device)
    uppers = wp.empty(ne, dtype=wp.vec3, device=f.mid.device)
    wp.launch(_k.midpoint_bounds, dim=ne, inputs=[f.mid], outputs=[lowers, uppers], device=f.mid.device, record_tape=False)
    return wp.Bvh(lowers, uppers)


def _segment_bvh(x: wp.array, f: EdgeFields) -> wp.Bvh:
    ne = f.edges.shape[0]
    lowers = wp.empty(ne, dtype=wp.vec3, device=x.device)
    uppers = wp.empty(ne, dtype=wp.vec3, device=x.device)
    wp.launch(_k.segment_bounds, dim=ne, inputs=[x, f.edges], outputs=[lowers, uppers], device=x.device, record_tape=False)
    return wp.Bvh(lowers, uppers)


def _partials(groups: _pairs.Groups, device, *dtypes, pool: _pairs.Pool | None = None) -> list:
    shape = (groups.splits, groups.padded)
    return [_pairs._empty(pool, device, shape, dt) for dt in dtypes]


def _soft_bvh(x, tau_arr, kappa, f, outputs):
    """VNC-soft through a per-thread BVH query; returns the backward closure."""
    device = x.device
    V = x.shape[0]
    bvh = _midpoint_bvh(f)
    wp.launch(_k.soft_forward, dim=V, inputs=[x, tau_arr, kappa, bvh.id, f.mid, f.length, f.angle, f.normal],
              outputs=outputs, device=device, record_tape=False)
    num, den, nsum, H, n = outputs

    def backward():
        wp.launch(
            _k.soft_backward, dim=V,
            inputs=[x, tau_arr, kappa, bvh.id, f.mid, f.length, f.angle, f.normal, num, den, nsum, H.grad, n.grad],
            outputs=[x.grad, f.mid.grad, f.length.grad, f.angle.grad, f.normal.grad],
            device=device, record_tape=False,
        )

    return backward


def _soft_sources(cells, f: EdgeFields, device, pool: _pairs.Pool | None = None) -> tuple[wp.array, wp.array]:
    """Edge midpoints+lengths and angles+normals as vec4s in cell order (one 128-bit load each in the kernels)."""
    E = f.mid.shape[0]
    pos = _pairs._empty(pool, device, E, wp.vec4)
    val = _pairs._empty(pool, device, E, wp.vec4)
    wp.launch(_k.pack_soft_sources, dim=E, inputs=[cells.order, f.mid, f.length, f.angle, f.normal],
              outputs=[pos, val], device=device, record_tape=False)
    return pos, val


def _ball_sources(cells, x: wp.array, f: EdgeFields, device, pool: _pairs.Pool | None = None, form: str = "half"
                  ) -> tuple[wp.array, wp.array, wp.array]:
    """Edge segments and angles+normals as vec4s in cell order (:func:`pack_ball_sources`): ``form`` "half"
    (midpoint, half-vector) or "unit" (midpoint, unit direction)."""
    E = f.edges.shape[0]
    seg_m, seg_h, val = (_pairs._empty(pool, device, E, wp.vec4) for _ in range(3))
    wp.launch(_k.pack_ball_sources, dim=E, inputs=[cells.order, x, f.edges, f.angle, f.normal, int(form == "unit")],
              outputs=[seg_m, seg_h, val], device=device, record_tape=False)
    return seg_m, seg_h, val


def _soft_cells(mesh, x, tau_arr, kappa, f, outputs, b: _pairs.Bounds, strategy: str, pool=None):
    """VNC-soft through the grid or dense traversal; returns the backward closure (same pairs, gathered)."""
    device = x.device
    V, E = x.shape[0], f.mid.shape[0]
    cells, groups = _pairs.plan(x, tau_arr, f.mid, b, strategy, b.rmean, max_per_thread=_k.QB, cache=mesh._cache,
                                pool=pool)
    pos, val = _soft_sources(cells, f, device, pool)
    parts = _partials(groups, device, wp.float32, wp.float32, wp.vec3, pool=pool)
    wp.launch(_k.soft_cells_kernel(groups.per_thread), dim=groups.dim, inputs=[x, tau_arr, kappa, *groups.args(cells), pos, val],
              outputs=parts, device=device, record_tape=False, block_dim=_k.CELLS_BLOCK)
    wp.launch(_k.reduce_sums, dim=V, inputs=[groups.order, *parts], outputs=outputs, device=device,
              record_tape=False)
    num, den, nsum, H, n = outputs

    def backward():
        (gx,) = _partials(groups, device, wp.vec3)
        wp.launch(_k.soft_cells_grad_x, dim=(groups.splits, groups.padded),
                  inputs=[x, tau_arr, kappa, *groups.args(cells), pos, val, num, den, nsum, H.grad, n.grad],
                  outputs=[gx], device=device, record_tape=False)
        wp.launch(_k.reduce_add_vec3, dim=V, inputs=[groups.order, gx], outputs=[x.grad], device=device,
                  record_tape=False)
        # edge adjoints: each edge gathers over the vertices whose ball (radius tau_k) reaches its midpoint
        # (the kernel adds the reach as the groups' pad, so per-edge radii are zero)
        zero = wp.zeros(E, dtype=wp.float32, device=device)
        vcells, egroups = _pairs.plan(f.mid, zero, x, b, strategy, b.rmax, b.rmax)
        vpos = wp.empty(V, dtype=wp.vec4, device=device)
        vcoef = wp.empty(V, dtype=wp.vec4, device=device)
        vgs = wp.empty(V, dtype=wp.vec4, device=device)
        wp.launch(_k.pack_vertex_adjoints, dim=V,
                  inputs=[vcells.order, x, tau_arr, kappa, num, den, nsum, H.grad, n.grad],
                  outputs=[vpos, vcoef, vgs], device=device, record_tape=False)
        eparts = _partials(egroups, device, wp.float32, wp.float32, wp.vec3, wp.vec3)
        wp.launch(_k.soft_cells_grad_edges, dim=egroups.dim,
                  inputs=[f.mid, f.angle, f.normal, *egroups.args(vcells), vpos, vcoef, vgs],
                  outputs=eparts, device=device, record_tape=False)
        wp.launch(_k.reduce_edge_grads, dim=E, inputs=[egroups.order, f.length, f.angle, f.normal, *eparts],
                  outputs=[f.angle.grad, f.length.grad, f.normal.grad, f.mid.grad], device=device,
                  record_tape=False)

    return backward


def vnc_soft(
    mesh,
    tau,
    *,
    kappa: float = 6.0,
    device=None,
    positions: wp.array | None = None,
    tape: wp.Tape | None = None,
    strategy: str = "auto",
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
        positions: (V,) vec3 ``wp.array`` overriding the vertex positions of a :class:`~vnc_warp.Mesh`, e.g. with
            ``requires_grad=True``.
        tape: a ``wp.Tape`` to record on; pass the tape you are inside to differentiate through this call (with
            ``positions`` that require gradients).
        strategy: how pairs within the cut-off are found: "auto", "grid", "dense" or "bvh" (same result; the
            backward pass visits the same pairs as the forward).

    Returns:
        ``(H, n)``: dimensionless curvature (positive on convex regions) and unit normals, per vertex: (V,) float32
        and (V,) vec3 Warp arrays for a Mesh, (V_in,) and (V_in, 3) NumPy arrays for a trimesh, pair or path, torch
        tensors for tensors. A vertex with no edge in reach gets ``H = 0`` and ``n = 0``; a vertex no face uses,
        NaN.
    """
    src = mesh_input(mesh)
    _mesh_only(src, "vnc_soft", positions=positions, tape=tape)
    if src.kind == "torch":
        from .torch import _vnc_soft_input

        return _vnc_soft_input(mesh[0], src, tau, kappa=kappa, device=device)
    tau = src.to_mesh_vertices(tau, "tau")
    H, n = _vnc_soft(src.mesh, tau, kappa=kappa, device=device if device is not None else src.device,
                     positions=positions, tape=tape, strategy=strategy)
    if positions is None:
        _warn_if_degenerate("vnc_soft", src, tau, kappa, n)
    return src.per_vertex(H), src.per_vertex(n)


def _mesh_only(src: MeshInput, op: str, **advanced) -> None:
    """Arguments that address a Mesh's own vertex order need a :class:`Mesh`."""
    given = [k for k, v in advanced.items() if v is not None]
    if given and src.kind != "warp":
        raise TypeError(f"{op}: {', '.join(given)}= needs a vw.Mesh (its own vertex order); "
                        "make one with vw.load_mesh(...)")


class DegenerateResultWarning(UserWarning):
    """A result that is zero for a reason outside the surface: no edge in reach, or weights that underflow."""


_warned: set = set()


def _warn_if_degenerate(op: str, src: MeshInput, tau, kappa: float | None, n: wp.array, *, soft: bool = True) -> None:
    """Warn once per operator and reason when no vertex had anything in reach (``n = 0`` everywhere: on a flat
    mesh ``n`` is not zero, so only the reach is tested). Checked where reading ``n`` costs nothing: on the CPU,
    or when the results go to the host anyway."""
    if n.device.is_cuda and src.kind == "warp":
        return
    if np.any(n.numpy()):
        return
    reason = _degenerate_reason(src.mesh, tau, kappa, soft=soft)
    if reason is not None:
        _warn_once(op, reason[0], f"{op} on {src.mesh.name}: every vertex got H = 0 and n = 0: {reason[1]}")


def _warn_once(op: str, reason: str, message: str) -> None:
    """A :class:`DegenerateResultWarning`, once per operator and reason in a process (stack: user, operator,
    checker, here)."""
    if (op, reason) not in _warned:
        _warned.add((op, reason))
        warnings.warn(message, DegenerateResultWarning, stacklevel=4)


def _degenerate_reason(mesh: Mesh, tau, kappa: float | None, *, soft: bool) -> tuple[str, str] | None:
    """Why nothing was in reach anywhere: ``("reach", text)`` or ``("kappa", text)``; None when neither explains it."""
    from scipy.spatial import cKDTree

    v = mesh.local_vertices.astype(np.float64)
    e = mesh.topology.interior
    if e.shape[0] == 0:
        return None
    d = cKDTree(0.5 * (v[e[:, 0]] + v[e[:, 1]])).query(v)[0]
    t = np.broadcast_to(np.asarray(_host_values(tau), np.float64), d.shape)
    edge = mesh.mean_edge_length
    if soft and (t < d).all():
        return "reach", (f"tau = {_fmt(t)} is below every vertex's distance to its nearest edge midpoint (at least "
                         f"{d.min():.4g}, {d.min() / edge:.2f} mean edge lengths), so no edge is within reach; take "
                         f"tau of a few mean edge lengths (vw.default_scales)")
    if kappa is not None:
        sigma = t / float(kappa)
        ratio = float((d / sigma).min())
        if ratio > 13.0:
            return "kappa", (f"kappa = {kappa:g} makes sigma = tau / kappa = {_fmt(sigma)}, and the nearest edge "
                             f"midpoints are {ratio:.0f} sigma away or more: every Gaussian weight exp(-d^2 / 2 "
                             f"sigma^2) underflows to 0 in float32; the paper uses kappa = 6")
    return None


def _host_values(value):
    return value.numpy() if isinstance(value, wp.array) else (
        value.detach().cpu().numpy() if hasattr(value, "detach") else value)


def _fmt(a: np.ndarray) -> str:
    a = np.asarray(a)
    lo, hi = float(a.min()), float(a.max())
    return f"{lo:.4g}" if lo == hi else f"{lo:.4g}..{hi:.4g}"


def _vnc_soft(mesh: Mesh, tau, *, kappa: float, device, positions: wp.array | None, tape: wp.Tape | None,
              strategy: str) -> tuple[wp.array, wp.array]:
    """:func:`vnc_soft` on a :class:`Mesh`: Warp arrays per mesh vertex."""
    if not (kappa > 0.0):
        raise ValueError(f"kappa must be positive for VNC-soft, got {kappa}")
    _pairs.check_strategy(strategy)
    device = positions.device if positions is not None else get_device(device)
    x = _positions(mesh, positions, device)
    if tape is not None and not x.requires_grad:
        raise ValueError("vnc_soft(tape=...) needs positions given as a wp.array with requires_grad=True")
    rg = x.requires_grad
    t = _host_scalar(tau, "tau")
    if t is not None and positions is None and tape is None and strategy != "bvh":
        # a call fixed by its arguments: replayed from a captured graph from its second time on (vnc_warp._replay)
        key = ("vnc_soft", t, float(kappa), strategy)
        H, n = _replay.call(mesh, device, key, "vnc_soft",
                            lambda pool, fresh: _soft_call(mesh, x, t, float(kappa), strategy, pool, fresh)[0][3:])
        return H, n
    # without a backward pass nothing outlives the call but H and n: the rest is pooled scratch
    pool = None if (rg or tape is not None) else _pairs.Pool(device, "vnc_soft")
    outputs, f, backward = _soft_call(mesh, x, tau, float(kappa), strategy, pool, True)
    H, n = outputs[3], outputs[4]
    if tape is not None:
        tape.record_func(backward=backward, arrays=[H, n, f.mid, f.length, f.angle, f.normal])
    return H, n


def _host_scalar(value, what: str) -> float | None:
    """``value`` as a float when it is a scalar given on the host (checked positive and finite), else None."""
    if isinstance(value, wp.array) or (hasattr(value, "requires_grad") and value.requires_grad) or np.ndim(value) != 0:
        return None
    try:
        v = float(value.detach().cpu() if hasattr(value, "detach") else value)
    except (TypeError, ValueError):
        raise TypeError(f"{what} must be a positive number or an array of per-point values, got {value!r}") from None
    if not (np.isfinite(v) and v > 0.0):
        raise ValueError(f"{what} must be positive and finite, got {v}")
    return v


def _soft_call(mesh, x, tau, kappa: float, strategy: str, pool, fresh: bool):
    """The launches of one VNC-soft call: ``([num, den, nsum, H, n], edge fields, backward closure)``.

    ``pool``: scratch (None: new arrays, kept by the backward closure); ``fresh``: ``H`` and ``n`` are new arrays
    (else from ``pool``: a captured call's outputs, see :mod:`vnc_warp._replay`)."""
    device = x.device
    V = mesh.num_vertices
    rg = x.requires_grad
    tau_arr = _per_point(tau, V, device, "tau", pool)
    f = _edge_fields(mesh, x, pool=pool)
    outputs = [_pairs._empty(pool, device, V, wp.float32), _pairs._empty(pool, device, V, wp.float32),
               _pairs._empty(pool, device, V, wp.vec3)]
    if fresh:
        outputs += [wp.empty(V, dtype=wp.float32, device=device, requires_grad=rg),
                    wp.empty(V, dtype=wp.vec3, device=device, requires_grad=rg)]
    else:
        outputs += [pool.empty(V, wp.float32), pool.empty(V, wp.vec3)]
    if strategy == "bvh":
        _check_values(mesh, x, tau_arr)
        backward = _soft_bvh(x, tau_arr, kappa, f, outputs)
    else:
        b = _host_bounds(mesh, x, _radius_stats(tau)) or _pairs.bounds(x, tau_arr)
        concrete = _pairs.resolve(strategy, device, b, b.rmean, V, f.mid.shape[0])
        backward = _soft_cells(mesh, x, tau_arr, kappa, f, outputs, b, concrete, pool)
    return outputs, f, backward


def choose_strategy(mesh: Mesh, tau, *, variant: str = "soft", device=None, positions: wp.array | None = None) -> str:
    """The traversal ``strategy="auto"`` takes for this call of :func:`vnc_soft` ("soft") or :func:`vnc_hard` /
    :func:`integrated_mean_curvature` ("hard"): "grid" or "dense".

    ``tau`` may be a scalar or a (V,) array, as for the operators; for a scale curve pass its largest scale.
    """
    if variant not in ("soft", "hard"):
        raise ValueError(f"variant must be 'soft' or 'hard', got {variant!r}")
    device = positions.device if positions is not None else get_device(device)
    x = _positions(mesh, positions, device)
    V = mesh.num_vertices
    tau_arr = _per_point(tau, V, device, "tau")
    E = mesh.topology.num_interior
    stats = _radius_stats(tau)
    if variant == "soft":
        b = _host_bounds(mesh, x, stats) or _pairs.bounds(x, tau_arr)
        return _pairs.resolve("auto", device, b, b.rmean, V, E)
    f = edge_fields(mesh, positions=x, device=device)
    b = _host_bounds(mesh, x, stats, lengths=True) or _pairs.bounds(x, tau_arr, f.length)
    return _pairs.resolve("auto", device, b, b.rmean + 0.5 * b.lmax, V, E)


@dataclass
class _PieceSources:
    """Pieces sorted into a grid (:class:`~vnc_warp._pairs.PieceGrid`) and their records for the ball kernels
    (:func:`kernels.vnc.pack_piece_sources`); ``chunk_lo``, ``chunk_hi``: the boxes of their runs
    (:func:`kernels.vnc.chunk_boxes`) when kept with them, else None (made per call when a traversal tests runs)."""

    grid: _pairs.PieceGrid
    seg_m: wp.array
    seg_h: wp.array
    val: wp.array
    chunk_lo: wp.array | None = None
    chunk_hi: wp.array | None = None


def _piece_sources(x: wp.array, f: EdgeFields, grid: _pairs.PieceGrid, pool: _pairs.Pool | None) -> _PieceSources:
    """The records of the sorted pieces of ``grid`` (scratch from ``pool``; None: new arrays)."""
    device = x.device
    n = grid.pieces.capacity
    seg_m, seg_h, val = (_pairs._empty(pool, device, n, wp.vec4) for _ in range(3))
    p = grid.pieces
    wp.launch(_k.pack_piece_sources, dim=n,
              inputs=[grid.cells.order, p.piece_edge, p.piece_index, p.counts, x, f.edges, f.angle, f.normal],
              outputs=[seg_m, seg_h, val], device=device, record_tape=False)
    return _PieceSources(grid, seg_m, seg_h, val)


def _kept_pieces(mesh: Mesh, x: wp.array, f: EdgeFields) -> _PieceSources | None:
    """The pieces of the mesh's own edges for single-scale ball traversals on the CPU (:data:`_pairs.CPU_PIECES`):
    sorted once per vertex array and kept with the mesh, whatever the radius (as trimesh keeps an R-tree of its
    edges), with the boxes of their runs. While a graph is captured (its arrays only hold values once it runs) only
    pieces kept before, else None."""
    piece, cell = _pairs.CPU_PIECES
    device = x.device
    name = ("cpu_pieces", str(device), piece, cell)
    if device.is_capturing:
        return mesh._kept(name)

    def build():
        b = _host_bounds(mesh, x, (0.0, 0.0), lengths=True)
        grid = _pairs.piece_grid(x, f.edges, f.length, b, "grid", piece=piece * b.lmean, cell=cell * b.lmean,
                                 fine=True, capacity=lambda p: _pairs.piece_capacity(_interior_lengths(mesh), p))
        src = _piece_sources(x, f, grid, None)
        src.chunk_lo, src.chunk_hi = _chunk_boxes(src.seg_m, src.seg_h, True, grid.cells.first, grid.cells.first,
                                                  None)
        return src

    return mesh._memo(name, build)


def _chunk_boxes(seg_m: wp.array, seg_h: wp.array, unit: bool, start: wp.array | None, end: wp.array,
                 pool: _pairs.Pool | None) -> tuple[wp.array, wp.array]:
    """The boxes of the runs of :data:`kernels.vnc.CHUNK` records a chunked traversal reads, from the first record
    ``start[0]`` (None: no traversal tests runs; empty boxes) to ``end[-1]`` (:func:`kernels.vnc.chunk_boxes`)."""
    device = seg_m.device
    nchunks = -(-seg_m.shape[0] // int(_k.CHUNK)) if start is not None else 0
    lo, hi = (_pairs._empty(pool, device, nchunks, wp.vec3) for _ in range(2))
    if nchunks:
        # few threads, each a serial loop: blocks of one warp spread them over every multiprocessor
        wp.launch(_k.chunk_boxes, dim=nchunks, inputs=[seg_m, seg_h, int(unit), start, end], outputs=[lo, hi],
                  device=device, block_dim=32)
    return lo, hi


def _ball_sums(mesh: Mesh, points, radius, g, device, strategy: str, x: wp.array | None = None,
               radius_stats=None, pool: _pairs.Pool | None = None, fresh: bool = True):
    """Eqs. (1)-(2) sums per query point: ``(num, den, nsum, H, n)`` (``H``, ``n`` normalized as in Eq. (2)).

    ``points is x`` (the mesh's vertices on ``device``) marks the vertices as the queries: their Morton order is
    then kept with the mesh. ``radius_stats``: ``(max, mean)`` of ``radius`` when known on the host. ``pool``: the
    scratch (default: the device's); ``fresh``: ``H`` and ``n`` are new arrays (else from ``pool``)."""
    _pairs.check_strategy(strategy)
    if x is None:
        x = _mesh_vertices(mesh, device)
    pool = pool or _pairs.Pool(device, "ball")
    # on the (one-thread) CPU the mesh's own edges' fields are kept with it, as their pieces are (_kept_pieces)
    f = _edge_fields(mesh, x, pool=pool, keep=device.is_cpu)
    P = points.shape[0]
    outputs = [_pairs._empty(pool, device, P, dt) for dt in (wp.float32, wp.float32, wp.vec3)]
    outputs += [_pairs._empty(None if fresh else pool, device, P, dt) for dt in (wp.float32, wp.vec3)]
    if strategy == "bvh":
        _check_values(mesh, x, radius)
        bvh = _segment_bvh(x, f)
        wp.launch(_k.ball_sums, dim=P, inputs=[points, radius, g, bvh.id, x, f.edges, f.mid, f.angle, f.normal],
                  outputs=outputs[:3], device=device)
        wp.launch(_k.normalize_sums, dim=P, inputs=outputs[:3], outputs=outputs[3:], device=device)
        return outputs
    E = f.mid.shape[0]
    host = _host_bounds(mesh, x, radius_stats, lengths=True)
    b = host or _pairs.bounds(x, radius, f.length)
    # an edge crosses the ball only if its midpoint is within radius + L / 2
    concrete = _pairs.resolve(strategy, device, b, b.rmean + 0.5 * b.lmax, P, E)
    reach = _pairs.ball_reach(b)
    cache = mesh._cache if points is x else None
    # on the CPU the pieces of the mesh's own edges are kept with it, whatever the radius (_kept_pieces)
    kept = (_kept_pieces(mesh, x, f) if device.is_cpu and _pairs.CPU_PIECES is not None and _own_vertices(mesh, x)
            and _pairs.uses_pieces(concrete, b, any_length=True) else None)
    if kept is not None or _pairs.uses_pieces(concrete, b):
        # pieces of the edges, in "unit" records (the only form that holds a piece)
        if kept is not None:
            src = kept
        else:
            capacity = None if host is None else (lambda piece: mesh._memo(
                ("piece_capacity", piece), lambda: _pairs.piece_capacity(_interior_lengths(mesh), piece)))
            src = _piece_sources(x, f, _pairs.piece_grid(x, f.edges, f.length, b, concrete, capacity=capacity,
                                                         max_per_thread=_k.QB, pool=pool), pool)
        cells, groups, _ = _pairs.piece_plan(points, radius, x, f.edges, f.length, b, concrete, max_per_thread=_k.QB,
                                             cache=cache, pool=pool, grid=src.grid)
        plans = [(cells, groups)]
        variants = [dict(_k.ball_variant(concrete, groups.per_thread, reach, tuple(cells.dims) == (1, 1, 1),
                                         device.is_cuda), form="unit")]
        seg_m, seg_h, val = src.seg_m, src.seg_h, src.val
    else:
        src = None
        plans = _pairs.ball_plans(points, radius, f.mid, f.length, b, concrete, max_per_thread=_k.QB, cache=cache,
                                  pool=pool,
                                  tier_size=_tier_sizes(mesh) if radius_stats is not None and b.lmax > 0 else None)
        groups = plans[0][1]
        variants = [_k.ball_variant(concrete, groups.per_thread, reach, tuple(c.dims) == (1, 1, 1), device.is_cuda)
                    for c, _ in plans]
        # every traversal reads the edges in one sorted order (ball_plans)
        seg_m, seg_h, val = _ball_sources(plans[0][0], x, f, device, pool, form=variants[0]["form"])
    ns = groups.splits
    parts = [pool.empty((ns, groups.padded), dt) for dt in (wp.float32, wp.float32, wp.vec3)]
    variant = variants[0]
    chunked = [cells for (cells, _), v in zip(plans, variants) if v["chunks"]]
    if src is not None and src.chunk_lo is not None:
        chunk_lo, chunk_hi = src.chunk_lo, src.chunk_hi  # kept with the pieces
    else:
        chunk_lo, chunk_hi = _chunk_boxes(seg_m, seg_h, variant["form"] == "unit", chunked[0].first if chunked else None,
                                          plans[-1][0].first, pool)
    for i, (cells, grp) in enumerate(plans):
        kernel = _k.ball_cells_kernel(grp.per_thread, **variants[i])
        wp.launch(kernel, dim=grp.dim, inputs=[points, radius, g, *grp.args(cells), seg_m, seg_h, val, chunk_lo,
                                               chunk_hi, grp.splits, int(i > 0)],
                  outputs=parts, device=device, block_dim=_k.CELLS_BLOCK)
    wp.launch(_k.reduce_sums, dim=P, inputs=[groups.order, *parts], outputs=outputs, device=device)
    return outputs


def _ball_call(mesh: Mesh, device, tau, kappa: float | None, strategy: str, pool: _pairs.Pool, fresh: bool):
    """The launches of VNC-hard / Eq. (1) at the vertices: ``(num, den, nsum, H, n)``; ``kappa=None``: w = 1."""
    V = mesh.num_vertices
    radius = _per_point(tau, V, device, "tau", pool)
    g = pool.empty(V, wp.float32)
    if kappa is None:
        g.zero_()
    else:
        wp.launch(_k.gaussian_factor, dim=V, inputs=[radius, float(kappa)], outputs=[g], device=device)
    points = _mesh_vertices(mesh, device)
    return _ball_sums(mesh, points, radius, g, device, strategy, x=points, radius_stats=_radius_stats(tau),
                      pool=pool, fresh=fresh)


def vnc_hard(mesh, tau, *, kappa: float | None = 6.0, device=None, strategy: str = "auto"):
    """VNC-hard, Eq. (2): exact edge/ball intersections, normalized by the weighted intersected length.

    ``H(v_k, r) = sum_j alpha_j delta_j w_kj l_j / (2 sum_j w_kj l_j)`` over the edges crossing the ball of
    radius ``r = tau`` around ``v_k``, ``l_j`` the length of edge ``j`` inside the ball and
    ``w_kj = exp(-|v_k - m_j|^2 / 2 sigma^2)`` with ``sigma = tau / kappa``; ``kappa=None`` means ``w = 1``.
    The normal weights the edges' area-weighted normals by ``w_kj l_j``. Not differentiable (use VNC-soft).

    Args:
        mesh: a :class:`~vnc_warp.Mesh`, a ``trimesh.Trimesh``, a ``(V, F)`` pair (NumPy or torch) or a path.
        tau: ball radius (mesh units): a scalar or one value per vertex (of the input).
        kappa: radius-to-sigma ratio, or None for the unweighted operator.
        device: Warp device (default: a tensor's device, else the preferred device).
        strategy: "auto", "grid", "dense" or "bvh" (see :func:`vnc_soft`).

    Returns:
        ``(H, n)`` per vertex, as for :func:`vnc_soft`: Warp arrays for a Mesh, NumPy arrays (one row per input
        vertex) for a trimesh, pair or path, torch tensors for tensors.
    """
    src = mesh_input(mesh)
    tau = src.to_mesh_vertices(tau, "tau")
    H, n = _vnc_hard(src.mesh, tau, kappa=kappa, device=device if device is not None else src.device,
                     strategy=strategy)
    _warn_if_degenerate("vnc_hard", src, tau, kappa, n, soft=False)
    return src.per_vertex(H), src.per_vertex(n)


def _vnc_hard(mesh: Mesh, tau, *, kappa: float | None, device, strategy: str) -> tuple[wp.array, wp.array]:
    """:func:`vnc_hard` on a :class:`Mesh`: Warp arrays per mesh vertex."""
    device = get_device(device)
    if kappa is not None and not (kappa > 0.0):
        raise ValueError(f"kappa must be positive or None, got {kappa}")
    _pairs.check_strategy(strategy)
    k = None if kappa is None else float(kappa)
    t = _host_scalar(tau, "tau")
    if t is not None and strategy != "bvh":
        H, n = _replay.call(mesh, device, ("vnc_hard", t, k, strategy), "ball",
                            lambda pool, fresh: _ball_call(mesh, device, t, k, strategy, pool, fresh)[3:])
        return H, n
    outputs = _ball_call(mesh, device, tau, k, strategy, _pairs.Pool(device, "ball"), True)
    return outputs[3], outputs[4]


def integrated_mean_curvature(mesh, radius, points=None, *, device=None, strategy: str = "auto"):
    """Eq. (1): integrated discrete mean curvature in balls, ``1/2 sum_j alpha_j delta_j l_j``.

    The normal-cycle measure of Cohen-Steiner and Morvan, equal to trimesh's
    ``curvature.discrete_mean_curvature_measure(mesh, points, radius)``.

    Args:
        mesh: a :class:`~vnc_warp.Mesh`, a ``trimesh.Trimesh``, a ``(V, F)`` pair (NumPy or torch) or a path.
        radius: ball radius (mesh units), a scalar, or one value per point (per input vertex without ``points``).
        points: (P, 3) ball centres (NumPy, torch or a list); defaults to the vertices.
        device: Warp device (default: a tensor's device, else the preferred device).
        strategy: "auto", "grid", "dense" or "bvh" (see :func:`vnc_soft`).

    Returns:
        In mesh units (length x angle): per vertex as for :func:`vnc_soft` (a (V,) float32 Warp array for a Mesh,
        NumPy for a trimesh, pair or path, torch for tensors), or one value per point in the same kind.
    """
    src = mesh_input(mesh)
    dev = device if device is not None else src.device
    if points is None:
        return src.per_vertex(_integrated(src.mesh, src.to_mesh_vertices(radius, "radius"), None, device=dev,
                                          strategy=strategy))
    out = _integrated(src.mesh, radius, points, device=dev, strategy=strategy)
    return src.per_point(out)


def _integrated(mesh: Mesh, radius, points, *, device, strategy: str) -> wp.array:
    """:func:`integrated_mean_curvature` on a :class:`Mesh`: a (V,) or (P,) Warp array."""
    device = get_device(device)
    t = _host_scalar(radius, "radius")
    if points is None and t is not None and strategy != "bvh":
        def run(pool, fresh):
            num = _ball_call(mesh, device, t, None, strategy, pool, fresh)[0]
            out = _pairs._empty(None if fresh else pool, device, mesh.num_vertices, wp.float32)
            wp.launch(_k.scaled_copy, dim=mesh.num_vertices, inputs=[num, 0.5], outputs=[out], device=device)
            return [out]

        return _replay.call(mesh, device, ("integrated_mean_curvature", t, strategy), "ball", run)[0]
    if points is None:
        pts = mesh.vertices
    else:
        pts = np.asarray(_host_values(points), dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"points must be (P, 3), got {pts.shape}")
        pts = pts - mesh.origin  # the kernels run on coordinates relative to the mesh's centre
        if not np.isfinite(pts).all():
            raise ValueError("points contain NaN or infinite coordinates")
    P = pts.shape[0]
    if P == 0:
        _per_point(radius, 0, device, "radius")
        return wp.empty(0, dtype=wp.float32, device=device)
    points_wp = _mesh_vertices(mesh, device) if points is None else wp.array(
        np.asarray(pts, dtype=np.float32), dtype=wp.vec3, device=device)
    r = _per_point(radius, P, device, "radius")
    g = wp.zeros(P, dtype=wp.float32, device=device)
    num = _ball_sums(mesh, points_wp, r, g, device, strategy, x=points_wp if points is None else None,
                     radius_stats=_radius_stats(radius))[0]
    out = wp.empty(P, dtype=wp.float32, device=device)
    wp.launch(_k.scaled_copy, dim=P, inputs=[num, 0.5], outputs=[out], device=device)
    return out
