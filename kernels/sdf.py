"""Warp kernels for signed distances to a triangle mesh (paper Sec. 3.2, SDF-remesh of Algorithm 1).

Conventions shared by every kernel here:

* ``use_winding`` is 1 for the sign from the fast winding number (robust for open meshes such as raw
  scans; the ``wp.Mesh`` must be built with ``support_winding_number=True``) and 0 for the sign from
  the closest face's normal (faster, watertight meshes only).
* Distances are clamped to ``max_dist`` but the sign is always exact: a point with no face closer
  than ``max_dist`` is classified by a second, unbounded query.
* A grid node ``(i, j, k)`` sits at ``origin + spacing * (i, j, k)``.
"""

import warp as wp


@wp.func
def signed_distance_winding(mesh_id: wp.uint64, p: wp.vec3, max_dist: float) -> float:
    """Signed distance, sign from the winding number, clamped to ``[-max_dist, max_dist]``."""
    q = wp.mesh_query_point_sign_winding_number(mesh_id, p, max_dist)
    if q.result:
        return q.sign * wp.length(p - wp.mesh_eval_position(mesh_id, q.face, q.u, q.v))
    # no face within max_dist: the bounded query returned no sign, so classify with an unbounded one
    s = wp.mesh_query_point_sign_winding_number(mesh_id, p, 1.0e18)
    if s.result:
        return s.sign * max_dist
    return max_dist


@wp.func
def signed_distance_normal(mesh_id: wp.uint64, p: wp.vec3, max_dist: float) -> float:
    """Signed distance, sign from the closest face's normal, clamped to ``[-max_dist, max_dist]``."""
    q = wp.mesh_query_point_sign_normal(mesh_id, p, max_dist)
    if q.result:
        return q.sign * wp.length(p - wp.mesh_eval_position(mesh_id, q.face, q.u, q.v))
    s = wp.mesh_query_point_sign_normal(mesh_id, p, 1.0e18)
    if s.result:
        return s.sign * max_dist
    return max_dist


@wp.func
def query_signed_distance(mesh_id: wp.uint64, p: wp.vec3, max_dist: float, use_winding: int) -> float:
    """Signed distance from ``p`` to the mesh, negative inside, clamped to ``[-max_dist, max_dist]``."""
    if use_winding != 0:
        return signed_distance_winding(mesh_id, p, max_dist)
    return signed_distance_normal(mesh_id, p, max_dist)


@wp.kernel(enable_backward=False)
def signed_distance_points(
    mesh_id: wp.uint64,
    points: wp.array(dtype=wp.vec3),
    max_dist: float,
    use_winding: int,
    out: wp.array(dtype=float),
):
    """Per query point: the signed distance to the mesh."""
    i = wp.tid()
    out[i] = query_signed_distance(mesh_id, points[i], max_dist, use_winding)


@wp.kernel(enable_backward=False)
def signed_distance_grid(
    mesh_id: wp.uint64,
    origin: wp.vec3,
    spacing: float,
    max_dist: float,
    use_winding: int,
    out: wp.array3d(dtype=float),
):
    """Per grid node: the signed distance to the mesh."""
    i, j, k = wp.tid()
    p = origin + spacing * wp.vec3(float(i), float(j), float(k))
    out[i, j, k] = query_signed_distance(mesh_id, p, max_dist, use_winding)


@wp.kernel(enable_backward=False)
def mark_band_cells(coarse: wp.array3d(dtype=float), band: float, active: wp.array3d(dtype=wp.int32)):
    """Per coarse cell: 1 when the surface may cross it, else 0.

    A cell may hold a surface point only if some corner lies within ``band`` (at least half the cell
    diagonal) of the surface; a sign change between corners without a close corner also marks it,
    since the winding-number sign of an open mesh flips across its holes away from any face.
    """
    i, j, k = wp.tid()
    d0 = coarse[i, j, k]
    near = 0
    flip = 0
    for c in range(8):
        d = coarse[i + (c & 1), j + ((c >> 1) & 1), k + ((c >> 2) & 1)]
        if wp.abs(d) <= band:
            near = 1
        if (d < 0.0 and d0 >= 0.0) or (d >= 0.0 and d0 < 0.0):
            flip = 1
    active[i, j, k] = wp.max(near, flip)


