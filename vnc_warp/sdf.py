"""Signed distances to a triangle mesh, at query points or on a grid (paper Sec. 3.2, Algorithm 1).

VNC-Flow's SDF-remesh (:mod:`vnc_warp.remesh`) samples the grid, and the C-VAE dataset builder labels
query points with :func:`signed_distance`. Both classify inside/outside with Warp's mesh queries:

* ``sign="winding"`` (default) uses the fast generalised winding number
  (``wp.mesh_query_point_sign_winding_number``): a mesh with holes, such as a raw scan, still gets a
  sound inside, bounded by the winding-number 1/2 level across each hole.
* ``sign="normal"`` uses the closest face's normal (``wp.mesh_query_point_sign_normal``): faster, but
  only right for watertight, consistently wound meshes.

Distances are negative inside, in the mesh's units. The ``wp.Mesh`` (with its BVH) built for a
:class:`~vnc_warp.mesh.Mesh` is cached on that Mesh per device and sign mode, so repeated queries on
the same mesh do not rebuild it; treat a Mesh as immutable once queried (use ``with_vertices``).
"""

from __future__ import annotations

import sys
import weakref
from typing import Any

import numpy as np
import warp as wp

from vnc_warp._device import get_device
from vnc_warp.kernels import sdf as _k
from vnc_warp.mesh import Mesh, load_mesh

__all__ = ["signed_distance", "sdf_grid", "surface_samples", "inward_distances"]

_SIGNS = ("winding", "normal")
# the wp.Mesh of each Mesh, per device, kept while the Mesh lives
_WP_MESHES: "weakref.WeakKeyDictionary[Mesh, dict]" = weakref.WeakKeyDictionary()
# "no bound" for the closest-point search; its square stays finite in float32
_UNBOUNDED = 1.0e18
# coarse-to-fine factors tried for the narrow-band grid
_BAND_FACTORS = (1, 2, 4, 8)


def sign_flag(sign: str) -> int:
    """The kernels' ``use_winding`` flag for a ``sign`` argument; raises ValueError on unknown modes."""
    if sign not in _SIGNS:
        raise ValueError(f"sign must be one of {_SIGNS}, got {sign!r}")
    return int(sign == "winding")


def warp_mesh(mesh: Mesh, device: wp.context.Device, *, winding: bool) -> wp.Mesh:
    """The ``wp.Mesh`` of ``mesh`` on ``device``, built once and cached on the Mesh.

    Args:
        mesh: the mesh.
        device: where the BVH lives.
        winding: build the winding-number data (needed by ``sign="winding"``).

    Returns:
        A ``wp.Mesh``; a winding-enabled one also serves ``sign="normal"`` queries.
    """
    cache = _WP_MESHES.setdefault(mesh, {})
    key = device.alias
    found = cache.get(key)
    if found is not None and (found.support_winding_number or not winding):
        return found
    points = wp.array(mesh.vertices, dtype=wp.vec3, device=device)
    indices = wp.array(mesh.faces.reshape(-1), dtype=wp.int32, device=device)
    wm = wp.Mesh(points=points, indices=indices, support_winding_number=winding)
    cache[key] = wm
    return wm


def _is_torch(x: Any) -> bool:
    torch = sys.modules.get("torch")
    return torch is not None and isinstance(x, torch.Tensor)


