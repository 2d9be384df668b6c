"""Sums and vertex normals on the device that come out bit for bit the same on every run (:mod:`kernels.reduce`).

Every quantity VNC-Flow branches on between two recorded stages goes through here rather than through a float
``atomic_add``, whose order of addition on CUDA follows thread timing.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from vnc_warp.kernels import flow as _kf
from vnc_warp.kernels import reduce as _k
from vnc_warp.kernels import remesh as _kr

# Partial sums of the first pass: a fixed count, so the order of the additions is the same on the CPU and on CUDA.
PARTS = 256


def ordered_sum(values: wp.array):
    """``sum_k values[k]`` of a (N,) float32, float64 or vec3d device array, added in a fixed order in float64.

    Returns:
        A float, or a (3,) float64 array for vec3d values.
    """
    if values.dtype == wp.float32:
        kernel, dtype = _kf.strided_sums, wp.float64
    elif values.dtype == wp.float64:
        kernel, dtype = _k.strided_sums_f64, wp.float64
    elif values.dtype == wp.vec3d:
        kernel, dtype = _k.strided_sums_vec3d, wp.vec3d
    else:
        raise TypeError(f"ordered_sum: values of dtype {values.dtype} (float32, float64 or vec3d expected)")
    partial = wp.empty(PARTS, dtype=dtype, device=values.device)
    wp.launch(kernel, dim=PARTS, inputs=[values], outputs=[partial], device=values.device)
    total = np.sum(partial.numpy(), axis=0, dtype=np.float64)
    return float(total) if dtype == wp.float64 else np.asarray(total, dtype=np.float64)


def vertex_normals(x: wp.array, tri: wp.array, out: wp.array | None = None) -> wp.array:
    """(V,) unit area-weighted vertex normals of a triangle mesh (zero at a vertex without faces or with a zero sum).

    Each vertex adds its faces' cross products in face order (its corners sorted by a stable radix sort), so the
    result is the same on every run and device schedule; on the CPU it equals the face-by-face scatter.

    Args:
        x: (V,) vec3 positions.
        tri: (3F,) int32 corners.
        out: (V,) vec3 array to write (new if None).

    Returns:
        ``out``.
    """
    device = x.device
    n, V = tri.shape[0], x.shape[0]
    if out is None:
        out = wp.empty(V, dtype=wp.vec3, device=device)
    keys = wp.empty(2 * n, dtype=wp.int32, device=device)
    corners = wp.empty(2 * n, dtype=wp.int32, device=device)
    wp.copy(keys, tri, count=n)
    wp.launch(_k.iota, dim=n, outputs=[corners], device=device)
    wp.utils.radix_sort_pairs(keys, corners, n)
    counts = wp.zeros(V, dtype=wp.int32, device=device)
    wp.launch(_k.count_corners, dim=n, inputs=[tri], outputs=[counts], device=device)
    offsets = wp.empty(V, dtype=wp.int32, device=device)
    wp.utils.array_scan(counts, offsets, inclusive=False)
    wp.launch(_k.gather_vertex_normals, dim=V, inputs=[x, tri, corners, offsets, counts], outputs=[out],
              device=device)
    return out


def face_measures(x: wp.array, tri: wp.array, sliver: float = 0.0, tiny: float = 0.0):
    """Area, enclosed volume and area-weighted centroid sum of a triangle mesh, summed in a fixed order in float64.

    Args:
        x: (V,) vec3 positions.
        tri: (3F,) int32 corners, wound outward.
        sliver, tiny: the sliver test of :func:`kernels.remesh.face_measures`.

    Returns:
        ``(area, volume, centroid_sum, bad)``: floats in the mesh's units (squared, cubed), the (3,) float64
        ``sum_f area_f centroid_f``, and (2,) int counts of faces with a non-finite corner and of slivers.
    """
    device, F = x.device, tri.shape[0] // 3
    area = wp.empty(F, dtype=wp.float64, device=device)
    volume = wp.empty(F, dtype=wp.float64, device=device)
    centroid = wp.empty(F, dtype=wp.vec3d, device=device)
    bad = wp.zeros(2, dtype=wp.int32, device=device)
    wp.launch(_kr.face_measures, dim=F, inputs=[x, tri, float(sliver), float(tiny)],
              outputs=[area, volume, centroid, bad], device=device)
    return ordered_sum(area), ordered_sum(volume), ordered_sum(centroid), bad.numpy()