@wp.func
def cell_range(i: int, factor: int, num_cells: int) -> wp.vec2i:
    """First and last coarse cell (inclusive) along one axis that contain fine node ``i``."""
    hi = wp.min(i // factor, num_cells - 1)
    lo = hi
    if i % factor == 0 and i > 0:
        lo = i // factor - 1
    return wp.vec2i(lo, hi)


@wp.kernel(enable_backward=False)
def refine_band_grid(
    mesh_id: wp.uint64,
    coarse: wp.array3d(dtype=float),
    active: wp.array3d(dtype=wp.int32),
    factor: int,
    origin: wp.vec3,
    spacing: float,
    max_dist: float,
    use_winding: int,
    out: wp.array3d(dtype=float),
):
    """Per fine node: the exact signed distance if a band cell contains the node, else the trilinear
    interpolation of the coarse grid (same sign, no zero crossing: enough for marching cubes).

    The coarse grid has spacing ``factor * spacing`` and shares ``origin``.
    """
    i, j, k = wp.tid()
    if i % factor == 0 and j % factor == 0 and k % factor == 0:
        out[i, j, k] = coarse[i // factor, j // factor, k // factor]
        return
    ri = cell_range(i, factor, active.shape[0])
    rj = cell_range(j, factor, active.shape[1])
    rk = cell_range(k, factor, active.shape[2])
    in_band = int(0)
    for ci in range(ri[0], ri[1] + 1):
        for cj in range(rj[0], rj[1] + 1):
            for ck in range(rk[0], rk[1] + 1):
                in_band = wp.max(in_band, active[ci, cj, ck])
    if in_band != 0:
        p = origin + spacing * wp.vec3(float(i), float(j), float(k))
        out[i, j, k] = query_signed_distance(mesh_id, p, max_dist, use_winding)
        return
    ci = ri[1]
    cj = rj[1]
    ck = rk[1]
    inv = 1.0 / float(factor)
    tx = float(i - ci * factor) * inv
    ty = float(j - cj * factor) * inv
    tz = float(k - ck * factor) * inv
    c00 = wp.lerp(coarse[ci, cj, ck], coarse[ci + 1, cj, ck], tx)
    c10 = wp.lerp(coarse[ci, cj + 1, ck], coarse[ci + 1, cj + 1, ck], tx)
    c01 = wp.lerp(coarse[ci, cj, ck + 1], coarse[ci + 1, cj, ck + 1], tx)
    c11 = wp.lerp(coarse[ci, cj + 1, ck + 1], coarse[ci + 1, cj + 1, ck + 1], tx)
    out[i, j, k] = wp.lerp(wp.lerp(c00, c10, ty), wp.lerp(c01, c11, ty), tz)


@wp.kernel(enable_backward=False)
def inward_thickness(
    mesh_id: wp.uint64,
    points: wp.array(dtype=wp.vec3),
    normals: wp.array(dtype=wp.vec3),
    offset: float,
    max_t: float,
    out: wp.array(dtype=float),
):
    """Per surface sample: distance along the inward normal ``-n`` to the next surface hit, or -1.

    The ray starts ``offset`` inside so it does not hit its own face.
    """
    i = wp.tid()
    n = normals[i]
    q = wp.mesh_query_ray(mesh_id, points[i] - offset * n, -n, max_t)
    out[i] = -1.0
    if q.result:
        out[i] = q.t + offset


@wp.kernel(enable_backward=False)
def push_off_zero(grid: wp.array3d(dtype=float), min_abs: float):
    """Per grid node: move values within ``min_abs`` of zero to ``+-min_abs`` (zero counts as outside).

    Marching cubes puts a vertex where an edge's values cross zero; a value near zero puts it on the
    node itself, and the triangles around that node collapse to slivers.
    """
    i, j, k = wp.tid()
    d = grid[i, j, k]
    if wp.abs(d) < min_abs:
        grid[i, j, k] = wp.where(d < 0.0, -min_abs, min_abs)


@wp.kernel(enable_backward=False)
def farthest_distance(mesh_id: wp.uint64, points: wp.array(dtype=wp.vec3), max_dist: float,
                      out: wp.array(dtype=float)):
    """Per point: its distance to the mesh (``max_dist`` when none is closer), maxed into ``out[0]`` (zeroed
    first): a one-sided Hausdorff distance, capped."""
    i = wp.tid()
    p = points[i]
    d = max_dist
    q = wp.mesh_query_point_no_sign(mesh_id, p, max_dist)
    if q.result:
        d = wp.min(d, wp.length(p - wp.mesh_eval_position(mesh_id, q.face, q.u, q.v)))
    wp.atomic_max(out, 0, d)


@wp.kernel(enable_backward=False)
def face_areas(x: wp.array(dtype=wp.vec3), tri: wp.array(dtype=wp.int32), out: wp.array(dtype=float)):
    """Per face: its area."""
    f = wp.tid()
    a = x[tri[3 * f]]
    out[f] = 0.5 * wp.length(wp.cross(x[tri[3 * f + 1]] - a, x[tri[3 * f + 2]] - a))


@wp.kernel(enable_backward=False)
def area_samples(x: wp.array(dtype=wp.vec3), tri: wp.array(dtype=wp.int32), cdf: wp.array(dtype=float),
                 u: wp.array(dtype=float), points: wp.array(dtype=wp.vec3), normals: wp.array(dtype=wp.vec3)):
    """Per sample: the centroid and unit normal of the face whose slice of the inclusive area prefix sum
    ``cdf`` holds ``u[i] * cdf[-1]`` (``u`` uniform in [0, 1)): faces drawn with probability proportional
    to area. Faces are wound outward, so ``normals`` point out."""
    i = wp.tid()
    target = u[i] * cdf[cdf.shape[0] - 1]
    lo = int(0)
    hi = cdf.shape[0] - 1
    while lo < hi:
        mid = (lo + hi) // 2
        if cdf[mid] <= target:
            lo = mid + 1
        else:
            hi = mid
    a = x[tri[3 * lo]]
    b = x[tri[3 * lo + 1]]
    c = x[tri[3 * lo + 2]]
    points[i] = (a + b + c) / 3.0
    normals[i] = wp.normalize(wp.cross(b - a, c - a))


@wp.kernel(enable_backward=False)
def bounds(x: wp.array(dtype=wp.vec3), lo: wp.array(dtype=float), hi: wp.array(dtype=float)):
    """Per point: its coordinates min-ed into ``lo`` and max-ed into ``hi`` ((3,) each, set to +-inf first)."""
    i = wp.tid()
    p = x[i]
    for d in range(3):
        wp.atomic_min(lo, d, p[d])
        wp.atomic_max(hi, d, p[d])


@wp.kernel(enable_backward=False)
def count_buried(mesh_id: wp.uint64, x: wp.array(dtype=wp.vec3), normals: wp.array(dtype=wp.vec3), offset: float,
                 use_winding: int, count: wp.array(dtype=wp.int32)):
    """Per vertex: count in ``count[0]`` the ones whose point ``offset`` outside along the unit ``normals`` is
    inside the mesh: the surface there is buried in another part of the shape, or another sheet is closer
    than ``offset``."""
    i = wp.tid()
    if query_signed_distance(mesh_id, x[i] + offset * normals[i], offset, use_winding) < 0.0:
        wp.atomic_add(count, 0, 1)


@wp.kernel(enable_backward=False)
def negate_grid(grid: wp.array3d(dtype=float), out: wp.array3d(dtype=float)):
    """Per grid node: minus its value (inside becomes positive)."""
    i, j, k = wp.tid()
    out[i, j, k] = -grid[i, j, k]


@wp.kernel(enable_backward=False)
def reverse_triangles(indices: wp.array(dtype=wp.int32), out: wp.array(dtype=wp.int32)):
    """Per triangle of the (3F,) corners: its corners in reverse order (the other winding)."""
    f = wp.tid()
    out[3 * f] = indices[3 * f]
    out[3 * f + 1] = indices[3 * f + 2]
    out[3 * f + 2] = indices[3 * f + 1]


@wp.kernel(enable_backward=False)
def blend_ellipsoid_grid(grid: wp.array3d(dtype=float), origin: wp.vec3, spacing: float, center: wp.vec3,
                         axes: wp.mat33, radii: wp.vec3, a: float, min_abs: float, out: wp.array3d(dtype=float)):
    """Per grid node ``p``: ``(1 - a) f(p) + a g(p)``, with ``f`` the node's value in ``grid`` and ``g`` the signed
    distance (estimate ``k0 (k0 - 1) / k1``: continuous, exact on the surface and along the axes) of the ellipsoid
    with ``center``, principal directions the columns of ``axes`` and semi-axes ``radii``; values within ``min_abs``
    of zero are pushed off it as in :func:`push_off_zero`."""
    i, j, k = wp.tid()
    p = origin + spacing * wp.vec3(float(i), float(j), float(k))
    q = wp.transpose(axes) * (p - center)
    k0 = wp.length(wp.cw_div(q, radii))
    k1 = wp.length(wp.cw_div(q, wp.cw_mul(radii, radii)))
    g = -wp.min(radii[0], wp.min(radii[1], radii[2]))
    if k1 > 0.0:
        g = wp.max(k0 * (k0 - 1.0) / k1, g)
    d = (1.0 - a) * grid[i, j, k] + a * g
    if wp.abs(d) < min_abs:
        d = wp.where(d < 0.0, -min_abs, min_abs)
    out[i, j, k] = d


@wp.kernel(enable_backward=False)
def blend_grids(f: wp.array3d(dtype=float), g: wp.array3d(dtype=float), a: float, min_abs: float,
                out: wp.array3d(dtype=float)):
    """Per grid node: ``(1 - a) f + a g`` of two signed-distance grids on the same nodes; values within ``min_abs`` of
    zero are pushed off it as in :func:`push_off_zero`."""
    i, j, k = wp.tid()
    d = (1.0 - a) * f[i, j, k] + a * g[i, j, k]
    if wp.abs(d) < min_abs:
        d = wp.where(d < 0.0, -min_abs, min_abs)
    out[i, j, k] = d