def _points_to_warp(points: Any, device) -> tuple[wp.array, wp.context.Device, bool]:
    """(N,) vec3 Warp view of ``points``, the device to run on, and whether the input was torch."""
    if _is_torch(points):
        import torch

        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"signed_distance: points must be (N, 3), got {tuple(points.shape)}")
        if points.dtype != torch.float32:
            raise TypeError(f"signed_distance: torch points must be float32, got {points.dtype}")
        dev = get_device(points.device if device is None else device)
        if get_device(points.device) != dev:
            raise ValueError(f"signed_distance: points are on {points.device} but device={dev.alias!r}; "
                             "move them first (points.to(...)) to make the copy explicit")
        pts = points.detach()
        if pts.stride(1) != 1:
            pts = pts.contiguous()
        return wp.from_torch(pts, dtype=wp.vec3, requires_grad=False), dev, True
    if isinstance(points, wp.array):
        dev = get_device(points.device if device is None else device)
        if points.device != dev:
            raise ValueError(f"signed_distance: points are on {points.device.alias} but device={dev.alias!r}; "
                             "copy them first (points.to(device)) to make the copy explicit")
        if points.dtype == wp.vec3 and points.ndim == 1:
            return points, dev, False
        if points.dtype == wp.float32 and points.ndim == 2 and points.shape[1] == 3 and points.is_contiguous:
            return points.view(wp.vec3), dev, False
        raise TypeError(f"signed_distance: Warp points must be (N,) vec3 or contiguous (N, 3) float32, "
                        f"got {points.ndim}-d {points.dtype.__name__}")
    arr = np.asarray(points, dtype=np.float32)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"signed_distance: points must be (N, 3), got {arr.shape}")
    dev = get_device(device)
    return wp.array(np.ascontiguousarray(arr), dtype=wp.vec3, device=dev), dev, False


def signed_distance(mesh: Any, points: Any, *, device=None, max_dist: float | None = None,
                    sign: str = "winding"):
    """Signed distance from each point to the mesh surface, negative inside.

    Args:
        mesh: a :class:`~vnc_warp.mesh.Mesh`, or anything :func:`~vnc_warp.mesh.load_mesh` accepts.
            Open meshes are fine with ``sign="winding"``.
        points: (N, 3) query positions in the mesh's units: a NumPy array (any float dtype, copied to
            ``device`` as float32), a Warp array ((N,) vec3 or (N, 3) float32), or a float32 torch
            tensor. Warp arrays and torch tensors are used in place, without a host copy
            (``wp.from_torch``), and must already be on ``device`` when it is given.
        device: where to run; None means the points' device for Warp/torch input, else Warp's
            preferred device.
        max_dist: clamp distances to ``[-max_dist, max_dist]`` (mesh units, > 0), e.g. for
            truncated-SDF labels; points with no face that close get ``+-max_dist`` with the exact
            sign, from a second, unbounded query (so this is a clamp, not a speed-up). None: no clamp.
        sign: ``"winding"`` (robust, also for open meshes) or ``"normal"`` (faster, watertight only).

    Returns:
        (N,) float32 signed distances: a ``wp.array`` on ``device``, or, for torch input, a torch
        tensor on the points' device sharing memory with that array (``wp.to_torch``), computed
        on torch's current CUDA stream. Not differentiable.

    Raises:
        ValueError: bad shapes, ``sign``, ``max_dist``, or points on a device other than ``device``.
        TypeError: torch points that are not float32, Warp points of another dtype.
    """
    use_winding = sign_flag(sign)
    if max_dist is None:
        bound = _UNBOUNDED
    else:
        bound = float(max_dist)
        if not np.isfinite(bound) or bound <= 0.0:
            raise ValueError(f"signed_distance: max_dist must be a positive finite distance, got {max_dist!r}")
    pts, dev, from_torch = _points_to_warp(points, device)
    m = load_mesh(mesh)
    # torch CUDA tensors: run on torch's current stream, ordered after whatever produced the points
    # and before whatever consumes the result
    stream = wp.stream_from_torch(points.device) if from_torch and dev.is_cuda else None
    with wp.ScopedStream(stream):
        out = wp.empty(pts.shape[0], dtype=wp.float32, device=dev)
        if pts.shape[0] > 0:
            wm = warp_mesh(m, dev, winding=bool(use_winding))
            wp.launch(_k.signed_distance_points, dim=pts.shape[0], inputs=[wm.id, pts, bound, use_winding],
                      outputs=[out], device=dev)
    return wp.to_torch(out) if from_torch else out


def choose_band_factor(shape: tuple[int, int, int], area: float, spacing: float) -> int:
    """Coarse-to-fine factor with the fewest estimated exact queries.

    A coarse grid of factor ``f`` costs one query per coarse node; the band then costs the fine nodes
    of the cells within half a coarse diagonal of the surface, about ``area * (sqrt(3) + 1) * f *
    spacing`` of volume.
    """
    best, best_cost = 1, float(np.prod(shape))
    for f in _BAND_FACTORS[1:]:
        coarse = np.prod([(n - 2) // f + 2 for n in shape])
        band = area * (np.sqrt(3.0) + 1.0) * f / (spacing * spacing)
        cost = float(coarse + band)
        if cost < best_cost:
            best, best_cost = f, cost
    return best


def sample_grid(wm: wp.Mesh, origin: np.ndarray, spacing: float, shape: tuple[int, int, int], *,
                band_factor: int, use_winding: int, device: wp.context.Device) -> wp.array:
    """Signed distances at the nodes ``origin + spacing * (i, j, k)`` of a ``shape`` grid.

    With ``band_factor > 1`` only the nodes of coarse cells (``band_factor`` fine cells wide) that
    may hold the surface are queried; the rest are interpolated from the coarse grid, which keeps
    their sign and never crosses zero there (enough for marching cubes, not an exact SDF).

    Returns:
        ``shape`` float32 ``wp.array3d`` on ``device``.
    """
    o = wp.vec3(*(float(x) for x in origin))
    out = wp.empty(shape, dtype=wp.float32, device=device)
    if band_factor <= 1:
        wp.launch(_k.signed_distance_grid, dim=shape, inputs=[wm.id, o, float(spacing), _UNBOUNDED, use_winding],
                  outputs=[out], device=device)
        return out
    f = int(band_factor)
    coarse_shape = tuple(max((n - 2) // f + 2, 2) for n in shape)
    coarse = wp.empty(coarse_shape, dtype=wp.float32, device=device)
    active = wp.empty(tuple(n - 1 for n in coarse_shape), dtype=wp.int32, device=device)
    wp.launch(_k.signed_distance_grid, dim=coarse_shape,
              inputs=[wm.id, o, float(spacing * f), _UNBOUNDED, use_winding], outputs=[coarse], device=device)
    # a cell holds no surface if every corner is farther than half the cell diagonal from it
    band = 0.5 * np.sqrt(3.0) * spacing * f * 1.01
    wp.launch(_k.mark_band_cells, dim=active.shape, inputs=[coarse, float(band)], outputs=[active], device=device)
    wp.launch(_k.refine_band_grid, dim=shape,
              inputs=[wm.id, coarse, active, f, o, float(spacing), _UNBOUNDED, use_winding],
              outputs=[out], device=device)
    return out


def sdf_grid(mesh: Any, resolution: int, *, padding: float = 0.1, device=None, sign: str = "winding",
             narrow_band: bool = False) -> tuple[wp.array, np.ndarray, float]:
    """Sample the signed distance on a dense cubic grid around the mesh (for marching cubes).

    The cube is centred on the mesh's bounding box; its side is the longest box side times
    ``1 + 2 * padding``; node ``(i, j, k)`` sits at ``origin + spacing * (i, j, k)``.

    Args:
        mesh: a :class:`~vnc_warp.mesh.Mesh`, or anything :func:`~vnc_warp.mesh.load_mesh` accepts.
        resolution: nodes per axis ``R`` (>= 2).
        padding: margin on each side, as a fraction of the longest bounding-box side (>= 0). Keep it
            above ``1 / R`` so the outer nodes are outside and marching cubes closes the surface.
        device: where to run; None means Warp's preferred device.
        sign: ``"winding"`` or ``"normal"``, as in :func:`signed_distance`.
        narrow_band: query exactly only the nodes near the surface (see below), else every node.
            Near the surface the values are exact either way; far from it they keep the exact sign
            but are a trilinear interpolation of a coarser exact grid, often 5-20x fewer queries.

    Returns:
        ``(grid, origin, spacing)``: (R, R, R) float32 ``wp.array3d`` on ``device`` (negative
        inside), (3,) float64 position of node ``(0, 0, 0)``, and the node spacing (mesh units).

    Raises:
        ValueError: ``resolution < 2``, negative ``padding``, unknown ``sign``.
    """
    use_winding = sign_flag(sign)
    r = int(resolution)
    if r < 2:
        raise ValueError(f"sdf_grid: resolution must be at least 2 nodes per axis, got {resolution!r}")
    if not padding >= 0.0:
        raise ValueError(f"sdf_grid: padding must be >= 0, got {padding!r}")
    m = load_mesh(mesh)
    dev = get_device(device)
    lo = m.vertices.min(0).astype(np.float64)
    hi = m.vertices.max(0).astype(np.float64)
    side = float((hi - lo).max()) * (1.0 + 2.0 * float(padding))
    spacing = side / (r - 1)
    origin = 0.5 * (lo + hi) - 0.5 * side
    shape = (r, r, r)
    factor = choose_band_factor(shape, m.area(), spacing) if narrow_band else 1
    wm = warp_mesh(m, dev, winding=bool(use_winding))
    grid = sample_grid(wm, origin, spacing, shape, band_factor=factor, use_winding=use_winding, device=dev)
    return grid, origin, spacing


def surface_samples(x: wp.array, tri: wp.array, count: int, *, seed: int = 0) -> tuple[wp.array, wp.array]:
    """Centroids and unit normals of ``count`` faces drawn with probability proportional to their area.

    The uniform numbers come from NumPy with a fixed ``seed``, so every device draws the same faces.

    Args:
        x: (V,) vec3 positions.
        tri: (3F,) int32 corners.
        count: number of samples.
        seed: seed of the draw.

    Returns:
        ``(points, normals)``: (count,) vec3 arrays on ``x``'s device; normals follow the winding.
    """
    device = x.device
    num_faces = tri.shape[0] // 3
    area = wp.empty(num_faces, dtype=wp.float32, device=device)
    wp.launch(_k.face_areas, dim=num_faces, inputs=[x, tri], outputs=[area], device=device)
    # a float scan on CUDA adds its blocks' totals in the order they finish; a host prefix sum adds in face order
    cdf = wp.array(np.cumsum(area.numpy(), dtype=np.float32), dtype=wp.float32, device=device)
    u = np.random.default_rng(seed).random(count, dtype=np.float64).astype(np.float32)
    points = wp.empty(count, dtype=wp.vec3, device=device)
    normals = wp.empty(count, dtype=wp.vec3, device=device)
    wp.launch(_k.area_samples, dim=count, inputs=[x, tri, cdf, wp.array(u, dtype=wp.float32, device=device)],
              outputs=[points, normals], device=device)
    return points, normals


def inward_distances(wm: wp.Mesh, x: wp.array, tri: wp.array, count: int, *, seed: int = 0,
                     span: float) -> np.ndarray:
    """Distances through a closed surface along inward face normals, at area-weighted random faces.

    ``count`` faces are drawn with probability proportional to their area (a fixed ``seed``: the same
    faces on every device); from each face's centroid a ray runs along the inward normal to the next
    surface hit. This is the surface's thickness where it is sampled: the diameter of a limb, the
    width of a fin, the length of a tip.

    Args:
        wm: ``wp.Mesh`` of the surface (its BVH answers the rays).
        x: (V,) vec3 positions of the surface, on ``wm``'s device.
        tri: (3F,) int32 corners, outward winding.
        count: number of rays.
        seed: seed of the uniform numbers that pick the faces.
        span: longest distance looked for (mesh units; the bounding-box diagonal or more).

    Returns:
        (count,) float64 distances in mesh units; 0 where a ray found no surface (an open mesh).
    """
    device = x.device
    points, normals = surface_samples(x, tri, count, seed=seed)
    out = wp.empty(count, dtype=wp.float32, device=device)
    wp.launch(_k.inward_thickness, dim=count, inputs=[wm.id, points, normals, 1e-5 * span, 2.0 * span],
              outputs=[out], device=device)
    return np.maximum(out.numpy().astype(np.float64), 0.0)
